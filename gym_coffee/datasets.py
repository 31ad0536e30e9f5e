"""Demonstrations in the dataset formats other learners read: robomimic-style HDF5 and Minari.

* :func:`export_robomimic` writes the layout of robomimic's datasets (``data/demo_i/obs/<key>``,
  ``next_obs/<key>``, ``actions``, ``rewards``, ``dones``, ``data.attrs["env_args"]`` with
  ``type`` 2 (a Gym env), per-demo ``num_samples``, a ``mask/train``/``mask/valid`` split) with
  h5py; :func:`import_robomimic` reads such a file back into a :class:`DemonstrationSet`, exactly.
* :func:`export_minari` writes a Minari dataset through its buffer API
  (``minari.create_dataset_from_buffers``; no jax), which ``minari.load_dataset`` opens.

Both need the ``datasets`` extra (``pip install "gym-coffee[datasets]"``: h5py, minari); they
are imported only when a function here is called.

A demonstration of ``n`` recorded states is ``n - 1`` transitions: ``obs`` are states ``0..n-2``,
``next_obs`` states ``1..n-1``, ``actions`` the actions applied in between (the demonstration's
last, unapplied action is kept in ``gym_coffee/final_action``). Rewards are the env's *sparse*
reward (``reward_type="sparse"``: 1 on the transition into success, else 0), the only reward the
demonstration file determines. ``dones`` is 1 on the last transition of every demonstration (as in
robomimic's datasets); Minari's ``terminations`` mark a successful end, ``truncations`` any other
end (the file does not record whether a failed episode was truncated or the cup fell).

Everything a :class:`Demonstration` holds that the standard layout has no place for -- the stage
flags, the object poses per step (the frames), the float64 robot state, seeds -- is stored as
well: in the HDF5 file under ``data/demo_i/gym_coffee/``, in the Minari dataset in each episode's
``infos``. See ``docs/human-demonstrations.md`` for the layouts.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import math
import os
import re
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gym_coffee._io import FileFormatError, atomic_output, parse_json, refuse_existing
from gym_coffee.demonstrations import (
    ACTION_DIMS,
    DEFAULT_MAX_BYTES,
    MAX_METADATA_CHARS,
    N_JOINTS,
    STAGE_NAMES,
    Demonstration,
    DemonstrationFormatError,
    DemonstrationSet,
)

__all__ = [
    "ROBOMIMIC_ENV_TYPE",
    "export_minari",
    "export_robomimic",
    "import_robomimic",
    "obs_keys",
    "sparse_rewards",
]

ROBOMIMIC_ENV_TYPE = 2
"""``env_args["type"]`` of a Gym environment in robomimic (``EnvType.GYM_TYPE``)."""
EXTRA = "datasets"
"""The optional dependency group that provides h5py and minari."""
_DEMO_NAME = re.compile(r"demo_(\d+)")
_MAX_DEMOS = 1_000_000
_MAX_KEY_CHARS = 64
"""Longest observation key name (``obs/<key>``)."""
_MAX_KEYS_BYTES = 1 << 16
"""Longest ``gym_coffee_obs_keys`` JSON text read (bytes)."""
_MAX_ATTRS_BYTES = 4 * MAX_METADATA_CHARS
"""Most bytes all attributes of one group may take in the file (``data``: the metadata JSON,
at most ``MAX_METADATA_CHARS``, ``env_args``, the observation keys); checked before any of them is
touched, since HDF5 decodes a whole attribute even to find it by name."""
_MAX_CHUNK_BYTES = 16 << 20
"""Largest chunk of a chunked dataset (bytes) when the dataset itself is smaller."""


def _require(module: str, what: str) -> ModuleType:
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ImportError(
            f"{what} needs the optional package {module.split('.')[0]!r}: "
            f'pip install "gym-coffee[{EXTRA}]"'
        ) from exc


# ------------------------------------------------------------------------------------------------
# Shared
# ------------------------------------------------------------------------------------------------


def obs_keys(demos: DemonstrationSet) -> list[tuple[str, int, int]]:
    """``(name, start, stop)`` of the observation parts, in order, covering the observation.

    From ``metadata["obs_slices"]`` (written by the recorders) when it describes the whole
    observation, else ``gym_coffee.env.OBS_SLICES`` when the size matches, else one part
    ``"flat"``.
    """
    obs_dim = demos[0].obs_dim
    slices = demos.metadata.get("obs_slices")
    if not _covers(slices, obs_dim):
        from gym_coffee.env import OBS_SLICES

        slices = {k: [v.start, v.stop] for k, v in OBS_SLICES.items()}
    if not _covers(slices, obs_dim):
        return [("flat", 0, obs_dim)]
    assert isinstance(slices, Mapping)
    return sorted(((str(k), int(v[0]), int(v[1])) for k, v in slices.items()), key=lambda p: p[1])


def _plain_name(name: Any) -> bool:
    """Whether ``name`` can be an observation key: an identifier of at most
    :data:`_MAX_KEY_CHARS` characters (it becomes an HDF5 path component, ``obs/<key>``)."""
    return isinstance(name, str) and name.isidentifier() and len(name) <= _MAX_KEY_CHARS


def _covers(slices: Any, obs_dim: int) -> bool:
    """Whether ``slices`` (name -> [start, stop]) tile ``range(obs_dim)`` with valid names."""
    if not isinstance(slices, Mapping) or not slices:
        return False
    parts = []
    for name, value in slices.items():
        if not (_plain_name(name) and name != "flat"):
            return False
        if not (
            isinstance(value, (list, tuple))
            and len(value) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
        ):
            return False
        parts.append((value[0], value[1]))
    parts.sort()
    edges = [0, *(b for _a, b in parts)]
    return all(a == e and b > a for (a, b), e in zip(parts, edges, strict=False)) and (
        edges[-1] == obs_dim
    )


def sparse_rewards(demo: Demonstration) -> NDArray[np.float64]:
    """``(n_steps - 1,)`` the env's sparse reward of each transition: 1 on the last one of a
    successful demonstration (the episode ends on success), else 0."""
    rewards = np.zeros(demo.n_steps - 1)
    if demo.success and rewards.size:
        rewards[-1] = 1.0
    return rewards


def _check_exportable(demos: Any) -> DemonstrationSet:
    if not isinstance(demos, DemonstrationSet):
        raise TypeError(f"demos must be a DemonstrationSet, got {type(demos).__name__}")
    if not len(demos):
        raise ValueError("demos is empty: nothing to export")
    for i, d in enumerate(demos):
        if d.n_steps < 2:
            raise ValueError(
                f"demonstration {i} has {d.n_steps} recorded state; a dataset sample is a "
                "transition, so every demonstration needs at least 2"
            )
    return demos


# ------------------------------------------------------------------------------------------------
# robomimic-style HDF5
# ------------------------------------------------------------------------------------------------


def export_robomimic(
    demos: DemonstrationSet,
    path: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    valid_fraction: float = 0.1,
    split_seed: int = 0,
) -> Path:
    """Write ``demos`` as a robomimic-style HDF5 file, atomically.

    Layout (``i`` = 0, 1, ...; ``T_i`` = ``n_steps - 1`` transitions of demonstration ``i``)::

        data                      attrs: total (sum of T_i), env_args (JSON: env_name, type=2,
                                         env_kwargs), gym_coffee_metadata (JSON)
        data/demo_i               attrs: num_samples (T_i), seed, success, action_type
        data/demo_i/obs/<key>     (T_i, size) float32   states 0..n-2, one key per observation part
        data/demo_i/next_obs/<key>(T_i, size) float32   states 1..n-1
        data/demo_i/actions       (T_i, action_dim) float32
        data/demo_i/rewards       (T_i,) float64   sparse: 1 on the transition into success
        data/demo_i/dones         (T_i,) int64     1 on the last transition
        data/demo_i/gym_coffee/   time, joint_pos, gripper, ee_pos (n, ...) float64,
                                  stages (n, 3) bool, object_pos/<name>, object_quat/<name>
                                  (n, 3|4) float64, final_action (action_dim,) float32
        mask/train, mask/valid    demo names (bytes), a seeded split (when valid_fraction > 0)

    There is no ``states`` dataset: robomimic uses it to reset a MuJoCo simulator to a recorded
    state, and a PyBullet episode cannot be restored from recorded arrays (contacts, the button's
    spring); replay a demonstration from its ``seed`` and actions instead.

    Args:
        demos: the demonstrations (each with at least 2 recorded states).
        path: the ``.hdf5`` file to write.
        overwrite: replace an existing file (CLI: ``--force``).
        valid_fraction: fraction of demonstrations in ``mask/valid`` (at least one when > 0 and
            there are 2 or more demonstrations); 0 writes no ``mask`` group.
        split_seed: seed of the train/valid shuffle.

    Returns:
        The path written.

    Raises:
        ImportError: h5py is not installed (the ``datasets`` extra).
        FileExistsError: ``path`` exists and ``overwrite`` is false.
        ValueError: empty set, a demonstration with fewer than 2 states, bad ``valid_fraction``.
    """
    path = Path(path)
    demos = _check_exportable(demos)
    if not 0.0 <= float(valid_fraction) < 1.0:
        raise ValueError(f"valid_fraction must be in [0, 1), got {valid_fraction!r}")
    refuse_existing(path, overwrite)
    h5py = _require("h5py", "export to robomimic HDF5")
    keys = obs_keys(demos)
    meta = demos.file_metadata()
    env_args = {
        "env_name": demos.metadata.get("env_id"),
        "type": ROBOMIMIC_ENV_TYPE,
        "env_kwargs": demos.metadata.get("env_kwargs", {}),
    }
    with atomic_output(path, overwrite=overwrite, suffix=".hdf5") as tmp:
        with h5py.File(tmp, "w") as f:
            data = f.create_group("data")
            total = 0
            for i, demo in enumerate(demos):
                total += _write_demo(data.create_group(f"demo_{i}"), demo, keys)
            data.attrs["total"] = total
            # Fixed-length byte strings: their size is in the attribute's type, so a reader can
            # check it before reading (a variable-length string's is not).
            data.attrs["env_args"] = np.bytes_(json.dumps(env_args, sort_keys=True))
            data.attrs["gym_coffee_metadata"] = np.bytes_(json.dumps(meta, sort_keys=True))
            data.attrs["gym_coffee_obs_keys"] = np.bytes_(json.dumps(keys))
            if valid_fraction > 0 and len(demos) >= 2:
                names = np.array([f"demo_{i}" for i in range(len(demos))])
                order = np.random.default_rng(split_seed).permutation(len(demos))
                n_valid = max(1, round(valid_fraction * len(demos)))
                for key, picked in (("valid", order[:n_valid]), ("train", order[n_valid:])):
                    f.create_dataset(f"mask/{key}", data=np.sort(names[picked]).astype("S"))
    return path


def _write_demo(group: Any, demo: Demonstration, keys: list[tuple[str, int, int]]) -> int:
    n = demo.n_steps - 1
    group.attrs["num_samples"] = n
    group.attrs["seed"] = demo.seed
    group.attrs["success"] = demo.success
    group.attrs["action_type"] = demo.action_type
    obs = demo.observations
    for name, start, stop in keys:
        group.create_dataset(f"obs/{name}", data=obs[:-1, start:stop])
        group.create_dataset(f"next_obs/{name}", data=obs[1:, start:stop])
    group.create_dataset("actions", data=demo.actions[:-1])
    group.create_dataset("rewards", data=sparse_rewards(demo))
    dones = np.zeros(n, dtype=np.int64)
    dones[-1] = 1
    group.create_dataset("dones", data=dones)
    extra = group.create_group("gym_coffee")
    for name, value in _extras(demo).items():
        extra.create_dataset(name, data=value)
    return n


def _extras(demo: Demonstration) -> dict[str, NDArray[Any]]:
    """The per-demonstration arrays the standard layout has no place for (HDF5 names)."""
    out: dict[str, NDArray[Any]] = {
        "time": demo.time,
        "joint_pos": demo.joint_pos,
        "gripper": demo.gripper,
        "ee_pos": demo.ee_pos,
        "stages": demo.stages,
        "final_action": demo.actions[-1],
    }
    for obj in sorted(demo.object_pos):
        out[f"object_pos/{obj}"] = demo.object_pos[obj]
        out[f"object_quat/{obj}"] = demo.object_quat[obj]
    return out


def import_robomimic(
    path: str | os.PathLike[str], *, max_bytes: int = DEFAULT_MAX_BYTES
) -> DemonstrationSet:
    """Read a file written by :func:`export_robomimic` back into a :class:`DemonstrationSet`.

    The arrays come back exactly (same values and dtypes). The file is checked like a
    demonstration file (:meth:`DemonstrationSet.load`): only the datasets of the layout are read,
    each one's shape and dtype are checked before its data are read, soft and external links (at
    any component of a path), external storage, virtual and compressed (filtered) datasets are
    refused, the size of every attribute is checked before it is read (the metadata JSON: at
    most ``MAX_METADATA_CHARS`` bytes), at most ``max_bytes`` are read, and every value is
    validated before anything is built.

    Raises:
        ImportError: h5py is not installed (the ``datasets`` extra).
        FileNotFoundError: no such file.
        DemonstrationFormatError: not an HDF5 file, not written by :func:`export_robomimic`, or
            anything in it breaks the schema; the message says what.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no robomimic file at {path}")
    h5py = _require("h5py", "import from robomimic HDF5")
    size = path.stat().st_size
    if size > max_bytes:
        raise DemonstrationFormatError(
            f"{path} has {size} bytes; the limit is {max_bytes} (raise max_bytes to read it)"
        )
    try:
        with open(path, "rb") as fh:
            is_hdf5 = fh.read(8) == b"\x89HDF\r\n\x1a\n"
        if not is_hdf5:
            raise DemonstrationFormatError("is not an HDF5 file")
        with h5py.File(path, "r") as f:
            reader = _H5Reader(h5py, max_bytes)
            arrays = _read_robomimic(f, reader)
        return DemonstrationSet.from_arrays(arrays)
    except (DemonstrationFormatError, FileFormatError) as exc:
        raise DemonstrationFormatError(f"{path}: {exc}") from None
    except (OSError, KeyError, RuntimeError, ValueError, TypeError) as exc:  # h5py on damage
        raise DemonstrationFormatError(
            f"{path} is not a readable HDF5 file (truncated or corrupt?): {exc}"
        ) from None


