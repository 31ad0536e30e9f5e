"""Teaching by hand: record demonstrations by teleoperating the arm's end effector.

The recorder (:func:`record_teleop`) drives the env in an end-effector action mode
(``action_type="ee_rot"``: Cartesian and rotation deltas plus the gripper; or ``"ee"``) with
commands from an input device and writes the same
:class:`~gym_coffee.demonstrations.DemonstrationSet` as the scripted teacher (``actions`` in the
mode used, ``metadata["teleop"]`` says how they were made). Every episode ends with a decision:
keep it or discard it.

Input devices share one small protocol, :class:`InputDevice`: ``poll(obs, info)`` returns a
:class:`TeleopCommand`. Implementations:

* :class:`KeyboardInput` -- keys in the PyBullet GUI window (``getKeyboardEvents`` of the env's
  physics client); :data:`KEYBOARD_HELP` lists them, and the window shows them.
* :class:`SpaceMouseInput` -- a 3Dconnexion SpaceMouse through ``pyspacemouse`` (the optional
  ``teleop`` extra), with the keyboard for keep / discard / quit.
* :class:`ScriptedInput` -- replays a list of commands (tests, scripted corrections).
* :class:`WaypointInput` -- a scripted operator that steers towards the waypoints the scripted
  teacher plans from ``env.unwrapped.task_points()``: it completes the task headless, so the whole
  path (device -> end-effector actions -> file -> ``fit``) is tested without a person.

Mouse dragging of the end effector is not offered: PyBullet's GUI uses the mouse for the camera and
for its own force-based picking, and a hand moved by such forces would not be described by the
recorded actions (replaying them would not reproduce the episode).

Example (GUI)::

    import gymnasium as gym, gym_coffee
    from gym_coffee.teleop import KeyboardInput, record_teleop
    env = gym.make(gym_coffee.ENV_ID, render_mode="human", action_type="ee_rot",
                   max_episode_steps=3000)
    demos = record_teleop(env, KeyboardInput(), n=3, seed=0)
    demos.save("my_demos.npz")
"""

from __future__ import annotations

import importlib
import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gym_coffee import STAGES
from gym_coffee.demonstrations import (
    Demonstration,
    DemonstrationSet,
    _demonstration_from_steps,
    _env_identity,
    _versions,
)

__all__ = [
    "KEYBOARD_HELP",
    "TELEOP_ACTION_TYPES",
    "InputDevice",
    "KeyboardInput",
    "ScriptedInput",
    "SpaceMouseInput",
    "TeleopCommand",
    "WaypointInput",
    "command_to_action",
    "record_teleop",
]

TELEOP_ACTION_TYPES = ("ee_rot", "ee")
"""Action modes teleoperation drives (``ee_rot`` can turn the hand for the side grasp the task
needs; ``ee`` keeps the hand pointing down)."""
EXTRA = "teleop"
"""The optional dependency group that provides ``pyspacemouse``."""


def _unit_vector(name: str, value: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return np.clip(arr, -1.0, 1.0)


@dataclass(frozen=True)
class TeleopCommand:
    """One poll of an input device.

    Attributes:
        delta_xyz: translation of the grasp point, each in [-1, 1] (times
            ``gym_coffee.robot.MAX_EE_STEP`` metres per control step), world frame.
        delta_rpy: rotation of the hand about the world x, y, z axes, each in [-1, 1] (times
            ``MAX_EE_ROT_STEP`` rad per step); ignored in the ``"ee"`` mode.
        gripper: the gripper command in [-1, 1] (-1 closed, 1 open), or ``None``: unchanged.
        keep: end the episode now and keep it.
        discard: end the episode now and throw it away.
        quit: stop recording (the episode in progress is discarded; kept ones are returned).
    """

    delta_xyz: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    delta_rpy: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    gripper: float | None = None
    keep: bool = False
    discard: bool = False
    quit: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "delta_xyz", _unit_vector("delta_xyz", self.delta_xyz))
        object.__setattr__(self, "delta_rpy", _unit_vector("delta_rpy", self.delta_rpy))
        if self.gripper is not None:
            g = float(self.gripper)
            if not math.isfinite(g):
                raise ValueError(f"gripper must be finite or None, got {self.gripper!r}")
            object.__setattr__(self, "gripper", min(1.0, max(-1.0, g)))
        if sum((self.keep, self.discard, self.quit)) > 1:
            raise ValueError("a command can keep, discard or quit, not several at once")

    @property
    def ends_episode(self) -> bool:
        """Whether the command ends the episode (keep, discard or quit)."""
        return self.keep or self.discard or self.quit


