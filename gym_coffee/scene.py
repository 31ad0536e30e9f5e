"""The coffee-task scene: table, cup, coffee machine with a spring-loaded button, layout sampling.

World frame: the robot base (``panda_link0``) stands at the origin on the table top (z = 0) and
faces +x. Geometry of the assets (``gym_coffee/assets/*.urdf``) is mirrored by the constants below.

Layout regions (drawn uniformly from the env's ``np_random`` at every reset):

==================  ===========================================================================
cup base centre     x in ``CUP_REGION_X``, y in ``CUP_REGION_Y`` (in front, to the robot's right)
machine footprint   x in ``MACHINE_REGION_X``, y in ``MACHINE_REGION_Y`` (to the robot's left),
                    yaw ``MACHINE_YAW_NOMINAL`` (90 degrees: the machine's front faces -y,
                    towards the cup's side) plus uniform noise within ``MACHINE_YAW_RANGE``
==================  ===========================================================================

The cup is therefore carried sideways (along +y) into the machine, the gripper horizontal and
pointing along the machine's axis, which suits the Panda's wrist. Cup and machine are redrawn until
the cup is at least ``MIN_CUP_MACHINE_DISTANCE`` from the machine's footprint centre, so the cup
never starts under or next to the machine.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gym_coffee._checks import check_real, check_vector
from gym_coffee.simulation import Simulation

__all__ = [
    "BUTTON_PRESS_TRAVEL",
    "CUP_HEIGHT",
    "CUP_RADIUS",
    "CUP_REGION_X",
    "CUP_REGION_Y",
    "LAYOUT_KEYS",
    "LEVEL_SPECS",
    "MACHINE_REGION_X",
    "MACHINE_REGION_Y",
    "MACHINE_YAW_NOMINAL",
    "MACHINE_YAW_RANGE",
    "PLACE_TOLERANCE",
    "CoffeeScene",
    "Layout",
    "LevelSpec",
]

# --- table (m) ---------------------------------------------------------------------------------
TABLE_TOP_Z = 0.0
TABLE_X = (-0.35, 1.05)
TABLE_Y = (-0.6, 0.6)
# --- cup: 6 cm diameter, 8 cm tall, 0.15 kg; frame at the centre of its base ----------------------
CUP_RADIUS = 0.03
CUP_HEIGHT = 0.08
CUP_MASS = 0.15
# --- coffee machine (machine frame: footprint centre on the table, +x from front to back) --------
MACHINE_SIZE = (0.24, 0.20, 0.32)  # depth, width, height
TRAY_TOP_Z = 0.03  # drip-tray top, machine frame
HEAD_BOTTOM_Z = 0.21  # underside of the overhanging head
HEAD_FRONT_X = -0.12  # front panel of the head
#: Where the cup's base centre stands on the drip tray, under the spout (machine frame).
PLACE_OFFSET = np.array([-0.05, 0.0, TRAY_TOP_Z])
#: Centre of the button's face at rest (machine frame); the button presses along the machine's +x.
BUTTON_FACE_OFFSET = np.array([-0.132, 0.05, 0.265])
BUTTON_RADIUS = 0.012
BUTTON_MAX_TRAVEL = 0.008
#: Travel (m) past which the button counts as pressed (latched), if it was pushed along its axis.
BUTTON_PRESS_TRAVEL = 0.005
#: Travel (m) below which the button counts as released (a press is measured from there).
BUTTON_REST_TRAVEL = 0.001
#: Return force of the button's spring (N), a weak position motor towards travel 0.
BUTTON_SPRING_FORCE = 3.0
#: Horizontal distance (m) within which the cup's base centre counts as under the spout.
PLACE_TOLERANCE = 0.025
# --- layout regions ----------------------------------------------------------------------------
CUP_REGION_X = (0.40, 0.56)
CUP_REGION_Y = (-0.26, -0.06)
MACHINE_REGION_X = (0.45, 0.60)
MACHINE_REGION_Y = (0.30, 0.38)
MACHINE_YAW_NOMINAL = np.pi / 2
MACHINE_YAW_RANGE = np.deg2rad(15.0)
MIN_CUP_MACHINE_DISTANCE = 0.28
# --- hard level: the machine on either side (the approach direction flips with it), wider regions
HARD_CUP_REGION_X = (0.36, 0.60)
HARD_CUP_REGION_Y = (-0.30, 0.0)
HARD_MACHINE_REGION_X = (0.42, 0.62)
HARD_MACHINE_REGION_Y = (0.28, 0.40)
HARD_MACHINE_YAW_RANGE = np.deg2rad(30.0)
# --- failure ----------------------------------------------------------------------------------
#: The cup counts as tipped over beyond this tilt (rad) while not held by both fingers.
CUP_TIPPED_TILT = np.deg2rad(60.0)
#: Placed means at rest: upright below this tilt (rad) and slower than these speeds (the cup
#: standing on the tray after a teacher's placement: < 0.01 deg, < 0.003 rad/s, ~0 m/s).
CUP_UPRIGHT_TILT = np.deg2rad(5.0)
CUP_REST_SPEED = 0.01  # m/s
CUP_REST_ANGULAR_SPEED = 0.1  # rad/s

FINGER_LINKS = (9, 10)


def rot_z(yaw: float) -> NDArray[np.float64]:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class LevelSpec:
    """Where a difficulty level puts the cup and the machine (see the module docstring).

    The machine's footprint centre is drawn with ``|y|`` in ``machine_y`` on the machine's side
    (+y, the robot's left; with ``mirror`` the side is drawn too, 50/50), its yaw is the nominal
    one of that side (front towards the middle of the table) plus uniform noise within
    ``yaw_range``; the cup's y is in ``cup_y`` on the other side (mirrored with the machine).
    """

    cup_x: tuple[float, float]
    cup_y: tuple[float, float]
    machine_x: tuple[float, float]
    machine_y: tuple[float, float]
    yaw_range: float
    mirror: bool
    min_distance: float


#: The difficulty levels (``gym_coffee.LEVELS`` maps them to the registered ids).
LEVEL_SPECS: dict[str, LevelSpec] = {
    "easy": LevelSpec(
        CUP_REGION_X,
        CUP_REGION_Y,
        MACHINE_REGION_X,
        MACHINE_REGION_Y,
        MACHINE_YAW_RANGE,
        mirror=False,
        min_distance=MIN_CUP_MACHINE_DISTANCE,
    ),
    "hard": LevelSpec(
        HARD_CUP_REGION_X,
        HARD_CUP_REGION_Y,
        HARD_MACHINE_REGION_X,
        HARD_MACHINE_REGION_Y,
        HARD_MACHINE_YAW_RANGE,
        mirror=True,
        min_distance=MIN_CUP_MACHINE_DISTANCE,
    ),
}

#: The keys of a layout (``reset(options={"layout": {...}})`` and ``info["layout"]``).
LAYOUT_KEYS = ("cup_pos", "machine_pos", "machine_yaw")


@dataclass(frozen=True)
class Layout:
    """One episode's layout: cup base centre (3,), machine footprint centre (3,) and yaw (rad)."""

    cup_pos: NDArray[np.float64]
    machine_pos: NDArray[np.float64]
    machine_yaw: float

    @classmethod
    def sample(cls, rng: np.random.Generator, level: str = "easy") -> Layout:
        """Draw a layout of ``level`` from ``rng`` (rejection sampling keeps the cup away from the
        machine)."""
        spec = LEVEL_SPECS[level]
        while True:
            side = (1.0 if rng.uniform() < 0.5 else -1.0) if spec.mirror else 1.0
            cup = np.array([rng.uniform(*spec.cup_x), side * rng.uniform(*spec.cup_y), TABLE_TOP_Z])
            machine = np.array(
                [rng.uniform(*spec.machine_x), side * rng.uniform(*spec.machine_y), TABLE_TOP_Z]
            )
            yaw = side * MACHINE_YAW_NOMINAL + float(rng.uniform(-spec.yaw_range, spec.yaw_range))
            if np.linalg.norm(cup[:2] - machine[:2]) >= spec.min_distance:
                return cls(cup, machine, yaw)

    def as_dict(self) -> dict[str, Any]:
        """The layout as ``info["layout"]`` reports it (tuples of floats; ``reset`` accepts it
        back as ``options={"layout": ...}``)."""
        return {
            "cup_pos": tuple(float(v) for v in self.cup_pos),
            "machine_pos": tuple(float(v) for v in self.machine_pos),
            "machine_yaw": float(self.machine_yaw),
        }

    def replace(self, options: Any) -> Layout:
        """This layout with the entries of ``options`` (a dict with some of ``LAYOUT_KEYS``: the
        cup's and machine's positions (2,) on the table or (3,) with z = 0, the machine's yaw in
        rad), checked: ``ValueError`` naming the key for an unknown key, a wrong shape, a value
        that is not finite, off the table, or a cup closer than ``MIN_CUP_MACHINE_DISTANCE`` to
        the machine."""
        if not isinstance(options, Mapping):
            raise ValueError(
                f"options['layout'] must be a dict with keys {list(LAYOUT_KEYS)}, "
                f"got {type(options).__name__}"
            )
        unknown = sorted(set(map(str, options)) - set(LAYOUT_KEYS))
        if unknown:
            raise ValueError(
                f"options['layout'] has unknown key(s) {unknown}; expected some of "
                f"{list(LAYOUT_KEYS)}"
            )
        values: dict[str, Any] = {
            "cup_pos": self.cup_pos,
            "machine_pos": self.machine_pos,
            "machine_yaw": self.machine_yaw,
        }
        for key in ("cup_pos", "machine_pos"):
            if key in options:
                name = f"options['layout']['{key}']"
                pos = check_vector(name, options[key], (2, 3))
                if pos.shape[0] == 3 and abs(pos[2] - TABLE_TOP_Z) > 1e-9:
                    raise ValueError(f"{name} must stand on the table (z = {TABLE_TOP_Z})")
                if not (
                    TABLE_X[0] + 0.1 <= pos[0] <= TABLE_X[1] - 0.1
                    and TABLE_Y[0] + 0.1 <= pos[1] <= TABLE_Y[1] - 0.1
                ):
                    raise ValueError(
                        f"{name} must be on the table, x in [{TABLE_X[0] + 0.1}, "
                        f"{TABLE_X[1] - 0.1}] and y in [{TABLE_Y[0] + 0.1}, {TABLE_Y[1] - 0.1}] m,"
                        f" got {pos[:2].tolist()}"
                    )
                values[key] = np.array([pos[0], pos[1], TABLE_TOP_Z])
        if "machine_yaw" in options:
            values["machine_yaw"] = check_real(
                "options['layout']['machine_yaw']", options["machine_yaw"], -np.pi, np.pi, "rad"
            )
        distance = float(np.linalg.norm(values["cup_pos"][:2] - values["machine_pos"][:2]))
        if distance < MIN_CUP_MACHINE_DISTANCE:
            raise ValueError(
                f"options['layout']: the cup must be at least {MIN_CUP_MACHINE_DISTANCE} m from "
                f"the machine's footprint centre, got {distance:.3f} m"
            )
        return Layout(values["cup_pos"], values["machine_pos"], values["machine_yaw"])


class CoffeeScene:
    """Table, cup and coffee machine in a :class:`~gym_coffee.simulation.Simulation`."""

    def __init__(self, sim: Simulation) -> None:
        self.sim = sim
        self._set_layout(
            Layout(np.array([0.5, -0.15, 0.0]), np.array([0.52, 0.34, 0.0]), np.pi / 2)
        )

    def _set_layout(self, layout: Layout) -> None:
        self.layout = layout
        # The machine's frame and points, fixed for an episode (read at every step).
        self._rotation = rot_z(layout.machine_yaw)
        self.place_pos = self.machine_point(PLACE_OFFSET)
        self.button_pos = self.machine_point(BUTTON_FACE_OFFSET)

    BODIES = ("plane", "table", "machine", "cup")

    def load(self) -> None:
        """Load the scene's bodies, once per physics server (a no-op when they are loaded).

        Resets re-pose the loaded bodies (:meth:`reset`, after
        :meth:`Simulation.clear_contact_caches`) instead of removing and loading them afresh:
        PyBullet does not free everything a removed body held (a reload leaked ~14 KiB per reset).
        """
        sim = self.sim
        if "plane" not in sim.bodies:
            sim.load_urdf(
                "plane", "plane.urdf", (0.0, 0.0, -0.72), use_fixed_base=True, package_asset=False
            )
        if "table" not in sim.bodies:
            sim.load_urdf("table", "table.urdf", (0.0, 0.0, TABLE_TOP_Z), use_fixed_base=True)
        if "machine" not in sim.bodies:
            sim.load_urdf(
                "machine",
                "coffee_machine.urdf",
                self.layout.machine_pos,
                use_fixed_base=True,
                self_collision=True,  # the button's hard stop against the front panel
            )
        # The button's hard stop (see :meth:`Simulation.set_joint_stop`): the button's cap also
        # collides with the front panel after 8 mm, but a fast strike still pushed it up to 10 mm
        # into the (soft) contact.
        sim.set_joint_stop("machine", 0, BUTTON_MAX_TRAVEL)
        if "cup" not in sim.bodies:
            sim.load_urdf("cup", "cup.urdf", self.layout.cup_pos)

    #: Bodies whose base stands still during an episode (the machine's button moves; it is a link).
    STATIC_BODIES = ("plane", "table", "machine")

    #: Bodies that move between episodes; their contact caches are cleared at every reset.
    MOVABLE_BODIES = ("machine", "cup")

    def reset(self, layout: Layout) -> None:
        """Put the cup and machine where ``layout`` says, at rest, the button released.

        Call :meth:`Simulation.clear_contact_caches` first (``CoffeeEnv.reset`` does), so that
        nothing of the previous episode's contacts is left.
        """
        self._set_layout(layout)
        sim = self.sim
        yaw = layout.machine_yaw
        sim.set_base_pose(
            "machine", layout.machine_pos, (0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2))
        )
        sim.set_base_pose("cup", layout.cup_pos, (0.0, 0.0, 0.0, 1.0))
        sim.reset_joint_states("machine", [0], [0.0])  # the button, at rest
        self.apply_spring()

    def apply_spring(self) -> None:
        """The button's return spring: a weak position motor towards travel 0 (set at every reset;
        PyBullet keeps a motor's settings, also through the stop's joint resets)."""
        self.sim.control_joints(
            "machine", [0], [0.0], [BUTTON_SPRING_FORCE], [0.2], position_gain=0.1
        )

    # ---------------------------------------------------------------- state
    @property
    def machine_rotation(self) -> NDArray[np.float64]:
        """Rotation (3, 3) of the machine frame: its x axis is the button's axis."""
        return self._rotation

    def machine_point(self, offset: NDArray[np.float64]) -> NDArray[np.float64]:
        """World position of a point given in the machine frame."""
        return self.layout.machine_pos + self.machine_rotation @ offset

    def cup_pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Cup base centre (3,) and quaternion (4,) xyzw."""
        return self.sim.get_base_pose("cup")

    def cup_tilt(self, quat: NDArray[np.float64]) -> float:
        """Angle (rad) between the cup's axis and the vertical."""
        x, y = float(quat[0]), float(quat[1])
        # z component of the rotated z axis: 1 - 2 (x^2 + y^2)
        return math.acos(min(max(1.0 - 2.0 * (x * x + y * y), -1.0), 1.0))

    def button_travel(self) -> float:
        """How far the button is pushed in (m, >= 0)."""
        return max(self.sim.joint_position("machine", 0), 0.0)

    def robot_cup_contacts(self) -> tuple[bool, bool, bool]:
        """Whether the left finger, the right finger and any link of the robot touch the cup
        (one contact query)."""
        links = self.sim.contact_links("panda", "cup")
        return FINGER_LINKS[0] in links, FINGER_LINKS[1] in links, bool(links)

    def robot_touches_cup(self) -> bool:
        return self.robot_cup_contacts()[2]

    def cup_on_table(self) -> bool:
        return self.sim.n_contacts("cup", "table") > 0

    def task_points(self) -> dict[str, NDArray[np.float64]]:
        """Points of the task in the world frame (see ``docs/CONTRACTS.md``)."""
        cup_pos, _ = self.cup_pose()
        rot = self.machine_rotation
        return {
            "cup_pos": cup_pos,
            "cup_radius": np.array(CUP_RADIUS),
            "cup_height": np.array(CUP_HEIGHT),
            "place_pos": self.place_pos.copy(),
            "place_tolerance": np.array(PLACE_TOLERANCE),
            "button_pos": self.button_pos.copy(),
            "button_axis": rot[:, 0].copy(),
            "button_travel_to_press": np.array(BUTTON_PRESS_TRAVEL),
        }
