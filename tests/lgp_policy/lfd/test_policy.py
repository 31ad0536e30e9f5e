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
from gym_coffee.env import OBS_DIM, OBS_SLICES, obs_part
from lgp_policy.lfd.adapters.coffee import to_trajectories
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
        ({"extrapolate": -0.5}, "extrapolate"),
        ({"extrapolate": float("nan")}, "extrapolate"),
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
    assert policy.demonstrations_env_ == {"env_id": "test", "env_kwargs": {}}  # the demos' env
    assert loaded.demonstrations_env_ == policy.demonstrations_env_
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
        ({"demonstrations_env": "CoffeeEasy-v0"}, "demonstrations_env"),
        ({"demonstrations_env": {"env_id": 5}}, "demonstrations_env.*env_id"),
        ({"demonstrations_env": {"env_id": "x" * 201}}, "demonstrations_env.*env_id"),
        ({"demonstrations_env": {"env_kwargs": {"level": ["easy"]}}}, "env_kwargs"),
        ({"demonstrations_env": {"env_kwargs": {str(i): i for i in range(33)}}}, "env_kwargs"),
    ],
)
def test_every_name_and_number_is_checked_on_load(policy, tmp_path, changes, match):
    good = policy.save(tmp_path / "good.npz")
    with pytest.raises(PolicyFileError, match=match):
        GPDemonstrationPolicy.load(_with_meta(good, tmp_path / "bad.npz", **changes))


def test_the_demonstrations_env_is_recorded_only_when_they_name_one(demos, policy, tmp_path):
    """Free-form metadata (no env id, or keywords that are not JSON scalars) records nothing;
    a file written before the record existed loads with none."""
    for metadata in ({}, {"env_id": None}, {"env_id": "test", "env_kwargs": {"f": object()}}):
        trajs = to_trajectories(demos)
        trajs.metadata = metadata
        fitted = GPDemonstrationPolicy(n_steps=60, n_grid=200).fit(trajs, allow_failed=True)
        assert fitted.demonstrations_env_ is None
    good = policy.save(tmp_path / "good.npz")
    with np.load(good, allow_pickle=False) as data:
        meta = json.loads(str(data["metadata"]))
    del meta["demonstrations_env"]
    old = _rewrite(good, tmp_path / "old.npz", metadata=np.array(json.dumps(meta)))
    assert GPDemonstrationPolicy.load(old).demonstrations_env_ is None


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


def test_the_coffee_adapter_reads_one_row_as_it_reads_a_batch(demos):
    """The one-row read (floats, the control loop) gives the batch read's arrays bit for bit:
    the cup held and not, the machine on either side, tracked and initial cup positions."""
    from lgp_policy.lfd.adapters import rotation_about_z, rotation_from_angle
    from lgp_policy.lfd.adapters.coffee import CoffeeAdapter

    rng = np.random.default_rng(0)
    obs = np.concatenate([d.observations for d in demos]).astype(float)
    obs[:, OBS_SLICES["machine_yaw"]] = rng.uniform(-np.pi, np.pi, (len(obs), 1))
    obs[:, OBS_SLICES["machine_pos"].start + 1] *= rng.choice([-1.0, 1.0], len(obs))
    held = rng.random(len(obs)) < 0.5  # the grasp point at the cup's middle, fingers on the cup
    cup = obs[held, OBS_SLICES["cup_pos"]]
    obs[held, OBS_SLICES["ee_pos"]] = (
        cup + np.array([0.0, 0.0, 0.05]) + rng.normal(0, 0.01, cup.shape)
    )
    obs[held, OBS_SLICES["gripper"]] = rng.uniform(0.03, 0.08, (int(held.sum()), 1))
    for track in (True, False):
        adapter = CoffeeAdapter(track_cup=track)
        batch = adapter.read(obs)
        assert 0 < batch.events["cup_held"].sum() < len(obs)
        for i in range(len(obs)):
            one = adapter.read(obs[i : i + 1])
            np.testing.assert_array_equal(one.time, batch.time[i : i + 1])
            np.testing.assert_array_equal(one.state, batch.state[i : i + 1])
            for name, (pos, rot) in batch.frames.items():
                np.testing.assert_array_equal(one.frames[name][0], pos[i : i + 1])
                np.testing.assert_array_equal(one.frames[name][1], rot[i : i + 1])
            for kind in ("valid", "events"):
                a, b = getattr(one, kind), getattr(batch, kind)
                assert a.keys() == b.keys()
                for key in a:
                    np.testing.assert_array_equal(a[key], b[key][i : i + 1])
    angles = rng.uniform(-10.0, 10.0, 50)
    for dim in (2, 3):
        batch_rot = rotation_from_angle(angles, dim)
        for i, a in enumerate(angles.tolist()):
            np.testing.assert_array_equal(rotation_about_z(a, dim), batch_rot[i : i + 1])