@runtime_checkable
class InputDevice(Protocol):
    """What the recorder needs from an input device."""

    name: str
    """Short name stored in the file's metadata (``"keyboard"``, ``"spacemouse"``, ...)."""
    realtime: bool
    """Whether a person is in the loop: the recorder then paces the steps to the control rate
    and waits for the keep/discard decision."""

    def start_episode(self, env: Any, obs: NDArray[np.float32]) -> None:
        """Called after each ``reset`` with the env and its first observation."""

    def poll(self, obs: NDArray[np.float32], info: dict[str, Any]) -> TeleopCommand:
        """The command for the current observation ``obs`` and ``info`` (the env's last info:
        stage flags, ``is_success``); also asked for the keep/discard decision after the env
        ended the episode."""

    def close(self) -> None:
        """Release the device."""


def command_to_action(
    command: TeleopCommand, action_type: str, gripper: float
) -> NDArray[np.float32]:
    """The env action of ``command`` for ``action_type`` (``gripper``: the current command)."""
    grip = np.array([gripper])
    if action_type == "ee":
        return np.concatenate([command.delta_xyz, grip]).astype(np.float32)
    if action_type == "ee_rot":
        return np.concatenate([command.delta_xyz, command.delta_rpy, grip]).astype(np.float32)
    raise ValueError(f"action_type must be one of {TELEOP_ACTION_TYPES}, got {action_type!r}")


# ------------------------------------------------------------------------------------------------
# Devices
# ------------------------------------------------------------------------------------------------


class ScriptedInput:
    """Replays ``commands`` one per poll; then returns ``then`` (default: keep the episode).

    Args:
        commands: the commands of one episode, or a list of such lists (one per episode).
        then: the command after the script of an episode is used up.
    """

    name = "scripted"
    realtime = False

    def __init__(
        self,
        commands: Sequence[TeleopCommand] | Sequence[Sequence[TeleopCommand]],
        then: TeleopCommand | None = None,
    ) -> None:
        items: list[Any] = list(commands)
        episodes = items if items and not isinstance(items[0], TeleopCommand) else [items]
        self.episodes: list[list[TeleopCommand]] = [list(e) for e in episodes]
        for e in self.episodes:
            for c in e:
                if not isinstance(c, TeleopCommand):
                    raise TypeError(f"expected TeleopCommand items, got {type(c).__name__}")
        self.then = then if then is not None else TeleopCommand(keep=True)
        self._episode = -1
        self._i = 0

    def start_episode(self, env: Any, obs: NDArray[np.float32]) -> None:
        self._episode += 1
        self._i = 0

    def poll(self, obs: NDArray[np.float32], info: dict[str, Any]) -> TeleopCommand:
        script = self.episodes[min(self._episode, len(self.episodes) - 1)]
        if self._i < len(script):
            self._i += 1
            return script[self._i - 1]
        return self.then

    def close(self) -> None:
        pass


