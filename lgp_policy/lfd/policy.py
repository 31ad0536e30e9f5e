"""``GPDemonstrationPolicy``: the paper's LfD controller as a stable-baselines3 ``PolicyPredictor``.

Task-agnostic: the policy sees a task only through an adapter
(:class:`~lgp_policy.lfd.adapters.ObservationAdapter`: observation -> time, robot state, named
frames, events; the robot's kinematics; the action mapping). Without one it uses the gym-coffee
adapter (:mod:`lgp_policy.lfd.adapters.coffee`), so ``GPDemonstrationPolicy.fit(coffee_demos)``
works as before.

``fit(demos)`` takes a :class:`~lgp_policy.lfd.demonstrations.TrajectorySet` (plain arrays) or
anything the adapter converts (``adapter.to_trajectories``, e.g. a gym-coffee
``DemonstrationSet``), encodes it (:class:`~lgp_policy.lfd.encoding.DemonstrationEncoder`: the
robot state plus the gripper command, and the hand relative to every frame) and evaluates every
GP once on a dense phase grid. The paper notes that "the prediction part can then be performed
very quickly": ``predict`` only interpolates that table and runs one step of Algorithm 3
(:func:`~lgp_policy.lfd.reproduction.reproduction_step`) from the *measured* state, for a whole
batch of observations in one vectorised pass.

By default the demonstrations are first aligned in time on the gripper command's closing and
opening events (``align="gripper"``; landmarks at their mean normalised time, see
:func:`lgp_policy.lfd.encoding.phase_of`).

Per step, for each observation:

1. **phase**: ``s = (tau + lookahead * control_dt) / duration`` with ``tau`` the episode's task
   clock (the observation's time, or counted control steps), clipped to ``[0, 1]``. The clock
   *waits* (event-driven phase): just before each demonstrated gripper event (closing, opening)
   until the grasp point is within ``reach_tolerance`` of the target of the frame that is
   tightest there, and while an event the demonstrations reached by phase ``s_e`` (e.g.
   ``cup_held``) has not been observed yet in this episode; at most ``max_wait`` s in all;
2. **frames**: each frame's pose is filtered over the episode (a static-object Kalman filter with
   measurement std ``frame_noise``; a jump of the object is detected and followed); where the
   adapter says a frame is not observed (a grasped cup) its last estimate is kept;
3. the joint-space estimate and, for every frame, the world target ``o + R x_hat(s)`` with
   precision ``R diag(1/var) R^T``. ``x`` is the task vector: the grasp point and, for a robot
   with a hand orientation, a second point ``approach_offset`` behind it on the approach axis
   (``p = 6``), so that the frames also carry the approach direction;
4. Algorithm 3 (information form) gives the state increment, scaled down as a whole if a
   coordinate would move more than the action map's ``max_step``;
5. ``action = adapter.action_map(state, step, gripper)``, the gripper being the joint-space GP's
   gripper mean.

The per-environment memory (clock, filters, seen events) is the SB3 ``state``: pass back what
``predict`` returned, with ``episode_start``. With ``state=None`` the policy keeps it itself and
starts a new episode where ``episode_start`` says so or the observation's time went back.

Files: one ``.npz`` (``allow_pickle=False``) holding the phase table and a JSON string ``metadata``
(format name, schema version, parameters, adapter name, frame names, the constraint report, and
``demonstrations_env``: the env id and keywords the demonstrations were recorded with, or null;
optional, so files written before it load with none). Saving is atomic and refuses to overwrite
unless ``overwrite=True``; loading validates every name and number before building anything.
"""

from __future__ import annotations

import io
import json
import math
import os
import time as _time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lgp_policy._io import (
    FileFormatError,
    MemberSpec,
    atomic_save_npz,
    read_json_member,
    read_npz,
)
from lgp_policy.gp.local import COMBINE_RULES, DEFAULT_COMBINE
from lgp_policy.lfd.demonstrations import Trajectory, TrajectorySet
from lgp_policy.lfd.encoding import (
    JOINT_FRAME,
    DemonstrationEncoder,
    intervals_report,
    new_demonstration_scale,
    phase_of,
)
from lgp_policy.lfd.reproduction import (
    DEFAULT_ALPHA,
    DEFAULT_DAMPING,
    DEFAULT_RIDGE,
    FrameStack,
    limit_step,
    reproduction_step,
)

__all__ = [
    "FORMAT_NAME",
    "SCHEMA_VERSION",
    "GPDemonstrationPolicy",
    "PolicyDistribution",
    "PolicyFileError",
    "PolicyState",
    "demonstrations_env",
    "hand_points",
    "layout_features",
    "posture_clusters",
]

FORMAT_NAME = "lgp_policy.gp_demonstration_policy"
"""``format`` and ``kind`` of the file's JSON metadata (``residual.load_any_policy`` keys on it)."""
SCHEMA_VERSION = 3
_READABLE_VERSIONS = (1, 2, 3)
MODELS = ("local", "heteroscedastic", "exact", "empirical")
#: Bounds on numbers read from files or given to the constructor.
MAX_GRID = 100_000
MAX_STEPS = 100_000
MAX_DURATION = 1e5
MAX_CONTROL_DT = 60.0
#: Kalman filter of a static frame: process std per step = frame_noise / FILTER_WINDOW (an
#: averaging window of about this many steps) and innovation gate (std) for a jump.
FILTER_WINDOW = 25.0
JUMP_GATE = 4.0
#: Default ``posture_distance`` (rad): aligned joint trajectories further apart than this (RMS over
#: phase and joints, average linkage) are different postures. Measured on the coffee teacher: one
#: posture family 0.06-0.56 rad apart, the two mirrored families 0.97-1.31 rad.
DEFAULT_POSTURE_DISTANCE = 0.75
#: m per unit of ``|R_1 - R_2|_F``: how a frame's rotation counts against its position when the
#: layouts of two episodes are compared (a half turn about one axis counts 0.28 m).
ROTATION_LENGTH = 0.1


class PolicyFileError(FileFormatError):
    """A policy file is missing, malformed or of an unsupported version."""


@dataclass(frozen=True)
class PolicyDistribution:
    """What the policy predicts for a batch of ``n`` observations (see ``predict_distribution``).

    Attributes:
        phase: ``(n,)`` normalised time at which the GPs were read (includes the lookahead).
        action: ``(n, a)`` float32, the action ``predict`` returns.
        joint_increment: ``(n, k)`` fused state increment of Algorithm 3 (before step limiting).
        joint_std: ``(n, k)`` its std (diagonal of the fused covariance; the remaining variance).
        gripper: ``(n,)`` commanded gripper.
        frame_std: per frame (``"joint"`` and the object frames), the GPs' predicted std at
            ``phase``, ``(n, d)``; small = constrained.
    """

    phase: NDArray[np.float64]
    action: NDArray[np.float32]
    joint_increment: NDArray[np.float64]
    joint_std: NDArray[np.float64]
    gripper: NDArray[np.float64]
    frame_std: dict[str, NDArray[np.float64]]


@dataclass
class PolicyState:
    """Per-environment memory of the policy (row ``i`` = environment ``i``): the SB3 ``state``.

    Attributes:
        clock: ``(n,)`` task time (s): the episode's time minus the time spent waiting.
        last_time: ``(n,)`` time of the last observation (s).
        waited: ``(n,)`` time spent waiting for events (s).
        seen: per event, ``(n,)`` whether it has been observed in this episode.
        reached: per gripper landmark (index), ``(n,)`` whether the hand reached its target.
        position, variance, rotation: per frame, the filtered pose ``(n, d)``, its variance
            ``(n,)`` and the last observed rotation ``(n, d, d)``.
        outliers: per frame, ``(n,)`` consecutive observations outside the filter's gate.
        fresh: ``(n,)`` rows that start a new episode at the next observation.
    """

    clock: NDArray[np.float64]
    last_time: NDArray[np.float64]
    waited: NDArray[np.float64]
    fresh: NDArray[np.bool_]
    seen: dict[str, NDArray[np.bool_]] = field(default_factory=dict)
    reached: dict[int, NDArray[np.bool_]] = field(default_factory=dict)
    position: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    variance: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    rotation: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    outliers: dict[str, NDArray[np.int64]] = field(default_factory=dict)

    @classmethod
    def new(cls, n: int) -> PolicyState:
        """Memory for ``n`` environments, all at the start of an episode."""
        z = np.zeros(n)
        return cls(z.copy(), z.copy(), z.copy(), np.ones(n, dtype=bool))

    def __len__(self) -> int:
        return int(self.clock.shape[0])


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


def _coffee_adapter() -> Any:
    from lgp_policy.lfd.adapters.coffee import CoffeeAdapter

    return CoffeeAdapter()


def _builtin_adapter(name: str) -> Any:
    if name == "coffee":
        return _coffee_adapter()
    raise PolicyFileError(
        f"the policy was fitted with the adapter {name!r}; pass it: load(path, adapter=...)"
    )


MAX_ENV_KWARGS = 32
"""Most env keywords a policy file may record for its demonstrations' env."""


def demonstrations_env(metadata: Any) -> dict[str, Any] | None:
    """``{"env_id", "env_kwargs"}`` of the env the demonstrations were recorded on, from their
    metadata (``collect_demonstrations`` writes both) or a policy file's record; ``None`` when
    it names no env id.

    Raises:
        ValueError: an env id that is not a string of 1-200 characters, or env keywords that are
            not at most :data:`MAX_ENV_KWARGS` names with JSON scalar values (strings of at most
            200 characters, finite numbers, booleans, null).
    """
    if not isinstance(metadata, Mapping) or metadata.get("env_id") is None:
        return None
    env_id, kwargs = metadata["env_id"], metadata.get("env_kwargs") or {}
    if not isinstance(env_id, str) or not 0 < len(env_id) <= 200:
        raise ValueError(f"env_id must be a string of 1-200 characters, got {str(env_id)[:80]!r}")

    def scalar(v: Any) -> bool:
        if isinstance(v, str):
            return len(v) <= 200
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return math.isfinite(v)
        return v is None or isinstance(v, bool)

    if (
        not isinstance(kwargs, Mapping)
        or len(kwargs) > MAX_ENV_KWARGS
        or not all(isinstance(k, str) and 0 < len(k) <= 200 for k in kwargs)
        or not all(scalar(v) for v in kwargs.values())
    ):
        raise ValueError(
            f"env_kwargs must map at most {MAX_ENV_KWARGS} names to JSON scalars, got "
            f"{str(kwargs)[:80]!r}"
        )
    return {"env_id": env_id, "env_kwargs": dict(kwargs)}


