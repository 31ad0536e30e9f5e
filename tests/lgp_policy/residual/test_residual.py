"""Residual RL: gate, wrapper, zero-init, fine-tuning, save/load round trips, the rl extra."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile

import numpy as np
import pytest
from residual_helpers import (
    TIME_INDEX,
    CoffeeSway,
    PendulumPD,
    Recorder,
    coffee_gate,
    make_coffee,
    make_pendulum,
    pendulum_curve,
    rollout_base,
)

from lgp_policy.residual import (
    RL_EXTRA_HINT,
    PhaseGate,
    ResidualWrapper,
    gate_from_config,
    require_rl,
)


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
    from lgp_policy.app.cli import main

    monkeypatch.setitem(sys.modules, "torch", None)
    policy = tmp_path / "policy.npz"
    policy.write_bytes(b"")
    assert main(["finetune", str(policy), "--timesteps", "10"]) == 1
    err = capsys.readouterr().err
    assert RL_EXTRA_HINT in err and len(err.strip().splitlines()) == 1


def test_modules_import_without_sb3_and_torch():
    code = (
        "import sys\n"
        "sys.modules['stable_baselines3'] = None\n"
        "sys.modules['torch'] = None\n"
        "import lgp_policy.residual, lgp_policy.app.finetune_cli\n"
        "from lgp_policy.residual import ResidualWrapper, ResidualPolicy, PhaseGate\n"
        "import numpy as np, gymnasium as gym\n"
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

from lgp_policy.residual import DEFAULT_HYPERPARAMETERS, ResidualPolicy, finetune  # noqa: E402
from lgp_policy.residual.models import build_model  # noqa: E402


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
    model = build_model(algo, env, hp, seed=0)
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
        progress=False,
        skip_ungated=False,
    )
    buffer = result.policy.model.replay_buffer
    actions = buffer.actions[: buffer.pos].ravel()
    assert actions.size >= 50
    assert np.max(np.abs(actions)) < 0.95  # uniform warm-up would reach ~1
    assert np.mean(np.abs(actions)) < 0.35  # uniform warm-up: 0.5


def test_tiny_finetune_saves_a_policy_that_loads_and_predicts_identically(tmp_path, monkeypatch):
    base = PendulumPD()
    scratch = tmp_path / "system-tmp"  # the system's temporary directory for this test
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    result = finetune(
        base,
        make_pendulum,
        algo="sac",
        total_env_steps=300,
        seed=1,
        scale=0.5,
        gate=PhaseGate(start=0.5, ramp=0.0),
        evaluate=pendulum_curve,
        eval_freq=150,
        checkpoint_freq=150,
        out_dir=tmp_path / "run",
        hyperparameters={"batch_size": 32},
        progress=False,
    )
    assert result.env_steps >= 300
    assert result.agent_steps < result.env_steps  # ungated steps were skipped
    # no SB3-<date> log folder left behind (torch may keep its own cache there)
    assert not [p.name for p in scratch.iterdir() if p.name.startswith("SB3-")]
    assert result.curve[0]["env_steps"] == 0 and len(result.curve) >= 3
    run = tmp_path / "run"
    summary = json.loads((run / "learning_curve.json").read_text())
    assert summary["algo"] == "sac" and summary["curve"][-1]["env_steps"] == result.env_steps
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
    # one row takes another matrix kernel than a batch: equal to float32 rounding, not bit for bit
    np.testing.assert_allclose(single, expected[40], rtol=1e-6, atol=1e-7)
    # Closed gate: exactly the base.
    base_action, _ = base.predict(obs[:32])
    np.testing.assert_array_equal(got[:32], base_action)

    with pytest.raises(FileExistsError, match="force"):
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


# ---------------------------------------------------------------------------- the coffee env
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


def test_keep_best_returns_and_saves_the_best_curve_point(tmp_path):
    """``keep_best``: the policy of the curve point with the highest success (here the middle
    one of three, scored by a scripted curve) is returned and saved, with its normaliser; it
    equals that step's checkpoint, not the last state."""
    scores = iter([0.5, 1.0, 0.2, 0.2])

    def curve(policy):
        return {"episodes": 1, "rates": {"is_success": next(scores)}}

    with pytest.raises(ValueError, match="keep_best needs evaluate"):
        finetune(PendulumPD(), make_pendulum, total_env_steps=10, keep_best=True, progress=False)
    result = finetune(
        PendulumPD(),
        make_pendulum,
        total_env_steps=300,
        seed=2,
        gate=PhaseGate(start=0.0, ramp=0.0),
        evaluate=curve,
        eval_freq=150,
        keep_best=True,
        checkpoint_freq=150,
        out_dir=tmp_path / "run",
        hyperparameters={"batch_size": 32, "learning_starts": 20},
        progress=False,
    )
    run = tmp_path / "run"
    assert [c["env_steps"] for c in result.curve][:2] == [0, 150]
    assert result.kept_env_steps == 150
    assert json.loads((run / "learning_curve.json").read_text())["kept_env_steps"] == 150
    obs = np.stack([make_pendulum().observation_space.sample() for _ in range(32)])
    obs[:, TIME_INDEX] = np.linspace(0, 1, 32)
    saved = ResidualPolicy.load(run / "residual_policy.npz", base=PendulumPD())
    at_150 = ResidualPolicy.load(run / "checkpoints" / "step_0000150.npz", base=PendulumPD())
    got, _ = saved.predict(obs, deterministic=True)
    np.testing.assert_array_equal(got, at_150.predict(obs, deterministic=True)[0])
    np.testing.assert_array_equal(result.policy.predict(obs, deterministic=True)[0], got)
    last = sorted((run / "checkpoints").iterdir())[-1]
    assert last.name != "step_0000150.npz"  # training went on past the kept point
    later = ResidualPolicy.load(last, base=PendulumPD()).predict(obs, deterministic=True)[0]
    assert not np.array_equal(later, got)