class _H5Reader:
    """Reads datasets only after checking link kind, storage, shape, dtype and the byte budget."""

    def __init__(self, h5py: ModuleType, max_bytes: int) -> None:
        self.h5py = h5py
        self.budget = int(max_bytes)

    def node(self, group: Any, name: str) -> Any:
        """The object at the relative path ``name`` under ``group``, one component at a time:
        every component must be a hard link (an object of this file), never a soft link (a
        path, which may lead anywhere in the file) or an external link (another file)."""
        parts = name.split("/")
        if not all(part and part != "." for part in parts):
            raise DemonstrationFormatError(f"{group.name}: {name!r} is not a relative path")
        node, where = group, group.name.rstrip("/")
        for i, part in enumerate(parts):
            where = f"{where}/{part}"
            if i and not isinstance(node, self.h5py.Group):
                raise DemonstrationFormatError(f"{node.name} is not a group")
            try:
                link = node.get(part, getlink=True)
            except TypeError:  # h5py: a user-defined link type
                raise DemonstrationFormatError(
                    f"{where} is a link of an unknown type; links are not followed"
                ) from None
            if link is None:
                raise DemonstrationFormatError(f"missing {where}")
            if not isinstance(link, self.h5py.HardLink):
                kind = type(link).__name__
                raise DemonstrationFormatError(
                    f"{where} is {'an' if kind[0] in 'AEIOU' else 'a'} {kind}; links to other "
                    "files or paths are not followed"
                )
            node = node[part]
        return node

    def group(self, group: Any, name: str) -> Any:
        node = self.node(group, name)
        if not isinstance(node, self.h5py.Group):
            raise DemonstrationFormatError(f"{node.name} is not a group")
        return node

    def read(
        self, group: Any, name: str, shape: tuple[int | None, ...], kinds: str = "biuf"
    ) -> NDArray[Any]:
        """Read dataset ``name``; ``shape`` may hold ``None`` for a free size."""
        ds = self.node(group, name)
        if not isinstance(ds, self.h5py.Dataset):
            raise DemonstrationFormatError(f"{ds.name} is not a dataset")
        if ds.is_virtual or ds.external:
            raise DemonstrationFormatError(f"{ds.name} keeps its data in other files; refused")
        if ds.id.get_create_plist().get_nfilters():
            raise DemonstrationFormatError(
                f"{ds.name} is compressed or filtered ({ds.compression or 'a filter'}); "
                "expected a plain dataset as export_robomimic writes (a filter could inflate "
                "without bound)"
            )
        if ds.dtype.kind not in kinds or ds.dtype.names is not None or ds.dtype.subdtype:
            raise DemonstrationFormatError(f"{ds.name} has dtype {ds.dtype}; expected numbers")
        got = tuple(ds.shape)
        if len(got) != len(shape) or any(
            w is not None and g != w for g, w in zip(got, shape, strict=True)
        ):
            want = tuple("*" if w is None else w for w in shape)
            raise DemonstrationFormatError(f"{ds.name} has shape {got}; expected {want}")
        n_bytes = math.prod(got) * ds.dtype.itemsize
        if n_bytes > self.budget:
            raise DemonstrationFormatError(
                f"{ds.name} ({n_bytes} bytes) would exceed the limit of bytes read"
            )
        if ds.chunks is not None:
            chunk_bytes = math.prod(ds.chunks) * ds.dtype.itemsize
            if chunk_bytes > max(n_bytes, _MAX_CHUNK_BYTES):
                raise DemonstrationFormatError(
                    f"{ds.name} has chunks of {chunk_bytes} bytes; expected at most "
                    f"{max(n_bytes, _MAX_CHUNK_BYTES)} (16 MiB, or the dataset's own size)"
                )
        self.budget -= n_bytes
        return np.asarray(ds[()])

    def _attr(self, node: Any, name: str, kinds: str, max_bytes: int, expected: str) -> Any:
        """The attribute's value, after checking its type, shape and size (from its header,
        with h5py's low-level API) against ``kinds`` and ``max_bytes``; ``None`` if missing."""
        self.check_attrs_size(node)
        if name not in node.attrs:
            return None
        attr = node.attrs.get_id(name)
        where = f"{node.name}.attrs[{name!r}]"
        dtype, shape = attr.dtype, attr.shape
        if dtype.kind not in kinds or dtype.names is not None or shape not in ((), (1,)):
            raise DemonstrationFormatError(
                f"{where} has type {dtype} and shape {shape}; expected {expected}"
            )
        n_bytes = max(dtype.itemsize, attr.get_storage_size())
        if n_bytes > min(max_bytes, self.budget):
            raise DemonstrationFormatError(
                f"{where} has {n_bytes} bytes; expected at most {min(max_bytes, self.budget)} "
                f"({expected})"
            )
        self.budget -= n_bytes
        return np.asarray(node.attrs[name]).reshape(-1)[0]

    def check_attrs_size(self, node: Any) -> None:
        """Refuse a node whose attributes take more than :data:`_MAX_ATTRS_BYTES` in the file,
        from the object's header information (no attribute is decoded)."""
        info = self.h5py.h5o.get_info(node.id)
        attrs = info.meta_size.attr
        n_bytes = int(info.hdr.space.total) + int(attrs.heap_size) + int(attrs.index_size)
        if n_bytes > _MAX_ATTRS_BYTES:
            raise DemonstrationFormatError(
                f"{node.name}.attrs take {n_bytes} bytes in the file; expected at most "
                f"{_MAX_ATTRS_BYTES} (e.g. 'gym_coffee_metadata' holds at most "
                f"{MAX_METADATA_CHARS} bytes of JSON); no attribute was read"
            )

    def text_attr(self, node: Any, name: str, max_bytes: int) -> str:
        """A fixed-length byte-string attribute of at most ``max_bytes``, its size checked
        before it is read."""
        value = self._attr(node, name, "S", max_bytes, "one fixed-length byte string")
        if value is None:
            raise DemonstrationFormatError(f"missing text attribute {node.name}.attrs[{name!r}]")
        return bytes(value).decode("utf-8", errors="replace")

    def int_attr(self, node: Any, name: str) -> int:
        """A scalar integer attribute."""
        value = self._attr(node, name, "iu", 8, "one integer")
        if value is None:
            raise DemonstrationFormatError(f"missing {node.name}.attrs[{name!r}]; expected int")
        return int(value)

    def bool_attr(self, node: Any, name: str, default: bool) -> bool:
        """A scalar boolean attribute (or 0/1); ``default`` if missing."""
        value = self._attr(node, name, "biu", 8, "one boolean")
        if value is None:
            return default
        if value not in (0, 1):
            raise DemonstrationFormatError(
                f"{node.name}.attrs[{name!r}] is {value!r}; expected one boolean"
            )
        return bool(value)


