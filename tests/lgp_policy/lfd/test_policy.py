"""GPDemonstrationPolicy on the coffee adapter: fit, SB3 predict protocol, save/load, validation.

The demonstrations here are short scripted joint-space motions recorded in the env (no teacher
needed), so these tests check the mechanics, not task success (see tests/test_end_to_end.py and
benchmarks/lfd_success.py for that).
"""

from __future__ import annotations

import io
import json

import gymnasium as gym
import numpy as np
import pytest

import gym_coffee
from gym_coffee.demonstrations import Demonstration, DemonstrationSet
from gym_coffee.env import OBS_DIM, obs_part
from lgp_policy.lfd.policy import GPDemonstrationPolicy, PolicyFileError, PolicyState

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
    env = gym.make(gym_coffee.ENV_ID)
    try:
        return DemonstrationSet([_wiggle_demo(env, s) for s in range(3)], {"env_id": "test"})
    finally:
        env.close()


@pytest.fixture(scope="module")
def policy(demos):
    return GPDemonstrationPolicy(n_steps=60, n_grid=200).fit(demos, allow_failed=True)


def test_fit_as_classmethod_and_instance(demos, policy):
    p = GPDemonstrationPolicy.fit(demos[:1], progress=False, allow_failed=True)
    assert isinstance(p, GPDemonstrationPolicy) and p.n_grid == 500
    assert policy.frame_names_ == ["joint", "cup", "machine"]
    assert policy.mean_["joint"].shape == (200, 8)
    assert policy.std_["cup"].shape == (200, 6)  # grasp point + a point on the approach axis
    assert policy.approach_offset_ == 0.1
    assert policy.duration_ == pytest.approx(N_STEPS * policy.control_dt_, rel=1e-3)


def test_failed_demonstrations_are_refused_by_index(demos):
    with pytest.raises(ValueError, match=r"demonstrations \[0, 1, 2\] did not succeed"):
        GPDemonstrationPolicy(n_steps=20, n_grid=50).fit(demos)


def test_unknown_frame_is_an_error(demos):
    with pytest.raises(ValueError, match="unknown frames"):
        GPDemonstrationPolicy(frames=("cup", "kettle")).fit(demos, allow_failed=True)


def test_predict_single_and_batched_agree(policy, demos):
    obs = demos[0].observations[5]
    action, state = policy.predict(obs, episode_start=np.array([True]), deterministic=True)
    assert action.shape == (8,) and action.dtype == np.float32
    assert isinstance(state, PolicyState) and len(state) == 1
    assert np.all(np.abs(action) <= 1.0)
    batch = demos[1].observations[:4]
    actions, st = policy.predict(batch, episode_start=np.ones(4, bool))
    assert actions.shape == (4, 8) and len(st) == 4
    for k in range(4):  # one vectorised pass == one observation at a time
        single, _ = policy.predict(batch[k], episode_start=np.array([True]))
        np.testing.assert_allclose(actions[k], single, atol=1e-5)
    assert policy.phase(batch).shape == (4,)
    assert 0.0 <= policy.phase(obs) <= 1.0


def test_state_is_threaded_like_sb3(policy, demos):
    """Passing the returned state back gives what the policy's own memory gives."""
    obs = demos[2].observations[:6]
    own = [policy.predict(o, episode_start=np.array([i == 0]))[0] for i, o in enumerate(obs)]
    state, threaded = None, []
    for i, o in enumerate(obs):
        a, state = policy.predict(o[None], state=state, episode_start=np.array([i == 0]))
        threaded.append(a[0])
    np.testing.assert_array_equal(np.stack(own), np.stack(threaded))
    with pytest.raises(ValueError, match="state"):
        policy.predict(obs[:2], state=state)


def test_predict_distribution(policy, demos):
    obs = demos[0].observations[10:13]
    dist = policy.predict_distribution(obs, episode_start=np.ones(3, bool))
    assert dist.action.shape == (3, 8)
    assert dist.joint_std.shape == (3, 7) and np.all(dist.joint_std > 0)
    assert set(dist.frame_std) == {"joint", "cup", "machine"}
    again, _ = policy.predict(obs, episode_start=np.ones(3, bool))
    np.testing.assert_allclose(dist.action, again, atol=1e-6)


@pytest.mark.parametrize("length", [OBS_DIM - 1, OBS_DIM + 1])
def test_observation_of_the_wrong_length_is_refused(policy, length):
    with pytest.raises(ValueError, match=rf"observation must have shape \({OBS_DIM},\)"):
        policy.predict(np.zeros(length, np.float32))
    with pytest.raises(ValueError, match="observation"):
        policy.predict(np.zeros((2, 2, OBS_DIM)))


