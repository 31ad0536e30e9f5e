"""Demonstration files: lossless round trip, validation messages, safe writing.

Everything here runs on synthetic arrays (no simulator), except one test, which records
one real teacher episode.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

from gym_coffee import ENV_ID
from gym_coffee.demonstrations import (
    ACTION_DIMS,
    SCHEMA_VERSION,
    Demonstration,
    DemonstrationFormatError,
    DemonstrationSet,
)

OBS_DIM = 41


def unit_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def make_demo(
    rng: np.random.Generator,
    n_steps: int,
    seed: int = 0,
    action_type: str = "joint",
    obs_dim: int = OBS_DIM,
) -> Demonstration:
    """Random arrays within the schema's ranges (no simulator); also used by test_datasets."""
    return Demonstration(
        time=np.arange(n_steps) * 0.05,
        joint_pos=rng.uniform(-2, 2, size=(n_steps, 7)),
        gripper=rng.uniform(0, 0.08, size=n_steps),
        ee_pos=rng.normal(0, 0.3, size=(n_steps, 3)),
        object_pos={
            "cup": rng.normal(0, 0.3, size=(n_steps, 3)),
            "machine": rng.normal(0, 0.3, size=(n_steps, 3)),
        },
        object_quat={"cup": unit_quats(rng, n_steps), "machine": unit_quats(rng, n_steps)},
        stages=rng.random((n_steps, 3)) > 0.5,
        actions=rng.uniform(-1, 1, size=(n_steps, ACTION_DIMS[action_type])).astype(np.float32),
        observations=rng.normal(size=(n_steps, obs_dim)).astype(np.float32),
        seed=seed,
        success=True,
        action_type=action_type,
    )


@pytest.fixture
def demos() -> DemonstrationSet:
    rng = np.random.default_rng(0)
    return DemonstrationSet(
        [make_demo(rng, 30, seed=3), make_demo(rng, 25, seed=4), make_demo(rng, 1, seed=7)],
        metadata={"env_id": ENV_ID, "env_kwargs": {"a": 1}, "seeds": [3, 4, 7]},
    )


def rewrite(path: Path, out: Path, compressed: bool = False, **changes) -> None:
    """Copy an .npz, replacing (value) or deleting (None) arrays."""
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    for key, value in changes.items():
        key = key.replace("__", ".")
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    (np.savez_compressed if compressed else np.savez)(out, **arrays)


def load_error(path: Path) -> str:
    with pytest.raises(DemonstrationFormatError) as info:
        DemonstrationSet.load(path)
    return str(info.value)


