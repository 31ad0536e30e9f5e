"""Teleoperation, headless: scripted input devices drive the real env (PyBullet DIRECT) in the
end-effector action modes; the recorder writes demonstrations that load, replay, export and fit."""

from __future__ import annotations

import sys
import types

import gymnasium as gym
import numpy as np
import pytest

from gym_coffee import ENV_ID, STAGES
from gym_coffee.demonstrations import DemonstrationSet
from gym_coffee.teleop import (
    InputDevice,
    KeyboardInput,
    ScriptedInput,
    SpaceMouseInput,
    TeleopCommand,
    WaypointInput,
    command_to_action,
    keyboard_command,
    record_teleop,
    replay_actions,
)

UP = TeleopCommand(delta_xyz=[0, 0, 1])  # gripper unchanged
CLOSE = TeleopCommand(delta_rpy=[0, 0, 0.5], gripper=-1.0)


@pytest.fixture(scope="module")
def env():
    env = gym.make(ENV_ID, action_type="ee_rot")
    yield env
    env.close()


@pytest.fixture(scope="module")
def taught(env) -> DemonstrationSet:
    """One episode taught by the scripted operator (the teacher's waypoints, human-like)."""
    return record_teleop(env, WaypointInput(variation=1.0), n=1, seed=3)


def test_command_validation_and_actions():
    c = TeleopCommand(delta_xyz=[2, -0.5, 0], delta_rpy=(0, 0, -3), gripper=5)
    assert c.delta_xyz.tolist() == [1, -0.5, 0] and c.delta_rpy[2] == -1 and c.gripper == 1
    for bad in ({"delta_xyz": [np.nan, 0, 0]}, {"delta_rpy": [0, 0]}, {"gripper": np.inf}):
        with pytest.raises(ValueError):
            TeleopCommand(**bad)
    with pytest.raises(ValueError, match="not several"):
        TeleopCommand(keep=True, discard=True)
    np.testing.assert_array_equal(command_to_action(c, "ee", -1.0), [1, -0.5, 0, -1])
    assert command_to_action(c, "ee_rot", 0.25).tolist() == [1, -0.5, 0, 0, 0, -1, 0.25]
    with pytest.raises(ValueError, match="action_type"):
        command_to_action(c, "joint", 0.0)
    for device in (ScriptedInput([UP]), WaypointInput(), KeyboardInput()):
        assert isinstance(device, InputDevice)


def test_scripted_episodes_keep_discard_and_quit(env):
    """Episode 1 is discarded by the device, episode 2 kept after 6 commands, then quit."""
    device = ScriptedInput(
        [
            [UP, UP, TeleopCommand(discard=True)],
            [UP, UP, UP, CLOSE, CLOSE, UP, TeleopCommand(keep=True)],
            [UP, TeleopCommand(quit=True)],
        ]
    )
    log = []
    demos = record_teleop(env, device, n=5, seed=40, on_episode=lambda *a: log.append(a[2]))
    assert log == ["discarded", "kept", "quit"]
    assert len(demos) == 1 and demos.seeds == [41] and demos.action_type == "ee_rot"
    demo = demos[0]
    assert demo.n_steps == 7  # 6 applied actions, then the final state
    expected = [
        command_to_action(c, "ee_rot", g)
        for c, g in zip([UP, UP, UP, CLOSE, CLOSE, UP], [1, 1, 1, -1, -1, -1], strict=True)
    ]
    np.testing.assert_array_equal(demo.actions[:-1], expected)
    np.testing.assert_array_equal(demo.actions[-1], [0, 0, 0, 0, 0, 0, -1])  # no motion
    assert demo.ee_pos[5, 2] > demo.ee_pos[0, 2] + 0.05  # moved up (4 x 0.02 m commanded)
    teleop = demos.metadata["teleop"]
    assert teleop["device"] == "scripted" and teleop["discarded_seeds"] == [40, 42]
    assert teleop["quit"] and demos.metadata["env_id"] == ENV_ID
    assert demos.metadata["env_kwargs"]["action_type"] == "ee_rot"