def test_non_finite_observation_is_refused(policy, demos):
    obs = demos[0].observations[3].copy()
    obs[4] = np.nan
    with pytest.raises(ValueError, match="observation contains NaN or inf"):
        policy.predict(obs)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_grid": 1}, "n_grid"),
        ({"n_steps": 1}, "n_steps"),
        ({"alpha": float("nan")}, "alpha"),
        ({"alpha": -0.1}, "alpha"),
        ({"lookahead": float("inf")}, "lookahead"),
        ({"max_joint_step": 0.0}, "max_joint_step"),
        ({"model": "nope"}, "model"),
        ({"frames": "cup"}, "frames"),
        ({"frame_noise": -1.0}, "frame_noise"),
        ({"std_scale": {"cup": float("nan")}}, "std_scale"),
    ],
)
def test_constructor_arguments_are_checked_at_construction(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GPDemonstrationPolicy(**kwargs)


def test_follows_the_demonstrated_motion(policy):
    """Closed loop from a demonstrated start, the policy's gripper command follows the demos."""
    env = gym.make(gym_coffee.ENV_ID)
    obs, _ = env.reset(seed=0)
    grip = []
    for i in range(N_STEPS):
        action, _ = policy.predict(obs, episode_start=np.array([i == 0]))
        grip.append(action[7])
        obs, *_ = env.step(action)
    env.close()
    assert grip[2] > 0.5 and grip[-2] < -0.5


def test_evaluate_policy_from_sb3(policy):
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    venv = make_vec_env(gym_coffee.ENV_ID, n_envs=2, seed=10_000)
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
    starts = np.ones(len(obs), bool)
    a0, _ = policy.predict(obs, episode_start=starts)
    a1, _ = loaded.predict(obs, episode_start=starts)
    np.testing.assert_array_equal(a0, a1)
    assert loaded.get_params() == policy.get_params()
    assert loaded.constraint_intervals() == policy.constraint_intervals()
    assert loaded.event_phases_ == policy.event_phases_
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["metadata"]))
    assert meta["kind"] == "lgp_policy.gp_demonstration_policy" and meta["adapter"] == "coffee"
    embedded = GPDemonstrationPolicy.load(io.BytesIO(path.read_bytes()))  # from memory
    np.testing.assert_array_equal(embedded.predict(obs, episode_start=starts)[0], a0)


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


def _with_meta(good, dst, **meta_changes):
    with np.load(good, allow_pickle=False) as data:
        meta = json.loads(str(data["metadata"]))
    for k, v in meta_changes.items():
        if isinstance(v, dict) and isinstance(meta.get(k), dict):
            meta[k] = {**meta[k], **v}
        else:
            meta[k] = v
    return _rewrite(good, dst, metadata=np.array(json.dumps(meta)))


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
    with pytest.raises(PolicyFileError, match="schema version"):
        GPDemonstrationPolicy.load(_with_meta(good, tmp_path / "d.npz", schema_version=99))
    bad = policy.std_["machine"].copy()
    bad[3, 1] = np.nan
    with pytest.raises(PolicyFileError, match="std__machine"):
        GPDemonstrationPolicy.load(_rewrite(good, tmp_path / "e.npz", std__machine=bad))


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"frame_names": ["joint", "cup", "kettle"]}, "unknown frames"),
        ({"duration": 1e308}, "duration"),
        ({"duration": -1.0}, "duration"),
        ({"control_dt": 0.0}, "control_dt"),
        ({"params": {"n_grid": 1}}, "n_grid"),
        ({"params": {"alpha": 1e9}}, "alpha"),
        ({"params": {"bogus": 1}}, "bogus"),
        ({"event_phases": {"cup_held": 7.0}}, "event_phases"),
        ({"adapter": "somewhere_else"}, "adapter"),
        ({"approach_offset": 1e9}, "approach_offset"),
    ],
)
def test_every_name_and_number_is_checked_on_load(policy, tmp_path, changes, match):
    good = policy.save(tmp_path / "good.npz")
    with pytest.raises(PolicyFileError, match=match):
        GPDemonstrationPolicy.load(_with_meta(good, tmp_path / "bad.npz", **changes))


def test_unknown_members_are_not_read(policy, tmp_path):
    good = policy.save(tmp_path / "good.npz")
    extra = _rewrite(good, tmp_path / "extra.npz", junk=np.zeros(10))
    assert GPDemonstrationPolicy.load(extra).frame_names_ == policy.frame_names_


def test_unfitted(policy):
    with pytest.raises(RuntimeError, match="not fitted"):
        GPDemonstrationPolicy().predict(np.zeros(OBS_DIM, np.float32))


def test_one_observation_matches_the_batch_path_on_a_rollout(policy, single_matches_batch):
    """A recorded episode of the policy itself, then a second one after ``episode_start``."""
    env = gym.make(gym_coffee.ENV_ID)
    rows, starts = [], []
    for seed in (10_000, 10_001):
        obs, _ = env.reset(seed=seed)
        for i in range(40):
            rows.append(obs)
            starts.append(i == 0)
            action, _ = policy.predict(obs, episode_start=np.array([i == 0]))
            obs, *_ = env.step(action)
    env.close()
    single_matches_batch(policy, rows, starts)
