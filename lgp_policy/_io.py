"""The one file helper of :mod:`lgp_policy`: atomic writes and bounded ``.npz`` reads.

Writing (:func:`atomic_write_bytes`, :func:`atomic_write_text`, :func:`atomic_save_npz`,
:func:`atomic_output`): the data goes to a temporary file in the target's folder, is flushed
and ``fsync``-ed, gets the permissions of any other new file (``0o666`` minus the umask, i.e.
usually ``0644``), and only then takes the target's name (``os.replace``). A crash, a full disk
or a Ctrl-C leaves the old file intact and no temporary file behind. An existing target is
refused with :class:`FileExistsError` unless ``force=True``; without ``force`` the final step is
a hard link, so a file created meanwhile by someone else is not overwritten either.

Reading (:func:`read_npz`, :func:`read_json_member`): files we load are never unpickled and never
read unbounded data. Only the members a caller asks for are decompressed; each member's declared
uncompressed size (zip central directory) and its ``.npy`` header (``shape * itemsize``) are
checked against the limits before a byte is decompressed; object dtypes are refused; the number
of archive entries is checked before the archive's directory is parsed. Every problem raises one
error class, :class:`FileFormatError` (a :class:`ValueError`), whose message names the file, the
member and what was expected.

Example:
    >>> atomic_save_npz("policy.npz", {"w": np.zeros(3)}, force=False)  # doctest: +SKIP
    >>> read_npz("policy.npz", schema={"w": MemberSpec(dtype="f", ndim=1)})  # doctest: +SKIP
    {'w': array([0., 0., 0.])}
"""

from __future__ import annotations

import contextlib
import fnmatch
import io
import json
import math
import os
import struct
import tempfile
import zipfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "DEFAULT_MAX_ENTRIES",
    "DEFAULT_MAX_MEMBER_BYTES",
    "DEFAULT_MAX_TOTAL_BYTES",
    "FileFormatError",
    "MemberSpec",
    "atomic_output",
    "atomic_save_npz",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_creatable",
    "check_output_path",
    "read_json_member",
    "read_npz",
]

DEFAULT_MAX_MEMBER_BYTES = 256 * 2**20
"""Largest uncompressed member :func:`read_npz` accepts by default (256 MiB)."""
DEFAULT_MAX_TOTAL_BYTES = 1024 * 2**20
"""Largest sum of the uncompressed members read by default (1 GiB)."""
DEFAULT_MAX_ENTRIES = 10_000
"""Most entries an archive may list (its directory is parsed into memory, ~0.5 KiB each)."""
MAX_JSON_BYTES = 16 * 2**20
"""Largest JSON text :func:`read_json_member` accepts by default (16 MiB)."""

_ZIP_MAGIC = b"PK\x03\x04"
_EMPTY_ZIP_MAGIC = b"PK\x05\x06"
_EOCD = struct.Struct("<4s4H2LH")  # end of central directory record (22 bytes)
_ZIP64_LOCATOR = struct.Struct("<4sLQL")  # its ZIP64 locator, just before it (20 bytes)
_ZIP64_EOCD = struct.Struct("<4sQ2H2L4Q")  # the ZIP64 end of central directory record (56 bytes)
DIRECTORY_BYTES_PER_ENTRY = 46 + 256
"""Room per allowed entry in an archive's central directory: the fixed 46 bytes plus 256 for
name, extra field and comment (``numpy.savez`` writes about 60 bytes per entry). The directory's
declared size is what :mod:`zipfile` parses, so this bounds its work whatever the entry count
claims."""


class FileFormatError(ValueError):
    """A file is not what it should be: not an ``.npz``, a missing, oversized or malformed
    member, an object (pickle) array, invalid JSON. The message names the file, the member and
    what was expected; :attr:`path` and :attr:`member` hold them."""

    def __init__(self, message: str, *, path: str | None = None, member: str | None = None):
        super().__init__(message)
        self.path = path
        self.member = member


# ----------------------------------------------------------------------------------- writing
def _file_mode() -> int:
    """``0o666`` minus the process umask: the mode ``open(path, "w")`` would give."""
    umask = os.umask(0o022)
    os.umask(umask)
    return 0o666 & ~umask


def _refuse_existing(path: Path) -> FileExistsError:
    return FileExistsError(
        f"{path} exists; pass --force (force=True) to overwrite it",
    )


