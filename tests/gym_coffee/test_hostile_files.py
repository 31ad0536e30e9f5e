"""Hostile demonstration files (.npz) and robomimic HDF5 files: each is refused with one clear
:class:`DemonstrationFormatError` naming the file and what was expected, quickly and with bounded
memory, without following links to other files, and without writing anything.

Every file is crafted here in ``tmp_path`` from a small synthetic demonstration set.
"""

from __future__ import annotations

import io
import json
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
from test_demonstrations import make_demo  # the synthetic demonstrations of the file tests

from gym_coffee.demonstrations import DemonstrationFormatError, DemonstrationSet


@pytest.fixture
def demos() -> DemonstrationSet:
    """Two demonstrations of the same length (so that one's arrays fit the other's shapes)."""
    rng = np.random.default_rng(11)
    return DemonstrationSet(
        [make_demo(rng, 6, seed=1), make_demo(rng, 6, seed=2)], metadata={"who": "synthetic"}
    )


def save_arrays(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    np.savez(path, **arrays)  # type: ignore[arg-type]
    return path


def load_error(source, **kwargs) -> str:
    with pytest.raises(DemonstrationFormatError) as info:
        DemonstrationSet.load(source, **kwargs)
    return str(info.value)


def cli(args: list[str]) -> int:
    from lgp_policy.app.cli import main

    return main(args)


# -- metadata JSON is parsed strictly -------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "shown"),
    [("NaN", "NaN"), ("Infinity", "Infinity"), ("-Infinity", "-Infinity"), ("1e400", "1e400")],
)
def test_metadata_with_nan_infinity_or_overflow_is_refused(demos, tmp_path, value, shown):
    arrays = demos.to_arrays()
    text = str(arrays["metadata"])
    arrays["metadata"] = np.array(text[:-1] + f', "note": {value}}}')
    path = save_arrays(tmp_path / "nan.npz", arrays)
    msg = load_error(path)
    assert msg.startswith(str(path)) and "'metadata'" in msg and shown in msg
    assert "expected strict JSON" in msg
    # The command line reports the bad file (exit 2) instead of failing later in the export.
    out = tmp_path / "x.hdf5"
    assert cli(["export", str(path), "--format", "robomimic", "--out", str(out)]) == 2
    assert not out.exists()


def test_metadata_with_a_huge_integer_is_refused(demos, tmp_path):
    arrays = demos.to_arrays()
    text = str(arrays["metadata"])
    arrays["metadata"] = np.array(text[:-1] + ', "note": ' + "9" * 400 + "}")
    msg = load_error(save_arrays(tmp_path / "big.npz", arrays))
    assert "'metadata'" in msg and "expected strict JSON" in msg


