"""Recorded demonstrations of the coffee task: record, save, load, validate.

A :class:`Demonstration` is one teacher episode as per-step arrays; a :class:`DemonstrationSet` is
several of them plus metadata (env id and kwargs, seeds, versions, teacher settings). Sets are saved
as ONE ``.npz`` file without pickle: per-step arrays of all demonstrations concatenated along the
first axis, ``lengths`` to split them again, and the metadata as a JSON string. The schema is
documented in ``docs/demonstration-format.md``; :meth:`DemonstrationSet.load` checks every part of
it and raises :class:`DemonstrationFormatError` naming what is wrong.

Row ``t`` of a demonstration is the state *before* the ``t``-th action: row 0 is the state
returned by ``reset``, the last row is the state in which the episode ended. ``actions[t]`` is the
teacher's action in state ``t``; for the last row the teacher is asked as well but its action is
not applied (the episode is over), so that every per-step array has ``n_steps`` rows.

Example:
    >>> import gymnasium as gym, gym_coffee                      # doctest: +SKIP
    >>> env = gym.make("gym_coffee/CoffeeTask-v0")
    >>> demos = gym_coffee.collect_demonstrations(env, n=4, seed=0)
    >>> demos.save("demos.npz")
    >>> demos = gym_coffee.DemonstrationSet.load("demos.npz")
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
import zipfile
import zlib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, overload

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "ACTION_DIM",
    "FORMAT_NAME",
    "N_JOINTS",
    "OBJECT_NAMES",
    "SCHEMA_VERSION",
    "STAGE_NAMES",
    "Demonstration",
    "DemonstrationFormatError",
    "DemonstrationSet",
    "collect_demonstrations",
]

FORMAT_NAME = "gym_coffee.demonstrations"
"""Value of ``metadata["format"]``: tells our files from other ``.npz`` files."""
SCHEMA_VERSION = 1
"""Version of the file schema written by :meth:`DemonstrationSet.save`."""
SUPPORTED_SCHEMA_VERSIONS = (1,)
N_JOINTS = 7
"""Panda arm joints (``joint_pos`` columns)."""
ACTION_DIM = 8
"""7 joint-position deltas + 1 gripper command (``actions`` columns)."""
STAGE_NAMES = ("cup_grasped", "cup_placed", "button_pressed")
"""Columns of ``stages``, in order; the same names as the flags in the env's ``info``."""
OBJECT_NAMES = ("cup", "machine")
"""Objects whose pose the env reports; keys of ``object_pos`` and ``object_quat``."""

# Per-step arrays: name -> (dtype, trailing shape). ``None`` in a trailing shape means "the
# observation size", taken from the data (and checked against ``metadata["obs_dim"]``).
_STEP_ARRAYS: dict[str, tuple[type, tuple[int | None, ...]]] = {
    "time": (np.float64, ()),
    "joint_pos": (np.float64, (N_JOINTS,)),
    "gripper": (np.float64, ()),
    "ee_pos": (np.float64, (3,)),
    "stages": (np.bool_, (len(STAGE_NAMES),)),
    "actions": (np.float32, (ACTION_DIM,)),
    "observations": (np.float32, (None,)),
}
_OBJECT_ARRAYS: dict[str, tuple[type, tuple[int, ...]]] = {
    "object_pos": (np.float64, (3,)),
    "object_quat": (np.float64, (4,)),
}


class DemonstrationFormatError(ValueError):
    """A demonstration file or array does not follow the schema; the message says what is wrong."""


def _shape_str(trailing: tuple[int | None, ...], lead: str = "n_steps") -> str:
    dims = [lead, *("obs_dim" if d is None else str(d) for d in trailing)]
    return "(" + ", ".join(dims) + ("," if len(dims) == 1 else "") + ")"


