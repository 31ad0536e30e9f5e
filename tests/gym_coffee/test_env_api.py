"""API conformance of every registered gym_coffee env (Gymnasium, SB3, determinism, resources).

Parametrised over :data:`gym_coffee.ENV_IDS`, the way Gymnasium and panda-gym test their envs.
Checkers run with warnings turned into errors: "passes check_env" means "passes it silently".
"""

from __future__ import annotations

import gc
import hashlib
import os
import pickle
import subprocess
import sys
import textwrap
import warnings

import gymnasium as gym
import numpy as np
import pytest

import gym_coffee

ENV_IDS = gym_coffee.ENV_IDS
#: The levels share bodies, code paths and reset logic and differ only in the layouts drawn:
#: the costly resource and reuse checks run on one id (the checkers and determinism on all).
ONE_ID = [gym_coffee.ENV_ID]
N_STEPS = 40  # steps per determinism rollout


def make(env_id: str, **kwargs) -> gym.Env:
    return gym.make(env_id, **kwargs)


def rollout_digest(env_id: str, seed: int, n_steps: int = N_STEPS) -> str:
    """sha256 of all observations, rewards, flags and infos of a seeded random-action rollout."""
    env = make(env_id)
    try:
        digest = hashlib.sha256()
        actions = np.random.default_rng(seed).uniform(-1, 1, (n_steps, *env.action_space.shape))
        obs, info = env.reset(seed=seed)
        digest.update(np.ascontiguousarray(obs).tobytes())
        for action in actions.astype(env.action_space.dtype):
            obs, reward, terminated, truncated, info = env.step(action)
            digest.update(np.ascontiguousarray(obs).tobytes())
            digest.update(np.float64(reward).tobytes())
            digest.update(repr((terminated, truncated, sorted(info.items()))).encode())
            if terminated or truncated:
                obs, info = env.reset()
        return digest.hexdigest()
    finally:
        env.close()