def test_robomimic_metadata_with_nan_is_refused(demos, tmp_path):
    import h5py

    from gym_coffee.datasets import export_robomimic, import_robomimic

    path = export_robomimic(demos, tmp_path / "d.hdf5")
    with h5py.File(path, "a") as f:
        text = bytes(f["data"].attrs["gym_coffee_metadata"]).decode()
        f["data"].attrs["gym_coffee_metadata"] = np.bytes_(text[:-1] + ', "note": NaN}')
    with pytest.raises(DemonstrationFormatError) as info:
        import_robomimic(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and "data.attrs['gym_coffee_metadata']" in msg
    assert "NaN" in msg


# -- robomimic HDF5: links are never followed, at any component of a path -------------------------


@pytest.fixture
def exported(demos, tmp_path) -> tuple[Path, Path]:
    """(a file to edit, another valid file with the same layout but other values)."""
    from gym_coffee.datasets import export_robomimic

    rng = np.random.default_rng(99)
    other = DemonstrationSet(
        [make_demo(rng, 6, seed=1), make_demo(rng, 6, seed=2)], metadata={"who": "synthetic"}
    )
    target = export_robomimic(other, tmp_path / "elsewhere" / "other.hdf5")
    return export_robomimic(demos, tmp_path / "d.hdf5"), target


def h5_error(path: Path) -> str:
    from gym_coffee.datasets import import_robomimic

    with pytest.raises(DemonstrationFormatError) as info:
        import_robomimic(path)
    msg = str(info.value)
    assert msg.startswith(str(path))
    return msg


@pytest.mark.parametrize(
    ("where", "kind", "target"),
    [
        ("data/demo_0/obs", "ExternalLink", "/data/demo_0/obs"),  # an intermediate group
        ("data/demo_0/gym_coffee/object_pos", "ExternalLink", "/data/demo_0/gym_coffee/object_pos"),
        ("data/demo_0/next_obs/flat", "ExternalLink", "/data/demo_0/next_obs/flat"),  # final
        ("data", "ExternalLink", "/data"),
        ("data/demo_1/gym_coffee", "SoftLink", "/data/demo_0/gym_coffee"),  # intermediate
        ("data/demo_1/actions", "SoftLink", "/data/demo_0/actions"),  # final
        ("data/demo_1/obs/flat", "SoftLink", "/data/demo_0/obs/flat"),
        ("data/demo_1", "SoftLink", "/data/demo_0"),
    ],
)
def test_robomimic_links_are_refused_at_every_component(exported, where, kind, target):
    """The link would resolve to data that import fine (the other file is a valid export, the
    soft link points at a demonstration of the same length): the import must still fail, so
    that no other file, and no other part of this one, is read through a link."""
    import h5py

    from gym_coffee.datasets import import_robomimic

    path, other = exported
    assert import_robomimic(other)  # a good file to link to
    with h5py.File(path, "a") as f:
        del f[where]
        if kind == "ExternalLink":
            f[where] = h5py.ExternalLink(str(other), target)
        else:
            f[where] = h5py.SoftLink(target)
    msg = h5_error(path)
    assert f"/{where} is {'an' if kind == 'ExternalLink' else 'a'} {kind}; links " in msg
    assert "are not followed" in msg


# -- robomimic HDF5: the observation keys attribute -----------------------------------------------


def set_text_attr(path: Path, name: str, text: str | bytes, node: str = "data") -> None:
    import h5py

    with h5py.File(path, "a", libver="latest") as f:  # "latest": allows attributes > 64 KiB
        f[node].attrs[name] = np.bytes_(text)


@pytest.mark.parametrize(
    "text",
    [
        "5",
        "NaN",
        '"flat"',
        "{}",
        "[]",
        "[5]",
        '[["flat", 0, 41], 5]',  # a valid key, then junk
        "[" * 20_000 + "]" * 20_000,  # a nesting bomb
        "[[" * 500 + "]]" * 500,  # deep, but within the recursion limit
        '[["flat", "0", 41]]',
        '[["flat", 0, 41.0]]',
        '[["flat", false, 41]]',
        '[["flat", 0, 1e400]]',
        "[[1, 0, 41]]",
        '[["a", 0, 20], ["a", 20, 41]]',  # the same key twice
        '[["a", 0, 41], ["a", 0, 41]]',
        '[["a", 0, 20], ["b", 21, 41]]',  # a gap
        '[["a", 0, 40]]',  # too short
    ],
)
def test_robomimic_obs_keys_of_the_wrong_type_are_named(exported, text):
    path, _ = exported
    set_text_attr(path, "gym_coffee_obs_keys", text)
    msg = h5_error(path)
    assert "data.attrs['gym_coffee_obs_keys']" in msg and "expected" in msg, msg
    assert "not a readable HDF5 file" not in msg


@pytest.mark.parametrize(
    "name",
    ["a/b", "/data/demo_0/actions", "../x", ".", "", "x" * 65, "two words", "flat\x00"],
)
def test_robomimic_obs_key_names_must_be_plain_short_names(exported, name):
    """A key becomes a path component (obs/<key>): no '/', nothing but a short identifier."""
    path, _ = exported
    set_text_attr(path, "gym_coffee_obs_keys", json.dumps([[name, 0, 41]]))
    msg = h5_error(path)
    assert "data.attrs['gym_coffee_obs_keys']" in msg and "plain name" in msg, msg


# -- robomimic HDF5: attribute and dataset sizes are checked before reading -----------------------


def with_dense_attributes(path: Path) -> Path:
    """Copy an exported file into one whose groups can hold attributes over 64 KiB."""
    import h5py

    out = path.with_name("dense.hdf5")
    with h5py.File(path, "r") as src, h5py.File(out, "w", libver="latest") as dst:
        data = dst.create_group("data")
        for key, value in src["data"].attrs.items():
            data.attrs[key] = value
        for name in src["data"]:
            src.copy(src["data"][name], data, name)
    return out


def test_robomimic_huge_metadata_attribute_is_refused_unread(exported):
    import h5py

    from gym_coffee.datasets import import_robomimic
    from gym_coffee.demonstrations import MAX_METADATA_CHARS

    path = with_dense_attributes(exported[0])
    assert import_robomimic(path)  # the copy itself is fine
    with h5py.File(path, "a") as f:
        text = bytes(f["data"].attrs["gym_coffee_metadata"]).decode()
        padded = text[:-1] + ', "pad": "' + "x" * MAX_METADATA_CHARS + '"}'
        f["data"].attrs["gym_coffee_metadata"] = np.bytes_(padded)
    msg = h5_error(path)
    assert "/data.attrs['gym_coffee_metadata'] has " in msg
    assert f"expected at most {MAX_METADATA_CHARS}" in msg


def test_robomimic_attributes_too_big_for_any_export_are_refused_before_any_is_decoded(exported):
    """HDF5 decodes a whole attribute even to find it by name: the total size of a group's
    attributes is checked first, from the object's header information."""
    path = with_dense_attributes(exported[0])
    set_text_attr(path, "padding", b"x" * (5 << 20))
    msg = h5_error(path)
    assert "/data.attrs take " in msg and "no attribute was read" in msg
    assert "'gym_coffee_metadata' holds at most 1048576 bytes" in msg


def test_robomimic_huge_obs_keys_attribute_is_refused_unread(exported):
    path = with_dense_attributes(exported[0])
    text = '[["flat", 0, 41]' + " " * 200_000 + "]"
    set_text_attr(path, "gym_coffee_obs_keys", text)
    msg = h5_error(path)
    assert f"/data.attrs['gym_coffee_obs_keys'] has {len(text)} bytes; expected at most" in msg


@pytest.mark.parametrize(
    ("name", "value", "expected"),
    [
        ("num_samples", np.arange(5000), "expected one integer"),
        ("num_samples", np.bytes_("5"), "expected one integer"),
        ("num_samples", 5.0, "expected one integer"),
        ("seed", np.zeros((80, 80), np.int64), "expected one integer"),
        ("success", np.ones(30_000, bool), "expected one boolean"),
        ("success", np.int64(7), "expected one boolean"),
    ],
)
def test_robomimic_demo_attributes_are_checked_before_reading(exported, name, value, expected):
    import h5py

    path = exported[0]
    with h5py.File(path, "a") as f:
        f["data/demo_1"].attrs[name] = value
    msg = h5_error(path)
    assert f"/data/demo_1.attrs[{name!r}]" in msg and expected in msg, msg


def test_robomimic_compressed_or_huge_chunked_datasets_are_refused(exported):
    """export_robomimic writes plain datasets; a filter could inflate without bound."""
    import h5py

    path = exported[0]
    with h5py.File(path, "a") as f:
        data = f["data/demo_0/actions"][()]
        del f["data/demo_0/actions"]
        f.create_dataset("data/demo_0/actions", data=data, compression="gzip")
    assert "/data/demo_0/actions is compressed or filtered" in h5_error(path)
    with h5py.File(path, "a") as f:
        del f["data/demo_0/actions"]
        f.create_dataset(
            "data/demo_0/actions", data=data, maxshape=(None, 8), chunks=(1_000_000, 8)
        )
    assert "/data/demo_0/actions has chunks of 32000000 bytes" in h5_error(path)


# -- .npz: the zip directory is bounded before zipfile parses it ----------------------------------

_EOCD = struct.Struct("<4s4H2LH")
_CENTRAL = struct.Struct("<4s4B4HL2L5H2L")
_LOCAL = struct.Struct("<4s2B4HL2L2H")


def split_zip(data: bytes) -> tuple[bytes, bytes, tuple]:
    """(local headers and data, central directory, EOCD fields) of a zip without a comment."""
    fields = _EOCD.unpack(data[-_EOCD.size :])
    cd_size, cd_offset = fields[5], fields[6]
    return data[:cd_offset], data[cd_offset : cd_offset + cd_size], fields


def central_entry(name: bytes, offset: int = 0) -> bytes:
    """A directory record of an empty stored member (a 46-byte header and the name)."""
    return (
        _CENTRAL.pack(
            b"PK\x01\x02", 20, 3, 20, 0, 0, 0, 0, 0, 0, 0, 0, len(name), 0, 0, 0, 0, 0, offset
        )
        + name
    )


def build_zip(
    body: bytes,
    directory: bytes,
    n_entries: int,
    *,
    zip64: bool = False,
    cd_size: int | None = None,
    cd_offset: int | None = None,
) -> bytes:
    """``body`` + ``directory`` + an end record declaring ``n_entries`` (and a ZIP64 end record
    and locator with ``zip64``); ``cd_size``/``cd_offset`` override the true values (a lie)."""
    size = len(directory) if cd_size is None else cd_size
    offset = len(body) if cd_offset is None else cd_offset
    out = body + directory
    if zip64:
        z64_at = len(out)
        out += struct.pack(
            "<4sQ2H2L4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, n_entries, n_entries, size, offset
        )
        out += struct.pack("<4sLQL", b"PK\x06\x07", 0, z64_at, 1)
        return out + _EOCD.pack(b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 2**32 - 1, 2**32 - 1, 0)
    return out + _EOCD.pack(b"PK\x05\x06", 0, 0, n_entries, n_entries, size, offset, 0)


def npz_bytes(demos: DemonstrationSet, compressed: bool = True) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **demos.to_arrays())
    return buf.getvalue()