# ------------------------------------------------------------------ posture clusters (issue 11)
_POSTURE = np.array([-0.2, 0.9, 0.0, -1.9, 1.4, 1.5, 1.2])
_MIRROR = _POSTURE * np.array([-1, 1, -1, 1, -1, 1, -1]) + np.array([0, 0, 0, 0, 0, 0, 1.57])


def _posture_demo(side: int, seed: int):
    """A joint motion around the posture of the machine's side (mirrored for ``side = -1``),
    with the layout mirrored too; the gripper closes and opens once (two alignment events)."""
    from lgp_policy.lfd.adapters import rotation_from_angle
    from lgp_policy.lfd.adapters.coffee import cup_rotation
    from lgp_policy.lfd.demonstrations import Trajectory

    rng = np.random.default_rng(seed)
    n = 30
    t = np.arange(n) * 0.04
    base = _POSTURE if side > 0 else _MIRROR
    wave = np.sin(np.linspace(0.0, np.pi, n))[:, None] * np.array([0.2, 0.1, 0, 0.2, 0, 0, 0.1])
    state = base + wave * np.array([side, 1, side, 1, side, 1, side]) + rng.normal(0, 0.03, 7)
    grip = np.where((np.arange(n) >= 10) & (np.arange(n) < 20), 0.0, 0.08)
    cup = np.array([0.5, -0.15 * side, 0.0]) + rng.normal(0, 0.02, 3) * [1, 1, 0]
    machine = np.array([0.45, 0.35 * side, 0.0]) + rng.normal(0, 0.02, 3) * [1, 1, 0]
    yaw = np.array([-np.pi / 2 * side + rng.normal(0, 0.1)])
    return Trajectory(
        time=t,
        state=state,
        gripper=grip,
        frames={
            "cup": (cup, cup_rotation(cup[None], machine[None], yaw)[0]),
            "machine": (machine, rotation_from_angle(yaw, 3)[0]),
        },
    )


def _observation(tr, q=None):
    """A coffee observation at the start of the demonstration ``tr``'s layout."""
    obs = np.zeros(OBS_DIM)
    obs[1:8] = tr.state[0] if q is None else q
    obs[15] = 0.08
    obs[16:19] = [0.3, 0.0, 0.5]  # the hand far from the cup: not held
    cup, machine = tr.frames["cup"][0][0], tr.frames["machine"][0][0]
    obs[19:22] = obs[26:29] = cup
    obs[29:32] = machine
    R = tr.frames["machine"][1][0]
    obs[32] = np.arctan2(R[1, 0], R[0, 0])
    return obs


@pytest.fixture(scope="module")
def postures():
    from lgp_policy.lfd.demonstrations import TrajectorySet

    sides = [1, 1, -1, 1, -1, 1]
    demos = TrajectorySet([_posture_demo(s, i) for i, s in enumerate(sides)])
    single = GPDemonstrationPolicy(n_steps=30, n_grid=59, posture_distance=None).fit(demos)
    # n_grid = 59: every second point is one of the encoder's T = 30
    return demos, GPDemonstrationPolicy(n_steps=30, n_grid=59).fit(demos), single


def test_mirrored_postures_get_a_joint_model_each(postures):
    _demos, policy, single = postures
    np.testing.assert_array_equal(policy.posture_labels_, [0, 0, 1, 0, 1, 0])
    assert policy.layout_features_.shape == (6, 2 * (3 + 9))
    enc = policy.encoder_.data_["joint"][:, :, :7]
    for c in (0, 1):  # the cluster's mean on the encoder's grid, the gripper of all demonstrations
        mean = enc[policy.posture_labels_ == c].mean(axis=0)
        np.testing.assert_allclose(policy.posture_mean_[c][::2, :7], mean, atol=1e-12)
        np.testing.assert_array_equal(policy.posture_mean_[c][:, 7], policy.mean_["joint"][:, 7])
        # the tied spread is far below the spread of the mixture where the postures differ
        assert np.all(policy.posture_std_[c][:, 4] < 0.5 * policy.std_["joint"][:, 4])
    # the same demonstrations without clusters: one joint model (the paper)
    assert single.posture_labels_ is None and single.posture_mean_ == []


def test_the_nearest_layout_chooses_the_posture(postures):
    demos, policy, global_ = postures
    for i, tr in enumerate(demos):
        # the arm half-way between the postures: the clustered policy pulls towards the
        # layout's posture (joint 5 flips sign with the side), the single model barely
        q = 0.5 * (_POSTURE + _MIRROR)
        obs = _observation(tr, q)
        side = 1.0 if policy.posture_labels_[i] == 0 else -1.0
        dq = policy.predict_distribution(obs, episode_start=[True]).joint_increment[0]
        assert policy._posture_of(policy._memory)[0] == policy.posture_labels_[i]
        assert policy._posture_one(policy._memory) == policy.posture_labels_[i]  # one row
        two, _ = policy.predict(np.stack([obs, obs]), episode_start=[True, True])
        np.testing.assert_array_equal(two[0], policy.predict(obs, episode_start=[True])[0])
        dq_global = global_.predict_distribution(obs, episode_start=[True]).joint_increment[0]
        assert side * dq[4] > 0.05
        assert abs(dq_global[4]) < 0.5 * abs(dq[4])