@pytest.mark.parametrize(
    ("env_id", "kwargs"),
    [(env_id, {}) for env_id in ENV_IDS] + [(gym_coffee.ENV_ID, {"reward_type": "sparse"})],
)
def test_gymnasium_check_env_without_warnings(env_id, kwargs):
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = make(env_id, render_mode="rgb_array", **kwargs)
        try:
            check_env(env.unwrapped)
        finally:
            env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_sb3_check_env_without_warnings(env_id):
    env_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = make(env_id, render_mode="rgb_array")
        try:
            # With the render check: SB3 renders, calls env.close() and then keeps resetting
            # and stepping the env (it reconnects in reset).
            env_checker.check_env(env, warn=True, skip_render_check=False)
        finally:
            env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_passive_env_checker_is_silent_on_a_rollout(env_id):
    """gym.make wraps in PassiveEnvChecker: a seeded rollout must not warn either."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rollout_digest(env_id, seed=3, n_steps=10)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_same_seed_same_actions_same_observations(env_id):
    assert rollout_digest(env_id, seed=5) == rollout_digest(env_id, seed=5)
    assert rollout_digest(env_id, seed=5) != rollout_digest(env_id, seed=6)


@pytest.mark.parametrize("env_id", ONE_ID)
def test_two_envs_in_one_process_do_not_interact(env_id):
    """Interleaved stepping of two envs gives the same as stepping each alone."""
    seeds, n = (11, 12), 20
    envs = [make(env_id) for _ in seeds]
    try:
        rngs = [np.random.default_rng(s) for s in seeds]
        outs = [[env.reset(seed=s)[0]] for env, s in zip(envs, seeds, strict=True)]
        for _ in range(n):
            for env, rng, out in zip(envs, rngs, outs, strict=True):
                out.append(env.step(rng.uniform(-1, 1, 8).astype(np.float32))[0])
    finally:
        for env in envs:
            env.close()
    for s, out in zip(seeds, outs, strict=True):
        env = make(env_id)
        rng = np.random.default_rng(s)
        try:
            alone = [env.reset(seed=s)[0]]
            alone += [env.step(rng.uniform(-1, 1, 8).astype(np.float32))[0] for _ in range(n)]
        finally:
            env.close()
        np.testing.assert_array_equal(np.array(out), np.array(alone))


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_determinism_across_processes(env_id):
    here = rollout_digest(env_id, seed=7)
    code = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_env_api import rollout_digest
        print(rollout_digest({env_id!r}, seed=7))
        """
    )
    env = {**os.environ, "PYTHONHASHSEED": "12345", "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == here


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_pickle_round_trip(env_id):
    env = make(env_id)
    try:
        copy = pickle.loads(pickle.dumps(env))
        try:
            # (EzPickle rebuilds the env from its constructor arguments; gym.make's ``spec``
            # is not part of the pickled state, so it is not compared.)
            assert type(copy.unwrapped) is type(env.unwrapped)
            obs_a, info_a = env.reset(seed=21)
            obs_b, info_b = copy.reset(seed=21)
            np.testing.assert_array_equal(obs_a, obs_b)
            assert info_a == info_b
            action = np.linspace(-1, 1, 8).astype(np.float32)
            for _ in range(5):
                a, b = env.step(action), copy.step(action)
                np.testing.assert_array_equal(a[0], b[0])
                assert a[1:] == b[1:]
        finally:
            copy.close()
    finally:
        env.close()


@pytest.mark.parametrize("env_id", ONE_ID)
@pytest.mark.parametrize("context", [None, "spawn"])
def test_async_vector_env(env_id, context):
    def make_env() -> gym.Env:
        # With "spawn"/"forkserver" (Python 3.14's default on Linux) the worker is a fresh
        # interpreter: the env function must import gym_coffee itself to register the ids.
        import gym_coffee  # noqa: F401

        return gym.make(env_id)

    envs = gym.vector.AsyncVectorEnv([make_env] * 2, context=context)
    try:
        obs, info = envs.reset(seed=[1, 2])
        assert obs.shape == (2, *envs.single_observation_space.shape)
        assert not np.array_equal(obs[0], obs[1])  # different layouts
        for _ in range(5):
            obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
        assert obs.shape == (2, *envs.single_observation_space.shape)
        assert reward.shape == terminated.shape == truncated.shape == (2,)
        assert "is_success" in info
        assert envs.single_observation_space.contains(obs[0])
    finally:
        envs.close()
    # Same seeds in a fresh vector env give the same first observations.
    envs = gym.vector.AsyncVectorEnv([make_env] * 2, context=context)
    try:
        again, _ = envs.reset(seed=[1, 2])
    finally:
        envs.close()
    single = make(env_id)
    try:
        np.testing.assert_array_equal(again[0], single.reset(seed=1)[0])
    finally:
        single.close()


@pytest.mark.parametrize("env_id", ONE_ID)
def test_close_twice_and_close_without_reset(env_id):
    env = make(env_id)
    env.reset(seed=0)
    env.close()
    env.close()
    fresh = make(env_id)
    fresh.close()
    fresh.close()


@pytest.mark.parametrize("env_id", ONE_ID)
@pytest.mark.parametrize("size", [None, (96, 128)])
def test_rgb_array_render(env_id, size):
    kwargs = {} if size is None else {"width": size[1], "height": size[0]}
    env = make(env_id, render_mode="rgb_array", **kwargs)
    try:
        env.reset(seed=0)
        frame = env.render()
        assert isinstance(frame, np.ndarray)
        assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
        if size is not None:
            assert frame.shape[:2] == size
        assert frame.std() > 5  # something is drawn, not a blank image
        env.step(env.action_space.sample())
        assert env.render().shape == frame.shape
    finally:
        env.close()


def test_making_resetting_and_rendering_print_nothing(capfd):
    """PyBullet prints "argv[0]=" to the C stdout when connected with an options string; it
    ended up between the lines of every command's output (and in files piped from it)."""
    env = make(gym_coffee.ENV_ID, render_mode="rgb_array")
    try:
        env.reset(seed=0)
        env.step(env.action_space.sample())
        env.render()
    finally:
        env.close()
    assert capfd.readouterr().out == ""


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_render_mode_none_returns_none(env_id):
    env = make(env_id)
    try:
        env.reset(seed=0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Gymnasium warns about render() without a mode
            assert env.render() is None
    finally:
        env.close()


def _rss_kib() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError("no VmRSS in /proc/self/status")


def _n_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def _heap_kib() -> int | None:
    """Bytes in use by C malloc (glibc ``mallinfo2``), in KiB; None where unavailable.

    Unlike RSS this is not hidden by memory that earlier tests freed and malloc reuses, so a
    C-level leak (PyBullet) shows up even late in a test session.
    """
    import ctypes
    import ctypes.util

    class _MallInfo2(ctypes.Structure):
        _fields_ = [
            (name, ctypes.c_size_t)
            for name in (
                "arena", "ordblks", "smblks", "hblks", "hblkhd",
                "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost",
            )
        ]  # fmt: skip

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallinfo2 = libc.mallinfo2
    except (OSError, AttributeError):
        return None
    mallinfo2.restype = _MallInfo2
    info = mallinfo2()
    return int(info.uordblks + info.hblkhd) // 1024


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux /proc")
@pytest.mark.parametrize("env_id", ONE_ID)
def test_make_close_cycles_do_not_leak(env_id):
    def cycle():
        env = make(env_id)
        env.reset(seed=0)
        env.step(env.action_space.sample())
        env.close()

    for _ in range(10):  # warm-up: caches, allocator pools, lazily loaded modules
        cycle()
    gc.collect()
    rss0, fds0, heap0 = _rss_kib(), _n_fds(), _heap_kib()
    for _ in range(100):
        cycle()
    gc.collect()
    rss1, fds1, heap1 = _rss_kib(), _n_fds(), _heap_kib()
    assert fds1 - fds0 <= 2, f"open file descriptors grew from {fds0} to {fds1}"
    if heap0 is not None and heap1 is not None:
        grown = heap1 - heap0
        assert grown < 2 * 1024, f"malloc'd memory grew by {grown / 1024:.1f} MiB in 100 cycles"
    # 100 cycles; a leak of one body or client per cycle would be far above this.
    assert rss1 - rss0 < 16 * 1024, f"RSS grew by {(rss1 - rss0) / 1024:.1f} MiB in 100 cycles"


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux /proc")
@pytest.mark.parametrize("env_id", ONE_ID)
def test_resets_in_one_env_do_not_grow_memory(env_id):
    """RL runs reset one env many thousand times: memory must stay flat (the env re-poses its
    bodies at reset; removing and reloading them leaked ~14 KiB per reset in PyBullet)."""
    env = make(env_id, exact_reset=False)
    try:
        for i in range(30):  # warm-up
            env.reset(seed=i)
        gc.collect()
        heap0 = _heap_kib()
        rss0 = _rss_kib()
        for i in range(500):
            env.reset(seed=i)
        gc.collect()
        heap1 = _heap_kib()
        rss_grown = _rss_kib() - rss0
    finally:
        env.close()
    assert rss_grown < 2 * 1024, f"RSS grew by {rss_grown / 1024:.1f} MiB over 500 resets"
    if heap0 is not None and heap1 is not None:
        grown = heap1 - heap0
        assert grown < 1024, f"malloc'd memory grew by {grown / 1024:.1f} MiB over 500 resets"


def _teacher_episode(env: gym.Env, seed: int, max_steps: int = 400) -> tuple[np.ndarray, dict]:
    from gym_coffee.teacher import ScriptedTeacher

    obs, info = env.reset(seed=seed)
    teacher = ScriptedTeacher(env, rng=[1, seed])
    observations = [obs]
    for _ in range(max_steps):
        obs, _, terminated, truncated, info = env.step(teacher.act(obs))
        observations.append(obs)
        if terminated or truncated:
            break
    return np.array(observations), info


def _random_episode(env: gym.Env, seed: int, n_steps: int = N_STEPS) -> np.ndarray:
    actions = np.random.default_rng(seed).uniform(-1, 1, (n_steps, 8)).astype(np.float32)
    observations = [env.reset(seed=seed)[0]]
    for action in actions:
        observations.append(env.step(action)[0])
    return np.array(observations)


@pytest.mark.parametrize("env_id", ONE_ID)
def test_reset_after_a_full_episode_equals_a_fresh_env(env_id):
    """Reset re-poses the loaded bodies: after an episode that grasped, placed and pressed (or
    stopped with the cup in the gripper), a seeded random-action episode equals a fresh env's
    bit for bit."""
    reused = make(env_id, exact_reset=False)
    try:
        _, info = _teacher_episode(reused, seed=3)  # grasps, places, presses
        assert info["is_success"], info
        after_success = _random_episode(reused, seed=11)
        _teacher_episode(reused, seed=5, max_steps=120)  # stopped with the cup in the gripper
        after_grasp = _random_episode(reused, seed=12)
    finally:
        reused.close()
    for seed, got in [(11, after_success), (12, after_grasp)]:
        fresh = make(env_id, exact_reset=False)
        try:
            np.testing.assert_array_equal(got, _random_episode(fresh, seed))
        finally:
            fresh.close()


@pytest.mark.parametrize("env_id", ONE_ID)
def test_exact_reset_teacher_episode_in_a_reused_env_equals_a_fresh_env(env_id):
    """With ``exact_reset=True`` even a contact-rich episode after a full one (grasp, place,
    press) equals a fresh env's bit for bit. (The default re-posing reset does not promise this:
    Bullet's broadphase keeps history; see the env docstring.)"""
    reused = make(env_id, exact_reset=True)
    try:
        _, info = _teacher_episode(reused, seed=3)
        assert info["is_success"], info
        got, _ = _teacher_episode(reused, seed=8)
    finally:
        reused.close()
    fresh = make(env_id, exact_reset=True)
    try:
        np.testing.assert_array_equal(got, _teacher_episode(fresh, seed=8)[0])
    finally:
        fresh.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_exact_reset_equals_a_freshly_loaded_world(env_id):
    """An exact reset restores the state saved right after loading (``Simulation.restore_state``)
    instead of rebuilding the world. After a full episode (grasp, place, press) and one stopped
    with the cup in the gripper, a teacher episode equals the one in a freshly loaded world (the
    reset after ``close()`` starts a new physics server and loads everything again) bit for bit,
    and so does a random-action episode."""
    env = make(env_id, exact_reset=True)
    try:
        _, info = _teacher_episode(env, seed=3)
        assert info["is_success"], info
        _teacher_episode(env, seed=5, max_steps=120)  # stopped with the cup in the gripper
        restored, _ = _teacher_episode(env, seed=8)
        restored_random = _random_episode(env, seed=12)
        env.close()  # the next reset loads the world afresh
        fresh, info = _teacher_episode(env, seed=8)
        env.close()
        fresh_random = _random_episode(env, seed=12)
    finally:
        env.close()
    assert info["cup_grasped"], info  # the episode had contacts to lose bits in
    np.testing.assert_array_equal(restored, fresh)
    np.testing.assert_array_equal(restored_random, fresh_random)


def test_exact_reset_after_a_body_was_added_loads_the_world_afresh():
    """PyBullet restores a saved state only into the same bodies: with a body added after loading
    (through the simulation or PyBullet directly), the reset loads the world afresh, as a reset
    did before it restored states, and the episode is a fresh env's."""
    import pybullet_data

    env = make(gym_coffee.ENV_ID)
    fresh = make(gym_coffee.ENV_ID)
    try:
        sim = env.unwrapped.sim
        env.reset(seed=0)
        sim.load_urdf("block", "cube_small.urdf", (0.3, 0.0, 0.8), package_asset=False)
        assert sim.restore_state() is False
        np.testing.assert_array_equal(_random_episode(env, seed=4), _random_episode(fresh, 4))
        assert "block" not in sim.bodies
        sim.p.loadURDF(os.path.join(pybullet_data.getDataPath(), "cube_small.urdf"), [0.3, 0, 1])
        np.testing.assert_array_equal(_random_episode(env, seed=5), _random_episode(fresh, 5))
        assert sim.p.getNumBodies() == len(sim.bodies)
    finally:
        env.close()
        fresh.close()


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux /proc")
@pytest.mark.parametrize("env_id", ONE_ID)
def test_exact_resets_do_not_grow_memory(env_id):
    env = make(env_id, exact_reset=True)
    try:
        for i in range(10):
            env.reset(seed=i)
        gc.collect()
        heap0, rss0 = _heap_kib(), _rss_kib()
        for i in range(60):
            env.reset(seed=i)
        gc.collect()
        heap1, rss_grown = _heap_kib(), _rss_kib() - rss0
    finally:
        env.close()
    assert rss_grown < 1024, f"RSS grew by {rss_grown / 1024:.1f} MiB over 60 exact resets"
    if heap0 is not None and heap1 is not None:
        assert heap1 - heap0 < 256, f"malloc'd memory grew by {heap1 - heap0} KiB"


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_usable_after_close(env_id):
    """Reset after close() reconnects (SB3's render check closes the env and goes on): the
    episode equals a fresh env's."""
    env = make(env_id)
    try:
        env.reset(seed=4)
        env.close()
        again = _random_episode(env, seed=4, n_steps=10)
    finally:
        env.close()
    fresh = make(env_id)
    try:
        np.testing.assert_array_equal(again, _random_episode(fresh, seed=4, n_steps=10))
    finally:
        fresh.close()


def test_no_visual_meshes_unless_rendering_and_the_same_episodes():
    """Without a render mode the world is built without visual shapes (the fast reset); headless
    frames draw the scene's visual shapes and the Panda's collision meshes in
    ``HEADLESS_COLORS`` (its visual meshes only in the GUI); the physics is the same bit for
    bit as in a rendering env, for a contact-rich teacher episode in a reused env."""
    from gym_coffee.robot import HEADLESS_COLORS

    plain = make(gym_coffee.ENV_ID)
    rendering = make(gym_coffee.ENV_ID, render_mode="rgb_array")
    try:
        for env, expected in [(plain, False), (rendering, True)]:
            sim = env.unwrapped.sim
            env.reset(seed=0)
            shapes = sim.p.getVisualShapeData(sim.bodies["panda"])
            assert not any(b"/visual/" in shape[4] for shape in shapes)
            colors = {shape[1]: shape[7] for shape in shapes}
            assert (colors[9] == pytest.approx(HEADLESS_COLORS[9])) is expected
            # The table: one collision box, five visual boxes (top and legs).
            assert len(sim.p.getVisualShapeData(sim.bodies["table"])) == (5 if expected else 1)
            assert sim.visual_shapes is expected
        _teacher_episode(plain, seed=3)
        got, info = _teacher_episode(plain, seed=8)
        assert info["is_success"]
        np.testing.assert_array_equal(got, _teacher_episode(rendering, seed=8)[0])
    finally:
        plain.close()
        rendering.close()


def test_composited_frames_equal_frames_drawn_at_once():
    """Headless frames composite the floor, the table and the machine's housing from a backdrop
    (drawn once per layout); the pixels are those of drawing the whole scene every frame, over
    two layouts (the machine moves between them) and a moving arm and button."""
    composited = make(gym_coffee.ENV_ID, render_mode="rgb_array", width=96, height=72)
    direct = make(gym_coffee.ENV_ID, render_mode="rgb_array", width=96, height=72)
    direct.unwrapped.sim.static_bodies = ()  # draw everything every frame
    rng = np.random.default_rng(0)
    try:
        assert composited.unwrapped.sim.static_bodies == ("plane", "table", "machine")
        for seed in (0, 1):
            for env in (composited, direct):
                env.reset(seed=seed)
            for _ in range(4):
                action = rng.uniform(-1, 1, 8).astype(np.float32)
                frames = [env.render() for env in (composited, direct)]
                np.testing.assert_array_equal(frames[0], frames[1])
                assert (frames[0] != frames[0][0, 0]).any()  # a picture, not a blank
                for env in (composited, direct):
                    env.step(action)
    finally:
        composited.close()
        direct.close()