class WaypointInput:
    """A scripted operator: steers the hand towards the scripted teacher's waypoints.

    At each episode start it plans with :class:`gym_coffee.teacher.ScriptedTeacher` (from
    ``env.unwrapped.task_points()``; ``variation`` as in the teacher) and then, like a person
    with a 6-axis device, commands the hand towards the planned pose of the next control step:
    the position error of the measured grasp point and the rotation between the commanded and the
    planned hand orientation, each scaled to the step limits and clipped to [-1, 1]. When the plan
    is over it asks to keep the episode (a person would look at the success overlay).

    Args:
        variation: the teacher's human-like variation (0: the nominal plan).
        gain: scale of the position command (1: reach the target in one step when possible).
        seed: seed of the variation (default: the layout seed passed by the recorder).
    """

    name = "waypoints"
    realtime = False

    def __init__(self, variation: float = 0.0, gain: float = 1.0, seed: int | None = None) -> None:
        self.variation = float(variation)
        self.gain = float(gain)
        self.seed = seed
        self.layout_seed: int | None = None
        self._teacher: Any = None
        self._rotation = np.eye(3)
        self._kinematics: Any = None

    def start_episode(self, env: Any, obs: NDArray[np.float32]) -> None:
        from gym_coffee.demonstrations import teacher_rng
        from gym_coffee.teacher import ScriptedTeacher

        seed = self.seed if self.seed is not None else (self.layout_seed or 0)
        self._teacher = ScriptedTeacher(env, rng=teacher_rng(seed), variation=self.variation)
        self._teacher.reset(np.asarray(obs, dtype=np.float64))
        self._kinematics = env.unwrapped.kinematics
        q = self._joint_pos(obs)
        self._rotation = self._kinematics.forward_pose(q)[1]  # the env's commanded orientation

    @staticmethod
    def _joint_pos(obs: NDArray[Any]) -> NDArray[np.float64]:
        from gym_coffee.env import obs_part

        return np.asarray(obs_part(np.asarray(obs, dtype=np.float64), "joint_pos"))

    def poll(self, obs: NDArray[np.float32], info: dict[str, Any]) -> TeleopCommand:
        from scipy.spatial.transform import Rotation

        from gym_coffee.env import CONTROL_DT, obs_part
        from gym_coffee.robot import GRIPPER_MAX_OPENING, MAX_EE_ROT_STEP, MAX_EE_STEP

        if self._teacher is None:
            raise RuntimeError("start_episode was not called")
        obs64 = np.asarray(obs, dtype=np.float64)
        t = float(obs_part(obs64, "time")[0])
        if info.get("is_success") or t > self._teacher.duration + 0.5:
            return TeleopCommand(keep=True)
        pos_d, rot_d, grip = self._teacher.target(t + CONTROL_DT)
        ee = obs_part(obs64, "ee_pos")
        delta_xyz = np.clip(self.gain * (pos_d - ee) / MAX_EE_STEP, -1.0, 1.0)
        turn = Rotation.from_matrix(rot_d @ self._rotation.T).as_euler("xyz")
        delta_rpy = np.clip(turn / MAX_EE_ROT_STEP, -1.0, 1.0)
        # Mirror the env's integration of the commanded orientation (float32 actions).
        applied = delta_rpy.astype(np.float32).astype(np.float64) * MAX_EE_ROT_STEP
        self._rotation = Rotation.from_euler("xyz", applied).as_matrix() @ self._rotation
        return TeleopCommand(
            delta_xyz=delta_xyz,
            delta_rpy=delta_rpy,
            gripper=2.0 * grip / GRIPPER_MAX_OPENING - 1.0,
        )

    def close(self) -> None:
        self._teacher = None


KEYBOARD_HELP = (
    ("arrows", "move the hand: up/down = +x/-x, left/right = +y/-y"),
    ("r / f", "move up / down (z)"),
    ("u o / i k / j l", "roll / pitch / yaw (ee_rot)"),
    ("space", "open / close the gripper"),
    ("[ / ]", "slower / faster"),
    ("enter", "end the episode and keep it"),
    ("backspace", "end the episode and discard it"),
    ("escape / q", "quit (kept episodes are saved)"),
    ("h", "hide / show this help"),
)
"""Keys of :class:`KeyboardInput` (shown in the GUI window)."""

_SPEEDS = (0.1, 0.25, 0.5, 1.0)


