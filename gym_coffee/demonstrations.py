"""Recorded demonstrations of the coffee task: record, save, load, validate.

A :class:`Demonstration` is one episode (of the scripted teacher, or taught by hand with
:mod:`gym_coffee.teleop`) as per-step arrays; a :class:`DemonstrationSet` is several of them plus
metadata (env id and kwargs, seeds, versions, who demonstrated). Sets are saved as ONE ``.npz``
file without pickle: per-step arrays of all demonstrations concatenated along the first axis,
``lengths`` to split them again, and the metadata as a JSON string. The schema is documented in
``docs/demonstration-format.md``; :meth:`DemonstrationSet.load` reads only the arrays it knows,
checks every declared size before decompressing and every number before building anything, and
raises :class:`DemonstrationFormatError` naming what is wrong.

Row ``t`` of a demonstration is the state *before* the ``t``-th action: row 0 is the state
returned by ``reset``, the last row is the state in which the episode ended. ``actions[t]`` is the
demonstrator's action in state ``t`` in the env's action mode (``action_type``); for the last row
the teacher is asked as well but its action is not applied (the episode is over), so that every
per-step array has ``n_steps`` rows.

Example:
    >>> import gymnasium as gym, gym_coffee                      # doctest: +SKIP
    >>> env = gym.make(gym_coffee.ENV_ID)
    >>> demos = gym_coffee.collect_demonstrations(env, n=4, seed=0)
    >>> demos.save("demos.npz")
    >>> demos = gym_coffee.DemonstrationSet.load("demos.npz")
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Container, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, overload

import numpy as np
from numpy.typing import NDArray

from gym_coffee import STAGES
from gym_coffee._io import (
    FileFormatError,
    NpzReader,
    atomic_output,
    parse_json,
    refuse_existing,
)

__all__ = [
    "ACTION_DIM",
    "ACTION_DIMS",
    "DEFAULT_MAX_BYTES",
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
SCHEMA_VERSION = 2
"""Version of the file schema written by :meth:`DemonstrationSet.save` (2: ``action_type``)."""
SUPPORTED_SCHEMA_VERSIONS = (1, 2)
N_JOINTS = 7
"""Panda arm joints (``joint_pos`` columns)."""
ACTION_DIMS: dict[str, int] = {"joint": 8, "ee": 4, "ee_rot": 7}
"""Action size of each of the env's action modes (``action_type``); the gripper is the last
column in every mode."""
ACTION_DIM = ACTION_DIMS["joint"]
"""7 joint-position deltas + 1 gripper command (``actions`` columns of the default mode)."""
STAGE_NAMES = STAGES
"""Columns of ``stages``, in order; the same names as the flags in the env's ``info``."""
OBJECT_NAMES = ("cup", "machine")
"""Objects whose pose the env reports; keys of ``object_pos`` and ``object_quat``."""
DEFAULT_MAX_BYTES = 1 << 30
"""Default limit of :meth:`DemonstrationSet.load` (1 GiB): the file on disk, any one array
uncompressed and all arrays read together (200 teacher demonstrations take about 30 MB)."""
MAX_METADATA_CHARS = 1 << 20
"""Longest metadata JSON text read (characters)."""
MAX_OBS_DIM = 10_000
"""Largest ``obs_dim`` accepted from a file."""
_QUAT_NORM_TOL = 1e-3


@dataclass(frozen=True)
class _Spec:
    """One per-step array: dtype, trailing shape (``"obs_dim"``/``"action_dim"`` for sizes that
    come from the data) and the closed range of its values (the env's observation bounds)."""

    dtype: type
    trailing: tuple[int | str, ...]
    low: float = -math.inf
    high: float = math.inf


