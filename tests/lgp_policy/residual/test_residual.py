"""Residual RL (issue 5): wrapper, gate, zero-init, fine-tuning, save/load, the rl extra."""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.wrappers import TimeAwareObservation

from lgp_policy.app.finetune_cli import add_finetune_subcommand
from lgp_policy.residual.core import (
    RL_EXTRA_HINT,
    PhaseGate,
    ResidualPolicyFormatError,
    ResidualWrapper,
    evaluate_stages,
    gate_from_config,
    load_any_policy,
    require_rl,
)

TIME_INDEX = 3  # Pendulum (cos, sin, thetadot) + normalised time


class PendulumPD:
    """A stateless PolicyPredictor for Pendulum-v1 (+ normalised time); exposes its phase."""

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        obs = np.asarray(observation, dtype=np.float64)
        o = np.atleast_2d(obs)
        theta = np.arctan2(o[:, 1], o[:, 0])
        a = np.clip((-2.0 * theta - 0.5 * o[:, 2]) / 2.0, -1.0, 1.0)[:, None].astype(np.float32)
        return (a if obs.ndim == 2 else a[0]), state

    def phase(self, observation):
        return np.atleast_2d(observation)[:, TIME_INDEX]


def make_pendulum() -> gym.Env:
    return TimeAwareObservation(gym.make("Pendulum-v1"), normalize_time=True)


class Recorder(gym.Wrapper):
    """Records the actions the inner env receives."""

    def __init__(self, env):
        super().__init__(env)
        self.actions = []

    def step(self, action):
        self.actions.append(np.array(action, copy=True))
        return self.env.step(action)


def rollout_base(env, base, seed, n_steps):
    obs, _ = env.reset(seed=seed)
    observations, rewards = [obs], []
    for _ in range(n_steps):
        action, _ = base.predict(obs[None, :], deterministic=True)
        obs, reward, terminated, truncated, _ = env.step(action[0])
        observations.append(obs)
        rewards.append(reward)
        if terminated or truncated:
            break
    return np.array(observations), np.array(rewards)


# ---------------------------------------------------------------------------------- wrapper
@pytest.mark.parametrize("gate_start", [0.0, 0.5])
def test_zero_residual_reproduces_base_trajectory_pendulum(gate_start):
    base = PendulumPD()
    ref_obs, ref_rew = rollout_base(make_pendulum(), base, seed=3, n_steps=200)
    env = ResidualWrapper(make_pendulum(), base, scale=0.5, gate=PhaseGate(start=gate_start))
    obs, _ = env.reset(seed=3)
    got_obs, got_rew = [obs[:4]], []
    for _ in range(200):
        obs, reward, terminated, truncated, _ = env.step(np.zeros(1, np.float32))
        got_obs.append(obs[:4])
        got_rew.append(reward)
        if terminated or truncated:
            break
    np.testing.assert_array_equal(np.array(got_obs), ref_obs)
    np.testing.assert_array_equal(np.array(got_rew), ref_rew)
    assert env.observation_space.shape == (4 + 1 + 1,)
    assert env.observation_space.contains(obs)


def test_zero_residual_reproduces_base_with_skipping():
    """With skip_ungated the agent sees fewer steps, but the env trajectory is the same."""
    base = PendulumPD()
    ref_obs, ref_rew = rollout_base(make_pendulum(), base, seed=5, n_steps=200)
    env = ResidualWrapper(
        make_pendulum(), base, gate=PhaseGate(start=0.6, ramp=0.0), skip_ungated=True
    )
    obs, _ = env.reset(seed=5)
    total, env_steps, agent_steps, done = 0.0, 0, 0, False
    while not done:
        obs, reward, terminated, truncated, info = env.step(np.zeros(1, np.float32))
        total += reward
        env_steps += info["env_steps"]
        agent_steps += 1
        done = terminated or truncated
    assert env_steps == len(ref_rew) == 200
    assert agent_steps == 1 + 200 - 120  # the first step, then one per gated step
    np.testing.assert_array_equal(obs[:4], ref_obs[-1])
    assert total == pytest.approx(ref_rew.sum(), rel=1e-12)


