"""Bad input, table-driven (issue 8): every class gets one clear error naming what is wrong.

Each row is one class of bad input a careless user or an attacker produces, with the fragment the
error message must contain:

* ``cli`` rows run ``gym-coffee`` in-process: exit code 2, exactly one line on stderr starting
  ``gym-coffee CMD: error:``, no traceback, and no file written or changed;
* ``call`` rows call the library: a :class:`ValueError` (or :class:`FileNotFoundError`, which
  the CLI also maps to exit code 2) whose message holds the fragment;
* ``proc`` rows run in a child process with a memory limit, for inputs that used to abort the
  interpreter or allocate gigabytes: the child must print ``CLEAN:`` and the error message.

Rows marked ``xfail(strict=True, reason="pending <helper>")`` are written against the documented
contract of a fix another part of the project is making; the mark goes when the fix lands (a
strict xfail that passes fails the run, so a forgotten mark is noticed).
"""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
import textwrap
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import gym_coffee
from lgp_policy.app.cli import main

ROOT = Path(__file__).resolve().parents[1]


def pending(helper: str) -> pytest.MarkDecorator:
    return pytest.mark.xfail(strict=True, reason=f"pending {helper}")


# ------------------------------------------------------------------------------- fixtures
@dataclass
class Ctx:
    tmp: Path
    demos: Path
    policy: Path
    files: dict[str, Path]
    env: Any = None

    def __getitem__(self, key: str) -> Path:
        return self.files[key]


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _write(path: Path, arrays: dict[str, Any], compressed: bool = True) -> Path:
    (np.savez_compressed if compressed else np.savez)(path, **arrays)
    return path


def _with_meta(arrays: dict[str, np.ndarray], **changes: Any) -> dict[str, np.ndarray]:
    meta = json.loads(str(arrays["metadata"]))
    for key, value in changes.items():
        if value is _DROP:
            meta.pop(key, None)
        else:
            meta[key] = value
    return {**arrays, "metadata": np.array(json.dumps(meta))}


_DROP = object()