class KeyboardInput:
    """Keys in the PyBullet GUI window (see :data:`KEYBOARD_HELP`).

    Motion keys act while held; space toggles the gripper; enter / backspace / escape are read
    once per press. PyBullet's own keyboard shortcuts (wireframe, shadows, ...) are switched off
    while recording so that the keys mean only what the help says.

    Args:
        speed: initial fraction of the largest step (``[`` and ``]`` change it).
    """

    name = "keyboard"
    realtime = True

    def __init__(self, speed: float = 0.5) -> None:
        self.speed = float(speed)
        self.gripper = 1.0
        self.show_help = True
        self._client: Any = None

    def start_episode(self, env: Any, obs: NDArray[np.float32]) -> None:
        self._client = env.unwrapped.sim.client
        self._client.configureDebugVisualizer(self._client.COV_ENABLE_KEYBOARD_SHORTCUTS, 0)
        self.gripper = 1.0

    def _key_codes(self) -> dict[str, int]:
        c = self._client
        return {
            "up": c.B3G_UP_ARROW,
            "down": c.B3G_DOWN_ARROW,
            "left": c.B3G_LEFT_ARROW,
            "right": c.B3G_RIGHT_ARROW,
            "enter": c.B3G_RETURN,
            "backspace": c.B3G_BACKSPACE,
            "escape": 27,
        }

    def poll(self, obs: NDArray[np.float32], info: dict[str, Any]) -> TeleopCommand:
        if self._client is None:
            raise RuntimeError("start_episode was not called")
        events: dict[int, int] = self._client.getKeyboardEvents()
        down = self._client.KEY_IS_DOWN
        pressed = self._client.KEY_WAS_TRIGGERED
        return keyboard_command(events, self._key_codes(), down, pressed, self)

    def close(self) -> None:
        self._client = None


def keyboard_command(
    events: dict[int, int], codes: dict[str, int], down: int, pressed: int, state: Any
) -> TeleopCommand:
    """The command for one poll of PyBullet keyboard ``events`` (key code -> flags); ``state``
    holds ``speed``, ``gripper`` and ``show_help`` and is updated by toggles."""

    def code(key: str) -> int:
        return codes[key] if key in codes else ord(key)

    def held(key: str) -> float:
        return 1.0 if events.get(code(key), 0) & down else 0.0

    def hit(key: str) -> bool:
        return bool(events.get(code(key), 0) & pressed)

    if hit("[") or hit("]"):
        i = int(np.argmin([abs(s - state.speed) for s in _SPEEDS]))
        i = max(0, i - 1) if hit("[") else min(len(_SPEEDS) - 1, i + 1)
        state.speed = _SPEEDS[i]
    if hit(" "):
        state.gripper = -state.gripper
    if hit("h"):
        state.show_help = not state.show_help
    xyz = np.array([held("up") - held("down"), held("left") - held("right"), held("r") - held("f")])
    rpy = np.array([held("u") - held("o"), held("i") - held("k"), held("j") - held("l")])
    return TeleopCommand(
        delta_xyz=state.speed * xyz,
        delta_rpy=state.speed * rpy,
        gripper=state.gripper,
        keep=hit("enter"),
        discard=hit("backspace") and not hit("enter"),
        quit=(hit("escape") or hit("q")) and not (hit("enter") or hit("backspace")),
    )