def with_empty_entries(data: bytes, n_extra: int, *, declared: int | None = None) -> bytes:
    """The file plus ``n_extra`` empty members; the end record declares ``declared`` entries
    (default: the true count)."""
    body, directory, fields = split_zip(data)
    extra_body, extra_dir, offset = [body], [directory], len(body)
    for i in range(n_extra):
        name = b"e%d" % i
        local = _LOCAL.pack(b"PK\x03\x04", 20, 0, 0, 0, 0, 0, 0, 0, 0, len(name), 0) + name
        extra_body.append(local)
        extra_dir.append(central_entry(name, offset))
        offset += len(local)
    count = fields[4] + n_extra if declared is None else declared
    return build_zip(b"".join(extra_body), b"".join(extra_dir), count)


def test_valid_files_of_numpy_and_zip64_records_still_load(demos, tmp_path):
    from gym_coffee._io import NpzReader

    for compressed in (True, False):
        data = npz_bytes(demos, compressed)
        assert DemonstrationSet.load(io.BytesIO(data)) == demos
        body, directory, fields = split_zip(data)
        z64 = build_zip(body, directory, fields[4], zip64=True)
        with zipfile.ZipFile(io.BytesIO(z64)) as zf:  # zipfile reads the ZIP64 records too
            assert len(zf.infolist()) == fields[4]
        assert DemonstrationSet.load(io.BytesIO(z64)) == demos
    path = tmp_path / "c.npz"
    with zipfile.ZipFile(io.BytesIO(npz_bytes(demos))) as src, zipfile.ZipFile(path, "w") as dst:
        for info in src.infolist():
            dst.writestr(info, src.read(info))
        dst.comment = b"a zip comment"
    assert DemonstrationSet.load(path) == demos
    with NpzReader(path, max_bytes=1 << 20, max_entries=fields[4]) as npz:
        assert "actions" in npz.members