def _as_step_array(
    name: str,
    value: Any,
    dtype: type,
    trailing: tuple[int | None, ...],
    n_steps: int | None,
    lead: str | None = None,
) -> NDArray[Any]:
    """Convert ``value`` to ``dtype``; check shape ``(n_steps, *trailing)`` and finiteness."""
    arr = np.asarray(value)
    if arr.dtype == object:
        raise DemonstrationFormatError(
            f"array {name!r} has dtype object; expected {np.dtype(dtype)}"
        )
    if dtype is np.bool_ and arr.dtype != np.bool_:
        if arr.size and not np.isin(arr, (0, 1)).all():
            raise DemonstrationFormatError(f"array {name!r} must hold booleans (0/1)")
    if dtype is not np.bool_ and not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise DemonstrationFormatError(
            f"array {name!r} has dtype {arr.dtype}; expected a numeric dtype ({np.dtype(dtype)})"
        )
    arr = np.ascontiguousarray(arr, dtype=dtype)
    expected_ndim = 1 + len(trailing)
    ok = arr.ndim == expected_ndim and all(
        want is None or got == want for got, want in zip(arr.shape[1:], trailing, strict=True)
    )
    if ok and n_steps is not None and arr.shape[0] != n_steps:
        ok = False
    if not ok:
        if lead is None:
            lead = "n_steps" if n_steps is None else f"n_steps={n_steps}"
        raise DemonstrationFormatError(
            f"array {name!r} has shape {arr.shape}; expected {_shape_str(trailing, lead)}"
        )
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0]
        what = "NaN" if np.isnan(arr[tuple(bad)]) else "inf"
        raise DemonstrationFormatError(
            f"array {name!r} contains {what} (first at index {tuple(int(i) for i in bad)})"
        )
    return arr


@dataclass(eq=False)
class Demonstration:
    """One demonstration: the teacher's episode as per-step arrays of length ``n_steps``.

    Row ``t`` is the state before action ``t`` (row 0 = after ``reset``; last row = final state).
    Arrays are converted to the dtypes below and checked on construction.

    Attributes:
        time: ``(n_steps,)`` float64, seconds since reset (the observation's ``time``).
        joint_pos: ``(n_steps, 7)`` float64, arm joint positions (rad).
        gripper: ``(n_steps,)`` float64, finger opening (m).
        ee_pos: ``(n_steps, 3)`` float64, end-effector (grasp point) position, world frame (m).
        object_pos: name -> ``(n_steps, 3)`` float64, object positions, world frame; keys
            ``"cup"`` and ``"machine"``.
        object_quat: name -> ``(n_steps, 4)`` float64, object orientations as unit quaternions
            ``(x, y, z, w)``; same keys as ``object_pos``.
        stages: ``(n_steps, 3)`` bool, stage flags ``STAGE_NAMES`` in that state.
        actions: ``(n_steps, 8)`` float32, the teacher's action in that state (the last row's
            action was not applied).
        observations: ``(n_steps, obs_dim)`` float32, the env's observation in that state.
        seed: the ``reset(seed=...)`` that produced the layout.
        success: whether the episode ended with ``is_success``.
    """

    time: NDArray[np.float64]
    joint_pos: NDArray[np.float64]
    gripper: NDArray[np.float64]
    ee_pos: NDArray[np.float64]
    object_pos: dict[str, NDArray[np.float64]]
    object_quat: dict[str, NDArray[np.float64]]
    stages: NDArray[np.bool_]
    actions: NDArray[np.float32]
    observations: NDArray[np.float32]
    seed: int
    success: bool

    def __post_init__(self) -> None:
        t = np.asarray(self.time)
        if t.ndim != 1 or t.shape[0] < 1:
            raise DemonstrationFormatError(
                f"array 'time' has shape {t.shape}; expected (n_steps,) with n_steps >= 1"
            )
        n = t.shape[0]
        for name, (dtype, trailing) in _STEP_ARRAYS.items():
            setattr(self, name, _as_step_array(name, getattr(self, name), dtype, trailing, n))
        if set(self.object_pos) != set(self.object_quat):
            raise DemonstrationFormatError(
                f"object_pos has objects {sorted(self.object_pos)} but object_quat has "
                f"{sorted(self.object_quat)}; they must name the same objects"
            )
        for attr, (dtype, trailing) in _OBJECT_ARRAYS.items():
            objects = getattr(self, attr)
            setattr(
                self,
                attr,
                {
                    _check_object_name(obj): _as_step_array(
                        f"{attr}.{obj}", value, dtype, trailing, n
                    )
                    for obj, value in objects.items()
                },
            )
        self.seed = int(self.seed)
        self.success = bool(self.success)

    @property
    def n_steps(self) -> int:
        """Number of recorded states (rows)."""
        return int(self.time.shape[0])

    @property
    def obs_dim(self) -> int:
        """Length of one observation."""
        return int(self.observations.shape[1])

    def __len__(self) -> int:
        return self.n_steps

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Demonstration):
            return NotImplemented
        if (self.seed, self.success) != (other.seed, other.success):
            return False
        if set(self.object_pos) != set(other.object_pos):
            return False
        pairs = [(getattr(self, k), getattr(other, k)) for k in _STEP_ARRAYS]
        pairs += [(self.object_pos[k], other.object_pos[k]) for k in self.object_pos]
        pairs += [(self.object_quat[k], other.object_quat[k]) for k in self.object_quat]
        return all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in pairs)

    __hash__ = None  # type: ignore[assignment]  # mutable arrays

    def __repr__(self) -> str:
        return (
            f"Demonstration(seed={self.seed}, success={self.success}, n_steps={self.n_steps}, "
            f"duration={self.time[-1] - self.time[0]:.2f}s, objects={sorted(self.object_pos)})"
        )


