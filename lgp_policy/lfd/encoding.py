"""Encoding of demonstrations (paper Sec. III): time-indexed GPs per frame, constraint profile.

Every demonstration is resampled to ``n_steps`` points on normalised time (phase ``s`` in
``[0, 1]``, ``s = (t - t_0) / (t_end - t_0)``). One GP per output dimension per *frame* then maps
the phase to

* ``"joint"``: the joint positions and the gripper, absolute (``(n_steps, n_joints + 1)``);
* one entry per object: the end-effector position relative to the object's *initial* pose,
  expressed in the object's frame: ``x_rel = R_0^T (x_ee - o_0)`` (a rotated machine is learned in
  its own axes and reproduced as ``o + R x_rel``).

All demonstrations share the phase grid, so each GP sees ``n_demos`` replicates per input; the GP
layer collapses them exactly. The predicted std of a heteroscedastic model includes the
input-dependent noise ``r(s)`` (Eq. 6): in LfD that noise *is* the variation between the
demonstrations, and where it is small the task is constrained (Sec. III).

This module works on plain arrays; it does not import ``gym_coffee``.
"""

from __future__ import annotations

import time as _time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lgp_policy.gp.heteroscedastic import MAX_LENGTH_SCALE_FRACTION, _data_scale
from lgp_policy.gp.local import DEFAULT_COMBINE
from lgp_policy.lfd.demonstrations import check_finite, check_time_stamps, real_array

__all__ = [
    "JOINT_FRAME",
    "MODELS",
    "DemonstrationEncoder",
    "constraint_intervals",
    "new_demonstration_scale",
    "phase_of",
    "resample",
]

JOINT_FRAME = "joint"
"""Name of the joint-space 'frame' (absolute joint positions and gripper)."""
MODELS = ("local", "heteroscedastic", "exact", "empirical")
"""Encoders: ``local`` LocalGP of heteroscedastic GPs (the paper), ``heteroscedastic`` one global
heteroscedastic GP, ``exact`` one homoscedastic exact GP, ``empirical`` the per-phase mean and std
across demonstrations (no GP; a baseline)."""
MIN_STD = 1e-4
"""Absolute cap of the floor on predicted standard deviations (units of the dimension: rad, m);
the floor itself is ``min(MIN_STD, MIN_RELATIVE_STD * scale)`` per dimension, see
:data:`MIN_RELATIVE_STD`."""
MIN_RELATIVE_STD = 1e-2
"""Floor on predicted standard deviations relative to each output dimension's own scale (its
standard deviation over all demonstrations and phases, or a float-precision scale for a constant
dimension: :func:`lgp_policy.gp.heteroscedastic._data_scale`); the floor is
``min(MIN_STD, MIN_RELATIVE_STD * scale)``. An absolute 1e-4 alone dominated demonstrations in
small units (data std 7e-7: a predicted std of 1e-4 everywhere, 142x the data's std); capped at
1% of the dimension's std it never does. The absolute cap stays because the coffee task's
policy depends on it: its gripper column (std 0.038) is floored at 1e-4 where the four
demonstrations coincide (the GP says 6.5e-5), and a purely relative floor would move it."""


def new_demonstration_scale(n_demos: int, level: float = 0.95) -> float:
    """Factor on a GP's predictive std that makes it a calibrated prediction of a *new*
    demonstration from ``n_demos`` of them.

    The GP's noise ``r(s)`` is the spread of ``n_demos`` demonstrations, estimated with
    ``n_demos - 1`` degrees of freedom (a demonstration deviates over long stretches, so pooling
    over time adds little): a new demonstration then follows a Student t with ``n_demos - 1``
    degrees of freedom, not a Gaussian. The factor matches the Gaussian's ``level`` interval to
    the t's: ``t_{n-1}(q) / z(q)`` with ``q = (1 + level) / 2`` (2.19 for 3 demonstrations, 1.62
    for 4, 1.21 for 8, -> 1). Measured in ``benchmarks/gp_quality.py``: 95% coverage of held-out
    demonstrations 0.80-0.85 without it, see ``docs/design-gp.md`` for the figures with it.
    """
    if n_demos < 2:
        return 1.0
    import scipy.special  # the quantile functions themselves (scipy.stats costs ~0.75 s to import)

    q = 0.5 * (1.0 + level)
    return float(scipy.special.stdtrit(n_demos - 1, q) / scipy.special.ndtri(q))


