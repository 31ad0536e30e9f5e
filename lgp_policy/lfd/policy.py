"""``GPDemonstrationPolicy``: the paper's LfD controller as a stable-baselines3 ``PolicyPredictor``.

``fit(demos)`` encodes the demonstrations (:class:`~lgp_policy.lfd.encoding.DemonstrationEncoder`:
joint space plus the hand relative to the cup and to the machine) and then evaluates every
GP once on a dense phase grid. The paper notes that "the prediction part can then be performed very
quickly": ``predict`` only interpolates that table and runs one step of Algorithm 3
(:func:`~lgp_policy.lfd.reproduction.reproduction_step`) from the *measured* joint positions, so the
controller is closed loop and takes well under a millisecond.

By default the demonstrations are first aligned in time on the gripper command's closing and
opening events (``align="gripper"``; landmarks at their mean normalised time, see
:func:`lgp_policy.lfd.encoding.phase_of`), so that reach, release and press line up across
demonstrations whose tempo differs.

Per step, for an observation with ``time`` ``t`` (seconds since reset):

1. phase ``s = (t + lookahead * control_dt) / duration`` (``duration`` = mean demonstration length,
   clipped to ``[0, 1]``; after the demonstrated duration the final posture is held);
2. the joint-space estimate ``theta_hat(s)`` and, for every object in the observation, the world
   target ``o + R x_hat(s)`` with covariance ``R diag(std^2) R^T``. ``x`` is the task vector of
   Algorithm 3: the grasp point and, with ``approach_offset`` (default 0.1 m), a second point
   that far behind it on the hand's approach axis (``p = 6``), so that the object frames also
   carry the approach direction; ``approach_offset=None`` is the paper's position-only ``p = 3``
   (the hand's orientation then comes from the joint-space estimate alone);
3. Algorithm 3 (information-form product) gives the joint increment, scaled down as a whole if a
   joint would move more than ``max_joint_step`` (the env's ``MAX_JOINT_STEP``);
4. the gripper opening is the joint-space GP's gripper mean (the teacher's *commanded* opening);
5. ``action = gym_coffee.robot.action_from_targets(q, q + dtheta, gripper)``.

For residual RL and diagnostics: :meth:`GPDemonstrationPolicy.phase` (normalised time of an
observation) and :meth:`GPDemonstrationPolicy.predict_distribution` (phase, action, fused joint
increment and its std, per-frame predicted std at that phase).

Files: one ``.npz`` (``allow_pickle=False``) holding the phase table and a JSON string ``metadata``
(format name, schema version, parameters, frame names, the constraint report). Saving is atomic
and refuses to overwrite unless ``overwrite=True``; loading validates and says what is wrong.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
import time as _time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lgp_policy.lfd.encoding import JOINT_FRAME, DemonstrationEncoder, intervals_report, phase_of
from lgp_policy.lfd.reproduction import (
    DEFAULT_ALPHA,
    DEFAULT_DAMPING,
    DEFAULT_RIDGE,
    MIN_VARIANCE,
    FrameEstimate,
    limit_step,
    reproduction_step,
)

__all__ = [
    "FORMAT_NAME",
    "SCHEMA_VERSION",
    "GPDemonstrationPolicy",
    "PolicyDistribution",
    "PolicyFileError",
]

FORMAT_NAME = "lgp_policy.gp_demonstration_policy"
"""``format`` and ``kind`` of the file's JSON metadata (``residual.load_any_policy`` keys on it)."""
SCHEMA_VERSION = 1
STAGE_NAMES = ("cup_grasped", "cup_placed", "button_pressed")
#: Which frame should be tight at which stage (the paper's Fig. 4 and the constraint check).
EXPECTED_TIGHT_FRAME = {"cup_grasped": "cup", "cup_placed": "machine", "button_pressed": "machine"}


class PolicyFileError(ValueError):
    """A policy file is missing, malformed or of an unsupported version."""


