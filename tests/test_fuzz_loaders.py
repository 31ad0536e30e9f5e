"""Fuzzing the file loaders (issue 8 Deliver 5): mutated valid files and random bytes give a
clean error or a valid object, never another exception, never more than a bounded amount of
memory.

"Clean error": a :class:`ValueError` (every format error of the project subclasses it; the CLI
maps it to one line and exit code 2). Memory: the peak of Python and numpy allocations
(:mod:`tracemalloc`) while loading one file stays under ``MEMORY_BOUND``; the valid files are
~100 KiB, so a loader that trusts a size in the file blows through it.

The examples are derandomised (the same inputs every run) and few, so the module runs in about
10 s; raise ``FUZZ_EXAMPLES`` in the environment for a longer hunt (``FUZZ_SHRINK=1`` to
minimise a failing example).
"""

from __future__ import annotations

import io
import json
import os
import re
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from lgp_policy._io import FileFormatError, MemberSpec, read_npz

MEMORY_BOUND = 48 * 2**20
EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "40"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    # No shrinking by default: a failure is reported at once (set FUZZ_SHRINK=1 to minimise it).
    phases=list(Phase) if os.environ.get("FUZZ_SHRINK") else [Phase.explicit, Phase.generate],
)


class _Files(dict):  # type: ignore[type-arg]
    def __repr__(self) -> str:  # hypothesis prints the arguments of a failing example
        return "<valid files>"


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Any]:
    """Valid files: real demonstrations (2, from the scripted teacher), the GP policy fitted to
    them (empirical model: fast), both compressed and stored, and a scratch path."""
    import gymnasium as gym

    import gym_coffee
    from gym_coffee.demonstrations import collect_demonstrations
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    tmp = tmp_path_factory.mktemp("fuzz")
    env = gym.make(gym_coffee.ENV_ID)
    try:
        demos = collect_demonstrations(env, n=2, seed=0, progress=False)
    finally:
        env.close()
    policy = GPDemonstrationPolicy(model="empirical").fit(demos)
    out: dict[str, Any] = _Files(scratch=tmp / "fuzz.npz")
    out["demos"] = demos.save(tmp / "demos.npz").read_bytes()
    out["policy"] = policy.save(tmp / "policy.npz").read_bytes()
    for name in ("demos", "policy"):  # stored (uncompressed): mutations hit headers and data
        with np.load(io.BytesIO(out[name]), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        out[f"{name}_stored"] = buf.getvalue()
    return out


class _Mutated(bytes):
    """Bytes that print as how they were made (hypothesis shows failing draws)."""

    how = ""

    def __repr__(self) -> str:
        return f"<{len(self)} bytes: {self.how}>"


def _mutated(data: bytes | bytearray, how: str) -> _Mutated:
    out = _Mutated(data)
    out.how = how
    return out


@st.composite
def mutations(draw: st.DrawFn, base: bytes) -> bytes:
    """``base`` with bytes flipped, cut, spliced, or replaced by random bytes."""
    kind = draw(st.sampled_from(["flip", "truncate", "splice", "random", "header", "shape"]))
    data = bytearray(base)
    shapes = list(re.finditer(rb"'shape': \((\d+)", data))
    if kind == "shape" and shapes:  # a huge shape in a consistent header (a memory bomb)
        m = draw(st.sampled_from(shapes))
        zeros = b"0" * draw(st.integers(3, 9))
        end = data.index(b"\n", m.end())  # the header is padded with spaces before "\n"
        if data[end - len(zeros) : end] == b" " * len(zeros):
            del data[end - len(zeros) : end]
            data[m.end() : m.end()] = zeros
            return _mutated(data, f"shape at byte {m.start()} x 10**{len(zeros)}")
        kind = "flip"
    if kind == "flip":
        where = []
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, len(data) - 1))
            data[i] ^= draw(st.integers(1, 255))
            where.append(i)
        kind = f"flipped bytes {where}"
    elif kind == "truncate":
        data = data[: draw(st.integers(0, len(data) - 1))]
        kind = f"cut at {len(data)}"
    elif kind == "splice":
        i = draw(st.integers(0, len(data)))
        data[i:i] = draw(st.binary(min_size=1, max_size=64))
        kind = f"spliced at {i}"
    elif kind == "header":  # overwrite inside a .npy header: shapes, dtypes, lengths
        hits = [i for i in range(len(data) - 6) if data[i : i + 6] == b"\x93NUMPY"]
        i = draw(st.sampled_from(hits)) if hits else 0
        j = i + draw(st.integers(6, 120))
        data[j : j + 4] = draw(st.binary(min_size=4, max_size=4))
        kind = f"header bytes {j}..{j + 4}"
    else:
        return _mutated(draw(st.binary(max_size=2048)), "random")
    return _mutated(data, kind)


def _check(load: Callable[[bytes], Any], data: bytes, valid: Callable[[Any], None]) -> None:
    tracemalloc.start()
    try:
        try:
            obj = load(data)
        except ValueError:
            obj = None  # clean error (every format error is a ValueError)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < MEMORY_BOUND, f"loading took {peak / 2**20:.0f} MiB"
    if obj is not None:
        valid(obj)


def _gp_policy(data: bytes) -> Any:
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    return GPDemonstrationPolicy.load(io.BytesIO(data))


