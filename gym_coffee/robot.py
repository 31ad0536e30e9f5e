"""The Franka Panda: 7 arm joints under position control and a parallel two-finger gripper.

Action (``docs/CONTRACTS.md``): ``a[:7]`` are joint-position deltas, joint targets = measured joint
positions + ``a[:7] * MAX_JOINT_STEP`` (rad per control step), clipped to the joint limits; ``a[7]``
is the absolute gripper opening ``(a[7] + 1) / 2 * GRIPPER_MAX_OPENING`` (m, distance between the
fingers). :func:`action_from_targets` is the inverse.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gym_coffee.kinematics import JOINT_LOWER, JOINT_UPPER, JOINT_VELOCITY_LIMIT, PandaKinematics
from gym_coffee.simulation import Simulation

__all__ = [
    "ACTION_TYPES",
    "ARM_JOINTS",
    "EE_LINK",
    "FINGER_JOINTS",
    "GRIPPER_MAX_OPENING",
    "MAX_EE_ROT_STEP",
    "MAX_EE_STEP",
    "MAX_JOINT_STEP",
    "NEUTRAL_JOINTS",
    "Panda",
    "action_from_targets",
]

#: Largest joint-position change commanded per control step (rad); at 25 Hz, 1.25 rad/s.
MAX_JOINT_STEP = 0.05
#: Largest Cartesian step of the grasp point commanded per control step in the end-effector
#: action modes (m); at 25 Hz, 0.5 m/s.
MAX_EE_STEP = 0.02
#: Largest rotation of the hand about each world axis per control step (rad), ``"ee_rot"``.
MAX_EE_ROT_STEP = 0.05
#: Action modes and their action sizes: joint deltas + gripper, Cartesian delta + gripper,
#: Cartesian and roll/pitch/yaw deltas + gripper.
ACTION_TYPES: dict[str, int] = {"joint": 8, "ee": 4, "ee_rot": 7}
#: Largest distance between the fingers (m).
GRIPPER_MAX_OPENING = 0.08
#: PyBullet joint indices of panda_joint1..7, of the two finger joints, and the grasp-target link.
ARM_JOINTS = (0, 1, 2, 3, 4, 5, 6)
FINGER_JOINTS = (9, 10)
FINGER_LINKS = (9, 10)
EE_LINK = 11
#: Arm and finger joints, read in one query (:meth:`Panda.state`).
_STATE_JOINTS = (*ARM_JOINTS, *FINGER_JOINTS)
#: Start posture (rad), gripper pointing down in front of the robot.
NEUTRAL_JOINTS = np.array([0.0, -0.6, 0.0, -2.4, 0.0, 1.85, 0.785])
#: Joint torque limits (N m) of the Panda arm and force limit (N) per finger.
ARM_FORCES = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
FINGER_FORCE = 20.0
FINGER_MAX_VELOCITY = 0.2  # m/s per finger (URDF)
#: Colours of the links (-1: the base) in headless ``rgb_array`` frames, which draw the Panda's
#: collision meshes (~3.5k triangles) instead of its visual meshes (~130k triangles: TinyRenderer
#: took ~36 of a frame's ~62 ms on them): white links, grey joint caps and hand, dark fingers.
HEADLESS_COLORS: dict[int, tuple[float, float, float, float]] = {
    -1: (0.93, 0.93, 0.93, 1.0),
    0: (0.93, 0.93, 0.93, 1.0),
    1: (0.93, 0.93, 0.93, 1.0),
    2: (0.93, 0.93, 0.93, 1.0),
    3: (0.93, 0.93, 0.93, 1.0),
    4: (0.93, 0.93, 0.93, 1.0),
    5: (0.93, 0.93, 0.93, 1.0),
    6: (0.55, 0.55, 0.58, 1.0),
    8: (0.85, 0.85, 0.87, 1.0),
    9: (0.25, 0.25, 0.27, 1.0),
    10: (0.25, 0.25, 0.27, 1.0),
}
# The constant limits as tuples of floats, passed to every command.
_ARM_FORCES = tuple(ARM_FORCES.tolist())
_ARM_MAX_VELOCITIES = tuple(JOINT_VELOCITY_LIMIT.tolist())
_FINGER_FORCES = (FINGER_FORCE, FINGER_FORCE)
_FINGER_MAX_VELOCITIES = (FINGER_MAX_VELOCITY, FINGER_MAX_VELOCITY)
#: Gain of the joints' position controller: the fraction of the error corrected per 4 ms
#: (``Simulation.control_joints``; a time constant of 11 ms with every physics preset).
POSITION_GAIN = 0.3


def action_from_targets(
    q: ArrayLike, q_target: ArrayLike, gripper_opening: float
) -> NDArray[np.float32]:
    """The action (8,) that commands joint targets ``q_target`` from measured ``q`` and a gripper
    opening (m).

    Clipped to [-1, 1]; the inverse of the scaling in :meth:`Panda.joint_targets`. Works on (7,) or
    (n, 7) with a scalar or (n,) ``gripper_opening``.
    """
    q = np.asarray(q, dtype=np.float64)
    q_target = np.asarray(q_target, dtype=np.float64)
    delta = (q_target - q) / MAX_JOINT_STEP
    grip = 2.0 * np.asarray(gripper_opening, dtype=np.float64) / GRIPPER_MAX_OPENING - 1.0
    grip = np.broadcast_to(grip, delta.shape[:-1])[..., None]
    return np.clip(np.concatenate([delta, grip], axis=-1), -1.0, 1.0).astype(np.float32)


class Panda:
    """The Panda arm and gripper in a :class:`~gym_coffee.simulation.Simulation`.

    Args:
        sim: the simulation to load the robot into.
        base_position: world position of ``panda_link0``.
    """

    name = "panda"

    def __init__(self, sim: Simulation, base_position: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        self.sim = sim
        self.base_position = np.asarray(base_position, dtype=np.float64)
        self.kinematics = PandaKinematics(self.base_position)
        self.joint_lower = JOINT_LOWER.copy()
        self.joint_upper = JOINT_UPPER.copy()

    def load(self) -> None:
        """Load the Panda (with its detailed visual meshes only in the GUI: headless frames
        draw the collision meshes, see :data:`HEADLESS_COLORS`)."""
        sim = self.sim
        sim.load_urdf(
            self.name,
            "franka_panda/panda.urdf",
            self.base_position,
            use_fixed_base=True,
            package_asset=False,
            visual_shapes=sim.gui,
        )
        for link in FINGER_LINKS:
            sim.set_dynamics(
                self.name, link, lateralFriction=1.0, spinningFriction=0.003, rollingFriction=0.0001
            )
        if sim.visual_shapes and not sim.gui:
            for link, rgba in HEADLESS_COLORS.items():
                sim.set_color(self.name, link, rgba)

    def reset(self, q: ArrayLike, gripper_opening: float = GRIPPER_MAX_OPENING) -> None:
        """Put the base in place, the arm at ``q`` and the gripper at an opening (m), at rest, and
        hold them there."""
        q = np.clip(np.asarray(q, dtype=np.float64), self.joint_lower, self.joint_upper)
        half = 0.5 * float(gripper_opening)
        self.sim.set_base_pose(self.name, self.base_position, (0.0, 0.0, 0.0, 1.0))
        self.sim.reset_joint_states(self.name, ARM_JOINTS, q)
        self.sim.reset_joint_states(self.name, FINGER_JOINTS, [half, half])
        self.command(q, gripper_opening)

    def command(self, q_target: NDArray[np.float64], gripper_opening: float) -> None:
        """Hold the arm's joint targets ``q_target`` (7,) and the gripper opening (m)."""
        self.sim.control_joints(
            self.name,
            ARM_JOINTS,
            q_target,
            _ARM_FORCES,
            _ARM_MAX_VELOCITIES,
            position_gain=POSITION_GAIN,
        )
        half = 0.5 * float(gripper_opening)
        self.sim.control_joints(
            self.name,
            FINGER_JOINTS,
            [half, half],
            _FINGER_FORCES,
            _FINGER_MAX_VELOCITIES,
            position_gain=POSITION_GAIN,
        )

    def joint_targets(
        self, q: NDArray[np.float64], action: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Joint targets (7,) of a joint-mode action (8,) in [-1, 1] from measured joints ``q``."""
        target = q + action[:7] * MAX_JOINT_STEP
        return np.minimum(np.maximum(target, self.joint_lower), self.joint_upper)

    def joint_states(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Arm joint positions (7,) and velocities (7,)."""
        return self.sim.get_joint_states(self.name, ARM_JOINTS)

    def state(self) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        """Arm joint positions (7,), velocities (7,) and the gripper opening (m), in one query."""
        pos, vel = self.sim.get_joint_states(self.name, _STATE_JOINTS)
        return pos[:7], vel[:7], float(pos[7] + pos[8])

    def gripper_opening(self) -> float:
        """Distance between the fingers (m)."""
        pos, _ = self.sim.get_joint_states(self.name, FINGER_JOINTS)
        return float(pos.sum())

    def ee_position(self) -> NDArray[np.float64]:
        """World position of the grasp point (from the simulator)."""
        return self.sim.get_link_pose(self.name, EE_LINK)[0]