def _finite(name: str, value: Any, low: float, high: float, *, low_open: bool = True) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    ok = math.isfinite(v) and (v > low if low_open else v >= low) and v <= high
    if not ok or isinstance(value, bool):
        bracket = "(" if low_open else "["
        raise ValueError(
            f"{name} must be a finite number in {bracket}{low}, {high}], got {value!r}"
        )
    return v


def _integer(name: str, value: Any, low: int, high: int) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or not low <= value <= high
    ):
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    return int(value)


def hand_points(
    robot: Any, q: NDArray[np.float64], offset: float | None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The task vector of ``q (k,)`` or a batch ``(n, k)``: the grasp point ``(n, d)``, or with
    ``offset`` the grasp point and a point ``offset`` behind it on the hand's approach (last) axis
    ``(n, 2d)``; and its Jacobian ``(n, p, k)`` (unbatched for one ``q``).

    With ``p`` the grasp point, ``z`` the approach axis and ``omega_i`` the angular-velocity
    column ``i`` of the geometric Jacobian: ``d(p - offset z)/dq_i = J_p[:, i] - offset
    (omega_i x z)``.
    """
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        if offset is not None:
            return _hand_points_one(robot, q, offset)
        x, J = hand_points(robot, q[None], offset)
        return x[0], J[0]
    if q.shape[0] == 1 and offset is not None:
        x, J = _hand_points_one(robot, q[0], offset)
        return x[None], J[None]
    p, R, J6 = _pose_and_jacobian(robot, q)
    d = p.shape[-1]
    Jp = J6[:, :d]
    if offset is None:
        return p, Jp
    z = R[:, :, -1]
    Jw = J6[:, d:]  # (n, 3, k)
    zx, zy, zz = z[:, 0:1], z[:, 1:2], z[:, 2:3]  # omega_i x z for every column i, (n, 3, k)
    cross = np.stack(
        [
            Jw[:, 1] * zz - Jw[:, 2] * zy,
            Jw[:, 2] * zx - Jw[:, 0] * zz,
            Jw[:, 0] * zy - Jw[:, 1] * zx,
        ],
        axis=1,
    )
    J2 = Jp - offset * cross
    return np.concatenate([p, p - offset * z], axis=1), np.concatenate([Jp, J2], axis=1)


def _pose_and_jacobian(
    robot: Any, q: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``forward_pose`` and ``jacobian`` of one state ``(k,)`` or a batch ``(n, k)``, in one pass
    where the robot offers it."""
    both = getattr(robot, "pose_and_jacobian", None)
    if both is not None:
        return both(q)
    p, R = robot.forward_pose(q)
    return p, R, np.asarray(robot.jacobian(q), dtype=float)


def _hand_points_one(
    robot: Any, q: NDArray[np.float64], offset: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`hand_points` with an offset for one state ``q (k,)`` (``d = 3``), unbatched, in a few
    calls: ``omega_i x z = -[z]_x omega_i``, so ``[J_p; J_p - offset (omega x z)] = T J6`` with
    ``T = [[I, 0], [I, offset [z]_x]]``."""
    p, R, J6 = _pose_and_jacobian(robot, q)
    p0, p1, p2 = p.tolist()
    z0, z1, z2 = R[:, 2].tolist()
    a, b, c = offset * z0, offset * z1, offset * z2
    T = np.array(  # from a flat list: cheaper than nested rows
        [
            *(1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
            *(0.0, 1.0, 0.0, 0.0, 0.0, 0.0),
            *(0.0, 0.0, 1.0, 0.0, 0.0, 0.0),
            *(1.0, 0.0, 0.0, 0.0, -c, b),
            *(0.0, 1.0, 0.0, c, 0.0, -a),
            *(0.0, 0.0, 1.0, -b, a, 0.0),
        ]
    ).reshape(6, 6)
    x = np.array([p0, p1, p2, p0 - a, p1 - b, p2 - c])
    return x, T.dot(J6)


def gripper_events(tr: Trajectory, midpoint: float) -> NDArray[np.float64]:
    """Times at which a demonstration's gripper command crosses ``midpoint`` (closing or opening),
    linearly interpolated between control steps."""
    if tr.gripper is None:
        return np.zeros(0)
    t, g = tr.time, tr.gripper - midpoint
    i = np.flatnonzero(np.sign(g[:-1]) * np.sign(g[1:]) < 0)
    w = g[i] / (g[i] - g[i + 1])
    return t[i] + w * (t[i + 1] - t[i])


def _event_phases(tr: Trajectory, phase: NDArray[np.float64]) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for name, flags in tr.events.items():
        idx = np.flatnonzero(flags)
        out[name] = float(phase[idx[0]]) if idx.size else None
    return out


def posture_clusters(joints: ArrayLike, distance: float) -> NDArray[np.intp]:
    """Group demonstrations by the posture the robot moved in.

    Args:
        joints: ``(n_demos, T, k)`` the robot states of the demonstrations, resampled on a common
            (aligned) phase grid.
        distance: demonstrations whose trajectories are further apart than this (RMS over phase
            and coordinates, average linkage) are in different clusters.

    Returns:
        ``(n_demos,)`` cluster labels ``0, 1, ...`` numbered in order of first appearance (the
        first demonstration is in cluster 0); all zeros for one demonstration.
    """
    data = np.asarray(joints, dtype=float)
    n = data.shape[0]
    if n < 2:
        return np.zeros(n, dtype=np.intp)
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    diff = data[:, None] - data[None]
    dist = np.sqrt(np.mean(diff * diff, axis=(2, 3)))
    tree = linkage(squareform(dist, checks=False), method="average")
    raw = fcluster(tree, t=distance, criterion="distance")
    order = {c: i for i, c in enumerate(dict.fromkeys(raw.tolist()))}
    return np.array([order[c] for c in raw.tolist()], dtype=np.intp)


def layout_features(
    frames: Mapping[str, tuple[ArrayLike, ArrayLike]], names: Sequence[str]
) -> NDArray[np.float64]:
    """The task parameters of a batch of layouts as one vector per row, for nearest-layout search.

    Per frame (in the order of ``names``), the position ``(n, d)`` and ``ROTATION_LENGTH`` times
    the rotation matrix's entries ``(n, d d)``, so that the Euclidean distance between two rows is
    ``sum_m |o_1 - o_2|^2 + ROTATION_LENGTH^2 |R_1 - R_2|_F^2`` under the square root.

    Args:
        frames: ``{name: (position (n, d), rotation (n, d, d))}``.
        names: the frames to use.

    Returns:
        ``(n, F)`` with ``F = len(names) (d + d^2)``.
    """
    cols = []
    for name in names:
        pos, rot = frames[name]
        p = np.asarray(pos, dtype=float)
        n = p.shape[0]
        cols += [p, ROTATION_LENGTH * np.asarray(rot, dtype=float).reshape(n, -1)]
    return np.concatenate(cols, axis=1)


class GPDemonstrationPolicy:
    """Closed-loop reproduction of demonstrations with local heteroscedastic GPs (Sec. III).

    Args (keyword-only after ``robot`` and ``adapter``):

    ================ ===================================================================
    robot            kinematics (``lgp_policy.lfd.robots.RobotModel``); default ``adapter.robot``
    adapter          how observations are read (``lgp_policy.lfd.adapters.ObservationAdapter``);
                     default the gym-coffee adapter
    n_steps          ``T``, resampled points per demonstration (encoding), >= 2
    n_grid           points of the precomputed phase table used by ``predict``, >= 2
    model            encoder model: ``local`` (paper), ``heteroscedastic``, ``exact``,
                     ``empirical``
    combine          ``LocalGP`` combination (``lgp_policy.gp.local.COMBINE_RULES``; ``product`` is
                     the paper's Eqs. 8-9); default the GP layer's ``DEFAULT_COMBINE``
    frames           frames to use (default: all in the demonstrations); ``()`` = state only
    alpha            null-space weight of Algorithm 3 (0.5 in the paper), in [0, 1]
    null_space_std   ``None``: a frame's null-space information = the joint estimate's; or a std
    posture_distance rad; demonstrations of a redundant robot whose aligned joint trajectories
                     are further apart than this (RMS, average linkage) move in different postures
                     (e.g. mirrored arm configurations): the joint-space GPs are fitted per
                     posture cluster and each step uses the cluster of the demonstration whose
                     layout (the frames' poses) is nearest the current one; ``None``: one joint
                     model of all demonstrations (the paper)
    lookahead        control steps ahead at which the GPs are read (compensates tracking lag)
    max_joint_step   largest change of a state coordinate per step; default the action map's
    std_scale        per-frame multiplier of the predicted std, e.g. ``{"cup": 0.5}``
    align            ``"gripper"``: align the demonstrations in time on the gripper command's
                     closing/opening events before encoding; ``None``: plain normalised time
    approach_offset  ``"auto"`` (0.1 m for a robot with a hand orientation, else ``None``), a
                     distance (m) of a second task point behind the grasp point along the hand's
                     approach axis (task vector p = 6), or ``None``: position only (the paper)
    frame_noise      std (m) of the observed frame positions for the online filter; 0 = trust
                     every observation
    max_wait         s; longest time per episode the phase waits (for the hand to reach the
                     target before a gripper event, and for a demonstrated event); 0 = clock only
    reach_tolerance  m; before a demonstrated gripper event the phase waits until the grasp point
                     is this close (or within 3 predicted std) to the target of the tightest frame
                     at that event
    extrapolate      s; past the end of the demonstrations (an episode the task has not ended
                     yet) the targets go on along the demonstrations' mean motion over their last
                     2% of phase for at most this long, then stop; 0 = hold the last targets
    encoder_kwargs   extra arguments for :class:`~lgp_policy.lfd.encoding.DemonstrationEncoder`
    ================ ===================================================================

    Attributes (after ``fit`` or ``load``):
        phase_grid_: ``(n_grid,)``; ``mean_`` / ``std_``: per frame, ``(n_grid, d)`` tables.
        frame_names_: ``["joint", <frames>...]`` (those used). ``duration_``: mean
        demonstration duration (s); ``control_dt_``: control period (s).
        approach_offset_: the resolved approach offset (m or ``None``).
        event_phases_: per event, the latest phase at which a demonstration first showed it.
        landmarks_: ``[(phase, frame), ...]``: the aligned gripper events and the frame that is
            tightest at each (where the phase waits for the hand to arrive).
        constraints_: the constraint report (see :meth:`constraint_report`).
        posture_labels_: ``(n_demos,)`` posture cluster of each demonstration, or ``None`` (one
            posture: the joint model of all demonstrations is used everywhere).
        layout_features_: ``(n_demos, F)`` the demonstrations' layouts (:func:`layout_features`
            of the frames' initial poses), or ``None``.
        posture_mean_, posture_std_: per posture cluster, ``(n_grid, d)`` joint-frame tables (the
            state from the cluster, the gripper from all demonstrations).
        demonstrations_env_: ``{"env_id", "env_kwargs"}`` of the env the demonstrations were
            recorded on, when their metadata names one (gym-coffee's recordings do), else
            ``None``; saved with the policy (``gym-coffee evaluate`` defaults to it).
        encoder_: the fitted encoder (only after ``fit``; not saved).
    """

    def __init__(
        self,
        robot: Any = None,
        adapter: Any = None,
        *,
        n_steps: int = 200,
        n_grid: int = 500,
        model: str = "local",
        combine: str = DEFAULT_COMBINE,
        frames: Sequence[str] | None = None,
        alpha: float = DEFAULT_ALPHA,
        null_space_std: float | None = None,
        posture_distance: float | None = DEFAULT_POSTURE_DISTANCE,
        lookahead: float = 1.0,
        max_joint_step: float | None = None,
        std_scale: Mapping[str, float] | None = None,
        approach_offset: float | str | None = "auto",
        align: str | None = "gripper",
        frame_noise: float = 0.005,
        max_wait: float = 2.0,
        reach_tolerance: float = 0.01,
        extrapolate: float = 1.0,
        encoder_kwargs: Mapping[str, Any] | None = None,
    ) -> None:
        self.robot = robot
        self.adapter = adapter
        self.n_steps = _integer("n_steps", n_steps, 2, MAX_STEPS)
        self.n_grid = _integer("n_grid", n_grid, 2, MAX_GRID)
        if model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {model!r}")
        if combine not in COMBINE_RULES:
            raise ValueError(f"combine must be one of {COMBINE_RULES}, got {combine!r}")
        self.model, self.combine = model, combine
        if frames is not None and (
            isinstance(frames, str) or not all(isinstance(f, str) for f in frames)
        ):
            raise ValueError(f"frames must be a sequence of frame names or None, got {frames!r}")
        self.frames = None if frames is None else tuple(frames)
        self.alpha = _finite("alpha", alpha, 0.0, 1.0, low_open=False)
        self.null_space_std = (
            None if null_space_std is None else _finite("null_space_std", null_space_std, 0.0, 1e3)
        )
        self.posture_distance = (
            None
            if posture_distance is None
            else _finite("posture_distance", posture_distance, 0.0, 1e3)
        )
        self.lookahead = _finite("lookahead", lookahead, 0.0, 100.0, low_open=False)
        self.max_joint_step = (
            None if max_joint_step is None else _finite("max_joint_step", max_joint_step, 0.0, 1e3)
        )
        scale = dict(std_scale or {})
        for k, v in scale.items():
            _finite(f"std_scale[{k!r}]", v, 0.0, 1e6)
        self.std_scale = scale or None
        if not (approach_offset is None or approach_offset == "auto"):
            approach_offset = _finite("approach_offset", approach_offset, -10.0, 10.0)
        self.approach_offset = approach_offset
        if align not in ("gripper", None):
            raise ValueError(f"align must be 'gripper' or None, got {align!r}")
        self.align = align
        self.frame_noise = _finite("frame_noise", frame_noise, 0.0, 10.0, low_open=False)
        self.max_wait = _finite("max_wait", max_wait, 0.0, 1e4, low_open=False)
        self.reach_tolerance = _finite("reach_tolerance", reach_tolerance, 0.0, 10.0)
        self.extrapolate = _finite("extrapolate", extrapolate, 0.0, 1e4, low_open=False)
        self.encoder_kwargs = None if encoder_kwargs is None else dict(encoder_kwargs)

    # -------------------------------------------------------------- parameters
    def get_params(self) -> dict[str, Any]:
        """Constructor arguments that are saved with the policy (all but ``robot``/``adapter``)."""
        return {
            "n_steps": self.n_steps,
            "n_grid": self.n_grid,
            "model": self.model,
            "combine": self.combine,
            "frames": None if self.frames is None else list(self.frames),
            "alpha": self.alpha,
            "null_space_std": self.null_space_std,
            "posture_distance": self.posture_distance,
            "lookahead": self.lookahead,
            "max_joint_step": self.max_joint_step,
            "std_scale": None if self.std_scale is None else dict(self.std_scale),
            "approach_offset": self.approach_offset,
            "align": self.align,
            "frame_noise": self.frame_noise,
            "max_wait": self.max_wait,
            "reach_tolerance": self.reach_tolerance,
            "extrapolate": self.extrapolate,
            "encoder_kwargs": None if self.encoder_kwargs is None else dict(self.encoder_kwargs),
        }

    def _resolve(self) -> None:
        """Adapter, robot and action map in use (``adapter_``, ``robot_``)."""
        self.adapter_ = self.adapter if self.adapter is not None else _coffee_adapter()
        self.robot_ = self.robot if self.robot is not None else self.adapter_.robot
        self.gripper_ = getattr(self.adapter_, "gripper", None)
        step = self.max_joint_step
        self.max_joint_step_ = float(
            step if step is not None else self.adapter_.action_map.max_step
        )

    def _trajectories(self, demos: Any) -> TrajectorySet:
        if isinstance(demos, TrajectorySet):
            return demos
        items = list(demos) if not isinstance(demos, Trajectory) else [demos]
        if items and all(isinstance(d, Trajectory) for d in items):
            return TrajectorySet(items)
        convert = getattr(self.adapter_, "to_trajectories", None)
        if convert is None:
            raise TypeError(
                f"demos must be a TrajectorySet or Trajectory list; the adapter "
                f"{type(self.adapter_).__name__} cannot convert {type(demos).__name__}"
            )
        return convert(demos)

    # -------------------------------------------------------------------- fit
    @_HybridFit
    def fit(
        self, demos: Any, *, progress: bool = False, allow_failed: bool = False
    ) -> GPDemonstrationPolicy:
        """Encode demonstrations and precompute the phase table.

        Callable on the class (default parameters) or on an instance.

        Args:
            demos: a :class:`~lgp_policy.lfd.demonstrations.TrajectorySet` (or a list of
                ``Trajectory``), or what the adapter converts (the coffee adapter: a gym-coffee
                ``DemonstrationSet``), with at least one demonstration.
            progress: print what is being fitted.
            allow_failed: fit demonstrations whose ``success`` flag is false too (otherwise
                they are refused, naming their indices).

        Returns:
            ``self``.
        """
        start = _time.perf_counter()
        self._resolve()
        trajs = self._trajectories(demos)
        failed = [i for i, tr in enumerate(trajs) if not tr.success]
        if failed and not allow_failed:
            raise ValueError(
                f"demonstrations {failed} did not succeed (success=False); remove them or pass "
                f"allow_failed=True"
            )
        robot = self.robot_
        if trajs.state_dim != robot.n_joints:
            raise ValueError(
                f"the demonstrations' state has {trajs.state_dim} entries, the robot "
                f"{type(robot).__name__} has {robot.n_joints}"
            )
        available = trajs.frame_names
        names = available if self.frames is None else list(self.frames)
        unknown = [n for n in names if n not in available]
        if unknown:
            raise ValueError(f"unknown frames {unknown}; the demonstrations have {available}")
        adapter_frames = tuple(getattr(self.adapter_, "frame_names", ()))
        missing = [n for n in names if n not in adapter_frames]
        if missing:
            raise ValueError(
                f"frames {missing} are in the demonstrations but the adapter reads only "
                f"{list(adapter_frames)}"
            )
        for n in names:
            d = trajs[0].frames[n][0].shape[1]
            if d != robot.dim:
                raise ValueError(
                    f"frame {n!r} is {d}-D but the robot's task space is {robot.dim}-D"
                )
        offset = self.approach_offset
        if offset == "auto":
            offset = 0.1 if robot.has_orientation else None
        elif offset is not None and not robot.has_orientation:
            raise ValueError("approach_offset needs a robot with a hand orientation; use None")
        self.approach_offset_: float | None = offset  # type: ignore[assignment]
        if (self.gripper_ is None) != (trajs[0].gripper is None):
            raise ValueError(
                "the demonstrations and the adapter disagree on the gripper: "
                f"demonstrations {'have' if trajs[0].gripper is not None else 'have no'} gripper "
                f"command, adapter gripper={self.gripper_!r}"
            )
        times = [tr.time for tr in trajs]
        joints = [
            tr.state if tr.gripper is None else np.column_stack([tr.state, tr.gripper])
            for tr in trajs
        ]
        ees = (
            [hand_points(robot, tr.state, self.approach_offset_)[0] for tr in trajs]
            if names
            else None
        )
        frames = [{n: tr.initial_frames()[n] for n in names} for tr in trajs] if names else None
        kwargs = dict(self.encoder_kwargs or {})
        kwargs.setdefault("n_steps", self.n_steps)
        kwargs.setdefault("model", self.model)
        kwargs.setdefault("combine", self.combine)
        encoder = DemonstrationEncoder(**kwargs)
        say = (lambda msg: print(f"  {msg}", flush=True)) if progress else None
        landmarks = None
        self.alignment_ = "none"
        if self.align == "gripper" and self.gripper_ is not None:
            events = [gripper_events(tr, self.gripper_.midpoint) for tr in trajs]
            if len({e.size for e in events}) == 1 and events[0].size > 0:
                landmarks = events
                self.alignment_ = f"gripper events ({events[0].size})"
            else:
                self.alignment_ = (
                    "none (gripper event counts differ: " + str([e.size for e in events]) + ")"
                )
        encoder.fit(times, joints, ees, frames, landmarks=landmarks, progress=say)
        self.encoder_ = encoder
        self.frame_names_ = list(encoder.frame_names_)
        self.phase_grid_ = np.linspace(0.0, 1.0, self.n_grid)
        self.mean_, self.std_ = {}, {}
        for name in self.frame_names_:
            self.mean_[name], self.std_[name] = encoder.predict(self.phase_grid_, name)
        self._fit_postures(encoder, kwargs, trajs, names, say)
        self.duration_ = float(np.mean(encoder.durations_))
        self.control_dt_ = float(np.median([np.median(np.diff(t)) for t in times]))
        self.n_demos_ = len(trajs)
        try:  # where the demonstrations came from, if they say (evaluation defaults to it)
            self.demonstrations_env_ = demonstrations_env(trajs.metadata)
        except ValueError:  # free-form metadata: not an env this library can make
            self.demonstrations_env_ = None
        lp = encoder.landmark_phases_
        self.stage_phases_ = [
            _event_phases(tr, phase_of(tr.time, landmarks[i] if landmarks else None, lp))
            for i, tr in enumerate(trajs)
        ]
        self.landmarks_ = []
        if landmarks is not None and names:
            for s_l in encoder.landmark_phases_:
                spread = {
                    n: float(np.sqrt(np.mean(encoder.predict([s_l], n)[1][0, : robot.dim] ** 2)))
                    for n in names
                }
                self.landmarks_.append((float(s_l), min(spread, key=spread.__getitem__)))
        self.event_phases_ = {}
        for ev in trajs[0].events:
            vals = [p.get(ev) for p in self.stage_phases_]
            if all(v is not None for v in vals):
                self.event_phases_[ev] = float(max(v for v in vals if v is not None))
        self.constraints_ = self.constraint_report()
        self._build_table()
        self.fit_time_ = _time.perf_counter() - start
        return self

    def _fit_postures(
        self,
        encoder: DemonstrationEncoder,
        kwargs: Mapping[str, Any],
        trajs: TrajectorySet,
        names: Sequence[str],
        say: Callable[[str], None] | None,
    ) -> None:
        """Joint-space tables per posture cluster (``posture_distance``), or none.

        Only for a redundant robot (more state coordinates than task-vector entries: the joint
        estimate then chooses a posture in the null space, and the mean of two postures is one
        the demonstrations never took) with object frames (their poses are the layout).

        The clusters share their spread, as the components of a Gaussian mixture with a tied
        covariance: a cluster's mean is the mean of its demonstrations' aligned joint
        trajectories; the spread is the GP (the policy's encoder) of every demonstration's
        deviation from its cluster's mean, corrected for the ``C`` estimated means
        (``sqrt(n / (n - C))``) and, as the encoder does, turned into a prediction of a new
        demonstration (Student t with ``n - C`` degrees of freedom, and ``sqrt(1 + 1 / n_c)`` for
        the cluster mean's own uncertainty). A cluster of one demonstration thus borrows the
        spread of the others; with no cluster of two, every cluster takes the spread of all
        demonstrations (the weakest pull). The gripper columns stay those of all
        demonstrations."""
        self.posture_labels_: NDArray[np.intp] | None = None
        self.layout_features_: NDArray[np.float64] | None = None
        self.posture_mean_: list[NDArray[np.float64]] = []
        self.posture_std_: list[NDArray[np.float64]] = []
        robot = self.robot_
        k = robot.n_joints
        p = robot.dim * (2 if self.approach_offset_ is not None else 1)
        if self.posture_distance is None or len(trajs) < 2 or not names or k <= p:
            return
        data = encoder.data_[JOINT_FRAME][:, :, :k]
        labels = posture_clusters(data, self.posture_distance)
        n, n_clusters = len(data), int(labels.max()) + 1
        if n_clusters == 1:
            return
        grid = encoder.phase_
        means = np.stack([data[labels == c].mean(axis=0) for c in range(n_clusters)])
        tied = None
        if n > n_clusters:
            if say is not None:
                say(f"encoding the joint frame's spread within {n_clusters} postures")
            sub = DemonstrationEncoder(**{**kwargs, "calibrate": False})
            sub.fit([grid] * n, list(data - means[labels]))
            tied = sub.predict(self.phase_grid_, JOINT_FRAME)[1] * math.sqrt(n / (n - n_clusters))
            if getattr(encoder, "calibrate", True):
                tied = tied * new_demonstration_scale(n - n_clusters + 1)
        for c in range(n_clusters):
            n_c = int(np.sum(labels == c))
            mean = np.stack([np.interp(self.phase_grid_, grid, col) for col in means[c].T], axis=1)
            std = (
                self.std_[JOINT_FRAME][:, :k]
                if tied is None
                else np.maximum(
                    tied * math.sqrt(1.0 + 1.0 / n_c), encoder.std_floor_[JOINT_FRAME][:k]
                )
            )
            # the gripper (and any other column after the state) from all demonstrations
            self.posture_mean_.append(np.hstack([mean, self.mean_[JOINT_FRAME][:, k:]]))
            self.posture_std_.append(np.hstack([std, self.std_[JOINT_FRAME][:, k:]]))
        self.posture_labels_ = labels
        initial = [tr.initial_frames() for tr in trajs]
        self.layout_features_ = layout_features(
            {
                n: (np.stack([f[n][0] for f in initial]), np.stack([f[n][1] for f in initial]))
                for n in names
            },
            names,
        )

    def _posture_of(self, state: PolicyState) -> NDArray[np.intp]:
        """Per environment, the posture cluster of the demonstration whose layout is nearest the
        frames' current (filtered) poses."""
        feats = layout_features(
            {n: (state.position[n], state.rotation[n]) for n in self.frame_names_[1:]},
            self.frame_names_[1:],
        )
        diff = feats[:, None, :] - self.layout_features_[None]  # type: ignore[index]
        nearest = np.argmin(np.einsum("ijk,ijk->ij", diff, diff), axis=1)
        return self.posture_labels_[nearest]  # type: ignore[index]

    def _posture_one(self, state: PolicyState) -> int:
        """:meth:`_posture_of` for one environment."""
        parts = []
        for name in self.frame_names_[1:]:
            parts += [state.position[name][0], ROTATION_LENGTH * state.rotation[name].reshape(-1)]
        diff = np.concatenate(parts) - self.layout_features_
        nearest = np.argmin(np.einsum("jk,jk->j", diff, diff))
        return int(self.posture_labels_[nearest])  # type: ignore[index]

    def _joint_rows(
        self, row: NDArray[np.float64], state: PolicyState
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The joint-space mean and variance ``(n, k)`` of each environment's posture cluster,
        from the table rows ``row (n, D)``."""
        labels = self._posture_of(state)
        if labels.shape == (1,):
            mcol, vcol = self._posture_cols[int(labels[0])]
            return row[:, mcol], row[:, vcol]
        d = self.posture_mean_[0].shape[1]
        mean, var = np.empty((len(row), d)), np.empty((len(row), d))
        for c, (mcol, vcol) in enumerate(self._posture_cols):
            sel = labels == c
            mean[sel], var[sel] = row[sel, mcol], row[sel, vcol]
        return mean, var

    # ------------------------------------------------------------------ table
    def _build_table(self) -> None:
        """Stack the means and variances of all frames in one ``(n_grid, D)`` table."""
        scale = dict(self.std_scale or {})
        cols, self._cols = [], {}
        c = 0
        for name in self.frame_names_:
            d = self.mean_[name].shape[1]
            var = (self.std_[name] * scale.get(name, 1.0)) ** 2
            cols += [self.mean_[name], var]
            self._cols[name] = (slice(c, c + d), slice(c + d, c + 2 * d))
            c += 2 * d
        # the object frames' columns, one after the other: (m, 2, p) = per frame, means and vars
        self._frame_block = slice(self._cols[JOINT_FRAME][1].stop, c)
        self._posture_cols = []
        for mean, std in zip(self.posture_mean_, self.posture_std_, strict=True):
            d = mean.shape[1]
            cols += [mean, (std * scale.get(JOINT_FRAME, 1.0)) ** 2]
            self._posture_cols.append((slice(c, c + d), slice(c + d, c + 2 * d)))
            c += 2 * d
        self._table = np.ascontiguousarray(np.hstack(cols))
        # past the end: the means' mean slope over the last 2% of phase (variances held)
        g = len(self.phase_grid_)
        k = max(1, round(0.02 * (g - 1)))
        slope = (self._table[-1] - self._table[-1 - k]) / (
            self.phase_grid_[-1] - self.phase_grid_[-1 - k]
        )
        for _, var_cols in [*self._cols.values(), *self._posture_cols]:
            slope[var_cols] = 0.0
        self._end_slope = slope
        self._memory: PolicyState | None = None

    def _check_fitted(self) -> None:
        if not hasattr(self, "_table"):
            raise RuntimeError("This GPDemonstrationPolicy is not fitted; call fit() or load().")

    def _row(self, s: float) -> NDArray[np.float64]:
        """:meth:`_rows` of one phase given as a float -> ``(D,)`` (the same operations)."""
        if s > 1.0 and self.extrapolate > 0.0:  # the motion goes on past the end
            return self._table[-1] + min(s - 1.0, self.extrapolate / self.duration_) * (
                self._end_slope
            )
        g = len(self.phase_grid_)
        x = min(max(s, 0.0), 1.0) * (g - 1)
        j = min(int(x), g - 2)
        w = x - j
        return (1.0 - w) * self._table[j] + w * self._table[j + 1]

    def _rows(self, s: NDArray[np.float64]) -> NDArray[np.float64]:
        """Linear interpolation of the table at phases ``s (n,)`` -> ``(n, D)``."""
        if s.shape == (1,):
            return self._row(float(s[0]))[None]
        g = len(self.phase_grid_)
        beyond = self.extrapolate / self.duration_  # phase past 1 over which the motion goes on
        x = np.clip(s, 0.0, 1.0) * (g - 1)
        i = np.minimum(x.astype(np.intp), g - 2)
        w = (x - i)[:, None]
        rows = (1.0 - w) * self._table[i] + w * self._table[i + 1]
        if beyond > 0.0 and np.any(s > 1.0):
            rows += np.clip(s - 1.0, 0.0, beyond)[:, None] * self._end_slope
        return rows

    def _frame_columns(self) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Table columns of the object frames' means and variances, ``(m, p)`` each."""
        cached = getattr(self, "_frame_cols", None)
        if cached is None or cached[0] is not self._table:
            names = self.frame_names_[1:]
            spans = [[np.arange(c.start, c.stop) for c in self._cols[f]] for f in names]
            cached = self._frame_cols = (
                self._table,
                np.array([m for m, _ in spans], dtype=np.intp).reshape(len(names), -1),
                np.array([v for _, v in spans], dtype=np.intp).reshape(len(names), -1),
            )
        return cached[1], cached[2]

    def _as_batch(self, observation: ArrayLike) -> tuple[NDArray[np.float64], bool]:
        dim = int(self.adapter_.obs_dim)
        try:
            obs = np.asarray(observation, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(
                f"observation must be numbers of shape ({dim},) or (n_envs, {dim})"
            ) from None
        single = obs.ndim == 1
        if obs.ndim not in (1, 2) or obs.shape[-1] != dim or obs.size == 0:
            raise ValueError(
                f"observation must have shape ({dim},) or (n_envs, {dim}), got {obs.shape}"
            )
        if single:  # a finite dot product means finite entries (it is cheaper on one row)
            if not math.isfinite(obs.dot(obs)) and not np.isfinite(obs).all():
                raise ValueError("observation contains NaN or inf")
            return obs[None], single
        if not np.isfinite(obs).all():
            raise ValueError("observation contains NaN or inf")
        return obs, single

    # ----------------------------------------------------------------- predict
    def phase(self, observation: ArrayLike) -> NDArray[np.float64] | float:
        """Normalised time ``t / duration`` of an observation (``(obs_dim,)`` -> float,
        ``(n, obs_dim)`` -> ``(n,)``), clipped to ``[0, 1]``; without the lookahead or waiting.
        Needs an adapter whose observation has a clock."""
        self._check_fitted()
        obs, single = self._as_batch(observation)
        t = self.adapter_.read(obs).time
        if t is None:
            raise ValueError("this adapter's observation has no time; the phase is in the state")
        s = np.clip(t / self.duration_, 0.0, 1.0)
        return float(s[0]) if single else s

    def _advance(
        self, state: PolicyState, observed: Any, hand: NDArray[np.float64] | None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Update the per-environment clock, frame filters and events.

        ``hand``: the grasp point ``(n, d)`` (for the waits before gripper events).

        Returns:
            ``(clock (n,), aim (n,))``: the task clock, and for rows waiting to reach the target
            of a gripper event the phase of that event (the motion aims there while the gripper
            keeps its command), else NaN.
        """
        t_obs = observed.time
        n = len(state)
        fresh = state.fresh.copy()
        if t_obs is not None:
            fresh |= t_obs < state.last_time - 1e-9
            dt = np.where(fresh, 0.0, t_obs - state.last_time)
            now = t_obs
            clock = np.where(fresh, t_obs, state.clock + dt)
        else:
            dt = np.where(fresh, 0.0, self.control_dt_)
            now = np.where(fresh, 0.0, state.last_time + self.control_dt_)
            clock = np.where(fresh, 0.0, state.clock + dt)
        self._filter_frames(state, fresh, observed)
        waited = np.where(fresh, 0.0, state.waited)
        s = clock / self.duration_
        hold = np.zeros(n, dtype=bool)
        aim = np.full(n, np.nan)
        if self.max_wait > 0:
            lead = (self.lookahead + 1.0) * self.control_dt_ / self.duration_
            for j, (s_l, frame) in enumerate(self.landmarks_ if hand is not None else []):
                reached = np.where(fresh, False, state.reached.get(j, np.zeros(n, bool)))
                due = ~reached & (s >= s_l - lead)
                if np.any(due) and hand is not None:
                    close = self._hand_at_landmark(state, frame, s_l, hand)
                    reached = reached | (due & close)
                    hold |= due & ~close
                    aim = np.where(due & ~close & np.isnan(aim), s_l, aim)
                state.reached[j] = reached
            for ev, s_e in self.event_phases_.items():
                flags = observed.events.get(ev)
                if flags is None:
                    continue
                seen = np.where(fresh, False, state.seen.get(ev, np.zeros(n, bool))) | flags
                state.seen[ev] = seen
                hold |= ~seen & (s >= s_e)
        hold &= (waited + dt <= self.max_wait) & ~fresh
        state.clock = np.where(hold, clock - dt, clock)
        state.waited = np.where(hold, waited + dt, waited)
        state.last_time = now
        state.fresh = np.zeros(n, dtype=bool)
        return state.clock, np.where(hold, aim, np.nan)

    def _hand_at_landmark(
        self, state: PolicyState, frame: str, s_l: float, hand: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        """Per row, whether the hand ``(n, d)`` is at the target ``o + R x_hat(s_l)`` of
        ``frame`` (as :func:`~lgp_policy.lfd.reproduction.frame_targets`), within
        ``reach_tolerance`` or 3 predicted std."""
        mcol, vcol = self._cols[frame]
        row = self._row(s_l)
        d = hand.shape[1]
        target = state.position[frame] + np.matvec(state.rotation[frame], row[mcol][:d])
        # a frame that is loose there (demonstrations disagree) asks for no precision
        tol = max(self.reach_tolerance, 3.0 * math.sqrt(sum(row[vcol][:d].tolist()) / d))
        return np.asarray(np.linalg.norm(hand - target, axis=1) <= tol)

    def _hand_at_landmark_one(
        self, state: PolicyState, frame: str, s_l: float, hand: list[float]
    ) -> bool:
        """:meth:`_hand_at_landmark` for one environment, the hand given as floats (the same
        operations in the same order)."""
        mcol, vcol = self._cols[frame]
        row = self._row(s_l)
        d = len(hand)
        mean, var = row[mcol][:d].tolist(), row[vcol][:d].tolist()
        origin, rot = state.position[frame][0].tolist(), state.rotation[frame][0].tolist()
        dist = 0.0
        spread = 0.0
        for i in range(d):  # target = o + R x_hat (frame_targets), |hand - target|
            m_r = 0.0
            for j in range(d):
                m_r += mean[j] * rot[i][j]
            diff = hand[i] - (origin[i] + m_r)
            dist += diff * diff
            spread += var[i]
        # a frame that is loose there (demonstrations disagree) asks for no precision
        tol = max(self.reach_tolerance, 3.0 * math.sqrt(spread / d))
        return math.sqrt(dist) <= tol

    def _advance_one(
        self, state: PolicyState, observed: Any, hand: list[float] | None
    ) -> tuple[float, float | None]:
        """:meth:`_advance` for one environment on plain floats (the same operations in the same
        order, so the same results; a batch of one is the common control loop): the hand's
        grasp point as floats; returns the clock and the phase aimed at (``None``: not
        waiting)."""
        t_obs = observed.time
        last = float(state.last_time.item(0))  # (item: a Python number, no numpy scalar)
        fresh = bool(state.fresh.item(0))
        if t_obs is not None:
            t = float(t_obs.item(0))
            fresh = fresh or t < last - 1e-9
            dt = 0.0 if fresh else t - last
            now = t
            clock = t if fresh else float(state.clock.item(0)) + dt
        else:
            dt = 0.0 if fresh else self.control_dt_
            now = 0.0 if fresh else last + self.control_dt_
            clock = 0.0 if fresh else float(state.clock.item(0)) + dt
        self._filter_one(state, fresh, observed)
        waited = 0.0 if fresh else float(state.waited.item(0))
        s = clock / self.duration_
        hold = False
        aim: float | None = None
        if self.max_wait > 0:
            lead = (self.lookahead + 1.0) * self.control_dt_ / self.duration_
            for j, (s_l, frame) in enumerate(self.landmarks_ if hand is not None else []):
                flag = state.reached.get(j)
                if flag is None:
                    flag = state.reached[j] = np.zeros(1, dtype=bool)
                reached = not fresh and bool(flag.item(0))
                if not reached and s >= s_l - lead and hand is not None:  # due
                    reached = self._hand_at_landmark_one(state, frame, s_l, hand)
                    if not reached:
                        hold = True
                        if aim is None:
                            aim = s_l
                flag[0] = reached
            events = observed.events
            for ev, s_e in self.event_phases_.items():
                observed_flag = events.get(ev)
                if observed_flag is None:
                    continue
                flag = state.seen.get(ev)
                if flag is None:
                    flag = state.seen[ev] = np.zeros(1, dtype=bool)
                seen = (not fresh and bool(flag.item(0))) or bool(observed_flag.item(0))
                flag[0] = seen
                hold = hold or (not seen and s >= s_e)
        hold = hold and waited + dt <= self.max_wait and not fresh
        if hold:
            clock, waited = clock - dt, waited + dt
        # written in place: the state's arrays are its own (PolicyState.new, _advance)
        state.clock[0] = clock
        state.waited[0] = waited
        state.last_time[0] = now
        state.fresh[0] = False
        return clock, aim if hold else None

    def _filter_one(self, state: PolicyState, fresh: bool, observed: Any) -> None:
        """:meth:`_filter_frames` for one environment on plain floats."""
        r = self.frame_noise**2
        q = r / FILTER_WINDOW**2
        for name in self.frame_names_[1:]:
            if name not in observed.frames:
                self._filter_frames(state, np.array([fresh]), observed)  # raises the error
            z_arr, R = observed.frames[name]
            flag = observed.valid.get(name)
            valid = True if flag is None else bool(flag.item(0))
            if name not in state.position:
                state.position[name] = z_arr.copy()
                state.variance[name] = np.full(1, r)
                state.rotation[name] = np.array(R, dtype=float)
                state.outliers[name] = np.zeros(1, dtype=np.int64)
            pos = state.position[name]
            take = fresh or valid
            if r == 0.0:
                if take:
                    pos[0] = z_arr[0]
            else:
                var = float(state.variance[name].item(0))
                out = int(state.outliers[name].item(0))
                z = z_arr[0].tolist()
                p = pos[0].tolist()
                var_p = var + q
                nu = [zi - pi for zi, pi in zip(z, p, strict=True)]
                S = var_p + r
                ss = 0.0
                for v in nu:
                    ss += v * v
                gate = ss > JUMP_GATE**2 * S * len(z)
                out = out + 1 if valid and gate else 0
                jump = fresh or (valid and gate and out >= 2)
                upd = valid and not gate
                K = var_p / S if upd else 0.0
                if jump:
                    pos[0] = z
                    var, out = r, 0
                else:
                    if K != 0.0:  # (K = 0 leaves the estimate as it is)
                        pos[0] = [pi + K * v for pi, v in zip(p, nu, strict=True)]
                    if valid:
                        var = (1.0 - K) * var_p if upd else var_p
                state.variance[name][0] = var
                state.outliers[name][0] = out
            if take:
                state.rotation[name][0] = R[0]

    def _filter_frames(self, state: PolicyState, fresh: NDArray[np.bool_], observed: Any) -> None:
        r = self.frame_noise**2
        q = r / FILTER_WINDOW**2
        for name in self.frame_names_[1:]:
            if name not in observed.frames:
                raise ValueError(
                    f"the adapter returned no frame {name!r} (it returned "
                    f"{sorted(observed.frames)}); the policy needs every frame it was fitted with"
                )
            z, R = observed.frames[name]
            n = len(fresh)
            valid = observed.valid.get(name)
            valid = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
            if name not in state.position:
                state.position[name] = z.copy()
                state.variance[name] = np.full(n, r)
                state.rotation[name] = np.array(R, dtype=float)
                state.outliers[name] = np.zeros(n, dtype=np.int64)
            pos, var = state.position[name], state.variance[name]
            out = state.outliers[name]
            take = fresh | valid
            if r == 0.0:
                pos[take] = z[take]
            else:
                var_p = var + q
                nu = z - pos
                S = var_p + r
                gate = np.einsum("ij,ij->i", nu, nu) > JUMP_GATE**2 * S * z.shape[1]
                out = np.where(valid & gate, out + 1, 0)
                jump = fresh | (valid & gate & (out >= 2))
                upd = valid & ~gate
                K = np.where(upd, var_p / S, 0.0)
                pos += K[:, None] * nu
                var = np.where(valid & ~jump, np.where(upd, (1.0 - K) * var_p, var_p), var)
                pos[jump] = z[jump]
                var = np.where(jump, r, var)
                out = np.where(jump, 0, out)
            rot = state.rotation[name]
            rot[take] = R[take]
            state.position[name], state.variance[name], state.outliers[name] = pos, var, out

    def _state_for(
        self, n: int, state: Any, episode_start: ArrayLike | None
    ) -> tuple[PolicyState, bool]:
        own = state is None
        if own:
            mem = self._memory
            state = mem if mem is not None and len(mem) == n else PolicyState.new(n)
        elif not isinstance(state, PolicyState) or len(state) != n:
            raise ValueError(
                f"state must be None or the PolicyState predict returned for {n} environments"
            )
        if episode_start is not None:
            starts = np.asarray(episode_start, dtype=bool).reshape(-1)
            if starts.shape != (n,):
                raise ValueError(f"episode_start must have {n} entries, got {starts.shape}")
            if n == 1:  # in place: the state's arrays are its own (PolicyState.new, _advance)
                if starts[0]:
                    state.fresh[0] = True
            else:
                state.fresh = state.fresh | starts
        return state, own

    def _compute(
        self, observation: ArrayLike, state: Any, episode_start: ArrayLike | None, cov: bool
    ) -> tuple[Any, ...]:
        self._check_fitted()
        obs, single = self._as_batch(observation)
        n = obs.shape[0]
        if n == 1:
            return self._compute_one(obs, single, state, episode_start, cov)
        mem, own = self._state_for(n, state, episode_start)
        observed = self.adapter_.read(obs)
        q = self._state_of(observed, n)
        x = J = None
        if len(self.frame_names_) > 1:
            x, J = hand_points(self.robot_, q, self.approach_offset_)
        clock, aim = self._advance(mem, observed, None if x is None else x[:, : self.robot_.dim])
        if own:
            self._memory = mem
        s = (clock + self.lookahead * self.control_dt_) / self.duration_
        row = self._rows(s)
        k = q.shape[1]
        jm, jv = self._cols[JOINT_FRAME]
        grip_row = row
        if np.any(~np.isnan(aim)):  # waiting to reach a gripper event's target: aim at it
            row = self._rows(np.where(np.isnan(aim), s, aim))
        if self.posture_labels_ is None:
            joint_mean, joint_var = row[:, jm], row[:, jv]
        else:  # the joint model of the posture the nearest demonstrated layout was shown in
            joint_mean, joint_var = self._joint_rows(row, mem)
        frames = None
        if x is not None:
            names = self.frame_names_[1:]
            mcols, vcols = self._frame_columns()
            frames = FrameStack(
                np.stack([mem.position[f] for f in names], axis=1),
                np.stack([mem.rotation[f] for f in names], axis=1),
                row[:, mcols],
                row[:, vcols],
            )
        dq, fused = reproduction_step(
            q,
            joint_mean[:, :k],
            joint_var[:, :k],
            x,
            J,
            frames,
            alpha=self.alpha,
            null_space_std=self.null_space_std,
            damping=DEFAULT_DAMPING,
            ridge=DEFAULT_RIDGE,
            return_cov=cov,
        )
        gripper = grip_row[:, jm][:, k] if joint_mean.shape[1] > k else np.zeros(n)
        action = self.adapter_.action_map(q, limit_step(dq, self.max_joint_step_), gripper)
        return single, mem, np.minimum(np.maximum(s, 0.0), 1.0), action, dq, fused, gripper, row

    def _compute_one(
        self,
        obs: NDArray[np.float64],
        single: bool,
        state: Any,
        episode_start: ArrayLike | None,
        cov: bool,
    ) -> tuple[Any, ...]:
        """:meth:`_compute` for one environment ``obs (1, obs_dim)`` (the control loop): the same
        steps in the same order on one row (floats and unbatched arrays, fewer and cheaper calls);
        tested equal to the batch path. Returns batched arrays (``n = 1``) as ``_compute`` does."""
        mem, own = self._state_for(1, state, episode_start)
        observed = self.adapter_.read(obs)
        q = self._state_of(observed, 1)
        k = q.shape[1]
        x = J = None
        if len(self.frame_names_) > 1:
            x, J = hand_points(self.robot_, q[0], self.approach_offset_)  # unbatched
        clock, aim = self._advance_one(
            mem, observed, None if x is None else x[: self.robot_.dim].tolist()
        )
        if own:
            self._memory = mem
        s = (clock + self.lookahead * self.control_dt_) / self.duration_
        row = grip_row = self._row(s)
        if aim is not None:  # waiting to reach a gripper event's target: aim at it
            row = self._row(aim)
        if self.posture_labels_ is None:
            jm, jv = self._cols[JOINT_FRAME]
        else:  # the joint model of the posture the nearest demonstrated layout was shown in
            jm, jv = self._posture_cols[self._posture_one(mem)]
        frames = None
        if x is not None and J is not None:
            names = self.frame_names_[1:]
            block = row[self._frame_block].reshape(len(names), 2, -1)  # per frame: means, vars
            frames = FrameStack(
                np.concatenate([mem.position[f] for f in names]),
                np.concatenate([mem.rotation[f] for f in names]),
                block[:, 0],
                block[:, 1],
            )
        joint_mean = row[jm]
        dq, fused = reproduction_step(
            q[0],
            joint_mean[:k],
            row[jv][:k],
            x,
            J,
            frames,
            alpha=self.alpha,
            null_space_std=self.null_space_std,
            damping=DEFAULT_DAMPING,
            ridge=DEFAULT_RIDGE,
            return_cov=cov,
        )
        dq = dq[None]
        jm_joint = self._cols[JOINT_FRAME][0]
        gripper = grip_row[jm_joint][k : k + 1] if joint_mean.shape[0] > k else np.zeros(1)
        action = self.adapter_.action_map(q, limit_step(dq, self.max_joint_step_), gripper)
        if not cov:  # predict: the action and the state are all it returns
            return single, mem, None, action, dq, None, gripper, row[None]
        phase = np.array([min(max(s, 0.0), 1.0)])
        return (
            single,
            mem,
            phase,
            action,
            dq,
            None if fused is None else fused[None],
            gripper,
            row[None],
        )

    def _state_of(self, observed: Any, n: int) -> NDArray[np.float64]:
        """The robot state ``(n, k)`` the adapter read, checked against the robot."""
        q = np.asarray(observed.state, dtype=float)
        if q.shape != (n, self.robot_.n_joints):
            raise ValueError(
                f"the adapter read a state of shape {q.shape}; the robot has "
                f"{self.robot_.n_joints} coordinates"
            )
        return q

    def predict(
        self,
        observation: ArrayLike,
        state: Any = None,
        episode_start: ArrayLike | None = None,
        deterministic: bool = False,
    ) -> tuple[NDArray[np.float32], Any]:
        """The action for an observation (stable-baselines3 ``PolicyPredictor`` protocol).

        Args:
            observation: ``(obs_dim,)`` or ``(n_envs, obs_dim)``, finite.
            state: ``None`` (the policy keeps the per-environment memory itself) or the
                :class:`PolicyState` a previous call returned.
            episode_start: ``(n_envs,)`` bool, environments that were just reset (needed when the
                observation has no clock).
            deterministic: unused (the policy follows the GP means; it is always deterministic).

        Returns:
            ``(action, state)`` with ``action`` ``(a,)`` or ``(n_envs, a)`` float32.
        """
        single, mem, _s, action, *_ = self._compute(observation, state, episode_start, False)
        return (action[0] if single else action), mem

    def predict_distribution(
        self, observation: ArrayLike, state: Any = None, episode_start: ArrayLike | None = None
    ) -> PolicyDistribution:
        """Phase, action, fused increment with its std, and per-frame std (batched; advances the
        same memory as :meth:`predict`). Accepts ``(obs_dim,)`` or ``(n, obs_dim)``; always
        returns batched arrays (``n = 1``)."""
        _single, _mem, s, action, dq, cov, gripper, row = self._compute(
            observation, state, episode_start, True
        )
        return PolicyDistribution(
            phase=s,
            action=action,
            joint_increment=dq,
            joint_std=np.sqrt(np.diagonal(cov, axis1=1, axis2=2)),
            gripper=gripper,
            frame_std={name: np.sqrt(row[:, self._cols[name][1]]) for name in self.frame_names_},
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
        """Where each object frame is tight, and whether that matches the demonstrated events.

        Returns:
            ``{"intervals": [{"frame", "start", "end", "min_std", "label"}...],
            "stage_phases": {event: mean phase over demonstrations},
            "checks": [{"stage", "phase", "expected_frame", "tight", "interval"}...]}``; the
            checks use the adapter's ``expected_tight`` (event -> frame), if it has one.
        """
        d = self.robot_.dim if hasattr(self, "robot_") else 3
        objects = {n: self.std_[n][:, :d] for n in self.frame_names_ if n != JOINT_FRAME}
        intervals = intervals_report(objects, self.phase_grid_, ratio=ratio, min_width=min_width)
        per_demo = list(getattr(self, "stage_phases_", []))
        names = sorted({k for p in per_demo for k in p})
        phases: dict[str, float | None] = {}
        for ev in names:
            vals = [p[ev] for p in per_demo if p.get(ev) is not None]
            phases[ev] = float(np.mean(vals)) if vals else None
        checks = []
        expected = getattr(getattr(self, "adapter_", None), "expected_tight", {}) or {}
        for stage, frame in expected.items():
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
        if path.is_dir():
            raise IsADirectoryError(f"{path} is a folder, not a policy file")
        metadata = {
            "format": FORMAT_NAME,
            "kind": FORMAT_NAME,
            "schema_version": SCHEMA_VERSION,
            "adapter": str(getattr(self.adapter_, "name", type(self.adapter_).__name__)),
            "params": self.get_params(),
            "frame_names": self.frame_names_,
            "approach_offset": self.approach_offset_,
            "duration": self.duration_,
            "control_dt": self.control_dt_,
            "n_demos": int(getattr(self, "n_demos_", 0)),
            "demonstrations_env": getattr(self, "demonstrations_env_", None),
            "alignment": getattr(self, "alignment_", "none"),
            "stage_phases": getattr(self, "stage_phases_", []),
            "event_phases": self.event_phases_,
            "landmarks": [[s_l, f] for s_l, f in self.landmarks_],
            "constraints": self.constraints_,
            "posture_labels": (
                None if self.posture_labels_ is None else [int(c) for c in self.posture_labels_]
            ),
        }
        arrays: dict[str, NDArray[Any]] = {
            "metadata": np.array(json.dumps(metadata)),
            "phase_grid": self.phase_grid_,
        }
        for name in self.frame_names_:
            arrays[f"mean__{name}"] = self.mean_[name]
            arrays[f"std__{name}"] = self.std_[name]
        if self.layout_features_ is not None:
            arrays["layout_features"] = self.layout_features_
        for c, (mean, std) in enumerate(zip(self.posture_mean_, self.posture_std_, strict=True)):
            arrays[f"posture_mean__{c}"] = mean
            arrays[f"posture_std__{c}"] = std
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_save_npz(path, arrays, force=overwrite)
        return path

    @classmethod
    def load(
        cls,
        path: str | os.PathLike[str] | io.BytesIO,
        robot: Any = None,
        adapter: Any = None,
    ) -> GPDemonstrationPolicy:
        """Read a policy written by :meth:`save`, validating every name and number first.

        ``path`` may also be an in-memory file (``io.BytesIO``), e.g. a policy embedded in another
        file; loading never writes anything. ``adapter``: needed unless the policy was fitted
        with a built-in adapter (``"coffee"``).

        Raises:
            FileNotFoundError: no such file.
            PolicyFileError: not a policy file, unsupported schema version, unknown frames,
                missing, non-finite or out-of-range values (the message names what is wrong).
        """
        label, arrays = _read_policy_npz(path)
        try:
            return cls._from_arrays(arrays, robot, adapter)
        except PolicyFileError as exc:
            raise PolicyFileError(f"{label}: {exc}") from None

    @classmethod
    def _from_arrays(
        cls, arrays: Mapping[str, NDArray[Any]], robot: Any, adapter: Any
    ) -> GPDemonstrationPolicy:
        if "metadata" not in arrays:
            raise PolicyFileError("no 'metadata' entry; not a GPDemonstrationPolicy file")
        try:  # NaN/Infinity parse here and are refused below, naming their field
            meta = json.loads(str(arrays["metadata"]))
        except (ValueError, RecursionError) as exc:
            raise PolicyFileError(f"metadata is not valid JSON ({str(exc)[:200]})") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
            found = meta.get("format") if isinstance(meta, dict) else None
            raise PolicyFileError(
                f"not a GPDemonstrationPolicy file (metadata 'format' is {found!r})"
            )
        version = meta.get("schema_version")
        if version not in _READABLE_VERSIONS or isinstance(version, bool):
            raise PolicyFileError(
                f"schema version {version!r} is not supported (this version of lgp_policy reads "
                f"{list(_READABLE_VERSIONS)})"
            )
        for key in ("params", "frame_names", "duration", "control_dt"):
            if key not in meta:
                raise PolicyFileError(f"metadata lacks {key!r}")
        try:
            duration = _finite("duration", meta["duration"], 0.0, MAX_DURATION)
            control_dt = _finite("control_dt", meta["control_dt"], 0.0, MAX_CONTROL_DT)
        except ValueError as exc:
            raise PolicyFileError(str(exc)) from None
        if control_dt > duration:
            raise PolicyFileError(f"control_dt {control_dt} exceeds the duration {duration}")
        if adapter is None:
            name = meta.get("adapter", "coffee")
            if not isinstance(name, str):
                raise PolicyFileError(f"adapter name must be a string, got {name!r}")
            adapter = _builtin_adapter(name)
        params = meta["params"]
        if not isinstance(params, dict):
            raise PolicyFileError("'params' must be an object")
        if version == 1:
            params = {k: v for k, v in params.items() if k != "approach_offset"}
        if version in (1, 2):  # before posture clusters: one joint model
            params = {**params, "posture_distance": None}
        if "extrapolate" not in params:  # written before it existed: hold the last targets
            params = {**params, "extrapolate": 0.0}
        try:
            policy = cls(robot, adapter, **params)
        except (TypeError, ValueError) as exc:
            raise PolicyFileError(f"invalid policy parameters ({exc})") from None
        policy._resolve()
        names = meta["frame_names"]
        if (
            not isinstance(names, list)
            or not names
            or names[0] != JOINT_FRAME
            or not all(isinstance(n, str) for n in names)
            or len(set(names)) != len(names)
        ):
            raise PolicyFileError(
                f"frame_names must be distinct names starting with {JOINT_FRAME!r}"
            )
        known = tuple(getattr(policy.adapter_, "frame_names", ()))
        unknown = [n for n in names[1:] if n not in known]
        if unknown:
            raise PolicyFileError(f"unknown frames {unknown}; the adapter reads {list(known)}")
        offset = meta.get("approach_offset", 0.1 if version == 1 else None)
        if offset is not None:
            try:
                offset = _finite("approach_offset", offset, -10.0, 10.0)
            except ValueError as exc:
                raise PolicyFileError(str(exc)) from None
            if not policy.robot_.has_orientation:
                raise PolicyFileError("approach_offset needs a robot with a hand orientation")
        grid = np.asarray(arrays.get("phase_grid", np.zeros(0)))
        if (
            grid.dtype.kind != "f"
            or grid.ndim != 1
            or not 2 <= len(grid) <= MAX_GRID
            or not np.all(np.isfinite(grid))
            or not np.all(np.diff(grid) > 0)
            or grid[0] < 0.0
            or grid[-1] > 1.0
        ):
            raise PolicyFileError("'phase_grid' must be an increasing 1-D float array in [0, 1]")
        k = policy.robot_.n_joints + (policy.gripper_ is not None)
        d = policy.robot_.dim * (2 if offset is not None else 1)
        mean: dict[str, NDArray[np.float64]] = {}
        std: dict[str, NDArray[np.float64]] = {}
        for name in names:
            want = k if name == JOINT_FRAME else d
            for kind, store in (("mean", mean), ("std", std)):
                key = f"{kind}__{name}"
                if key not in arrays:
                    raise PolicyFileError(f"missing array {key!r}")
                a = np.asarray(arrays[key])
                if a.dtype.kind != "f" or a.shape != (len(grid), want):
                    raise PolicyFileError(
                        f"{key!r} has shape {a.shape} ({a.dtype}), expected ({len(grid)}, {want}) "
                        f"floats"
                    )
                if not np.all(np.isfinite(a)) or np.any(np.abs(a) > 1e6):
                    raise PolicyFileError(f"{key!r} contains NaN, inf or values beyond 1e6")
                store[name] = a.astype(float)
            if np.any(std[name] <= 0):
                raise PolicyFileError(f"'std__{name}' must be positive")
        events = meta.get("event_phases", {})
        if not isinstance(events, dict):
            raise PolicyFileError("'event_phases' must be an object")
        for ev, s_e in events.items():
            try:
                _finite(f"event_phases[{ev!r}]", s_e, 0.0, 1.0, low_open=False)
            except ValueError as exc:
                raise PolicyFileError(str(exc)) from None
        landmarks = meta.get("landmarks", [])
        if not isinstance(landmarks, list) or not all(
            isinstance(m, list)
            and len(m) == 2
            and isinstance(m[0], (int, float))
            and not isinstance(m[0], bool)
            and 0.0 <= m[0] <= 1.0
            and m[1] in names[1:]
            for m in landmarks
        ):
            raise PolicyFileError("'landmarks' must be a list of [phase in [0, 1], fitted frame]")
        stage_phases = meta.get("stage_phases", [])
        if not isinstance(stage_phases, list) or not all(
            isinstance(p, dict)
            and all(v is None or (isinstance(v, (int, float)) and 0 <= v <= 1) for v in p.values())
            for p in stage_phases
        ):
            raise PolicyFileError("'stage_phases' must be a list of {event: phase in [0, 1]}")
        policy.posture_labels_, policy.layout_features_ = None, None
        policy.posture_mean_, policy.posture_std_ = [], []
        _read_postures(policy, meta, arrays, len(grid), k, len(names) - 1)
        policy.approach_offset_ = offset
        policy.phase_grid_ = grid.astype(float)
        policy.mean_, policy.std_ = mean, std
        policy.frame_names_ = list(names)
        policy.duration_ = duration
        policy.control_dt_ = control_dt
        policy.event_phases_ = {str(k): float(v) for k, v in events.items()}
        policy.landmarks_ = [(float(m[0]), str(m[1])) for m in landmarks]
        n_demos = meta.get("n_demos", 0)
        policy.n_demos_ = int(n_demos) if isinstance(n_demos, int) and n_demos >= 0 else 0
        policy.alignment_ = str(meta.get("alignment", "none"))[:200]
        recorded = meta.get("demonstrations_env")  # absent before it was recorded
        try:
            if recorded is not None and not isinstance(recorded, dict):
                raise ValueError(f"expected an object or null, got {str(recorded)[:80]!r}")
            policy.demonstrations_env_ = demonstrations_env(recorded)
        except ValueError as exc:
            raise PolicyFileError(f"demonstrations_env: {exc}") from None
        policy.stage_phases_ = stage_phases
        policy.constraints_ = policy.constraint_report()
        policy._build_table()
        return policy

    def __repr__(self) -> str:
        fitted = f", frames={self.frame_names_}" if hasattr(self, "frame_names_") else ""
        return f"GPDemonstrationPolicy(model={self.model!r}, alpha={self.alpha}{fitted})"


def _read_postures(
    policy: GPDemonstrationPolicy,
    meta: Mapping[str, Any],
    arrays: Mapping[str, NDArray[Any]],
    n_grid: int,
    width: int,
    n_frames: int,
) -> None:
    """Check and set the posture clusters of a policy file (``posture_labels`` in the metadata,
    ``layout_features`` and ``posture_mean__<c>`` / ``posture_std__<c>`` members)."""
    labels = meta.get("posture_labels")
    members = sorted(k for k in arrays if k.startswith("posture_") or k == "layout_features")
    if labels is None:
        if members:
            raise PolicyFileError(f"members {members} without 'posture_labels' in the metadata")
        return
    if (
        not isinstance(labels, list)
        or len(labels) < 2
        or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in labels)
        or set(labels) != set(range(max(labels) + 1))
        or max(labels) < 1
    ):
        raise PolicyFileError(
            "'posture_labels' must list one cluster 0, 1, ... per demonstration, at least two "
            "clusters, each used"
        )
    if policy.posture_distance is None:
        raise PolicyFileError("the file has posture clusters but posture_distance is None")
    n_clusters = max(labels) + 1
    expected = {"layout_features"} | {
        f"posture_{kind}__{c}" for c in range(n_clusters) for kind in ("mean", "std")
    }
    if set(members) != expected:
        raise PolicyFileError(
            f"posture members {members} do not match {n_clusters} clusters; expected "
            f"{sorted(expected)}"
        )
    d = policy.robot_.dim
    feats = np.asarray(arrays["layout_features"])
    want = (len(labels), n_frames * (d + d * d))
    if feats.dtype.kind != "f" or feats.shape != want or not np.all(np.isfinite(feats)):
        raise PolicyFileError(
            f"'layout_features' has shape {feats.shape} ({feats.dtype}), expected {want} finite "
            f"floats"
        )
    for c in range(n_clusters):
        for kind, store in (("mean", policy.posture_mean_), ("std", policy.posture_std_)):
            key = f"posture_{kind}__{c}"
            a = np.asarray(arrays[key])
            if a.dtype.kind != "f" or a.shape != (n_grid, width):
                raise PolicyFileError(
                    f"{key!r} has shape {a.shape} ({a.dtype}), expected ({n_grid}, {width}) floats"
                )
            if not np.all(np.isfinite(a)) or np.any(np.abs(a) > 1e6):
                raise PolicyFileError(f"{key!r} contains NaN, inf or values beyond 1e6")
            if kind == "std" and np.any(a <= 0):
                raise PolicyFileError(f"{key!r} must be positive")
            store.append(a.astype(float))
    policy.posture_labels_ = np.array(labels, dtype=np.intp)
    policy.layout_features_ = feats.astype(float)


MAX_METADATA_BYTES = 16 * 2**20
_SCHEMA = {
    "metadata": MemberSpec(dtype="U", ndim=0, max_bytes=MAX_METADATA_BYTES),
    "phase_grid": MemberSpec(dtype="f", ndim=1, finite=True),
    "mean__*": MemberSpec(dtype="f", ndim=2, finite=True),
    "std__*": MemberSpec(dtype="f", ndim=2, finite=True),
    "layout_features": MemberSpec(dtype="f", ndim=2, finite=True, required=False),
    "posture_mean__*": MemberSpec(dtype="f", ndim=2, finite=True, required=False),
    "posture_std__*": MemberSpec(dtype="f", ndim=2, finite=True, required=False),
}
MAX_MEMBER_BYTES = 64 * 2**20
MAX_FILE_BYTES = 512 * 2**20


def _read_policy_npz(path: str | os.PathLike[str] | io.BytesIO) -> tuple[str, dict[str, Any]]:
    """The arrays of a policy file, through :func:`lgp_policy._io.read_npz` (known members only,
    sizes checked before decompressing, never unpickled; a path or an in-memory file)."""
    if isinstance(path, io.BytesIO):
        label = str(getattr(path, "name", None) or "<embedded policy>")
        source: Any = path
    else:
        source = Path(path)
        label = str(source)
        if not source.exists():
            raise FileNotFoundError(f"no policy file at {source}")
    try:
        arrays = read_npz(
            source,
            schema=_SCHEMA,
            max_member_bytes=MAX_MEMBER_BYTES,
            max_total_bytes=MAX_FILE_BYTES,
            max_entries=1000,
        )
    except FileFormatError as exc:
        if _metadata_format(source) == DEMONSTRATIONS_FORMAT:
            raise PolicyFileError(
                f"{label} is a demonstrations file ({DEMONSTRATIONS_FORMAT}), not a policy; fit "
                f"a policy to it first (gym-coffee fit {label} --out policy.npz)"
            ) from None
        raise PolicyFileError(f"{label} is not a readable policy file: {exc}") from None
    return label, arrays


DEMONSTRATIONS_FORMAT = "gym_coffee.demonstrations"
"""The ``format`` of a gym-coffee demonstrations file (named when one is given as a policy)."""


def _metadata_format(source: Any) -> Any:
    """The ``format`` in a file's JSON ``metadata`` member (bounded read), or ``None``."""
    try:
        meta = read_json_member(source, "metadata", max_bytes=MAX_METADATA_BYTES)
    except (FileFormatError, OSError):
        return None
    finally:
        if isinstance(source, io.BytesIO):
            source.seek(0)
    return meta.get("format") if isinstance(meta, dict) else None
