"""The fine-tuned policy: a base policy plus a learned residual, and its file."""

from __future__ import annotations

import hashlib
import io
import json
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from lgp_policy.residual.files import (
    RESIDUAL_POLICY_KIND,
    SCHEMA_VERSION,
    ResidualPolicyFormatError,
    read_policy_file,
    read_policy_kind,
    write_policy_file,
)
from lgp_policy.residual.gates import PhaseGate, as_batch, gate_from_config
from lgp_policy.residual.models import (
    ALGOS,
    SpacesEnv,
    build_model,
    policy_arrays,
    require_rl,
)
from lgp_policy.residual.wrapper import check_residual_dims, check_scale, compose

__all__ = ["ObsNormalizer", "ResidualPolicy", "load_any_policy"]


@dataclass
class ObsNormalizer:
    """SB3 ``VecNormalize``'s observation normalisation, frozen as arrays:
    ``clip((x - mean) / sqrt(var + epsilon), -clip_obs, clip_obs)``."""

    mean: NDArray[np.float64]
    var: NDArray[np.float64]
    epsilon: float = 1e-8
    clip_obs: float = 10.0

    def __call__(self, x: NDArray[Any]) -> NDArray[np.float32]:
        z = (np.asarray(x, np.float64) - self.mean) / np.sqrt(self.var + self.epsilon)
        return np.clip(z, -self.clip_obs, self.clip_obs).astype(np.float32)