def test_too_many_entries_are_refused_before_the_directory_is_parsed(demos, tmp_path):
    from gym_coffee._io import DEFAULT_MAX_ENTRIES, FileFormatError, NpzReader

    data = npz_bytes(demos)
    n = split_zip(data)[2][4]
    path = tmp_path / "many.npz"
    path.write_bytes(with_empty_entries(data, 30))
    with pytest.raises(FileFormatError, match=f"lists {n + 30} entries.*at most {n + 29}"):
        with NpzReader(path, max_bytes=1 << 20, max_entries=n + 29):
            pass
    with NpzReader(path, max_bytes=1 << 20, max_entries=n + 30) as npz:
        assert "actions" in npz.members
    path.write_bytes(with_empty_entries(data, DEFAULT_MAX_ENTRIES + 1 - n))  # ~0.8 MB
    msg = load_error(path)
    assert msg.startswith(str(path))
    assert f"lists {DEFAULT_MAX_ENTRIES + 1} entries; expected at most {DEFAULT_MAX_ENTRIES}" in msg


@pytest.mark.parametrize("zip64", [False, True])
def test_an_end_record_that_lies_about_the_entries_is_refused(demos, tmp_path, zip64):
    import tracemalloc

    data = npz_bytes(demos)
    n = split_zip(data)[2][4]
    # 50,000 empty entries (2.5 MB) behind an end record that declares the original count:
    # zipfile would parse them all (it reads the directory by its size, not its count).
    body, directory, _ = split_zip(data)
    extra = b"".join(central_entry(b"") for _ in range(50_000))
    path = tmp_path / "lie.npz"
    path.write_bytes(build_zip(body, directory + extra, n, zip64=zip64))
    tracemalloc.start()
    try:
        msg = load_error(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert "zip directory" in msg and f"{n} entries" in msg, msg
    assert peak < 1_000_000
    # A few uncounted entries fit the size bound: the directory is counted exactly.
    path.write_bytes(build_zip(body, directory + extra[: 46 * 5], n, zip64=zip64))
    msg = load_error(path)
    assert f"holds {n + 1} or more entries but its end record declares {n}" in msg, msg


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"cd_offset": 7}, "does not end where the end record starts"),
        ({"cd_size": 100}, "does not end where the end record starts"),
        ({"n_entries": 0}, "holds"),
    ],
)
def test_an_end_record_that_disagrees_with_the_file_is_refused(demos, tmp_path, change, expected):
    data = npz_bytes(demos)
    body, directory, fields = split_zip(data)
    args = {"n_entries": fields[4], **change}
    path = tmp_path / "bad.npz"
    path.write_bytes(build_zip(body, directory, **args))
    msg = load_error(path)
    assert msg.startswith(str(path)) and expected in msg, msg
    path.write_bytes(data[:-3])  # a cut end record
    assert "end-of-directory record" in load_error(path)