class SpaceMouseInput:
    """A 3Dconnexion SpaceMouse (``pyspacemouse``, the ``teleop`` extra) for the hand, with the
    keyboard for the gripper (space, or the device's first button), keep / discard / quit.

    Args:
        speed: scale of the device's deflection (each axis in [-1, 1]).
        deadzone: deflections below this are read as 0.
    """

    name = "spacemouse"
    realtime = True

    def __init__(self, speed: float = 0.5, deadzone: float = 0.05) -> None:
        try:
            self._mouse = importlib.import_module("pyspacemouse")
        except ImportError as exc:
            raise ImportError(
                "the SpaceMouse needs the optional package 'pyspacemouse': "
                f'pip install "gym-coffee[{EXTRA}]"'
            ) from exc
        if not self._mouse.open():
            raise RuntimeError("no SpaceMouse found (pyspacemouse.open() failed)")
        self.speed = float(speed)
        self.deadzone = float(deadzone)
        self.keyboard = KeyboardInput(speed=speed)
        self._button_was = False

    @property
    def show_help(self) -> bool:
        """Whether the overlay shows the keys (``h`` toggles it)."""
        return bool(self.keyboard.show_help)

    def start_episode(self, env: Any, obs: NDArray[np.float32]) -> None:
        self.keyboard.start_episode(env, obs)

    def poll(self, obs: NDArray[np.float32], info: dict[str, Any]) -> TeleopCommand:
        keys = self.keyboard.poll(obs, info)
        state = self._mouse.read()
        buttons = list(getattr(state, "buttons", None) or getattr(state, "button", None) or [])
        button = bool(buttons and buttons[0])
        if button and not self._button_was:
            self.keyboard.gripper = -self.keyboard.gripper
        self._button_was = button

        def axes(*values: float) -> NDArray[np.float64]:
            v = np.array(values, dtype=np.float64)
            return np.where(np.abs(v) < self.deadzone, 0.0, v) * self.speed

        return TeleopCommand(
            delta_xyz=axes(state.x, state.y, state.z) + keys.delta_xyz,
            delta_rpy=axes(state.roll, state.pitch, state.yaw) + keys.delta_rpy,
            gripper=self.keyboard.gripper,
            keep=keys.keep,
            discard=keys.discard,
            quit=keys.quit,
        )

    def close(self) -> None:
        self.keyboard.close()
        close = getattr(self._mouse, "close", None)
        if callable(close):
            close()


# ------------------------------------------------------------------------------------------------
# Overlay (GUI only)
# ------------------------------------------------------------------------------------------------


class _Overlay:
    """Help text and a stage/success line in the PyBullet GUI (nothing in DIRECT mode).

    PyBullet has no screen-space text: the lines are placed in the world, in the upper left of
    the GUI camera's view (from ``getDebugVisualizerCamera``), and replaced only when they
    change."""

    LINE = 0.045  # line spacing at the camera distance 1.5 m (scaled with the distance)

    def __init__(self, env: Any, device: Any) -> None:
        sim = env.unwrapped.sim
        self.client = sim.client
        self.enabled = bool(getattr(sim, "gui", False))
        self.device = device
        self._ids: dict[str, int] = {}
        self._shown: dict[str, str] = {}
        self._origin = np.zeros(3)
        self._right = np.array([1.0, 0.0, 0.0])
        self._up = np.array([0.0, 0.0, 1.0])
        self._scale = 1.0

    def reset(self) -> None:
        """Remove the items drawn so far (an exact reset restores the bodies' state and keeps
        debug items; removing an id a new physics server no longer has is a no-op) and anchor
        to the camera."""
        drawn, self._ids, self._shown = self._ids, {}, {}
        if not self.enabled:
            return
        for item in drawn.values():
            if item >= 0:
                self.client.removeUserDebugItem(item)
        cam = self.client.getDebugVisualizerCamera()
        horizontal, vertical = np.asarray(cam[6], float), np.asarray(cam[7], float)
        if np.linalg.norm(horizontal) > 0 and np.linalg.norm(vertical) > 0:
            self._right = horizontal / np.linalg.norm(horizontal)
            self._up = vertical / np.linalg.norm(vertical)
        self._scale = float(cam[10]) / 1.5 if cam[10] else 1.0
        self._origin = np.asarray(cam[11], float)

    def _position(self, row: int) -> list[float]:
        s = self._scale
        point = self._origin + s * (0.6 - self.LINE * row) * self._up - s * 0.8 * self._right
        return [float(v) for v in point]

    def _text(self, key: str, row: int, text: str, color: Sequence[float]) -> None:
        if self._shown.get(key) == text:
            return
        kwargs: dict[str, Any] = {"textColorRGB": list(color), "textSize": 1.1}
        if key in self._ids and self._ids[key] >= 0:
            kwargs["replaceItemUniqueId"] = self._ids[key]
        self._ids[key] = self.client.addUserDebugText(text, self._position(row), **kwargs)
        self._shown[key] = text

    def draw(self, info: dict[str, Any], status: str) -> None:
        if not self.enabled:
            return
        flags = "   ".join(f"{'[x]' if info.get(s) else '[ ]'} {s}" for s in STAGES)
        success = "   SUCCESS" if info.get("is_success") else ""
        self._text("stages", 0, flags + success, (0.05, 0.45, 0.05))
        self._text("status", 1, status, (0.1, 0.1, 0.5))
        show = getattr(self.device, "show_help", False)
        for i, (keys, what) in enumerate(KEYBOARD_HELP):
            self._text(f"help{i}", 3 + i, f"{keys}: {what}" if show else "", (0.2, 0.2, 0.2))