def _check_object_name(name: str) -> str:
    if not isinstance(name, str) or not name.isidentifier():
        raise DemonstrationFormatError(
            f"object name {name!r} must be a Python identifier (it becomes part of a key)"
        )
    return name


class DemonstrationSet(Sequence[Demonstration]):
    """A sequence of :class:`Demonstration` plus ``metadata`` (a JSON-serialisable dict).

    ``metadata`` keys written by :func:`collect_demonstrations`: ``env_id``, ``env_kwargs``,
    ``seeds``, ``failed_seeds``, ``package_version``, ``versions``, ``teacher``,
    ``control_dt``, ``obs_slices``; :meth:`save` adds ``format``, ``schema_version``,
    ``obs_dim``, ``objects``, ``stage_names``.

    Args:
        demonstrations: the demonstrations; all must have the same ``obs_dim`` and objects.
        metadata: free-form, JSON-serialisable information about how they were made.
    """

    def __init__(
        self,
        demonstrations: Sequence[Demonstration] = (),
        metadata: Mapping[str, Any] | None = None,
    ) -> None:
        demos = list(demonstrations)
        for i, d in enumerate(demos):
            if not isinstance(d, Demonstration):
                raise TypeError(f"item {i} is a {type(d).__name__}, not a Demonstration")
        if demos:
            first = demos[0]
            for i, d in enumerate(demos[1:], start=1):
                if d.obs_dim != first.obs_dim:
                    raise DemonstrationFormatError(
                        f"demonstration {i} has obs_dim {d.obs_dim}, demonstration 0 has "
                        f"{first.obs_dim}; all must match"
                    )
                if set(d.object_pos) != set(first.object_pos):
                    raise DemonstrationFormatError(
                        f"demonstration {i} has objects {sorted(d.object_pos)}, demonstration 0 "
                        f"has {sorted(first.object_pos)}; all must match"
                    )
        self._demos = demos
        self.metadata: dict[str, Any] = dict(metadata or {})

    # -- Sequence -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._demos)

    @overload
    def __getitem__(self, index: int) -> Demonstration: ...
    @overload
    def __getitem__(self, index: slice) -> DemonstrationSet: ...
    def __getitem__(self, index: int | slice) -> Demonstration | DemonstrationSet:
        if isinstance(index, slice):
            return DemonstrationSet(self._demos[index], self.metadata)
        return self._demos[index]

    def __iter__(self) -> Iterator[Demonstration]:
        return iter(self._demos)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, DemonstrationSet):
            return NotImplemented
        return self._demos == other._demos and self.metadata == other.metadata

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        seeds = self.seeds
        shown = str(seeds) if len(seeds) <= 8 else f"[{seeds[0]}, {seeds[1]}, ..., {seeds[-1]}]"
        return (
            f"DemonstrationSet({len(self)} demonstrations, seeds={shown}, "
            f"env_id={self.metadata.get('env_id')!r})"
        )

    @property
    def seeds(self) -> list[int]:
        """The ``reset`` seed of each demonstration."""
        return [d.seed for d in self._demos]

    @property
    def objects(self) -> list[str]:
        """Names of the recorded objects (sorted)."""
        return sorted(self._demos[0].object_pos) if self._demos else list(OBJECT_NAMES)

    # -- saving ---------------------------------------------------------------------------------
    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The ``.npz`` contents: concatenated per-step arrays, ``lengths``, ``seeds``,
        ``success`` and ``metadata`` (a 0-d unicode array holding JSON)."""
        if not self._demos:
            raise DemonstrationFormatError("cannot save an empty DemonstrationSet")
        demos = self._demos
        out: dict[str, NDArray[Any]] = {}
        for name in _STEP_ARRAYS:
            out[name] = np.concatenate([getattr(d, name) for d in demos], axis=0)
        for attr in _OBJECT_ARRAYS:
            for obj in self.objects:
                out[f"{attr}.{obj}"] = np.concatenate([getattr(d, attr)[obj] for d in demos])
        out["lengths"] = np.array([d.n_steps for d in demos], dtype=np.int64)
        out["seeds"] = np.array(self.seeds, dtype=np.int64)
        out["success"] = np.array([d.success for d in demos], dtype=np.bool_)
        meta = dict(self.metadata)
        meta.update(
            format=FORMAT_NAME,
            schema_version=SCHEMA_VERSION,
            obs_dim=demos[0].obs_dim,
            objects=self.objects,
            stage_names=list(STAGE_NAMES),
        )
        try:
            text = json.dumps(meta, sort_keys=True, allow_nan=False, default=_json_default)
        except (TypeError, ValueError) as exc:
            raise TypeError(f"metadata is not JSON-serialisable: {exc}") from exc
        out["metadata"] = np.array(text)
        return out

    def save(self, path: str | os.PathLike[str], overwrite: bool = False) -> Path:
        """Write the set to ONE ``.npz`` file (no pickle), atomically.

        The data go to a temporary file in the same folder, which then replaces ``path``: an
        interrupted or failed write never leaves a half-written or damaged ``path`` behind.

        Args:
            path: file to write; the name is used as given (no ``.npz`` is appended).
            overwrite: replace an existing file. Without it an existing ``path`` is an error.

        Returns:
            The path written.

        Raises:
            FileExistsError: ``path`` exists and ``overwrite`` is false.
            FileNotFoundError: the folder of ``path`` does not exist.
            DemonstrationFormatError: the set is empty.
            TypeError: ``metadata`` is not JSON-serialisable.
        """
        path = Path(path)
        if path.exists() and not overwrite:
            raise FileExistsError(
                f"{path} exists; pass overwrite=True (CLI: --force) to replace it"
            )
        arrays = self.to_arrays()  # fails before anything touches the disk
        folder = path.parent if str(path.parent) else Path(".")
        if not folder.is_dir():
            raise FileNotFoundError(f"cannot write {path}: folder {folder} does not exist")
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez_compressed(fh, **arrays)
                fh.flush()
                os.fsync(fh.fileno())
            os.chmod(tmp_name, 0o666 & ~_umask())
            if overwrite:
                os.replace(tmp_name, path)
            else:
                # os.link fails if ``path`` appeared meanwhile: no silent clobbering in a race.
                try:
                    os.link(tmp_name, path)
                except FileExistsError:
                    raise FileExistsError(
                        f"{path} exists; pass overwrite=True (CLI: --force) to replace it"
                    ) from None
                except OSError:  # file systems without hard links
                    if path.exists():
                        raise FileExistsError(f"{path} exists; pass overwrite=True") from None
                    os.replace(tmp_name, path)
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp_name)
        return path

    # -- loading --------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> DemonstrationSet:
        """Read and validate a file written by :meth:`save`.

        Raises:
            FileNotFoundError: no such file.
            DemonstrationFormatError: the file is not a readable ``.npz`` (truncated, corrupt), is
                not a demonstration file, has an unsupported schema version, misses an array, has
                an array of the wrong shape or dtype, contains NaN/inf, or its ``lengths`` do not
                add up. The message names the file and what is wrong.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no demonstration file at {path}")
        try:
            with np.load(path, allow_pickle=False) as npz:
                keys = set(npz.files)
                arrays = {}
                for key in keys:
                    try:
                        arrays[key] = npz[key]
                    except ValueError as exc:
                        if "allow_pickle" in str(exc):
                            raise DemonstrationFormatError(
                                f"{path}: array {key!r} holds Python objects (pickle); "
                                "demonstration files must not"
                            ) from exc
                        raise DemonstrationFormatError(
                            f"{path}: array {key!r} cannot be read (truncated or corrupt "
                            f"file?): {exc}"
                        ) from exc
                    except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as exc:
                        raise DemonstrationFormatError(
                            f"{path}: array {key!r} cannot be read (truncated or corrupt "
                            f"file?): {exc}"
                        ) from exc
        except DemonstrationFormatError:
            raise
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as exc:
            raise DemonstrationFormatError(
                f"{path} is not a readable .npz file (truncated or corrupt?): {exc}"
            ) from exc
        try:
            return cls.from_arrays(arrays)
        except DemonstrationFormatError as exc:
            raise DemonstrationFormatError(f"{path}: {exc}") from None

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, NDArray[Any]]) -> DemonstrationSet:
        """Inverse of :meth:`to_arrays`, with full validation (see :meth:`load`)."""
        meta = _parse_metadata(arrays)
        objects = meta.get("objects")
        if (
            not isinstance(objects, list)
            or not objects
            or not all(isinstance(o, str) and o.isidentifier() for o in objects)
        ):
            raise DemonstrationFormatError(
                f"metadata 'objects' must be a non-empty list of names, got {objects!r}"
            )
        if meta.get("stage_names", list(STAGE_NAMES)) != list(STAGE_NAMES):
            raise DemonstrationFormatError(
                f"metadata 'stage_names' is {meta.get('stage_names')!r}; expected "
                f"{list(STAGE_NAMES)}"
            )
        required = ["lengths", "seeds", "success", *_STEP_ARRAYS]
        required += [f"{attr}.{obj}" for attr in _OBJECT_ARRAYS for obj in objects]
        missing = [k for k in required if k not in arrays]
        if missing:
            raise DemonstrationFormatError(
                "missing array"
                + ("s " if len(missing) > 1 else " ")
                + ", ".join(map(repr, missing))
            )

        lengths = np.asarray(arrays["lengths"])
        if lengths.ndim != 1 or lengths.size == 0 or lengths.dtype.kind not in "iu":
            raise DemonstrationFormatError(
                f"array 'lengths' has shape {lengths.shape} and dtype {lengths.dtype}; expected "
                "(n_demos,) integers with n_demos >= 1"
            )
        if (lengths < 1).any():
            raise DemonstrationFormatError(
                f"array 'lengths' has entries < 1: {lengths.tolist()}; every demonstration "
                "has at least one step"
            )
        n_demos, total = int(lengths.size), int(lengths.sum())
        seeds = np.asarray(arrays["seeds"])
        success = np.asarray(arrays["success"])
        if seeds.shape != (n_demos,) or seeds.dtype.kind not in "iu":
            raise DemonstrationFormatError(
                f"array 'seeds' has shape {seeds.shape} and dtype {seeds.dtype}; expected "
                f"({n_demos},) integers (one per entry of 'lengths')"
            )
        if success.shape != (n_demos,) or success.dtype != np.bool_:
            raise DemonstrationFormatError(
                f"array 'success' has shape {success.shape} and dtype {success.dtype}; expected "
                f"({n_demos},) bool (one per entry of 'lengths')"
            )
        if "seeds" in meta and meta["seeds"] != seeds.tolist():
            raise DemonstrationFormatError(
                f"metadata 'seeds' {meta['seeds']} differ from array 'seeds' {seeds.tolist()}"
            )

        # Check every per-step array's total length against sum(lengths) before splitting.
        step_names = list(_STEP_ARRAYS) + [f"{a}.{o}" for a in _OBJECT_ARRAYS for o in objects]
        obs_dim = meta.get("obs_dim")
        checked: dict[str, NDArray[Any]] = {}
        for name in step_names:
            attr = name.split(".")[0]
            dtype, trailing = _STEP_ARRAYS.get(attr) or _OBJECT_ARRAYS[attr]
            if attr == "observations" and isinstance(obs_dim, int):
                trailing = (obs_dim,)
            arr = np.asarray(arrays[name])
            if arr.ndim >= 1 and arr.shape[0] != total and arr.ndim == 1 + len(trailing):
                raise DemonstrationFormatError(
                    f"array {name!r} has {arr.shape[0]} rows but 'lengths' add up to {total} "
                    f"({lengths.tolist()}); expected shape {_shape_str(trailing, str(total))}"
                )
            try:
                checked[name] = _as_step_array(name, arr, dtype, trailing, total, lead=str(total))
            except DemonstrationFormatError as exc:
                msg = str(exc)
                if "contains" in msg:
                    msg += _locate_row(arr, lengths)
                raise DemonstrationFormatError(msg) from None

        bounds = np.concatenate([[0], np.cumsum(lengths)])
        demos = []
        for i in range(n_demos):
            sl = slice(int(bounds[i]), int(bounds[i + 1]))
            kw: dict[str, Any] = {name: checked[name][sl] for name in _STEP_ARRAYS}
            for attr in _OBJECT_ARRAYS:
                kw[attr] = {obj: checked[f"{attr}.{obj}"][sl] for obj in objects}
            demos.append(Demonstration(**kw, seed=int(seeds[i]), success=bool(success[i])))
        metadata = {
            k: v
            for k, v in meta.items()
            if k not in ("format", "schema_version", "obs_dim", "objects", "stage_names")
        }
        return cls(demos, metadata)