class ResidualPolicy:
    """A base policy plus a learned residual: ``clip(base + scale * gate * residual)``.

    Satisfies SB3's ``PolicyPredictor`` protocol, for one ``(obs_dim,)`` or a batch
    ``(n_envs, obs_dim)`` of env observations, so it works in
    ``stable_baselines3.common.evaluation.evaluate_policy``, ``gym-coffee evaluate`` and
    vectorised envs. The base is asked deterministically and its recurrent ``state`` is passed
    through; ``deterministic`` applies to the residual (deployment: ``True``).

    Arguments:
        base: the base ``PolicyPredictor``.
        model: the SB3 algorithm (or policy) whose ``predict`` gives the residual from the agent
            observation ``[obs, base action, gate]``.
        scale, gate, residual_dims, include_gate_obs: as in
            :class:`~lgp_policy.residual.wrapper.ResidualWrapper` (the same as in training).
        action_space: the env's action space (for the clip; default ``Box(-1, 1)``).
        algo, hyperparameters: recorded in the file.
        base_path: the base policy's file, embedded into :meth:`save`.
        obs_normalizer: applied to the agent observation before the residual network (the
            training ``VecNormalize``'s statistics; saved with the policy).
    """

    def __init__(
        self,
        base: Any,
        model: Any,
        *,
        scale: float = 0.5,
        gate: Any = None,
        residual_dims: Sequence[int] | None = None,
        include_gate_obs: bool = True,
        action_space: spaces.Box | None = None,
        algo: str | None = None,
        hyperparameters: Mapping[str, Any] | None = None,
        base_path: str | os.PathLike[str] | None = None,
        obs_normalizer: Callable[[NDArray[Any]], NDArray[np.float32]] | None = None,
    ) -> None:
        self.base = base
        self.model = model
        self.obs_normalizer = obs_normalizer
        self.scale = check_scale(scale)
        self.gate = gate if gate is not None else PhaseGate()
        model_obs = getattr(model, "observation_space", None)
        model_act = getattr(model, "action_space", None)
        if action_space is None:
            if residual_dims is not None or model_act is None:
                raise ValueError("pass the env's action_space (needed with residual_dims)")
            action_space = spaces.Box(-1.0, 1.0, model_act.shape, np.float32)
        self.action_space = action_space
        act_dim = int(action_space.shape[0])
        self.residual_dims = check_residual_dims(residual_dims, act_dim)
        self.include_gate_obs = bool(include_gate_obs)
        if model_act is not None and model_act.shape != (self.residual_dims.size,):
            raise ValueError(
                f"the residual model acts on {model_act.shape} but residual_dims has "
                f"{self.residual_dims.size} entries"
            )
        self.obs_dim = (
            int(model_obs.shape[0]) - act_dim - int(self.include_gate_obs)
            if model_obs is not None
            else None
        )
        self.algo = algo
        self.hyperparameters = dict(hyperparameters or {})
        self.base_path = None if base_path is None else Path(base_path)
        self._low = action_space.low.astype(np.float32)
        self._high = action_space.high.astype(np.float32)

    # -- prediction --------------------------------------------------------------------------
    def agent_observation(
        self, observation: NDArray[Any], base_action: NDArray[Any]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """``([obs, base action, gate] (n, agent_obs_dim), gate (n,))`` for a batch."""
        obs, _ = as_batch(observation)
        gate = np.asarray(self.gate(obs, self.base), dtype=np.float32).reshape(-1)
        parts = [obs.astype(np.float32), np.clip(base_action, self._low, self._high)]
        if self.include_gate_obs:
            parts.append(gate[:, None])
        return np.concatenate(parts, axis=1).astype(np.float32), gate

    def predict(
        self,
        observation: NDArray[Any],
        state: tuple[NDArray[Any], ...] | None = None,
        episode_start: NDArray[Any] | None = None,
        deterministic: bool = False,
    ) -> tuple[NDArray[np.float32], tuple[NDArray[Any], ...] | None]:
        obs, single = as_batch(observation)
        if self.obs_dim is not None and obs.shape[1] != self.obs_dim:
            raise ValueError(
                f"observation has {obs.shape[1]} entries, the policy expects {self.obs_dim}"
            )
        base_action, state = self.base.predict(
            obs, state=state, episode_start=episode_start, deterministic=True
        )
        base_action = np.asarray(base_action, dtype=np.float32).reshape(obs.shape[0], -1)
        agent_obs, gate = self.agent_observation(obs, base_action)
        residual = np.zeros((obs.shape[0], self.residual_dims.size), np.float32)
        open_rows = gate > 0
        if np.any(open_rows):  # the residual network is only run where the gate is open
            net_obs = agent_obs[open_rows]
            if self.obs_normalizer is not None:
                net_obs = self.obs_normalizer(net_obs)
            res, _ = self.model.predict(net_obs, deterministic=deterministic)
            residual[open_rows] = np.asarray(res, dtype=np.float32).reshape(-1, residual.shape[1])
        applied = compose(
            base_action, gate, residual, self.scale, self.residual_dims, self._low, self._high
        )
        return (applied[0] if single else applied), state

    def phase(self, observation: NDArray[Any]) -> NDArray[np.float64]:
        """The gate's phase (so a residual policy can itself be a base)."""
        phase: NDArray[np.float64] = self.gate.phase(observation, self.base)
        return phase

    # -- file --------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str], *, force: bool = False) -> Path:
        """Write ONE ``.npz`` (no pickle): weights, spaces, the base policy's file, JSON
        metadata (:mod:`lgp_policy.residual.files`).

        The base policy's file (``base_path``) is embedded as bytes with its SHA-256. A base
        without a file is not saved: pass it to :meth:`load` again. Written atomically; an
        existing file is kept unless ``force=True``.
        """
        path = Path(path)
        if self.algo not in ALGOS:
            raise ValueError(f"cannot save: unknown algo {self.algo!r} (one of {ALGOS})")
        to_config = getattr(self.gate, "to_config", None)
        if not callable(to_config):
            raise TypeError(
                f"cannot save a gate of type {type(self.gate).__name__}: it has no to_config()"
            )
        model_obs = self.model.observation_space
        arrays: dict[str, NDArray[Any]] = {
            f"param/{k}": v for k, v in policy_arrays(self.model).items()
        }
        arrays["space/obs_low"] = model_obs.low.astype(np.float32)
        arrays["space/obs_high"] = model_obs.high.astype(np.float32)
        arrays["space/act_low"] = self._low
        arrays["space/act_high"] = self._high
        norm_cfg: dict[str, float] | None = None
        if self.obs_normalizer is not None:
            frozen = self.obs_normalizer
            freeze = getattr(frozen, "freeze", None)
            if callable(freeze):
                frozen = freeze()
            if not isinstance(frozen, ObsNormalizer):
                raise TypeError(
                    f"cannot save an observation normaliser of type {type(frozen).__name__}"
                )
            arrays["obs_norm/mean"] = np.asarray(frozen.mean, np.float64)
            arrays["obs_norm/var"] = np.asarray(frozen.var, np.float64)
            norm_cfg = {"epsilon": frozen.epsilon, "clip_obs": frozen.clip_obs}
        base_ref: dict[str, Any] | None = None
        if self.base_path is not None:
            raw = self.base_path.read_bytes()
            base_ref = {
                "embedded": True,
                "sha256": hashlib.sha256(raw).hexdigest(),
                "kind": read_policy_kind(io.BytesIO(raw)),
            }
            arrays["base_file"] = np.frombuffer(raw, dtype=np.uint8)
        meta = {
            "kind": RESIDUAL_POLICY_KIND,
            "format": RESIDUAL_POLICY_KIND,
            "schema_version": SCHEMA_VERSION,
            "algo": self.algo,
            "hyperparameters": self.hyperparameters,
            "scale": self.scale,
            "gate": to_config(),
            "residual_dims": self.residual_dims.tolist(),
            "include_gate_obs": self.include_gate_obs,
            "obs_norm": norm_cfg,
            "obs_dim": self.obs_dim,
            "action_dim": int(self._low.shape[0]),
            "param_names": sorted(k[len("param/") :] for k in arrays if k.startswith("param/")),
            "base": base_ref,
            "versions": _versions(),
        }
        arrays["metadata"] = np.array(json.dumps(meta, allow_nan=False))
        write_policy_file(path, arrays, force=force)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str] | io.BytesIO, *, base: Any = None) -> ResidualPolicy:
        """Rebuild a policy written by :meth:`save`.

        The file is read and validated first (:func:`lgp_policy.residual.files.read_policy_file`:
        known members, sizes, every number); then the SB3 policy network is built from its
        (checked) settings and the weights are copied in.

        Arguments:
            base: the base policy; by default the embedded GP policy (loaded from memory).

        Raises:
            ResidualPolicyFormatError: naming what is missing, malformed or inconsistent.
            ImportError: without stable-baselines3/torch (``pip install "gym-coffee[rl]"``).
        """
        source = path if isinstance(path, io.BytesIO) else Path(path)
        where = str(source) if isinstance(source, Path) else "<in-memory file>"
        meta, arrays = read_policy_file(source)
        _, torch = require_rl()
        obs_space = spaces.Box(arrays["space/obs_low"], arrays["space/obs_high"], dtype=np.float32)
        act_space = spaces.Box(arrays["space/act_low"], arrays["space/act_high"], dtype=np.float32)
        res_space = spaces.Box(-1.0, 1.0, (len(meta["residual_dims"]),), np.float32)
        # Prediction needs the policy network only: the training buffers are not allocated.
        hp: dict[str, Any] = {"policy_kwargs": meta["hyperparameters"].get("policy_kwargs", {})}
        if meta["algo"] in ("sac", "td3"):
            hp["buffer_size"] = 1
        else:
            hp.update(n_steps=2, batch_size=2)
        model = build_model(meta["algo"], SpacesEnv(obs_space, res_space), hp, seed=0)
        expected = model.policy.state_dict()
        stored = {k[len("param/") :]: v for k, v in arrays.items() if k.startswith("param/")}
        missing = sorted(set(expected) - set(stored))
        unexpected = sorted(set(stored) - set(expected))
        if missing or unexpected:
            raise ResidualPolicyFormatError(
                f"{where}: network weights do not match the {meta['algo']} model: "
                f"missing {missing[:5]}, unexpected {unexpected[:5]}"
            )
        for name, tensor in expected.items():
            if tuple(stored[name].shape) != tuple(tensor.shape):
                raise ResidualPolicyFormatError(
                    f"{where}: weight {name!r} has shape {stored[name].shape}, the model needs "
                    f"{tuple(tensor.shape)}"
                )
        model.policy.load_state_dict(
            {k: torch.as_tensor(stored[k], dtype=expected[k].dtype) for k in expected}
        )
        normalizer = None
        if meta.get("obs_norm") is not None:
            cfg = meta["obs_norm"]
            normalizer = ObsNormalizer(
                arrays["obs_norm/mean"].astype(np.float64),
                arrays["obs_norm/var"].astype(np.float64),
                float(cfg["epsilon"]),
                float(cfg["clip_obs"]),
            )
        if base is None:
            base = _embedded_base(where, meta, arrays)
        policy = cls(
            base,
            model,
            scale=meta["scale"],
            gate=gate_from_config(meta["gate"]),
            residual_dims=meta["residual_dims"],
            include_gate_obs=meta["include_gate_obs"],
            action_space=act_space,
            algo=meta["algo"],
            hyperparameters=meta["hyperparameters"],
            obs_normalizer=normalizer,
        )
        base_shape = getattr(getattr(base, "observation_space", None), "shape", None)
        if base_shape not in (None, (meta["obs_dim"],)):
            raise ResidualPolicyFormatError(
                f"{where}: the base policy observes {base_shape}, the residual was trained "
                f"on observations of size {meta['obs_dim']}"
            )
        return policy