def test_recorder_refuses_bad_arguments(env):
    joint = gym.make(ENV_ID)
    try:
        with pytest.raises(ValueError, match="action_type in"):
            record_teleop(joint, ScriptedInput([UP]), n=1)
    finally:
        joint.close()
    with pytest.raises(TypeError, match="InputDevice"):
        record_teleop(env, object(), n=1)  # type: ignore[arg-type]
    for n in (0, -1, 1.5):
        with pytest.raises(ValueError, match="n must be"):
            record_teleop(env, ScriptedInput([UP]), n=n)  # type: ignore[arg-type]


def test_ee_mode_and_an_ended_episode(env):
    """In the 4-D mode too; when the time limit ends the episode, the device decides."""
    short = gym.make(ENV_ID, action_type="ee", max_episode_steps=3)
    try:
        demos = record_teleop(short, ScriptedInput([UP] * 10), n=1, seed=1)
    finally:
        short.close()
    assert demos[0].actions.shape == (4, 4) and demos[0].n_steps == 4
    assert not demos[0].success


def test_taught_episode_completes_the_task(env, taught, tmp_path):
    demo = taught[0]
    assert demo.success and demo.stages[-1].all()
    first = [int(np.argmax(demo.stages[:, j])) for j in range(len(STAGES))]
    assert 0 < first[0] < first[1] < first[2] == demo.n_steps - 1
    assert np.abs(demo.actions).max() <= 1.0 and demo.actions.shape[1] == 7
    # The recorded actions describe the episode: replaying them reproduces it exactly.
    replayed = [obs for obs, _ in replay_actions(env, demo)]
    np.testing.assert_array_equal(np.array(replayed), demo.observations)
    back = DemonstrationSet.load(taught.save(tmp_path / "t.npz"))
    assert back == taught and back.metadata["teleop"]["device"] == "waypoints"


def test_taught_episode_exports_exactly(taught, tmp_path, monkeypatch):
    """Real frames (object poses per step) and stage flags survive robomimic and Minari."""
    import minari

    from gym_coffee.datasets import export_minari, export_robomimic, import_robomimic

    back = import_robomimic(export_robomimic(taught, tmp_path / "t.hdf5"))
    assert back == taught
    np.testing.assert_array_equal(back[0].object_pos["cup"], taught[0].object_pos["cup"])
    np.testing.assert_array_equal(back[0].stages, taught[0].stages)
    export_minari(taught, "coffee/taught-v0", root=tmp_path / "m")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "m"))
    episode = next(minari.load_dataset("coffee/taught-v0").iterate_episodes())
    np.testing.assert_array_equal(episode.actions, taught[0].actions[:-1])
    np.testing.assert_array_equal(episode.infos["stages"]["cup_placed"], taught[0].stages[:, 1])


def test_taught_episode_is_accepted_by_fit(taught):
    """The learner takes hand-taught (end-effector) demonstrations like the teacher's."""
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    policy = GPDemonstrationPolicy(model="empirical").fit(taught)
    assert np.isfinite(policy.predict(taught[0].observations[0])[0]).all()


# -- devices ---------------------------------------------------------------------------------------

CODES = {
    "up": 65297,
    "down": 65298,
    "left": 65295,
    "right": 65296,
    "enter": 65309,
    "backspace": 65288,
    "escape": 27,
}
DOWN, HIT = 1, 2


class _State:
    speed, gripper, show_help = 0.5, 1.0, True


def test_keyboard_mapping():
    state = _State()
    c = keyboard_command(
        {CODES["up"]: DOWN, CODES["left"]: DOWN, ord("f"): DOWN}, CODES, DOWN, HIT, state
    )
    assert c.delta_xyz.tolist() == [0.5, 0.5, -0.5] and not c.ends_episode and c.gripper == 1
    c = keyboard_command(
        {ord(" "): HIT | DOWN, ord("]"): HIT, ord("j"): DOWN}, CODES, DOWN, HIT, state
    )
    assert c.gripper == -1 and state.speed == 1.0 and c.delta_rpy.tolist() == [0, 0, 1]
    assert keyboard_command({CODES["enter"]: HIT}, CODES, DOWN, HIT, state).keep
    assert keyboard_command({CODES["backspace"]: HIT}, CODES, DOWN, HIT, state).discard
    assert keyboard_command({ord("q"): HIT}, CODES, DOWN, HIT, state).quit
    keyboard_command({ord("["): HIT}, CODES, DOWN, HIT, state)
    assert state.speed == 0.5


