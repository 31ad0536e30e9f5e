"""Baselines with the GP policy's ``predict()``, fitted from the same demonstrations.

* :class:`NearestDemonstrationReplay`: the joint trajectory of the demonstration with the nearest
  initial layout, replayed in time;
* :class:`ObjectRelativeReplay`: one demonstration's hand path relative to the cup, then to the
  machine (hand-set frame switch), tracked with inverse kinematics;
* :class:`ProMPPolicy`: a ProMP per frame (``movement_primitives``, optional extra), reproduced
  with the GP policy's Algorithm 3.

They are the yardsticks of ``benchmarks/lfd_success.py`` (``docs/benchmark.md``).
"""

from __future__ import annotations

from lgp_policy.baselines.promp import ProMPPolicy
from lgp_policy.baselines.replay import NearestDemonstrationReplay, ObjectRelativeReplay

__all__ = ["NearestDemonstrationReplay", "ObjectRelativeReplay", "ProMPPolicy"]
