"""The residual policy file: one ``.npz`` without pickles, read with bounded memory.

Members (each a ``.npy`` inside the zip; nothing else is read):

- ``metadata``: a JSON string: ``kind``/``format`` (:data:`RESIDUAL_POLICY_KIND`),
  ``schema_version``, ``algo``, ``hyperparameters`` (with ``policy_kwargs.net_arch``), ``scale``,
  ``gate``, ``residual_dims``, ``include_gate_obs``, ``obs_norm``, ``obs_dim``, ``action_dim``,
  ``param_names``, ``base`` (``{"embedded": true, "sha256", "kind"}`` or ``null``) and
  ``versions``;
- ``param/<name>``: the SB3 policy's weights as float32 arrays;
- ``space/obs_low``, ``space/obs_high`` (the agent observation), ``space/act_low``,
  ``space/act_high`` (the env action);
- ``obs_norm/mean``, ``obs_norm/var``: the frozen observation normalisation (optional);
- ``base_file``: the base GP policy's own file, as bytes (optional).

Reading (:func:`read_policy_file`, through :func:`lgp_policy._io.read_npz`) checks each
member's declared size in the zip directory and its ``.npy`` header before decompressing it,
reads only the members above (never pickles), validates every number of the metadata
(finite, in range) and checks the network's layer sizes against the stored weights' shapes
before any network is built. Nothing from the file is used as a path; nothing is written.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lgp_policy._io import (
    FileFormatError,
    MemberSpec,
    atomic_save_npz,
    parse_json,
    read_json_member,
    read_npz,
)
from lgp_policy.residual.gates import gate_from_config
from lgp_policy.residual.models import ACTIVATIONS, ALGOS, DEFAULT_HYPERPARAMETERS

__all__ = [
    "RESIDUAL_POLICY_KIND",
    "ResidualPolicyFormatError",
    "check_hyperparameters",
    "read_policy_file",
    "read_policy_kind",
    "write_policy_file",
]

RESIDUAL_POLICY_KIND = "lgp_policy.residual_policy"
"""Value of ``metadata["kind"]`` (and ``metadata["format"]``) in a residual policy file."""
SCHEMA_VERSION = 1
SUPPORTED_SCHEMA_VERSIONS = (1,)

MAX_METADATA_BYTES = 1 << 20
MAX_ARRAY_BYTES = 64 << 20
MAX_BASE_BYTES = 256 << 20
MAX_TOTAL_BYTES = 512 << 20
MAX_PARAMS = 256
MAX_OBS_DIM = 4096
MAX_ACTION_DIM = 256
MAX_LAYERS = 8
MAX_UNITS = 4096


class ResidualPolicyFormatError(FileFormatError):
    """A residual policy file is missing something, is too large or does not fit together."""


# ------------------------------------------------------------------------------------ writing
def write_policy_file(path: Path, arrays: Mapping[str, NDArray[Any]], *, force: bool) -> None:
    """Write ``arrays`` as one ``.npz`` atomically; an existing file is kept unless ``force``."""
    atomic_save_npz(path, arrays, force=force)


# ------------------------------------------------------------------------------------ reading
_SCHEMA = {
    "metadata": MemberSpec(dtype="U", ndim=0, max_bytes=MAX_METADATA_BYTES),
    "space/*": MemberSpec(dtype="f", ndim=1, max_bytes=MAX_ARRAY_BYTES),
    "obs_norm/*": MemberSpec(
        dtype="f", ndim=1, required=False, finite=True, max_bytes=MAX_ARRAY_BYTES
    ),
    "param/*": MemberSpec(dtype="f", finite=True, max_bytes=MAX_ARRAY_BYTES),
    "base_file": MemberSpec(dtype="u", ndim=1, required=False, max_bytes=MAX_BASE_BYTES),
}


def _metadata(raw: NDArray[Any], where: str) -> dict[str, Any]:
    meta = parse_json(str(raw), where=where, member="metadata")
    if not isinstance(meta, dict):
        raise ResidualPolicyFormatError(f"{where}: metadata must be a JSON object")
    return meta


def read_policy_kind(source: Path | io.BytesIO) -> Any:
    """The ``kind`` (or ``format``) in the JSON metadata of an ``.npz`` policy file; reads the
    ``metadata`` member only (size-checked).

    Raises:
        FileFormatError: not a policy file, or its metadata is not a JSON object (the file may be
            of either kind, so the error is the common one, not a residual policy's).
    """
    where = str(source) if isinstance(source, Path) else "<in-memory file>"
    meta = read_json_member(source, "metadata", max_bytes=MAX_METADATA_BYTES)
    if isinstance(source, io.BytesIO):
        source.seek(0)
    if not isinstance(meta, dict):
        raise FileFormatError(f"{where}: metadata must be a JSON object", path=where)
    return meta.get("kind", meta.get("format"))


def _int(value: Any, lo: int, hi: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and lo <= value <= hi


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _layer_lists(algo: str, net_arch: Any) -> dict[str, list[int]]:
    """``net_arch`` as named chains of hidden sizes, validated (SB3's list or dict forms)."""
    keys = ("pi", "vf") if algo == "ppo" else ("pi", "qf")
    if isinstance(net_arch, list):
        chains = dict.fromkeys(keys, net_arch)
    elif isinstance(net_arch, dict) and set(net_arch) <= set(keys) and net_arch:
        chains = {k: net_arch.get(k, []) for k in keys}
    else:
        raise ValueError(f"net_arch must be a list of layer sizes or a dict with {keys}")
    for key, sizes in chains.items():
        if not (isinstance(sizes, list) and len(sizes) <= MAX_LAYERS) or not all(
            _int(h, 1, MAX_UNITS) for h in sizes
        ):
            raise ValueError(
                f"net_arch[{key!r}] must be at most {MAX_LAYERS} layer sizes in "
                f"[1, {MAX_UNITS}], got {sizes!r}"
            )
    return chains


def check_hyperparameters(algo: str, hp: Any) -> None:
    """Raise ValueError unless ``hp`` is a valid hyperparameter dict for ``algo``: known keys,
    finite numbers in range, a bounded ``net_arch`` and a known activation."""
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    if not isinstance(hp, dict):
        raise ValueError("hyperparameters must be an object")
    known = set(DEFAULT_HYPERPARAMETERS[algo])
    unknown = set(hp) - known
    if unknown:
        raise ValueError(f"unknown {algo} hyperparameters {sorted(unknown)}")
    for key, value in hp.items():
        if key == "policy_kwargs":
            continue
        if key == "ent_coef" and (value == "auto" or (_number(value) and value >= 0)):
            continue
        if not _number(value) or value < 0:
            raise ValueError(f"hyperparameter {key!r} must be a finite number >= 0, got {value!r}")
    if "buffer_size" in hp and not _int(hp["buffer_size"], 1, 10_000_000):
        raise ValueError(f"buffer_size must be an int in [1, 10000000], got {hp['buffer_size']!r}")
    for key in ("batch_size", "n_steps", "n_epochs", "train_freq", "gradient_steps"):
        if key in hp and not _int(hp[key], 1, 1_000_000):
            raise ValueError(f"{key} must be an int in [1, 1000000], got {hp[key]!r}")
    pk = hp.get("policy_kwargs", {})
    if not isinstance(pk, dict):
        raise ValueError("policy_kwargs must be an object")
    allowed = {"net_arch", "activation_fn"} | ({"log_std_init"} if algo == "ppo" else set())
    if set(pk) - allowed:
        raise ValueError(f"unknown policy_kwargs {sorted(set(pk) - allowed)}")
    if "net_arch" in pk:
        _layer_lists(algo, pk["net_arch"])
    if "activation_fn" in pk and pk["activation_fn"] not in ACTIVATIONS:
        raise ValueError(f"activation_fn must be one of {ACTIVATIONS}, got {pk['activation_fn']!r}")
    if "log_std_init" in pk and not (_number(pk["log_std_init"]) and abs(pk["log_std_init"]) < 20):
        raise ValueError(f"log_std_init must be a finite number, got {pk['log_std_init']!r}")


_REQUIRED_META: dict[str, type | tuple[type, ...]] = {
    "kind": str,
    "schema_version": int,
    "algo": str,
    "hyperparameters": dict,
    "scale": (int, float),
    "gate": dict,
    "residual_dims": list,
    "include_gate_obs": bool,
    "obs_dim": int,
    "action_dim": int,
}


def _check_metadata(meta: dict[str, Any], arrays: Mapping[str, NDArray[Any]], where: str) -> None:
    def fail(msg: str) -> ResidualPolicyFormatError:
        return ResidualPolicyFormatError(f"{where}: {msg}")

    if meta.get("kind") != RESIDUAL_POLICY_KIND:
        raise fail(
            f"kind is {meta.get('kind')!r}, expected {RESIDUAL_POLICY_KIND!r} (use "
            f"load_any_policy for other policy files)"
        )
    for key, typ in _REQUIRED_META.items():
        if key not in meta:
            raise fail(f"metadata lacks {key!r}")
        if not isinstance(meta[key], typ) or (typ is int and isinstance(meta[key], bool)):
            raise fail(f"metadata {key!r} has the wrong type ({type(meta[key]).__name__})")
    if meta["schema_version"] not in SUPPORTED_SCHEMA_VERSIONS:
        raise fail(
            f"schema version {meta['schema_version']} is not supported (this version reads "
            f"{SUPPORTED_SCHEMA_VERSIONS}); upgrade gym-coffee"
        )
    if meta["algo"] not in ALGOS:
        raise fail(f"algo {meta['algo']!r} is not one of {ALGOS}")
    if not _int(meta["obs_dim"], 1, MAX_OBS_DIM):
        raise fail(f"obs_dim must be in [1, {MAX_OBS_DIM}], got {meta['obs_dim']}")
    if not _int(meta["action_dim"], 1, MAX_ACTION_DIM):
        raise fail(f"action_dim must be in [1, {MAX_ACTION_DIM}], got {meta['action_dim']}")
    if not (_number(meta["scale"]) and 0 < meta["scale"] <= 2):
        raise fail(f"scale must be a finite number in (0, 2], got {meta['scale']}")
    dims = meta["residual_dims"]
    if (
        not dims
        or not all(_int(d, 0, meta["action_dim"] - 1) for d in dims)
        or len(set(dims)) != len(dims)
    ):
        raise fail(f"residual_dims {dims} must index the {meta['action_dim']} action entries")
    try:
        check_hyperparameters(meta["algo"], meta["hyperparameters"])
        gate_from_config(meta["gate"])
    except (TypeError, ValueError) as exc:
        raise fail(f"bad settings: {exc}") from exc
    norm = meta.get("obs_norm")
    if norm is not None and not (
        isinstance(norm, dict)
        and _number(norm.get("epsilon"))
        and 0 < norm["epsilon"] <= 1
        and _number(norm.get("clip_obs"))
        and norm["clip_obs"] > 0
    ):
        raise fail(f"obs_norm must be null or {{epsilon in (0, 1], clip_obs > 0}}, got {norm!r}")
    base = meta.get("base")
    if base is not None and not (
        isinstance(base, dict)
        and base.get("embedded") is True
        and isinstance(base.get("sha256"), str)
        and re.fullmatch(r"[0-9a-f]{64}", base["sha256"])
    ):
        raise fail("base must be null or {embedded: true, sha256: <64 hex digits>}")

    agent_dim = meta["obs_dim"] + meta["action_dim"] + int(meta["include_gate_obs"])
    shapes = {
        "space/obs_low": (agent_dim,),
        "space/obs_high": (agent_dim,),
        "space/act_low": (meta["action_dim"],),
        "space/act_high": (meta["action_dim"],),
    }
    if norm is not None:
        shapes.update({"obs_norm/mean": (agent_dim,), "obs_norm/var": (agent_dim,)})
    for key, shape in shapes.items():
        if key not in arrays:
            raise fail(f"array {key!r} is missing")
        value = arrays[key]
        if value.shape != shape or value.dtype.kind != "f":
            raise fail(f"array {key!r} must be float {shape}, got {value.dtype} {value.shape}")
        if np.any(np.isnan(value)):
            raise fail(f"array {key!r} has NaN")
    for lo, hi in (("space/obs_low", "space/obs_high"), ("space/act_low", "space/act_high")):
        if np.any(arrays[lo] > arrays[hi]):
            raise fail(f"{lo} exceeds {hi}")
    if norm is not None:
        mean, var = arrays["obs_norm/mean"], arrays["obs_norm/var"]
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0)):
            raise fail("observation statistics must be finite (and variances >= 0)")
    if base is not None and "base_file" not in arrays:
        raise fail("the embedded base policy ('base_file') is missing")
    if "base_file" in arrays and (
        arrays["base_file"].dtype != np.uint8 or arrays["base_file"].ndim != 1
    ):
        raise fail("'base_file' must be a 1-D uint8 array")

    params = {k[len("param/") :]: v for k, v in arrays.items() if k.startswith("param/")}
    for name, value in params.items():
        if value.dtype != np.float32 or value.ndim > 2:
            raise fail(f"weight {name!r} must be a float32 vector or matrix, got {value.dtype}")
        if not np.all(np.isfinite(value)):
            raise fail(f"weight {name!r} has NaN or infinity")
    # The network's hidden layers must be backed by stored weight matrices, checked on the
    # arrays' shapes before any network is built: a file declaring net_arch [8000, 8000] next
    # to small weights is refused without allocating the network.
    weight_shapes = {v.shape for v in params.values() if v.ndim == 2}
    net_arch = (
        meta["hyperparameters"]
        .get("policy_kwargs", {})
        .get("net_arch", DEFAULT_HYPERPARAMETERS[meta["algo"]]["policy_kwargs"]["net_arch"])
    )
    inputs = {
        "pi": agent_dim,
        "vf": agent_dim,
        "qf": agent_dim + len(dims),
    }
    for key, sizes in _layer_lists(meta["algo"], net_arch).items():
        previous = inputs[key]
        for size in sizes:
            if (size, previous) not in weight_shapes:
                raise fail(
                    f"net_arch {net_arch!r} does not match the stored weights: no {key!r} layer "
                    f"of shape ({size}, {previous})"
                )
            previous = size


def read_policy_file(source: Path | io.BytesIO) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(metadata, arrays)`` of a residual policy file, fully validated (see module doc).

    Raises:
        FileNotFoundError: no such file.
        ResidualPolicyFormatError: naming what is missing, malformed, too large or inconsistent.
    """
    where = str(source) if isinstance(source, Path) else "<in-memory file>"
    try:
        arrays = read_npz(
            source,
            schema=_SCHEMA,
            max_member_bytes=MAX_BASE_BYTES,
            max_total_bytes=MAX_TOTAL_BYTES,
            max_entries=MAX_PARAMS + 16,
        )
        meta = _metadata(arrays["metadata"], where)
    except FileFormatError as exc:
        if isinstance(exc, ResidualPolicyFormatError):
            raise
        raise ResidualPolicyFormatError(str(exc)) from exc
    _check_metadata(meta, arrays, where)
    return meta, arrays
