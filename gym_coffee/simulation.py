"""The PyBullet wrapper: the only module of gym-coffee that imports ``pybullet``.

Each :class:`Simulation` owns one physics server (a ``BulletClient``), so two environments in one
process never share state. Bodies are addressed by name.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
from collections.abc import Callable, Sequence
from contextlib import suppress
from typing import Any

import numpy as np
import pybullet
import pybullet_data
from numpy.typing import ArrayLike, NDArray
from pybullet_utils import bullet_client

__all__ = ["ASSETS_DIR", "Simulation"]

#: Folder of the package's URDF assets (cup, coffee machine, table).
ASSETS_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "assets")
#: Simulated time (s) to which :meth:`Simulation.control_joints`' ``position_gain`` refers (the
#: default physics step).
GAIN_TIMESTEP = 1.0 / 250.0

logger = logging.getLogger(__name__)


class _Client(bullet_client.BulletClient):
    """A ``BulletClient`` that binds each PyBullet function to its server once, not at every call
    (``BulletClient.__getattr__`` inspects and wraps the function anew each time: ~20% of a
    step's CPU time went there)."""

    def __init__(self, connection_mode: int) -> None:
        # BulletClient's own __init__ passes ``options=""``, and PyBullet prints "argv[0]=" to
        # the C stdout for any options string: in every command's output, between its lines.
        self._shapes: dict[Any, Any] = {}
        self._pid = os.getpid()
        self._client = pybullet.connect(connection_mode)

    def __getattr__(self, name: str) -> Any:
        attribute = super().__getattr__(name)
        if name != "disconnect" and isinstance(attribute, functools.partial):
            self.__dict__[name] = attribute
        return attribute


def _float_list(values: ArrayLike) -> list[float]:
    """``values`` as a list of Python floats (a tuple of floats, e.g. a robot's constant limits,
    without the round trip through numpy)."""
    if isinstance(values, tuple) and all(type(v) is float for v in values):
        return list(values)
    return np.asarray(values, dtype=float).tolist()


def display_available() -> bool:
    """Whether a GUI can open (on Linux: an X11 or Wayland display is set)."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


class Simulation:
    """One PyBullet physics server with bodies addressed by name.

    Args:
        render_mode: ``"human"`` opens the PyBullet GUI; anything else runs headless (``DIRECT``).
        timestep: physics time step (s).
        n_substeps: physics steps per :meth:`step`.
        solver_iterations: constraint-solver iterations per physics step (at most).
        solver_residual: PyBullet's ``solverResidualThreshold``: the solver stops iterating once
            the square of the largest velocity correction (m/s, rad/s) of a sweep over the
            constraints is below it. PyBullet's default, 1e-7, runs every iteration here.
        static_bodies: bodies whose base link never moves while frames are drawn (e.g. the
            floor, a table): headless frames composite them from a backdrop (see :meth:`render`).
    """

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        timestep: float = 1.0 / 250.0,
        n_substeps: int = 10,
        solver_iterations: int = 50,
        solver_residual: float = 1e-7,
        static_bodies: Sequence[str] = (),
    ) -> None:
        self.render_mode = render_mode
        self.gui = render_mode == "human" and display_available()
        #: Load the bodies' visual shapes (meshes) only when something renders: loading the
        #: Panda's visual meshes took ~80% of a world rebuild (see docs/design-env.md).
        self.visual_shapes = render_mode is not None
        if render_mode == "human" and not self.gui:
            # PyBullet's GUI would hang or abort without a display (e.g. in check_env on CI).
            logger.warning("render_mode='human' but no display is available: running headless")
        self.client: bullet_client.BulletClient | None = None
        self.set_physics(  # applied to the server by connect()
            timestep=timestep,
            n_substeps=n_substeps,
            solver_iterations=solver_iterations,
            solver_residual=solver_residual,
        )
        self.bodies: dict[str, int] = {}
        #: Offset of each base's inertial frame from its URDF frame (None where they coincide).
        self._inertial_offset: dict[str, NDArray[np.float64] | None] = {}
        #: Upper stops enforced after every physics step: (body name, joint) -> position.
        self._joint_stops: dict[tuple[str, int], float] = {}
        #: Bodies whose base link stands still (see :meth:`render`); headless frames draw their
        #: base links once per pose into a backdrop and every frame only the rest.
        self.static_bodies = tuple(static_bodies) if not self.gui else ()
        #: How each body was loaded (path, flags), to load the static ones into the backdrop.
        self._sources: dict[str, tuple[str, int, bool]] = {}
        self._backdrop: _Backdrop | None = None
        #: PyBullet's id of the state kept by :meth:`save_state` (None: nothing kept) and the
        #: number of bodies the world had then.
        self._saved_state: int | None = None
        self._saved_bodies = 0
        self.connect()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` disconnected the physics server (see :meth:`connect`)."""
        return self.client is None

    def connect(self) -> None:
        """Start a physics server (an empty world) if there is none: at construction, and again
        after :meth:`close`."""
        if self.client is not None:
            return
        mode = pybullet.GUI if self.gui else pybullet.DIRECT
        self.client = _Client(connection_mode=mode)
        if self.gui:
            self.client.configureDebugVisualizer(pybullet.COV_ENABLE_GUI, 0)
        self.reset_world()

    # ------------------------------------------------------------------ world
    @property
    def dt(self) -> float:
        """Simulated time (s) per :meth:`step`."""
        return self.timestep * self.n_substeps

    @property
    def p(self) -> bullet_client.BulletClient:
        if self.client is None:
            raise RuntimeError("the simulation is closed")
        return self.client

    def reset_world(self) -> None:
        """Remove every body (and the state kept by :meth:`save_state`) and restore the physics
        parameters."""
        p = self.p
        if self._saved_state is not None:
            p.removeState(self._saved_state)
            self._saved_state = None
        p.resetSimulation()
        p.setGravity(0.0, 0.0, -9.81)
        self._apply_physics()
        self.bodies.clear()
        self._inertial_offset.clear()
        self._joint_stops.clear()
        self._sources.clear()
        if self._backdrop is not None:
            self._backdrop.hidden.clear()

    def _apply_physics(self) -> None:
        self.p.setPhysicsEngineParameter(
            fixedTimeStep=self.timestep,
            numSubSteps=0,
            numSolverIterations=self.solver_iterations,
            solverResidualThreshold=self.solver_residual,
            deterministicOverlappingPairs=1,
        )

    def set_physics(
        self,
        *,
        timestep: float | None = None,
        n_substeps: int | None = None,
        solver_iterations: int | None = None,
        solver_residual: float | None = None,
    ) -> None:
        """Change the physics settings of the constructor (those given) from the next
        :meth:`step` on (a closed simulation applies them when it connects)."""
        if timestep is not None:
            self.timestep = float(timestep)
        if n_substeps is not None:
            self.n_substeps = int(n_substeps)
        if solver_iterations is not None:
            self.solver_iterations = int(solver_iterations)
        if solver_residual is not None:
            self.solver_residual = float(solver_residual)
        if self.client is not None:
            self._apply_physics()

    def save_state(self) -> None:
        """Keep the world's current state in the physics server (PyBullet's ``saveState``: the
        bodies' positions and velocities and the contact points with their solver impulses), for
        :meth:`restore_state`; replaces a state kept before."""
        p = self.p
        if self._saved_state is not None:
            p.removeState(self._saved_state)
        self._saved_state = p.saveState()
        self._saved_bodies = p.getNumBodies()

    def restore_state(self) -> bool:
        """Put the world back into the state kept by :meth:`save_state` (~0.5 ms); ``False``
        (and nothing changed) if no state was kept since the last :meth:`reset_world`, or if the
        world no longer has the bodies it had then (PyBullet restores a state only into the same
        bodies).

        Restored right after loading and followed by :meth:`clear_contact_caches`, the next
        episode equals one in a freshly loaded world bit for bit, whatever ran before (tested
        with contact-rich episodes), where re-posing the bodies alone does not. What is not part
        of a body's state is kept (e.g. ``changeDynamics``, colours, motor settings).
        """
        p = self.p
        if self._saved_state is None or p.getNumBodies() != self._saved_bodies:
            return False
        try:
            p.restoreState(stateId=self._saved_state)
        except pybullet.error:
            return False
        return True

    def clear_contact_caches(self, names: Sequence[str]) -> None:
        """Forget the contact state of the bodies ``names`` (and remove every user constraint).

        Re-sets each link's collision filter to PyBullet's default, which takes the link out of
        the broadphase and puts it back: its overlapping pairs and contact manifolds (points,
        warm-starting impulses) are dropped at once, and the colliders are re-added in a fixed
        order. Call it at every reset, in the same order, the first one included: a reused world
        then steps exactly (bit for bit) like a freshly loaded one. (Moving the bodies away and
        running ``performCollisionDetection`` is not enough: the broadphase removes stale pairs a
        few at a time.)
        """
        p = self.p
        for i in reversed(range(p.getNumConstraints())):
            p.removeConstraint(p.getConstraintUniqueId(i))
        for name in names:
            body = self.bodies[name]
            fixed_base = p.getDynamicsInfo(body, -1)[0] == 0.0
            for link in range(-1, p.getNumJoints(body)):
                static = link == -1 and fixed_base
                # PyBullet's defaults: btBroadphaseProxy::DefaultFilter / StaticFilter.
                group, mask = (2, -1 ^ 2) if static else (1, -1)
                p.setCollisionFilterGroupMask(body, link, group, mask)

    def set_joint_stop(self, name: str, joint: int, upper: float) -> None:
        """A hard upper stop of one joint: after every physics step of :meth:`step`, a position
        beyond ``upper`` is set back to it, at rest (until the world is reset)."""
        self._joint_stops[(name, int(joint))] = float(upper)

    def step(self, after_substep: Callable[[], None] | None = None) -> None:
        """Advance the physics by ``n_substeps`` physics steps; after each, enforce the joint stops
        (:meth:`set_joint_stop`) and call ``after_substep``."""
        p = self.p
        step = p.stepSimulation
        stops = [(self.bodies[n], j, upper) for (n, j), upper in self._joint_stops.items()]
        if not stops and after_substep is None:
            for _ in range(self.n_substeps):
                step()
            return
        get, reset = p.getJointState, p.resetJointState
        for _ in range(self.n_substeps):
            step()
            for body, joint, upper in stops:  # ~1 us each, bound once per step
                if get(body, joint)[0] > upper:
                    reset(body, joint, upper, 0.0)
            if after_substep is not None:
                after_substep()

    def close(self) -> None:
        """Disconnect from the physics server (safe to call more than once)."""
        if self.client is not None:
            with suppress(Exception):
                self.client.disconnect()
            self.client = None
        self._saved_state = None  # it lived in the server
        if self._backdrop is not None:
            self._backdrop.close()
            self._backdrop = None
        self.bodies.clear()
        self._inertial_offset.clear()
        self._joint_stops.clear()
        self._sources.clear()

    def __del__(self) -> None:
        self.close()

    # ------------------------------------------------------------------ bodies
    def load_urdf(
        self,
        name: str,
        file_name: str,
        base_position: ArrayLike = (0.0, 0.0, 0.0),
        base_orientation: ArrayLike = (0.0, 0.0, 0.0, 1.0),
        *,
        use_fixed_base: bool = False,
        package_asset: bool = True,
        self_collision: bool = False,
        visual_shapes: bool = True,
    ) -> int:
        """Load a URDF as body ``name``; ``package_asset`` picks gym-coffee's assets over
        pybullet_data's; ``self_collision`` lets the body's links collide with each other, a link
        with its parent included. Visual shapes are loaded only if :attr:`visual_shapes` and
        ``visual_shapes``; without them PyBullet draws the collision shapes (the physics is the
        same either way)."""
        path = os.path.join(ASSETS_DIR if package_asset else pybullet_data.getDataPath(), file_name)
        flags = pybullet.URDF_USE_INERTIA_FROM_FILE | pybullet.URDF_ENABLE_CACHED_GRAPHICS_SHAPES
        if self_collision:
            flags |= (
                pybullet.URDF_USE_SELF_COLLISION | pybullet.URDF_USE_SELF_COLLISION_INCLUDE_PARENT
            )
        if not (self.visual_shapes and visual_shapes):
            flags |= pybullet.URDF_IGNORE_VISUAL_SHAPES
        body = self.p.loadURDF(
            path,
            basePosition=[float(v) for v in np.asarray(base_position, dtype=float)],
            baseOrientation=[float(v) for v in np.asarray(base_orientation, dtype=float)],
            useFixedBase=use_fixed_base,
            flags=flags,
        )
        self.bodies[name] = body
        self._sources[name] = (path, flags, bool(use_fixed_base))
        if self._backdrop is not None:
            self._backdrop.hidden.discard(name)
        # PyBullet reports and resets a base by its inertial frame; keep the offset to the URDF
        # frame.
        offset = np.array(self.p.getDynamicsInfo(body, -1)[3])
        self._inertial_offset[name] = offset if offset.any() else None
        return body

    def set_base_pose(self, name: str, position: ArrayLike, orientation: ArrayLike) -> None:
        """Put the base's URDF link frame at ``position`` with quaternion ``orientation`` (xyzw),
        at rest."""
        position = np.asarray(position, dtype=float)
        orientation = [float(v) for v in np.asarray(orientation, dtype=float)]
        offset = self._inertial_offset[name]
        if offset is not None:
            rot = np.array(self.p.getMatrixFromQuaternion(orientation)).reshape(3, 3)
            position = position + rot @ offset
        self.p.resetBasePositionAndOrientation(self.bodies[name], position.tolist(), orientation)
        self.p.resetBaseVelocity(self.bodies[name], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])

    def get_base_pose(self, name: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Position (3,) and quaternion (4,) xyzw of the base's URDF link frame."""
        p = self.p
        pos, quat = p.getBasePositionAndOrientation(self.bodies[name])
        offset = self._inertial_offset[name]
        if offset is None:
            return np.array(pos), np.array(quat)
        rot = np.array(p.getMatrixFromQuaternion(quat)).reshape(3, 3)
        return np.array(pos) - rot @ offset, np.array(quat)

    def get_base_velocity(self, name: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        lin, ang = self.p.getBaseVelocity(self.bodies[name])
        return np.array(lin), np.array(ang)

    def get_link_pose(
        self, name: str, link: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World position (3,) and quaternion (4,) of a link's URDF frame."""
        state = self.p.getLinkState(self.bodies[name], link, computeForwardKinematics=True)
        return np.array(state[4]), np.array(state[5])

    def get_joint_states(
        self, name: str, joints: Sequence[int]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Positions and velocities of the given joints (one query)."""
        joints = joints if isinstance(joints, (list, tuple)) else list(joints)
        states = self.p.getJointStates(self.bodies[name], joints)
        return np.array([s[0] for s in states]), np.array([s[1] for s in states])

    def joint_position(self, name: str, joint: int) -> float:
        """Position of one joint."""
        return float(self.p.getJointState(self.bodies[name], joint)[0])

    def reset_joint_states(self, name: str, joints: Sequence[int], positions: ArrayLike) -> None:
        body = self.bodies[name]
        for joint, value in zip(joints, np.asarray(positions, dtype=float), strict=True):
            self.p.resetJointState(body, joint, float(value), 0.0)

    def control_joints(
        self,
        name: str,
        joints: Sequence[int],
        targets: ArrayLike,
        forces: ArrayLike,
        max_velocities: ArrayLike | None = None,
        position_gain: float = 0.1,
    ) -> None:
        """Position control of the given joints with force and (optionally) velocity limits.

        ``position_gain`` is the fraction of the position error the controller corrects per
        :data:`GAIN_TIMESTEP` of simulated time (when no force or velocity limit binds). PyBullet's
        gain acts per physics step, so it is converted to ``timestep``: the controller's time
        constant, and the arm's response per control step, do not depend on the physics step.
        """
        body = self.bodies[name]
        control = self.p.setJointMotorControl2
        mode = pybullet.POSITION_CONTROL
        target_list: list[float] = np.asarray(targets, dtype=float).tolist()
        force_list: list[float] = _float_list(forces)
        gain = float(position_gain)
        if self.timestep != GAIN_TIMESTEP:
            gain = 1.0 - (1.0 - gain) ** (self.timestep / GAIN_TIMESTEP)
        if max_velocities is None:
            for j, t, f in zip(joints, target_list, force_list, strict=True):
                control(body, j, mode, targetPosition=t, force=f, positionGain=gain)
        else:
            vel: list[float] = _float_list(max_velocities)
            for j, t, f, v in zip(joints, target_list, force_list, vel, strict=True):
                control(body, j, mode, targetPosition=t, force=f, maxVelocity=v, positionGain=gain)

    def set_dynamics(self, name: str, link: int, **kwargs: float) -> None:
        """``changeDynamics`` of one link (keyword names as in PyBullet: lateralFriction, ...)."""
        self.p.changeDynamics(self.bodies[name], link, **kwargs)

    def set_color(self, name: str, link: int, rgba: Sequence[float]) -> None:
        """Colour of one link's shapes as drawn (``changeVisualShape``); a no-op unless
        :attr:`visual_shapes`."""
        if self.visual_shapes:
            self.p.changeVisualShape(self.bodies[name], link, rgbaColor=[float(v) for v in rgba])

    def n_contacts(
        self, name_a: str, name_b: str, link_a: int | None = None, link_b: int | None = None
    ) -> int:
        """Number of contact points between two bodies (optionally restricted to links)."""
        kwargs = {}
        if link_a is not None:
            kwargs["linkIndexA"] = link_a
        if link_b is not None:
            kwargs["linkIndexB"] = link_b
        return len(self.p.getContactPoints(self.bodies[name_a], self.bodies[name_b], **kwargs))

    def contact_links(self, name_a: str, name_b: str) -> set[int]:
        """Links of body ``name_a`` that touch body ``name_b``."""
        return {pt[3] for pt in self.p.getContactPoints(self.bodies[name_a], self.bodies[name_b])}

    # ------------------------------------------------------------------ rendering
    def render(
        self,
        width: int,
        height: int,
        target: ArrayLike,
        distance: float,
        yaw: float,
        pitch: float,
        fov: float = 45.0,
        shadows: bool = False,
    ) -> NDArray[np.uint8]:
        """RGB image (height, width, 3) from a camera looking at ``target`` (TinyRenderer,
        headless). ``shadows`` costs about twice the time (TinyRenderer draws the scene twice).

        Headless, without shadows and with :attr:`static_bodies`, a frame is composited: the
        static bodies' base links are drawn once per camera and pose into a backdrop (colour and
        depth, in a second physics server holding only them), and each frame draws the rest of
        the scene (they are hidden in this server) and takes, pixel by pixel, the nearer of the
        two. The pixels are those of drawing everything at once (TinyRenderer shades each
        triangle on its own when there are no shadows), in ~10 instead of ~36 ms (320x240).
        """
        camera = (
            int(width),
            int(height),
            tuple(float(v) for v in np.asarray(target, dtype=float)),
            float(distance),
            float(yaw),
            float(pitch),
            float(fov),
        )
        if self.static_bodies and not shadows and not self.gui:
            return self._composite(camera)
        return self._draw(self.p, camera, shadows, self.gui)[0]

    @staticmethod
    def _draw(
        p: bullet_client.BulletClient,
        camera: tuple[Any, ...],
        shadows: bool = False,
        gui: bool = False,
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """Colour (height, width, 3) and depth buffer (height, width) of one camera image."""
        width, height, target, distance, yaw, pitch, fov = camera
        view = p.computeViewMatrixFromYawPitchRoll(
            cameraTargetPosition=list(target),
            distance=distance,
            yaw=yaw,
            pitch=pitch,
            roll=0.0,
            upAxisIndex=2,
        )
        proj = p.computeProjectionMatrixFOV(
            fov=fov, aspect=width / height, nearVal=0.05, farVal=5.0
        )
        renderer = pybullet.ER_BULLET_HARDWARE_OPENGL if gui else pybullet.ER_TINY_RENDERER
        _, _, rgba, depth, _ = p.getCameraImage(
            width=width,
            height=height,
            viewMatrix=view,
            projectionMatrix=proj,
            shadow=int(bool(shadows)),
            lightDirection=[0.6, -0.4, 1.0],
            renderer=renderer,
            flags=pybullet.ER_NO_SEGMENTATION_MASK,  # unused; the same pixels, ~3% less time
        )
        rgba = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)
        depth = np.asarray(depth, dtype=np.float32).reshape(height, width)
        return np.ascontiguousarray(rgba[..., :3]), depth

    def _composite(self, camera: tuple[Any, ...]) -> NDArray[np.uint8]:
        """A frame from the backdrop of :attr:`static_bodies` and the rest drawn now."""
        p = self.p
        if self._backdrop is None:
            self._backdrop = _Backdrop()
        backdrop = self._backdrop
        static = [n for n in self.static_bodies if n in self.bodies]
        poses = tuple(p.getBasePositionAndOrientation(self.bodies[n]) for n in static)
        # Fixed bases can flicker in the last bit (a quaternion renormalised every other physics
        # step, and -0.0 for 0.0): the backdrop is redrawn when a pose moves by more than 1e-9.
        key = (
            camera,
            tuple(static),
            tuple((np.round(np.concatenate(pq), 9) + 0.0).tobytes() for pq in poses),
        )
        if backdrop.key != key:
            for name, pose in zip(static, poses, strict=True):
                backdrop.place(name, self._sources[name], pose)
            for name in set(backdrop.bodies) - set(static):
                backdrop.place(name, None, None)
            backdrop.image = self._draw(backdrop.client, camera)
            backdrop.key = key
        for name in static:  # hidden here once per load (their look lives in the backdrop)
            if name not in backdrop.hidden:
                p.changeVisualShape(self.bodies[name], -1, rgbaColor=[1.0, 1.0, 1.0, 0.0])
                backdrop.hidden.add(name)
        rgb, depth = self._draw(p, camera)
        assert backdrop.image is not None
        back_rgb, back_depth = backdrop.image
        return np.where((depth < back_depth)[..., None], rgb, back_rgb)

    def reset_debug_camera(
        self, target: ArrayLike, distance: float, yaw: float, pitch: float
    ) -> None:
        if self.gui:
            self.p.resetDebugVisualizerCamera(
                cameraDistance=float(distance),
                cameraYaw=float(yaw),
                cameraPitch=float(pitch),
                cameraTargetPosition=[float(v) for v in np.asarray(target, dtype=float)],
            )


class _Backdrop:
    """A second (headless) physics server holding only the static bodies' base links, and its
    last image: colour and depth (see :meth:`Simulation.render`). Nothing in it is simulated."""

    def __init__(self) -> None:
        self.client = _Client(connection_mode=pybullet.DIRECT)
        #: name -> (body id here, its source)
        self.bodies: dict[str, tuple[int, tuple[str, int, bool]]] = {}
        #: Names whose base link is hidden in the main server (until it loads them again).
        self.hidden: set[str] = set()
        self.key: Any = None
        self.image: tuple[NDArray[np.uint8], NDArray[np.float32]] | None = None

    def place(
        self,
        name: str,
        source: tuple[str, int, bool] | None,
        pose: tuple[Sequence[float], Sequence[float]] | None,
    ) -> None:
        """Put body ``name`` (loaded from ``source``: path, flags, fixed base) at the base pose
        ``pose`` (as ``getBasePositionAndOrientation`` reports it); ``None``: take it out."""
        p = self.client
        if name in self.bodies and (source is None or self.bodies[name][1] != source):
            p.removeBody(self.bodies.pop(name)[0])
        if source is None or pose is None:
            return
        if name not in self.bodies:
            path, flags, fixed = source
            body = p.loadURDF(path, useFixedBase=fixed, flags=flags)
            for link in range(p.getNumJoints(body)):  # moving links are drawn every frame
                p.changeVisualShape(body, link, rgbaColor=[1.0, 1.0, 1.0, 0.0])
            self.bodies[name] = (body, source)
        p.resetBasePositionAndOrientation(self.bodies[name][0], pose[0], pose[1])

    def close(self) -> None:
        with suppress(Exception):
            self.client.disconnect()
