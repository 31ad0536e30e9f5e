"""``--level`` / ``--env-id`` of ``gym-coffee record`` and ``evaluate``: the level's registered id
(``gym_coffee.LEVELS``) reaches the env, and the choice is recorded in the outputs."""

from __future__ import annotations

import json

import pytest

import gym_coffee
from gym_coffee.demonstrations import DemonstrationSet
from lgp_policy.app import commands, evaluation
from lgp_policy.app.cli import main


@pytest.fixture
def seen_env_ids(monkeypatch):
    """Stub the evaluation; collect the ``env_id`` each call was given."""
    seen: list[str] = []

    def fake_evaluate(policy, n_episodes, *args, env_id=gym_coffee.ENV_ID, **kwargs):
        seen.append(env_id)
        return {"n_episodes": n_episodes}

    monkeypatch.setattr(commands, "load_policy", lambda path: object())
    monkeypatch.setattr(evaluation, "evaluate_policy_stages", fake_evaluate)
    monkeypatch.setattr(evaluation, "format_results", lambda r: "formatted")
    return seen


@pytest.mark.parametrize(
    ("options", "level"),
    [([], "easy"), (["--level", "hard"], "hard"), (["--level", "easy"], "easy")]
    + [(["--env-id", env_id], name) for name, env_id in gym_coffee.LEVELS.items()],
)
def test_evaluate_runs_on_the_chosen_level(options, level, tmp_path, seen_env_ids, capsys):
    policy = tmp_path / "policy.npz"
    policy.write_bytes(b"stub")  # never opened: load_policy is stubbed
    out = tmp_path / "r.json"
    argv = ["evaluate", str(policy), "--episodes", "2", "--json", str(out), *options]
    assert main(argv) == 0, capsys.readouterr().err
    assert seen_env_ids == [gym_coffee.LEVELS[level]]
    assert f"on {gym_coffee.LEVELS[level]}" in capsys.readouterr().out
    assert json.loads(out.read_text())["env_id"] == gym_coffee.LEVELS[level]


HARD_FAST = {
    "env_id": gym_coffee.LEVELS["hard"],
    "env_kwargs": {"level": "hard", "physics": "fast"},
}


@pytest.mark.parametrize(
    ("recorded", "options", "level", "physics", "note"),
    [
        # the policy file's record of its demonstrations' env is the default
        (HARD_FAST, [], "hard", "fast", False),
        ({"env_id": gym_coffee.LEVELS["hard"], "env_kwargs": {}}, [], "hard", None, False),
        # what the user gives wins, with a note where it differs from the demonstrations'
        (HARD_FAST, ["--level", "easy"], "easy", "fast", True),
        (HARD_FAST, ["--physics", "default"], "hard", None, True),
        (
            HARD_FAST,
            ["--env-id", gym_coffee.LEVELS["hard"], "--physics", "fast"],
            "hard",
            "fast",
            False,
        ),
        # no record, or an env that is not a coffee level: the defaults
        (None, [], "easy", None, False),
        ({"env_id": "CartPole-v1", "env_kwargs": {}}, [], "easy", None, False),
    ],
)
@pytest.mark.parametrize("residual", [False, True])
def test_evaluate_defaults_to_the_env_of_the_policys_demonstrations(
    recorded, options, level, physics, note, residual, tmp_path, monkeypatch, capsys
):
    from types import SimpleNamespace

    seen: list[tuple[str, dict]] = []

    def fake_evaluate(policy, n_episodes, *args, env_id=None, env_kwargs=None, **kwargs):
        seen.append((env_id, env_kwargs))
        return {"n_episodes": n_episodes}

    gp = SimpleNamespace(demonstrations_env_=recorded)
    loaded = SimpleNamespace(base=gp) if residual else gp  # a residual policy: its base's record
    monkeypatch.setattr(commands, "load_policy", lambda path: loaded)
    monkeypatch.setattr(evaluation, "evaluate_policy_stages", fake_evaluate)
    monkeypatch.setattr(evaluation, "format_results", lambda r: "formatted")
    policy = tmp_path / "policy.npz"
    policy.write_bytes(b"stub")  # never opened: load_policy is stubbed
    out = tmp_path / "r.json"
    argv = ["evaluate", str(policy), "--episodes", "2", "--json", str(out), *options]
    assert main(argv) == 0
    expected = {} if physics is None else {"physics": physics}
    assert seen == [(gym_coffee.LEVELS[level], expected)]
    result = json.loads(out.read_text())
    assert (result["env_id"], result["env_kwargs"]) == (gym_coffee.LEVELS[level], expected)
    captured = capsys.readouterr()
    assert f"on {gym_coffee.LEVELS[level]}" in captured.out
    assert ("fitted on demonstrations of" in captured.err) == note