def _locate_row(arr: NDArray[Any], lengths: NDArray[Any]) -> str:
    """' (demonstration i, step j)' for the first non-finite row of a concatenated array."""
    arr = np.asarray(arr, dtype=np.float64)
    rows = np.argwhere(~np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1)).ravel()
    if rows.size == 0:
        return ""
    row = int(rows[0])
    demo = int(np.searchsorted(np.cumsum(lengths), row, side="right"))
    step = row - int(np.sum(lengths[:demo]))
    return f"; row {row} is demonstration {demo}, step {step}"


def _parse_metadata(arrays: Mapping[str, NDArray[Any]]) -> dict[str, Any]:
    if "metadata" not in arrays:
        raise DemonstrationFormatError(
            "missing array 'metadata' (the JSON header); not a gym_coffee demonstration file"
        )
    raw = np.asarray(arrays["metadata"])
    if raw.dtype.kind != "U" or raw.size != 1:
        raise DemonstrationFormatError(
            f"array 'metadata' has dtype {raw.dtype} and shape {raw.shape}; expected one "
            "unicode string holding JSON"
        )
    try:
        meta = json.loads(str(raw.reshape(())))
    except json.JSONDecodeError as exc:
        raise DemonstrationFormatError(f"array 'metadata' is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise DemonstrationFormatError("array 'metadata' must hold a JSON object")
    if meta.get("format") != FORMAT_NAME:
        raise DemonstrationFormatError(
            f"metadata 'format' is {meta.get('format')!r}; expected {FORMAT_NAME!r} "
            "(not a gym_coffee demonstration file)"
        )
    version = meta.get("schema_version")
    if version not in SUPPORTED_SCHEMA_VERSIONS:
        newer = isinstance(version, int) and version > max(SUPPORTED_SCHEMA_VERSIONS)
        hint = " (written by a newer gym_coffee? upgrade gym-coffee)" if newer else ""
        raise DemonstrationFormatError(
            f"schema version {version!r} is not supported; this gym_coffee reads "
            f"{list(SUPPORTED_SCHEMA_VERSIONS)}{hint}"
        )
    if "obs_dim" in meta and not (isinstance(meta["obs_dim"], int) and meta["obs_dim"] > 0):
        raise DemonstrationFormatError(
            f"metadata 'obs_dim' is {meta['obs_dim']!r}; expected a positive integer"
        )
    return meta


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (Path, type)):
        return str(obj)
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    raise TypeError(f"{type(obj).__name__} {obj!r} cannot be stored as JSON")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# ------------------------------------------------------------------------------------------------
# Recording
# ------------------------------------------------------------------------------------------------


