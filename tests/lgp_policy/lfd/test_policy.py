"""GPDemonstrationPolicy: fit, the SB3 predict protocol, save/load, validation.

The demonstrations here are short scripted joint-space motions recorded in the env (no teacher
needed), so these tests check the mechanics, not task success (see tests/test_end_to_end.py and
benchmarks/lfd_success.py for that).
"""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest

import gym_coffee
from gym_coffee.demonstrations import Demonstration, DemonstrationSet
from gym_coffee.env import OBS_DIM, obs_part
from lgp_policy.lfd.policy import GPDemonstrationPolicy, PolicyFileError

N_STEPS = 40


def _wiggle_demo(env, seed: int) -> Demonstration:
    """Move the joints along a smooth seeded path, close the gripper half way."""
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    amp = rng.uniform(0.2, 0.6, 7)
    observations, infos, actions = [obs], [info], []
    for k in range(N_STEPS):
        a = np.zeros(8, dtype=np.float32)
        a[:7] = amp * np.cos(np.pi * k / N_STEPS)
        a[7] = 1.0 if k < N_STEPS // 2 else -1.0
        actions.append(a)
        obs, _r, _te, _tr, info = env.step(a)
        observations.append(obs)
        infos.append(info)
    actions.append(actions[-1])
    o = np.asarray(observations, dtype=np.float32)
    yaw = obs_part(o, "machine_yaw")[:, 0].astype(float)
    quat = np.stack([np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2), np.cos(yaw / 2)], 1)
    return Demonstration(
        time=obs_part(o, "time")[:, 0],
        joint_pos=obs_part(o, "joint_pos"),
        gripper=obs_part(o, "gripper")[:, 0],
        ee_pos=obs_part(o, "ee_pos"),
        object_pos={"cup": obs_part(o, "cup_pos"), "machine": obs_part(o, "machine_pos")},
        object_quat={"cup": obs_part(o, "cup_quat"), "machine": quat},
        stages=np.zeros((len(o), 3), dtype=bool),
        actions=np.asarray(actions, dtype=np.float32),
        observations=o,
        seed=seed,
        success=False,
    )


@pytest.fixture(scope="module")
def demos():
    env = gym.make(gym_coffee.ENV_IDS[0])
    try:
        return DemonstrationSet([_wiggle_demo(env, s) for s in range(3)], {"env_id": "test"})
    finally:
        env.close()


@pytest.fixture(scope="module")
def policy(demos):
    return GPDemonstrationPolicy(n_steps=60, n_grid=200).fit(demos)


def test_fit_as_classmethod_and_instance(demos, policy):
    p = GPDemonstrationPolicy.fit(demos[:2], progress=False)
    assert isinstance(p, GPDemonstrationPolicy)
    assert p.frame_names_ == ["joint", "cup", "machine"]
    assert policy.mean_["joint"].shape == (200, 8)
    assert policy.std_["cup"].shape == (200, 6)  # grasp point + a point on the approach axis
    assert policy.duration_ == pytest.approx(N_STEPS * policy.control_dt_, rel=1e-3)


def test_predict_single_and_batched(policy, demos):
    obs = demos[0].observations[5]
    action, state = policy.predict(obs, deterministic=True)
    assert action.shape == (8,) and action.dtype == np.float32 and state is None
    assert np.all(np.abs(action) <= 1.0)
    batch = demos[1].observations[:4]
    actions, _ = policy.predict(batch, state="s", episode_start=np.ones(4, bool))
    assert actions.shape == (4, 8)
    for k in range(4):
        np.testing.assert_array_equal(actions[k], policy.predict(batch[k])[0])
    assert policy.phase(batch).shape == (4,)
    assert 0.0 <= policy.phase(obs) <= 1.0


def test_predict_distribution(policy, demos):
    dist = policy.predict_distribution(demos[0].observations[10:13])
    assert dist.action.shape == (3, 8)
    assert dist.joint_std.shape == (3, 7) and np.all(dist.joint_std > 0)
    assert set(dist.frame_std) == {"joint", "cup", "machine"}
    np.testing.assert_array_equal(dist.action, policy.predict(demos[0].observations[10:13])[0])


def test_follows_the_demonstrated_motion(policy):
    """Closed loop from a demonstrated start, the policy's gripper command follows the demos."""
    env = gym.make(gym_coffee.ENV_IDS[0])
    obs, _ = env.reset(seed=0)
    grip = []
    for _ in range(N_STEPS):
        action, _ = policy.predict(obs)
        grip.append(action[7])
        obs, *_ = env.step(action)
    env.close()
    assert grip[2] > 0.5 and grip[-2] < -0.5


def test_evaluate_policy_from_sb3(policy):
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    venv = make_vec_env(gym_coffee.ENV_IDS[0], n_envs=2, seed=10_000)
    mean, std = evaluate_policy(policy, venv, n_eval_episodes=2, deterministic=True, warn=False)
    venv.close()
    assert np.isfinite(mean) and np.isfinite(std)


def test_save_load_round_trip_gives_identical_actions(policy, demos, tmp_path):
    path = policy.save(tmp_path / "policy.npz")
    with pytest.raises(FileExistsError):
        policy.save(path)
    policy.save(path, overwrite=True)
    loaded = GPDemonstrationPolicy.load(path)
    obs = np.concatenate([d.observations for d in demos])
    a0, _ = policy.predict(obs)
    a1, _ = loaded.predict(obs)
    np.testing.assert_array_equal(a0, a1)
    assert loaded.get_params() == policy.get_params()
    assert loaded.constraint_intervals() == policy.constraint_intervals()
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["metadata"]))
    assert meta["kind"] == "lgp_policy.gp_demonstration_policy"


def _rewrite(src, dst, **changes):
    with np.load(src, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    np.savez(dst, **arrays)
    return dst


def test_malformed_files_give_clear_errors(policy, tmp_path):
    good = policy.save(tmp_path / "good.npz")
    with pytest.raises(FileNotFoundError):
        GPDemonstrationPolicy.load(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(PolicyFileError, match="not a readable"):
        GPDemonstrationPolicy.load(tmp_path / "junk.npz")
    with pytest.raises(PolicyFileError, match="metadata"):
        GPDemonstrationPolicy.load(_rewrite(good, tmp_path / "a.npz", metadata=None))
    with pytest.raises(PolicyFileError, match="mean__cup"):
        GPDemonstrationPolicy.load(_rewrite(good, tmp_path / "b.npz", mean__cup=None))
    with pytest.raises(PolicyFileError, match="shape"):
        GPDemonstrationPolicy.load(_rewrite(good, tmp_path / "c.npz", std__joint=np.ones((3, 8))))
    with np.load(good, allow_pickle=False) as data:
        meta = json.loads(str(data["metadata"]))
    meta["schema_version"] = 99
    with pytest.raises(PolicyFileError, match="schema version"):
        GPDemonstrationPolicy.load(
            _rewrite(good, tmp_path / "d.npz", metadata=np.array(json.dumps(meta)))
        )
    bad = policy.std_["machine"].copy()
    bad[3, 1] = np.nan
    with pytest.raises(PolicyFileError, match="NaN"):
        GPDemonstrationPolicy.load(_rewrite(good, tmp_path / "e.npz", std__machine=bad))


def test_unfitted_and_bad_input(policy):
    with pytest.raises(RuntimeError, match="not fitted"):
        GPDemonstrationPolicy().predict(np.zeros(OBS_DIM, np.float32))
    with pytest.raises(ValueError, match="OBS_DIM"):
        policy.predict(np.zeros((2, 2, OBS_DIM)))