def test_gate_is_zero_outside_press_phase():
    gate = PhaseGate(start=0.8, ramp=0.1, source="observation", time_index=0)
    phase = np.array([0.0, 0.5, 0.69, 0.7, 0.75, 0.8, 0.95, 1.0, 1.5])
    values = gate(phase[:, None])
    np.testing.assert_array_equal(values[:4], 0.0)
    assert 0.0 < values[4] < 1.0
    np.testing.assert_array_equal(values[5:], 1.0)
    closed = PhaseGate(start=0.8, end=1.0, ramp=0.0, source="observation", time_index=0)
    np.testing.assert_array_equal(closed(phase[:, None]), [0, 0, 0, 0, 0, 1, 1, 1, 0])
    assert gate_from_config(gate.to_config()) == gate
    assert gate_from_config(json.loads(json.dumps(closed.to_config()))) == closed

    # In the wrapper: random residuals change nothing while the gate is closed.
    base = PendulumPD()
    rec = Recorder(make_pendulum())
    env = ResidualWrapper(rec, base, scale=1.0, gate=PhaseGate(start=0.5, ramp=0.0))
    env.reset(seed=0)
    env.action_space.seed(0)
    gates, bases = [], []
    for _ in range(200):
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        gates.append(info["residual_gate"])
        bases.append(info["base_action"])
        if terminated or truncated:
            break
    gates, bases, applied = np.array(gates), np.array(bases), np.array(rec.actions)
    assert np.all(gates[:100] == 0.0) and np.all(gates[100:] == 1.0)
    np.testing.assert_array_equal(applied[:100], bases[:100])
    assert np.any(applied[100:] != bases[100:])


def test_policy_gate_needs_phase_or_time_index():
    class NoPhase:
        def predict(self, observation, state=None, episode_start=None, deterministic=False):
            return np.zeros((len(np.atleast_2d(observation)), 1), np.float32), state

    with pytest.raises(TypeError, match="phase"):
        PhaseGate()(np.zeros((1, 4)), NoPhase())
    with pytest.raises(ValueError, match="time_index"):
        PhaseGate(source="observation")


def test_wrapper_rejects_bad_arguments():
    with pytest.raises(ValueError, match="scale"):
        ResidualWrapper(make_pendulum(), PendulumPD(), scale=0.0)
    with pytest.raises(ValueError, match="residual_dims"):
        ResidualWrapper(make_pendulum(), PendulumPD(), residual_dims=[1])
    with pytest.raises(TypeError, match="predict"):
        ResidualWrapper(make_pendulum(), object())


# ---------------------------------------------------------------------------- optional extra
def test_require_rl_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)
    with pytest.raises(ImportError, match=r'pip install "gym-coffee\[rl\]"'):
        require_rl()


def test_finetune_cli_without_rl_says_which_extra(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "torch", None)
    parser = argparse.ArgumentParser(prog="gym-coffee")
    add_finetune_subcommand(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["finetune", str(tmp_path / "policy.npz"), "--timesteps", "10"])
    assert args.func(args) == 2
    assert RL_EXTRA_HINT in capsys.readouterr().err