_STEP_ARRAYS: dict[str, _Spec] = {
    "time": _Spec(np.float64, (), 0.0, 1e4),
    "joint_pos": _Spec(np.float64, (N_JOINTS,), -2 * math.pi, 2 * math.pi),
    "gripper": _Spec(np.float64, (), 0.0, 0.1),
    "ee_pos": _Spec(np.float64, (3,), -5.0, 5.0),
    "stages": _Spec(np.bool_, (len(STAGE_NAMES),)),
    "actions": _Spec(np.float32, ("action_dim",), -1.0, 1.0),
    "observations": _Spec(np.float32, ("obs_dim",), -1e4, 1e4),
}
_OBJECT_ARRAYS: dict[str, _Spec] = {
    "object_pos": _Spec(np.float64, (3,), -5.0, 5.0),
    "object_quat": _Spec(np.float64, (4,), -1.0, 1.0),  # and unit norm
}
# Keys that save() adds to the metadata to describe the file; load() removes them again.
_FILE_KEYS = ("format", "schema_version", "obs_dim", "objects", "stage_names", "action_type")


class DemonstrationFormatError(FileFormatError):
    """A demonstration file or array does not follow the schema; the message says what is wrong.

    A ``ValueError`` (through :class:`gym_coffee._io.FileFormatError`)."""


def _shape_str(trailing: tuple[int | str, ...], lead: str = "n_steps") -> str:
    dims = [lead, *(str(d) for d in trailing)]
    return "(" + ", ".join(dims) + ("," if len(dims) == 1 else "") + ")"


def _resolve(trailing: tuple[int | str, ...], sizes: Mapping[str, int]) -> tuple[int | str, ...]:
    return tuple(sizes.get(d, d) if isinstance(d, str) else d for d in trailing)


def _first_bad(mask: NDArray[np.bool_]) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(mask)[0])


def _as_step_array(
    name: str,
    value: Any,
    spec: _Spec,
    trailing: tuple[int | str, ...],
    n_steps: int | None,
    lead: str | None = None,
    lengths: NDArray[np.int64] | None = None,
) -> NDArray[Any]:
    """Convert ``value`` to the spec's dtype; check shape ``(n_steps, *trailing)`` (a ``str`` in
    ``trailing`` matches any size), finiteness and range. With ``lengths`` (rows of concatenated
    demonstrations) a message about a value also names its demonstration and step."""
    arr = np.asarray(value)
    dtype = spec.dtype
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
    ok = arr.ndim == 1 + len(trailing) and all(
        isinstance(want, str) or got == want
        for got, want in zip(arr.shape[1:], trailing, strict=True)
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
        bad = _first_bad(~np.isfinite(arr))
        what = "NaN" if np.isnan(arr[bad]) else "inf"
        raise DemonstrationFormatError(
            f"array {name!r} contains {what} (first at index {bad}){_where(bad[0], lengths)}"
        )
    if arr.dtype.kind in "iuf" and (spec.low > -math.inf or spec.high < math.inf):
        # float32 rounding of the env's (float32) bounds: allow one part in 1e6
        slack = 1e-6 * max(1.0, abs(spec.low), abs(spec.high))
        outside = (arr < spec.low - slack) | (arr > spec.high + slack)
        if outside.any():
            bad = _first_bad(outside)
            raise DemonstrationFormatError(
                f"array {name!r} has a value outside [{spec.low:g}, {spec.high:g}]: "
                f"{arr[bad].item()!r} at index {bad}{_where(bad[0], lengths)}"
            )
    return np.ascontiguousarray(arr, dtype=dtype)


def _check_unit_quaternions(name: str, quat: NDArray[np.float64]) -> None:
    err = np.abs(np.linalg.norm(quat, axis=-1) - 1.0)
    if quat.size and (err > _QUAT_NORM_TOL).any():
        row = int(np.argmax(err > _QUAT_NORM_TOL))
        raise DemonstrationFormatError(
            f"array {name!r} row {row} is not a unit quaternion (norm "
            f"{np.linalg.norm(quat[row]):.6g}); expected (x, y, z, w) with norm 1"
        )


def _check_time(time: NDArray[np.float64]) -> None:
    steps = np.diff(time)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0))
        raise DemonstrationFormatError(
            f"array 'time' does not increase at step {i + 1} ({time[i]!r} -> {time[i + 1]!r}); "
            "expected strictly increasing seconds since reset"
        )


def _check_action_type(action_type: Any) -> str:
    if not isinstance(action_type, str) or action_type not in ACTION_DIMS:
        raise DemonstrationFormatError(
            f"action_type is {action_type!r}; expected one of {sorted(ACTION_DIMS)}"
        )
    return action_type