def _embedded_base(where: str, meta: Mapping[str, Any], arrays: Mapping[str, Any]) -> Any:
    """The embedded GP policy, loaded from memory: nothing from the file is used as a path and
    nothing is written. Only a GP policy may be embedded (no nesting of residual policies)."""
    if meta.get("base") is None:
        raise ResidualPolicyFormatError(
            f"{where} was saved without its base policy (the base had no file); pass "
            f"ResidualPolicy.load(path, base=...)"
        )
    raw = arrays["base_file"].tobytes()
    if hashlib.sha256(raw).hexdigest() != meta["base"]["sha256"]:
        raise ResidualPolicyFormatError(f"{where}: the embedded base policy is corrupted")
    from lgp_policy.lfd.policy import GPDemonstrationPolicy, PolicyFileError

    try:
        return GPDemonstrationPolicy.load(io.BytesIO(raw))
    except (PolicyFileError, ValueError) as exc:
        raise ResidualPolicyFormatError(
            f"{where}: the embedded base policy is not a valid GP policy ({exc})"
        ) from exc


def _versions() -> dict[str, str]:
    import lgp_policy

    out = {"lgp_policy": lgp_policy.__version__, "numpy": np.__version__}
    try:
        sb3, torch = require_rl()
    except ImportError:
        return out
    out["stable_baselines3"] = sb3.__version__
    out["torch"] = torch.__version__
    return out


def load_any_policy(path: str | os.PathLike[str]) -> Any:
    """Open a GP policy file or a residual policy file, by the ``kind`` in its JSON metadata."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no policy file at {path}")
    if read_policy_kind(path) == RESIDUAL_POLICY_KIND:
        return ResidualPolicy.load(path)
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    return GPDemonstrationPolicy.load(path)