def test_modules_import_without_sb3_and_torch():
    code = (
        "import sys\n"
        "sys.modules['stable_baselines3'] = None\n"
        "sys.modules['torch'] = None\n"
        "import lgp_policy, lgp_policy.residual.core, lgp_policy.app.finetune_cli\n"
        "from lgp_policy import ResidualWrapper, ResidualPolicy\n"
        "import numpy as np, gymnasium as gym\n"
        "from lgp_policy.residual.core import PhaseGate\n"
        "class B:\n"
        "    def predict(self, o, state=None, episode_start=None, deterministic=False):\n"
        "        return np.zeros((len(o), 1), np.float32), state\n"
        "g = PhaseGate(source='observation', time_index=0)\n"
        "env = ResidualWrapper(gym.make('Pendulum-v1'), B(), gate=g)\n"
        "env.reset(seed=0); env.step(np.zeros(1, np.float32))\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().endswith("ok")


# ---------------------------------------------------------------------------- SB3 mechanics
sb3 = pytest.importorskip("stable_baselines3")
torch = pytest.importorskip("torch")

from lgp_policy.residual.core import (  # noqa: E402
    DEFAULT_HYPERPARAMETERS,
    ResidualPolicy,
    _build_model,
    finetune,
)


def _wrapped(gate_start=0.0):
    return ResidualWrapper(
        make_pendulum(), PendulumPD(), scale=0.5, gate=PhaseGate(start=gate_start, ramp=0.0)
    )


@pytest.mark.parametrize("algo", ["sac", "td3", "ppo"])
def test_zero_initialised_actor_outputs_zero(algo):
    env = _wrapped()
    hp = dict(DEFAULT_HYPERPARAMETERS[algo])
    if algo != "ppo":
        hp["buffer_size"] = 100
    model = _build_model(algo, env, hp, seed=0)
    obs = np.stack([env.observation_space.sample() for _ in range(16)])
    action, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(action, 0.0)
    if algo == "td3":
        with torch.no_grad():
            target = model.policy.actor_target(torch.as_tensor(obs))
        np.testing.assert_array_equal(target.numpy(), 0.0)
    if algo in ("sac", "ppo"):  # the exploration noise is small, not uniform on [-1, 1]
        sampled, _ = model.predict(np.repeat(obs, 50, axis=0), deterministic=False)
        assert 0.05 < np.std(sampled) < 0.45


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_warmup_does_not_inject_full_scale_residuals(algo):
    hp = {"buffer_size": 200, "batch_size": 16}
    result = finetune(
        PendulumPD(),
        make_pendulum,
        algo=algo,
        total_env_steps=60,
        gate=PhaseGate(start=0.0),
        hyperparameters=hp,
        eval_seeds=[],
        progress=False,
        skip_ungated=False,
    )
    buffer = result.policy.model.replay_buffer
    actions = buffer.actions[: buffer.pos].ravel()
    assert actions.size >= 50
    assert np.max(np.abs(actions)) < 0.95  # uniform warm-up would reach ~1
    assert np.mean(np.abs(actions)) < 0.35  # uniform warm-up: 0.5


def test_tiny_finetune_saves_a_policy_that_loads_and_predicts_identically(tmp_path):
    base = PendulumPD()
    result = finetune(
        base,
        make_pendulum,
        algo="sac",
        total_env_steps=300,
        seed=1,
        scale=0.5,
        gate=PhaseGate(start=0.5, ramp=0.0),
        eval_seeds=[20_000, 20_001],
        eval_freq=150,
        checkpoint_freq=150,
        out_dir=tmp_path / "run",
        hyperparameters={"batch_size": 32},
        progress=False,
    )
    assert result.env_steps >= 300
    assert result.agent_steps < result.env_steps  # ungated steps were skipped
    assert result.curve[0]["env_steps"] == 0 and len(result.curve) >= 3
    run = tmp_path / "run"
    assert (run / "learning_curve.png").stat().st_size > 1000
    assert json.loads((run / "learning_curve.json").read_text())["algo"] == "sac"
    assert sorted(p.name for p in (run / "checkpoints").iterdir())
    path = run / "residual_policy.npz"
    with np.load(path, allow_pickle=False) as data:  # nothing pickled
        assert all(data[k].dtype != object for k in data.files)
        assert "obs_norm/mean" in data.files  # VecNormalize statistics travel with the weights

    loaded = ResidualPolicy.load(path, base=base)
    obs = np.stack([make_pendulum().observation_space.sample() for _ in range(64)])
    obs[:, TIME_INDEX] = np.linspace(0, 1, 64)
    expected, _ = result.policy.predict(obs, deterministic=True)
    got, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(got, expected)
    single, _ = loaded.predict(obs[40], deterministic=True)
    np.testing.assert_array_equal(single, expected[40])
    # Closed gate: exactly the base.
    base_action, _ = base.predict(obs[:32])
    np.testing.assert_array_equal(got[:32], base_action)

    with pytest.raises(FileExistsError, match="overwrite"):
        result.policy.save(path)
    with pytest.raises(FileExistsError):
        finetune(base, make_pendulum, total_env_steps=10, out_dir=run, progress=False)

    # The loaded policy works in SB3's evaluate_policy (batched, vectorised).
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    venv = DummyVecEnv([lambda: Monitor(make_pendulum())] * 2)
    mean, _ = evaluate_policy(loaded, venv, n_eval_episodes=2)
    assert np.isfinite(mean)


SMALL = {
    "sac": {"buffer_size": 50, "batch_size": 8},
    "td3": {"buffer_size": 50, "batch_size": 8},
    "ppo": {"n_steps": 16, "batch_size": 8},
}


def _save_small_policy(tmp_path, algo="td3"):
    result = finetune(
        PendulumPD(),
        make_pendulum,
        algo=algo,
        total_env_steps=20,
        gate=PhaseGate(start=0.0),
        eval_seeds=[],
        progress=False,
        hyperparameters=SMALL[algo],
    )
    path = tmp_path / f"{algo}.npz"
    result.policy.save(path)
    return path, result.policy


@pytest.mark.parametrize("algo", ["td3", "ppo"])
def test_round_trip_other_algorithms(tmp_path, algo):
    path, policy = _save_small_policy(tmp_path, algo)
    loaded = ResidualPolicy.load(path, base=PendulumPD())
    obs = np.stack([make_pendulum().observation_space.sample() for _ in range(8)])
    np.testing.assert_array_equal(
        loaded.predict(obs, deterministic=True)[0], policy.predict(obs, deterministic=True)[0]
    )


def _rewrite(src: Path, dst: Path, edit) -> Path:
    with np.load(src, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    edit(arrays)
    np.savez(dst, **arrays)
    return dst


def test_malformed_files_give_clear_errors(tmp_path):
    path, _ = _save_small_policy(tmp_path)
    base = PendulumPD()

    def set_meta(**changes):
        def edit(arrays):
            meta = json.loads(str(arrays["metadata"]))
            meta.update(changes)
            arrays["metadata"] = np.array(json.dumps(meta))

        return edit

    def drop_weight(arrays):
        del arrays[next(k for k in arrays if k.startswith("param/"))]

    def bad_shape(arrays):
        key = next(k for k in arrays if k.startswith("param/") and arrays[k].ndim == 2)
        arrays[key] = arrays[key][:, :-1]

    def nan_weight(arrays):
        key = next(k for k in arrays if k.startswith("param/") and arrays[k].ndim == 2)
        arrays[key] = np.full_like(arrays[key], np.nan)

    cases = {
        "kind": (set_meta(kind="something_else"), "kind"),
        "version": (set_meta(schema_version=99), "schema version 99"),
        "algo": (set_meta(algo="dqn"), "algo"),
        "scale": (set_meta(scale=-1.0), "scale"),
        "missing": (drop_weight, "missing"),
        "shape": (bad_shape, "shape"),
        "nan": (nan_weight, "NaN"),
        "meta": (lambda a: a.pop("metadata"), "metadata"),
        "norm": (lambda a: a.pop("obs_norm/var"), "obs_norm"),
    }
    for name, (edit, message) in cases.items():
        bad = _rewrite(path, tmp_path / f"bad_{name}.npz", edit)
        with pytest.raises(ResidualPolicyFormatError, match=message):
            ResidualPolicy.load(bad, base=base)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ResidualPolicyFormatError, match="not a readable"):
        ResidualPolicy.load(truncated, base=base)
    with pytest.raises(ResidualPolicyFormatError, match="without its base"):
        ResidualPolicy.load(path)  # saved without a base file
    assert zipfile.is_zipfile(path)


def test_load_any_policy_dispatches_on_kind(tmp_path):
    path, _ = _save_small_policy(tmp_path)
    with pytest.raises(ResidualPolicyFormatError, match="without its base"):
        load_any_policy(path)  # reached ResidualPolicy.load
    other = tmp_path / "other.npz"
    np.savez(other, metadata=np.array(json.dumps({"kind": "mystery"})))
    with pytest.raises(ResidualPolicyFormatError, match="unknown policy kind 'mystery'"):
        load_any_policy(other)
    with pytest.raises(FileNotFoundError):
        load_any_policy(tmp_path / "nope.npz")


def test_evaluate_stages_reports_return_without_stage_flags():
    res = evaluate_stages(PendulumPD(), make_pendulum, seeds=[0, 1])
    assert res["episodes"] == 2 and res["rates"] == {} and res["mean_length"] == 200


# ---------------------------------------------------------------------------- the coffee env
class CoffeeSway:
    """A cheap stateless base for the coffee env: joint targets swaying with time."""

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        from gym_coffee.env import OBS_SLICES
        from gym_coffee.robot import NEUTRAL_JOINTS, action_from_targets

        obs = np.atleast_2d(np.asarray(observation, dtype=np.float64))
        t = obs[:, OBS_SLICES["time"]]
        q = obs[:, OBS_SLICES["joint_pos"]]
        target = NEUTRAL_JOINTS + 0.3 * np.sin(2.0 * t + np.arange(7))
        a = action_from_targets(q, target, 0.04)
        return (a if np.ndim(observation) == 2 else a[0]), state


def make_coffee():
    import gym_coffee  # noqa: F401

    return gym.make("gym_coffee/CoffeeTask-v0")


def coffee_gate(start=0.5):
    from gym_coffee.env import OBS_SLICES

    return PhaseGate(
        start=start,
        ramp=0.1,
        source="observation",
        time_index=OBS_SLICES["time"].start,
        time_scale=4.0,
    )


def test_zero_residual_reproduces_base_trajectory_coffee():
    base = CoffeeSway()
    ref_obs, _ = rollout_base(make_coffee(), base, seed=11, n_steps=120)
    env = ResidualWrapper(make_coffee(), base, gate=coffee_gate(0.3), residual_dims=range(7))
    obs, _ = env.reset(seed=11)
    got = [obs[: ref_obs.shape[1]]]
    for _ in range(120):
        obs, *_ = env.step(np.zeros(7, np.float32))
        got.append(obs[: ref_obs.shape[1]])
    np.testing.assert_array_equal(np.array(got), ref_obs)


def test_tiny_finetune_on_the_coffee_env(tmp_path):
    base = CoffeeSway()
    res = finetune(
        base,
        make_coffee,
        algo="sac",
        total_env_steps=300,
        seed=0,
        gate=coffee_gate(0.5),
        residual_dims=list(range(7)),
        eval_seeds=[20_000],
        eval_freq=300,
        out_dir=tmp_path,
        hyperparameters={"batch_size": 32},
        progress=False,
    )
    assert res.env_steps >= 300
    assert set(res.curve[0]["rates"]) >= {"cup_grasped", "button_pressed", "is_success"}
    loaded = ResidualPolicy.load(tmp_path / "residual_policy.npz", base=base)
    env = make_coffee()
    obs = []
    o, _ = env.reset(seed=20_001)
    for _ in range(80):
        obs.append(o)
        o, *_ = env.step(base.predict(o)[0])
    obs = np.array(obs)
    np.testing.assert_array_equal(
        loaded.predict(obs, deterministic=True)[0], res.policy.predict(obs, deterministic=True)[0]
    )
    assert loaded.predict(obs[0])[0].shape == (8,)

    # A crafted file whose embedded base names a path outside its folder: loading must neither
    # write that path nor anything else, and must fail with the format error.
    with np.load(tmp_path / "residual_policy.npz", allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays["metadata"]))
    target = tmp_path / "outside" / "bashrc"
    payload = b"echo pwned\n"
    for name in (str(target), "../../outside/bashrc"):
        meta["base"] = {
            "embedded": True,
            "name": name,
            "path": name,
            "sha256": hashlib.sha256(payload).hexdigest(),
        }
        arrays["metadata"] = np.array(json.dumps(meta))
        arrays["base_file"] = np.frombuffer(payload, dtype=np.uint8)
        evil = tmp_path / "evil.npz"
        np.savez(evil, **arrays)
        before = sorted(p.name for p in tmp_path.rglob("*"))
        with pytest.raises(ResidualPolicyFormatError, match="embedded base policy"):
            ResidualPolicy.load(evil)
        assert not target.exists()
        assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_gp_policy_kind_is_read_from_the_gp_policy_module():
    from lgp_policy.lfd.policy import FORMAT_NAME
    from lgp_policy.residual.core import gp_policy_kind

    assert gp_policy_kind() == FORMAT_NAME