@dataclass(eq=False)
class Demonstration:
    """One demonstration: an episode as per-step arrays of length ``n_steps``.

    Row ``t`` is the state before action ``t`` (row 0 = after ``reset``; last row = final state).
    Arrays are converted to the dtypes below and checked on construction (shapes, finite, within
    the env's observation bounds, unit quaternions, increasing time).

    Attributes:
        time: ``(n_steps,)`` float64, seconds since reset (the observation's ``time``), increasing.
        joint_pos: ``(n_steps, 7)`` float64, arm joint positions (rad).
        gripper: ``(n_steps,)`` float64, finger opening (m).
        ee_pos: ``(n_steps, 3)`` float64, end-effector (grasp point) position, world frame (m).
        object_pos: name -> ``(n_steps, 3)`` float64, object positions, world frame; keys
            ``"cup"`` and ``"machine"``.
        object_quat: name -> ``(n_steps, 4)`` float64, object orientations as unit quaternions
            ``(x, y, z, w)``; same keys as ``object_pos``.
        stages: ``(n_steps, 3)`` bool, stage flags ``STAGE_NAMES`` in that state.
        actions: ``(n_steps, ACTION_DIMS[action_type])`` float32 in [-1, 1], the demonstrator's
            action in that state (the last row's action was not applied).
        observations: ``(n_steps, obs_dim)`` float32, the env's observation in that state.
        seed: the ``reset(seed=...)`` that produced the layout.
        success: whether the episode ended with ``is_success``.
        action_type: the env's action mode of ``actions``: ``"joint"`` (8-D, default), ``"ee"``
            (4-D) or ``"ee_rot"`` (7-D); see :data:`ACTION_DIMS`.
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
    action_type: str = "joint"

    def __post_init__(self) -> None:
        t = np.asarray(self.time)
        if t.ndim != 1 or t.shape[0] < 1:
            raise DemonstrationFormatError(
                f"array 'time' has shape {t.shape}; expected (n_steps,) with n_steps >= 1"
            )
        n = t.shape[0]
        self.action_type = _check_action_type(self.action_type)
        sizes = {"action_dim": ACTION_DIMS[self.action_type]}
        for name, spec in _STEP_ARRAYS.items():
            trailing = _resolve(spec.trailing, sizes)
            setattr(self, name, _as_step_array(name, getattr(self, name), spec, trailing, n))
        _check_time(self.time)
        if set(self.object_pos) != set(self.object_quat):
            raise DemonstrationFormatError(
                f"object_pos has objects {sorted(self.object_pos)} but object_quat has "
                f"{sorted(self.object_quat)}; they must name the same objects"
            )
        for attr, spec in _OBJECT_ARRAYS.items():
            objects = getattr(self, attr)
            checked = {
                _check_object_name(obj): _as_step_array(
                    f"{attr}.{obj}", value, spec, spec.trailing, n
                )
                for obj, value in objects.items()
            }
            setattr(self, attr, checked)
        for obj, quat in self.object_quat.items():
            _check_unit_quaternions(f"object_quat.{obj}", quat)
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise DemonstrationFormatError(f"seed must be an integer, got {self.seed!r}")
        if self.seed < 0:
            raise DemonstrationFormatError(f"seed must be >= 0 (a reset seed), got {self.seed}")
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

    @property
    def gripper_command(self) -> NDArray[np.float32]:
        """``(n_steps,)`` the commanded gripper opening in [-1, 1] (-1 closed, 1 open): the last
        action column in every action mode."""
        return self.actions[:, -1]

    def __len__(self) -> int:
        return self.n_steps

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Demonstration):
            return NotImplemented
        if (self.seed, self.success, self.action_type) != (
            other.seed,
            other.success,
            other.action_type,
        ):
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
            f"duration={self.time[-1] - self.time[0]:.2f}s, objects={sorted(self.object_pos)}, "
            f"action_type={self.action_type!r})"
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
    ``control_dt``, ``obs_slices`` (:func:`gym_coffee.teleop.record_teleop` writes ``teleop``
    instead of ``teacher``); :meth:`save` adds ``format``, ``schema_version``, ``obs_dim``,
    ``objects``, ``stage_names``, ``action_type`` to the file.

    Args:
        demonstrations: the demonstrations; all must have the same ``obs_dim``, objects and
            ``action_type``.
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
                for what, mine, theirs in (
                    ("obs_dim", d.obs_dim, first.obs_dim),
                    ("objects", sorted(d.object_pos), sorted(first.object_pos)),
                    ("action_type", d.action_type, first.action_type),
                ):
                    if mine != theirs:
                        raise DemonstrationFormatError(
                            f"demonstration {i} has {what} {mine!r}, demonstration 0 has "
                            f"{theirs!r}; all must match"
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
            f"env_id={self.metadata.get('env_id')!r}, action_type={self.action_type!r})"
        )

    @property
    def seeds(self) -> list[int]:
        """The ``reset`` seed of each demonstration."""
        return [d.seed for d in self._demos]

    @property
    def objects(self) -> list[str]:
        """Names of the recorded objects (sorted)."""
        return sorted(self._demos[0].object_pos) if self._demos else list(OBJECT_NAMES)

    @property
    def action_type(self) -> str:
        """The env action mode of the demonstrations' ``actions`` (``"joint"`` if empty)."""
        return self._demos[0].action_type if self._demos else "joint"

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
        out["metadata"] = np.array(json.dumps(self.file_metadata(), sort_keys=True))
        return out

    def file_metadata(self) -> dict[str, Any]:
        """``metadata`` plus the keys that describe the file (``format``, ``schema_version``,
        ``obs_dim``, ``objects``, ``stage_names``, ``action_type``), as plain JSON values.

        Raises:
            DemonstrationFormatError: the set is empty.
            TypeError: ``metadata`` is not JSON-serialisable.
        """
        if not self._demos:
            raise DemonstrationFormatError("cannot save an empty DemonstrationSet")
        meta = dict(self.metadata)
        meta.update(
            format=FORMAT_NAME,
            schema_version=SCHEMA_VERSION,
            obs_dim=self._demos[0].obs_dim,
            objects=self.objects,
            stage_names=list(STAGE_NAMES),
            action_type=self.action_type,
        )
        try:
            text = json.dumps(meta, allow_nan=False, default=_json_default)
        except (TypeError, ValueError) as exc:
            raise TypeError(f"metadata is not JSON-serialisable: {exc}") from exc
        result: dict[str, Any] = json.loads(text)
        return result

    def save(self, path: str | os.PathLike[str], overwrite: bool = False) -> Path:
        """Write the set to ONE ``.npz`` file (no pickle), atomically.

        The data go to a temporary file in the same folder, which then replaces ``path``: an
        interrupted or failed write never leaves a half-written or damaged ``path`` behind.

        Args:
            path: file to write; the name is used as given (no ``.npz`` is appended); a
                missing folder is created.
            overwrite: replace an existing file. Without it an existing ``path`` is an error.

        Returns:
            The path written.

        Raises:
            FileExistsError: ``path`` exists and ``overwrite`` is false.
            DemonstrationFormatError: the set is empty.
            TypeError: ``metadata`` is not JSON-serialisable.
        """
        path = Path(path)
        refuse_existing(path, overwrite)
        arrays = self.to_arrays()  # fails before anything touches the disk
        with atomic_output(path, overwrite=overwrite) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
        return path

    # -- loading --------------------------------------------------------------------------------
    @classmethod
    def load(
        cls,
        source: str | os.PathLike[str] | BinaryIO,
        *,
        max_bytes: int = DEFAULT_MAX_BYTES,
    ) -> DemonstrationSet:
        """Read and validate a file written by :meth:`save` (any supported schema version).

        Only the arrays of the schema are read; arrays it does not know are ignored unread. The
        file's size, each array's declared size (zip directory and ``.npy`` header) and each
        array's shape (against ``lengths`` and the metadata) are checked before its data are
        decompressed, and every value is checked (finite, in range) before a
        :class:`Demonstration` is built. Nothing is unpickled and nothing is written.

        Args:
            source: a path or a binary file object (``io.BytesIO``).
            max_bytes: the largest file, array and total of arrays read (bytes).

        Raises:
            FileNotFoundError: no such file.
            DemonstrationFormatError: the file is not an ``.npz`` file (a text file, truncated,
                corrupt), is larger than ``max_bytes``, is not a demonstration file, has an
                unsupported schema version, misses an array, has an array of the wrong shape or
                dtype, contains NaN/inf or values out of range, or its ``lengths`` do not add up.
                The message names the file and what is wrong.
        """
        if isinstance(source, (str, os.PathLike)):
            what = str(source)
            if not Path(source).is_file():
                raise FileNotFoundError(f"no demonstration file at {source}")
        else:
            what = "demonstration file"
        try:
            with NpzReader(source, max_bytes=max_bytes, what=what) as npz:
                arrays = _read_members(npz)
            return cls.from_arrays(arrays)
        except DemonstrationFormatError as exc:
            if str(exc).startswith(what):
                raise
            raise DemonstrationFormatError(f"{what}: {exc}") from None
        except FileFormatError as exc:
            raise DemonstrationFormatError(str(exc)) from None

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, NDArray[Any]]) -> DemonstrationSet:
        """Inverse of :meth:`to_arrays`, with full validation (see :meth:`load`)."""
        meta = _parse_metadata(np.asarray(arrays["metadata"]) if "metadata" in arrays else None)
        _check_missing(meta, arrays)
        lengths, seeds, success = _check_index_arrays(
            meta, arrays["lengths"], arrays["seeds"], arrays["success"]
        )
        total = int(lengths.sum())
        shapes = _expected_shapes(meta, total)
        checked: dict[str, NDArray[Any]] = {}
        for name, trailing in shapes.items():
            spec = _spec_of(name)
            arr = np.asarray(arrays[name])
            _check_shape(name, arr.shape, trailing, lengths)
            checked[name] = _as_step_array(
                name, arr, spec, trailing, total, lead=str(total), lengths=lengths
            )

        bounds = np.concatenate([[0], np.cumsum(lengths)])
        objects = meta["objects"]
        kwargs = []
        for i in range(len(lengths)):
            sl = slice(int(bounds[i]), int(bounds[i + 1]))
            kw: dict[str, Any] = {name: checked[name][sl] for name in _STEP_ARRAYS}
            for attr in _OBJECT_ARRAYS:
                kw[attr] = {obj: checked[f"{attr}.{obj}"][sl] for obj in objects}
            kwargs.append(kw)
        # The checks that need one demonstration at a time (increasing time, unit quaternions)
        # run in the constructor; a failure names the demonstration.
        demos = []
        for i, kw in enumerate(kwargs):
            try:
                demo = Demonstration(
                    **kw,
                    seed=int(seeds[i]),
                    success=bool(success[i]),
                    action_type=meta["action_type"],
                )
            except DemonstrationFormatError as exc:
                raise DemonstrationFormatError(f"demonstration {i}: {exc}") from None
            demos.append(demo)
        metadata = {k: v for k, v in meta.items() if k not in _FILE_KEYS}
        return cls(demos, metadata)


