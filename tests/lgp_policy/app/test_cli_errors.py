"""``gym-coffee``: one error path (one line, exit 2, ``--debug``), Ctrl-C, one overwrite rule.

The commands' work is replaced by stubs here, so these tests check only the CLI layer (fast);
real runs are in test_cli_record.py and test_end_to_end.py.
"""

from __future__ import annotations

import errno
import json

import pytest

import gym_coffee
from lgp_policy import _io
from lgp_policy._io import FileFormatError
from lgp_policy.app import commands, evaluation, pipeline
from lgp_policy.app.cli import main


def _one_line(err: str, command: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith(f"gym-coffee {command}: error: "), err
    return lines[0]


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if a command starts working (loads a policy, evaluates, runs)."""

    def forbidden(*args, **kwargs):
        raise AssertionError("work started before the arguments were checked")

    monkeypatch.setattr(commands, "load_policy", forbidden)
    monkeypatch.setattr(pipeline, "run_pipeline", forbidden)
    monkeypatch.setattr(evaluation, "evaluate_policy_stages", forbidden)


@pytest.fixture
def policy_file(tmp_path):
    path = tmp_path / "policy.npz"
    path.write_bytes(b"stub")  # never opened: load_policy is stubbed
    return path


@pytest.fixture
def fake_evaluation(monkeypatch):
    result = {"seeds": [10000], "rates": {"cup_grasped": 1.0}}
    monkeypatch.setattr(commands, "load_policy", lambda path: object())
    monkeypatch.setattr(evaluation, "evaluate_policy_stages", lambda *a, **k: dict(result))
    monkeypatch.setattr(evaluation, "format_results", lambda r: "formatted")
    return result


def test_library_errors_are_one_line_exit_2(monkeypatch, capsys, policy_file):
    def bad(path):
        raise FileFormatError(f"{path}: member 'metadata': expected a JSON object")

    monkeypatch.setattr(commands, "load_policy", bad)
    assert main(["evaluate", str(policy_file), "--episodes", "1"]) == 2
    line = _one_line(capsys.readouterr().err, "evaluate")
    assert "member 'metadata': expected a JSON object" in line


def test_debug_shows_the_traceback(monkeypatch, capsys, policy_file):
    def bad(path):
        raise ValueError("boom")

    monkeypatch.setattr(commands, "load_policy", bad)
    assert main(["evaluate", str(policy_file), "--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err
    assert err.rstrip().endswith("gym-coffee evaluate: error: argument POLICY: boom")
    assert main(["--debug", "evaluate", str(policy_file)]) == 2
    assert "Traceback" in capsys.readouterr().err


def test_internal_errors_and_disk_errors_exit_1(monkeypatch, capsys, policy_file):
    def bug(path):
        raise TypeError("unsupported operand")

    monkeypatch.setattr(commands, "load_policy", bug)
    assert main(["evaluate", str(policy_file)]) == 1
    line = _one_line(capsys.readouterr().err, "evaluate")
    assert "internal error: TypeError" in line and "--debug" in line


def test_ctrl_c_is_one_line_exit_130(monkeypatch, capsys, policy_file):
    def interrupted(path):
        raise KeyboardInterrupt

    monkeypatch.setattr(commands, "load_policy", interrupted)
    assert main(["evaluate", str(policy_file)]) == 130
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert [line for line in err.splitlines() if line] == [
        "gym-coffee evaluate: interrupted; finished files are kept, partial ones removed"
    ]


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["evaluate", "{policy}", "--json", "{tmp}/old.json"], "old.json exists; pass --force"),
        (["evaluate", "{policy}", "--video", "{tmp}/old.gif"], "old.gif exists; pass --force"),
        (["evaluate", "{policy}", "--video", "{tmp}/v.avi"], "expected a name ending in .mp4"),
        (["evaluate", "{policy}", "--json", "{tmp}/r.txt"], "expected a name ending in .json"),
        (["evaluate", "{policy}", "--json", "{tmp}/a.json", "--video", "{tmp}/a.json"], ""),
        (["evaluate", "{policy}", "--json", "{tmp}/old.json/x.json"], "is not a folder"),
        (["evaluate", "{policy}", "--json", "{tmp}"], "is a folder"),
        (["evaluate", "{policy}", "--address", "auto"], "--address: needs --backend ray"),
        (["evaluate", "{policy}", "--seed", "2147483000"], "argument --seed: expected at most"),
        (["run", "--out", "{tmp}"], "is not empty"),
        (["run", "--out", "{tmp}/old.json"], "is a file; expected a folder"),
        (["run", "--out", "{tmp}/new", "--combine", "rbcm", "--model", "exact"], "--model local"),
        (["fit", "{policy}", "--out", "{policy}", "--force"], "is also an input"),
        (["fit", "{policy}", "--out", "{tmp}/p.json"], "expected a name ending in .npz"),
        (["record", "--out", "{tmp}/d.npz", "--env-id", "CartPole-v1"], "--env-id: expected"),
        (["record", "--out", "{tmp}/old.json"], "expected a name ending in .npz"),
    ],
)
def test_outputs_are_checked_before_any_work(
    argv, fragment, tmp_path, policy_file, no_work, capsys
):
    (tmp_path / "old.json").write_text('{"keep": 1}')
    (tmp_path / "old.gif").write_bytes(b"GIF89a")
    argv = [a.format(tmp=tmp_path, policy=policy_file) for a in argv]
    assert main(argv) == 2
    line = _one_line(capsys.readouterr().err, argv[0])
    assert fragment in line
    assert "argument " in line
    assert (tmp_path / "old.json").read_text() == '{"keep": 1}'


def test_evaluate_json_is_atomic_on_a_full_disk(
    monkeypatch, tmp_path, policy_file, fake_evaluation, capsys
):
    path = tmp_path / "results.json"
    path.write_text('{"old": true}')

    def no_space(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_io.os, "fsync", no_space)
    assert main(["evaluate", str(policy_file), "--json", str(path), "--force"]) == 1
    assert "No space left on device" in _one_line(capsys.readouterr().err, "evaluate")
    assert json.loads(path.read_text()) == {"old": True}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["policy.npz", "results.json"]


def test_evaluate_json_written_with_force_and_deprecated_alias(
    tmp_path, policy_file, fake_evaluation, capsys
):
    path = tmp_path / "results.json"
    assert main(["evaluate", str(policy_file), "--json", str(path)]) == 0
    assert json.loads(path.read_text()) == {
        **fake_evaluation,
        "env_id": gym_coffee.ENV_ID,
        "env_kwargs": {},
    }
    assert main(["evaluate", str(policy_file), "--json", str(path)]) == 2
    assert main(["evaluate", str(policy_file), "--json", str(path), "--overwrite"]) == 0
    assert "--overwrite is deprecated; use --force" in capsys.readouterr().err


def test_run_force_replaces_only_the_files_run_writes(monkeypatch, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    for name in ("results.json", "fig4_constraints.png", "rollout.gif"):
        (out / name).write_text("old run")
    (out / "notes.txt").write_text("mine")
    seen = {}

    def fake_run(folder, **kwargs):
        seen["files"] = sorted(p.name for p in folder.iterdir())
        seen["kwargs"] = kwargs

    monkeypatch.setattr(pipeline, "run_pipeline", fake_run)
    assert main(["run", "--out", str(out), "--episodes", "3", "--seed", "5"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert main(["run", "--out", str(out), "--episodes", "3", "--seed", "5", "--force"]) == 0
    # nothing deleted before the run: the pipeline sets the earlier files aside (tested there)
    assert seen["files"] == ["fig4_constraints.png", "notes.txt", "results.json", "rollout.gif"]
    assert seen["kwargs"]["force"] is True
    assert seen["kwargs"]["n_episodes"] == 3 and seen["kwargs"]["seed"] == 5
    (out / "results.json").unlink()
    (out / "policy.npz").mkdir()  # a folder where run writes a file: refused, nothing touched
    assert main(["run", "--out", str(out), "--force"]) == 2
    assert "policy.npz is a folder; this command writes a file there" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == [
        "fig4_constraints.png",
        "notes.txt",
        "policy.npz",
        "rollout.gif",
    ]


def test_record_refuses_before_making_an_env(monkeypatch, tmp_path, capsys):
    import gymnasium as gym

    def forbidden(*a, **k):
        raise AssertionError("env made before the arguments were checked")

    monkeypatch.setattr(gym, "make", forbidden)
    (tmp_path / "v.gif").write_bytes(b"GIF89a")
    argv = ["record", "--out", str(tmp_path / "d.npz"), "--video", str(tmp_path / "v.gif")]
    assert main(argv) == 2
    assert "v.gif exists; pass --force" in _one_line(capsys.readouterr().err, "record")


def test_a_real_sigint_ends_with_one_line_and_130(tmp_path):
    """SIGINT to the process group (what Ctrl-C in a terminal sends) while a command works."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    script = tmp_path / "slow_evaluate.py"
    script.write_text(
        "import sys, time\n"
        "from lgp_policy.app import commands, evaluation\n"
        "from lgp_policy.app.cli import main\n"
        "commands.load_policy = lambda path: object()\n"
        "def slow(*a, **k):\n"
        "    print('working', flush=True)\n"
        "    time.sleep(60)\n"
        "evaluation.evaluate_policy_stages = slow\n"
        f"sys.exit(main(['evaluate', {str(tmp_path / 'p.npz')!r}, '--json', "
        f"{str(tmp_path / 'r.json')!r}]))\n"
    )
    (tmp_path / "p.npz").write_bytes(b"stub")
    root = Path(__file__).resolve().parents[3]
    proc = subprocess.Popen(
        [sys.executable, str(script)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(root)},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        start_new_session=True,
    )
    try:
        assert proc.stdout is not None
        printed = [proc.stdout.readline().strip() for _ in range(2)]  # "evaluating ...", then
        assert printed[0].startswith("evaluating ") and printed[1] == "working", printed
        t0 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130 and time.monotonic() - t0 < 10
    ours = [line for line in err.splitlines() if line.startswith("gym-coffee")]
    assert ours == [
        "gym-coffee evaluate: interrupted; finished files are kept, partial ones removed"
    ]
    assert "Traceback" not in err
    assert not (tmp_path / "r.json").exists()