@dataclass(frozen=True)
class PolicyDistribution:
    """What the policy predicts for a batch of ``n`` observations (see ``predict_distribution``).

    Attributes:
        phase: ``(n,)`` normalised time at which the GPs were read (includes the lookahead).
        action: ``(n, 8)`` float32, the action ``predict`` returns.
        joint_increment: ``(n, 7)`` fused joint increment of Algorithm 3 (before step limiting).
        joint_std: ``(n, 7)`` its std (diagonal of the fused covariance; the remaining variance).
        gripper: ``(n,)`` commanded gripper opening (m).
        frame_std: per frame (``"joint"``, ``"cup"``, ``"machine"``), the GPs' predicted std at
            ``phase``, ``(n, d)``; small = constrained.
    """

    phase: NDArray[np.float64]
    action: NDArray[np.float32]
    joint_increment: NDArray[np.float64]
    joint_std: NDArray[np.float64]
    gripper: NDArray[np.float64]
    frame_std: dict[str, NDArray[np.float64]]


class _HybridFit:
    """Lets ``fit`` be called on the class (``GPDemonstrationPolicy.fit(demos)``, default
    parameters) or on an instance (``GPDemonstrationPolicy(alpha=0.3).fit(demos)``)."""

    def __init__(self, func: Callable[..., Any]) -> None:
        self.func = func
        self.__doc__ = func.__doc__

    def __get__(self, obj: Any, cls: type) -> Callable[..., Any]:
        def bound(*args: Any, **kwargs: Any) -> Any:
            return self.func(obj if obj is not None else cls(), *args, **kwargs)

        bound.__doc__ = self.func.__doc__
        return bound


def _default_robot() -> Any:
    from gym_coffee.kinematics import PandaKinematics

    return PandaKinematics()