# -- .npz: members that zipfile or numpy cannot read are bad files, named -------------------------


def patch_directory(data: bytes, member: str, *, flags: int | None = None, method=None) -> bytes:
    """Change the general-purpose flags or the compression method of ``member`` in the zip
    directory (where zipfile reads them)."""
    body, directory, fields = split_zip(data)
    out, at = bytearray(directory), 0
    while at < len(directory):
        entry = list(_CENTRAL.unpack_from(directory, at))
        size = _CENTRAL.size + entry[12] + entry[13] + entry[14]
        name = directory[at + _CENTRAL.size : at + _CENTRAL.size + entry[12]].decode()
        if name == member:
            entry[5] = entry[5] if flags is None else flags
            entry[6] = entry[6] if method is None else method
            out[at : at + _CENTRAL.size] = _CENTRAL.pack(*entry)
        at += size
    return build_zip(body, bytes(out), fields[4])


@pytest.mark.parametrize(
    ("member", "change", "expected"),
    [
        ("metadata.npy", {"flags": 1}, "encrypted"),
        ("lengths.npy", {"flags": 1}, "encrypted"),
        ("actions.npy", {"method": 6}, "compression method"),  # implode
        ("metadata.npy", {"method": 14}, "cannot be read"),  # LZMA over deflate data
        ("time.npy", {"method": 12}, "cannot be read"),  # bzip2 over deflate data
    ],
)
def test_members_zipfile_cannot_read_name_the_file_and_member(
    demos, tmp_path, member, change, expected
):
    path = tmp_path / "bad.npz"
    path.write_bytes(patch_directory(npz_bytes(demos), member, **change))
    msg = load_error(path)
    name = member.removesuffix(".npy")
    assert msg.startswith(str(path)) and f"array {name!r}" in msg, msg
    assert expected in msg, msg
    out = tmp_path / "x.hdf5"  # the command line: a bad input file (2), not a failure (1)
    assert cli(["export", str(path), "--format", "robomimic", "--out", str(out)]) == 2