def _read_robomimic(f: Any, r: _H5Reader) -> dict[str, NDArray[Any]]:
    if f.get("data", getlink=True) is None:
        raise DemonstrationFormatError(
            "has no 'data' group: not a robomimic dataset written by "
            "gym_coffee.datasets.export_robomimic (only its files can be imported)"
        )
    data = r.group(f, "data")
    r.check_attrs_size(data)  # before any name lookup, which decodes a whole attribute
    if "gym_coffee_metadata" not in data.attrs:
        raise DemonstrationFormatError(
            "has no data.attrs['gym_coffee_metadata']: not written by "
            "gym_coffee.datasets.export_robomimic (only its files can be imported)"
        )
    # The metadata of a demonstration file: at most MAX_METADATA_CHARS (ASCII JSON) bytes.
    meta_text = r.text_attr(data, "gym_coffee_metadata", MAX_METADATA_CHARS)
    arrays: dict[str, NDArray[Any]] = {"metadata": np.array(meta_text)}
    # The header checks of a demonstration file (format, version, objects, action type).
    from gym_coffee.demonstrations import _parse_metadata

    meta = _parse_metadata(arrays["metadata"], where="data.attrs['gym_coffee_metadata']")
    obs_dim = meta.get("obs_dim")
    if obs_dim is None:
        raise DemonstrationFormatError(
            "data.attrs['gym_coffee_metadata'] has no 'obs_dim'; expected the observation size"
        )
    keys = _parse_obs_keys(r.text_attr(data, "gym_coffee_obs_keys", _MAX_KEYS_BYTES), obs_dim)
    if len(data) > _MAX_DEMOS:  # counted before the names are listed
        raise DemonstrationFormatError(f"data holds {len(data)} groups; expected <= {_MAX_DEMOS}")
    names = list(data.keys())
    if not all(_DEMO_NAME.fullmatch(n) for n in names):
        raise DemonstrationFormatError("data holds groups other than demo_<i>")
    names.sort(key=lambda n: int(n[5:]))
    if names != [f"demo_{i}" for i in range(len(names))] or not names:
        raise DemonstrationFormatError(f"data must hold demo_0 ... demo_<n-1>, has {names[:5]}")
    action_dim = ACTION_DIMS[meta["action_type"]]
    per_step: dict[str, list[NDArray[Any]]] = {}
    lengths, seeds, success = [], [], []
    for name in names:
        group = r.group(data, name)
        n = r.int_attr(group, "num_samples")
        if n < 1:
            raise DemonstrationFormatError(f"{group.name}.attrs['num_samples'] is {n}; need >= 1")
        lengths.append(n + 1)
        seeds.append(r.int_attr(group, "seed"))
        success.append(r.bool_attr(group, "success", default=False))
        obs = [r.read(group, f"obs/{k}", (n, stop - start)) for k, start, stop in keys]
        last = [r.read(group, f"next_obs/{k}", (n, stop - start))[-1:] for k, start, stop in keys]
        observations = np.concatenate([np.hstack(obs), np.hstack(last)])
        actions = r.read(group, "actions", (n, action_dim))
        final = r.read(group, "gym_coffee/final_action", (action_dim,))
        step = {
            "observations": observations,
            "actions": np.concatenate([actions, final[None].astype(actions.dtype)]),
        }
        for field, trailing in _EXTRA_SHAPES.items():
            step[field] = r.read(group, f"gym_coffee/{field}", (n + 1, *trailing))
        for obj in meta["objects"]:
            step[f"object_pos.{obj}"] = r.read(group, f"gym_coffee/object_pos/{obj}", (n + 1, 3))
            step[f"object_quat.{obj}"] = r.read(group, f"gym_coffee/object_quat/{obj}", (n + 1, 4))
        for key, value in step.items():
            per_step.setdefault(key, []).append(value)
    arrays.update({k: np.concatenate(v) for k, v in per_step.items()})
    arrays["lengths"] = np.array(lengths, dtype=np.int64)
    arrays["seeds"] = np.array(seeds, dtype=np.int64)
    arrays["success"] = np.array(success, dtype=np.bool_)
    return arrays