def test_posture_clusters_are_saved_and_checked(postures, tmp_path):
    demos, policy, _ = postures
    path = policy.save(tmp_path / "p.npz")
    loaded = GPDemonstrationPolicy.load(path)
    np.testing.assert_array_equal(loaded.posture_labels_, policy.posture_labels_)
    obs = np.stack([_observation(tr) for tr in demos])
    starts = np.ones(len(obs), bool)
    np.testing.assert_array_equal(
        loaded.predict(obs, episode_start=starts)[0], policy.predict(obs, episode_start=starts)[0]
    )
    bad = [
        ({"posture_labels": [0, 0, 0, 0, 0, 0]}, {}, "posture_labels"),
        ({"posture_labels": [0, 2, 2, 0, 2, 0]}, {}, "posture_labels"),
        ({"posture_labels": [0, 1]}, {}, "layout_features"),
        ({"posture_labels": None}, {}, "without 'posture_labels'"),
        ({"params": {"posture_distance": None}}, {}, "posture_distance"),
        ({"params": {"posture_distance": -1.0}}, {}, "posture_distance"),
        ({}, {"posture_std__1": None}, "posture members"),
        ({}, {"posture_mean__1": np.ones((59, 7))}, "posture_mean__1"),
        ({}, {"posture_std__0": np.zeros((59, 8))}, "positive"),
        ({}, {"layout_features": np.ones((6, 5))}, "layout_features"),
    ]
    for k, (meta, members, match) in enumerate(bad):
        dst = _with_meta(path, tmp_path / f"m{k}.npz", **meta) if meta else path
        dst = _rewrite(dst, tmp_path / f"b{k}.npz", **members)
        with pytest.raises(PolicyFileError, match=match):
            GPDemonstrationPolicy.load(dst)


def test_files_before_posture_clusters_load_with_one_joint_model(policy, tmp_path):
    good = policy.save(tmp_path / "good.npz")
    with np.load(good, allow_pickle=False) as data:
        meta = json.loads(str(data["metadata"]))
    del meta["params"]["posture_distance"], meta["posture_labels"]
    meta["schema_version"] = 2
    old = _rewrite(good, tmp_path / "v2.npz", metadata=np.array(json.dumps(meta)))
    loaded = GPDemonstrationPolicy.load(old)
    assert loaded.posture_distance is None and loaded.posture_labels_ is None


def test_past_the_end_the_demonstrated_motion_goes_on_then_stops(policy, tmp_path):
    """Beyond phase 1 the means move along their slope over the last 2% of phase for at most
    ``extrapolate`` s (variances held); ``extrapolate=0`` and files written before the parameter
    existed hold the last targets."""
    table, g = policy._table, len(policy.phase_grid_)
    k = max(1, round(0.02 * (g - 1)))
    slope = (table[-1] - table[-1 - k]) / (policy.phase_grid_[-1] - policy.phase_grid_[-1 - k])
    beyond = policy.extrapolate / policy.duration_
    assert beyond > 0.0
    mean_cols = np.concatenate([np.arange(m.start, m.stop) for m, _ in policy._cols.values()])
    var_cols = np.concatenate([np.arange(v.start, v.stop) for _, v in policy._cols.values()])
    assert np.abs(slope[mean_cols]).max() > 0.0  # the demonstrations still move at their end
    for s in (0.5 * beyond, beyond):
        expected = table[-1] + s * np.where(np.isin(np.arange(len(slope)), var_cols), 0.0, slope)
        for phases in (np.array([1.0 + s]), np.array([0.3, 1.0 + s])):  # one row and a batch
            np.testing.assert_allclose(policy._rows(phases)[-1], expected, rtol=1e-12, atol=1e-15)
    far = policy._rows(np.array([1.0 + 5.0 * beyond]))[0]  # it stops after `extrapolate` s
    np.testing.assert_allclose(far, policy._rows(np.array([1.0 + beyond]))[0], rtol=1e-12)
    np.testing.assert_array_equal(policy._rows(np.array([0.7, 1.0]))[1], table[-1])

    good = policy.save(tmp_path / "good.npz")
    with np.load(good, allow_pickle=False) as data:
        meta = json.loads(str(data["metadata"]))
    del meta["params"]["extrapolate"]
    old = _rewrite(good, tmp_path / "old.npz", metadata=np.array(json.dumps(meta)))
    held = GPDemonstrationPolicy.load(old)
    assert held.extrapolate == 0.0
    np.testing.assert_array_equal(held._rows(np.array([1.0 + beyond]))[0], table[-1])
