"""Safe file writing and bounded ``.npz`` reading for gym_coffee's own files.

Two things every file of the task package needs (demonstrations, videos, dataset exports):

* :func:`atomic_output` -- write to a temporary file in the target's folder and move it onto the
  target only when the write is complete, never replacing an existing file unless asked to.
* :class:`NpzReader` -- read selected members of an ``.npz`` archive without pickle and without
  trusting any size in it: the archive's size, each member's declared (uncompressed) size in the
  zip directory and the ``.npy`` header's shape and dtype are all checked against limits *before*
  anything is decompressed, and only the members asked for are ever read. The zip directory
  itself (its number of entries and its size in bytes) is checked against the file before
  :mod:`zipfile` parses it.
* :func:`parse_json` -- strict JSON: no ``NaN``/``Infinity``, no numbers that overflow a float,
  nesting bombs refused.

(``lgp_policy`` has its own file helper; ``gym_coffee`` must not import ``lgp_policy``.)
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import struct
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.lib import format as npy_format
from numpy.typing import NDArray

__all__ = [
    "DEFAULT_MAX_ENTRIES",
    "FileFormatError",
    "NpzReader",
    "atomic_output",
    "parse_json",
    "refuse_existing",
]

#: Largest ``.npy`` header read (bytes); numpy's own default limit.
MAX_NPY_HEADER = 10_000
#: Most entries an archive may list by default (zipfile keeps ~0.5 KiB per entry in memory).
DEFAULT_MAX_ENTRIES = 10_000
#: Most bytes one entry may take in the zip directory (a 46-byte header, then the name, the
#: extra field and the comment; numpy's entries take under 100).
MAX_DIRECTORY_ENTRY_BYTES = 1024
_EOCD = struct.Struct("<4s4H2LH")  # end of central directory record (22 bytes)
_ZIP64_LOCATOR = struct.Struct("<4sLQL")  # ZIP64 end of central directory locator (20 bytes)
_ZIP64_EOCD = struct.Struct("<4sQ2H2L4Q")  # ZIP64 end of central directory record (56 bytes)
_CENTRAL = struct.Struct("<4s4B4HL2L5H2L")  # central directory entry header (46 bytes)
#: dtype kinds a member may have: bool, signed/unsigned integers, floats, unicode text.
_ALLOWED_KINDS = frozenset("biufU")


class FileFormatError(ValueError):
    """A file cannot be read as what it claims to be; the message says what is wrong."""


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text[:40]} overflows a float")
    return value


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > 308:  # larger than any float (and slow to convert)
        raise ValueError(f"an integer of {len(text)} digits overflows a float")
    return int(text)


def parse_json(text: str, *, where: str) -> Any:
    """Parse JSON text strictly: no ``NaN``/``Infinity``, no numbers that overflow a float, no
    nesting deeper than Python's recursion limit.

    Raises:
        FileFormatError: ``"<where>: expected strict JSON ..."`` naming the problem.
    """
    try:
        return json.loads(
            text, parse_constant=_no_constant, parse_float=_finite_float, parse_int=_bounded_int
        )
    except (ValueError, RecursionError) as exc:
        raise FileFormatError(
            f"{where}: expected strict JSON (no NaN/Infinity, no numbers that overflow a float, "
            f"bounded nesting): {type(exc).__name__}: {str(exc)[:200]}"
        ) from None


def _exists(path: Path) -> FileExistsError:
    return FileExistsError(f"{path} exists; pass --force (overwrite=True) to overwrite it")


def refuse_existing(path: Path, overwrite: bool) -> None:
    """Raise ``FileExistsError`` if anything is at ``path`` and ``overwrite`` is false.

    A symlink counts, even a dangling one (``os.path.lexists``; ``Path.exists`` follows the
    link and says no): writing would replace the link.
    """
    if not overwrite and os.path.lexists(path):
        raise _exists(path)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_output(
    path: str | os.PathLike[str], *, overwrite: bool = False, suffix: str = ".tmp"
) -> Iterator[Path]:
    """Context manager yielding a temporary path next to ``path``; on success it becomes ``path``.

    Write the complete file to the yielded path inside the ``with`` block. When the block ends
    without an exception the file is flushed to disk, given the usual permissions (``0666 &
    ~umask``) and moved onto ``path``: with ``overwrite`` by ``os.replace``, otherwise by a hard
    link, which fails if ``path`` appeared in the meantime (no silent clobbering in a race).
    On an exception, or a full disk, the temporary file is removed and an existing ``path`` is
    untouched. A symlink at ``path`` (dangling or not) is an existing file: it is refused
    without ``overwrite`` and replaced itself with it, never written through to its target.

    Args:
        path: the file to produce. A missing folder is created (as ``mkdir -p``).
        overwrite: replace an existing ``path``; otherwise an existing one is refused up front.
        suffix: suffix of the temporary file (some writers choose the format from it).

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is false.
        OSError: the folder cannot be created (e.g. a part of it is a file).
    """
    path = Path(path)
    refuse_existing(path, overwrite)
    folder = path.parent if str(path.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=folder)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600
        if overwrite:
            os.replace(tmp, path)  # replaces a symlink at path, not its target
        else:
            try:
                os.link(tmp, path)  # never follows a symlink at path: fails if one is there
            except FileExistsError:
                raise _exists(path) from None
            except OSError:  # a file system without hard links
                refuse_existing(path, overwrite)
                os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


class NpzReader:
    """Bounded, pickle-free reader of selected members of an ``.npz`` archive.

    Use as a context manager. ``members`` lists the array names in the archive (``name.npy``
    entries); :meth:`header` returns a member's shape and dtype from its ``.npy`` header only, and
    :meth:`read` reads one member after checking its declared sizes. Nothing is decompressed
    except the ``.npy`` headers of members asked about and the data of members read.

    Args:
        source: a path or a binary file object (e.g. ``io.BytesIO``).
        max_bytes: the most bytes the archive may have on disk and any single member may
            declare uncompressed; :meth:`read` also refuses once the members read so far would
            exceed it in total.
        what: how to call the file in messages (default: the path).
        max_entries: the most entries the zip directory may hold. The directory's end record
            (and ZIP64 end record) is read first: its entry count and the directory's size
            (at most ``MAX_DIRECTORY_ENTRY_BYTES`` per entry) are checked, as is that the
            directory ends where the end record starts, and its entries are counted, all
            before :mod:`zipfile` parses a byte of it.

    Raises:
        FileNotFoundError: ``source`` is a path and there is no such file.
        FileFormatError: the file is larger than ``max_bytes``, is not a zip archive, or its
            zip directory is too large or disagrees with its end record or the file.
    """

    def __init__(
        self,
        source: str | os.PathLike[str] | BinaryIO,
        *,
        max_bytes: int,
        what: str | None = None,
        max_entries: int = DEFAULT_MAX_ENTRIES,
    ) -> None:
        self.max_bytes = int(max_bytes)
        self._read_total = 0
        if isinstance(source, (str, os.PathLike)):
            path = Path(source)
            self.what = what or str(path)
            if not path.is_file():
                raise FileNotFoundError(f"no file at {path}")
            size = path.stat().st_size
            fh: BinaryIO = open(path, "rb")  # closed by close()
        else:
            fh = source
            self.what = what or "the file"
            size = fh.seek(0, io.SEEK_END)
            fh.seek(0)
        self._fh = fh
        self._own = isinstance(source, (str, os.PathLike))
        try:
            if size > self.max_bytes:
                raise FileFormatError(
                    f"{self.what} has {size} bytes; the limit is {self.max_bytes} "
                    "(raise max_bytes to read larger files)"
                )
            if size < 4 or fh.read(4) != b"PK\x03\x04":
                fh.seek(0)
                start = fh.read(64)
                if not start:
                    kind = "an empty file"
                elif start.startswith(b"\x93NUMPY"):
                    kind = "a single .npy array"
                elif _looks_like_text(start):
                    kind = "a text file"
                else:
                    kind = "not a zip archive"
                raise FileFormatError(
                    f"{self.what} is not an .npz file ({kind}; an .npz file is a zip archive "
                    "of .npy arrays)"
                )
            _check_directory(fh, size, self.what, int(max_entries))
            fh.seek(0)
            try:
                self._zip = zipfile.ZipFile(fh)
            except Exception as exc:  # BadZipFile, OSError, ...: a damaged directory
                raise FileFormatError(
                    f"{self.what} is not a readable .npz file (truncated or corrupt?): {exc}"
                ) from exc
        except BaseException:
            self.close()
            raise
        infos: dict[str, zipfile.ZipInfo] = {}
        for info in self._zip.infolist():
            if info.filename.endswith(".npy"):
                infos.setdefault(info.filename[: -len(".npy")], info)
        self._infos = infos

    # -- context manager ----------------------------------------------------------------------
    def __enter__(self) -> NpzReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the archive (and the file, if this reader opened it)."""
        zf = getattr(self, "_zip", None)
        if zf is not None:
            zf.close()
        if self._own:
            self._fh.close()

    # -- reading ------------------------------------------------------------------------------
    @property
    def members(self) -> frozenset[str]:
        """Names of the ``.npy`` members (without the suffix)."""
        return frozenset(self._infos)

    def _open(self, name: str) -> tuple[Any, tuple[int, ...], np.dtype[Any], bool, int]:
        """Open member ``name``; return (stream after the header, shape, dtype, fortran, data
        bytes) after checking the declared sizes."""
        if name not in self._infos:
            raise FileFormatError(f"{self.what}: missing array {name!r}")
        info = self._infos[name]
        if info.file_size > self.max_bytes:
            raise FileFormatError(
                f"{self.what}: array {name!r} declares {info.file_size} bytes uncompressed; the "
                f"limit is {self.max_bytes}"
            )
        try:
            stream = self._zip.open(info)
        except Exception as exc:  # bad headers, encrypted (RuntimeError), unknown method, ...
            raise self._corrupt(name, exc) from exc
        try:
            version = npy_format.read_magic(stream)
            if version == (1, 0):
                hdr = npy_format.read_array_header_1_0(stream, max_header_size=MAX_NPY_HEADER)
            elif version in ((2, 0), (3, 0)):
                hdr = npy_format.read_array_header_2_0(stream, max_header_size=MAX_NPY_HEADER)
            else:
                raise ValueError(f"unknown .npy format version {version}")
            header_len = stream.tell()
        except Exception as exc:  # also zlib/lzma/bz2 errors of a damaged member
            stream.close()
            raise self._corrupt(name, exc) from exc
        shape, fortran, dtype = hdr
        if dtype.hasobject or dtype.names is not None or dtype.subdtype is not None:
            stream.close()
            raise FileFormatError(
                f"{self.what}: array {name!r} has dtype {dtype} (Python objects, pickle or "
                "records); these files hold plain numbers and text only"
            )
        if dtype.kind not in _ALLOWED_KINDS:
            stream.close()
            raise FileFormatError(
                f"{self.what}: array {name!r} has dtype {dtype}; expected numbers or text"
            )
        if dtype.itemsize == 0:  # numpy cannot even build such an array from bytes
            stream.close()
            raise FileFormatError(
                f"{self.what}: array {name!r} has dtype {dtype} (zero bytes per element); "
                "expected numbers or text of at least one character"
            )
        n_bytes = math.prod(shape) * dtype.itemsize
        if header_len + n_bytes != info.file_size:
            stream.close()
            raise FileFormatError(
                f"{self.what}: array {name!r} has shape {shape} and dtype {dtype} "
                f"({n_bytes} bytes) but its member holds {info.file_size - header_len} bytes "
                "of data (corrupt file?)"
            )
        return stream, tuple(int(d) for d in shape), dtype, bool(fortran), n_bytes

    def header(self, name: str) -> tuple[tuple[int, ...], np.dtype[Any]]:
        """Shape and dtype of member ``name``, from its ``.npy`` header (data not read)."""
        stream, shape, dtype, _fortran, _n = self._open(name)
        stream.close()
        return shape, dtype

    def read(self, name: str) -> NDArray[Any]:
        """Read member ``name`` (sizes checked before decompressing; never unpickles)."""
        stream, shape, dtype, fortran, n_bytes = self._open(name)
        if self._read_total + n_bytes > self.max_bytes:
            stream.close()
            raise FileFormatError(
                f"{self.what}: reading array {name!r} ({n_bytes} bytes) would exceed the "
                f"limit of {self.max_bytes} bytes in total"
            )
        try:
            with stream:
                data = stream.read(n_bytes)
        except Exception as exc:  # zlib/lzma/bz2 errors, a bad CRC, ...
            raise self._corrupt(name, exc) from exc
        if len(data) != n_bytes:
            raise self._corrupt(name, EOFError(f"{len(data)} of {n_bytes} bytes"))
        self._read_total += n_bytes
        arr = np.frombuffer(data, dtype=dtype)
        return arr.reshape(shape, order="F" if fortran else "C").copy()

    def _corrupt(self, name: str, exc: BaseException) -> FileFormatError:
        info = self._infos[name]
        if info.flag_bits & 0x1:
            problem = "is encrypted; expected a plain (unencrypted) zip member"
        elif isinstance(exc, NotImplementedError):
            problem = (
                f"uses zip compression method {info.compress_type}, which cannot be read; "
                "expected stored or deflate (as numpy writes)"
            )
        else:
            problem = f"cannot be read (truncated or corrupt file?): {type(exc).__name__}: {exc}"
        return FileFormatError(f"{self.what}: array {name!r} {problem}")