def check_output_path(
    path: str | os.PathLike[str],
    *,
    force: bool,
    suffixes: tuple[str, ...] | None = None,
    what: str = "output file",
) -> Path:
    """Check, before any work, that ``path`` can be written; return it as a :class:`Path`.

    Raises:
        ValueError: the suffix is not one of ``suffixes`` (case-insensitive), ``path`` is an
            existing folder, or its nearest existing parent is not a writable folder.
        FileExistsError: ``path`` exists and ``force`` is false.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{what} {path} is a folder; expected a file name")
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise ValueError(
            f"{what} {path}: expected a name ending in {' or '.join(suffixes)}, "
            f"got {path.suffix or 'no suffix'!r}"
        )
    if os.path.lexists(path) and not force:  # a dangling link too: the writer would refuse it
        raise _refuse_existing(path)
    check_creatable(path.absolute().parent, f"{what} {path}")
    return path


def check_creatable(folder: str | os.PathLike[str], what: str) -> None:
    """Check that ``folder`` is, or can be made, a writable folder: its nearest existing
    ancestor must be a writable folder.

    Raises:
        ValueError: ``"{what}: ..."`` naming the ancestor that is a file or not writable.
    """
    parent = Path(folder).absolute()
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"{what}: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{what}: folder {parent} is not writable")


@contextlib.contextmanager
def atomic_output(
    path: str | os.PathLike[str], *, force: bool, suffix: str | None = None
) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it becomes ``path`` atomically.

    For writers that want a file name (video encoders, h5py): write the whole file to the
    yielded path and return; on any exception (Ctrl-C included) the temporary file is removed
    and ``path`` is left as it was. The parent folder is created if missing.

    Arguments:
        force: replace an existing ``path``; otherwise :class:`FileExistsError` is raised, both
            before and (if the file appeared meanwhile) after writing.
        suffix: the temporary file's suffix (default ``path``'s, for writers that pick the
            format from the name).

    Raises:
        FileExistsError: ``path`` exists and ``force`` is false.
    """
    path = Path(path)
    if os.path.lexists(path) and not force:
        raise _refuse_existing(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=path.suffix if suffix is None else suffix, dir=path.parent
    )
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, _file_mode())
        if force:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)  # fails if path appeared meanwhile: never overwrite
            except FileExistsError:
                raise _refuse_existing(path) from None
            except OSError:  # no hard links on this file system
                if os.path.lexists(path):
                    raise _refuse_existing(path) from None
                os.replace(tmp, path)
        _fsync_folder(path.parent)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def _fsync_folder(folder: Path) -> None:
    """Make the rename durable (best effort: not every platform can open a folder)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, *, force: bool) -> Path:
    """Write ``data`` to ``path`` atomically (see the module docstring); return the path.

    Raises:
        FileExistsError: ``path`` exists and ``force`` is false.
        OSError: the write failed (e.g. a full disk); the old file, if any, is intact.
    """
    path = Path(path)
    with atomic_output(path, force=force) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
    return path


def atomic_write_text(
    path: str | os.PathLike[str], text: str, *, force: bool, encoding: str = "utf-8"
) -> Path:
    """Write ``text`` to ``path`` atomically; see :func:`atomic_write_bytes`."""
    return atomic_write_bytes(path, text.encode(encoding), force=force)


def atomic_save_npz(
    path: str | os.PathLike[str],
    arrays: Mapping[str, NDArray[Any]],
    *,
    force: bool,
    compressed: bool = True,
) -> Path:
    """Save ``arrays`` as one ``.npz`` at exactly ``path`` (no suffix is added), atomically.

    Object arrays are refused (they would need a pickle to be read back).

    Raises:
        ValueError: an array has an object dtype.
        FileExistsError: ``path`` exists and ``force`` is false.
    """
    path = Path(path)
    for name, value in arrays.items():
        if np.asarray(value).dtype.hasobject:
            raise ValueError(f"array {name!r} has an object dtype; it cannot be saved unpickled")
    save = np.savez_compressed if compressed else np.savez
    with atomic_output(path, force=force) as tmp, open(tmp, "wb") as fh:
        save(fh, **dict(arrays))  # type: ignore[arg-type]
    return path


# ----------------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class MemberSpec:
    """What one ``.npz`` member must be; checked by :func:`read_npz` (header before data).

    Attributes:
        dtype: accepted dtype kinds (``numpy.dtype.kind`` letters), e.g. ``"f"``, ``"iu"``,
            ``"U"``; ``None`` accepts any non-object dtype.
        ndim: required number of dimensions, or ``None``.
        shape: required shape; ``None`` entries are free (e.g. ``(None, 3)``).
        required: a missing member is an error (for a pattern: no member matches it).
        finite: float data must be finite (no NaN/inf).
        max_bytes: a tighter bound than ``max_member_bytes`` for this member.
    """

    dtype: str | None = None
    ndim: int | None = None
    shape: tuple[int | None, ...] | None = None
    required: bool = True
    finite: bool = False
    max_bytes: int | None = None


def _label(source: str | os.PathLike[str] | IO[bytes]) -> str:
    if isinstance(source, (str, os.PathLike)):
        return str(source)
    return str(getattr(source, "name", None) or "<in-memory file>")


def _directory(fh: IO[bytes], size: int, label: str) -> tuple[int, int]:
    """``(entries, bytes)`` of the archive's central directory as its end-of-central-directory
    record (or the ZIP64 one it points to) declares them, read before :mod:`zipfile` parses the
    directory: :mod:`zipfile` reads and parses exactly that many bytes, whatever the entry
    count says."""
    tail = min(size, _EOCD.size + 0xFFFF)
    fh.seek(size - tail)
    data = fh.read(tail)
    pos = data.rfind(_EMPTY_ZIP_MAGIC)
    if pos < 0 or len(data) - pos < _EOCD.size:
        raise FileFormatError(
            f"{label}: not an .npz file (no zip directory at its end; truncated?)", path=label
        )
    fields = _EOCD.unpack_from(data, pos)
    entries, directory = int(fields[4]), int(fields[5])
    if entries == 0xFFFF or directory == 0xFFFFFFFF or fields[6] == 0xFFFFFFFF:  # ZIP64
        loc = pos - _ZIP64_LOCATOR.size
        if loc < 0 or data[loc : loc + 4] != b"PK\x06\x07":
            raise FileFormatError(
                f"{label}: not an .npz file (a ZIP64 directory without its locator)", path=label
            )
        offset = int(_ZIP64_LOCATOR.unpack_from(data, loc)[2])
        if not 0 <= offset <= size - _ZIP64_EOCD.size:
            raise FileFormatError(f"{label}: not an .npz file (bad ZIP64 record)", path=label)
        fh.seek(offset)
        record = fh.read(_ZIP64_EOCD.size)
        if record[:4] != b"PK\x06\x06":
            raise FileFormatError(f"{label}: not an .npz file (bad ZIP64 record)", path=label)
        fields64 = _ZIP64_EOCD.unpack(record)
        entries, directory = int(fields64[7]), int(fields64[8])
    return entries, directory


def _open_archive(
    source: str | os.PathLike[str] | IO[bytes], label: str, *, max_bytes: int, max_entries: int
) -> tuple[zipfile.ZipFile, IO[bytes]]:
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if not path.exists():
            raise FileNotFoundError(f"no such file: {path}")
        if path.is_dir():
            raise FileFormatError(f"{label} is a folder; expected an .npz file", path=label)
        fh: IO[bytes] = open(path, "rb")  # closed by the caller
    else:
        fh = source
    try:
        fh.seek(0, io.SEEK_END)
        size = fh.tell()
        fh.seek(0)
        head = fh.read(6)
        if head[:4] not in (_ZIP_MAGIC, _EMPTY_ZIP_MAGIC):
            found = "a single .npy array" if head == b"\x93NUMPY" else "not a zip archive"
            raise FileFormatError(
                f"{label} is not an .npz file (expected a zip archive of .npy arrays; {found})",
                path=label,
            )
        if size > max_bytes:
            raise FileFormatError(
                f"{label} is {size} bytes; expected at most {max_bytes} (raise max_total_bytes "
                "if the file is genuine)",
                path=label,
            )
        n_entries, directory = _directory(fh, size, label)
        if n_entries > max_entries:
            raise FileFormatError(
                f"{label} lists {n_entries} entries; expected at most {max_entries}", path=label
            )
        if directory > min(size, max_entries * DIRECTORY_BYTES_PER_ENTRY):
            raise FileFormatError(
                f"{label} has a {directory}-byte zip directory; expected at most "
                f"{max_entries * DIRECTORY_BYTES_PER_ENTRY} (room for {max_entries} entries) "
                "within the file",
                path=label,
            )
        fh.seek(0)
        return zipfile.ZipFile(fh), fh
    except FileFormatError:
        if fh is not source:
            fh.close()
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError) as exc:
        if fh is not source:
            fh.close()
        raise FileFormatError(
            f"{label} is not a readable .npz file (corrupt or truncated zip): {exc}", path=label
        ) from None


def _select(
    names: list[str], schema: Mapping[str, MemberSpec] | None, label: str
) -> dict[str, MemberSpec]:
    """The members to read (archive name without ``.npy`` -> its spec)."""
    arrays = [n[: -len(".npy")] for n in names if n.endswith(".npy")]
    if schema is None:
        return {name: MemberSpec() for name in arrays}
    chosen: dict[str, MemberSpec] = {}
    for key, spec in schema.items():
        pattern = any(c in key for c in "*?[")
        if pattern:
            matches = [n for n in arrays if fnmatch.fnmatchcase(n, key)]
        else:
            matches = [key] if key in arrays else []
        if not matches and spec.required:
            raise FileFormatError(
                f"{label}: missing {'a member matching' if pattern else 'member'} {key!r} "
                f"(expected by this file type; the file has {sorted(arrays)[:20]})",
                path=label,
                member=key,
            )
        for name in matches:
            chosen.setdefault(name, spec)
    return chosen


def _read_member(
    zf: zipfile.ZipFile,
    name: str,
    spec: MemberSpec,
    label: str,
    limit: int,
) -> NDArray[Any]:
    info = zf.getinfo(name + ".npy")
    where = f"{label}: member {name!r}"

    def fail(expected: str) -> FileFormatError:
        return FileFormatError(f"{where}: {expected}", path=label, member=name)

    if info.file_size > limit:
        raise fail(f"declares {info.file_size} bytes uncompressed; expected at most {limit}")
    with zf.open(info) as fh:
        try:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
            else:
                raise fail(f".npy format version {version} is not supported (1.0 or 2.0)")
        except FileFormatError:
            raise
        except (ValueError, SyntaxError, TypeError, EOFError, OSError) as exc:
            raise fail(f"expected a .npy array header ({exc})") from None
        if dtype.hasobject:
            raise fail(
                f"holds Python objects (dtype {dtype}); expected plain numbers or text (files "
                "are never unpickled)"
            )
        if spec.dtype is not None and dtype.kind not in spec.dtype:
            raise fail(f"has dtype {dtype}; expected dtype kind {' or '.join(spec.dtype)}")
        if spec.ndim is not None and len(shape) != spec.ndim:
            raise fail(f"has shape {shape}; expected {spec.ndim} dimension(s)")
        if spec.shape is not None and (
            len(shape) != len(spec.shape)
            or any(e is not None and e != s for e, s in zip(spec.shape, shape, strict=True))
        ):
            raise fail(f"has shape {shape}; expected {spec.shape} (None: any length)")
        count = math.prod(shape)
        nbytes = count * dtype.itemsize
        data_bytes = info.file_size - fh.tell()
        if nbytes != data_bytes:
            raise fail(
                f"header says {shape} x {dtype} ({nbytes} bytes) but the member holds "
                f"{data_bytes} bytes of data"
            )
        if max(nbytes, count) > limit:  # count: a zero-size dtype has no bytes per element
            raise fail(f"is {nbytes} bytes ({count} elements); expected at most {limit}")
        flat = np.empty(count, dtype=dtype)
        buffer = flat.view(np.uint8) if nbytes else np.empty(0, np.uint8)
        got = 0
        while got < nbytes:
            chunk = fh.read(min(nbytes - got, 1 << 20))
            if not chunk:
                raise fail(f"is truncated ({got} of {nbytes} bytes of data)")
            buffer[got : got + len(chunk)] = np.frombuffer(chunk, dtype=np.uint8)
            got += len(chunk)
        if fh.read(1):  # also makes zipfile check the CRC at the end of the member
            raise fail("holds more data than its header declares")
    array = flat.reshape(shape, order="F" if fortran else "C")
    if spec.finite and dtype.kind in "fc" and not np.all(np.isfinite(array)):
        raise fail("contains NaN or inf; expected finite numbers")
    return array


def read_npz(
    source: str | os.PathLike[str] | IO[bytes],
    *,
    schema: Mapping[str, MemberSpec] | None = None,
    members: Mapping[str, MemberSpec] | None = None,
    max_member_bytes: int = DEFAULT_MAX_MEMBER_BYTES,
    max_total_bytes: int = DEFAULT_MAX_TOTAL_BYTES,
    max_entries: int = DEFAULT_MAX_ENTRIES,
) -> dict[str, NDArray[Any]]:
    """Read the arrays of an ``.npz`` file with bounded memory, never unpickling.

    Arguments:
        source: a path or a binary file object (e.g. :class:`io.BytesIO` of an embedded file).
        schema: member name (without ``.npy``; ``fnmatch`` patterns such as ``"param/*"`` are
            allowed) -> :class:`MemberSpec`. Only these members are read; others are never
            decompressed. ``None`` reads every array member (still bounded). ``members`` is
            the same argument under another name (give one of them).
        max_member_bytes: largest uncompressed member (checked in the zip directory and in the
            ``.npy`` header before decompressing).
        max_total_bytes: largest sum of the members read; also bounds the file's own size.
        max_entries: most entries the archive may list.

    Returns:
        ``{name: array}`` for every member read.

    Raises:
        FileNotFoundError: ``source`` is a path that does not exist.
        FileFormatError: not an ``.npz``; a required member is missing; a member is too big,
            has an object dtype, a wrong dtype/shape, is corrupt or truncated.
    """
    if schema is not None and members is not None:
        raise TypeError("give schema or members, not both")
    schema = schema if schema is not None else members
    label = _label(source)
    zf, fh = _open_archive(
        source,
        label,
        max_bytes=max_total_bytes + max_total_bytes // 64 + 2**20,  # + zip overhead
        max_entries=max_entries,
    )
    out: dict[str, NDArray[Any]] = {}
    total = 0
    try:
        with zf:
            chosen = _select(zf.namelist(), schema, label)
            for name, spec in chosen.items():
                limit = min(
                    max_member_bytes,
                    max_total_bytes - total,
                    spec.max_bytes if spec.max_bytes is not None else max_member_bytes,
                )
                try:
                    array = _read_member(zf, name, spec, label, limit)
                except FileFormatError:
                    raise
                except Exception as exc:  # zlib/lzma/bz2 errors, bad CRC, encrypted, ...
                    raise FileFormatError(
                        f"{label}: member {name!r} cannot be read (corrupt or truncated file; "
                        f"expected a .npy array): {type(exc).__name__}: {exc}",
                        path=label,
                        member=name,
                    ) from None
                total += array.nbytes
                out[name] = array
    finally:
        if fh is not source:
            fh.close()
    return out


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text} overflows a float")
    return value


def parse_json(text: str, *, where: str, member: str | None = None) -> Any:
    """Parse JSON text strictly (no NaN/Infinity, no overflowing numbers, bounded nesting).

    Raises:
        FileFormatError: naming ``where`` (and ``member``) and the problem.
    """
    try:
        return json.loads(text, parse_constant=_no_constant, parse_float=_finite_float)
    except (ValueError, RecursionError) as exc:
        raise FileFormatError(
            f"{where}: expected valid JSON ({type(exc).__name__}: {str(exc)[:200]})",
            path=where,
            member=member,
        ) from None


def read_json_member(
    source: str | os.PathLike[str] | IO[bytes],
    member: str = "metadata",
    *,
    max_bytes: int = MAX_JSON_BYTES,
    required_keys: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Read a JSON object stored as a 0-d text array (``np.array(json.dumps(obj))``).

    Raises:
        FileNotFoundError: ``source`` is a path that does not exist.
        FileFormatError: not an ``.npz``; ``member`` is missing, not a 0-d text array, larger
            than ``max_bytes``, not valid JSON, not a JSON object, or lacks a ``required_keys``
            entry.
    """
    label = _label(source)
    arrays = read_npz(
        source,
        schema={member: MemberSpec(dtype="U", ndim=0, max_bytes=4 * max_bytes)},
        max_member_bytes=4 * max_bytes,  # UTF-32 in the .npy
        max_total_bytes=4 * max_bytes,
    )
    value = parse_json(str(arrays[member]), where=f"{label}: member {member!r}", member=member)
    if not isinstance(value, dict):
        raise FileFormatError(
            f"{label}: member {member!r}: expected a JSON object, got {type(value).__name__}",
            path=label,
            member=member,
        )
    for key in required_keys:
        if key not in value:
            raise FileFormatError(
                f"{label}: member {member!r}: expected a key {key!r} (it has {sorted(value)})",
                path=label,
                member=member,
            )
    return value
