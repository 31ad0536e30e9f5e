"""``CoffeeEnv``: the coffee task of Schneider & Ertel (IROS 2010, Sec. IV, Fig. 3) in PyBullet."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import EzPickle
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from gym_coffee import PHYSICS_PRESETS, STAGES
from gym_coffee._checks import check_bool, check_choice, check_int, check_real, check_vector
from gym_coffee.kinematics import PandaKinematics
from gym_coffee.robot import (
    ACTION_TYPES,
    GRIPPER_MAX_OPENING,
    MAX_EE_ROT_STEP,
    MAX_EE_STEP,
    MAX_JOINT_STEP,
    NEUTRAL_JOINTS,
    Panda,
)
from gym_coffee.scene import (
    BUTTON_PRESS_TRAVEL,
    BUTTON_REST_TRAVEL,
    CUP_HEIGHT,
    CUP_REST_ANGULAR_SPEED,
    CUP_REST_SPEED,
    CUP_TIPPED_TILT,
    CUP_UPRIGHT_TILT,
    LEVEL_SPECS,
    MIN_CUP_MACHINE_DISTANCE,
    PLACE_TOLERANCE,
    TABLE_TOP_Z,
    TABLE_X,
    TABLE_Y,
    CoffeeScene,
    Layout,
    rot_z,
)
from gym_coffee.simulation import Simulation

__all__ = [
    "CONTROL_DT",
    "MAX_EPISODE_STEPS",
    "N_SUBSTEPS",
    "OBS_DIM",
    "OBS_SLICES",
    "PHYSICS_DT",
    "PHYSICS_PRESETS",
    "CoffeeEnv",
    "object_frames",
    "obs_part",
]

#: Physics time step (s) and physics steps per control step of the default physics
#: (``gym_coffee.PHYSICS_PRESETS``); control period CONTROL_DT = 0.04 s (25 Hz) with every preset.
PHYSICS_DT, N_SUBSTEPS = PHYSICS_PRESETS["default"][:2]
CONTROL_DT = PHYSICS_DT * N_SUBSTEPS
#: Time limit used at registration (steps); 400 steps = 16 s.
MAX_EPISODE_STEPS = 400
#: Uniform noise (rad) added to each joint of the start posture.
START_JOINT_NOISE = 0.05
#: Largest rendered image side (pixels) accepted for ``width`` and ``height``.
MAX_IMAGE_SIDE = 4096
#: Largest accepted ``obs_noise`` and ``calibration_bias`` (m), ``actuation_noise`` (rad) and
#: ``cup_push`` distance (m).
MAX_PERTURBATION = 0.1
#: ``cup_push``: the cup is moved at a step drawn uniformly from this range (0.4-1.4 s after the
#: reset: during the approach, before a hand reaches it).
CUP_PUSH_STEPS = (10, 35)
#: Observed parts that carry the object-position perturbations (``obs_noise``; with
#: ``calibration_bias``: each with its object's offset).
PERTURBED_OBS = {"cup_pos": "cup", "cup_init_pos": "cup", "machine_pos": "machine"}

# name, size, (low, high): observations are clipped to these bounds.
_OBS_LAYOUT = [
    ("time", 1, (0.0, 1e4)),
    ("joint_pos", 7, (-2 * np.pi, 2 * np.pi)),
    ("joint_vel", 7, (-50.0, 50.0)),
    ("gripper", 1, (0.0, 0.1)),
    ("ee_pos", 3, (-5.0, 5.0)),
    ("cup_pos", 3, (-5.0, 5.0)),
    ("cup_quat", 4, (-1.0, 1.0)),
    ("cup_init_pos", 3, (-5.0, 5.0)),
    ("machine_pos", 3, (-5.0, 5.0)),
    ("machine_yaw", 1, (-np.pi, np.pi)),
    ("button_travel", 1, (0.0, 0.01)),
]


def _make_slices() -> dict[str, slice]:
    slices, start = {}, 0
    for name, size, _ in _OBS_LAYOUT:
        slices[name] = slice(start, start + size)
        start += size
    return slices


#: Named parts of the flat observation vector.
OBS_SLICES: dict[str, slice] = _make_slices()
#: Length of the observation vector.
OBS_DIM: int = sum(size for _, size, _ in _OBS_LAYOUT)
OBS_LOW = np.concatenate([np.full(size, lo) for _, size, (lo, _) in _OBS_LAYOUT]).astype(np.float32)
OBS_HIGH = np.concatenate([np.full(size, hi) for _, size, (_, hi) in _OBS_LAYOUT]).astype(
    np.float32
)
# The bounds as float64 (observations are clipped before the cast to float32), and the parts'
# positions (single values as indices).
_OBS_LOW64 = OBS_LOW.astype(np.float64)
_OBS_HIGH64 = OBS_HIGH.astype(np.float64)
_TIME = OBS_SLICES["time"].start
_JOINT_POS = OBS_SLICES["joint_pos"]
_JOINT_VEL = OBS_SLICES["joint_vel"]
_GRIPPER = OBS_SLICES["gripper"].start
_EE_POS = OBS_SLICES["ee_pos"]
_CUP_POS = OBS_SLICES["cup_pos"]
_CUP_QUAT = OBS_SLICES["cup_quat"]
_CUP_INIT_POS = OBS_SLICES["cup_init_pos"]
_MACHINE_POS = OBS_SLICES["machine_pos"]
_MACHINE_YAW = OBS_SLICES["machine_yaw"].start
_BUTTON_TRAVEL = OBS_SLICES["button_travel"].start

REWARD_TERMS = ("reach", "carry", "press", "stage", "success", "failure")
_REWARD_KEYS = tuple(f"reward_{name}" for name in REWARD_TERMS)
STAGE_BONUS = 1.0
#: From the cup's base centre to its middle (the reach term's target).
_CUP_MIDDLE = np.array([0.0, 0.0, 0.5 * CUP_HEIGHT])
SUCCESS_BONUS = 10.0
FAILURE_PENALTY = -10.0


def obs_part(obs: NDArray[Any], name: str) -> NDArray[Any]:
    """The part ``name`` of one observation (OBS_DIM,) or a batch (n, OBS_DIM)."""
    return np.asarray(obs)[..., OBS_SLICES[name]]


def object_frames(obs: NDArray[Any]) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """Object frames (position (3,), rotation (3, 3)) rebuilt from one observation (OBS_DIM,).

    ``cup``: at the cup's initial base centre, identity rotation (the cup is rotationally
    symmetric); ``machine``: at the machine's footprint centre, rotated by ``Rz(machine_yaw)``.
    """
    obs = np.asarray(obs, dtype=np.float64)
    yaw = float(obs_part(obs, "machine_yaw")[0])
    return {
        "cup": (obs_part(obs, "cup_init_pos").copy(), np.eye(3)),
        "machine": (obs_part(obs, "machine_pos").copy(), rot_z(yaw)),
    }


class _State(NamedTuple):
    q: NDArray[np.float64]
    qd: NDArray[np.float64]
    gripper: float
    ee: NDArray[np.float64]  # grasp point (forward kinematics of q)
    cup_pos: NDArray[np.float64]
    cup_quat: NDArray[np.float64]
    travel: float


class CoffeeEnv(gym.Env, EzPickle):
    """A Franka Panda makes coffee: grasp a cup, put it under the machine's spout, press the button.

    ## Description
    The coffee task of Schneider & Ertel, *Robot Learning by Demonstration with Local Gaussian
    Process Regression* (IROS 2010), Sec. IV and Fig. 3, in PyBullet with a 7-DOF Franka Panda
    instead of the paper's 5-DOF Katana. A cup (6 cm x 8 cm, 0.15 kg) stands somewhere on the table
    to the robot's right; a coffee machine stands to its left, its front turned towards the cup's
    side. The robot must grasp the cup (from the side: the machine's head overhangs the drip tray,
    so a top grasp cannot bring the cup under the spout), place it upright on the drip tray under
    the spout, let go, move away without knocking it over and press the small spring-loaded button
    on the machine's front panel.

    ## Action Space
    ``Box(-1, 1, (n,), float32)``; ``action_type`` picks the mode. In every mode the last value is
    the absolute gripper opening ``(a[-1] + 1) / 2 * 0.08`` m.

    * ``"joint"`` (default, n = 8): ``a[:7]`` are joint-position deltas, joint targets = measured
      positions + ``a[:7] * MAX_JOINT_STEP`` (0.05 rad per step), clipped to the joint limits.
      ``gym_coffee.robot.action_from_targets`` inverts this.
    * ``"ee"`` (n = 4): ``a[:3] * MAX_EE_STEP`` (0.02 m per step) is a Cartesian displacement of
      the grasp point (world frame) from its measured position; the hand keeps the orientation it
      had at reset (gripper down).
    * ``"ee_rot"`` (n = 7): as ``"ee"``, and ``a[3:6] * MAX_EE_ROT_STEP`` (0.05 rad per step)
      rotates the commanded hand orientation about the world x, y and z axes (roll, pitch, yaw).
      The side grasp the task needs is reachable in this mode (or in ``"joint"``), not in
      ``"ee"``.

    The end-effector modes go through damped-least-squares inverse kinematics of the 6-D pose
    (:meth:`PandaKinematics.ik_step`, two iterations, null-space pull to the start posture) and
    then to joint targets (the joint step scaled down as a whole where a joint would move more
    than ``MAX_JOINT_STEP``, so the hand keeps the commanded direction). Finite values
    outside [-1, 1] are clipped (Gymnasium's convention); an action of another shape or with NaN
    or inf raises ``ValueError``.

    ## Observation Space
    Flat ``Box(OBS_LOW, OBS_HIGH, (OBS_DIM,), float32)`` (wide finite bounds); ``OBS_SLICES`` names
    the parts and :func:`obs_part` extracts them: ``time`` (s since reset), ``joint_pos`` (7, rad),
    ``joint_vel`` (7, rad/s), ``gripper`` (finger opening, m), ``ee_pos`` (grasp point, world, m),
    ``cup_pos`` (cup base centre), ``cup_quat`` (xyzw), ``cup_init_pos``, ``machine_pos`` (footprint
    centre), ``machine_yaw`` (rad), ``button_travel`` (m). :func:`object_frames` rebuilds the cup
    and machine frames.

    ## Rewards
    ``reward_type="dense"``: the sum of named terms, each in ``info`` as ``reward_<name>``:
    ``reach`` (minus the grasp point's distance to the cup's middle, until the cup is grasped),
    ``carry`` (minus the cup's distance to the place under the spout, after grasping, until placed),
    ``press`` (once placed: minus the grasp point's distance to the button, plus the button's travel
    as a fraction of the press travel), ``stage`` (+1 when a stage is reached: grasped, placed,
    success; -1 when one is lost), ``success`` (+10 on success) and ``failure`` (-10 if the cup
    falls off the table or tips over).
    ``reward_type="sparse"``: ``success`` only, 1 on success, else 0 (the other terms are 0).

    ## Starting State
    The Panda in a ready posture (gripper down, open) with uniform noise of +-0.05 rad per joint;
    the cup upright and the machine where the level puts them (``scene.LEVEL_SPECS``), all drawn
    from ``self.np_random``, so ``reset(seed=s)`` fixes the layout:

    * ``"easy"`` (``gym_coffee.ENV_ID``): the cup in ``scene.CUP_REGION_*`` to the robot's right,
      the machine in ``scene.MACHINE_REGION_*`` to its left, its yaw 90 degrees (front facing -y)
      +-15 degrees.
    * ``"hard"`` (``"gym_coffee/CoffeeTaskHard-v0"``): the machine on either side (50/50), yaw
      +-90 degrees (front towards the middle) +-30 degrees, the cup on the other side in a wider
      region (``scene.HARD_*``): the grasp, carry and press directions flip with the side.

    ``reset(options={"layout": {...}})`` sets the layout instead: any of ``cup_pos`` and
    ``machine_pos`` ((2,) or (3,) with z = 0, m, on the table) and ``machine_yaw`` (rad), the
    others drawn as usual; it is checked (``ValueError`` naming the key). ``info["layout"]``
    (reset and every step) is the episode's layout in the same form (tuples), so
    ``reset(options={"layout": info["layout"]})`` replays it.

    ## Episode End
    Terminates on success (cup grasped, placed under the spout and the button pressed while it
    stands there) or on an unrecoverable failure (cup off the table or tipped over). Truncated by
    the time limit (``max_episode_steps=400`` at registration, 16 s at 25 Hz).

    ## Info
    ``is_success``, ``cup_grasped`` (latched: the cup was lifted off the table between both
    fingers), ``cup_placed`` (now: at rest upright on the tray, base within ``place_tolerance``
    of the place under the spout, not touched by the robot: tilt < 5 degrees, speed < 0.01 m/s,
    angular speed < 0.1 rad/s), ``button_pressed`` (latched: travel passed 5 mm while the grasp
    point had moved along the button's axis since the button was last at rest, at least half
    the threshold and more along the axis than across it: a sideways swipe does not count; the
    button stops hard at 8 mm), ``stage`` (0: none, 1: grasped, 2: grasped and placed, 3:
    success), ``layout`` (see Starting State) and the ``reward_<name>`` terms.

    ## Arguments
    ==================  ==========  ===========================================================
    ``render_mode``     ``None``    ``"rgb_array"`` (headless TinyRenderer) or ``"human"`` (GUI)
    ``reward_type``     ``"dense"`` ``"dense"`` or ``"sparse"``
    ``width``           ``320``     image width for ``"rgb_array"``
    ``height``          ``240``     image height for ``"rgb_array"``
    ``render_shadows``  ``False``   draw shadows in ``"rgb_array"`` frames (about 2x the time)
    ``exact_reset``     ``True``    restore the world as loaded at every reset (see below)
    ``action_type``     ``"joint"`` ``"joint"``, ``"ee"`` or ``"ee_rot"`` (see Action Space)
    ``level``           ``"easy"``  difficulty level (the registered ids of ``gym_coffee.LEVELS``
                                    set it; see Starting State)
    ``obs_noise``       ``0.0``     std (m) of Gaussian noise added at every step to the
                                    observed ``cup_pos``, ``cup_init_pos`` and ``machine_pos``
    ``calibration_bias`` ``0.0``    length (m) of a constant offset per episode, in a random
                                    3-D direction, of the observed cup positions (``cup_pos``,
                                    ``cup_init_pos``) and, another one, of ``machine_pos``
    ``actuation_noise`` ``0.0``     std (rad) of Gaussian noise added to every joint target
    ``cup_push``        ``None``    ``(low, high)`` (m): the cup is moved on the table by a
                                    distance in [low, high] in a random horizontal direction
                                    (away from the machine), once, 10-35 steps after the reset
                                    (during the approach), unless the robot touches it already
    ``physics``         ``"default"`` ``"fast"``: 5 physics steps of 8 ms with 20 solver
                                    iterations per control step instead of 10 of 4 ms with up
                                    to 50 (``PHYSICS_PRESETS``): ~40% less CPU per step, other
                                    trajectories (not comparable with default-physics data)
    ==================  ==========  ===========================================================

    Every argument is checked at construction (``ValueError`` naming it): ``width`` and
    ``height`` are integers in [1, 4096], the perturbations finite numbers in [0, 0.1].

    ## Perturbations
    All four are off by default, usable on every level, and drawn from ``self.np_random`` after
    the layout and the start posture, so ``reset(seed=s)`` reproduces them (also in another
    process) and the unperturbed episodes stay what they are. They perturb what the policy
    observes or does, not the simulator's truth: ``task_points()`` and the stage checks use the
    true poses.

    ## Reset and reproducibility
    ``reset(seed=s)`` fixes the layout, and a fresh env reproduces an episode bit for bit (also in
    another process). By default (``exact_reset=True``) every reset restores the state the world
    had right after loading (PyBullet's ``saveState``/``restoreState``, ~0.5 ms; no memory
    growth) before it re-poses the bodies, so every episode equals a fresh env's with the same
    seed, whatever ran before: evaluation results do not depend on how episodes are spread over
    workers. ``exact_reset=False`` only re-poses the bodies (~1 ms), and Bullet's broadphase keeps
    some history (the order of its pair cache), so an episode with contacts in a *reused* env can
    then differ from a fresh env's in the last bits, and the difference can grow over a
    contact-rich episode (e.g. 1e-2 rad after a grasp); it is kept for compatibility and is no
    faster.

    Pickling (``EzPickle``) keeps the constructor arguments only: the copy is a fresh env, and its
    episode starts anew at its next ``reset``.

    After :meth:`close`, the next ``reset`` starts a new physics server.

    With ``gym.vector.AsyncVectorEnv(..., context="spawn")`` or ``"forkserver"`` (Python 3.14's
    default on Linux) the workers are fresh interpreters: make the env with
    ``gym.make("gym_coffee:" + gym_coffee.ENV_ID)`` or ``import gym_coffee`` inside the env
    function, so that the id is registered there.

    ## Version History
    * v0: first version.
    """

    metadata: dict[str, Any] = {  # noqa: RUF012  (Gymnasium's class attribute)
        "render_modes": ["human", "rgb_array"],
        "render_fps": round(1.0 / CONTROL_DT),
    }

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        reward_type: str = "dense",
        width: int = 320,
        height: int = 240,
        render_shadows: bool = False,
        exact_reset: bool = True,
        action_type: str = "joint",
        level: str = "easy",
        obs_noise: float = 0.0,
        calibration_bias: float = 0.0,
        actuation_noise: float = 0.0,
        cup_push: tuple[float, float] | None = None,
        physics: str = "default",
    ) -> None:
        EzPickle.__init__(
            self,
            render_mode,
            reward_type=reward_type,
            width=width,
            height=height,
            render_shadows=render_shadows,
            exact_reset=exact_reset,
            action_type=action_type,
            level=level,
            obs_noise=obs_noise,
            calibration_bias=calibration_bias,
            actuation_noise=actuation_noise,
            cup_push=cup_push,
            physics=physics,
        )
        # Every argument is checked before the physics server starts.
        self.render_mode = check_choice(
            "render_mode", render_mode, [None, *self.metadata["render_modes"]]
        )
        self.reward_type = check_choice("reward_type", reward_type, ["dense", "sparse"])
        self.width = check_int("width", width, 1, MAX_IMAGE_SIDE)
        self.height = check_int("height", height, 1, MAX_IMAGE_SIDE)
        self.render_shadows = check_bool("render_shadows", render_shadows)
        self.exact_reset = check_bool("exact_reset", exact_reset)
        self.action_type = check_choice("action_type", action_type, list(ACTION_TYPES))
        self.level = check_choice("level", level, list(LEVEL_SPECS))
        self.obs_noise = check_real("obs_noise", obs_noise, 0.0, MAX_PERTURBATION, "m")
        self.calibration_bias = check_real(
            "calibration_bias", calibration_bias, 0.0, MAX_PERTURBATION, "m"
        )
        self.actuation_noise = check_real(
            "actuation_noise", actuation_noise, 0.0, MAX_PERTURBATION, "rad"
        )
        self.cup_push = self._check_cup_push(cup_push)
        self.physics = check_choice("physics", physics, list(PHYSICS_PRESETS))

        timestep, n_substeps, iterations, residual = PHYSICS_PRESETS[self.physics]
        # Headless frames without shadows composite the bodies that stand still (floor, table,
        # the machine's housing) from a backdrop (Simulation.render: the same pixels, ~3x faster).
        static = CoffeeScene.STATIC_BODIES if not self.render_shadows else ()
        self.sim = Simulation(
            render_mode,
            timestep=timestep,
            n_substeps=n_substeps,
            solver_iterations=iterations,
            solver_residual=residual,
            static_bodies=static,
        )
        self.robot = Panda(self.sim)
        self.scene = CoffeeScene(self.sim)
        self._load()

        self.action_space = spaces.Box(
            -1.0, 1.0, (ACTION_TYPES[self.action_type],), dtype=np.float32
        )
        self.observation_space = spaces.Box(OBS_LOW, OBS_HIGH, dtype=np.float32)

        self._n_steps = 0
        self._cup_init_pos = np.zeros(3)
        self._grasped = False
        self._pressed = False
        self._stage = 0
        self._pressed_with_cup = False
        self._rest_posture = NEUTRAL_JOINTS.copy()
        self._hand_rotation = np.eye(3)  # commanded hand orientation (end-effector modes)
        self._press_origin = np.zeros(3)  # grasp point when the button was last at rest
        self._bias = {"cup": np.zeros(3), "machine": np.zeros(3)}
        self._push: tuple[int, NDArray[np.float64]] | None = None  # (step, displacement)
        self._layout_info: dict[str, Any] = {}

    # ------------------------------------------------------------------ public API
    @property
    def kinematics(self) -> PandaKinematics:
        """Forward kinematics and Jacobian of the grasp point (the ``RobotModel`` protocol)."""
        return self.robot.kinematics

    def task_points(self) -> dict[str, NDArray[np.float64]]:
        """Task points in the world frame: ``cup_pos``, ``cup_radius``, ``cup_height``,
        ``place_pos``,
        ``place_tolerance``, ``button_pos``, ``button_axis``, ``button_travel_to_press``."""
        return self.scene.task_points()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        super().reset(seed=seed)
        rng = self.np_random
        layout = Layout.sample(rng, self.level)
        q0 = NEUTRAL_JOINTS + rng.uniform(-START_JOINT_NOISE, START_JOINT_NOISE, size=7)
        if options is not None:  # checked before any work
            if not isinstance(options, Mapping) or set(map(str, options)) - {"layout"}:
                raise ValueError(
                    f"options must be None or a dict {{'layout': ...}}, got {options!r}"
                )
            if "layout" in options:
                layout = layout.replace(options["layout"])
        self._draw_perturbations(rng, layout)
        if self.sim.closed:  # reusable after close() (SB3's check_env renders, closes, resets)
            self.sim.connect()
            self._load()
        elif self.exact_reset and not self.sim.restore_state():  # restored: ~0.5 ms
            # The world changed since it was loaded (e.g. a body added): load it afresh (~20 ms).
            self.sim.reset_world()
            self._load()
        # Otherwise the bodies stay loaded (removing and reloading single bodies leaked memory in
        # PyBullet) and are re-posed; their contact caches are dropped first.
        self.sim.clear_contact_caches((self.robot.name, *self.scene.MOVABLE_BODIES))
        self.scene.reset(layout)
        self.robot.reset(q0, GRIPPER_MAX_OPENING)
        self._n_steps = 0
        self._cup_init_pos = layout.cup_pos.copy()
        self._grasped = False
        self._pressed = False
        self._stage = 0
        self._pressed_with_cup = False
        self._rest_posture = q0.copy()
        q, _ = self.robot.joint_states()
        self._press_origin, self._hand_rotation = self.kinematics.forward_pose(q)
        self._layout_info = layout.as_dict()
        state = self._read_state()
        obs = self._get_obs(state)
        info = self._evaluate(state)[0]
        if self.render_mode == "human":
            self.render()
        return obs, info

    def step(
        self, action: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        q_target, opening = self._targets(self._check_action(action))
        if self.actuation_noise > 0.0:
            noise = self.np_random.normal(0.0, self.actuation_noise, 7)
            q_target = np.clip(q_target + noise, self.robot.joint_lower, self.robot.joint_upper)
        self.robot.command(q_target, opening)
        self._simulate()
        if self._push is not None and self._n_steps == self._push[0]:
            self._push_cup(self._push[1])
        state = self._read_state()
        obs = self._get_obs(state)
        info, failed = self._evaluate(state)
        reward = float(sum(info[key] for key in _REWARD_KEYS))
        terminated = bool(info["is_success"] or failed)
        if self.render_mode == "human":
            self.render()
        return obs, reward, terminated, False, info

    def render(self) -> NDArray[np.uint8] | None:
        """An RGB frame (height, width, 3) for ``"rgb_array"``; moves the GUI camera for
        ``"human"``."""
        # The whole arm in view, also at the start (its top was cut off at distance 1.25).
        target, distance, yaw, pitch = (0.35, 0.06, 0.32), 1.5, 45.0, -28.0
        if self.render_mode == "rgb_array":
            return self.sim.render(
                self.width, self.height, target, distance, yaw, pitch, shadows=self.render_shadows
            )
        if self.render_mode == "human":
            self.sim.reset_debug_camera(target, distance, yaw, pitch)
        return None

    def close(self) -> None:
        if getattr(self, "sim", None) is not None:
            self.sim.close()

    # ------------------------------------------------------------------ internals
    @staticmethod
    def _check_cup_push(cup_push: Any) -> tuple[float, float] | None:
        if cup_push is None:
            return None
        expected = (
            f"cup_push must be None or (low, high) with 0 <= low <= high <= {MAX_PERTURBATION} m"
        )
        try:
            low, high = (float(v) for v in cup_push)
        except (TypeError, ValueError):
            raise ValueError(f"{expected}, got {cup_push!r}") from None
        if not (np.isfinite([low, high]).all() and 0.0 <= low <= high <= MAX_PERTURBATION):
            raise ValueError(f"{expected}, got {cup_push!r}")
        return low, high

    def _draw_perturbations(self, rng: np.random.Generator, layout: Layout) -> None:
        """This episode's calibration offsets and cup push (no draws when they are off)."""
        for name in ("cup", "machine"):
            offset = np.zeros(3)
            if self.calibration_bias > 0.0:
                direction = rng.normal(size=3)
                offset = self.calibration_bias * direction / np.linalg.norm(direction)
            self._bias[name] = offset
        self._push = None
        if self.cup_push is not None:
            step = int(rng.integers(CUP_PUSH_STEPS[0], CUP_PUSH_STEPS[1] + 1))
            distance = float(rng.uniform(*self.cup_push))
            angle = float(rng.uniform(0.0, 2.0 * np.pi))
            displacement = distance * np.array([np.cos(angle), np.sin(angle), 0.0])
            # Away from the machine where the drawn direction would bring the cup close to it.
            pushed = layout.cup_pos + displacement
            if np.linalg.norm(pushed[:2] - layout.machine_pos[:2]) < MIN_CUP_MACHINE_DISTANCE:
                displacement = -displacement
            self._push = (step, displacement)

    def _push_cup(self, displacement: NDArray[np.float64]) -> None:
        """Move the standing cup by ``displacement`` (at rest), unless the robot touches it."""
        if self._grasped or self.scene.robot_touches_cup():
            return
        pos, quat = self.scene.cup_pose()
        self.sim.set_base_pose("cup", pos + displacement, quat)

    def _check_action(self, action: Any) -> NDArray[np.float64]:
        """The action as float64, clipped to [-1, 1]; ValueError for a wrong shape or NaN/inf."""
        size = ACTION_TYPES[self.action_type]
        if isinstance(action, np.ndarray) and action.shape == (size,) and action.dtype.kind == "f":
            array = action.astype(np.float64)  # the usual action: only its values to check
            if not np.isfinite(array).all():
                array = check_vector(f"action (action_type={self.action_type!r})", action, (size,))
        else:
            array = check_vector(f"action (action_type={self.action_type!r})", action, (size,))
        return np.minimum(np.maximum(array, -1.0), 1.0)

    def _targets(self, action: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
        """Joint targets (7,) and gripper opening (m) for an action of the env's ``action_type``."""
        q, _ = self.robot.joint_states()
        opening = (action[-1] + 1.0) / 2.0 * GRIPPER_MAX_OPENING
        if self.action_type == "joint":
            return self.robot.joint_targets(q, action), opening
        position = self.kinematics.forward_kinematics(q) + action[:3] * MAX_EE_STEP
        if self.action_type == "ee_rot":
            turn = Rotation.from_euler("xyz", action[3:6] * MAX_EE_ROT_STEP).as_matrix()
            self._hand_rotation = turn @ self._hand_rotation
        q_target = self.kinematics.ik_step(
            q,
            position,
            self._hand_rotation,
            self._rest_posture,
            max_step=MAX_JOINT_STEP,
            keep_direction=True,
        )
        return q_target, opening

    def _load(self) -> None:
        """Load robot and scene into the (new) physics server and keep the loaded world's state
        (what every exact reset restores)."""
        self.robot.load()
        self.scene.load()
        self.robot.reset(NEUTRAL_JOINTS)
        self.sim.save_state()

    def _simulate(self) -> None:
        """One control step of physics with the robot's commands set (the button's spring is set
        at reset; its hard stop is checked after every physics step by the simulation), the
        clock."""
        self.sim.step()
        self._n_steps += 1

    def _read_state(self) -> _State:
        """The simulator's state that observation and evaluation need, read once per step."""
        q, qd, gripper = self.robot.state()
        ee = self.kinematics.forward_kinematics(q)
        cup_pos, cup_quat = self.scene.cup_pose()
        return _State(q, qd, gripper, ee, cup_pos, cup_quat, self.scene.button_travel())

    def _get_obs(self, state: _State | None = None) -> NDArray[np.float32]:
        state = self._read_state() if state is None else state
        layout = self.scene.layout
        cup_bias = self._bias["cup"]
        obs = np.empty(OBS_DIM)  # filled part by part (OBS_SLICES), then clipped to the bounds
        obs[_TIME] = self._n_steps * CONTROL_DT
        obs[_JOINT_POS] = state.q
        obs[_JOINT_VEL] = state.qd
        obs[_GRIPPER] = state.gripper
        obs[_EE_POS] = state.ee
        obs[_CUP_POS] = state.cup_pos + cup_bias
        obs[_CUP_QUAT] = state.cup_quat
        obs[_CUP_INIT_POS] = self._cup_init_pos + cup_bias
        obs[_MACHINE_POS] = layout.machine_pos + self._bias["machine"]
        obs[_MACHINE_YAW] = layout.machine_yaw
        obs[_BUTTON_TRAVEL] = state.travel
        if self.obs_noise > 0.0:
            for name in PERTURBED_OBS:
                obs[OBS_SLICES[name]] += self.np_random.normal(0.0, self.obs_noise, 3)
        np.maximum(obs, _OBS_LOW64, out=obs)
        np.minimum(obs, _OBS_HIGH64, out=obs)
        return obs.astype(np.float32)

    def _evaluate(self, state: _State | None = None) -> tuple[dict[str, Any], bool]:
        """Stage flags, reward terms and whether the episode failed, from the simulator's state."""
        scene = self.scene
        state = self._read_state() if state is None else state
        cup_pos = state.cup_pos
        cup_x, cup_y, cup_z = cup_pos.tolist()  # the same doubles, as Python floats (cheaper)
        tilt = scene.cup_tilt(state.cup_quat)
        left, right, touched = scene.robot_cup_contacts()
        held = left and right
        # Grasped (latched): the cup is off the table between both fingers.
        if held and not scene.cup_on_table() and cup_z > TABLE_TOP_Z + 0.005:
            self._grasped = True
        offset = cup_pos - scene.place_pos
        # At rest (speeds read only when the pose qualifies: the velocity query changes nothing).
        placed = bool(
            tilt < CUP_UPRIGHT_TILT
            and np.hypot(offset[0], offset[1]) < PLACE_TOLERANCE
            and abs(offset[2]) < 0.01
            and not touched
            and self._cup_at_rest()
        )
        ee = state.ee
        travel = state.travel
        if travel < BUTTON_REST_TRAVEL:
            self._press_origin = ee
        elif travel >= BUTTON_PRESS_TRAVEL and self._pushed_along_axis(ee):
            self._pressed = True
            if placed:
                self._pressed_with_cup = True
        success = bool(self._grasped and placed and self._pressed_with_cup)
        off_table = bool(
            cup_z < TABLE_TOP_Z - 0.05
            or not (TABLE_X[0] < cup_x < TABLE_X[1] and TABLE_Y[0] < cup_y < TABLE_Y[1])
        )
        tipped = bool(tilt > CUP_TIPPED_TILT and not held)
        failed = off_table or tipped

        stage = 3 if success else (2 if self._grasped and placed else (1 if self._grasped else 0))
        previous_stage, self._stage = self._stage, stage
        terms = dict.fromkeys(REWARD_TERMS, 0.0)
        if self.reward_type == "dense":
            cup_middle = cup_pos + _CUP_MIDDLE
            if not self._grasped:
                terms["reach"] = -float(np.linalg.norm(ee - cup_middle))
            elif not placed:
                terms["carry"] = -float(np.linalg.norm(offset))
            else:
                button = scene.button_pos
                terms["press"] = -float(np.linalg.norm(ee - button)) + min(
                    travel / BUTTON_PRESS_TRAVEL, 1.0
                )
            # Paid on stage changes only (negative if a stage is lost), so an agent cannot farm
            # the bonus by holding an intermediate stage instead of finishing the task.
            terms["stage"] = STAGE_BONUS * (stage - previous_stage)
            terms["success"] = SUCCESS_BONUS if success else 0.0
            terms["failure"] = FAILURE_PENALTY if failed else 0.0
        else:
            terms["success"] = 1.0 if success else 0.0
        info: dict[str, Any] = {
            "is_success": success,
            **dict(zip(STAGES, (bool(self._grasped), placed, bool(self._pressed)), strict=True)),
            "stage": int(stage),
            "layout": dict(self._layout_info),
        }
        for key, value in zip(_REWARD_KEYS, terms.values(), strict=True):
            info[key] = float(value)
        return info, failed

    def _cup_at_rest(self) -> bool:
        lin, ang = self.sim.get_base_velocity("cup")
        return bool(
            np.linalg.norm(lin) < CUP_REST_SPEED and np.linalg.norm(ang) < CUP_REST_ANGULAR_SPEED
        )

    def _pushed_along_axis(self, ee: NDArray[np.float64]) -> bool:
        """Whether the grasp point moved along the button's axis since the button was at rest:
        at least half the press threshold, and more along the axis than across it."""
        axis = self.scene.machine_rotation[:, 0]
        moved = ee - self._press_origin
        along = float(moved @ axis)
        across = float(np.linalg.norm(moved - along * axis))
        return along >= 0.5 * BUTTON_PRESS_TRAVEL and across <= along