def test_evaluate_help_lists_the_levels(capsys):
    with pytest.raises(SystemExit) as info:
        main(["evaluate", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "--level" in out and "--env-id" in out
    for name, env_id in gym_coffee.LEVELS.items():
        assert name in out and env_id in out


def test_record_notes_seeds_that_evaluation_uses(tmp_path, capsys):
    out = tmp_path / "d.npz"
    assert main(["record", "--n", "1", "--seed", "10000", "--out", str(out), "--no-progress"]) == 0
    assert (
        "note: seeds [10000] are also layouts of `gym-coffee evaluate`" in capsys.readouterr().err
    )
    assert main(["record", "--n", "1", "--seed", "9000", "--out", str(out), "--force"]) == 0
    assert "note" not in capsys.readouterr().err


def test_record_on_the_hard_level(tmp_path, capsys):
    """A real recording: the demonstration file says it came from the hard level's env."""
    out = tmp_path / "hard.npz"
    argv = ["record", "--n", "1", "--seed", "7", "--out", str(out), "--level", "hard"]
    assert main([*argv, "--no-progress"]) == 0, capsys.readouterr().err
    assert f"on {gym_coffee.LEVELS['hard']}" in capsys.readouterr().out
    demos = DemonstrationSet.load(out)
    assert demos.metadata["env_id"] == gym_coffee.LEVELS["hard"]
    assert len(demos) == 1 and demos[0].success


@pytest.mark.parametrize(
    ("options", "level"),
    [
        ([], "easy"),
        (["--level", "hard"], "hard"),
        (["--env-id", gym_coffee.LEVELS["hard"]], "hard"),
    ],
)
def test_run_passes_the_chosen_level_to_the_pipeline(options, level, tmp_path, monkeypatch):
    from lgp_policy.app import pipeline

    seen: list[str | None] = []
    monkeypatch.setattr(pipeline, "run_pipeline", lambda out, **kw: seen.append(kw["env_id"]))
    assert main(["run", "--out", str(tmp_path / "r"), *options]) == 0
    assert seen == [gym_coffee.LEVELS[level]]


@pytest.mark.parametrize(("options", "progress"), [([], True), (["--no-progress"], False)])
def test_run_no_progress(options, progress, tmp_path, monkeypatch):
    from lgp_policy.app import pipeline

    seen: list[bool] = []
    monkeypatch.setattr(pipeline, "run_pipeline", lambda out, **kw: seen.append(kw["progress"]))
    assert main(["run", "--out", str(tmp_path / "r"), *options]) == 0
    assert seen == [progress]


@pytest.mark.parametrize(
    ("options", "kwargs"), [([], {}), (["--physics", "fast"], {"physics": "fast"})]
)
def test_run_and_evaluate_pass_the_physics_preset(options, kwargs, tmp_path, monkeypatch):
    """``--physics`` reaches the pipeline's and the evaluation's env keywords (the default
    physics as no keyword) and the evaluation's JSON records it."""
    from lgp_policy.app import pipeline

    seen: list[dict] = []
    monkeypatch.setattr(pipeline, "run_pipeline", lambda out, **kw: seen.append(kw["env_kwargs"]))
    assert main(["run", "--out", str(tmp_path / "r"), *options]) == 0

    def fake_evaluate(policy, n_episodes, *args, env_kwargs=None, **kw):
        seen.append(dict(env_kwargs or {}))
        return {"n_episodes": n_episodes}

    monkeypatch.setattr(commands, "load_policy", lambda path: object())
    monkeypatch.setattr(evaluation, "evaluate_policy_stages", fake_evaluate)
    monkeypatch.setattr(evaluation, "format_results", lambda r: "formatted")
    policy, out = tmp_path / "policy.npz", tmp_path / "r.json"
    policy.write_bytes(b"stub")  # never opened: load_policy is stubbed
    assert main(["evaluate", str(policy), "--episodes", "2", "--json", str(out), *options]) == 0
    assert seen == [kwargs, kwargs]
    assert json.loads(out.read_text())["env_kwargs"] == kwargs


def test_record_with_the_fast_physics(tmp_path, capsys):
    """A real recording with ``--physics fast``: the teacher succeeds and the file records the
    preset among its env keywords."""
    out = tmp_path / "fast.npz"
    argv = ["record", "--n", "1", "--seed", "7", "--out", str(out), "--physics", "fast"]
    assert main([*argv, "--no-progress"]) == 0, capsys.readouterr().err
    demos = DemonstrationSet.load(out)
    assert demos.metadata["env_kwargs"].get("physics") == "fast"
    assert len(demos) == 1 and demos[0].success