def _raw_member(path: Path, name: str, payload: bytes, base: dict[str, np.ndarray]) -> Path:
    """``base``'s arrays plus one raw member written by hand (lying headers, bombs)."""
    _write(path, base)
    with zipfile.ZipFile(path, "a", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(name, payload)
    return path


def _lying_npy(shape: tuple[int, ...], data: bytes) -> bytes:
    header = np.lib.format.header_data_from_array_1_0(np.zeros(1))
    header["shape"] = shape
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue() + data


def _make_files(tmp: Path, demos: Path, policy: Path) -> dict[str, Path]:
    d, p = _arrays(demos), _arrays(policy)
    f: dict[str, Path] = {}

    def new(name: str) -> Path:
        """A neutral file name (a fragment must not match the file's own name)."""
        f[name] = tmp / f"f{len(f):03d}{Path(name).suffix}"
        return f[name]

    def put(name: str, arrays: dict[str, Any], compressed: bool = True) -> None:
        _write(new(name), arrays, compressed)

    new("text.npz").write_text("this is a text file, renamed\n")
    with open(new("huge.npz"), "wb") as fh:  # 3 GiB, sparse: a read into memory would show
        fh.write(b"PK\x03\x04")
        fh.truncate(3 * 2**30)
    new("empty.npz").write_bytes(b"")
    buf = io.BytesIO()
    np.save(buf, np.ones(3))
    new("array.npz").write_bytes(buf.getvalue())
    raw = demos.read_bytes()
    new("trunc_demos.npz").write_bytes(raw[: len(raw) // 2])
    raw = policy.read_bytes()
    new("trunc_policy.npz").write_bytes(raw[: len(raw) // 3])
    new("folder.npz").mkdir()
    new("nothere.npz")  # never created
    new("existing.json").write_text('{"keep": true}')
    new("existing.gif").write_bytes(b"GIF89a keep")
    new("existing.npz").write_bytes(b"keep")
    new("dangling.npz").symlink_to(tmp / "nowhere" / "x.npz")
    new("dangling_dir").symlink_to(tmp / "nowhere" / "d")
    new("dangling.json").symlink_to(tmp / "nowhere" / "r.json")
    new("nonempty").mkdir()
    (f["nonempty"] / "notes.txt").write_text("mine")

    # demonstrations
    put("d_pickle.npz", {**d, "lengths": np.array([{"a": 1}], dtype=object)}, compressed=False)
    put("d_nan.npz", {**d, "joint_pos": np.where(np.arange(7) == 2, np.nan, d["joint_pos"])})
    put(
        "d_inf_time.npz", {**d, "time": np.where(np.arange(len(d["time"])) == 5, np.inf, d["time"])}
    )
    put("d_lengths.npz", {**d, "lengths": d["lengths"] + 1})
    put("d_neg_lengths.npz", {**d, "lengths": np.array([-1, len(d["time"]) + 1])})
    put("d_no_actions.npz", {k: v for k, v in d.items() if k != "actions"})
    put("d_actions_shape.npz", {**d, "actions": d["actions"][:, :5]})
    put("d_obs_dtype.npz", {**d, "observations": d["observations"].astype("U8")})
    put("d_no_meta.npz", {k: v for k, v in d.items() if k != "metadata"})
    put("d_meta_json.npz", {**d, "metadata": np.array("{not json")})
    put("d_meta_version.npz", _with_meta(d, schema_version=999))
    put("d_meta_list.npz", {**d, "metadata": np.array("[1, 2]")})
    put("d_failed.npz", {**d, "success": np.zeros_like(d["success"])})
    put("d_is_policy.npz", p)
    _raw_member(new("d_bomb.npz"), "junk.npy", b"\0" * (64 * 2**20), d)
    put("d_zero_length.npz", {**d, "lengths": np.array([0, int(d["lengths"].sum())])})
    put("d_stages_float.npz", {**d, "stages": d["stages"].astype(float)})
    put("p_no_frames.npz", _with_meta(p, frame_names=[]))
    put("d_time_decreasing.npz", {**d, "time": d["time"][::-1].copy()})

    # GP policies
    put("p_no_meta.npz", {k: v for k, v in p.items() if k != "metadata"})
    put("p_meta_json.npz", {**p, "metadata": np.array("{not json")})
    put("p_meta_nan.npz", {**p, "metadata": np.array('{"format": NaN}')})
    put("p_version.npz", _with_meta(p, schema_version=999))
    put("p_format.npz", _with_meta(p, format="something.else", kind="something.else"))
    put("p_grid.npz", {**p, "phase_grid": p["phase_grid"][::-1].copy()})
    put("p_mean_nan.npz", {**p, "mean__joint": np.full_like(p["mean__joint"], np.nan)})
    put("p_std_neg.npz", {**p, "std__joint": -p["std__joint"]})
    put("p_missing_array.npz", {k: v for k, v in p.items() if k != "std__cup"})
    put("p_shape.npz", {**p, "mean__cup": p["mean__cup"][:, :2]})
    put("p_params.npz", _with_meta(p, params={"no_such_parameter": 1}))
    put("p_duration.npz", _with_meta(p, duration=1e308))
    put("p_dt_inf.npz", _with_meta(p, control_dt=float("inf")))  # json writes Infinity
    put("p_dt_zero.npz", _with_meta(p, control_dt=0.0))
    put("p_dt_huge.npz", _with_meta(p, control_dt=1e300))
    params = json.loads(str(p["metadata"]))["params"]
    put("p_alpha_5.npz", _with_meta(p, params={**params, "alpha": 5.0}))
    put(
        "p_alpha_nan.npz",
        _with_meta(p, params={**json.loads(str(p["metadata"]))["params"], "alpha": float("nan")}),
    )
    names = json.loads(str(p["metadata"]))["frame_names"]
    renamed = {k.replace("__cup", "__mug"): v for k, v in p.items()}
    put("p_frames.npz", _with_meta(renamed, frame_names=[n.replace("cup", "mug") for n in names]))
    put("p_pickle.npz", {**p, "phase_grid": np.array([None, 1.0], dtype=object)}, compressed=False)
    _raw_member(new("p_bomb.npz"), "junk.npy", b"\0" * (64 * 2**20), p)
    _raw_member(
        new("p_lying.npz"),
        "mean__joint.npy",
        _lying_npy((10**11,), b"\0" * 64),
        {k: v for k, v in p.items() if k != "mean__joint"},
    )
    put("p_is_demos.npz", d)
    return f


@pytest.fixture(scope="module")
def ctx(tmp_path_factory) -> Ctx:
    import gymnasium as gym

    import gym_coffee
    from gym_coffee.demonstrations import collect_demonstrations
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    tmp = tmp_path_factory.mktemp("bad_input")
    env = gym.make(gym_coffee.ENV_ID)
    demos = collect_demonstrations(env, n=2, seed=0, progress=False)
    demos_path = demos.save(tmp / "demos.npz")
    policy = GPDemonstrationPolicy(model="empirical").fit(demos)  # real fit, ~0.1 s
    policy_path = policy.save(tmp / "policy.npz")
    c = Ctx(tmp, demos_path, policy_path, _make_files(tmp, demos_path, policy_path), env=env)
    c.policy_object = policy  # type: ignore[attr-defined]
    yield c
    env.close()


# ------------------------------------------------------------------------------- the rows
CLI: list[Any] = []
CALL: list[Any] = []
PROC: list[Any] = []


def cli(id_: str, argv: str, fragment: str, *marks: pytest.MarkDecorator) -> None:
    CLI.append(pytest.param(argv, fragment, id=id_, marks=marks))


def call(id_: str, func: Callable[[Ctx], Any], fragment: str, *marks: Any) -> None:
    CALL.append(pytest.param(func, fragment, id=id_, marks=marks))


def proc(id_: str, code: str, fragment: str, *marks: Any) -> None:
    PROC.append(pytest.param(textwrap.dedent(code), fragment, id=id_, marks=marks))


# --- the command line: arguments --------------------------------------------------------
cli("no-command", "", "required: COMMAND")
cli("unknown-command", "frobnicate", "invalid choice: 'frobnicate'")
cli("unknown-option", "fit {demos} --out {tmp}/p.npz --frob", "unrecognized arguments: --frob")
for value in ("0", "-3", "two", "1.5", ""):
    cli(
        f"record-n-{value or 'empty'}",
        f"record --n '{value}' --out {{tmp}}/d.npz",
        "argument --n: expected a number of demonstrations in [1, 10000]",
    )
cli(
    "record-seed-negative", "record --seed -1 --out {tmp}/d.npz", "argument --seed: expected a seed"
)
cli(
    "record-seed-huge",
    "record --seed 99999999999 --out {tmp}/d.npz",
    "argument --seed: expected a seed",
)
cli("record-seed-nan", "record --seed nan --out {tmp}/d.npz", "argument --seed")
cli("record-out-missing", "record --n 1", "required: --out")
cli(
    "record-out-suffix",
    "record --out {tmp}/d.txt",
    "argument --out: output {tmp}/d.txt: expected a name ending in .npz",
)
cli("record-out-exists", "record --out {existing.npz}", "{existing.npz} exists; pass --force")
cli("record-out-dangling", "record --out {dangling.npz}", "{dangling.npz} exists; pass --force")
cli("record-out-folder", "record --out {folder.npz}", "is a folder")
cli("record-out-under-file", "record --out {existing.json}/d.npz", "is not a folder")
cli("record-video-suffix", "record --out {tmp}/d.npz --video {tmp}/v.avi", "argument --video")
cli(
    "record-video-no-suffix",
    "record --out {tmp}/d.npz --video {tmp}/video",
    "ending in .mp4 or .gif",
)
cli(
    "record-video-exists",
    "record --out {tmp}/d.npz --video {existing.gif}",
    "{existing.gif} exists; pass --force",
)
cli(
    "record-env-id",
    "record --out {tmp}/d.npz --env-id CartPole-v1",
    "argument --env-id: expected one of",
)
cli(
    "record-level",
    "record --out {tmp}/d.npz --level medium",
    "argument --level: invalid choice: 'medium'",
)
cli(
    "record-physics",
    "record --out {tmp}/d.npz --physics slow",
    "argument --physics: invalid choice: 'slow'",
)
cli(
    "record-level-and-env-id",
    f"record --out {{tmp}}/d.npz --level hard --env-id {gym_coffee.ENV_ID}",
    "argument --env-id: not allowed with argument --level",
)
cli("fit-demos-missing", "fit {tmp}/nothere.npz --out {tmp}/p.npz", "argument demos: no such file")
cli("fit-demos-folder", "fit {folder.npz} --out {tmp}/p.npz", "is not a file")
cli(
    "fit-demos-suffix",
    "fit {existing.json} --out {tmp}/p.npz",
    "argument demos: expected a .npz file",
)
cli("fit-out-missing", "fit {demos}", "required: --out")
cli("fit-out-exists", "fit {demos} --out {existing.npz}", "{existing.npz} exists; pass --force")
cli("fit-out-dangling", "fit {demos} --out {dangling.npz}", "{dangling.npz} exists; pass --force")
cli("fit-out-is-input", "fit {demos} --out {demos} --force", "is also an input")
cli("fit-out-suffix", "fit {demos} --out {tmp}/policy.json", "expected a name ending in .npz")
cli(
    "fit-model",
    "fit {demos} --out {tmp}/p.npz --model gaussian",
    "argument --model: invalid choice",
)
cli(
    "fit-combine",
    "fit {demos} --out {tmp}/p.npz --combine mean",
    "argument --combine: invalid choice",
)
cli(
    "fit-combine-model",
    "fit {demos} --out {tmp}/p.npz --model exact --combine rbcm",
    "--model local only",
)
for value in ("nan", "inf", "-inf", "-0.1", "2", "half"):
    cli(
        f"fit-alpha-{value}",
        f"fit {{demos}} --out {{tmp}}/p.npz --alpha={value}",
        "argument --alpha",
    )
cli("evaluate-policy-missing", "evaluate {tmp}/nothere.npz", "argument policy: no such file")
cli("evaluate-level", "evaluate {policy} --level expert", "argument --level: invalid choice")
cli("evaluate-physics", "evaluate {policy} --physics turbo", "argument --physics: invalid choice")
cli("run-physics", "run --out {tmp}/r --physics ''", "argument --physics: invalid choice")
cli("evaluate-level-empty", "evaluate {policy} --level ''", "argument --level: invalid choice")
cli(
    "evaluate-env-id",
    "evaluate {policy} --env-id CartPole-v1",
    "argument --env-id: expected one of",
)
cli(
    "evaluate-env-id-level-name",
    "evaluate {policy} --env-id hard",
    "argument --env-id: expected one of",
)
cli(
    "evaluate-level-and-env-id",
    f"evaluate {{policy}} --env-id {gym_coffee.ENV_ID} --level easy",
    "argument --level: not allowed with argument --env-id",
)
cli("evaluate-policy-folder", "evaluate {folder.npz}", "is not a file")
cli("evaluate-policy-suffix", "evaluate {existing.json}", "expected a .npz file")
for value in ("0", "-1", "ten", "1e3"):
    cli(
        f"evaluate-episodes-{value}",
        f"evaluate {{policy}} --episodes {value}",
        "argument --episodes",
    )
for value in ("0", "-2", "100000"):
    cli(f"evaluate-workers-{value}", f"evaluate {{policy}} --workers {value}", "argument --workers")
cli("evaluate-seed-negative", "evaluate {policy} --seed -5", "argument --seed")
cli(
    "evaluate-seed-overflow",
    "evaluate {policy} --seed 2147480000 --episodes 9000",
    "argument --seed: expected at most",
)
cli(
    "evaluate-json-exists",
    "evaluate {policy} --json {existing.json}",
    "{existing.json} exists; pass --force",
)
cli(
    "evaluate-json-suffix",
    "evaluate {policy} --json {tmp}/r.txt",
    "expected a name ending in .json",
)
cli("evaluate-json-folder", "evaluate {policy} --json {tmp}", "is a folder")
cli("evaluate-json-dangling", "evaluate {policy} --json {dangling.json}", "exists; pass --force")
cli("evaluate-json-is-input", "evaluate {policy} --json {policy}", "is also an input")
cli("evaluate-video-suffix", "evaluate {policy} --video {tmp}/v.webm", "ending in .mp4 or .gif")
cli(
    "evaluate-video-exists",
    "evaluate {policy} --video {existing.gif}",
    "{existing.gif} exists; pass --force",
)
cli(
    "evaluate-video-under-file",
    "evaluate {policy} --video {existing.json}/v.gif",
    "is not a folder",
)
cli("evaluate-backend", "evaluate {policy} --backend dask", "argument --backend: invalid choice")
cli("evaluate-address-local", "evaluate {policy} --address auto", "--address: needs --backend ray")
cli("run-out-file", "run --out {existing.json}", "is a file; expected a folder")
cli("run-out-dangling", "run --out {dangling_dir}", "is a link to nothing; expected a folder")
cli("run-out-nonempty", "run --out {nonempty}", "is not empty (notes.txt); pass --force")
cli("run-demos-0", "run --out {tmp}/r --demos 0", "argument --demos")
cli("run-episodes-0", "run --out {tmp}/r --episodes 0", "argument --episodes")
cli("run-workers-0", "run --out {tmp}/r --workers 0", "argument --workers")
cli("run-level", "run --out {tmp}/r --level expert", "argument --level: invalid choice")
cli("run-env-id", "run --out {tmp}/r --env-id CartPole-v1", "argument --env-id: expected one of")
cli("run-seed-negative", "run --out {tmp}/r --seed -1", "argument --seed")
cli("run-alpha-nan", "run --out {tmp}/r --alpha nan", "argument --alpha")
cli("run-model", "run --out {tmp}/r --model gp", "argument --model: invalid choice")
cli(
    "finetune-policy-missing",
    "finetune {nothere.npz} --out {tmp}/ft",
    "{nothere.npz}",
)
cli(
    "finetune-policy-is-demos",
    "finetune {p_is_demos.npz} --out {tmp}/ft",
    "argument POLICY: {p_is_demos.npz} is a demonstrations file (gym_coffee.demonstrations), "
    "not a policy; fit a policy to it first",
)
cli("finetune-policy-text", "finetune {text.npz} --out {tmp}/ft", "POLICY: {text.npz} is not")
cli(
    "finetune-policy-huge",
    "finetune {huge.npz} --out {tmp}/ft",
    "argument POLICY: {huge.npz} is 3221225472 bytes; a policy file has at most",
)

# --- the command line: input files ----------------------------------------------------------
cli("fit-demos-text", "fit {text.npz} --out {tmp}/p.npz", "{text.npz}")
cli("fit-demos-empty", "fit {empty.npz} --out {tmp}/p.npz", "{empty.npz}")
cli("fit-demos-npy", "fit {array.npz} --out {tmp}/p.npz", "{array.npz}")
cli("fit-demos-truncated", "fit {trunc_demos.npz} --out {tmp}/p.npz", "{trunc_demos.npz}")
cli("fit-demos-pickle", "fit {d_pickle.npz} --out {tmp}/p.npz", "Python objects")
cli("fit-demos-nan", "fit {d_nan.npz} --out {tmp}/p.npz --model empirical", "NaN")
cli("fit-demos-is-policy", "fit {d_is_policy.npz} --out {tmp}/p.npz", "{d_is_policy.npz}")
cli("evaluate-policy-text", "evaluate {text.npz}", "{text.npz} is not")
cli("evaluate-policy-empty", "evaluate {empty.npz}", "{empty.npz}")
cli("evaluate-policy-truncated", "evaluate {trunc_policy.npz}", "{trunc_policy.npz}")
cli(
    "evaluate-policy-is-demos",
    "evaluate {p_is_demos.npz}",
    "argument POLICY: {p_is_demos.npz} is a demonstrations file",
)
cli("evaluate-policy-version", "evaluate {p_version.npz}", "schema version")
cli("evaluate-policy-nan", "evaluate {p_mean_nan.npz}", "NaN")
cli("evaluate-policy-pickle", "evaluate {p_pickle.npz}", "Python objects")


def _gp_load(name: str) -> Callable[[Ctx], Any]:
    def run(c: Ctx) -> Any:
        from lgp_policy.lfd.policy import GPDemonstrationPolicy

        return GPDemonstrationPolicy.load(c[name])

    return run


def _demos_load(name: str) -> Callable[[Ctx], Any]:
    def run(c: Ctx) -> Any:
        from gym_coffee.demonstrations import DemonstrationSet

        return DemonstrationSet.load(c[name])

    return run


# --- demonstration files (DemonstrationSet.load) --------------------------------------------
call("demos-text", _demos_load("text.npz"), "{text.npz}")
call("demos-empty", _demos_load("empty.npz"), "{empty.npz}")
call("demos-npy-renamed", _demos_load("array.npz"), "{array.npz}")
call("demos-truncated", _demos_load("trunc_demos.npz"), "{trunc_demos.npz}")
call("demos-pickle", _demos_load("d_pickle.npz"), "Python objects")
call("demos-nan", _demos_load("d_nan.npz"), "NaN")
call("demos-inf-time", _demos_load("d_inf_time.npz"), "time")
call("demos-lengths", _demos_load("d_lengths.npz"), "lengths")
call("demos-negative-lengths", _demos_load("d_neg_lengths.npz"), "lengths")
call("demos-missing-array", _demos_load("d_no_actions.npz"), "actions")
call("demos-action-shape", _demos_load("d_actions_shape.npz"), "actions")
call("demos-obs-dtype", _demos_load("d_obs_dtype.npz"), "observations")
call("demos-no-metadata", _demos_load("d_no_meta.npz"), "metadata")
call("demos-metadata-json", _demos_load("d_meta_json.npz"), "metadata")
call("demos-metadata-list", _demos_load("d_meta_list.npz"), "metadata")
call("demos-schema-version", _demos_load("d_meta_version.npz"), "version")
call("demos-is-policy", _demos_load("d_is_policy.npz"), "{d_is_policy.npz}")
call("demos-zero-length", _demos_load("d_zero_length.npz"), "lengths")
call("demos-stages-float", _demos_load("d_stages_float.npz"), "stages")
call("demos-time-decreasing", _demos_load("d_time_decreasing.npz"), "time")

# --- GP policy files (GPDemonstrationPolicy.load) --------------------------------------------
call("policy-text", _gp_load("text.npz"), "{text.npz} is not")
call("policy-empty", _gp_load("empty.npz"), "{empty.npz}")
call("policy-npy-renamed", _gp_load("array.npz"), "{array.npz}")
call("policy-truncated", _gp_load("trunc_policy.npz"), "{trunc_policy.npz}")
call("policy-folder", _gp_load("folder.npz"), "{folder.npz}")
call("policy-missing", _gp_load("nothere.npz"), "{nothere.npz}")
call("policy-no-metadata", _gp_load("p_no_meta.npz"), "metadata")
call("policy-metadata-json", _gp_load("p_meta_json.npz"), "JSON")
call("policy-metadata-nan", _gp_load("p_meta_nan.npz"), "metadata")
call("policy-schema-version", _gp_load("p_version.npz"), "schema version 999")
call("policy-wrong-format", _gp_load("p_format.npz"), "something.else")
call("policy-is-demos", _gp_load("p_is_demos.npz"), "{p_is_demos.npz}")
call("policy-grid-decreasing", _gp_load("p_grid.npz"), "phase_grid")
call("policy-mean-nan", _gp_load("p_mean_nan.npz"), "NaN")
call("policy-std-negative", _gp_load("p_std_neg.npz"), "std__joint")
call("policy-missing-array", _gp_load("p_missing_array.npz"), "std__cup")
call("policy-array-shape", _gp_load("p_shape.npz"), "cup")
call("policy-no-frames", _gp_load("p_no_frames.npz"), "frame_names")
call("policy-unknown-params", _gp_load("p_params.npz"), "no_such_parameter")
call("policy-dt-zero", _gp_load("p_dt_zero.npz"), "control_dt")
call("policy-dt-inf", _gp_load("p_dt_inf.npz"), "control_dt must be a finite number")
call("policy-dt-huge", _gp_load("p_dt_huge.npz"), "control_dt")
call("policy-duration-huge", _gp_load("p_duration.npz"), "duration")
call("policy-alpha-nan", _gp_load("p_alpha_nan.npz"), "alpha must be a finite number")
call("policy-alpha-range", _gp_load("p_alpha_5.npz"), "alpha")
call("policy-unknown-frames", _gp_load("p_frames.npz"), "mug")
call("policy-pickle", _gp_load("p_pickle.npz"), "Python objects")
call("policy-lying-header", _gp_load("p_lying.npz"), "mean__joint")


def _any_load(name: str) -> Callable[[Ctx], Any]:
    def run(c: Ctx) -> Any:
        from lgp_policy.app.commands import load_policy

        return load_policy(c[name])

    return run


call("any-policy-text", _any_load("text.npz"), "{text.npz}")
call("any-policy-is-demos", _any_load("p_is_demos.npz"), "{p_is_demos.npz}")
call("any-policy-unknown-kind", _any_load("p_format.npz"), "something.else")


# --- the policy at run time (lfd) ------------------------------------------------------------
def _predict(obs: Callable[[int], np.ndarray]) -> Callable[[Ctx], Any]:
    def run(c: Ctx) -> Any:
        from gym_coffee.env import OBS_DIM

        return c.policy_object.predict(obs(OBS_DIM))  # type: ignore[attr-defined]

    return run


call("predict-obs-short", _predict(lambda n: np.zeros(n - 1)), "observation")
call("predict-obs-long", _predict(lambda n: np.zeros(n + 1)), "observation")
call(
    "predict-obs-batch-long",
    _predict(lambda n: np.zeros((3, n + 1))),
    "observation",
)
call("predict-obs-text", _predict(lambda n: np.array(["a"] * n)), "observation")
call("predict-obs-3d", _predict(lambda n: np.zeros((2, 2, n))), "observation")
call("predict-obs-nan", _predict(lambda n: np.full(n, np.nan)), "observation")
call("predict-obs-inf", _predict(lambda n: np.full(n, np.inf)), "observation")


def _fit(demos_name: str | None = None, **params: Any) -> Callable[[Ctx], Any]:
    def run(c: Ctx) -> Any:
        from gym_coffee.demonstrations import DemonstrationSet
        from lgp_policy.lfd.policy import GPDemonstrationPolicy

        demos = DemonstrationSet.load(c[demos_name] if demos_name else c.demos)
        return GPDemonstrationPolicy(**{"model": "empirical", **params}).fit(demos)

    return run


call("fit-failed-demos", _fit("d_failed.npz"), "success")
call("fit-alpha-nan", _fit(alpha=float("nan")), "alpha")
call("fit-alpha-negative", _fit(alpha=-1.0), "alpha")
call("fit-n-grid-1", _fit(n_grid=1), "n_grid")
call("fit-n-steps-0", _fit(n_steps=0), "n_steps")
call("fit-model-unknown", _fit(model="gaussian"), "model")
call("fit-no-demos", lambda c: _fit()(c).fit([]), "at least one demonstration")


# --- the environment (env) -------------------------------------------------------------------
def _step(action: Callable[[], np.ndarray]) -> Callable[[Ctx], Any]:
    def run(c: Ctx) -> Any:
        c.env.reset(seed=0)
        return c.env.step(action())

    return run


call("env-action-nan", _step(lambda: np.full(8, np.nan, np.float32)), "action")
call("env-action-inf", _step(lambda: np.full(8, np.inf, np.float32)), "action")
call("env-action-9d", _step(lambda: np.zeros(9, np.float32)), "action")
call("env-action-7d", _step(lambda: np.zeros(7, np.float32)), "action")
call("env-action-2d", _step(lambda: np.zeros((1, 8), np.float32)), "action")


def _make(**kwargs: Any) -> Callable[[Ctx], Any]:
    def run(c: Ctx) -> Any:
        import gymnasium as gym

        import gym_coffee

        env = gym.make(gym_coffee.ENV_ID, **kwargs)
        env.close()

    return run


call("env-action-text", _step(lambda: np.array(["a"] * 8)), "action")


def _reset(options: Any) -> Callable[[Ctx], Any]:
    def run(c: Ctx) -> Any:
        return c.env.reset(seed=0, options=options)

    return run


call("env-reset-options", _reset({"layuot": {}}), "options")
call("env-reset-layout-far", _reset({"layout": {"cup_pos": [10.0, 10.0]}}), "cup_pos")
call("env-reset-layout-nan", _reset({"layout": {"machine_yaw": float("nan")}}), "machine_yaw")
call("env-reward-type", _make(reward_type="shaped"), "reward_type")
call("env-render-mode", _make(render_mode="window"), "render_mode")
call("env-height-zero", _make(render_mode="rgb_array", height=0), "height")
call("env-width-float", _make(render_mode="rgb_array", width=2.5), "width")
call("env-obs-noise-negative", _make(obs_noise=-0.1), "obs_noise")
call("env-obs-noise-nan", _make(obs_noise=float("nan")), "obs_noise")
call("env-cup-push-reversed", _make(cup_push=(0.05, 0.03)), "cup_push")
call("env-action-type", _make(action_type="torque"), "action_type")
call(
    "env-actuation-noise-inf",
    _make(actuation_noise=float("inf")),
    "actuation_noise",
)

proc(
    "env-width-negative-no-abort",
    """
    import gymnasium as gym, gym_coffee
    try:
        env = gym.make(gym_coffee.ENV_ID, render_mode="rgb_array", width=-5)
        env.reset(seed=0)
        env.render()
    except ValueError as exc:
        print("CLEAN:", exc)
    """,
    "width",
)


# --- Gaussian processes (gp) -------------------------------------------------------------
def _gp(cls: str, X: Callable[[], np.ndarray], y: Callable[[], np.ndarray], **kw: Any):
    def run(c: Ctx) -> Any:
        import lgp_policy.gp.exact
        import lgp_policy.gp.heteroscedastic
        import lgp_policy.gp.local

        for module in (lgp_policy.gp.exact, lgp_policy.gp.heteroscedastic, lgp_policy.gp.local):
            if hasattr(module, cls):
                model = getattr(module, cls)(**kw)
                break
        model.fit(X(), y())
        mean = model.predict(X())
        mean = mean[0] if isinstance(mean, tuple) else mean
        if not np.all(np.isfinite(mean)):
            raise AssertionError(f"silent NaN/inf mean: {mean[:3]}")
        return model

    return run


_x = lambda: np.linspace(0, 1, 20)[:, None]  # noqa: E731
call("gp-x-nan", _gp("GaussianProcess", lambda: np.full((20, 1), np.nan), lambda: np.ones(20)), "X")
call("gp-y-inf", _gp("GaussianProcess", _x, lambda: np.full(20, np.inf)), "y")
call("gp-length-mismatch", _gp("GaussianProcess", _x, lambda: np.ones(19)), "19")
call("gp-empty", _gp("GaussianProcess", lambda: np.zeros((0, 1)), lambda: np.zeros(0)), "empty")
call(
    "gp-y-overflow",
    _gp("GaussianProcess", _x, lambda: np.linspace(1, 2, 20) * 1e300),
    "y",
)
call(
    "hgp-y-overflow",
    _gp("HeteroscedasticGP", _x, lambda: np.linspace(1, 2, 20) * 1e300),
    "y",
)
call(
    "local-y-overflow",
    _gp("LocalGP", _x, lambda: np.linspace(1, 2, 20) * 1e300),
    "y",
)
call("gp-y-nan", _gp("GaussianProcess", _x, lambda: np.full(20, np.nan)), "y")
call("gp-x-3d", _gp("GaussianProcess", lambda: np.zeros((20, 1, 1)), lambda: np.ones(20)), "X")
call("local-combine", _gp("LocalGP", _x, lambda: np.ones(20), combine="mean"), "combine")

proc(
    "gp-exact-too-large-points-to-localgp",
    """
    import resource, numpy as np
    resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))
    from lgp_policy.gp.exact import GaussianProcess
    X = np.random.default_rng(0).uniform(size=(40000, 1))
    try:
        GaussianProcess(optimizer=None).fit(X, np.sin(X[:, 0]))
    except ValueError as exc:
        print("CLEAN:", exc)
    except MemoryError as exc:
        print("MemoryError", exc)
    """,
    "LocalGP",
)


# --- residual policy files (resid) ------------------------------------------------------------
def _residual_file(c: Ctx, name: str, **meta_changes: Any) -> Path:
    """A residual-policy file: valid metadata and spaces, no trained weights; ``meta_changes``
    make it bad in one way."""
    from lgp_policy.residual import PhaseGate

    meta = {
        "kind": "lgp_policy.residual_policy",
        "format": "lgp_policy.residual_policy",
        "schema_version": 1,
        "algo": "sac",
        "hyperparameters": {"policy_kwargs": {"net_arch": [16, 16]}},
        "scale": 0.1,
        "gate": PhaseGate(start=0.5).to_config(),
        "residual_dims": [0],
        "include_gate_obs": False,
        "obs_norm": None,
        "obs_dim": 3,
        "action_dim": 1,
        "param_names": [],
        "base": None,
    }
    meta.update(meta_changes)
    arrays = {
        "metadata": np.array(json.dumps(meta)),
        "space/obs_low": -np.ones(4, np.float32),
        "space/obs_high": np.ones(4, np.float32),
        "space/act_low": -np.ones(1, np.float32),
        "space/act_high": np.ones(1, np.float32),
        "param/actor.mu.weight": np.zeros((1, 16), np.float32),  # weights are checked later
    }
    return _write(c.tmp / name, arrays)


def _residual(name: str, **meta_changes: Any) -> Callable[[Ctx], Any]:
    def run(c: Ctx) -> Any:
        from lgp_policy.app.commands import load_policy

        return load_policy(_residual_file(c, name, **meta_changes))

    return run


call("residual-algo", _residual("r0.npz", algo="dqn"), "algo")
call("residual-scale-zero", _residual("r1.npz", scale=0.0), "scale")
call("residual-scale-huge", _residual("r2.npz", scale=1e308), "scale")
call("residual-dims", _residual("r3.npz", residual_dims=[5]), "residual_dims")
call("residual-version", _residual("r4.npz", schema_version=99), "schema version")
call(
    "residual-net-arch-huge",
    _residual("r5.npz", hyperparameters={"policy_kwargs": {"net_arch": [3000, 3000]}}),
    "net_arch",
)


def _residual_embedded_base_path(c: Ctx) -> Any:
    """An embedded base whose name is a path outside the folder: nothing may be written."""
    from lgp_policy.app.commands import load_policy

    raw = c.policy.read_bytes()
    import hashlib

    target = c.tmp / "evil_target.txt"
    path = _residual_file(
        c,
        "r6.npz",
        base={
            "name": str(target),
            "path": str(target),
            "embedded": True,
            "sha256": hashlib.sha256(raw).hexdigest(),
            "kind": None,
        },
    )
    arrays = {**_arrays(path), "base_file": np.frombuffer(raw, np.uint8)}
    _write(path, arrays)
    try:
        return load_policy(path)
    finally:
        assert not target.exists(), "loading wrote a file named by the file"


call("residual-embedded-base-path", _residual_embedded_base_path, "r6.npz")


# ------------------------------------------------------------------------------- the tests
def _fill(text: str, ctx: Ctx) -> str:
    """Replace ``{name}`` by the path of that test file (``{tmp}``, ``{demos}``, ``{policy}``)."""
    paths = {"tmp": ctx.tmp, "demos": ctx.demos, "policy": ctx.policy, **ctx.files}
    return re.sub(r"\{([^{}]+)\}", lambda m: str(paths[m.group(1)]), text)


@pytest.fixture
def no_long_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """A row whose check is missing must fail fast, not start minutes of work."""
    import gym_coffee.demonstrations
    from lgp_policy.app import evaluation, pipeline

    def started(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("work started: the bad input was not caught before")

    monkeypatch.setattr(pipeline, "run_pipeline", started)
    monkeypatch.setattr(evaluation, "evaluate_policy_stages", started)
    monkeypatch.setattr(gym_coffee.demonstrations, "collect_demonstrations", started)


@pytest.mark.parametrize(("argv", "fragment"), CLI)
def test_cli_row(
    argv: str, fragment: str, ctx: Ctx, no_long_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    import shlex

    args = [_fill(a, ctx) for a in shlex.split(argv)]
    before = sorted(p.name for p in ctx.tmp.iterdir())
    with pytest.raises(SystemExit) as info:
        raise SystemExit(main(args))
    err = capsys.readouterr().err
    assert info.value.code == 2, err
    lines = [line for line in err.splitlines() if line.strip() and "warning" not in line]
    assert len(lines) == 1 and "Traceback" not in err, err
    prefixes = ("gym-coffee: error: ", f"gym-coffee {args[0] if args else ''}: error: ")
    assert lines[0].startswith(prefixes), err
    assert _fill(fragment, ctx) in lines[0], err
    assert "allow_pickle" not in err
    assert sorted(p.name for p in ctx.tmp.iterdir()) == before  # nothing written
    assert ctx["existing.json"].read_text() == '{"keep": true}'


@pytest.mark.parametrize(("func", "fragment"), CALL)
def test_call_row(func: Callable[[Ctx], Any], fragment: str, ctx: Ctx) -> None:
    with pytest.raises((ValueError, FileNotFoundError)) as info:
        func(ctx)
    message = str(info.value)
    assert _fill(fragment, ctx) in message, message
    assert "allow_pickle" not in message


@pytest.mark.parametrize(("code", "fragment"), PROC)
def test_process_row(code: str, fragment: str) -> None:
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "OMP_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
    }
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "CLEAN:" in result.stdout and fragment in result.stdout, (
        result.stdout + result.stderr[-500:]
    )


def test_table_counts() -> None:
    """The table covers at least the issue's 135 classes."""
    assert len(CLI) + len(CALL) + len(PROC) >= 135


@pytest.mark.parametrize(
    ("loader", "name"),
    [
        pytest.param(_demos_load, "d_bomb.npz", id="demos"),
        pytest.param(_gp_load, "p_bomb.npz", id="gp-policy"),
    ],
)
def test_unknown_member_is_never_decompressed(loader: Any, name: str, ctx: Ctx) -> None:
    """A valid file plus a 64 MiB member the loader does not know (a decompression bomb, 65 KiB
    on disk): it loads, and the unknown member is never decompressed."""
    import tracemalloc

    tracemalloc.start()
    try:
        loader(name)(ctx)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, f"peak {peak / 2**20:.0f} MiB"