# ------------------------------------------------------------------------------------------------
# Recorder
# ------------------------------------------------------------------------------------------------


def record_teleop(
    env: Any,
    device: InputDevice,
    n: int,
    seed: int = 0,
    *,
    max_attempts: int | None = None,
    on_episode: Callable[[int, Demonstration | None, str], None] | None = None,
) -> DemonstrationSet:
    """Record up to ``n`` kept demonstrations by teleoperation.

    Episode ``i`` resets with ``seed + i``. Each control step the device is polled with the
    current observation and its command becomes the env action (:func:`command_to_action`);
    observation, info flags and action are recorded exactly as for the scripted teacher (row
    ``t`` = state before action ``t``; the last row's action is "no motion" with the current
    gripper command, not applied). An episode ends when the device asks to keep or discard it,
    or when the env terminates or truncates it; then a person (``device.realtime``) is asked
    to keep or discard it while the overlay shows whether it succeeded, and a scripted device is
    polled for that decision. A kept episode needs at least 2 recorded states.

    Args:
        env: a ``gym_coffee`` env made with ``action_type="ee_rot"`` or ``"ee"`` (wrappers are
            fine); for a person, with ``render_mode="human"`` and a generous
            ``max_episode_steps``. It is reset but not closed.
        device: the input device (:class:`InputDevice`); closed at the end.
        n: demonstrations to keep (>= 1); recording also stops when the device quits.
        seed: layout seed of the first episode.
        max_attempts: stop after this many episodes (default ``10 * n``).
        on_episode: called after each episode with (episode index, the demonstration or
            ``None`` if discarded, ``"kept"``/``"discarded"``/``"quit"``).

    Returns:
        The kept demonstrations; ``metadata["teleop"]`` records the device, the action mode,
        kept and discarded seeds.

    Raises:
        ValueError: bad ``n``/``seed``, or the env is not in an end-effector action mode.
        TypeError: ``device`` does not follow :class:`InputDevice`.
    """
    from gym_coffee import __version__
    from gym_coffee.env import CONTROL_DT, OBS_SLICES, obs_part

    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    if not isinstance(device, InputDevice):
        raise TypeError(f"device must follow gym_coffee.teleop.InputDevice, got {device!r}")
    action_type = getattr(env.unwrapped, "action_type", "joint")
    if action_type not in TELEOP_ACTION_TYPES:
        raise ValueError(
            f"env has action_type={action_type!r}; teleoperation drives the end effector: make "
            f"the env with action_type in {TELEOP_ACTION_TYPES}"
        )
    n, seed = int(n), int(seed)
    max_attempts = 10 * n if max_attempts is None else int(max_attempts)
    env_id, env_kwargs, max_steps = _env_identity(env)
    overlay = _Overlay(env, device)
    kept: list[Demonstration] = []
    kept_seeds: list[int] = []
    discarded: list[int] = []
    quit_ = False
    try:
        for attempt in range(max_attempts):
            if len(kept) >= n or quit_:
                break
            episode_seed = seed + attempt
            if hasattr(device, "layout_seed"):
                device.layout_seed = episode_seed
            demo, decision = _record_episode(
                env,
                device,
                overlay,
                episode_seed,
                action_type,
                max_steps,
                CONTROL_DT,
                obs_part,
                status=f"episode {attempt + 1} (seed {episode_seed}), kept {len(kept)} of {n}",
            )
            if decision == "kept" and demo is not None:
                kept.append(demo)
                kept_seeds.append(episode_seed)
            else:
                discarded.append(episode_seed)
                demo = None
            quit_ = decision == "quit"
            if on_episode is not None:
                on_episode(attempt, demo, decision)
    finally:
        device.close()
    metadata = {
        "env_id": env_id,
        "env_kwargs": env_kwargs,
        "max_episode_steps": max_steps,
        "seeds": kept_seeds,
        "package_version": __version__,
        "versions": _versions(),
        "teleop": {
            "device": device.name,
            "device_class": f"{type(device).__module__}.{type(device).__qualname__}",
            "action_type": action_type,
            "discarded_seeds": discarded,
            "quit": quit_,
        },
        "control_dt": float(CONTROL_DT),
        "obs_slices": {k: [v.start, v.stop] for k, v in OBS_SLICES.items()},
    }
    return DemonstrationSet(kept, metadata)


