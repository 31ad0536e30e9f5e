"""The baselines: fitted from 2 scripted demonstrations, right shapes, and the replays repeat
their demonstration on its own layout."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import gym_coffee
from lgp_policy.baselines import NearestDemonstrationReplay, ObjectRelativeReplay

DEMO_SEED = 3000  # far from the evaluation seeds (10 000+)


@pytest.fixture(scope="module")
def env():
    e = gym.make(gym_coffee.ENV_ID)
    yield e
    e.close()


@pytest.fixture(scope="module")
def demos(env):
    return gym_coffee.collect_demonstrations(env, n=2, seed=DEMO_SEED)


def _rollout(policy, env, seed):
    """Joint positions per step and the stages reached on ``reset(seed=seed)``."""
    obs, info = env.reset(seed=seed)
    joints = [obs[gym_coffee.OBS_SLICES["joint_pos"]]]
    reached = dict.fromkeys(gym_coffee.STAGES, False)
    done = False
    while not done:
        action, _ = policy.predict(obs, deterministic=True)
        obs, _r, terminated, truncated, info = env.step(action)
        joints.append(obs[gym_coffee.OBS_SLICES["joint_pos"]])
        for k in gym_coffee.STAGES:
            reached[k] |= bool(info[k])
        done = terminated or truncated
    return np.asarray(joints, dtype=float), reached, bool(info["is_success"])


def _check_shapes(policy, demo, *, stateless=True):
    obs = demo.observations
    action, state = policy.predict(obs[0])
    assert action.shape == (8,) and action.dtype == np.float32
    batch, _ = policy.predict(obs[:5])
    assert batch.shape == (5, 8) and batch.dtype == np.float32
    assert np.all(np.abs(batch) <= 1.0)
    if stateless:  # the replays keep no state: a batch row = the single prediction
        assert state is None and policy.predict(obs[0], state="s")[1] == "s"
        np.testing.assert_array_equal(batch[0], action)


def test_nearest_replay_repeats_its_demonstration(env, demos):
    policy = NearestDemonstrationReplay().fit(demos)
    _check_shapes(policy, demos[0])
    for i, demo in enumerate(demos):
        assert policy.nearest(demo.observations[0]) == i
    demo = demos[1]
    joints, _reached, success = _rollout(policy, env, demo.seed)
    assert success
    assert len(joints) == demo.n_steps
    np.testing.assert_allclose(joints, demo.joint_pos, atol=1e-4)


def test_object_relative_replay_on_its_layout(env, demos):
    policy = ObjectRelativeReplay(demo_index=1).fit(demos)
    _check_shapes(policy, demos[1])
    demo = demos[1]
    # The target path on the demonstration's own layout is the demonstration's hand path.
    from lgp_policy.lfd.policy import hand_points

    for k in (0, demo.n_steps // 2, demo.n_steps - 1):
        expected = hand_points(policy.adapter_.robot, demo.joint_pos[k], policy.approach_offset)[0]
        got = policy.target(demo.observations[k], t=demo.time[k])
        np.testing.assert_allclose(got, expected, atol=1e-4)  # float32 observations
    joints, reached, success = _rollout(policy, env, demo.seed)
    assert success and all(reached.values())
    # Tracked with IK, not the teacher's actions: close to the demonstration, not identical.
    n = min(len(joints), demo.n_steps)
    assert np.max(np.abs(joints[:n] - demo.joint_pos[:n])) < 0.3


def test_promp_policy_fits_and_predicts(demos):
    pytest.importorskip("movement_primitives")
    from lgp_policy.baselines import ProMPPolicy

    policy = ProMPPolicy(n_steps=60, n_grid=100, n_weights_per_dim=10).fit(demos)
    assert policy.frame_names_ == ["joint", "cup", "machine"]
    assert set(policy.promps_) == set(policy.frame_names_)
    for name in policy.frame_names_:
        dims = 8 if name == "joint" else 6
        assert policy.mean_[name].shape == policy.std_[name].shape == (100, dims)
        assert np.all(policy.std_[name] > 0)
    # The ProMP mean follows the demonstrations' mean in every frame.
    data = policy.encoder_.data_["joint"].mean(axis=0)
    grid = np.interp(policy.encoder_.phase_, policy.phase_grid_, policy.mean_["joint"][:, 0])
    assert np.max(np.abs(grid - data[:, 0])) < 0.1
    _check_shapes(policy, demos[0], stateless=False)
    with pytest.raises(TypeError, match="model"):
        ProMPPolicy(model="local")


@pytest.mark.parametrize("cls", [NearestDemonstrationReplay, ObjectRelativeReplay])
def test_bad_input(cls, demos):
    with pytest.raises(ValueError, match="demos"):
        cls().fit([])
    with pytest.raises(RuntimeError, match="not fitted"):
        cls().predict(demos[0].observations[0])
    with pytest.raises(ValueError, match="observation"):
        cls().fit(demos).predict(demos[0].observations[0, :-1])


def test_object_relative_replay_arguments(demos):
    with pytest.raises(ValueError, match="demo_index"):
        ObjectRelativeReplay(demo_index=5).fit(demos)
    with pytest.raises(ValueError, match="switch_event"):
        ObjectRelativeReplay(switch_event="never").fit(demos)
    with pytest.raises(ValueError, match="frames"):
        ObjectRelativeReplay(frames=("cup", "table")).fit(demos)