def _fine_tuning_env_rollout(seed, knock_at_stage=None):
    """Agent rewards and env infos of a scripted-teacher episode in the fine-tuning wrapper,
    with the reward :func:`finetune` trains on by default; optionally the placed cup is knocked
    8 cm off its place the step after ``info["stage"]`` first reaches ``knock_at_stage``."""
    import inspect

    import gym_coffee
    from gym_coffee.env import OBS_SLICES
    from lgp_policy.residual.core import TeacherBase, finetune

    reward_fn = inspect.signature(finetune).parameters["reward_fn"].default
    env = ResidualWrapper(
        gym.make(gym_coffee.ENV_ID),
        TeacherBase(),
        gate=PhaseGate(start=0.0, ramp=0.0, source="observation", time_index=0),
        residual_dims=range(7),
        reward_fn=reward_fn,
    )
    assert OBS_SLICES["time"].start == 0
    env.reset(seed=seed)
    steps, knocked, done = [], False, False
    while not done:
        _, reward, terminated, truncated, info = env.step(np.zeros(7, np.float32))
        steps.append((reward, info))
        done = terminated or truncated
        if knock_at_stage is not None and not knocked and info["stage"] == knock_at_stage:
            sim = env.unwrapped.sim
            pos, quat = sim.get_base_pose("cup")
            sim.set_base_pose("cup", pos + np.array([0.0, -0.08, 0.0]), quat)
            knocked = True
    env.close()
    return steps