def _quat_from_yaw(yaw: NDArray[Any]) -> NDArray[np.float64]:
    """Unit quaternions ``(x, y, z, w)`` of rotations by ``yaw`` about the world z axis."""
    yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
    q = np.zeros((yaw.size, 4))
    q[:, 2] = np.sin(yaw / 2.0)
    q[:, 3] = np.cos(yaw / 2.0)
    return q


def _env_identity(env: Any) -> tuple[str | None, dict[str, Any], int | None]:
    """(env id, env kwargs, max_episode_steps) of a ``gym.make`` env or a raw env."""
    import gymnasium as gym

    spec = getattr(env, "spec", None) or getattr(env.unwrapped, "spec", None)
    if spec is not None:
        return spec.id, dict(spec.kwargs), spec.max_episode_steps
    cls = type(env.unwrapped)
    entry = f"{cls.__module__}:{cls.__qualname__}"
    for env_spec in gym.registry.values():
        if env_spec.entry_point == entry:
            kwargs = dict(getattr(env.unwrapped, "init_kwargs", None) or {})
            return env_spec.id, kwargs, env_spec.max_episode_steps
    return None, {}, None


def _versions() -> dict[str, str]:
    from importlib import metadata as im

    out = {}
    for dist in ("gym-coffee", "gymnasium", "numpy", "pybullet"):
        try:
            out[dist] = im.version(dist)
        except im.PackageNotFoundError:
            out[dist] = "unknown"
    return out