_EXTRA_SHAPES: dict[str, tuple[int, ...]] = {
    "time": (),
    "joint_pos": (N_JOINTS,),
    "gripper": (),
    "ee_pos": (3,),
    "stages": (len(STAGE_NAMES),),
}


def _parse_obs_keys(text: str, obs_dim: int) -> list[tuple[str, int, int]]:
    """The ``gym_coffee_obs_keys`` attribute: a JSON list of ``[name, start, stop]`` that tile
    the observation (or the one key ``["flat", 0, obs_dim]``); names are plain, short names."""
    where = "data.attrs['gym_coffee_obs_keys']"
    expected = (
        f"expected a JSON list of [name, start, stop] entries (names: identifiers of at most "
        f"{_MAX_KEY_CHARS} characters) that tile the observation's {obs_dim} values"
    )
    try:
        keys = parse_json(text, where=where)
    except FileFormatError as exc:
        raise DemonstrationFormatError(f"{exc}; {expected}") from None
    if not isinstance(keys, list) or not keys or len(keys) > obs_dim:
        raise DemonstrationFormatError(f"{where} is {text[:100]!r}; {expected}")
    out = []
    for key in keys:
        if not (
            isinstance(key, list)
            and len(key) == 3
            and all(isinstance(v, int) and not isinstance(v, bool) for v in key[1:])
        ):
            what = f"a list of {len(key)} items" if isinstance(key, list) else type(key).__name__
            raise DemonstrationFormatError(
                f"{where} has an entry ({what}) that is not [name, start, stop] with integer "
                f"start and stop; {expected}"
            )
        if not _plain_name(key[0]):
            raise DemonstrationFormatError(
                f"{where} has a key name {str(key[0])[:100]!r} that is not a plain name; {expected}"
            )
        out.append((key[0], key[1], key[2]))
    if out != [("flat", 0, obs_dim)] and (
        len({name for name, _, _ in out}) != len(out)
        or not _covers({name: [start, stop] for name, start, stop in out}, obs_dim)
    ):
        raise DemonstrationFormatError(
            f"{where} do not tile the observation: {text[:200]}; {expected} (each once)"
        )
    return sorted(out, key=lambda k: k[1])