def test_fine_tuning_reward_pays_each_stage_change_once_from_real_env_steps():
    """Reaching a stage pays +1 once, losing one (the placed cup knocked away) costs 1.

    The env pays its stage bonus only on a stage change; the reward the residual trains on must
    keep that meaning (an earlier reward divided it by the stage again and paid +1 for losing
    a stage).
    """
    from gym_coffee.env import STAGE_BONUS

    for knock in (None, 2):
        steps = _fine_tuning_env_rollout(seed=4, knock_at_stage=knock)
        stage_terms, previous = [], 0
        for reward, info in steps:
            terms = {k: v for k, v in info.items() if k.startswith("reward_")}
            stage_term = reward - (sum(terms.values()) - terms["reward_stage"])
            assert stage_term == pytest.approx(STAGE_BONUS * (info["stage"] - previous), abs=1e-9)
            if info["stage"] != previous:
                stage_terms.append((previous, info["stage"], round(stage_term, 9)))
            previous = info["stage"]
        if knock is None:  # the teacher succeeds: grasp, place, press, each paid +1
            assert stage_terms == [(0, 1, 1.0), (1, 2, 1.0), (2, 3, 1.0)]
            assert steps[-1][1]["is_success"]
        else:  # placed, then knocked away: the lost stage costs what reaching it paid
            assert stage_terms[:3] == [(0, 1, 1.0), (1, 2, 1.0), (2, 1, -1.0)]
            assert not steps[-1][1]["is_success"]