def collect_demonstrations(
    env: Any,
    n: int,
    seed: int = 0,
    progress: bool = False,
    teacher_kwargs: Mapping[str, Any] | None = None,
    *,
    keep_failed: bool = False,
    max_attempts: int | None = None,
) -> DemonstrationSet:
    """Record ``n`` demonstrations of :class:`gym_coffee.teacher.ScriptedTeacher` in ``env``.

    Attempt ``i`` resets with ``seed + i`` and runs the teacher until the episode terminates or
    is truncated. By default only successful episodes are kept: a failed one is skipped and the
    next seed is tried, so asking for 4 demonstrations gives 4 successful ones. The seeds used
    are ``metadata["seeds"]`` (and each demonstration's ``seed``); skipped ones are
    ``metadata["failed_seeds"]``.

    Args:
        env: a ``gym.make("gym_coffee/CoffeeTask-v0")`` env (wrappers are fine) or a raw
            :class:`gym_coffee.env.CoffeeEnv`. It is reset but not closed.
        n: number of demonstrations (>= 1).
        seed: first layout seed. Keep it below ``EVAL_SEED_OFFSET`` (10 000) so that evaluation
            layouts stay disjoint from demonstration layouts.
        progress: show a tqdm progress bar.
        teacher_kwargs: keyword arguments for ``ScriptedTeacher`` (recorded in the metadata).
        keep_failed: keep failed episodes too (``success=False``) instead of retrying.
        max_attempts: give up after this many episodes; default ``2 * n + 10``.

    Returns:
        A :class:`DemonstrationSet` of ``n`` demonstrations.

    Raises:
        ValueError: ``n < 1``.
        RuntimeError: fewer than ``n`` successful episodes within ``max_attempts``.
    """
    from gym_coffee import __version__
    from gym_coffee.env import OBS_SLICES, obs_part
    from gym_coffee.teacher import ScriptedTeacher

    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    n = int(n)
    seed = int(seed)
    max_attempts = 2 * n + 10 if max_attempts is None else int(max_attempts)
    teacher_kwargs = dict(teacher_kwargs or {})
    env_id, env_kwargs, max_steps = _env_identity(env)
    if max_steps is None:
        max_steps = 400  # a raw env has no TimeLimit; do not loop forever on a stuck teacher

    from gym_coffee import env as env_module

    demos: list[Demonstration] = []
    failed: list[int] = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc="recording demonstrations", unit="demo")
    try:
        attempt = 0
        while len(demos) < n:
            if attempt >= max_attempts:
                raise RuntimeError(
                    f"the teacher succeeded on only {len(demos)} of {attempt} layouts (seeds "
                    f"{seed}..{seed + attempt - 1}; failed: {failed}); wanted {n}. Raise "
                    "max_attempts or pass keep_failed=True."
                )
            s = seed + attempt
            attempt += 1
            demo = _record_episode(env, s, ScriptedTeacher, teacher_kwargs, max_steps, obs_part)
            if demo.success or keep_failed:
                demos.append(demo)
                if bar is not None:
                    bar.update(1)
            else:
                failed.append(s)
            if bar is not None:
                bar.set_postfix(attempts=attempt, failed=len(failed))
    finally:
        if bar is not None:
            bar.close()

    metadata = {
        "env_id": env_id,
        "env_kwargs": env_kwargs,
        "seeds": [d.seed for d in demos],
        "failed_seeds": failed,
        "keep_failed": keep_failed,
        "package_version": __version__,
        "versions": _versions(),
        "teacher": {
            "class": f"{ScriptedTeacher.__module__}.{ScriptedTeacher.__qualname__}",
            "kwargs": teacher_kwargs,
            "rng": f"numpy.random.default_rng([{TEACHER_STREAM}, seed])",
        },
        "control_dt": float(getattr(env_module, "CONTROL_DT", math.nan)),
        "obs_slices": {k: [v.start, v.stop] for k, v in OBS_SLICES.items()},
    }
    if not math.isfinite(metadata["control_dt"]):
        metadata["control_dt"] = None
    return DemonstrationSet(demos, metadata)