def test_round_trip_is_lossless(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    loaded = DemonstrationSet.load(path)
    assert loaded == demos
    assert len(loaded) == 3 and loaded.seeds == [3, 4, 7]
    assert loaded.metadata == demos.metadata
    for a, b in zip(loaded, demos, strict=True):
        for name in ("time", "joint_pos", "gripper", "ee_pos", "stages", "actions", "observations"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and x.shape == y.shape
            np.testing.assert_array_equal(x, y)
        for obj in ("cup", "machine"):
            np.testing.assert_array_equal(a.object_pos[obj], b.object_pos[obj])
            np.testing.assert_array_equal(a.object_quat[obj], b.object_quat[obj])


def test_file_is_one_npz_without_pickle(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    assert sorted(os.listdir(tmp_path)) == ["d.npz"]  # no temp file left behind
    with np.load(path, allow_pickle=False) as npz:
        for key in npz.files:
            assert npz[key].dtype != object
        meta = json.loads(str(npz["metadata"]))
    assert meta["schema_version"] == SCHEMA_VERSION
    assert meta["obs_dim"] == OBS_DIM
    assert meta["objects"] == ["cup", "machine"]
    np.testing.assert_array_equal(npz_lengths(path), [30, 25, 1])


def npz_lengths(path: Path) -> np.ndarray:
    with np.load(path, allow_pickle=False) as npz:
        return npz["lengths"]


def test_sequence_protocol(demos):
    assert [d.seed for d in demos] == [3, 4, 7]
    assert demos[-1].n_steps == 1
    assert isinstance(demos[:2], DemonstrationSet) and len(demos[:2]) == 2
    assert "seeds=[3, 4, 7]" in repr(demos)


def test_never_overwrites_without_overwrite(demos, tmp_path):
    path = tmp_path / "d.npz"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        demos.save(path)
    assert path.read_bytes() == b"precious"
    demos.save(path, overwrite=True)
    assert DemonstrationSet.load(path) == demos
    assert sorted(os.listdir(tmp_path)) == ["d.npz"]


def test_failed_write_leaves_old_file_intact(demos, tmp_path, monkeypatch):
    path = demos.save(tmp_path / "d.npz")
    before = path.read_bytes()

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", disk_full)
    with pytest.raises(OSError, match="No space"):
        demos[:1].save(path, overwrite=True)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["d.npz"]  # the temp file was removed


def test_unserialisable_metadata_fails_before_touching_disk(demos, tmp_path):
    demos.metadata["bad"] = object()
    with pytest.raises(TypeError, match="JSON"):
        demos.save(tmp_path / "d.npz")
    assert os.listdir(tmp_path) == []


def test_missing_folder_is_created(demos, tmp_path):
    path = demos.save(tmp_path / "new" / "sub" / "d.npz")
    assert DemonstrationSet.load(path) == demos
    assert sorted(os.listdir(path.parent)) == ["d.npz"]  # no temporary file left
    (tmp_path / "file").write_bytes(b"")
    with pytest.raises(OSError):  # a file where a folder would have to be
        demos.save(tmp_path / "file" / "d.npz")


def test_empty_set_cannot_be_saved(tmp_path):
    with pytest.raises(DemonstrationFormatError, match="empty"):
        DemonstrationSet([]).save(tmp_path / "d.npz")


@pytest.mark.parametrize("keep", [10, 500, 0.5])
def test_truncated_file(demos, tmp_path, keep):
    path = demos.save(tmp_path / "d.npz")
    data = path.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: int(len(data) * keep) if keep < 1 else keep])
    msg = load_error(cut)
    assert "cut.npz" in msg and ("truncated or corrupt" in msg)


@pytest.mark.parametrize(
    ("content", "kind"),
    [
        (b"time,x\n0.0,1.0\n", "a text file"),
        (b"", "an empty file"),
        (b"\x00\xff\x10\x80binary", "not a zip archive"),
        (None, "a single .npy array"),
    ],
)
def test_not_an_npz_file(tmp_path, content, kind):
    """A text (or other) file renamed .npz: one clear line, not numpy's allow_pickle hint."""
    path = tmp_path / "x.npz"
    if content is None:
        np.save(tmp_path / "a.npy", np.zeros(3))
        content = (tmp_path / "a.npy").read_bytes()
    path.write_bytes(content)
    msg = load_error(path)
    assert f"is not an .npz file ({kind};" in msg and "x.npz" in msg
    assert "pickle" not in msg


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        DemonstrationSet.load(tmp_path / "nope.npz")


def test_corrupt_member(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    # Flip bytes in the middle of the compressed data of one member: CRC / zlib error.
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("joint_pos.npy")
    data = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    for i in range(start + 20, start + 60):
        data[i] ^= 0xFF
    bad = tmp_path / "bad.npz"
    bad.write_bytes(bytes(data))
    msg = load_error(bad)
    assert "truncated or corrupt" in msg


def test_wrong_shape_names_array_and_expected_shape(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    rewrite(path, tmp_path / "w.npz", joint_pos=np.zeros((56, 6)))
    msg = load_error(tmp_path / "w.npz")
    assert "'joint_pos'" in msg and "(56, 6)" in msg and "expected (56, 7)" in msg


def test_wrong_observation_size(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    rewrite(path, tmp_path / "w.npz", observations=np.zeros((56, OBS_DIM + 1), np.float32))
    msg = load_error(tmp_path / "w.npz")
    assert "'observations'" in msg and f"expected (56, {OBS_DIM})" in msg


def test_lengths_that_do_not_add_up(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    rewrite(path, tmp_path / "w.npz", lengths=np.array([30, 25, 2]))
    msg = load_error(tmp_path / "w.npz")
    assert "add up to 57" in msg and "56 rows" in msg


def test_lengths_and_seeds_disagree(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    rewrite(path, tmp_path / "w.npz", seeds=np.array([3, 4]))
    assert "'seeds'" in load_error(tmp_path / "w.npz")
    rewrite(path, tmp_path / "w2.npz", lengths=np.array([30, 26, 0]))
    assert "entries < 1" in load_error(tmp_path / "w2.npz")


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_non_finite_values_name_the_array_and_row(demos, tmp_path, value):
    path = demos.save(tmp_path / "d.npz")
    with np.load(path) as npz:
        ee = npz["ee_pos"].copy()
    ee[33, 1] = value  # demonstration 1, step 3
    rewrite(path, tmp_path / "w.npz", ee_pos=ee)
    msg = load_error(tmp_path / "w.npz")
    word = "NaN" if np.isnan(value) else "inf"
    assert f"'ee_pos' contains {word}" in msg and "demonstration 1, step 3" in msg


def test_non_finite_in_object_pose(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    with np.load(path) as npz:
        q = npz["object_quat.machine"].copy()
    q[0, 0] = np.nan
    rewrite(path, tmp_path / "w.npz", object_quat__machine=q)
    assert "'object_quat.machine' contains NaN" in load_error(tmp_path / "w.npz")


def test_missing_array(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    rewrite(path, tmp_path / "w.npz", object_pos__cup=None, stages=None)
    msg = load_error(tmp_path / "w.npz")
    assert "missing arrays" in msg and "'stages'" in msg and "'object_pos.cup'" in msg


def edit_metadata(path: Path, out: Path, **changes) -> None:
    with np.load(path) as npz:
        meta = json.loads(str(npz["metadata"]))
    meta.update(changes)
    rewrite(path, out, metadata=np.array(json.dumps(meta)))


@pytest.mark.parametrize("version", [SCHEMA_VERSION + 1, 0, "1", None])
def test_wrong_schema_version(demos, tmp_path, version):
    path = demos.save(tmp_path / "d.npz")
    edit_metadata(path, tmp_path / "w.npz", schema_version=version)
    msg = load_error(tmp_path / "w.npz")
    assert f"schema version {version!r} is not supported" in msg
    if version == SCHEMA_VERSION + 1:
        assert "newer" in msg


def test_not_a_demonstration_file(tmp_path):
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    assert "missing array 'metadata'" in load_error(tmp_path / "other.npz")
    np.savez(tmp_path / "other2.npz", metadata=np.array('{"format": "something"}'))
    assert "not a gym_coffee demonstration file" in load_error(tmp_path / "other2.npz")
    np.savez(tmp_path / "other3.npz", metadata=np.array("{not json"))
    assert "not valid JSON" in load_error(tmp_path / "other3.npz")


def test_pickled_array_is_refused(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    rewrite(path, tmp_path / "w.npz", stages=np.array([{"x": 1}], dtype=object))
    assert "pickle" in load_error(tmp_path / "w.npz")


def test_wrong_dtype(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    rewrite(path, tmp_path / "w.npz", time=np.array(["a"] * 56))
    assert "'time' has dtype" in load_error(tmp_path / "w.npz")
    with np.load(path) as npz:
        stages, actions = npz["stages"], npz["actions"]
    rewrite(path, tmp_path / "s.npz", stages=stages.astype(float))  # 0.0 / 1.0, not flags
    assert "'stages' has dtype float64; expected bool" in load_error(tmp_path / "s.npz")
    rewrite(path, tmp_path / "a.npz", actions=actions.astype(np.int64))
    assert "'actions' has dtype int64; expected float32" in load_error(tmp_path / "a.npz")
    rewrite(path, tmp_path / "f.npz", actions=actions.astype(np.float64))  # any float is fine
    assert DemonstrationSet.load(tmp_path / "f.npz") == demos


def test_constructor_validates_shapes():
    rng = np.random.default_rng(1)
    demo = make_demo(rng, 5)
    with pytest.raises(DemonstrationFormatError, match=r"'ee_pos' has shape \(5, 2\)"):
        Demonstration(**{**vars(demo), "ee_pos": np.zeros((5, 2))})
    with pytest.raises(DemonstrationFormatError, match=r"'actions' has shape \(4, 8\)"):
        Demonstration(**{**vars(demo), "actions": np.zeros((4, 8))})
    with pytest.raises(DemonstrationFormatError, match="same objects"):
        Demonstration(**{**vars(demo), "object_quat": {"cup": np.zeros((5, 4))}})
    with pytest.raises(DemonstrationFormatError, match="NaN"):
        Demonstration(**{**vars(demo), "time": np.full(5, np.nan)})
    other = make_demo(rng, 5)
    other.observations = np.zeros((5, OBS_DIM + 2), np.float32)
    with pytest.raises(DemonstrationFormatError, match="obs_dim"):
        DemonstrationSet([demo, other])


# -- collect_demonstrations -----------------------------------------------------------------------


class _FakeEnv:
    spec = None

    @property
    def unwrapped(self):
        return self


def test_failed_episodes_are_skipped_and_recorded(monkeypatch):
    """A failed teacher episode is retried with the next seed; the skipped seeds are recorded."""
    import gym_coffee.demonstrations as demonstrations

    rng = np.random.default_rng(0)

    def fake_episode(env, seed, *args):
        demo = make_demo(rng, 4, seed=seed)
        demo.success = seed not in (11, 13)
        return demo

    monkeypatch.setattr(demonstrations, "_record_episode", fake_episode)
    demos = demonstrations.collect_demonstrations(_FakeEnv(), n=3, seed=10)
    assert demos.seeds == [10, 12, 14]
    assert demos.metadata["seeds"] == [10, 12, 14]
    assert demos.metadata["failed_seeds"] == [11, 13]
    assert all(d.success for d in demos)

    kept = demonstrations.collect_demonstrations(_FakeEnv(), n=3, seed=10, keep_failed=True)
    assert kept.seeds == [10, 11, 12] and [d.success for d in kept] == [True, False, True]

    with pytest.raises(RuntimeError, match="succeeded on only 2 of 4 layouts"):
        demonstrations.collect_demonstrations(_FakeEnv(), n=3, seed=11, max_attempts=4)
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="positive integer"):
            demonstrations.collect_demonstrations(_FakeEnv(), n=bad, seed=0)


def test_collect_one_real_demonstration_from_a_raw_env(tmp_path):
    """A raw CoffeeEnv (no gym.make) works; recorded arrays agree with the observations."""
    from gym_coffee.env import CONTROL_DT, CoffeeEnv, obs_part

    env = CoffeeEnv()
    try:
        demos = gym_coffee_collect(env, n=1, seed=0)
    finally:
        env.close()
    demo = demos[0]
    meta = demos.metadata
    assert meta["env_id"] == ENV_ID  # found through the registry
    assert meta["seeds"] == [demo.seed] and demo.success
    assert meta["control_dt"] == pytest.approx(CONTROL_DT)
    obs = demo.observations
    np.testing.assert_allclose(demo.time, np.arange(demo.n_steps) * CONTROL_DT, atol=1e-5)
    np.testing.assert_array_equal(demo.joint_pos, obs_part(obs, "joint_pos"))
    np.testing.assert_array_equal(demo.object_pos["cup"], obs_part(obs, "cup_pos"))
    yaw = obs_part(obs, "machine_yaw")[:, 0].astype(np.float64)
    np.testing.assert_allclose(demo.object_quat["machine"][:, 2], np.sin(yaw / 2))
    np.testing.assert_allclose(np.linalg.norm(demo.object_quat["cup"], axis=1), 1.0, atol=1e-5)
    assert not demo.stages[0].any() and demo.stages[-1].all()
    # Stage flags switch on in the task's order.
    first = [int(np.argmax(demo.stages[:, i])) for i in range(3)]
    assert first[0] < first[1] < first[2]
    assert np.abs(demo.actions).max() <= 1.0
    path = demos.save(tmp_path / "real.npz")
    assert DemonstrationSet.load(path) == demos


def gym_coffee_collect(env, **kwargs):
    from gym_coffee import collect_demonstrations

    return collect_demonstrations(env, **kwargs)


# -- bounded, pickle-free loading (issue 8) --------------------------------------------------------


def add_members(path: Path, out: Path, members: dict[str, bytes]) -> None:
    """Copy a zip and add raw members."""
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            dst.writestr(info, src.read(info))
        for name, data in members.items():
            dst.writestr(name, data)


def npy_bytes(arr: np.ndarray, header_shape: tuple[int, ...] | None = None) -> bytes:
    """The .npy encoding of ``arr``; ``header_shape`` makes the header lie about the shape."""
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf,
        {
            "descr": np.lib.format.dtype_to_descr(arr.dtype),
            "fortran_order": False,
            "shape": arr.shape if header_shape is None else header_shape,
        },
    )
    return buf.getvalue() + arr.tobytes()


def test_unknown_members_are_never_read(demos, tmp_path):
    """Arrays the schema does not know -- a pickle, a zip bomb -- are ignored unread."""
    path = demos.save(tmp_path / "d.npz")
    bomb = np.zeros(20_000_000, np.uint8)  # 20 MB of zeros: ~20 kB compressed
    pickled = (
        b"\x93NUMPY\x01\x00v\x00{'descr': '|O', 'fortran_order': False, 'shape': (1,), }"
        + b" " * 41
        + b"\n"
        + b"\x80\x04\x95\x00"
    )
    add_members(path, tmp_path / "x.npz", {"bomb.npy": npy_bytes(bomb), "evil.npy": pickled})
    assert DemonstrationSet.load(tmp_path / "x.npz", max_bytes=1_000_000) == demos


def test_declared_size_is_checked_before_decompressing(demos, tmp_path):
    """A known member that declares more than max_bytes is refused before it is inflated."""
    import tracemalloc

    path = demos.save(tmp_path / "d.npz")
    rewrite(
        path,
        tmp_path / "bomb.npz",
        compressed=True,
        observations=np.zeros((56, 200_000), np.float32),
    )
    size = (tmp_path / "bomb.npz").stat().st_size
    assert size < 1_000_000  # 45 MB of zeros compress to a small file
    tracemalloc.start()
    try:
        msg = load_error_kw(tmp_path / "bomb.npz", max_bytes=1_000_000)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert "'observations' declares 44800128 bytes uncompressed; the limit is 1000000" in msg
    assert peak < 1_000_000


def test_file_larger_than_the_limit(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    msg = load_error_kw(path, max_bytes=1000)
    assert f"has {path.stat().st_size} bytes; the limit is 1000" in msg


def test_npy_header_that_lies_about_the_shape(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    rewrite(path, tmp_path / "w.npz", time=None)
    add_members(
        tmp_path / "w.npz",
        tmp_path / "lie.npz",
        {"time.npy": npy_bytes(np.zeros(56), header_shape=(10**12,))},
    )
    msg = load_error(tmp_path / "lie.npz")
    assert "'time' has shape (1000000000000,)" in msg and "holds 448 bytes" in msg


def test_load_from_memory_and_never_writes(demos, tmp_path):
    import io

    path = demos.save(tmp_path / "d.npz")
    before = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    assert DemonstrationSet.load(io.BytesIO(path.read_bytes())) == demos
    assert DemonstrationSet.load(path) == demos
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == before
    with pytest.raises(DemonstrationFormatError, match=r"demonstration file is not an \.npz"):
        DemonstrationSet.load(io.BytesIO(b"hello"))


def load_error_kw(path: Path, **kwargs) -> str:
    with pytest.raises(DemonstrationFormatError) as info:
        DemonstrationSet.load(path, **kwargs)
    return str(info.value)


@pytest.mark.parametrize(
    ("name", "row", "value", "expected"),
    [
        (
            "actions",
            40,
            1.5,
            "'actions' has a value outside [-1, 1]: 1.5 at index (40, 0); "
            "row 40 is demonstration 1, step 10",
        ),
        ("ee_pos", 3, 1e300, "'ee_pos' has a value outside [-5, 5]"),
        ("gripper", 0, -0.5, "'gripper' has a value outside [0, 0.1]"),
        ("joint_pos", 55, 7.0, "row 55 is demonstration 2, step 0"),
        ("observations", 1, 1e20, "'observations' has a value outside [-10000, 10000]"),
        (
            "object_quat.cup",
            31,
            0.0,
            "demonstration 1: array 'object_quat.cup' row 1 is not a unit quaternion",
        ),
        ("time", 2, 0.01, "demonstration 0: array 'time' does not increase at step 2"),
    ],
)
def test_values_out_of_range(demos, tmp_path, name, row, value, expected):
    path = demos.save(tmp_path / "d.npz")
    with np.load(path) as npz:
        arr = npz[name].copy()
    arr.reshape(arr.shape[0], -1)[row, 0] = value
    rewrite(path, tmp_path / "w.npz", **{name.replace(".", "__"): arr})
    assert expected in load_error(tmp_path / "w.npz")


def test_negative_seed_and_bad_action_type(demos, tmp_path):
    path = demos.save(tmp_path / "d.npz")
    edit_metadata(path, tmp_path / "m.npz", seeds=[3, 4, -7])
    rewrite(tmp_path / "m.npz", tmp_path / "w.npz", seeds=np.array([3, 4, -7]))
    assert "'seeds' has entries outside [0, 2**63)" in load_error(tmp_path / "w.npz")
    edit_metadata(path, tmp_path / "a.npz", action_type="mind_control")
    assert "action_type is 'mind_control'; expected one of" in load_error(tmp_path / "a.npz")
    edit_metadata(path, tmp_path / "o.npz", obs_dim=10**9)
    assert "'obs_dim' is 1000000000" in load_error(tmp_path / "o.npz")


def test_schema_version_1_files_still_load(demos, tmp_path):
    """Version 1 had joint actions only and no action_type."""
    path = demos.save(tmp_path / "d.npz")
    with np.load(path) as npz:
        meta = json.loads(str(npz["metadata"]))
    del meta["action_type"]
    meta["schema_version"] = 1
    rewrite(path, tmp_path / "v1.npz", metadata=np.array(json.dumps(meta)))
    loaded = DemonstrationSet.load(tmp_path / "v1.npz")
    assert loaded == demos and loaded.action_type == "joint"


@pytest.mark.parametrize("action_type", ["ee", "ee_rot"])
def test_end_effector_actions_round_trip(tmp_path, action_type):
    rng = np.random.default_rng(2)
    demos = DemonstrationSet([make_demo(rng, 6, 1, action_type), make_demo(rng, 4, 2, action_type)])
    assert demos[0].actions.shape == (6, ACTION_DIMS[action_type])
    np.testing.assert_array_equal(demos[0].gripper_command, demos[0].actions[:, -1])
    loaded = DemonstrationSet.load(demos.save(tmp_path / "d.npz"))
    assert loaded == demos and loaded.action_type == action_type
    with np.load(tmp_path / "d.npz") as npz:
        assert json.loads(str(npz["metadata"]))["action_type"] == action_type
    with pytest.raises(DemonstrationFormatError, match="action_type 'joint', demonstration 0"):
        DemonstrationSet([demos[0], make_demo(rng, 3)])
    with pytest.raises(DemonstrationFormatError, match=r"'actions' has shape \(6, 4\)"):
        Demonstration(**{**vars(demos[0]), "action_type": "ee_rot", "actions": np.zeros((6, 4))})


def test_teacher_refuses_an_end_effector_env():
    import gym_coffee.demonstrations as demonstrations

    env = _FakeEnv()
    env.action_type = "ee"
    with pytest.raises(ValueError, match="action_type='joint'"):
        demonstrations.collect_demonstrations(env, n=1)


# -- videos ----------------------------------------------------------------------------------------


def test_video_is_never_overwritten_by_default(tmp_path):
    from gym_coffee.video import write_video

    frames = [np.full((8, 10, 3), 20 * i, np.uint8) for i in range(4)]
    path = tmp_path / "v.gif"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_video(path, frames)
    assert path.read_bytes() == b"precious"
    write_video(path, frames, overwrite=True)
    assert path.read_bytes()[:3] == b"GIF"
    assert sorted(os.listdir(tmp_path)) == ["v.gif"]
    for fps in (0, -1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="fps must be a positive finite number"):
            write_video(tmp_path / "w.gif", frames, fps=fps)
    with pytest.raises(ValueError, match="frame 1 contains NaN"):
        write_video(tmp_path / "w.gif", [np.zeros((4, 4, 3)), np.full((4, 4, 3), np.nan)])
    assert sorted(os.listdir(tmp_path)) == ["v.gif"]


def test_failed_video_write_leaves_no_file(tmp_path, monkeypatch):
    import PIL.Image

    from gym_coffee.video import write_video

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    # GIFs are written by Pillow (a failure mid-write, after the temporary file exists).
    monkeypatch.setattr(PIL.Image.Image, "save", disk_full)
    with pytest.raises(OSError, match="No space"):
        write_video(tmp_path / "v.gif", [np.zeros((4, 4, 3), np.uint8)])
    assert os.listdir(tmp_path) == []
