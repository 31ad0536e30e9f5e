"""``lgp_policy._io``: atomic writes that never lose a file, bounded reads that never unpickle."""

from __future__ import annotations

import errno
import io
import json
import os
import stat
import tracemalloc
import zipfile

import numpy as np
import pytest

from lgp_policy import _io
from lgp_policy._io import (
    FileFormatError,
    MemberSpec,
    atomic_save_npz,
    atomic_write_bytes,
    atomic_write_text,
    check_output_path,
    read_json_member,
    read_npz,
)


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# ------------------------------------------------------------------------------------ writing
def test_atomic_write_refuses_existing_without_force(tmp_path):
    path = tmp_path / "a.json"
    atomic_write_text(path, "old", force=False)
    with pytest.raises(FileExistsError, match=r"a\.json exists; pass --force"):
        atomic_write_text(path, "new", force=False)
    assert path.read_text() == "old"
    atomic_write_text(path, "new", force=True)
    assert path.read_text() == "new"
    assert _leftovers(tmp_path) == []


def test_new_files_get_the_usual_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        a = atomic_write_bytes(tmp_path / "a.bin", b"x", force=False)
        b = atomic_save_npz(tmp_path / "b.npz", {"x": np.zeros(2)}, force=False)
    finally:
        os.umask(old)
    assert stat.S_IMODE(a.stat().st_mode) == 0o644
    assert stat.S_IMODE(b.stat().st_mode) == 0o644


def test_full_disk_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "results.json"
    path.write_text('{"old": 1}')

    def no_space(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_io.os, "fsync", no_space)
    with pytest.raises(OSError, match="No space"):
        atomic_write_text(path, json.dumps({"new": 2}), force=True)
    assert json.loads(path.read_text()) == {"old": 1}
    assert _leftovers(tmp_path) == []


def test_interrupted_writer_keeps_the_old_file(tmp_path):
    path = tmp_path / "v.gif"
    path.write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt), _io.atomic_output(path, force=True) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".gif"
        tmp.write_bytes(b"half")
        raise KeyboardInterrupt
    assert path.read_bytes() == b"old"
    assert _leftovers(tmp_path) == []


def test_a_file_created_meanwhile_is_not_overwritten(tmp_path):
    path = tmp_path / "x.bin"
    with pytest.raises(FileExistsError), _io.atomic_output(path, force=False) as tmp:
        tmp.write_bytes(b"mine")
        path.write_bytes(b"theirs")  # appears while we write
    assert path.read_bytes() == b"theirs"
    assert _leftovers(tmp_path) == []


def test_save_npz_keeps_the_name_and_refuses_objects(tmp_path):
    path = atomic_save_npz(tmp_path / "p.weights", {"w": np.arange(3.0)}, force=False)
    assert path.name == "p.weights"
    assert read_npz(path)["w"].tolist() == [0.0, 1.0, 2.0]
    with pytest.raises(ValueError, match="'bad' has an object dtype"):
        atomic_save_npz(tmp_path / "o.npz", {"bad": np.array([{}], dtype=object)}, force=False)
    assert not (tmp_path / "o.npz").exists()


def test_check_output_path(tmp_path):
    assert check_output_path(tmp_path / "new" / "v.mp4", force=False, suffixes=(".mp4",))
    with pytest.raises(ValueError, match=r"expected a name ending in \.mp4 or \.gif, got '\.avi'"):
        check_output_path(tmp_path / "v.avi", force=False, suffixes=(".mp4", ".gif"))
    with pytest.raises(ValueError, match="is a folder"):
        check_output_path(tmp_path, force=True)
    (tmp_path / "f").write_text("")
    with pytest.raises(FileExistsError, match="pass --force"):
        check_output_path(tmp_path / "f", force=False)
    with pytest.raises(ValueError, match="is not a folder"):
        check_output_path(tmp_path / "f" / "x.json", force=False)
    if os.geteuid() != 0:  # root may write anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(ValueError, match="not writable"):
            check_output_path(ro / "x.json", force=False)


def test_a_dangling_link_counts_as_an_existing_output(tmp_path):
    """Refused up front without force (the writer's hard link would refuse it after the work);
    with force the link itself is replaced, nothing is written through it."""
    link = tmp_path / "out.json"
    link.symlink_to(tmp_path / "elsewhere" / "target.json")
    with pytest.raises(FileExistsError, match="exists; pass --force"):
        check_output_path(link, force=False)
    with pytest.raises(FileExistsError, match="exists; pass --force"):
        atomic_write_text(link, "new", force=False)
    assert link.is_symlink() and not (tmp_path / "elsewhere").exists()
    assert check_output_path(link, force=True) == link
    atomic_write_text(link, "new", force=True)
    assert not link.is_symlink() and link.read_text() == "new"
    assert not (tmp_path / "elsewhere").exists()