TEACHER_STREAM = 0x7EAC4E2
"""First entropy word of the teacher's random generator: ``default_rng([TEACHER_STREAM, seed])``.

The env's layout generator is ``default_rng(seed)``-equivalent (Gymnasium seeding); seeding the
teacher with the bare ``seed`` would make its "human" variation the very same random numbers as
the layout. A separate stream keeps them independent and still reproducible.
"""


def teacher_rng(seed: int) -> np.random.Generator:
    """The teacher's random generator for the episode of layout ``seed``."""
    return np.random.default_rng([TEACHER_STREAM, int(seed)])


def _make_teacher(cls: Any, env: Any, seed: int, kwargs: dict[str, Any]) -> Any:
    """Construct the teacher for one episode; its human-like variation is seeded by ``seed``."""
    return cls(env, rng=teacher_rng(seed), **kwargs)


def _record_episode(
    env: Any,
    seed: int,
    teacher_cls: Any,
    teacher_kwargs: dict[str, Any],
    max_steps: int,
    obs_part: Any,
) -> Demonstration:
    obs, info = env.reset(seed=seed)
    teacher = _make_teacher(teacher_cls, env, seed, teacher_kwargs)
    observations, infos, actions = [obs], [info], []
    for _ in range(max_steps):
        action = np.asarray(teacher.act(obs), dtype=np.float32)
        actions.append(action)
        obs, _reward, terminated, truncated, info = env.step(action)
        observations.append(obs)
        infos.append(info)
        if terminated or truncated:
            break
    actions.append(np.asarray(teacher.act(obs), dtype=np.float32))  # not applied
    return _demonstration_from_steps(seed, observations, infos, actions, obs_part)


def _demonstration_from_steps(
    seed: int,
    observations: list[NDArray[Any]],
    infos: list[Mapping[str, Any]],
    actions: list[NDArray[Any]],
    obs_part: Any,
) -> Demonstration:
    obs = np.asarray(observations, dtype=np.float32)
    f64 = np.float64
    stages = np.array([[bool(i.get(k, False)) for k in STAGE_NAMES] for i in infos], dtype=bool)
    return Demonstration(
        time=obs_part(obs, "time").astype(f64).reshape(-1),
        joint_pos=obs_part(obs, "joint_pos").astype(f64),
        gripper=obs_part(obs, "gripper").astype(f64).reshape(-1),
        ee_pos=obs_part(obs, "ee_pos").astype(f64),
        object_pos={
            "cup": obs_part(obs, "cup_pos").astype(f64),
            "machine": obs_part(obs, "machine_pos").astype(f64),
        },
        object_quat={
            "cup": obs_part(obs, "cup_quat").astype(f64),
            "machine": _quat_from_yaw(obs_part(obs, "machine_yaw")),
        },
        stages=stages,
        actions=np.asarray(actions, dtype=np.float32),
        observations=obs,
        seed=seed,
        success=bool(infos[-1].get("is_success", False)),
    )