def _check_directory(fh: BinaryIO, size: int, what: str, max_entries: int) -> None:
    """Check an archive's zip directory before :mod:`zipfile` parses it (zipfile reads the whole
    directory, by its size in bytes, into memory and keeps every entry).

    The end-of-central-directory record (and the ZIP64 one, when its locator precedes the
    record: zipfile then uses it) gives the entry count, the directory's size and its offset.
    The count must be at most ``max_entries``, the size at most ``MAX_DIRECTORY_ENTRY_BYTES``
    per entry, and the directory must end exactly where the end record starts. The directory,
    now known to be small, is then read and its entries counted: the count must be the one the
    end record declares, so that a record that lies cannot smuggle in more entries.

    Raises:
        FileFormatError: naming the file and what is wrong.
    """

    def fail(problem: str) -> FileFormatError:
        return FileFormatError(
            f"{what} is not a readable .npz file (truncated or corrupt?): {problem}"
        )

    tail_size = min(size, _EOCD.size + 0xFFFF)  # the record and its longest comment
    fh.seek(size - tail_size)
    tail = fh.read(tail_size)
    if tail[-_EOCD.size : -_EOCD.size + 4] == b"PK\x05\x06" and tail[-2:] == b"\0\0":
        pos = len(tail) - _EOCD.size  # no comment (numpy's files); what zipfile looks at first
    else:
        pos = tail.rfind(b"PK\x05\x06")
    if pos < 0 or pos + _EOCD.size > len(tail):
        raise fail("no end-of-directory record at its end")
    _sig, disk, cd_disk, n_disk, n_total, cd_size, cd_offset, comment = _EOCD.unpack_from(tail, pos)
    if pos + _EOCD.size + comment != len(tail):
        raise fail("its end-of-directory record does not end the file")
    end_at = size - tail_size + pos  # where the directory must end
    if end_at >= _ZIP64_LOCATOR.size + _ZIP64_EOCD.size:
        fh.seek(end_at - _ZIP64_LOCATOR.size)
        locator = _ZIP64_LOCATOR.unpack(fh.read(_ZIP64_LOCATOR.size))
        if locator[0] == b"PK\x06\x07":
            z64_at = end_at - _ZIP64_LOCATOR.size - _ZIP64_EOCD.size
            fh.seek(z64_at)
            record = _ZIP64_EOCD.unpack(fh.read(_ZIP64_EOCD.size))
            if (
                record[0] != b"PK\x06\x06"
                or record[1] != _ZIP64_EOCD.size - 12
                or locator[2] != z64_at
                or locator[1] != 0
            ):
                raise fail("its ZIP64 end-of-directory record is not where its locator says")
            disk, cd_disk, n_disk, n_total, cd_size, cd_offset = record[4:]
            end_at = z64_at
    if disk or cd_disk or n_disk != n_total:
        raise fail("it spans several disks (multi-part zip archives are not supported)")
    if n_total > max_entries:
        raise FileFormatError(f"{what} lists {n_total} entries; expected at most {max_entries}")
    if cd_size > max(n_total, 1) * MAX_DIRECTORY_ENTRY_BYTES:
        raise fail(
            f"its zip directory takes {cd_size} bytes for the {n_total} entries its end record "
            f"declares; expected at most {MAX_DIRECTORY_ENTRY_BYTES} bytes per entry"
        )
    if cd_offset + cd_size != end_at:
        raise fail(
            f"its zip directory (bytes {cd_offset} to {cd_offset + cd_size}) does not end where "
            f"the end record starts (byte {end_at})"
        )
    fh.seek(cd_offset)
    directory = fh.read(cd_size)
    count = at = 0
    while at < len(directory) and count <= n_total:
        if at + _CENTRAL.size > len(directory) or directory[at : at + 4] != b"PK\x01\x02":
            raise fail(f"its zip directory has a malformed entry at byte {cd_offset + at}")
        fields = _CENTRAL.unpack_from(directory, at)
        at += _CENTRAL.size + fields[12] + fields[13] + fields[14]  # name, extra, comment
        count += 1
    if count != n_total or at != cd_size:
        more = "or more " if count > n_total else ""
        raise fail(
            f"its zip directory holds {count} {more}entries but its end record declares "
            f"{n_total} entries"
        )


def _looks_like_text(start: bytes) -> bool:
    """Whether the first bytes of a file look like UTF-8 text (a multi-byte character may be cut
    at the end)."""
    text = start.decode("utf-8", errors="replace").rstrip("\ufffd")
    return all(c.isprintable() or c in "\r\n\t" for c in text)
