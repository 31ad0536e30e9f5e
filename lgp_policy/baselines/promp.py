"""``ProMPPolicy``: the GP policy's reproduction with a ProMP per frame instead of the GPs.

A Probabilistic Movement Primitive (Paraschos et al., NeurIPS 2013; the implementation of
``movement_primitives``, an optional extra: ``pip install gym-coffee[baselines]``) is fitted per
frame to exactly the data the GP policy encodes: the demonstrations resampled on the same phase
grid, aligned on the same gripper events, in joint space (7 joints + gripper command) and relative
to the cup and the machine (grasp point and a point on the approach axis, ``p = 6``). Its mean and
per-dimension variance over phase replace the GPs' mean and variance; everything else (reading the
table at the phase, Algorithm 3's per-frame product, the gripper, the step limit) is
:class:`~lgp_policy.lfd.policy.GPDemonstrationPolicy`'s. So the comparison isolates the encoder: a
linear basis-function model with a Gaussian weight prior learnt by EM (``ProMP.imitate``) versus
local heteroscedastic GPs.

The ProMP's variance is the weight distribution's (the demonstrations' variation) plus its
learnt observation noise; with one demonstration the weight covariance collapses towards zero and
every frame is equally "tight", so Algorithm 3 weighs the frames by that floor.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from lgp_policy.lfd.policy import GPDemonstrationPolicy

__all__ = ["ProMPPolicy"]


def _promp_class() -> Any:
    try:
        from movement_primitives.promp import ProMP
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "ProMPPolicy needs the optional dependency movement_primitives: "
            "pip install 'gym-coffee[baselines]'"
        ) from exc
    return ProMP


class ProMPPolicy(GPDemonstrationPolicy):
    """A ProMP per frame, reproduced like the GP policy (stable-baselines3 ``predict``).

    Args:
        robot: kinematics; default the adapter's robot.
        adapter: how observations are read; default gym-coffee's adapter.
        n_weights_per_dim: radial basis functions per output dimension of each ProMP.
        n_iter: most EM iterations of ``ProMP.imitate``.
        **kwargs: :class:`~lgp_policy.lfd.policy.GPDemonstrationPolicy` arguments (``n_steps``,
            ``n_grid``, ``alpha``, ``lookahead``, ``align``, ``approach_offset``, ``frames``, ...);
            ``model`` is not accepted (the encoder is the ProMP).

    Attributes (after ``fit``): those of ``GPDemonstrationPolicy`` (``mean_``/``std_`` are the
    ProMPs'), plus ``promps_``: per frame, the fitted ``movement_primitives.promp.ProMP``.
    """

    def __init__(
        self,
        robot: Any = None,
        adapter: Any = None,
        *,
        n_weights_per_dim: int = 30,
        n_iter: int = 1000,
        **kwargs: Any,
    ) -> None:
        if "model" in kwargs:
            raise TypeError("ProMPPolicy does not take 'model': the encoder is a ProMP per frame")
        super().__init__(robot, adapter, model="empirical", **kwargs)
        self.n_weights_per_dim = n_weights_per_dim
        self.n_iter = n_iter

    def fit(
        self, demos: Sequence[Any], *, progress: bool = False, allow_failed: bool = False
    ) -> ProMPPolicy:
        """Resample and align the demonstrations as the GP policy does, fit one ProMP per frame.

        Args:
            demos: a ``TrajectorySet``, or what the adapter converts (a gym-coffee
                ``DemonstrationSet``), at least one.
            progress: print what is being fitted.
            allow_failed: also fit demonstrations that did not succeed.

        Returns:
            ``self``.
        """
        if int(self.n_weights_per_dim) < 2:
            raise ValueError(f"n_weights_per_dim must be >= 2, got {self.n_weights_per_dim!r}")
        ProMP = _promp_class()
        super().fit(
            demos, progress=progress, allow_failed=allow_failed
        )  # the empirical encoder: resampling and alignment
        encoder = self.encoder_
        self.promps_ = {}
        for name in self.frame_names_:
            data = np.asarray(encoder.data_[name], dtype=float)  # (n_demos, T, d)
            n_demos, _, n_dims = data.shape
            promp = ProMP(n_dims, int(self.n_weights_per_dim))
            promp.imitate(np.tile(encoder.phase_, (n_demos, 1)), data, n_iter=int(self.n_iter))
            mean = promp.mean_trajectory(self.phase_grid_)
            var = promp.var_trajectory(self.phase_grid_) + float(promp.variance)
            self.mean_[name] = np.asarray(mean, dtype=float)
            self.std_[name] = np.maximum(np.sqrt(var), encoder.std_floor_[name])
            self.promps_[name] = promp
            if progress:
                print(f"  ProMP for frame {name!r}: {n_dims} dims, {n_demos} demos", flush=True)
        self.constraints_ = self.constraint_report()
        self._build_table()
        return self

    def __repr__(self) -> str:
        fitted = f", frames={self.frame_names_}" if hasattr(self, "frame_names_") else ""
        return f"ProMPPolicy(n_weights_per_dim={self.n_weights_per_dim}{fitted})"