def _valid_policy(policy: Any) -> None:
    from gym_coffee.env import OBS_DIM

    action, _ = policy.predict(np.zeros(OBS_DIM))
    assert action.shape == (8,) and np.all(np.isfinite(action))


def _valid_demos(demos: Any) -> None:
    assert len(demos) >= 1
    for d in demos:
        assert np.all(np.isfinite(d.joint_pos)) and len(d.time) == len(d.actions)


# ----------------------------------------------------------------------------- read_npz
@FUZZ
@given(data=st.data())
def test_read_npz(files: dict[str, Any], data: st.DataObject) -> None:
    base = files[data.draw(st.sampled_from(["demos", "policy", "demos_stored", "policy_stored"]))]
    raw = data.draw(mutations(base))

    def load(raw: bytes) -> Any:
        try:
            return read_npz(io.BytesIO(raw), max_member_bytes=8 * 2**20, max_total_bytes=16 * 2**20)
        except FileFormatError as exc:
            assert "allow_pickle" not in str(exc) and "in-memory" in str(exc)
            raise

    def valid(arrays: Any) -> None:
        assert all(not a.dtype.hasobject for a in arrays.values())

    _check(load, raw, valid)


@FUZZ
@given(data=st.data())
def test_read_npz_with_schema(files: dict[str, Any], data: st.DataObject) -> None:
    raw = data.draw(mutations(files["policy_stored"]))
    schema = {
        "metadata": MemberSpec(dtype="U", ndim=0),
        "phase_grid": MemberSpec(dtype="f", ndim=1, finite=True),
        "mean__*": MemberSpec(dtype="f", ndim=2),
    }

    def valid(arrays: Any) -> None:
        assert arrays["phase_grid"].ndim == 1 and np.all(np.isfinite(arrays["phase_grid"]))
        assert arrays["metadata"].dtype.kind == "U"

    _check(lambda r: read_npz(io.BytesIO(r), schema=schema), raw, valid)


# ----------------------------------------------------------------------------- the loaders
@FUZZ
@given(data=st.data())
def test_gp_policy_loader(files: dict[str, Any], data: st.DataObject) -> None:
    base = files[data.draw(st.sampled_from(["policy", "policy_stored"]))]
    _check(_gp_policy, data.draw(mutations(base)), _valid_policy)


@FUZZ
@given(data=st.data())
def test_demonstration_loader(files: dict[str, Any], data: st.DataObject) -> None:
    from gym_coffee.demonstrations import DemonstrationSet

    base = files[data.draw(st.sampled_from(["demos", "demos_stored"]))]
    raw = data.draw(mutations(base))
    scratch: Path = files["scratch"]

    def load(raw: bytes) -> Any:
        scratch.write_bytes(raw)
        return DemonstrationSet.load(scratch)

    _check(load, raw, _valid_demos)


def _residual_metadata_file(changes: dict[str, Any]) -> bytes:
    meta: dict[str, Any] = {
        "kind": "lgp_policy.residual_policy",
        "format": "lgp_policy.residual_policy",
        "schema_version": 1,
        "algo": "sac",
        "hyperparameters": {"policy_kwargs": {"net_arch": [8, 8]}},
        "scale": 0.1,
        "gate": {"type": "phase", "start": 0.5},
        "residual_dims": [0],
        "include_gate_obs": False,
        "obs_norm": None,
        "obs_dim": 3,
        "action_dim": 1,
        "param_names": [],
        "base": None,
    }
    meta.update(changes)
    buf = io.BytesIO()
    np.savez(
        buf,
        metadata=np.array(json.dumps(meta)),
        **{
            "space/obs_low": -np.ones(4, np.float32),
            "space/obs_high": np.ones(4, np.float32),
            "space/act_low": -np.ones(1, np.float32),
            "space/act_high": np.ones(1, np.float32),
            "param/actor.mu.weight": np.zeros((1, 8), np.float32),
        },
    )
    return buf.getvalue()


JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**6), 10**12)
    | st.floats(allow_nan=False)
    | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=8,
)
RESIDUAL_KEYS = [
    "algo",
    "scale",
    "gate",
    "residual_dims",
    "obs_dim",
    "action_dim",
    "hyperparameters",
    "schema_version",
    "include_gate_obs",
    "base",
]


@pytest.fixture(scope="module")
def residual_warm(files: dict[str, Any]) -> None:
    """Load one residual file first, so the lazy imports (torch, SB3) are not traced."""
    from lgp_policy.app.commands import load_policy

    pytest.importorskip("stable_baselines3")
    files["scratch"].write_bytes(_residual_metadata_file({}))
    try:
        load_policy(files["scratch"])
    except ValueError:
        pass


@FUZZ
@given(data=st.data())
def test_residual_loader(files: dict[str, Any], residual_warm: None, data: st.DataObject) -> None:
    """Residual files with fuzzed metadata values (each key's value drawn from any JSON) and
    mutated bytes, through the CLI's dispatcher."""
    from lgp_policy.app.commands import load_policy

    changes = data.draw(st.dictionaries(st.sampled_from(RESIDUAL_KEYS), JSON_VALUES, max_size=3))
    raw = _residual_metadata_file(changes)
    if data.draw(st.booleans()):
        raw = data.draw(mutations(raw))
    scratch: Path = files["scratch"]

    def load(raw: bytes) -> Any:
        scratch.write_bytes(raw)
        return load_policy(scratch)

    _check(load, raw, lambda obj: None)