# ------------------------------------------------------------------------------------ reading
def _npz(tmp_path, name="f.npz", **arrays):
    path = tmp_path / name
    np.savez_compressed(path, **arrays)
    return path


def test_round_trip_with_schema_and_patterns(tmp_path):
    path = _npz(
        tmp_path,
        metadata=np.array(json.dumps({"kind": "k"})),
        **{"param/a": np.ones((2, 3), order="F"), "param/b": np.arange(4), "other": np.zeros(9)},
    )
    got = read_npz(
        path,
        schema={"param/*": MemberSpec(dtype="fi"), "metadata": MemberSpec(dtype="U", ndim=0)},
    )
    assert sorted(got) == ["metadata", "param/a", "param/b"]
    np.testing.assert_array_equal(got["param/a"], np.ones((2, 3)))
    assert read_json_member(path, required_keys=("kind",)) == {"kind": "k"}
    buf = io.BytesIO(path.read_bytes())
    assert sorted(read_npz(buf, members={"other": MemberSpec(shape=(9,))})) == ["other"]


def test_unknown_members_are_never_decompressed(tmp_path):
    path = _npz(tmp_path, w=np.ones(3), bomb=np.zeros(40 * 2**20, dtype=np.uint8))
    assert path.stat().st_size < 200_000
    tracemalloc.start()
    try:
        got = read_npz(path, schema={"w": MemberSpec()}, max_member_bytes=2**20)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert list(got) == ["w"] and peak < 2**20
    with pytest.raises(FileFormatError, match=r"member 'bomb': declares 41943\d+ bytes"):
        read_npz(path, max_member_bytes=2**20)


def _raw_npz(tmp_path, member, payload, name="raw.npz"):
    path = tmp_path / name
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(member, payload)
    return path


def _npy_bytes(array):
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def test_a_lying_header_is_refused_before_allocating(tmp_path):
    header = np.lib.format.header_data_from_array_1_0(np.zeros(4))
    header["shape"] = (10**10,)
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    path = _raw_npz(tmp_path, "x.npy", buf.getvalue() + np.zeros(4).tobytes())
    tracemalloc.start()
    try:
        with pytest.raises(FileFormatError, match=r"member 'x': header says \(10000000000,\)"):
            read_npz(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2**20


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        (b"hello, this is text\n", r"is not an .npz file \(expected a zip archive of .npy"),
        (b"", "is not an .npz file"),
        (None, "a single .npy array"),
    ],
)
def test_not_an_npz(tmp_path, content, fragment):
    path = tmp_path / "renamed.npz"
    path.write_bytes(_npy_bytes(np.ones(2)) if content is None else content)
    with pytest.raises(FileFormatError, match=fragment) as info:
        read_npz(path)
    assert "allow_pickle" not in str(info.value) and str(path) in str(info.value)


def test_object_arrays_are_refused_without_numpy_hint(tmp_path):
    path = tmp_path / "o.npz"
    np.savez(path, meta=np.array([{"a": 1}], dtype=object))
    with pytest.raises(FileFormatError, match="'meta': holds Python objects") as info:
        read_npz(path)
    assert "allow_pickle" not in str(info.value)


def test_truncated_and_corrupt_files(tmp_path):
    path = _npz(tmp_path, w=np.arange(1000.0))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError, match="truncated"):
        read_npz(path)
    stored = tmp_path / "s.npz"
    np.savez(stored, w=np.arange(1000.0))  # uncompressed: flip a data byte -> bad CRC
    data = bytearray(stored.read_bytes())
    data[500] ^= 0xFF
    stored.write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match="member 'w' cannot be read"):
        read_npz(stored)


def test_member_checks(tmp_path):
    path = _npz(tmp_path, w=np.array([1.0, np.nan]), i=np.arange(3))
    with pytest.raises(FileFormatError, match="missing member 'v'"):
        read_npz(path, schema={"v": MemberSpec()})
    assert read_npz(path, schema={"v": MemberSpec(required=False)}) == {}
    with pytest.raises(FileFormatError, match="'i': has dtype int64; expected dtype kind f"):
        read_npz(path, schema={"i": MemberSpec(dtype="f")})
    with pytest.raises(FileFormatError, match=r"'i': has shape \(3,\); expected 2 dim"):
        read_npz(path, schema={"i": MemberSpec(ndim=2)})
    with pytest.raises(FileFormatError, match=r"expected \(None, 3\)"):
        read_npz(path, schema={"i": MemberSpec(shape=(None, 3))})
    with pytest.raises(FileFormatError, match="'w': contains NaN or inf"):
        read_npz(path, schema={"w": MemberSpec(finite=True)})
    with pytest.raises(FileFormatError, match=r"'w': declares .* expected at most 8"):
        read_npz(path, schema={"w": MemberSpec(max_bytes=8)})
    with pytest.raises(FileNotFoundError):
        read_npz(tmp_path / "missing.npz")