def phase_of(
    time: ArrayLike,
    landmarks: ArrayLike | None = None,
    landmark_phases: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Normalised time of each time stamp of one demonstration.

    Without landmarks ``s = (t - t_0) / (t_end - t_0)``. With landmarks (times of events every
    demonstration has, in the same order, e.g. the gripper closing and opening), the phase is
    piecewise linear in ``t`` and puts landmark ``j`` at ``landmark_phases[j]`` (typically the
    mean over the demonstrations of its normalised time): a landmark-based time alignment.
    """
    t = np.asarray(time, dtype=float).reshape(-1)
    s = (t - t[0]) / (t[-1] - t[0])
    if landmarks is None or len(np.atleast_1d(landmarks)) == 0:
        return s
    lx = (np.asarray(landmarks, dtype=float).reshape(-1) - t[0]) / (t[-1] - t[0])
    ly = np.asarray(landmark_phases, dtype=float).reshape(-1)
    if lx.shape != ly.shape:
        raise ValueError(f"{lx.size} landmarks but {ly.size} landmark phases")
    kx = np.concatenate([[0.0], lx, [1.0]])
    ky = np.concatenate([[0.0], ly, [1.0]])
    if np.any(np.diff(kx) <= 0) or np.any(np.diff(ky) <= 0):
        raise ValueError("landmarks and their phases must be strictly increasing inside (0, 1)")
    return np.interp(s, kx, ky)


def resample(
    time: ArrayLike,
    values: ArrayLike,
    n_steps: int,
    landmarks: ArrayLike | None = None,
    landmark_phases: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Resample one demonstration to ``n_steps`` points, equally spaced in normalised time.

    Args:
        time: ``(n,)`` increasing time stamps.
        values: ``(n, d)`` (or ``(n,)``) samples.
        n_steps: ``T``.
        landmarks, landmark_phases: optional time alignment, see :func:`phase_of`.

    Returns:
        ``(n_steps, d)`` linear interpolation at phases ``linspace(0, 1, n_steps)``.
    """
    t = np.asarray(time, dtype=float).reshape(-1)
    v = np.asarray(values, dtype=float)
    v = v.reshape(len(v), -1)
    if len(t) != len(v):
        raise ValueError(f"time has {len(t)} samples but values have {len(v)}")
    if len(t) < 2:
        raise ValueError("a demonstration needs at least 2 samples")
    if np.any(np.diff(t) <= 0):
        raise ValueError("time stamps must be strictly increasing")
    phase = phase_of(t, landmarks, landmark_phases)
    grid = np.linspace(0.0, 1.0, n_steps)
    return np.stack([np.interp(grid, phase, v[:, j]) for j in range(v.shape[1])], axis=1)


def constraint_intervals(
    phase: ArrayLike, std: ArrayLike, *, ratio: float = 0.5, min_width: float = 0.02
) -> list[tuple[float, float, float]]:
    """Where a frame is *tight*: its std well below its own typical level.

    The frame's spread at phase ``s`` is ``sigma(s) = sqrt(mean_d std_d(s)^2)`` (RMS over its
    dimensions); it is tight where ``sigma(s) < ratio * median_s sigma(s)``.

    Args:
        phase: ``(n,)`` increasing phases.
        std: ``(n, d)`` predicted std per dimension.
        ratio: threshold relative to the frame's median spread.
        min_width: intervals shorter than this (in phase) are dropped.

    Returns:
        ``[(start, end, min_sigma), ...]`` in phase units, in order.
    """
    s = np.asarray(phase, dtype=float)
    sd = np.asarray(std, dtype=float).reshape(len(s), -1)
    sigma = np.sqrt(np.mean(sd**2, axis=1))
    tight = sigma < ratio * np.median(sigma)
    out: list[tuple[float, float, float]] = []
    i = 0
    while i < len(s):
        if not tight[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(s) and tight[j + 1]:
            j += 1
        if s[j] - s[i] >= min_width:
            out.append((float(s[i]), float(s[j]), float(sigma[i : j + 1].min())))
        i = j + 1
    return out


def _to_frame(
    x: NDArray[np.float64], origin: ArrayLike, rotation: ArrayLike, *, name: str, demo: int
) -> NDArray[np.float64]:
    """``R^T (p - o)`` for every ``d``-D point ``p`` in the rows of ``x (n, k d)``; ``(n, k d)``."""
    o = np.asarray(origin, dtype=float)
    R = np.asarray(rotation, dtype=float)
    where = f"frames[{demo}][{name!r}]"
    if o.ndim != 1 or o.shape[0] not in (2, 3):
        raise ValueError(f"{where}: origin must have shape (2,) or (3,), got {o.shape}")
    d = o.shape[0]
    if R.shape != (d, d):
        raise ValueError(
            f"{where}: rotation must have shape ({d}, {d}) to match its origin, got {R.shape}"
        )
    if not (np.all(np.isfinite(o)) and np.all(np.isfinite(R))):
        raise ValueError(f"{where}: origin and rotation must be finite")
    if x.ndim != 2 or x.shape[1] == 0 or x.shape[1] % d:
        raise ValueError(
            f"ee_pos[{demo}] must have shape (n_steps, k * {d}) for {d}-D frames, got {x.shape}"
        )
    pts = x.reshape(len(x), -1, d)  # every d-D point on the hand
    return ((pts - o) @ R).reshape(len(x), -1)  # R^T (x - o), row-wise


def _entries(value: Any, name: str, n: int | None = None) -> list[Any]:
    """``value`` as a list of per-demonstration entries (``n`` of them when given)."""
    if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__len__"):
        raise ValueError(
            f"{name} must be a sequence with one entry per demonstration, "
            f"got {type(value).__name__}"
        )
    out = list(value)
    if n is not None and len(out) != n:
        raise ValueError(
            f"{name} must have one entry per demonstration: {n} (as times), got {len(out)}"
        )
    return out


def _check_samples(
    value: Any, where: str, t: NDArray[np.float64], i: int, *, allow_1d: bool
) -> NDArray[np.float64]:
    """``(n_i, d)`` finite samples (``(n_i,)`` as one column if ``allow_1d``), one per time."""
    a = real_array(value, where)
    if a.ndim == 1 and allow_1d:
        a = a[:, None]
    if a.ndim != 2:
        expected = "(n_i, d) or (n_i,)" if allow_1d else "(n_i, d)"
        raise ValueError(f"{where} must have shape {expected}, got shape {a.shape}")
    if a.shape[0] != t.size:
        raise ValueError(
            f"{where} has {a.shape[0]} rows but times[{i}] has {t.size} time stamps: "
            "one row per time stamp"
        )
    if a.shape[1] == 0:
        raise ValueError(f"{where} has no columns: need at least one dimension")
    check_finite(a, where)
    return a


def _check_frames(value: Any, n: int, ee_pos: Any) -> tuple[list[str], list[Mapping[str, Any]]]:
    """The object names (sorted) and the per-demonstration frames, checked."""
    frames = _entries(value, "frames", n)
    if ee_pos is None:
        raise ValueError("ee_pos is required with frames: one (n_i, k d) array per demonstration")
    names: list[str] = []
    for i, f in enumerate(frames):
        if not isinstance(f, Mapping):
            raise ValueError(
                f"frames[{i}] must be a mapping {{object name: (origin, rotation)}}, "
                f"got {type(f).__name__}"
            )
        for key in f:
            if not isinstance(key, str):
                raise ValueError(f"frames[{i}] keys must be object names (str), got {key!r}")
        if JOINT_FRAME in f:
            raise ValueError(
                f"frames[{i}] names an object {JOINT_FRAME!r}: that name is reserved for the "
                "joint frame"
            )
        got = sorted(f)
        if i == 0:
            names = got
        elif got != names:
            raise ValueError(
                f"frames[{i}] names the objects {got} but frames[0] names {names}: every "
                "demonstration must name the same objects"
            )
        for name in got:
            pose = f[name]
            if isinstance(pose, (str, bytes)) or not hasattr(pose, "__len__") or len(pose) != 2:
                raise ValueError(
                    f"frames[{i}][{name!r}] must be a pair (origin, rotation), got "
                    f"{type(pose).__name__}"
                    + (f" of length {len(pose)}" if hasattr(pose, "__len__") else "")
                )
            real_array(pose[0], f"frames[{i}][{name!r}]: origin")
            real_array(pose[1], f"frames[{i}][{name!r}]: rotation")
    return names, frames


def _check_landmarks(value: Any, ts: list[NDArray[np.float64]]) -> list[NDArray[np.float64]]:
    """Per demonstration, ``(k,)`` strictly increasing times inside its time range, the same
    ``k`` for all."""
    marks: list[NDArray[np.float64]] = []
    for i, m in enumerate(_entries(value, "landmarks", len(ts))):
        where = f"landmarks[{i}]"
        a = real_array(m, where)
        if a.ndim > 1:
            raise ValueError(f"{where} must be 1-D, (k,) event times, got shape {a.shape}")
        a = a.reshape(-1)
        check_finite(a, where)
        if i and a.size != marks[0].size:
            raise ValueError(
                f"{where} has {a.size} events but landmarks[0] has {marks[0].size}: every "
                "demonstration needs as many landmarks"
            )
        t = ts[i]
        if a.size and (np.any(np.diff(a) <= 0) or a[0] <= t[0] or a[-1] >= t[-1]):
            raise ValueError(
                f"{where} must be strictly increasing times inside times[{i}]'s range "
                f"({float(t[0])!r}, {float(t[-1])!r}), got {a.tolist()}"
            )
        marks.append(a)
    return marks


class _UnknownFrameError(ValueError, KeyError):
    """An unknown frame name: a ValueError, and a KeyError as before."""

    __str__ = ValueError.__str__  # not KeyError's repr of the message


class _Empirical:
    """Per-phase mean and std across demonstrations (no GP); the ``empirical`` encoder."""

    def fit(self, X: NDArray, y: NDArray) -> _Empirical:
        x = X[:, 0]
        self.grid_ = np.unique(x)
        idx = np.searchsorted(self.grid_, x)
        n = np.bincount(idx, minlength=len(self.grid_))
        mean = np.bincount(idx, weights=y, minlength=len(self.grid_)) / n
        var = np.bincount(idx, weights=(y - mean[idx]) ** 2, minlength=len(self.grid_))
        self.mean_ = mean
        self.std_ = np.sqrt(var / np.maximum(n - 1, 1))
        return self

    def predict(self, X: NDArray, return_std: bool = False):
        x = np.asarray(X, dtype=float)[:, 0]
        mean = np.interp(x, self.grid_, self.mean_)
        if not return_std:
            return mean
        return mean, np.interp(x, self.grid_, self.std_)


class DemonstrationEncoder:
    """Time-indexed GPs of demonstrations in joint space and relative to every object (Sec. III).

    Args:
        n_steps: ``T``, points per resampled demonstration.
        model: one of :data:`MODELS` (``"local"``: the paper's local heteroscedastic GP).
        combine: how ``LocalGP`` combines its local models, one of
            :data:`lgp_policy.gp.local.COMBINE_RULES`; default
            :data:`lgp_policy.gp.local.DEFAULT_COMBINE` (the GP layer's, chosen on measurements);
            only for ``model="local"``.
        threshold: ``LocalGP``'s minimum covariance (relative to the signal variance) for joining
            a local model (Algorithm 1, line 11).
        length_scale: initial length scale of the squared-exponential kernel, in phase units.
        noise_level: initial white-noise variance (normalised outputs).
        model_kwargs: extra keyword arguments for the GP class.
        calibrate: scale the predicted std by :func:`new_demonstration_scale` so that it
            predicts a new demonstration (95% coverage) rather than the training ones.
        random_state: seed for the GP layer's random parts.

    Attributes:
        frame_names_: ``["joint", <object names>...]``.
        phase_: ``(n_steps,)`` the phase grid.
        data_: per frame, the resampled demonstrations ``(n_demos, n_steps, d)``.
        models_: per frame, one fitted model per dimension.
        durations_: ``(n_demos,)`` durations of the demonstrations (time units of the input).
        fit_time_: seconds spent in :meth:`fit`.
        std_scale_: the factor :meth:`predict` applies to the models' std (``calibrate``).
        std_floor_: per frame, ``(d,)`` the floor of each dimension's predicted std,
            ``min(MIN_STD, MIN_RELATIVE_STD * scale)`` with ``scale`` the dimension's standard
            deviation in ``data_`` (a float-precision scale if it is constant).
    """

    def __init__(
        self,
        *,
        n_steps: int = 200,
        model: str = "local",
        combine: str = DEFAULT_COMBINE,
        threshold: float = 0.5,
        length_scale: float = 0.1,
        noise_level: float = 0.1,
        model_kwargs: Mapping[str, Any] | None = None,
        calibrate: bool = True,
        random_state: int | None = 0,
    ) -> None:
        self.n_steps = n_steps
        self.model = model
        self.combine = combine
        self.threshold = threshold
        self.length_scale = length_scale
        self.noise_level = noise_level
        self.model_kwargs = model_kwargs
        self.calibrate = calibrate
        self.random_state = random_state

    # ----------------------------------------------------------------- models
    def make_kernel(self) -> Any:
        """The squared-exponential + white-noise kernel (Eq. 10) every GP starts from, with
        bounds that rule out the degenerate optima seen on demonstrations (see below)."""
        from lgp_policy.gp.kernels import SquaredExponential, WhiteNoise

        # A length scale below the grid spacing lets the likelihood "explain" a sharp step by
        # interpolating the grid points and reverting to the mean in between (measured on a
        # gripper command): keep it above 1.5 grid steps. The opposite degenerate optimum, "no
        # signal, all noise" (variance at its lower bound, length scale > the whole phase
        # range), flattens the heteroscedastic noise model too; a trajectory always has signal,
        # so bound the variance (normalised outputs) and keep the length scale below half the
        # phase range.
        min_ls = 1.5 / (self.n_steps - 1)
        return SquaredExponential(
            1.0,
            max(self.length_scale, min_ls),
            variance_bounds=(1e-2, 1e2),
            length_scale_bounds=(min_ls, MAX_LENGTH_SCALE_FRACTION),  # phase range 1
        ) + WhiteNoise(self.noise_level)

    def _make_model(self) -> Any:
        if self.model == "empirical":
            return _Empirical()
        kernel = self.make_kernel()
        kwargs = dict(self.model_kwargs or {})
        if self.model == "exact":
            from lgp_policy.gp.exact import GaussianProcess

            return GaussianProcess(kernel, random_state=self.random_state, **kwargs)
        if self.model == "heteroscedastic":
            from lgp_policy.gp.heteroscedastic import HeteroscedasticGP

            return HeteroscedasticGP(kernel, random_state=self.random_state, **kwargs)
        if self.model == "local":
            from lgp_policy.gp.local import LocalGP

            return LocalGP(
                kernel,
                threshold=self.threshold,
                combine=self.combine,
                random_state=self.random_state,
                **kwargs,
            )
        raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")

    # -------------------------------------------------------------------- fit
    def fit(
        self,
        times: Sequence[ArrayLike],
        joint_pos: Sequence[ArrayLike],
        ee_pos: Sequence[ArrayLike] | None = None,
        frames: Sequence[Mapping[str, tuple[ArrayLike, ArrayLike]]] | None = None,
        *,
        landmarks: Sequence[ArrayLike] | None = None,
        progress: Callable[[str], None] | None = None,
    ) -> DemonstrationEncoder:
        """Resample and encode ``n_demos`` demonstrations.

        Args:
            times: per demonstration, ``(n_i,)`` time stamps.
            joint_pos: per demonstration, ``(n_i, d_joint)`` joint positions (plus gripper).
            ee_pos: per demonstration, ``(n_i, d)`` end-effector positions (world frame), or
                ``(n_i, k d)`` for ``k`` points on the hand (each transformed into the frames);
                ``d`` is 2 or 3, the dimension of the frames' origins.
            frames: per demonstration, ``{object name: (origin (d,), rotation (d, d))}``, the
                object's *initial* pose in the world frame (``d = 2``: a planar task, ``d = 3``:
                a spatial one). Every demonstration must name the same objects.
            landmarks: optional, per demonstration, the times ``(k,)`` of ``k`` events every
                demonstration has in the same order; the phase is then aligned on them
                (:func:`phase_of`, each event at its mean normalised time, ``landmark_phases_``).
            progress: called with a short message before each frame is fitted.

        Returns:
            ``self``.

        Raises:
            ValueError: naming the argument and the demonstration (``times[2]``,
                ``joint_pos[1]``, ``frames[0]['cup']``, ...) and what was expected, before any
                work: time stamps that are not 1-D, finite and strictly increasing, samples
                that are not finite or whose rows do not match the time stamps, dimensions that
                differ between demonstrations, landmarks outside a demonstration's time range.
        """
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        if (
            isinstance(self.n_steps, bool)
            or not isinstance(self.n_steps, (int, np.integer))
            or self.n_steps < 2
        ):
            raise ValueError(f"n_steps must be an int >= 2, got {self.n_steps!r}")
        if progress is not None and not callable(progress):
            raise ValueError(f"progress must be callable or None, got {type(progress).__name__}")
        # every argument is checked before any work
        ts = [check_time_stamps(t, f"times[{i}]") for i, t in enumerate(_entries(times, "times"))]
        n = len(ts)
        if n == 0:
            raise ValueError("times must hold at least one demonstration, got none")
        qs = [
            _check_samples(q, f"joint_pos[{i}]", ts[i], i, allow_1d=True)
            for i, q in enumerate(_entries(joint_pos, "joint_pos", n))
        ]
        for i, q in enumerate(qs):
            if q.shape[1] != qs[0].shape[1]:
                raise ValueError(
                    f"joint_pos[{i}] has {q.shape[1]} columns but joint_pos[0] has "
                    f"{qs[0].shape[1]}: every demonstration needs the same dimensions"
                )
        names: list[str] = []
        locals_: dict[str, list[NDArray[np.float64]]] = {}
        if frames is not None and len(_entries(frames, "frames")) > 0:
            names, frame_list = _check_frames(frames, n, ee_pos)
            xs = [
                _check_samples(x, f"ee_pos[{i}]", ts[i], i, allow_1d=False)
                for i, x in enumerate(_entries(ee_pos, "ee_pos", n))
            ]
            locals_ = {
                name: [
                    _to_frame(x, *f[name], name=name, demo=i)
                    for i, (x, f) in enumerate(zip(xs, frame_list, strict=True))
                ]
                for name in names
            }
        marks: list[Any] = [None] * n
        if landmarks is not None:
            marks = _check_landmarks(landmarks, ts)
        start = _time.perf_counter()
        self.landmark_phases_ = np.zeros(0)
        self.phase_ = np.linspace(0.0, 1.0, self.n_steps)
        self.durations_ = np.array([float(t[-1] - t[0]) for t in ts])
        if landmarks is not None:
            rel_marks = [(m - t[0]) / d for m, t, d in zip(marks, ts, self.durations_, strict=True)]
            self.landmark_phases_ = np.mean(rel_marks, axis=0)
        lp = self.landmark_phases_
        data = {
            JOINT_FRAME: np.stack(
                [resample(t, q, self.n_steps, m, lp) for t, q, m in zip(ts, qs, marks, strict=True)]
            )
        }
        for name in names:
            data[name] = np.stack(
                [
                    resample(t, local, self.n_steps, mk, lp)
                    for t, local, mk in zip(ts, locals_[name], marks, strict=True)
                ]
            )
        self.data_ = data
        self.frame_names_ = [JOINT_FRAME, *names]
        self.std_floor_ = {
            name: np.minimum(
                MIN_STD,
                MIN_RELATIVE_STD
                * np.array([_data_scale(Y[:, :, j].reshape(-1)) for j in range(Y.shape[2])]),
            )
            for name, Y in data.items()
        }
        X = np.tile(self.phase_, n)[:, None]
        self.models_: dict[str, list[Any]] = {}
        for name in self.frame_names_:
            if progress is not None:
                progress(f"encoding frame '{name}'")
            Y = data[name]  # (n_demos, T, d)
            if self.model == "local" and Y.shape[2] > 1:
                # One LocalGP per dimension, fitted together: the dimensions share the inputs
                # and clusters, and their hyperparameter searches run in lockstep with batched
                # likelihoods (the same models as one fit per dimension, to rounding).
                multi = self._make_model().fit(X, Y.reshape(-1, Y.shape[2]))
                self.models_[name] = list(multi.estimators_)
            else:
                self.models_[name] = [
                    self._make_model().fit(X, Y[:, :, j].reshape(-1)) for j in range(Y.shape[2])
                ]
        self.std_scale_ = new_demonstration_scale(n) if self.calibrate else 1.0
        self.fit_time_ = _time.perf_counter() - start
        return self

    # ---------------------------------------------------------------- predict
    def _check_fitted(self) -> None:
        if not hasattr(self, "models_"):
            raise RuntimeError("This DemonstrationEncoder is not fitted yet; call fit() first.")

    def predict(
        self, phase: ArrayLike, frame: str = JOINT_FRAME
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean and std (incl. the demonstrations' variation) of one frame at the given phases.

        Args:
            phase: ``(n,)`` phases in ``[0, 1]``.
            frame: ``"joint"`` or an object name.

        Returns:
            ``(mean (n, d), std (n, d))``; each std at least the dimension's floor
            (:attr:`std_floor_`).

        Raises:
            ValueError: ``phase`` not 1-D finite real numbers, or an unknown ``frame`` (also a
                ``KeyError``).
        """
        self._check_fitted()
        if not isinstance(frame, str) or frame not in self.models_:
            raise _UnknownFrameError(f"frame must be one of {self.frame_names_}, got {frame!r}")
        s = real_array(phase, "phase")
        if s.ndim > 1:
            raise ValueError(f"phase must be 1-D, (n,) phases, got shape {s.shape}")
        check_finite(s.reshape(-1), "phase")
        X = s.reshape(-1, 1)
        means, stds = [], []
        for m in self.models_[frame]:
            mu, sd = m.predict(X, return_std=True)
            means.append(np.asarray(mu, dtype=float).reshape(-1))
            stds.append(np.asarray(sd, dtype=float).reshape(-1))
        std = np.stack(stds, axis=1) * self.std_scale_
        return np.stack(means, axis=1), np.maximum(std, self.std_floor_[frame])

    def constraint_profile(
        self, phase: ArrayLike | None = None
    ) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """Per frame, ``(mean (n, d), std (n, d))`` over phase (the Fig. 4 curves).

        Low std = a constraint (Sec. III). ``phase`` defaults to :attr:`phase_`.
        """
        self._check_fitted()
        s = self.phase_ if phase is None else np.asarray(phase, dtype=float)
        return {name: self.predict(s, name) for name in self.frame_names_}

    def constraint_report(
        self, *, ratio: float = 0.5, min_width: float = 0.02, n_grid: int = 400
    ) -> list[dict[str, Any]]:
        """Intervals where each object frame is tight (see :func:`constraint_intervals`).

        Returns:
            ``[{"frame", "start", "end", "min_std", "label"}, ...]`` with phases in ``[0, 1]`` and
            labels such as ``"cup, t 0.22-0.31"``; sorted by start.
        """
        s = np.linspace(0.0, 1.0, n_grid)
        return intervals_report(
            {name: self.predict(s, name)[1] for name in self.frame_names_ if name != JOINT_FRAME},
            s,
            ratio=ratio,
            min_width=min_width,
        )


def intervals_report(
    stds: Mapping[str, ArrayLike], phase: ArrayLike, *, ratio: float = 0.5, min_width: float = 0.02
) -> list[dict[str, Any]]:
    """:func:`constraint_intervals` for several frames, as JSON-ready dictionaries."""
    report = []
    for name, sd in stds.items():
        for a, b, m in constraint_intervals(phase, sd, ratio=ratio, min_width=min_width):
            report.append(
                {
                    "frame": name,
                    "start": round(a, 4),
                    "end": round(b, 4),
                    "min_std": m,
                    "label": f"{name}, t {a:.2f}-{b:.2f}",
                }
            )
    return sorted(report, key=lambda r: (r["start"], r["frame"]))