def test_spacemouse_is_an_optional_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyspacemouse", None)
    with pytest.raises(ImportError, match=r'pip install "gym-coffee\[teleop\]"'):
        SpaceMouseInput()


def test_spacemouse_commands(monkeypatch, env):
    """With a stand-in for pyspacemouse: axes, dead zone, the button toggles the gripper."""
    states = iter(
        [
            types.SimpleNamespace(x=0.5, y=-0.02, z=0.0, roll=0, pitch=0, yaw=1.0, buttons=[1, 0]),
            types.SimpleNamespace(x=0.0, y=0.0, z=1.0, roll=0, pitch=0, yaw=0, buttons=[0, 0]),
        ]
    )
    fake = types.SimpleNamespace(open=lambda: True, read=lambda: next(states), close=lambda: None)
    monkeypatch.setitem(sys.modules, "pyspacemouse", fake)
    device = SpaceMouseInput(speed=1.0)
    obs, info = env.reset(seed=0)
    device.start_episode(env, obs)  # DIRECT client: getKeyboardEvents is empty
    c1, c2 = device.poll(obs, info), device.poll(obs, info)
    assert c1.delta_xyz.tolist() == [0.5, 0, 0] and c1.delta_rpy[2] == 1 and c1.gripper == -1
    assert c2.delta_xyz.tolist() == [0, 0, 1] and c2.gripper == -1
    device.close()


def test_teleop_command_line(tmp_path, capsys):
    """`gym-coffee teleop --device waypoints` (no person, headless) writes a file `fit` reads."""
    from lgp_policy.app.cli import main

    out = tmp_path / "taught.npz"
    args = ["teleop", "--device", "waypoints", "--out", str(out), "--seed", "5"]
    assert main(args) == 0
    demos = DemonstrationSet.load(out)
    assert len(demos) == 1 and demos[0].success and demos.action_type == "ee_rot"
    assert "saved 1 demonstrations (1 successful" in capsys.readouterr().out
    assert main(args) == 2  # no overwrite without --force
    assert "exists" in capsys.readouterr().err
    assert main(["teleop", "--out", str(tmp_path / "x.txt")]) == 2
    assert main(["teleop", "--out", str(tmp_path / "y.npz"), "--env-id", "CartPole-v1"]) == 2
    assert "not a gym_coffee environment" in capsys.readouterr().err


def test_overlay_removes_its_texts_at_each_episode():
    """The GUI overlay's texts are removed when an episode starts: an exact reset restores the
    bodies' state and keeps PyBullet's debug items, so forgetting their ids stacked every
    episode's texts on top of the last ones. (A fake GUI client: no display here.)"""
    from gym_coffee.teleop import _Overlay

    class FakeClient:
        def __init__(self) -> None:
            self.live: set[int] = set()
            self.next_id = 0

        def addUserDebugText(self, text, position, replaceItemUniqueId=None, **kwargs):
            if replaceItemUniqueId is not None:
                return replaceItemUniqueId
            self.next_id += 1
            self.live.add(self.next_id)
            return self.next_id

        def removeUserDebugItem(self, item):
            self.live.discard(item)

        def getDebugVisualizerCamera(self):
            return (0, 0, None, None, None, None, (1.0, 0, 0), (0, 0, 1.0), 0, 0, 1.5, (0, 0, 0))

    client = FakeClient()
    sim = types.SimpleNamespace(client=client, gui=True)
    env = types.SimpleNamespace(unwrapped=types.SimpleNamespace(sim=sim))
    overlay = _Overlay(env, device=types.SimpleNamespace(show_help=True))
    for episode in range(3):
        overlay.reset()
        overlay.draw({s: False for s in STAGES}, f"episode {episode}")
        overlay.draw({s: True for s in STAGES}, f"episode {episode}, done")
        assert 0 < len(client.live) == len(overlay._ids)  # one text per line, none left over