# ------------------------------------------------------------------------------------------------
# Minari
# ------------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _minari_root(root: Path) -> Iterator[None]:
    """Point minari at ``root`` (``MINARI_DATASETS_PATH``) for the duration (not thread-safe)."""
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield
    finally:
        if old is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def export_minari(
    demos: DemonstrationSet,
    dataset_id: str,
    *,
    root: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
    author: str | None = None,
    author_email: str | None = None,
    code_permalink: str | None = None,
    description: str | None = None,
) -> Path:
    """Write ``demos`` as the Minari dataset ``dataset_id`` (e.g. ``"coffee/teleop-v0"``).

    Each demonstration is one episode: ``observations`` (all ``n`` states), ``actions``,
    ``rewards`` (sparse), ``terminations`` / ``truncations`` (``n - 1`` transitions), the
    episode's ``seed``, and ``infos`` with every per-step array of the demonstration (``time``,
    ``joint_pos``, ``gripper``, ``ee_pos``, ``stages/<stage>``, ``object_pos/<name>``,
    ``object_quat/<name>``), so stages and frames survive. The environment spec is stored when
    ``metadata["env_id"]`` is a registered ``gym_coffee`` id (``dataset.recover_environment()``
    then works); otherwise the spaces are taken from the data.

    The dataset is built in a temporary folder under the root and moved into place when complete;
    an existing dataset is replaced only with ``overwrite``.

    Args:
        demos: the demonstrations (each with at least 2 recorded states).
        dataset_id: Minari id ``(namespace/)name-v<version>``.
        root: the Minari datasets folder; default ``$MINARI_DATASETS_PATH`` or
            ``~/.minari/datasets`` (minari's own default).
        overwrite: replace an existing dataset of that id (CLI: ``--force``).
        author, author_email, code_permalink, description: Minari's dataset metadata.

    Returns:
        The dataset's folder.

    Raises:
        ImportError: minari is not installed (the ``datasets`` extra).
        FileExistsError: the dataset exists and ``overwrite`` is false.
        ValueError: malformed ``dataset_id``, empty set, a demonstration with fewer than 2
            states, or data that do not fit the env's spaces.
    """
    demos = _check_exportable(demos)
    minari = _require("minari", "export to Minari")
    from minari.data_collector.episode_buffer import EpisodeBuffer
    from minari.dataset.minari_dataset import parse_dataset_id
    from minari.storage import get_dataset_path

    try:
        namespace = parse_dataset_id(dataset_id)[0]
    except ValueError as exc:
        raise ValueError(f"dataset_id: {exc}") from None
    root = Path(get_dataset_path() if root is None else root)
    final = root / dataset_id
    refuse_existing(final, overwrite)
    env_spec, obs_space, act_space = _minari_spaces(demos)
    buffers = []
    for i, d in enumerate(demos):
        last = np.arange(d.n_steps - 1) == d.n_steps - 2
        buffers.append(
            EpisodeBuffer(
                id=i,
                seed=d.seed,
                observations=d.observations,
                actions=d.actions[:-1],
                rewards=sparse_rewards(d),
                terminations=last & d.success,
                truncations=last & (not d.success),
                infos=_infos(d),
            )
        )
    root.mkdir(parents=True, exist_ok=True)
    tmp_root = Path(tempfile.mkdtemp(prefix=".gym_coffee-export-", dir=root))
    try:
        with _minari_root(tmp_root), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"`(code_permalink|author|author_email)`")
            warnings.filterwarnings("ignore", message=r"`eval_env` is set to None")
            warnings.filterwarnings("ignore", message=r"env_spec is None")
            minari.create_dataset_from_buffers(
                dataset_id,
                buffers,
                env=env_spec,
                algorithm_name=_who(demos),
                author=author,
                author_email=author_email,
                code_permalink=code_permalink,
                action_space=act_space,
                observation_space=obs_space,
                description=description or _describe(demos),
            )
        if namespace is not None:
            with _minari_root(root):
                from minari.namespace import create_namespace, list_local_namespaces

                if namespace not in list_local_namespaces():
                    create_namespace(namespace)
        final.parent.mkdir(parents=True, exist_ok=True)
        if os.path.lexists(final):  # a symlink, even a dangling one, is moved away itself
            refuse_existing(final, overwrite)
            os.replace(final, tmp_root / ".replaced")
        os.replace(tmp_root / dataset_id, final)
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
    return final


