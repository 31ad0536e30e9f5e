"""``gym-coffee finetune``: arguments checked before any work, seeds locally or as Ray tasks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lgp_policy.app.cli import main

pytest.importorskip("stable_baselines3")


@pytest.fixture(scope="module")
def gp_policy(tmp_path_factory):
    """A small real GP policy file (2 teacher demonstrations, empirical encoder)."""
    import gymnasium as gym

    import gym_coffee
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    env = gym.make(gym_coffee.ENV_ID)
    demos = gym_coffee.collect_demonstrations(env, n=2, seed=0, progress=False)
    env.close()
    path = tmp_path_factory.mktemp("base") / "policy.npz"
    GPDemonstrationPolicy(n_steps=60, n_grid=200, model="empirical").fit(demos).save(path)
    return path


BAD_ARGUMENTS = {
    "--eval-episodes 0": "argument --eval-episodes: expected an integer in [1, 1000000000], got 0",
    "--n-envs 0": "argument --n-envs: expected an integer in [1, 64], got 0",
    "--gate-start 5": "argument --gate-start: expected a finite number in [0, 1], got '5'",
    "--gate-start nan": "argument --gate-start: expected a finite number in [0, 1], got 'nan'",
    "--scale 1e308": "argument --scale: expected a finite number in (0, 2], got '1e308'",
    "--scale nan": "argument --scale: expected a finite number in (0, 2], got 'nan'",
    "--scale 0": "argument --scale: expected a finite number in (0, 2], got '0'",
    "--timesteps -5": "argument --timesteps: expected an integer in [1, 1000000000], got -5",
    "--calibration-bias -0.002": "argument --calibration-bias: expected a finite number in [0,",
    "--seeds -1": "argument --seeds: expected a seed in [0, 2147483647], got -1",
    "--eval-freq -1": "argument --eval-freq: expected an integer (0: never) in [0,",
}


@pytest.mark.parametrize("extra", sorted(BAD_ARGUMENTS))
def test_bad_arguments_get_one_line_and_exit_2(extra, tmp_path, capsys):
    policy = tmp_path / "policy.npz"
    policy.write_bytes(b"")
    with pytest.raises(SystemExit) as exc:
        main(["finetune", str(policy), *extra.split()])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"gym-coffee finetune: error: {BAD_ARGUMENTS[extra]}" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["policy.npz"]


def test_checks_before_work(tmp_path, gp_policy, capsys):
    out = tmp_path / "out"
    (out / "seed3").mkdir(parents=True)
    (out / "seed3" / "residual_policy.npz").write_bytes(b"old")
    cases = {
        ("--seeds", "1", "1"): "argument --seeds: repeated seeds [1, 1]",
        ("--address", "ray://x:1"): "argument --address: needs --backend ray",
        ("--seeds", "3"): f"argument --out: folder {out / 'seed3'} is not empty",
    }
    for extra, message in cases.items():
        assert main(["finetune", str(gp_policy), "--out", str(out), *extra]) == 2
        assert f"gym-coffee finetune: error: {message}" in capsys.readouterr().err
    not_a_policy = tmp_path / "notes.npz"
    not_a_policy.write_text("text")
    assert main(["finetune", str(not_a_policy), "--out", str(out)]) == 2
    assert "error: argument POLICY: " in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["seed3"]
    assert (out / "seed3" / "residual_policy.npz").read_bytes() == b"old"


def test_notes_when_the_policys_demonstrations_are_of_another_env(
    tmp_path, gp_policy, capsys, monkeypatch
):
    """finetune trains on the easy level; a policy of hard-level demonstrations gets a note."""
    import gym_coffee
    from lgp_policy.app import finetune_cli

    monkeypatch.setattr(finetune_cli, "run_jobs", lambda jobs, out, **kw: {})  # no training
    assert main(["finetune", str(gp_policy), "--out", str(tmp_path / "a")]) == 0
    assert "note" not in capsys.readouterr().err
    with np.load(gp_policy, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays["metadata"]))
    meta["demonstrations_env"] = {"env_id": gym_coffee.LEVELS["hard"], "env_kwargs": {}}
    arrays["metadata"] = np.array(json.dumps(meta))
    hard = tmp_path / "hard.npz"
    np.savez(hard, **arrays)
    assert main(["finetune", str(hard), "--out", str(tmp_path / "b")]) == 0
    err = capsys.readouterr().err
    assert f"note: the policy was fitted on demonstrations of {gym_coffee.LEVELS['hard']}" in err


TINY = ["--timesteps", "40", "--eval-episodes", "1", "--eval-freq", "0", "--checkpoint-freq", "0"]


def _params(path):
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files if k.startswith(("param/", "obs_norm/"))}


def test_seeds_as_ray_tasks_give_the_local_results(tmp_path, gp_policy, capsys):
    """Seed 1 trained in this process (the CLI, local backend) and as a Ray task (next to
    seed 2) gives the same policy and curve; the policy file loads with its embedded base."""
    ray = pytest.importorskip("ray")
    from lgp_policy.app.finetune_cli import FinetuneJob, run_jobs
    from lgp_policy.residual import load_any_policy

    local = tmp_path / "local"
    assert (
        main(
            [
                "finetune",
                str(gp_policy),
                *TINY,
                "--seeds",
                "1",
                "--out",
                str(local),
                "--no-progress",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "seed 1:" in printed and "button_pressed" in printed
    settings = {
        "algo": "sac",
        "timesteps": 40,
        "scale": 0.5,
        "gate_start": None,
        "eval_episodes": 1,
        "eval_freq": 0,
        "checkpoint_freq": 0,
        "n_envs": 1,
        "calibration_bias": 0.0,
        "reward": "shaped",
        "progress": False,
    }
    base_bytes = gp_policy.read_bytes()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = tmp_path / "ray"
        summaries = run_jobs(
            [FinetuneJob(base_bytes, s, settings) for s in (1, 2)], remote, backend="ray"
        )
    finally:
        ray.shutdown()
    assert sorted(summaries) == [1, 2]
    a, b = (
        _params(local / "seed1" / "residual_policy.npz"),
        _params(remote / "seed1" / "residual_policy.npz"),
    )
    assert sorted(a) == sorted(b)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    local_curve = json.loads((local / "seed1" / "learning_curve.json").read_text())["curve"]
    assert [c["rates"] for c in summaries[1]["curve"]] == [c["rates"] for c in local_curve]
    assert (remote / "seed2" / "learning_curve.png").stat().st_size > 1000
    assert any(
        not np.array_equal(a[k], v)
        for k, v in _params(remote / "seed2" / "residual_policy.npz").items()
    )
    policy = load_any_policy(local / "seed1" / "residual_policy.npz")  # embedded base, from memory
    assert type(policy.base).__name__ == "GPDemonstrationPolicy"


def test_calibration_bias_is_the_envs_keyword():
    from gym_coffee.env import MAX_PERTURBATION
    from lgp_policy.app.finetune_cli import MAX_CALIBRATION_BIAS, build_env_fn

    assert MAX_CALIBRATION_BIAS == MAX_PERTURBATION
    env = build_env_fn(0.002)()
    assert env.unwrapped.calibration_bias == 0.002
    env.close()
