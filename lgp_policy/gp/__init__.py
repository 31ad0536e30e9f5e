"""Gaussian processes: exact (:mod:`.exact`), heteroscedastic (:mod:`.heteroscedastic`,
:mod:`.variational`), local (:mod:`.local`), their kernels (:mod:`.kernels`).

:class:`ConvergenceWarning` is what an iterative fit emits when it stops without meeting its
tolerance (filter it with ``warnings.simplefilter(..., lgp_policy.gp.ConvergenceWarning)``).
"""

from lgp_policy.gp._base import ConvergenceWarning

__all__ = ["ConvergenceWarning"]
