"""The whole pipeline from the command line: ``gym-coffee run`` (2 demonstrations, 2 evaluation
layouts), each layout rolled out once, then ``evaluate`` on its policy in 2 workers; and a run
interrupted after the evaluation keeps what finished."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("gym_coffee.teacher")

import gym_coffee
from lgp_policy import rollout
from lgp_policy.app import backends, evaluation, pipeline, plots
from lgp_policy.app.cli import main
from lgp_policy.lfd.policy import GPDemonstrationPolicy


def _count_episodes(monkeypatch) -> list[int]:
    """Patch the one episode loop wherever it is imported; return the list of seeds rolled out."""
    seeds: list[int] = []
    real = rollout.run_episode

    def counted(policy, env, seed, **kwargs):
        seeds.append(int(seed))
        return real(policy, env, seed, **kwargs)

    for module in (backends, evaluation):
        monkeypatch.setattr(module, "run_episode", counted)
    monkeypatch.setattr(rollout, "run_episode", counted)
    return seeds


def test_run_then_evaluate(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    real_run_episode = rollout.run_episode
    seeds = _count_episodes(monkeypatch)
    assert main(["run", "--out", str(out), "--demos", "2", "--episodes", "2", "--seed", "3"]) == 0
    monkeypatch.setattr(rollout, "run_episode", real_run_episode)
    printed = capsys.readouterr().out
    assert "button_pressed" in printed and "Wilson" in printed
    for i, (name, _) in enumerate(pipeline.PIPELINE_STAGES, 1):
        assert f"[{i}/5] {name}:" in printed
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == "complete"
    assert results["done"] == [name for name, _ in pipeline.PIPELINE_STAGES]
    assert set(results["timings"]) == set(results["done"]) | {"total"}
    assert results["evaluation"]["n_episodes"] == 2
    assert sorted(seeds) == results["evaluation"]["seeds"]  # each layout rolled out once
    assert results["demonstrations"]["n"] == 2
    assert set(results["evaluation"]["stages"]) >= {"cup_grasped", "cup_placed", "button_pressed"}
    for name in pipeline.RUN_FILES:
        assert (out / name).stat().st_size > 0, name
    # the constraint report agrees with the demonstrated stages: cup tight at the grasp,
    # machine tight at the place and the press
    checks = {c["stage"]: c for c in results["constraints"]["checks"]}
    assert set(checks) == {"cup_grasped", "cup_placed", "button_pressed"}
    assert all(c["tight"] for c in checks.values()), checks
    policy = GPDemonstrationPolicy.load(out / "policy.npz")
    assert policy.constraints_ == results["constraints"]
    # the Fig. 5 trace from the evaluation roll-out is the one a fresh roll-out gives
    fresh = plots.rollout_trace(policy, results["evaluation"]["seeds"][0])
    assert len(fresh["phase"]) == results["evaluation"]["episodes"][0]["length"]
    # a figure never replaces a file without force, and is written whole
    fig4 = out / "fig4_constraints.png"
    before = fig4.read_bytes()
    with pytest.raises(FileExistsError, match="force"):
        plots.plot_constraint_profile(policy, fig4)
    with pytest.raises(FileExistsError, match="force"):
        plots.make_all(policy, out, seed=3)
    assert fig4.read_bytes() == before
    plots.plot_constraint_profile(policy, fig4, force=True)
    assert fig4.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporary left

    js = tmp_path / "eval.json"
    argv = ["evaluate", str(out / "policy.npz"), "--episodes", "2", "--seed", "3"]
    assert main([*argv, "--workers", "2", "--json", str(js), "--no-progress"]) == 0
    again = json.loads(js.read_text())
    assert again["episodes"] == results["evaluation"]["episodes"]


def test_interrupted_run_keeps_what_finished(tmp_path, monkeypatch):
    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(plots, "make_all", interrupt)
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        pipeline.run_pipeline(
            out,
            n_demos=1,
            n_episodes=1,
            seed=5,
            video=False,
            policy_kwargs={"model": "empirical"},
            progress=False,
            env_id="hard",
            env_kwargs={"physics": "fast"},
        )
    results = json.loads((out / "results.json").read_text())
    assert results["env_id"] == gym_coffee.LEVELS["hard"]  # the level, recorded and evaluated
    assert results["env_kwargs"] == {"physics": "fast"}
    demos = gym_coffee.DemonstrationSet.load(out / "demonstrations.npz")
    assert demos.metadata["env_kwargs"]["physics"] == "fast"
    assert results["status"] == "interrupted" and results["interrupted_in"] == "plots"
    assert results["done"] == ["record", "fit", "evaluate"]
    assert results["evaluation"]["n_episodes"] == 1
    assert (out / "policy.npz").exists() and not (out / "rollout.gif").exists()
    with pytest.raises(FileExistsError, match="force"):  # a second run never mixes into it
        pipeline.run_pipeline(out, n_demos=1, n_episodes=1, progress=False)


def test_a_forced_run_sets_the_earlier_run_aside_until_it_completes(tmp_path, monkeypatch):
    """``force``: an interrupted run leaves the earlier run's files whole in ``.previous-run-*``
    (named in results.json), the folder holding only the new run's files; a complete run
    removes them."""
    out = tmp_path / "run"
    out.mkdir()
    for name in ("policy.npz", "results.json", "rollout.gif"):
        (out / name).write_text(f"earlier {name}")
    (out / "notes.txt").write_text("mine")
    quick = dict(n_demos=1, n_episodes=1, seed=5, video=False, progress=False, force=True)
    quick["policy_kwargs"] = {"model": "empirical"}

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(plots, "make_all", interrupt)
    with pytest.raises(KeyboardInterrupt):
        pipeline.run_pipeline(out, **quick)
    results = json.loads((out / "results.json").read_text())
    aside = Path(results["previous_run"])
    assert aside.parent == out and aside.name.startswith(".previous-run-")
    assert {p.name: p.read_text() for p in aside.iterdir()} == {
        n: f"earlier {n}" for n in ("policy.npz", "results.json", "rollout.gif")
    }
    assert not (out / "rollout.gif").exists()  # not this run's: no mix of two runs
    assert (out / "notes.txt").read_text() == "mine"
    monkeypatch.undo()
    pipeline.run_pipeline(out, **{**quick, "video": True})
    left = sorted(p.name for p in out.iterdir())
    assert [n for n in left if n.startswith(".")] == [aside.name]  # the interrupted run's aside
    assert {"notes.txt", "policy.npz", "results.json", "rollout.gif"} <= set(left)
    assert json.loads((out / "results.json").read_text())["status"] == "complete"


def test_run_refuses_bad_env_kwargs_before_any_work(tmp_path):
    with pytest.raises(ValueError, match=r"^physics must"):
        pipeline.run_pipeline(
            tmp_path / "run", n_demos=1, n_episodes=1, env_kwargs={"physics": "slow"}
        )
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("env_id", ["medium", "CartPole-v9", 3])
def test_run_refuses_an_unknown_task_before_any_work(tmp_path, env_id):
    with pytest.raises(ValueError, match="env_id"):
        pipeline.run_pipeline(tmp_path / "run", n_demos=1, n_episodes=1, env_id=env_id)
    assert not (tmp_path / "run").exists()