def test_machine_pose_error_shifts_only_the_observed_machine_position():
    from gym_coffee.env import OBS_SLICES
    from lgp_policy.residual.core import MachinePoseErrorWrapper

    plain, shifted = make_coffee(), MachinePoseErrorWrapper(make_coffee(), low=0.004, high=0.008)
    o1, _ = plain.reset(seed=3)
    o2, info = shifted.reset(seed=3)
    delta = info["machine_pose_error"]
    assert 0.004 <= delta <= 0.008
    yaw = o1[OBS_SLICES["machine_yaw"]][0]
    expected = o1[OBS_SLICES["machine_pos"]].copy()
    expected[:2] -= delta * np.array([np.cos(yaw), np.sin(yaw)])
    np.testing.assert_allclose(o2[OBS_SLICES["machine_pos"]], expected, atol=1e-6)
    rest = np.ones(o1.shape, bool)
    rest[OBS_SLICES["machine_pos"]] = False
    np.testing.assert_array_equal(o1[rest], o2[rest])
    a = np.zeros(8, np.float32)
    np.testing.assert_array_equal(plain.step(a)[0][rest], shifted.step(a)[0][rest])
    assert shifted.reset(seed=3)[1]["machine_pose_error"] == delta  # seeded


def test_press_phase_start_from_the_demonstrations_stage_phases():
    from lgp_policy.app.finetune_cli import PLACED_MARGIN, _press_phase_start, make_gate

    class Reported(PendulumPD):
        def constraint_report(self):
            return {"stage_phases": {"cup_placed": 0.7, "button_pressed": 1.0}}

        def constraint_intervals(self):
            return [{"frame": "machine", "start": 0.5, "end": 1.0}]

    class IntervalsOnly(PendulumPD):
        def constraint_intervals(self):
            return [{"frame": "machine", "start": 0.2}, {"frame": "machine", "start": 0.85}]

    assert _press_phase_start(Reported()) == pytest.approx(0.7 + PLACED_MARGIN)
    assert _press_phase_start(IntervalsOnly()) == pytest.approx(0.85)
    assert _press_phase_start(object()) == pytest.approx(0.8)
    gate = make_gate(Reported())
    assert gate.source == "policy" and gate.start == pytest.approx(0.75)