def _record_episode(
    env: Any,
    device: Any,
    overlay: _Overlay,
    seed: int,
    action_type: str,
    max_steps: int | None,
    control_dt: float,
    obs_part: Any,
    status: str,
) -> tuple[Demonstration | None, str]:
    """One episode: (demonstration or None, "kept" | "discarded" | "quit")."""
    obs, info = env.reset(seed=seed)
    device.start_episode(env, obs)
    overlay.reset()
    gripper = 1.0
    observations, infos, actions = [obs], [info], []
    decision: str | None = None
    done = False
    steps = 0
    limit = max_steps if max_steps is not None else 100_000
    while not done and steps < limit:
        tick = time.perf_counter()
        command = device.poll(obs, info)
        if command.ends_episode:
            decision = "kept" if command.keep else "quit" if command.quit else "discarded"
            break
        if command.gripper is not None:
            gripper = command.gripper
        action = command_to_action(command, action_type, gripper)
        actions.append(action)
        obs, _reward, terminated, truncated, info = env.step(action)
        observations.append(obs)
        infos.append(info)
        steps += 1
        done = bool(terminated or truncated)
        overlay.draw(info, f"{status}, step {steps}")
        if device.realtime:
            time.sleep(max(0.0, control_dt - (time.perf_counter() - tick)))
    if decision is None:  # the env ended the episode: ask for the decision
        result = "SUCCESS" if info.get("is_success") else "not successful"
        overlay.draw(info, f"{status}: episode over, {result}. Enter: keep, Backspace: discard")
        decision = _wait_for_decision(device, obs, info)
    if decision != "kept":
        return None, decision
    if len(observations) < 2:
        return None, "discarded"  # nothing happened: nothing to learn from
    actions.append(command_to_action(TeleopCommand(), action_type, gripper))  # not applied
    demo = _demonstration_from_steps(seed, observations, infos, actions, obs_part, action_type)
    return demo, decision


SCRIPTED_DECISION_POLLS = 1000
"""Polls a scripted device gets to keep or discard an ended episode before it is discarded."""


def _wait_for_decision(device: Any, obs: NDArray[np.float32], info: dict[str, Any]) -> str:
    """Poll until the device keeps, discards or quits (a person: as long as it takes)."""
    polls = 0
    while device.realtime or polls < SCRIPTED_DECISION_POLLS:
        command = device.poll(obs, info)
        if command.ends_episode:
            return "kept" if command.keep else "quit" if command.quit else "discarded"
        polls += 1
        if device.realtime:
            time.sleep(0.02)
    return "discarded"


def replay_actions(
    env: Any, demo: Demonstration
) -> Iterable[tuple[NDArray[np.float32], dict[str, Any]]]:
    """Replay ``demo``'s applied actions from ``reset(seed=demo.seed)``; yield (obs, info)."""
    obs, info = env.reset(seed=demo.seed)
    yield obs, info
    for action in demo.actions[:-1]:
        obs, _r, _te, _tr, info = env.step(action)
        yield obs, info