def _rot_z(yaw: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((*np.shape(yaw), 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def demonstration_frames(demo: Any) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """Initial object frames of one ``gym_coffee`` demonstration, as ``object_frames`` builds them.

    cup: initial position, identity rotation; machine: initial position, ``Rz(yaw)``.
    """
    frames = {}
    for name, pos in demo.object_pos.items():
        o = np.asarray(pos[0], dtype=float)
        if name == "cup":
            frames[name] = (o, np.eye(3))
        else:
            x, y, z, w = np.asarray(demo.object_quat[name][0], dtype=float)
            yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
            frames[name] = (o, _rot_z(np.asarray(yaw)))
    return frames


def gripper_events(demo: Any) -> NDArray[np.float64]:
    """Times at which the demonstrated gripper command crosses half open (closing or opening),
    linearly interpolated between control steps."""
    t = np.asarray(demo.time, dtype=float)
    g = np.asarray(demo.actions, dtype=float)[:, 7]  # in [-1, 1]; 0 = half open
    i = np.flatnonzero(np.sign(g[:-1]) * np.sign(g[1:]) < 0)
    w = g[i] / (g[i] - g[i + 1])
    return t[i] + w * (t[i + 1] - t[i])


def stage_phases(demo: Any, phase: NDArray[np.float64] | None = None) -> dict[str, float | None]:
    """Phase at which each stage flag first became true in a demonstration (``phase``: the
    demonstration's phase per step; default ``t / duration``)."""
    t = np.asarray(demo.time, dtype=float)
    s = (t - t[0]) / (t[-1] - t[0]) if phase is None else np.asarray(phase, dtype=float)
    stages = np.asarray(demo.stages, dtype=bool)
    out: dict[str, float | None] = {}
    for j, name in enumerate(STAGE_NAMES):
        idx = np.flatnonzero(stages[:, j])
        out[name] = float(s[idx[0]]) if idx.size else None
    return out


class GPDemonstrationPolicy:
    """Closed-loop reproduction of demonstrations with local heteroscedastic GPs (Sec. III).

    Args (keyword-only after ``robot``):

    ============== ===================================================================
    robot          kinematics (``RobotModel``); default ``gym_coffee``'s ``PandaKinematics``
    n_steps        ``T``, resampled points per demonstration (encoding)
    n_grid         points of the precomputed phase table used by ``predict``
    model          encoder model: ``local`` (paper), ``heteroscedastic``, ``exact``, ``empirical``
    combine        ``LocalGP`` combination: ``product`` (Eqs. 8-9) or the calibrated rule
    frames         object frames to use (default: all in the demonstrations); ``()`` = joint only
    alpha          null-space weight of Algorithm 3 (0.5 in the paper)
    null_space_std ``None``: a frame's null-space information = the joint estimate's; or a std (rad)
    lookahead      control steps ahead at which the GPs are read (compensates tracking lag)
    max_joint_step largest joint change per step (rad); default the env's ``MAX_JOINT_STEP``
    std_scale      per-frame multiplier of the predicted std, e.g. ``{"cup": 0.5}``
    align          ``"gripper"``: align the demonstrations in time on the gripper command's
                   closing/opening events (landmarks, piecewise-linear phase) before
                   encoding; ``None``: plain normalised time (the paper)
    approach_offset m; adds a second task point this far behind the grasp point along the
                   hand's approach (z) axis, so each object frame also encodes the approach
                   direction (task vector p = 6); ``None``: position only (p = 3, the paper).
                   Needs ``robot.forward_pose`` and ``robot.jacobian`` (``PandaKinematics``)
    encoder_kwargs extra arguments for :class:`~lgp_policy.lfd.encoding.DemonstrationEncoder`
    ============== ===================================================================

    Attributes (after ``fit`` or ``load``):
        phase_grid_: ``(n_grid,)``; ``mean_`` / ``std_``: per frame, ``(n_grid, d)`` tables.
        frame_names_: ``["joint", "cup", "machine"]`` (those used). ``duration_``: mean
        demonstration duration (s); ``control_dt_``: env control period (s).
        constraints_: the constraint report (see :meth:`constraint_report`).
        encoder_: the fitted encoder (only after ``fit``; not saved).
    """

    def __init__(
        self,
        robot: Any = None,
        *,
        n_steps: int = 200,
        n_grid: int = 500,
        model: str = "local",
        combine: str = "product",
        frames: Sequence[str] | None = None,
        alpha: float = DEFAULT_ALPHA,
        null_space_std: float | None = None,
        lookahead: float = 1.0,
        max_joint_step: float | None = None,
        std_scale: Mapping[str, float] | None = None,
        approach_offset: float | None = 0.1,
        align: str | None = "gripper",
        encoder_kwargs: Mapping[str, Any] | None = None,
    ) -> None:
        self.robot = robot
        self.n_steps = n_steps
        self.n_grid = n_grid
        self.model = model
        self.combine = combine
        self.frames = frames
        self.alpha = alpha
        self.null_space_std = null_space_std
        self.lookahead = lookahead
        self.max_joint_step = max_joint_step
        self.std_scale = std_scale
        self.approach_offset = approach_offset
        self.align = align
        self.encoder_kwargs = encoder_kwargs

    # -------------------------------------------------------------- parameters
    def get_params(self) -> dict[str, Any]:
        """Constructor arguments that are saved with the policy (all but ``robot``)."""
        return {
            "n_steps": self.n_steps,
            "n_grid": self.n_grid,
            "model": self.model,
            "combine": self.combine,
            "frames": None if self.frames is None else list(self.frames),
            "alpha": self.alpha,
            "null_space_std": self.null_space_std,
            "lookahead": self.lookahead,
            "max_joint_step": self.max_joint_step,
            "std_scale": None if self.std_scale is None else dict(self.std_scale),
            "approach_offset": self.approach_offset,
            "align": self.align,
            "encoder_kwargs": None if self.encoder_kwargs is None else dict(self.encoder_kwargs),
        }

    # -------------------------------------------------------------------- fit
    @_HybridFit
    def fit(self, demos: Any, *, progress: bool = False) -> GPDemonstrationPolicy:
        """Encode demonstrations and precompute the phase table.

        Callable on the class (default parameters) or on an instance.

        Args:
            demos: a ``gym_coffee.DemonstrationSet`` (or any sequence of objects with ``time``,
                ``joint_pos``, ``actions``, ``ee_pos``, ``object_pos``, ``object_quat``,
                ``stages``) with at least one demonstration.
            progress: print what is being fitted.

        Returns:
            ``self``.
        """
        from gym_coffee.robot import GRIPPER_MAX_OPENING

        demos = list(demos)
        if not demos:
            raise ValueError("need at least one demonstration")
        start = _time.perf_counter()
        times = [np.asarray(d.time, dtype=float) for d in demos]
        # joint space = 7 joints + the teacher's *commanded* gripper opening (a firm grasp)
        joints = [
            np.column_stack(
                [
                    np.asarray(d.joint_pos, dtype=float),
                    (np.asarray(d.actions, dtype=float)[:, 7] + 1.0) / 2.0 * GRIPPER_MAX_OPENING,
                ]
            )
            for d in demos
        ]
        robot = self.robot if self.robot is not None else _default_robot()
        ees = [np.asarray(d.ee_pos, dtype=float) for d in demos]
        if self.approach_offset is not None:  # second point along the hand's approach axis
            ees = [
                np.hstack(
                    [
                        ee,
                        np.stack(
                            [
                                hand_points(robot, q, self.approach_offset)[0][3:]
                                for q in np.asarray(d.joint_pos, dtype=float)
                            ]
                        ),
                    ]
                )
                for ee, d in zip(ees, demos, strict=True)
            ]
        all_frames = [demonstration_frames(d) for d in demos]
        names = sorted(all_frames[0]) if self.frames is None else list(self.frames)
        for n in names:
            if n not in all_frames[0]:
                raise ValueError(
                    f"unknown frame {n!r}; the demonstrations have {sorted(all_frames[0])}"
                )
        frames = [{n: f[n] for n in names} for f in all_frames]
        kwargs = dict(self.encoder_kwargs or {})
        kwargs.setdefault("n_steps", self.n_steps)
        kwargs.setdefault("model", self.model)
        kwargs.setdefault("combine", self.combine)
        encoder = DemonstrationEncoder(**kwargs)
        say = (lambda msg: print(f"  {msg}", flush=True)) if progress else None
        landmarks = None
        self.alignment_ = "none"
        if self.align == "gripper":
            events = [gripper_events(d) for d in demos]
            if len({e.size for e in events}) == 1 and events[0].size > 0:
                landmarks = events
                self.alignment_ = f"gripper events ({events[0].size})"
            else:
                self.alignment_ = (
                    "none (gripper event counts differ: " + str([e.size for e in events]) + ")"
                )
        elif self.align is not None:
            raise ValueError(f"align must be 'gripper' or None, got {self.align!r}")
        encoder.fit(
            times,
            joints,
            ees if names else None,
            frames if names else None,
            landmarks=landmarks,
            progress=say,
        )
        self.encoder_ = encoder
        self.frame_names_ = list(encoder.frame_names_)
        self.phase_grid_ = np.linspace(0.0, 1.0, self.n_grid)
        self.mean_, self.std_ = {}, {}
        for name in self.frame_names_:
            m, s = encoder.predict(self.phase_grid_, name)
            self.mean_[name], self.std_[name] = m, s
        self.duration_ = float(np.mean(encoder.durations_))
        dts = [float(np.median(np.diff(t))) for t in times]
        self.control_dt_ = float(np.median(dts))
        self.n_demos_ = len(demos)
        lp = encoder.landmark_phases_
        self.stage_phases_ = [
            stage_phases(d, phase_of(d.time, landmarks[i] if landmarks else None, lp))
            for i, d in enumerate(demos)
        ]
        self.constraints_ = self.constraint_report()
        self.fit_time_ = _time.perf_counter() - start
        self._build_table()
        return self

    # ------------------------------------------------------------------ table
    def _build_table(self) -> None:
        """Stack the means and variances of all frames in one ``(n_grid, D)`` table."""
        robot = self.robot if self.robot is not None else _default_robot()
        self.robot_ = robot
        if self.max_joint_step is None:
            from gym_coffee.robot import MAX_JOINT_STEP

            self.max_joint_step_ = float(MAX_JOINT_STEP)
        else:
            self.max_joint_step_ = float(self.max_joint_step)
        from gym_coffee.robot import action_from_targets

        self._action_from_targets = action_from_targets
        scale = dict(self.std_scale or {})
        cols, self._cols = [], {}
        c = 0
        for name in self.frame_names_:
            d = self.mean_[name].shape[1]
            var = (self.std_[name] * scale.get(name, 1.0)) ** 2
            cols += [self.mean_[name], var]
            self._cols[name] = (slice(c, c + d), slice(c + d, c + 2 * d))
            c += 2 * d
        self._table = np.ascontiguousarray(np.hstack(cols))
        self._obs_slices = _obs_slices()

    def _check_fitted(self) -> None:
        if not hasattr(self, "_table"):
            raise RuntimeError("This GPDemonstrationPolicy is not fitted; call fit() or load().")

    def _row(self, s: float) -> NDArray[np.float64]:
        g = self.phase_grid_
        x = min(max(s, 0.0), 1.0) * (len(g) - 1)
        i = min(int(x), len(g) - 2)
        w = x - i
        return (1.0 - w) * self._table[i] + w * self._table[i + 1]

    # ----------------------------------------------------------------- predict
    def phase(self, observation: ArrayLike) -> NDArray[np.float64] | float:
        """Normalised time ``t / duration`` of an observation (``(OBS_DIM,)`` -> float,
        ``(n, OBS_DIM)`` -> ``(n,)``), clipped to ``[0, 1]``; without the lookahead."""
        self._check_fitted()
        obs = np.asarray(observation, dtype=float)
        t = obs[..., self._obs_slices["time"]][..., 0]
        s = np.clip(t / self.duration_, 0.0, 1.0)
        return float(s) if obs.ndim == 1 else s

    def _step(self, obs: NDArray[np.float64]) -> tuple[Any, ...]:
        sl = self._obs_slices
        t = float(obs[sl["time"]][0])
        s = (t + self.lookahead * self.control_dt_) / self.duration_
        row = self._row(s)
        q = obs[sl["joint_pos"]]
        jm, jv = self._cols[JOINT_FRAME]
        joint_mean, joint_var = row[jm], row[jv]
        n_joints = q.shape[0]
        estimates = []
        x = J = None
        for name in self.frame_names_[1:]:
            origin, R = _frame_from_obs(obs, name, sl)
            if origin is None:  # footnote 2: object not detected
                continue
            mcol, vcol = self._cols[name]
            m, v = row[mcol], np.maximum(row[vcol], MIN_VARIANCE)
            if m.shape[0] == 3:
                estimates.append(FrameEstimate(origin + R @ m, (R * v) @ R.T, (R / v) @ R.T))
                continue
            if x is None:
                x, J = hand_points(self.robot_, q, self.approach_offset)
            pos = (origin + m.reshape(-1, 3) @ R.T).reshape(-1)
            cov = np.zeros((m.shape[0], m.shape[0]))
            prec = np.zeros_like(cov)
            for b in range(0, m.shape[0], 3):  # block diagonal: R diag(v) R^T per point
                cov[b : b + 3, b : b + 3] = (R * v[b : b + 3]) @ R.T
                prec[b : b + 3, b : b + 3] = (R / v[b : b + 3]) @ R.T
            estimates.append(FrameEstimate(pos, cov, prec))
        dq, cov = reproduction_step(
            self.robot_,
            q,
            joint_mean[:n_joints],
            joint_var[:n_joints],
            estimates,
            alpha=self.alpha,
            null_space_std=self.null_space_std,
            damping=DEFAULT_DAMPING,
            ridge=DEFAULT_RIDGE,
            ee_pos=x,
            jacobian=J,
        )
        gripper = float(joint_mean[n_joints]) if joint_mean.shape[0] > n_joints else 0.0
        step = limit_step(dq, self.max_joint_step_)
        action = self._action_from_targets(q, q + step, gripper)
        return min(max(s, 0.0), 1.0), action, dq, np.sqrt(np.diag(cov)), gripper, row

    def predict(
        self,
        observation: ArrayLike,
        state: Any = None,
        episode_start: ArrayLike | None = None,
        deterministic: bool = False,
    ) -> tuple[NDArray[np.float32], Any]:
        """The action for an observation (stable-baselines3 ``PolicyPredictor`` protocol).

        Args:
            observation: ``(OBS_DIM,)`` or ``(n_envs, OBS_DIM)``.
            state: unused (the policy is time-indexed, not recurrent); returned unchanged.
            episode_start: unused.
            deterministic: unused (the policy follows the GP means; it is always deterministic).

        Returns:
            ``(action, state)`` with ``action`` ``(8,)`` or ``(n_envs, 8)`` float32.
        """
        self._check_fitted()
        obs = np.asarray(observation, dtype=float)
        if obs.ndim == 1:
            return self._step(obs)[1], state
        if obs.ndim != 2:
            raise ValueError(
                f"observation must be (OBS_DIM,) or (n_envs, OBS_DIM), got {obs.shape}"
            )
        return np.stack([self._step(o)[1] for o in obs]), state

    def predict_distribution(self, observation: ArrayLike) -> PolicyDistribution:
        """Phase, action, fused joint increment with its std, and per-frame std (batched).

        Accepts ``(OBS_DIM,)`` or ``(n, OBS_DIM)``; always returns batched arrays (``n = 1``).
        """
        self._check_fitted()
        obs = np.atleast_2d(np.asarray(observation, dtype=float))
        out = [self._step(o) for o in obs]
        frame_std = {
            name: np.stack([np.sqrt(r[5][self._cols[name][1]]) for r in out])
            for name in self.frame_names_
        }
        return PolicyDistribution(
            phase=np.array([r[0] for r in out]),
            action=np.stack([r[1] for r in out]),
            joint_increment=np.stack([r[2] for r in out]),
            joint_std=np.stack([r[3] for r in out]),
            gripper=np.array([r[4] for r in out]),
            frame_std=frame_std,
        )

    def frame_std(self, phase: ArrayLike) -> dict[str, NDArray[np.float64]]:
        """Per frame, the predicted std at the given phases ``(n,)`` -> ``(n, d)``."""
        self._check_fitted()
        s = np.clip(np.asarray(phase, dtype=float).reshape(-1), 0.0, 1.0)
        return {
            name: np.stack(
                [np.interp(s, self.phase_grid_, col) for col in self.std_[name].T], axis=1
            )
            for name in self.frame_names_
        }

    # ------------------------------------------------------------ constraints
    def constraint_report(self, *, ratio: float = 0.5, min_width: float = 0.02) -> dict[str, Any]:
        """Where each object frame is tight, and whether that matches the demonstrated stages.

        Returns:
            ``{"intervals": [{"frame", "start", "end", "min_std", "label"}...],
            "stage_phases": {stage: mean phase over demonstrations},
            "checks": [{"stage", "phase", "expected_frame", "tight", "interval"}...]}``.
        """
        objects = {n: self.std_[n][:, :3] for n in self.frame_names_ if n != JOINT_FRAME}
        intervals = intervals_report(objects, self.phase_grid_, ratio=ratio, min_width=min_width)
        phases: dict[str, float | None] = {}
        for stage in STAGE_NAMES:
            vals = [
                p[stage] for p in getattr(self, "stage_phases_", []) if p.get(stage) is not None
            ]
            phases[stage] = float(np.mean(vals)) if vals else None
        checks = []
        for stage, frame in EXPECTED_TIGHT_FRAME.items():
            s = phases.get(stage)
            if s is None or frame not in objects:
                continue
            hit = [
                iv
                for iv in intervals
                if iv["frame"] == frame and iv["start"] - 0.05 <= s <= iv["end"] + 0.05
            ]
            checks.append(
                {
                    "stage": stage,
                    "phase": round(s, 4),
                    "expected_frame": frame,
                    "tight": bool(hit),
                    "interval": hit[0]["label"] if hit else None,
                }
            )
        return {"intervals": intervals, "stage_phases": phases, "checks": checks}

    def constraint_intervals(self) -> list[dict[str, Any]]:
        """The tight intervals of the object frames: ``[{"frame", "start", "end", "min_std",
        "label"}, ...]`` (phases), as in :meth:`constraint_report`."""
        self._check_fitted()
        return list(self.constraints_["intervals"])

    # -------------------------------------------------------------- save/load
    def save(self, path: str | os.PathLike[str], overwrite: bool = False) -> Path:
        """Write the policy to one ``.npz`` (no pickle); atomic; refuses to overwrite by default."""
        self._check_fitted()
        path = Path(path)
        if path.suffix != ".npz":
            path = (
                path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
            )
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
        metadata = {
            "format": FORMAT_NAME,
            "kind": FORMAT_NAME,
            "schema_version": SCHEMA_VERSION,
            "params": self.get_params(),
            "frame_names": self.frame_names_,
            "duration": self.duration_,
            "control_dt": self.control_dt_,
            "n_demos": int(getattr(self, "n_demos_", 0)),
            "alignment": getattr(self, "alignment_", "none"),
            "stage_phases": getattr(self, "stage_phases_", []),
            "constraints": self.constraints_,
        }
        arrays: dict[str, NDArray[Any]] = {
            "metadata": np.array(json.dumps(metadata)),
            "phase_grid": self.phase_grid_,
        }
        for name in self.frame_names_:
            arrays[f"mean__{name}"] = self.mean_[name]
            arrays[f"std__{name}"] = self.std_[name]
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez_compressed(fh, **arrays)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(
        cls, path: str | os.PathLike[str] | io.BytesIO, robot: Any = None
    ) -> GPDemonstrationPolicy:
        """Read a policy written by :meth:`save`, validating it.

        ``path`` may also be an in-memory file (``io.BytesIO``), e.g. a policy embedded in another
        file; loading never writes anything.

        Raises:
            FileNotFoundError: no such file.
            PolicyFileError: not a policy file, unsupported schema version, missing or
                inconsistent arrays (the message names what is wrong).
        """
        source: Any = path
        if isinstance(path, io.BytesIO):
            path = Path("<embedded policy>")
        else:
            path = source = Path(path)
            if not path.exists():
                raise FileNotFoundError(f"no policy file at {path}")
        try:
            with np.load(source, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except Exception as exc:
            raise PolicyFileError(f"{path} is not a readable .npz policy file: {exc}") from exc
        if "metadata" not in arrays:
            raise PolicyFileError(
                f"{path} has no 'metadata' entry; not a GPDemonstrationPolicy file"
            )
        try:
            meta = json.loads(str(arrays["metadata"]))
        except (json.JSONDecodeError, ValueError) as exc:
            raise PolicyFileError(f"{path}: metadata is not valid JSON ({exc})") from exc
        if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
            found = meta.get("format") if isinstance(meta, dict) else None
            raise PolicyFileError(f"{path} is not a GPDemonstrationPolicy file (format {found!r})")
        if meta.get("schema_version") != SCHEMA_VERSION:
            raise PolicyFileError(
                f"{path}: schema version {meta.get('schema_version')!r} is not supported "
                f"(this version of lgp_policy reads {SCHEMA_VERSION})"
            )
        for key in ("params", "frame_names", "duration", "control_dt"):
            if key not in meta:
                raise PolicyFileError(f"{path}: metadata lacks {key!r}")
        grid = arrays.get("phase_grid")
        if grid is None or grid.ndim != 1 or len(grid) < 2 or not np.all(np.diff(grid) > 0):
            raise PolicyFileError(f"{path}: 'phase_grid' must be an increasing 1-D array")
        if not (float(meta["duration"]) > 0 and float(meta["control_dt"]) > 0):
            raise PolicyFileError(f"{path}: duration and control_dt must be positive")
        names = list(meta["frame_names"])
        if not names or names[0] != JOINT_FRAME:
            raise PolicyFileError(
                f"{path}: frame_names must start with {JOINT_FRAME!r}, got {names}"
            )
        mean, std = {}, {}
        for name in names:
            for kind, store in (("mean", mean), ("std", std)):
                key = f"{kind}__{name}"
                if key not in arrays:
                    raise PolicyFileError(f"{path}: missing array {key!r}")
                a = np.asarray(arrays[key], dtype=float)
                if a.ndim != 2 or a.shape[0] != len(grid):
                    raise PolicyFileError(
                        f"{path}: {key!r} has shape {a.shape}, expected ({len(grid)}, n_dims)"
                    )
                if not np.all(np.isfinite(a)):
                    raise PolicyFileError(f"{path}: {key!r} contains NaN or inf")
                store[name] = a
            if np.any(std[name] <= 0) or std[name].shape != mean[name].shape:
                raise PolicyFileError(
                    f"{path}: {'std__' + name!r} must be positive, shaped like the mean"
                )
        params = dict(meta["params"])
        try:
            policy = cls(robot, **params)
        except TypeError as exc:
            raise PolicyFileError(f"{path}: unknown policy parameters ({exc})") from exc
        policy.phase_grid_ = np.asarray(grid, dtype=float)
        policy.mean_, policy.std_ = mean, std
        policy.frame_names_ = names
        policy.duration_ = float(meta["duration"])
        policy.control_dt_ = float(meta["control_dt"])
        policy.n_demos_ = int(meta.get("n_demos", 0))
        policy.alignment_ = str(meta.get("alignment", "none"))
        policy.stage_phases_ = list(meta.get("stage_phases", []))
        policy.constraints_ = meta.get("constraints") or policy.constraint_report()
        policy._build_table()
        return policy

    def __repr__(self) -> str:
        fitted = f", frames={self.frame_names_}" if hasattr(self, "frame_names_") else ""
        return f"GPDemonstrationPolicy(model={self.model!r}, alpha={self.alpha}{fitted})"


def hand_points(
    robot: Any, q: NDArray[np.float64], offset: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The grasp point and a point ``offset`` behind it on the hand's approach (z) axis, stacked
    ``(6,)``, and their Jacobian ``(6, k)``.

    With ``p`` the grasp point, ``z`` the approach axis and ``omega_i`` the angular-velocity
    column ``i`` of the geometric Jacobian: ``d(p - offset z)/dq_i = J_p[:, i] - offset
    (omega_i x z)``.
    """
    p, R = robot.forward_pose(q)
    J6 = np.asarray(robot.jacobian(q), dtype=float)
    z = np.asarray(R, dtype=float)[:, 2]
    Jp, Jw = J6[:3], J6[3:]
    cross = np.empty_like(Jw)  # omega_i x z for every column i
    cross[0] = Jw[1] * z[2] - Jw[2] * z[1]
    cross[1] = Jw[2] * z[0] - Jw[0] * z[2]
    cross[2] = Jw[0] * z[1] - Jw[1] * z[0]
    J2 = Jp - offset * cross
    return np.concatenate([p, p - offset * z]), np.vstack([Jp, J2])


def _obs_slices() -> dict[str, slice]:
    from gym_coffee.env import OBS_SLICES

    return dict(OBS_SLICES)


def _frame_from_obs(
    obs: NDArray[np.float64], name: str, sl: Mapping[str, slice]
) -> tuple[NDArray[np.float64] | None, NDArray[np.float64]]:
    """The object frame ``gym_coffee.env.object_frames`` builds, for one object (fast path)."""
    if name == "cup":
        return obs[sl["cup_init_pos"]], np.eye(3)
    if name == "machine":
        return obs[sl["machine_pos"]], _rot_z(np.asarray(obs[sl["machine_yaw"]][0]))
    return None, np.eye(3)