def test_teacher_base_is_bound_to_the_env_it_acts_in():
    from gym_coffee.teacher import ScriptedTeacher
    from lgp_policy.residual.core import TeacherBase

    env = make_coffee()
    teacher = ScriptedTeacher(env, rng=0, variation=0.0)
    obs, _ = env.reset(seed=4)
    reference = [obs]
    for _ in range(60):
        obs, *_ = env.step(teacher.act(obs))
        reference.append(obs)
    wrapped = ResidualWrapper(make_coffee(), TeacherBase(), gate=coffee_gate(0.0))
    obs, _ = wrapped.reset(seed=4)
    got = [obs[: reference[0].size]]
    for _ in range(60):
        obs, *_ = wrapped.step(np.zeros(8, np.float32))
        got.append(obs[: reference[0].size])
    np.testing.assert_array_equal(np.array(got), np.array(reference))
    with pytest.raises(RuntimeError, match="bind"):
        TeacherBase().predict(obs)


def test_actuation_noise_wrapper_starts_on_an_info_flag():
    from lgp_policy.residual.core import ActuationNoiseWrapper

    rec = Recorder(make_pendulum())
    env = ActuationNoiseWrapper(rec, bias=0.25, start_on_info="go")
    env.reset(seed=0)
    env.step(np.zeros(1, np.float32))
    assert rec.actions[-1][0] == 0.0  # "go" never appears in Pendulum's info: never active
    env = ActuationNoiseWrapper(rec, bias=0.25, noise_std=0.1)
    env.reset(seed=0)
    env.step(np.zeros(1, np.float32))
    first = rec.actions[-1][0]
    env.reset(seed=0)
    env.step(np.zeros(1, np.float32))
    assert rec.actions[-1][0] == first != 0.0  # seeded, and active from the start