def test_too_many_entries(tmp_path):
    path = _npz(tmp_path, **{f"a{i}": np.zeros(1) for i in range(20)})
    with pytest.raises(FileFormatError, match="lists 20 entries; expected at most 10"):
        read_npz(path, max_entries=10)


def _lying_count(path, count):
    """Set the end-of-central-directory record's entry counts to ``count`` (the directory and its
    declared size unchanged: :mod:`zipfile` still parses every entry)."""
    raw = bytearray(path.read_bytes())
    eocd = raw.rfind(b"PK\x05\x06")
    raw[eocd + 8 : eocd + 12] = count.to_bytes(2, "little") * 2
    path.write_bytes(bytes(raw))
    return path


def test_a_lying_entry_count_does_not_let_a_large_directory_through(tmp_path):
    """2000 entries declared as 2: the directory's size (what zipfile parses) is checked too."""
    path = _npz(tmp_path, w=np.zeros(3), **{f"x{i}": np.zeros(0) for i in range(2000)})
    _lying_count(path, 2)
    with pytest.raises(FileFormatError, match=r"\d+-byte zip directory; expected at most"):
        read_npz(path, max_entries=100)
    assert read_npz(_npz(tmp_path, w=np.zeros(3)), max_entries=1)["w"].shape == (3,)


def _as_zip64(path, count=None):
    """End the archive with a ZIP64 end record, its locator and a classic record whose fields
    point to them (as zipfile writes for >65535 entries); ``count``: the entries it declares."""
    raw = path.read_bytes()
    pos = raw.rfind(b"PK\x05\x06")
    _sig, _d, _dcd, _n, total, size, offset, _c = _io._EOCD.unpack_from(raw, pos)
    total = total if count is None else count
    record = _io._ZIP64_EOCD.pack(b"PK\x06\x06", 44, 45, 45, 0, 0, total, total, size, offset)
    locator = _io._ZIP64_LOCATOR.pack(b"PK\x06\x07", 0, pos, 1)
    end = _io._EOCD.pack(b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0)
    path.write_bytes(raw[:pos] + record + locator + end)
    return path


def test_zip64_directories_are_checked_in_their_zip64_record(tmp_path):
    good = _as_zip64(_npz(tmp_path, "good.npz", w=np.arange(3.0)))
    assert read_npz(good, max_entries=1)["w"].tolist() == [0.0, 1.0, 2.0]
    many = _as_zip64(_npz(tmp_path, "many.npz", **{f"x{i}": np.zeros(0) for i in range(20)}))
    with pytest.raises(FileFormatError, match="lists 20 entries; expected at most 10"):
        read_npz(many, max_entries=10)
    lying = _npz(tmp_path, "lying.npz", **{f"x{i}": np.zeros(0) for i in range(2000)})
    _as_zip64(lying, count=2)
    with pytest.raises(FileFormatError, match=r"\d+-byte zip directory; expected at most"):
        read_npz(lying, max_entries=100)
    raw = bytearray(good.read_bytes())
    raw[raw.rfind(b"PK\x06\x07") : raw.rfind(b"PK\x06\x07") + 4] = b"XXXX"  # no locator
    (tmp_path / "bad.npz").write_bytes(bytes(raw))
    with pytest.raises(FileFormatError, match="ZIP64"):
        read_npz(tmp_path / "bad.npz")


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("{not json", "expected valid JSON"),
        ('{"a": NaN}', "NaN is not a number"),
        ('{"a": 1e999}', "overflows a float"),
        ("[" * 100_000 + "]" * 100_000, "RecursionError"),
        ("[1, 2]", "expected a JSON object, got list"),
    ],
)
def test_json_member(tmp_path, text, fragment):
    path = _npz(tmp_path, metadata=np.array(text))
    with pytest.raises(FileFormatError, match=fragment) as info:
        read_json_member(path)
    assert "member 'metadata'" in str(info.value)


def test_json_member_wrong_kind_and_missing_key(tmp_path):
    path = _npz(tmp_path, metadata=np.array([1.0]))
    with pytest.raises(FileFormatError, match="has dtype float64; expected dtype kind U"):
        read_json_member(path)
    path = _npz(tmp_path, "g.npz", metadata=np.array("{}"))
    with pytest.raises(FileFormatError, match="expected a key 'kind'"):
        read_json_member(path, required_keys=("kind",))