def _who(demos: DemonstrationSet) -> str:
    meta = demos.metadata
    if isinstance(meta.get("teleop"), Mapping):
        return f"human teleoperation ({meta['teleop'].get('device', 'unknown device')})"
    teacher = meta.get("teacher")
    if isinstance(teacher, Mapping) and isinstance(teacher.get("class"), str):
        return str(teacher["class"])
    return "gym_coffee demonstrations"


def _describe(demos: DemonstrationSet) -> str:
    return (
        f"{len(demos)} demonstrations of {demos.metadata.get('env_id') or 'the coffee task'} "
        f"({demos.action_type} actions), exported by gym_coffee.datasets; infos hold the stage "
        "flags and object poses per step."
    )


def _infos(demo: Demonstration) -> dict[str, Any]:
    return {
        "time": demo.time,
        "joint_pos": demo.joint_pos,
        "gripper": demo.gripper,
        "ee_pos": demo.ee_pos,
        "stages": {name: demo.stages[:, j] for j, name in enumerate(STAGE_NAMES)},
        "object_pos": dict(demo.object_pos),
        "object_quat": dict(demo.object_quat),
    }


def _minari_spaces(demos: DemonstrationSet) -> tuple[Any, Any, Any]:
    """(env spec or None, observation space, action space) for the dataset."""
    import gymnasium as gym
    from gymnasium import spaces

    obs_dim, act_dim = demos[0].obs_dim, ACTION_DIMS[demos.action_type]
    env_id = demos.metadata.get("env_id")
    if isinstance(env_id, str) and env_id.startswith("gym_coffee/") and env_id in gym.registry:
        kwargs = demos.metadata.get("env_kwargs") or {}
        if not isinstance(kwargs, Mapping):
            raise ValueError(f"metadata 'env_kwargs' is {kwargs!r}; expected a mapping")
        kwargs = {k: v for k, v in kwargs.items() if k != "render_mode"}  # never open a GUI
        spec = gym.spec(env_id)
        spec = gym.envs.registration.EnvSpec(
            id=spec.id,
            entry_point=spec.entry_point,
            max_episode_steps=spec.max_episode_steps,
            kwargs={**spec.kwargs, **kwargs},
        )
        env = gym.make(spec)
        try:
            obs_space, act_space = env.observation_space, env.action_space
        finally:
            env.close()
        if obs_space.shape != (obs_dim,) or act_space.shape != (act_dim,):
            raise ValueError(
                f"the demonstrations have observations of {obs_dim} and actions of {act_dim} "
                f"values, but {env_id} with {kwargs} has spaces {obs_space.shape} and "
                f"{act_space.shape}"
            )
        return spec, obs_space, act_space
    obs_space = spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
    act_space = spaces.Box(-1.0, 1.0, (act_dim,), np.float32)
    return None, obs_space, act_space