def _spec_of(name: str) -> _Spec:
    attr = name.split(".")[0]
    return _STEP_ARRAYS.get(attr) or _OBJECT_ARRAYS[attr]


def _required_members(meta: Mapping[str, Any]) -> list[str]:
    objects = meta["objects"]
    return [
        "lengths",
        "seeds",
        "success",
        *_STEP_ARRAYS,
        *(f"{attr}.{obj}" for attr in _OBJECT_ARRAYS for obj in objects),
    ]


def _check_missing(meta: Mapping[str, Any], present: Container[str]) -> None:
    missing = [k for k in _required_members(meta) if k not in present]
    if missing:
        raise DemonstrationFormatError(
            "missing array" + ("s " if len(missing) > 1 else " ") + ", ".join(map(repr, missing))
        )


def _expected_shapes(meta: Mapping[str, Any], total: int) -> dict[str, tuple[int | str, ...]]:
    """Trailing shape of every per-step array (``total`` rows each)."""
    sizes: dict[str, int] = {"action_dim": ACTION_DIMS[meta["action_type"]]}
    if "obs_dim" in meta:
        sizes["obs_dim"] = meta["obs_dim"]
    return {name: _resolve(_spec_of(name).trailing, sizes) for name in _required_members(meta)[3:]}


def _check_index_arrays(
    meta: Mapping[str, Any], lengths: Any, seeds: Any, success: Any
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
    lengths = np.asarray(lengths)
    if lengths.ndim != 1 or lengths.size == 0 or lengths.dtype.kind not in "iu":
        raise DemonstrationFormatError(
            f"array 'lengths' has shape {lengths.shape} and dtype {lengths.dtype}; expected "
            "(n_demos,) integers with n_demos >= 1"
        )
    if (lengths < 1).any():
        raise DemonstrationFormatError(
            f"array 'lengths' has entries < 1: {lengths.tolist()[:20]}; every demonstration "
            "has at least one step"
        )
    if (lengths > 1 << 40).any():
        raise DemonstrationFormatError(f"array 'lengths' has absurd entries: {lengths.max()}")
    lengths = lengths.astype(np.int64)
    n_demos = int(lengths.size)
    seeds = np.asarray(seeds)
    success = np.asarray(success)
    if seeds.shape != (n_demos,) or seeds.dtype.kind not in "iu":
        raise DemonstrationFormatError(
            f"array 'seeds' has shape {seeds.shape} and dtype {seeds.dtype}; expected "
            f"({n_demos},) integers (one per entry of 'lengths')"
        )
    if (seeds < 0).any() or (seeds.dtype.kind == "u" and (seeds > np.iinfo(np.int64).max).any()):
        raise DemonstrationFormatError(
            f"array 'seeds' has entries outside [0, 2**63): {seeds.tolist()[:20]}"
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
    return lengths, seeds.astype(np.int64), success


def _check_shape(
    name: str, shape: tuple[int, ...], trailing: tuple[int | str, ...], lengths: NDArray[np.int64]
) -> None:
    """Refuse a per-step array whose shape is not ``(sum(lengths), *trailing)``."""
    total = int(lengths.sum())
    want = (total, *trailing)
    if len(shape) == len(want) and all(
        isinstance(w, str) or got == w for got, w in zip(shape, want, strict=True)
    ):
        return
    expected = _shape_str(trailing, str(total))
    if len(shape) == len(want) and shape[0] != total:
        shown = lengths.tolist() if lengths.size <= 10 else f"{lengths.size} demonstrations"
        raise DemonstrationFormatError(
            f"array {name!r} has {shape[0]} rows but 'lengths' add up to {total} ({shown}); "
            f"expected shape {expected}"
        )
    raise DemonstrationFormatError(f"array {name!r} has shape {shape}; expected {expected}")


def _read_members(npz: NpzReader) -> dict[str, NDArray[Any]]:
    """Read the schema's arrays from ``npz``, checking each header's shape before its data."""
    shape, dtype = npz.header("metadata")
    if dtype.kind != "U" or shape != () or dtype.itemsize // 4 > MAX_METADATA_CHARS:
        raise DemonstrationFormatError(
            f"array 'metadata' has dtype {dtype} and shape {shape}; expected one unicode string "
            f"holding JSON of at most {MAX_METADATA_CHARS} characters"
        )
    arrays = {"metadata": npz.read("metadata")}
    meta = _parse_metadata(arrays["metadata"])
    _check_missing(meta, npz.members)
    for name, kinds, what in (
        ("lengths", "iu", "integers"),
        ("seeds", "iu", "integers"),
        ("success", "b", "bool"),
    ):
        shape, dtype = npz.header(name)
        if len(shape) != 1 or dtype.kind not in kinds:
            raise DemonstrationFormatError(
                f"array {name!r} has shape {shape} and dtype {dtype}; expected (n_demos,) {what}"
            )
        arrays[name] = npz.read(name)
    lengths, _seeds, _success = _check_index_arrays(
        meta, arrays["lengths"], arrays["seeds"], arrays["success"]
    )
    total = int(lengths.sum())
    for name, trailing in _expected_shapes(meta, total).items():
        shape, dtype = npz.header(name)
        _check_shape(name, shape, trailing, lengths)
        want = np.dtype(_spec_of(name).dtype)
        if dtype.kind != want.kind:  # a file holds the schema's kinds: bool flags, float values
            raise DemonstrationFormatError(f"array {name!r} has dtype {dtype}; expected {want}")
        arrays[name] = npz.read(name)
    return arrays


def _where(row: int, lengths: NDArray[np.int64] | None) -> str:
    """'; row r is demonstration i, step j' for a row of concatenated demonstrations."""
    if lengths is None:
        return ""
    demo = int(np.searchsorted(np.cumsum(lengths), row, side="right"))
    step = row - int(np.sum(lengths[:demo]))
    return f"; row {row} is demonstration {demo}, step {step}"


def _parse_metadata(raw: NDArray[Any] | None, where: str = "array 'metadata'") -> dict[str, Any]:
    """Parse and check the metadata JSON (strictly: no NaN/Infinity, no overflowing numbers);
    fills ``action_type`` for schema version 1. ``where`` names the JSON text in messages."""
    if raw is None:
        raise DemonstrationFormatError(
            "missing array 'metadata' (the JSON header); not a gym_coffee demonstration file"
        )
    if raw.dtype.kind != "U" or raw.size != 1:
        raise DemonstrationFormatError(
            f"{where} has dtype {raw.dtype} and shape {raw.shape}; expected one "
            "unicode string holding JSON"
        )
    try:
        meta = parse_json(str(raw.reshape(())), where=f"{where} is not valid JSON")
    except FileFormatError as exc:
        raise DemonstrationFormatError(str(exc)) from None
    if not isinstance(meta, dict):
        raise DemonstrationFormatError(f"{where} must hold a JSON object")
    if meta.get("format") != FORMAT_NAME:
        raise DemonstrationFormatError(
            f"metadata 'format' is {meta.get('format')!r}; expected {FORMAT_NAME!r} "
            "(not a gym_coffee demonstration file)"
        )
    version = meta.get("schema_version")
    if isinstance(version, bool) or version not in SUPPORTED_SCHEMA_VERSIONS:
        newer = isinstance(version, int) and version > max(SUPPORTED_SCHEMA_VERSIONS)
        hint = " (written by a newer gym_coffee? upgrade gym-coffee)" if newer else ""
        raise DemonstrationFormatError(
            f"schema version {version!r} is not supported; this gym_coffee reads "
            f"{list(SUPPORTED_SCHEMA_VERSIONS)}{hint}"
        )
    obs_dim = meta.get("obs_dim")
    if "obs_dim" in meta and not (
        isinstance(obs_dim, int) and not isinstance(obs_dim, bool) and 0 < obs_dim <= MAX_OBS_DIM
    ):
        raise DemonstrationFormatError(
            f"metadata 'obs_dim' is {obs_dim!r}; expected an integer in [1, {MAX_OBS_DIM}]"
        )
    objects = meta.get("objects")
    if (
        not isinstance(objects, list)
        or not objects
        or len(objects) > 100
        or not all(isinstance(o, str) and o.isidentifier() for o in objects)
        or len(set(objects)) != len(objects)
    ):
        raise DemonstrationFormatError(
            f"metadata 'objects' must be a non-empty list of distinct names, got {objects!r:.200}"
        )
    if meta.get("stage_names", list(STAGE_NAMES)) != list(STAGE_NAMES):
        raise DemonstrationFormatError(
            f"metadata 'stage_names' is {meta.get('stage_names')!r:.200}; expected "
            f"{list(STAGE_NAMES)}"
        )
    if version == 1:  # schema 1 had joint actions only
        meta["action_type"] = "joint"
    meta["action_type"] = _check_action_type(meta.get("action_type"))
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
    action_type = getattr(env.unwrapped, "action_type", "joint")
    if action_type != "joint":
        raise ValueError(
            f"env has action_type={action_type!r}; the scripted teacher acts in joint space: "
            "make the env with action_type='joint' (the default)"
        )
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

    metadata: dict[str, Any] = {
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
    action_type: str = "joint",
) -> Demonstration:
    """A :class:`Demonstration` from an episode's observations, infos (``reset``'s first) and
    actions (one per observation; the last one not applied)."""
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
        action_type=action_type,
    )