def raw_npy(shape: tuple[int, ...], descr: str) -> bytes:
    """A .npy header alone (no data)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": descr, "fortran_order": False, "shape": shape}
    )
    return buf.getvalue()


@pytest.mark.parametrize(
    ("member", "shape", "descr"),
    [
        ("lengths", (10**12,), "<U0"),
        ("lengths", (3,), "<U0"),
        ("metadata", (), "<U0"),
        ("seeds", (10**12,), "|S0"),
        ("actions", (10**12, 8), "<U0"),
    ],
)
def test_zero_size_dtypes_are_refused_naming_the_member(demos, tmp_path, member, shape, descr):
    path = tmp_path / "u0.npz"
    arrays = demos.to_arrays()
    with zipfile.ZipFile(path, "w") as zf:
        for name, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, value)
            zf.writestr(f"{name}.npy", raw_npy(shape, descr) if name == member else buf.getvalue())
    msg = load_error(path)
    assert msg.startswith(str(path)) and f"{member!r}" in msg and "expected" in msg, msg
    assert "itemsize cannot be zero" not in msg


# -- outputs: a symlink (dangling or not) is an existing file; it is replaced, never written through


def writers(demos: DemonstrationSet):
    """(name, suffix, write(path, overwrite)) of each gym_coffee writer."""
    from gym_coffee.datasets import export_robomimic
    from gym_coffee.video import write_video

    frames = [np.zeros((4, 4, 3), np.uint8)] * 2
    return [
        ("save", ".npz", lambda p, o: demos.save(p, overwrite=o)),
        ("robomimic", ".hdf5", lambda p, o: export_robomimic(demos, p, overwrite=o)),
        ("video", ".gif", lambda p, o: write_video(p, frames, overwrite=o)),
    ]


@pytest.mark.parametrize("which", ["save", "robomimic", "video"])
@pytest.mark.parametrize("dangling", [True, False])
def test_symlinked_outputs_are_refused_or_replaced_never_written_through(
    demos, tmp_path, which, dangling
):
    import os

    _, suffix, write = next(w for w in writers(demos) if w[0] == which)
    target = tmp_path / "elsewhere" / f"target{suffix}"
    target.parent.mkdir()
    if not dangling:
        target.write_bytes(b"precious")
    link = tmp_path / f"out{suffix}"
    link.symlink_to(target)
    with pytest.raises(FileExistsError) as info:
        write(link, False)
    assert str(info.value) == f"{link} exists; pass --force (overwrite=True) to overwrite it"
    assert os.readlink(link) == str(target)  # untouched
    write(link, True)  # the link itself is replaced, atomically
    assert link.is_file() and not link.is_symlink()
    if dangling:
        assert not target.exists()
    else:
        assert target.read_bytes() == b"precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["elsewhere", link.name]


def test_atomic_output_sees_dangling_links(tmp_path):
    from gym_coffee._io import atomic_output, refuse_existing

    link = tmp_path / "x.bin"
    link.symlink_to(tmp_path / "missing" / "x.bin")
    with pytest.raises(FileExistsError, match="pass --force"):
        refuse_existing(link, False)
    with pytest.raises(FileExistsError, match="pass --force"):
        with atomic_output(link) as tmp:
            tmp.write_bytes(b"new")
    assert link.is_symlink()
    with atomic_output(link, overwrite=True) as tmp:
        tmp.write_bytes(b"new")
    assert link.read_bytes() == b"new" and not link.is_symlink()
    assert not (tmp_path / "missing").exists()


def test_minari_export_over_a_dangling_link(demos, tmp_path):
    from gym_coffee.datasets import export_minari

    final = tmp_path / "coffee" / "d-v0"
    final.parent.mkdir()
    final.symlink_to(tmp_path / "nowhere")
    with pytest.raises(FileExistsError, match=r"pass --force \(overwrite=True\)"):
        export_minari(demos, "coffee/d-v0", root=tmp_path)
    assert final.is_symlink()
    export_minari(demos, "coffee/d-v0", root=tmp_path, overwrite=True)
    assert final.is_dir() and not final.is_symlink()
    assert not (tmp_path / "nowhere").exists()
