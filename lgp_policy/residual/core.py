"""Residual reinforcement learning for the button press (the paper's future work, Sec. VI).

The paper's robot "was not able to press the tiny button and stopped a few millimeters in front of
it or [did not] press it deep enough" (Sec. IV). Here a learned residual corrects the demonstration
policy where it matters, and nowhere else:

    applied = clip(base + scale * gate * residual, low, high)

- ``base`` is any SB3 ``PolicyPredictor`` (``predict(obs, state, episode_start, deterministic)``),
  normally a :class:`~lgp_policy.lfd.policy.GPDemonstrationPolicy`; it is always asked
  deterministically.
- ``gate`` in ``[0, 1]`` confines the residual to the press phase. The default
  :class:`PhaseGate` is a function of the **phase** (normalised time) only: the base policy's own
  phase when it exposes ``phase(observation)``, else the observation's time entry divided by a
  fixed duration. The phase is what the time-indexed GP policy itself runs on, so the gate needs
  nothing the deployed policy lacks (no simulator stage flags, no privileged state), and
  :class:`ResidualPolicy` can compute it from the observation alone. The press is the last
  constrained interval of the machine frame (Fig. 4b, time steps 85-100 of 100); the gate stays
  open after the demonstrated duration ends, so the residual can finish a press the base stopped
  short of.
- ``residual`` is the action of an unmodified stable-baselines3 agent (SAC, TD3 or PPO) whose
  last actor layer is zero-initialised (:func:`zero_init_residual_actor`), so fine-tuning starts
  exactly at the base policy.

Only numpy and gymnasium are imported at module level: :class:`ResidualWrapper`, :class:`PhaseGate`,
:func:`load_any_policy` and :func:`evaluate_stages` work without the ``rl`` extra. Everything that
needs stable-baselines3 or torch imports them lazily and, when they are missing, raises an
:class:`ImportError` that says ``pip install "gym-coffee[rl]"``.

Files: a residual policy is ONE ``.npz`` written without pickle and read with
``allow_pickle=False``: the actor/critic weights as named float arrays (``param/<name>``), the
spaces as arrays (``space/...``), the base policy's file embedded as bytes (``base_file``) or
referenced by path and SHA-256, and a JSON string ``metadata`` (``kind``/``format``
``"lgp_policy.residual_policy"``, schema version, algorithm, hyperparameters, policy kwargs,
scale, gate, residual dimensions). Loading rebuilds the SB3 model from the JSON and copies the
arrays into it; every mismatch raises :class:`ResidualPolicyFormatError` naming what is wrong.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import math
import os
import tempfile
import time
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

__all__ = [
    "ALGOS",
    "DEFAULT_HYPERPARAMETERS",
    "RESIDUAL_POLICY_KIND",
    "RL_EXTRA_HINT",
    "ActuationNoiseWrapper",
    "FinetuneResult",
    "MachinePoseErrorWrapper",
    "ObsNormalizer",
    "PhaseGate",
    "ResidualPolicy",
    "ResidualPolicyFormatError",
    "ResidualWrapper",
    "TeacherBase",
    "evaluate_stages",
    "finetune",
    "gate_from_config",
    "gp_policy_kind",
    "load_any_policy",
    "register_policy_kind",
    "require_rl",
    "zero_init_residual_actor",
]

RESIDUAL_POLICY_KIND = "lgp_policy.residual_policy"
"""Value of ``metadata["kind"]`` (and ``metadata["format"]``) in a residual policy file."""
SCHEMA_VERSION = 1
SUPPORTED_SCHEMA_VERSIONS = (1,)
RL_EXTRA_HINT = 'pip install "gym-coffee[rl]"'
ALGOS = ("sac", "td3", "ppo")

STAGE_KEYS = ("cup_grasped", "cup_placed", "button_pressed", "is_success")
"""``info`` flags reported per episode by :func:`evaluate_stages` (true at any step)."""
CURVE_SEED_OFFSET = 20_000
"""Held-out layouts for the learning curve: seeds ``CURVE_SEED_OFFSET + i``. They are disjoint
from the demonstration seeds (``seed, seed + 1, ...``) and from ``gym-coffee evaluate``'s test
seeds (``EVAL_SEED_OFFSET + seed + i``, offset 10 000): the final benchmark is not selected on."""

# Off-policy warm-up: ``learning_starts=0`` so that SB3 never samples the uniform "random warm-up"
# actions of ``action_space.sample()`` (full-scale residuals); exploration comes from the
# zero-initialised actor itself (SAC: its own Gaussian with a small initial std; TD3: Gaussian
# action noise of std ``action_noise_sigma``; PPO: its Gaussian with ``log_std_init``).
DEFAULT_HYPERPARAMETERS: dict[str, dict[str, Any]] = {
    "sac": {
        "learning_rate": 3e-4,
        "buffer_size": 100_000,
        "batch_size": 256,
        "gamma": 0.98,
        "tau": 0.02,
        "train_freq": 1,
        "gradient_steps": 1,
        "learning_starts": 0,
        "ent_coef": "auto",
        "policy_kwargs": {"net_arch": [64, 64], "activation_fn": "relu"},
        "initial_std": 0.3,
    },
    "td3": {
        "learning_rate": 1e-3,
        "buffer_size": 100_000,
        "batch_size": 256,
        "gamma": 0.98,
        "tau": 0.02,
        "train_freq": 1,
        "gradient_steps": 1,
        "learning_starts": 0,
        "policy_kwargs": {"net_arch": [64, 64], "activation_fn": "relu"},
        "action_noise_sigma": 0.2,
    },
    "ppo": {
        "learning_rate": 3e-4,
        "n_steps": 512,
        "batch_size": 64,
        "n_epochs": 10,
        "gamma": 0.98,
        "gae_lambda": 0.95,
        "clip_range": 0.2,
        "ent_coef": 0.0,
        "policy_kwargs": {
            "net_arch": {"pi": [64, 64], "vf": [64, 64]},
            "activation_fn": "tanh",
            "log_std_init": -1.2,
        },
    },
}
# Keys of DEFAULT_HYPERPARAMETERS that are ours, not SB3 constructor arguments.
_OWN_KEYS = ("initial_std", "action_noise_sigma", "policy_kwargs")


# --------------------------------------------------------------------------------------------
# Optional dependencies
# --------------------------------------------------------------------------------------------


def require_rl() -> tuple[Any, Any]:
    """Import and return ``(stable_baselines3, torch)``, or explain which extra to install.

    Raises:
        ImportError: naming ``pip install "gym-coffee[rl]"`` when either is missing.
    """
    try:
        import stable_baselines3
        import torch
    except ImportError as exc:  # also raised for sys.modules[name] = None
        raise ImportError(
            f"Residual fine-tuning needs stable-baselines3 and torch ({exc}). "
            f"Install the optional extra: {RL_EXTRA_HINT}"
        ) from exc
    return stable_baselines3, torch


# --------------------------------------------------------------------------------------------
# Base policies
# --------------------------------------------------------------------------------------------


@runtime_checkable
class PolicyPredictor(Protocol):
    """Stable-baselines3's policy protocol (``stable_baselines3.common.type_aliases``)."""

    def predict(
        self,
        observation: NDArray[Any],
        state: tuple[NDArray[Any], ...] | None = None,
        episode_start: NDArray[Any] | None = None,
        deterministic: bool = False,
    ) -> tuple[NDArray[Any], tuple[NDArray[Any], ...] | None]: ...


def _as_batch(observation: Any) -> tuple[NDArray[Any], bool]:
    obs = np.asarray(observation)
    if obs.ndim == 1:
        return obs[None, :], True
    if obs.ndim != 2:
        raise ValueError(
            f"observation must have shape (obs_dim,) or (n_envs, obs_dim), got {obs.shape}"
        )
    return obs, False


def _bind(policy: Any, env: gym.Env) -> Any:
    """``policy.bind(env)`` for env-bound policies (scripted controllers), else ``policy``."""
    bind = getattr(policy, "bind", None)
    return bind(env) if callable(bind) else policy


class TeacherBase:
    """The scripted teacher (:class:`gym_coffee.teacher.ScriptedTeacher`) as a base policy.

    A stand-in for the GP policy while that is not available, and a reference: the teacher plans
    from the env's ``task_points()`` (privileged: the true button position), so it must be bound
    to the env it acts in (:meth:`bind`, done by :class:`ResidualWrapper` and
    :func:`evaluate_stages`). Deterministic per layout (``variation=0`` by default). Its phase is
    the observation time over the planned duration.
    """

    def __init__(self, env: gym.Env | None = None, *, variation: float = 0.0, seed: int = 0):
        self.variation = float(variation)
        self.seed = int(seed)
        self.env = env
        self._teacher: Any = None
        if env is not None:
            from gym_coffee.teacher import ScriptedTeacher

            self._teacher = ScriptedTeacher(env, rng=self.seed, variation=self.variation)

    def bind(self, env: gym.Env) -> TeacherBase:
        return TeacherBase(env, variation=self.variation, seed=self.seed)

    def predict(
        self,
        observation: NDArray[Any],
        state: Any = None,
        episode_start: Any = None,
        deterministic: bool = True,
    ) -> tuple[NDArray[np.float32], Any]:
        if self._teacher is None:
            raise RuntimeError("TeacherBase is not bound to an env; call bind(env)")
        obs = np.asarray(observation)
        if obs.ndim == 2:
            if obs.shape[0] != 1:
                raise ValueError("a bound TeacherBase acts in one env: pass one observation")
            return self._teacher.act(obs[0])[None, :], state
        return self._teacher.act(obs), state

    def phase(self, observation: NDArray[Any]) -> NDArray[np.float64]:
        from gym_coffee.env import OBS_SLICES

        obs = np.atleast_2d(np.asarray(observation, np.float64))
        duration = max(float(self._teacher.duration), 1e-6) if self._teacher is not None else 1.0
        return np.clip(obs[:, OBS_SLICES["time"].start] / duration, 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# Gates
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PhaseGate:
    """Open the residual in a window of the phase (normalised time, 0 at reset, 1 at the end of
    the demonstrated motion).

    ``gate = 0`` for ``phase < start - ramp``, rises linearly to 1 at ``start``, stays 1 up to
    ``end`` (default: forever, so the residual can finish a press the base stopped short of) and
    is 0 after ``end``.

    Arguments:
        start: phase at which the gate is fully open.
        end: phase after which it closes again (``inf``: never).
        ramp: width of the linear ramp before ``start`` (0: a step).
        source: where the phase comes from. ``"policy"``: ``base.phase(observation)`` (the GP
            policy's own normalised time). ``"observation"``: ``observation[..., time_index] /
            time_scale`` (e.g. the env's ``time`` entry in seconds divided by the demonstrated
            duration); use it for bases without a ``phase`` method.
        time_index: index of the time entry in the observation (``source="observation"``).
        time_scale: divisor that turns that entry into a phase.

    Why the phase and not the env's stage flags: ``cup_placed`` is the simulator's judgement
    (tolerance to the spout axis), which a deployed robot does not have; the phase is what the
    time-indexed GP policy runs on anyway. Why not the GP's predicted variance alone: the machine
    frame is tight twice (placing, Fig. 4b steps 50-65, and pressing, 85-100), so a variance gate
    needs the phase to tell the two apart; a phase window chosen from the policy's constraint
    report (the last tight interval of the machine frame) is that combination, made explicit.
    """

    start: float = 0.75
    end: float = math.inf
    ramp: float = 0.05
    source: str = "policy"
    time_index: int | None = None
    time_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.source not in ("policy", "observation"):
            raise ValueError(f"source must be 'policy' or 'observation', got {self.source!r}")
        if self.source == "observation" and self.time_index is None:
            raise ValueError("source='observation' needs time_index (the time entry's index)")
        if not (self.ramp >= 0 and self.end > self.start and self.time_scale > 0):
            raise ValueError(
                f"need ramp >= 0, end > start and time_scale > 0; got ramp={self.ramp}, "
                f"start={self.start}, end={self.end}, time_scale={self.time_scale}"
            )

    def phase(self, observation: NDArray[Any], base: Any = None) -> NDArray[np.float64]:
        """Phase per row of a batch ``observation (n, obs_dim)`` -> ``(n,)``."""
        obs, _ = _as_batch(observation)
        if self.source == "observation":
            return obs[:, self.time_index].astype(np.float64) / self.time_scale
        phase_fn = getattr(base, "phase", None)
        if not callable(phase_fn):
            raise TypeError(
                f"PhaseGate(source='policy') needs a base policy with a phase(observation) "
                f"method; {type(base).__name__} has none. Use PhaseGate(source='observation', "
                f"time_index=..., time_scale=...) instead."
            )
        phase = np.asarray(phase_fn(obs), dtype=np.float64).reshape(-1)
        if phase.shape != (obs.shape[0],):
            raise ValueError(f"base.phase returned shape {phase.shape}, expected ({obs.shape[0]},)")
        return phase

    def __call__(self, observation: NDArray[Any], base: Any = None) -> NDArray[np.float32]:
        """Gate value in ``[0, 1]`` per row of ``observation (n, obs_dim)`` -> ``(n,)``."""
        phase = self.phase(observation, base)
        if self.ramp > 0:
            rise = np.clip((phase - (self.start - self.ramp)) / self.ramp, 0.0, 1.0)
        else:
            rise = (phase >= self.start).astype(np.float64)
        gate = np.where(phase > self.end, 0.0, rise)
        return gate.astype(np.float32)

    def to_config(self) -> dict[str, Any]:
        cfg = dataclasses.asdict(self)
        cfg["end"] = None if math.isinf(self.end) else self.end
        return {"type": "phase", **cfg}


def gate_from_config(config: Mapping[str, Any]) -> PhaseGate:
    """Rebuild a gate from :meth:`PhaseGate.to_config`'s dict."""
    cfg = dict(config)
    kind = cfg.pop("type", None)
    if kind != "phase":
        raise ValueError(f"unknown gate type {kind!r} (known: 'phase')")
    if cfg.get("end") is None:
        cfg["end"] = math.inf
    fields = {f.name for f in dataclasses.fields(PhaseGate)}
    unknown = set(cfg) - fields
    if unknown:
        raise ValueError(f"unknown PhaseGate settings {sorted(unknown)}")
    return PhaseGate(**cfg)


def _compose(
    base_action: NDArray[Any],
    gate: NDArray[Any],
    residual: NDArray[Any],
    scale: float,
    residual_dims: NDArray[np.intp],
    low: NDArray[Any],
    high: NDArray[Any],
) -> NDArray[np.float32]:
    """``clip(base + scale * gate * residual, low, high)`` for batches ``(n, act_dim)``.

    Done in float32 on the residual dimensions only, so a zero residual (or a closed gate)
    returns the base action bit for bit (if it lies in the bounds).
    """
    applied = np.array(base_action, dtype=np.float32, copy=True)
    delta = (np.float32(scale) * np.asarray(gate, dtype=np.float32)[:, None]) * np.asarray(
        residual, dtype=np.float32
    )
    applied[:, residual_dims] += delta
    return np.clip(applied, low, high).astype(np.float32)


# --------------------------------------------------------------------------------------------
# The wrapper
# --------------------------------------------------------------------------------------------


class ResidualWrapper(gym.Wrapper):
    """Turn an env plus a base policy into the residual agent's env.

    Action space: ``Box(-1, 1, (len(residual_dims),))`` (the residual, before ``scale``).
    Observation space: flat float32 ``Box``: ``[env observation, base action, gate]`` (the gate
    entry only with ``include_gate_obs=True``). Applied action:
    ``clip(base + scale * gate * residual)`` on the ``residual_dims`` entries; the others are the
    base's.

    Arguments:
        env: a gymnasium env with flat ``Box`` observation and action spaces.
        base: any ``PolicyPredictor`` for ``env``; asked with ``deterministic=True``; its
            recurrent ``state`` is carried and reset with ``episode_start``.
        scale: the residual's largest contribution, in action units (default 0.5).
        gate: callable ``gate(observation (n, obs_dim), base) -> (n,)`` in ``[0, 1]``
            (default :class:`PhaseGate`).
        residual_dims: action entries the residual may change (default: all).
        include_gate_obs: append the gate value to the agent's observation.
        skip_ungated: while the gate is 0 the agent's action has no effect, so the wrapper steps
            the base alone until the gate opens or the episode ends; one agent step may then be
            several env steps. The reward is the (undiscounted) sum over them and
            ``info["env_steps"]`` counts them, so env-step budgets stay honest. Off by default
            (one agent step = one env step).
        reward_fn: ``reward_fn(env_reward, info, previous_info) -> float``, the agent's reward
            per env step (default: the env's reward).

    ``info`` gains ``env_steps``, ``residual_gate`` (the gate of the action just applied) and
    ``base_action``.

    A base with a ``bind(env)`` method (a scripted controller that reads the env, such as
    :class:`TeacherBase`) is bound to this wrapper's env first.
    """

    def __init__(
        self,
        env: gym.Env,
        base: Any,
        *,
        scale: float = 0.5,
        gate: Callable[..., NDArray[Any]] | None = None,
        residual_dims: Sequence[int] | None = None,
        include_gate_obs: bool = True,
        skip_ungated: bool = False,
        reward_fn: Callable[[float, Mapping[str, Any], Mapping[str, Any]], float] | None = None,
    ) -> None:
        super().__init__(env)
        if not hasattr(base, "predict"):
            raise TypeError(f"base must have a predict() method, got {type(base).__name__}")
        base = _bind(base, env)
        obs_space, act_space = env.observation_space, env.action_space
        if not (isinstance(obs_space, spaces.Box) and len(obs_space.shape) == 1):
            raise TypeError(f"ResidualWrapper needs a flat Box observation space, got {obs_space}")
        if not (isinstance(act_space, spaces.Box) and len(act_space.shape) == 1):
            raise TypeError(f"ResidualWrapper needs a flat Box action space, got {act_space}")
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be a positive number, got {scale}")
        self.base = base
        self.scale = float(scale)
        self.gate = gate if gate is not None else PhaseGate()
        act_dim = act_space.shape[0]
        dims = np.arange(act_dim) if residual_dims is None else np.asarray(residual_dims, int)
        if dims.ndim != 1 or dims.size == 0 or np.any((dims < 0) | (dims >= act_dim)):
            raise ValueError(f"residual_dims must index the {act_dim} action entries, got {dims}")
        if len(set(dims.tolist())) != dims.size:
            raise ValueError(f"residual_dims has repeated entries: {dims.tolist()}")
        self.residual_dims = dims.astype(np.intp)
        self.include_gate_obs = bool(include_gate_obs)
        self.skip_ungated = bool(skip_ungated)
        self.reward_fn = reward_fn
        self._prev_info: Mapping[str, Any] = {}
        self._act_low = act_space.low.astype(np.float32)
        self._act_high = act_space.high.astype(np.float32)
        self.observation_space = _agent_observation_space(obs_space, act_space, include_gate_obs)
        self.action_space = spaces.Box(-1.0, 1.0, (dims.size,), np.float32)
        self._obs: NDArray[Any] | None = None
        self._base_action: NDArray[np.float32] | None = None
        self._gate_value = np.float32(0.0)
        self._base_state: Any = None
        self._episode_start = True

    # -- internals ---------------------------------------------------------------------------
    def _query_base(self, obs: NDArray[Any]) -> None:
        batch = np.asarray(obs)[None, :]
        action, self._base_state = self.base.predict(
            batch,
            state=self._base_state,
            episode_start=np.array([self._episode_start]),
            deterministic=True,
        )
        self._episode_start = False
        self._obs = obs
        self._base_action = np.asarray(action, dtype=np.float32).reshape(self._act_low.shape)
        self._gate_value = np.float32(np.asarray(self.gate(batch, self.base)).reshape(-1)[0])

    def _agent_obs(self) -> NDArray[np.float32]:
        assert self._obs is not None and self._base_action is not None
        parts = [
            np.asarray(self._obs, dtype=np.float32).reshape(-1),
            np.clip(self._base_action, self._act_low, self._act_high),
        ]
        if self.include_gate_obs:
            parts.append(np.array([self._gate_value], dtype=np.float32))
        return np.concatenate(parts).astype(np.float32)

    # -- gymnasium API -----------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        self._base_state = None
        self._episode_start = True
        self._prev_info = info
        self._query_base(obs)
        return self._agent_obs(), info

    def _reward(self, reward: float, info: Mapping[str, Any]) -> float:
        if self.reward_fn is not None:
            reward = self.reward_fn(reward, info, self._prev_info)
        self._prev_info = info
        return float(reward)

    def step(
        self, action: NDArray[Any]
    ) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        if self._base_action is None:
            raise RuntimeError("call reset() before step()")
        residual = np.asarray(action, dtype=np.float32).reshape(1, -1)
        if residual.shape[1] != self.residual_dims.size:
            raise ValueError(
                f"residual action has {residual.shape[1]} entries, expected "
                f"{self.residual_dims.size}"
            )
        gate_applied = float(self._gate_value)
        base_applied = self._base_action
        applied = _compose(
            self._base_action[None, :],
            np.array([self._gate_value]),
            residual,
            self.scale,
            self.residual_dims,
            self._act_low,
            self._act_high,
        )[0]
        obs, reward, terminated, truncated, info = self.env.step(applied)
        total_reward = self._reward(reward, info)
        env_steps = 1
        # The base is also asked in a final state: the agent's last observation must hold the
        # base action there (SB3 bootstraps truncated episodes from it); it is never applied.
        self._query_base(obs)
        while self.skip_ungated and self._gate_value == 0.0 and not (terminated or truncated):
            obs, reward, terminated, truncated, info = self.env.step(
                np.clip(self._base_action, self._act_low, self._act_high)
            )
            total_reward += self._reward(reward, info)
            env_steps += 1
            self._query_base(obs)
        info = dict(info)
        info["env_steps"] = env_steps
        info["residual_gate"] = gate_applied
        info["base_action"] = base_applied
        return self._agent_obs(), total_reward, bool(terminated), bool(truncated), info


def _agent_observation_space(
    obs_space: spaces.Box, act_space: spaces.Box, include_gate: bool
) -> spaces.Box:
    lows = [obs_space.low.astype(np.float32), act_space.low.astype(np.float32)]
    highs = [obs_space.high.astype(np.float32), act_space.high.astype(np.float32)]
    if include_gate:
        lows.append(np.zeros(1, np.float32))
        highs.append(np.ones(1, np.float32))
    return spaces.Box(np.concatenate(lows), np.concatenate(highs), dtype=np.float32)


# --------------------------------------------------------------------------------------------
# A documented harder variant of an env
# --------------------------------------------------------------------------------------------


class ActuationNoiseWrapper(gym.ActionWrapper):
    """Actuation error: ``a' = clip(a + bias + noise)`` on chosen action entries.

    ``bias`` is a fixed offset (a miscalibrated joint; ``bias_std`` adds a per-episode random part
    drawn at ``reset(seed=...)``); ``noise_std`` adds white noise every step. Randomness comes from
    a generator seeded by ``reset(seed=...)``, so seeded episodes stay reproducible.

    The error acts from the start, or only once ``start_on_info`` (an ``info`` flag, e.g.
    ``"cup_placed"``) has been true at some step of the episode (latched), or once the
    observation's time (``time_index``) reaches ``start_time``. This is an env-side variant: it may
    read ``info``; the policy never sees when it starts. Used by ``benchmarks/residual_press.py``
    as the "harder variant" when the base already presses reliably on the plain env.
    """

    def __init__(
        self,
        env: gym.Env,
        *,
        dims: Sequence[int] | None = None,
        bias: float | Sequence[float] = 0.0,
        bias_std: float = 0.0,
        noise_std: float = 0.0,
        start_time: float | None = None,
        time_index: int | None = None,
        start_on_info: str | None = None,
    ) -> None:
        super().__init__(env)
        if start_time is not None and time_index is None:
            raise ValueError("start_time needs time_index (the observation's time entry)")
        act_dim = env.action_space.shape[0]
        self.dims = np.arange(act_dim) if dims is None else np.asarray(dims, dtype=np.intp)
        self.bias = np.broadcast_to(np.asarray(bias, np.float32), self.dims.shape).copy()
        self.bias_std = float(bias_std)
        self.noise_std = float(noise_std)
        self.start_time = start_time
        self.time_index = time_index
        self._rng = np.random.default_rng()
        self.start_on_info = start_on_info
        self._episode_bias = self.bias.copy()
        self._last_obs: NDArray[Any] | None = None
        self._active = False

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None:
            self._rng = np.random.default_rng([int(seed), 0xC0FFEE])
        self._episode_bias = self.bias + (
            self._rng.normal(0.0, self.bias_std, self.dims.shape).astype(np.float32)
            if self.bias_std > 0
            else 0.0
        )
        obs, info = self.env.reset(seed=seed, options=options)
        self._last_obs = obs
        self._active = False
        self._update_active(obs, info)
        return obs, info

    def _update_active(self, obs: NDArray[Any], info: Mapping[str, Any]) -> None:
        active = True
        if self.start_on_info is not None:
            active = bool(info.get(self.start_on_info, False))
        if self.start_time is not None:
            active = active and float(np.asarray(obs)[self.time_index]) >= self.start_time
        self._active = self._active or active

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        self._last_obs = obs
        self._update_active(obs, info)
        info = dict(info)
        info["actuation_error_active"] = self._active
        return obs, reward, terminated, truncated, info

    def action(self, action: NDArray[Any]) -> NDArray[np.float32]:
        a = np.array(action, dtype=np.float32, copy=True)
        if not self._active:
            return a
        a[self.dims] += self._episode_bias
        if self.noise_std > 0:
            a[self.dims] += self._rng.normal(0.0, self.noise_std, self.dims.shape)
        space = self.env.action_space
        return np.clip(a, space.low, space.high).astype(np.float32)


class MachinePoseErrorWrapper(gym.ObservationWrapper):
    """Perception error on the coffee machine's pose: the *observed* ``machine_pos`` is shifted by
    ``delta`` metres towards the machine's front (along ``-button_axis``, the machine frame's -x),
    with ``delta`` drawn per episode from ``U(low, high)`` at ``reset(seed=...)``.

    The physics are untouched; a policy that places and presses relative to the observed machine
    frame (the GP policy) aims everything ``delta`` short of the true position. Placing tolerates
    that (the place tolerance is 25 mm); the press does not (the button must travel 5 mm): the
    robot "stopped a few millimeters in front of it" (Sec. IV). ``info["machine_pose_error"]``
    is ``delta`` (for analysis; policies do not see it).
    """

    def __init__(self, env: gym.Env, *, low: float = 0.002, high: float = 0.010) -> None:
        super().__init__(env)
        if not 0 <= low <= high:
            raise ValueError(f"need 0 <= low <= high, got {low}, {high}")
        from gym_coffee.env import OBS_SLICES

        self.low, self.high = float(low), float(high)
        self._pos = OBS_SLICES["machine_pos"]
        self._yaw = OBS_SLICES["machine_yaw"].start
        self._rng = np.random.default_rng()
        self.delta = 0.0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None:
            self._rng = np.random.default_rng([int(seed), 0x5EE])
        self.delta = float(self._rng.uniform(self.low, self.high))
        obs, info = self.env.reset(seed=seed, options=options)
        info = dict(info)
        info["machine_pose_error"] = self.delta
        return self.observation(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        info = dict(info)
        info["machine_pose_error"] = self.delta
        return obs, reward, terminated, truncated, info

    def observation(self, observation: NDArray[Any]) -> NDArray[np.float32]:
        obs = np.array(observation, dtype=np.float32, copy=True)
        yaw = float(obs[self._yaw])
        obs[self._pos][:2] -= self.delta * np.array([np.cos(yaw), np.sin(yaw)], np.float32)
        return obs


# --------------------------------------------------------------------------------------------
# SB3 models: build, zero-init, weights as arrays
# --------------------------------------------------------------------------------------------


def _activation(name: str) -> Any:
    _, torch = require_rl()
    table = {"relu": torch.nn.ReLU, "tanh": torch.nn.Tanh, "elu": torch.nn.ELU}
    if name not in table:
        raise ValueError(f"unknown activation_fn {name!r} (known: {sorted(table)})")
    return table[name]


def _resolve_hyperparameters(algo: str, overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    hp = json.loads(json.dumps(DEFAULT_HYPERPARAMETERS[algo]))  # deep copy
    for key, value in (overrides or {}).items():
        if key == "policy_kwargs":
            hp["policy_kwargs"].update(value)
        else:
            hp[key] = value
    json.dumps(hp)  # must stay JSON-able: it goes into the policy file
    return hp


def _build_model(
    algo: str, env: Any, hyperparameters: Mapping[str, Any], seed: int | None, verbose: int = 0
) -> Any:
    """An SB3 algorithm with the residual actor zero-initialised (see
    :func:`zero_init_residual_actor`)."""
    sb3, _ = require_rl()
    hp = dict(hyperparameters)
    policy_kwargs = dict(hp.get("policy_kwargs", {}))
    if "activation_fn" in policy_kwargs:
        policy_kwargs["activation_fn"] = _activation(policy_kwargs["activation_fn"])
    kwargs = {k: v for k, v in hp.items() if k not in _OWN_KEYS}
    if algo == "td3":
        from stable_baselines3.common.noise import NormalActionNoise

        n = int(np.prod(env.action_space.shape))
        sigma = float(hp.get("action_noise_sigma", 0.0))
        if sigma > 0:
            kwargs["action_noise"] = NormalActionNoise(np.zeros(n), sigma * np.ones(n))
    cls = {"sac": sb3.SAC, "td3": sb3.TD3, "ppo": sb3.PPO}[algo]
    model = cls(
        "MlpPolicy",
        env,
        policy_kwargs=policy_kwargs,
        seed=seed,
        verbose=verbose,
        device="cpu",
        **kwargs,
    )
    zero_init_residual_actor(model, algo, initial_std=hp.get("initial_std"))
    return model


def zero_init_residual_actor(model: Any, algo: str, *, initial_std: float | None = None) -> None:
    """Make the SB3 actor output exactly zero, so the residual starts as the base policy.

    - **SAC**: zero ``actor.mu`` (the mean's last Linear); with ``initial_std`` also zero
      ``actor.log_std``'s weight and set its bias to ``log(initial_std)``, so the first
      exploratory residuals are ``tanh(N(0, initial_std^2))`` rather than ``tanh(N(0, 1))``.
      Deterministic output: ``tanh(0) = 0``.
    - **TD3**: zero the last Linear of ``actor.mu`` (before its Tanh) and copy the actor into
      ``actor_target``.
    - **PPO**: zero ``action_net`` (the Gaussian's mean); the std is ``exp(log_std_init)``
      (policy kwarg, default here -1.2, i.e. 0.3).

    Only the mean's last layer is zeroed: its weight still gets gradients (they are the hidden
    features times the actor loss's gradient), so learning proceeds; the hidden layers keep SB3's
    initialisation.
    """
    _, torch = require_rl()
    with torch.no_grad():
        if algo == "sac":
            actor = model.policy.actor
            mu = actor.mu[0] if isinstance(actor.mu, torch.nn.Sequential) else actor.mu
            mu.weight.zero_()
            mu.bias.zero_()
            if initial_std is not None and isinstance(actor.log_std, torch.nn.Linear):
                actor.log_std.weight.zero_()
                actor.log_std.bias.fill_(math.log(initial_std))
        elif algo == "td3":
            linears = [m for m in model.policy.actor.mu if isinstance(m, torch.nn.Linear)]
            linears[-1].weight.zero_()
            linears[-1].bias.zero_()
            model.policy.actor_target.load_state_dict(model.policy.actor.state_dict())
        elif algo == "ppo":
            model.policy.action_net.weight.zero_()
            model.policy.action_net.bias.zero_()
        else:
            raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")


class _SpacesEnv(gym.Env):
    """A stand-in env that only carries spaces, to rebuild an SB3 model for prediction."""

    def __init__(self, observation_space: spaces.Box, action_space: spaces.Box) -> None:
        self.observation_space = observation_space
        self.action_space = action_space

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action: Any):
        raise RuntimeError("_SpacesEnv only carries spaces; it cannot be stepped")


def _policy_arrays(model: Any) -> dict[str, NDArray[np.float32]]:
    return {
        name: tensor.detach().cpu().numpy().astype(np.float32, copy=True)
        for name, tensor in model.policy.state_dict().items()
    }


# --------------------------------------------------------------------------------------------
# The fine-tuned policy, and its file
# --------------------------------------------------------------------------------------------


class ResidualPolicyFormatError(ValueError):
    """A residual policy file is missing something or does not fit together."""


_KIND_LOADERS: dict[str, Callable[[str | os.PathLike[str]], Any]] = {}


def register_policy_kind(kind: str, loader: Callable[[str | os.PathLike[str]], Any]) -> None:
    """Let :func:`load_any_policy` open files whose JSON ``kind``/``format`` is ``kind``."""
    _KIND_LOADERS[kind] = loader


def _gp_policy_loader(path: str | os.PathLike[str]) -> Any:
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    return GPDemonstrationPolicy.load(path)


def gp_policy_kind() -> str | None:
    """``metadata["kind"]``/``["format"]`` of a GP policy file:
    ``lgp_policy.lfd.policy.FORMAT_NAME``, read from that module so the two never drift apart
    (``None`` if it cannot be imported)."""
    try:
        from lgp_policy.lfd.policy import FORMAT_NAME
    except ImportError:
        return None
    return str(FORMAT_NAME)


def _read_metadata(path: Path) -> dict[str, Any]:
    """The JSON metadata of one of our ``.npz`` files (``metadata`` string array) or of a JSON
    sidecar ``<path>.json`` / ``<stem>.json``."""
    if not path.exists():
        raise FileNotFoundError(f"no policy file at {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            if "metadata" in data.files:
                return json.loads(str(data["metadata"]))
    except (zipfile.BadZipFile, ValueError, OSError, json.JSONDecodeError) as exc:
        if path.suffix == ".json":
            return json.loads(path.read_text())
        raise ResidualPolicyFormatError(
            f"{path} is not a readable policy file (.npz with a JSON 'metadata' entry): {exc}"
        ) from exc
    for sidecar in (path.with_suffix(path.suffix + ".json"), path.with_suffix(".json")):
        if sidecar.exists():
            return json.loads(sidecar.read_text())
    raise ResidualPolicyFormatError(f"{path} has no 'metadata' entry and no JSON sidecar")


def load_any_policy(path: str | os.PathLike[str]) -> Any:
    """Open a policy file of any kind this project writes, dispatching on its JSON ``kind``.

    Known kinds: ``"lgp_policy.residual_policy"`` (:meth:`ResidualPolicy.load`) and the GP
    policy's :func:`gp_policy_kind` (:meth:`GPDemonstrationPolicy.load`); more via
    :func:`register_policy_kind`.
    """
    path = Path(path)
    meta = _read_metadata(path)
    kind = meta.get("kind", meta.get("format"))
    if kind == RESIDUAL_POLICY_KIND:
        return ResidualPolicy.load(path)
    if kind in _KIND_LOADERS:
        return _KIND_LOADERS[kind](path)
    gp_kind = gp_policy_kind()
    if kind is not None and kind == gp_kind:
        return _gp_policy_loader(path)
    known = [RESIDUAL_POLICY_KIND, gp_kind, *_KIND_LOADERS]
    raise ResidualPolicyFormatError(
        f"{path}: unknown policy kind {kind!r} (metadata 'kind'/'format'); known kinds: {known}"
    )


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _atomic_savez(path: Path, arrays: Mapping[str, NDArray[Any]], overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 -> the usual permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


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


class _LiveNormalizer:
    """The statistics of a training ``VecNormalize``, read at every call (no update)."""

    def __init__(self, vec_normalize: Any) -> None:
        self.vec_normalize = vec_normalize

    def __call__(self, x: NDArray[Any]) -> NDArray[np.float32]:
        return np.asarray(self.vec_normalize.normalize_obs(x), dtype=np.float32)

    def freeze(self) -> ObsNormalizer:
        vn = self.vec_normalize
        return ObsNormalizer(
            np.array(vn.obs_rms.mean, np.float64),
            np.array(vn.obs_rms.var, np.float64),
            float(vn.epsilon),
            float(vn.clip_obs),
        )


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
        scale, gate, residual_dims, include_gate_obs: as in :class:`ResidualWrapper` (must be the
            same as during training).
        action_space: the env's action space (for the clip; default ``Box(-1, 1)``).
        algo, hyperparameters: recorded in the file.
        base_path: the base policy's file, embedded into (or referenced by) :meth:`save`.
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
        self.scale = float(scale)
        self.gate = gate if gate is not None else PhaseGate()
        model_obs = getattr(model, "observation_space", None)
        model_act = getattr(model, "action_space", None)
        if action_space is None:
            if residual_dims is not None or model_act is None:
                raise ValueError("pass the env's action_space (needed with residual_dims)")
            action_space = spaces.Box(-1.0, 1.0, model_act.shape, np.float32)
        self.action_space = action_space
        act_dim = action_space.shape[0]
        dims = np.arange(act_dim) if residual_dims is None else np.asarray(residual_dims, int)
        self.residual_dims = dims.astype(np.intp)
        self.include_gate_obs = bool(include_gate_obs)
        if model_act is not None and model_act.shape != (dims.size,):
            raise ValueError(
                f"the residual model acts on {model_act.shape} but residual_dims has {dims.size} "
                f"entries"
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
        obs, _ = _as_batch(observation)
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
        obs, single = _as_batch(observation)
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
        applied = _compose(
            base_action, gate, residual, self.scale, self.residual_dims, self._low, self._high
        )
        return (applied[0] if single else applied), state

    def phase(self, observation: NDArray[Any]) -> NDArray[np.float64]:
        """The gate's phase (so a residual policy can itself be a base)."""
        return self.gate.phase(observation, self.base)

    def bind(self, env: gym.Env) -> ResidualPolicy:
        """This policy with an env-bound base (e.g. :class:`TeacherBase`) bound to ``env``."""
        if not callable(getattr(self.base, "bind", None)):
            return self
        clone = object.__new__(ResidualPolicy)
        clone.__dict__.update(self.__dict__)
        clone.base = _bind(self.base, env)
        return clone

    # -- file --------------------------------------------------------------------------------
    def save(
        self,
        path: str | os.PathLike[str],
        *,
        overwrite: bool = False,
        embed_base: bool = True,
    ) -> Path:
        """Write ONE ``.npz`` (no pickle): weights, spaces, base policy, JSON metadata.

        The base policy file (``base_path``) is embedded as bytes (``embed_base=True``) or
        referenced by absolute path and SHA-256. A base without a file is not saved: pass it to
        :meth:`load` again. Written atomically; an existing file is kept unless
        ``overwrite=True``.
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
            f"param/{k}": v for k, v in _policy_arrays(self.model).items()
        }
        arrays["space/obs_low"] = model_obs.low.astype(np.float32)
        arrays["space/obs_high"] = model_obs.high.astype(np.float32)
        arrays["space/act_low"] = self._low
        arrays["space/act_high"] = self._high
        norm_cfg: dict[str, float] | None = None
        if self.obs_normalizer is not None:
            frozen = self.obs_normalizer
            if isinstance(frozen, _LiveNormalizer):
                frozen = frozen.freeze()
            if not isinstance(frozen, ObsNormalizer):
                raise TypeError(
                    f"cannot save an observation normaliser of type {type(frozen).__name__}"
                )
            arrays["obs_norm/mean"] = np.asarray(frozen.mean, np.float64)
            arrays["obs_norm/var"] = np.asarray(frozen.var, np.float64)
            norm_cfg = {"epsilon": frozen.epsilon, "clip_obs": frozen.clip_obs}
        base_ref: dict[str, Any] | None = None
        if self.base_path is not None:
            base_file = self.base_path.resolve()
            base_ref = {
                "path": str(base_file),
                "name": base_file.name,
                "sha256": _sha256(base_file),
                "embedded": bool(embed_base),
                "kind": _read_metadata(base_file).get("kind"),
            }
            if embed_base:
                arrays["base_file"] = np.frombuffer(base_file.read_bytes(), dtype=np.uint8)
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
        arrays["metadata"] = np.array(json.dumps(meta))
        _atomic_savez(path, arrays, overwrite)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, base: Any = None) -> ResidualPolicy:
        """Rebuild a policy written by :meth:`save` (``allow_pickle=False``).

        Arguments:
            base: the base policy; by default it is loaded from the embedded file, else from the
                referenced path (whose SHA-256 must match).

        Raises:
            ResidualPolicyFormatError: naming what is missing, malformed or inconsistent.
            ImportError: without stable-baselines3/torch (``pip install "gym-coffee[rl]"``).
        """
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no residual policy file at {path}")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
            raise ResidualPolicyFormatError(
                f"{path} is not a readable .npz residual policy file: {exc}"
            ) from exc
        meta = _check_metadata(path, arrays)
        _, torch = require_rl()

        obs_space = spaces.Box(arrays["space/obs_low"], arrays["space/obs_high"], dtype=np.float32)
        act_space = spaces.Box(arrays["space/act_low"], arrays["space/act_high"], dtype=np.float32)
        n_res = len(meta["residual_dims"])
        expected_obs = meta["obs_dim"] + meta["action_dim"] + int(meta["include_gate_obs"])
        if obs_space.shape != (expected_obs,) or act_space.shape != (meta["action_dim"],):
            raise ResidualPolicyFormatError(
                f"{path}: spaces do not fit the metadata: agent observation {obs_space.shape}, "
                f"expected ({expected_obs},); action {act_space.shape}, expected "
                f"({meta['action_dim']},)"
            )
        hp = dict(meta["hyperparameters"])
        # Prediction needs no replay buffer: do not allocate one.
        if meta["algo"] in ("sac", "td3"):
            hp["buffer_size"] = 1
        res_space = spaces.Box(-1.0, 1.0, (n_res,), np.float32)
        try:
            model = _build_model(meta["algo"], _SpacesEnv(obs_space, res_space), hp, seed=0)
        except (TypeError, ValueError) as exc:
            raise ResidualPolicyFormatError(
                f"{path}: cannot rebuild the {meta['algo']} model from its hyperparameters: {exc}"
            ) from exc
        expected = model.policy.state_dict()
        stored = {k[len("param/") :]: v for k, v in arrays.items() if k.startswith("param/")}
        missing = sorted(set(expected) - set(stored))
        unexpected = sorted(set(stored) - set(expected))
        if missing or unexpected:
            raise ResidualPolicyFormatError(
                f"{path}: network weights do not match the {meta['algo']} model: "
                f"missing {missing[:5]}, unexpected {unexpected[:5]}"
            )
        for name, tensor in expected.items():
            value = stored[name]
            if tuple(value.shape) != tuple(tensor.shape):
                raise ResidualPolicyFormatError(
                    f"{path}: weight {name!r} has shape {value.shape}, the model needs "
                    f"{tuple(tensor.shape)}"
                )
            if not np.all(np.isfinite(value)):
                raise ResidualPolicyFormatError(f"{path}: weight {name!r} has NaN or infinity")
        model.policy.load_state_dict(
            {k: torch.as_tensor(stored[k], dtype=expected[k].dtype) for k in expected}
        )
        normalizer = None
        if meta.get("obs_norm") is not None:
            mean, var = arrays.get("obs_norm/mean"), arrays.get("obs_norm/var")
            if mean is None or var is None:
                raise ResidualPolicyFormatError(f"{path}: 'obs_norm/mean' or '/var' is missing")
            if mean.shape != obs_space.shape or var.shape != obs_space.shape:
                raise ResidualPolicyFormatError(
                    f"{path}: observation statistics have shapes {mean.shape}/{var.shape}, "
                    f"expected {obs_space.shape}"
                )
            if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0)):
                raise ResidualPolicyFormatError(f"{path}: observation statistics are not finite")
            cfg = meta["obs_norm"]
            normalizer = ObsNormalizer(
                mean, var, float(cfg.get("epsilon", 1e-8)), float(cfg.get("clip_obs", 10.0))
            )
        if base is None:
            base, base_path = _load_base(path, meta, arrays)
        else:
            base_path = None
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
            base_path=base_path,
            obs_normalizer=normalizer,
        )
        base_obs = getattr(base, "observation_space", None)
        if base_obs is not None and getattr(base_obs, "shape", None) not in (
            None,
            (meta["obs_dim"],),
        ):
            raise ResidualPolicyFormatError(
                f"{path}: the base policy observes {base_obs.shape}, the residual was trained "
                f"on observations of size {meta['obs_dim']}"
            )
        return policy


def _versions() -> dict[str, str]:
    import lgp_policy

    out = {"lgp_policy": lgp_policy.__version__, "numpy": np.__version__}
    with contextlib.suppress(ImportError):
        sb3, torch = require_rl()
        out["stable_baselines3"] = sb3.__version__
        out["torch"] = torch.__version__
    return out


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


def _check_metadata(path: Path, arrays: Mapping[str, NDArray[Any]]) -> dict[str, Any]:
    if "metadata" not in arrays:
        raise ResidualPolicyFormatError(f"{path}: no 'metadata' entry (not a residual policy?)")
    try:
        meta = json.loads(str(arrays["metadata"]))
    except json.JSONDecodeError as exc:
        raise ResidualPolicyFormatError(f"{path}: metadata is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise ResidualPolicyFormatError(f"{path}: metadata must be a JSON object")
    if meta.get("kind") != RESIDUAL_POLICY_KIND:
        raise ResidualPolicyFormatError(
            f"{path}: kind is {meta.get('kind')!r}, expected {RESIDUAL_POLICY_KIND!r} "
            f"(use load_any_policy for other policy files)"
        )
    for key, typ in _REQUIRED_META.items():
        if key not in meta:
            raise ResidualPolicyFormatError(f"{path}: metadata lacks {key!r}")
        if not isinstance(meta[key], typ) or (typ is int and isinstance(meta[key], bool)):
            raise ResidualPolicyFormatError(
                f"{path}: metadata {key!r} has the wrong type ({type(meta[key]).__name__})"
            )
    if meta["schema_version"] not in SUPPORTED_SCHEMA_VERSIONS:
        raise ResidualPolicyFormatError(
            f"{path}: schema version {meta['schema_version']} is not supported "
            f"(this version reads {SUPPORTED_SCHEMA_VERSIONS}); upgrade gym-coffee"
        )
    if meta["algo"] not in ALGOS:
        raise ResidualPolicyFormatError(f"{path}: algo {meta['algo']!r} is not one of {ALGOS}")
    if not (math.isfinite(meta["scale"]) and meta["scale"] > 0):
        raise ResidualPolicyFormatError(f"{path}: scale must be positive, got {meta['scale']}")
    dims = meta["residual_dims"]
    if not dims or any(not isinstance(d, int) or not 0 <= d < meta["action_dim"] for d in dims):
        raise ResidualPolicyFormatError(
            f"{path}: residual_dims {dims} must index the {meta['action_dim']} action entries"
        )
    for key in ("space/obs_low", "space/obs_high", "space/act_low", "space/act_high"):
        if key not in arrays:
            raise ResidualPolicyFormatError(f"{path}: array {key!r} is missing")
    try:
        gate_from_config(meta["gate"])
    except (TypeError, ValueError) as exc:
        raise ResidualPolicyFormatError(f"{path}: bad gate settings: {exc}") from exc
    return meta


def _load_base(
    path: Path, meta: Mapping[str, Any], arrays: Mapping[str, NDArray[Any]]
) -> tuple[Any, Path | None]:
    ref = meta.get("base")
    if ref is None:
        raise ResidualPolicyFormatError(
            f"{path} was saved without its base policy (the base had no file); pass "
            f"ResidualPolicy.load(path, base=...)"
        )
    if ref.get("embedded"):
        if "base_file" not in arrays:
            raise ResidualPolicyFormatError(f"{path}: the embedded base policy is missing")
        raw = arrays["base_file"].tobytes()
        if hashlib.sha256(raw).hexdigest() != ref.get("sha256"):
            raise ResidualPolicyFormatError(f"{path}: the embedded base policy is corrupted")
        # Loaded from memory: nothing from the file is ever used as a path, nothing is written.
        # Only a GP policy may be embedded (no nesting of residual policies).
        from lgp_policy.lfd.policy import GPDemonstrationPolicy, PolicyFileError

        try:
            return GPDemonstrationPolicy.load(io.BytesIO(raw)), None
        except PolicyFileError as exc:
            raise ResidualPolicyFormatError(
                f"{path}: the embedded base policy is not a valid GP policy ({exc})"
            ) from exc
    base_path = Path(ref["path"])
    if not base_path.is_absolute():
        base_path = path.parent / base_path
    if not base_path.exists():
        raise ResidualPolicyFormatError(
            f"{path}: its base policy {base_path} does not exist; pass base=... to load()"
        )
    if _sha256(base_path) != ref.get("sha256"):
        raise ResidualPolicyFormatError(
            f"{path}: the base policy at {base_path} changed since fine-tuning (SHA-256 differs)"
        )
    return load_any_policy(base_path), base_path


# --------------------------------------------------------------------------------------------
# Evaluation on held-out layouts
# --------------------------------------------------------------------------------------------


def evaluate_stages(
    policy: Any,
    env_fn: Callable[[], gym.Env],
    seeds: Sequence[int],
    *,
    deterministic: bool = True,
    env: gym.Env | None = None,
) -> dict[str, Any]:
    """Run one episode per seed and report per-stage success.

    A stage counts if its ``info`` flag (:data:`STAGE_KEYS`, those the env reports) was true at
    any step of the episode, as in :func:`lgp_policy.app.evaluation.evaluate_policy_stages` (which
    takes env ids; this one takes any env factory, e.g. a harder variant). Because ``cup_placed``
    is the env's "stands under the spout now", the rates also hold ``cup_placed_at_end``: a
    residual that knocks the cup over after it was placed loses that one. Returns ``{"episodes",
    "rates": {flag: rate}, "mean_return", "mean_length"}``.
    """
    own = env is None
    env = env_fn() if own else env
    policy = _bind(policy, env)
    hits = {k: 0 for k in STAGE_KEYS}
    placed_at_end = 0
    seen: set[str] = set()
    returns, lengths = [], []
    try:
        for seed in seeds:
            obs, info = env.reset(seed=int(seed))
            ever = {k: bool(info.get(k, False)) for k in STAGE_KEYS}
            state, start, ret, n = None, True, 0.0, 0
            done = False
            while not done:
                action, state = policy.predict(
                    obs[None, :],
                    state=state,
                    episode_start=np.array([start]),
                    deterministic=deterministic,
                )
                start = False
                obs, reward, terminated, truncated, info = env.step(np.asarray(action)[0])
                ret += float(reward)
                n += 1
                for k in STAGE_KEYS:
                    if k in info:
                        seen.add(k)
                        ever[k] = ever[k] or bool(info[k])
                done = terminated or truncated
            for k in STAGE_KEYS:
                hits[k] += ever[k]
            placed_at_end += bool(info.get("cup_placed", False))
            returns.append(ret)
            lengths.append(n)
    finally:
        if own:
            env.close()
    n_ep = max(len(seeds), 1)
    rates = {k: hits[k] / n_ep for k in STAGE_KEYS if k in seen}
    if "cup_placed" in seen:
        rates["cup_placed_at_end"] = placed_at_end / n_ep
    return {
        "episodes": len(seeds),
        "rates": rates,
        "mean_return": float(np.mean(returns)) if returns else float("nan"),
        "mean_length": float(np.mean(lengths)) if lengths else float("nan"),
    }


# --------------------------------------------------------------------------------------------
# Fine-tuning
# --------------------------------------------------------------------------------------------


@dataclass
class FinetuneResult:
    """What :func:`finetune` returns."""

    policy: ResidualPolicy
    curve: list[dict[str, Any]] = field(default_factory=list)
    env_steps: int = 0
    agent_steps: int = 0
    wall_time_s: float = 0.0
    out_dir: Path | None = None


def _curve_value(entry: Mapping[str, Any]) -> float:
    rates = entry["rates"]
    for key in ("button_pressed", "is_success"):
        if key in rates:
            return float(rates[key])
    return float(entry["mean_return"])


def finetune(
    base: Any,
    env_fn: Callable[[], gym.Env],
    *,
    algo: str = "sac",
    total_env_steps: int = 100_000,
    seed: int = 0,
    scale: float = 0.5,
    gate: Any = None,
    residual_dims: Sequence[int] | None = None,
    include_gate_obs: bool = True,
    skip_ungated: bool = True,
    reward_fn: Callable[[float, Mapping[str, Any], Mapping[str, Any]], float] | None = None,
    normalize_obs: bool = True,
    n_envs: int = 1,
    hyperparameters: Mapping[str, Any] | None = None,
    eval_env_fn: Callable[[], gym.Env] | None = None,
    eval_episodes: int = 20,
    eval_seeds: Sequence[int] | None = None,
    eval_freq: int = 10_000,
    checkpoint_freq: int = 25_000,
    out_dir: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
    base_path: str | os.PathLike[str] | None = None,
    progress: bool = True,
    verbose: int = 0,
) -> FinetuneResult:
    """Fine-tune a residual on top of ``base`` with an unmodified SB3 algorithm.

    Arguments:
        base: the base ``PolicyPredictor``.
        env_fn: makes one training env (the plain task env; it is wrapped here).
        algo: ``"sac"``, ``"td3"`` or ``"ppo"`` (defaults in :data:`DEFAULT_HYPERPARAMETERS`).
        total_env_steps: budget in **env** steps (skipped ungated steps count).
        seed: seeds the model and the training envs (``seed + i`` for env ``i``).
        n_envs: training envs; more than one runs them in ``SubprocVecEnv`` processes (the base
            must pickle), one uses ``DummyVecEnv`` (best on a 2-core machine: the SAC update
            dominates, not the env).
        eval_env_fn, eval_episodes, eval_seeds, eval_freq: the learning curve: every
            ``eval_freq`` env steps, the current policy runs one episode on each held-out layout
            (default seeds ``CURVE_SEED_OFFSET + i``); evaluation steps are not counted in the
            budget.
        checkpoint_freq: every that many env steps a checkpoint ``checkpoints/step_<N>.npz``.
        out_dir: where ``residual_policy.npz``, ``learning_curve.png``/``.json`` and the
            checkpoints go (nothing is written without it).
        base_path: the base's file, embedded into the saved policies.
        normalize_obs: wrap the training envs in SB3's ``VecNormalize`` (observations only;
            the agent observation mixes seconds, radians, metres and a 0-8 mm button travel);
            its statistics are frozen into the returned policy and saved with it.
        reward_fn: ``reward_fn(env_reward, info, previous_info)``, the agent's reward per env
            step (default: the env's own reward; the coffee env's dense reward pays its stage
            bonus once per stage change, +1 on reaching a stage and -1 on losing one).

    Returns:
        :class:`FinetuneResult` with the policy, the curve and the step counts.
    """
    _, torch = require_rl()
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    if total_env_steps <= 0:
        raise ValueError(f"total_env_steps must be positive, got {total_env_steps}")
    torch.set_num_threads(1)
    hp = _resolve_hyperparameters(algo, hyperparameters)
    if algo in ("sac", "td3"):
        hp["buffer_size"] = int(min(hp["buffer_size"], total_env_steps))
    gate = gate if gate is not None else PhaseGate()
    out = None if out_dir is None else Path(out_dir)
    if out is not None:
        final = out / "residual_policy.npz"
        if final.exists() and not overwrite:
            raise FileExistsError(f"{final} exists; pass overwrite=True (CLI: --force)")
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)

    def make_wrapped(rank: int) -> Callable[[], gym.Env]:
        def _init() -> gym.Env:
            from stable_baselines3.common.monitor import Monitor

            env = ResidualWrapper(
                env_fn(),
                base,
                scale=scale,
                gate=gate,
                residual_dims=residual_dims,
                include_gate_obs=include_gate_obs,
                skip_ungated=skip_ungated,
                reward_fn=reward_fn,
            )
            return Monitor(env)

        return _init

    fns = [make_wrapped(i) for i in range(n_envs)]
    vec_env = SubprocVecEnv(fns) if n_envs > 1 else DummyVecEnv(fns)
    vec_env.seed(seed)
    normalizer = None
    if normalize_obs:
        from stable_baselines3.common.vec_env import VecNormalize

        vec_env = VecNormalize(vec_env, norm_obs=True, norm_reward=False, clip_obs=10.0)
        normalizer = _LiveNormalizer(vec_env)
    model = _build_model(algo, vec_env, hp, seed=seed, verbose=verbose)
    seeds = (
        list(eval_seeds)
        if eval_seeds is not None
        else [CURVE_SEED_OFFSET + i for i in range(eval_episodes)]
    )
    eval_make = eval_env_fn or env_fn
    eval_env: gym.Env | None = eval_make()
    act_space = eval_env.action_space
    if not seeds:
        eval_env.close()
        eval_env = None
    policy = ResidualPolicy(
        base,
        model,
        scale=scale,
        gate=gate,
        residual_dims=residual_dims,
        include_gate_obs=include_gate_obs,
        action_space=act_space,
        algo=algo,
        hyperparameters=hp,
        base_path=base_path,
        obs_normalizer=normalizer,
    )
    curve: list[dict[str, Any]] = []
    t0 = time.perf_counter()

    def record(env_steps: int) -> None:
        if eval_env is None:
            return
        entry = evaluate_stages(policy, eval_make, seeds, env=eval_env)
        entry["env_steps"] = env_steps
        entry["wall_time_s"] = time.perf_counter() - t0
        curve.append(entry)

    class _Progress(BaseCallback):
        """Counts env steps, updates the bar, evaluates, checkpoints, stops at the budget."""

        def __init__(self) -> None:
            super().__init__()
            self.env_steps = 0
            self.next_eval = eval_freq
            self.next_ckpt = checkpoint_freq
            self.bar: Any = None

        def _on_training_start(self) -> None:
            if progress:
                from tqdm.auto import tqdm

                self.bar = tqdm(
                    total=total_env_steps, unit="step", desc=f"finetune {algo}", mininterval=0.5
                )
                if curve:
                    self.bar.set_postfix(held_out=f"{_curve_value(curve[-1]):.2f}")

        def _on_step(self) -> bool:
            n = sum(int(i.get("env_steps", 1)) for i in self.locals.get("infos", []))
            self.env_steps += n
            if self.bar is not None:
                self.bar.update(min(n, max(total_env_steps - self.bar.n, 0)))
            if eval_freq > 0 and self.env_steps >= self.next_eval:
                self.next_eval += eval_freq
                record(self.env_steps)
                if self.bar is not None:
                    self.bar.set_postfix(held_out=f"{_curve_value(curve[-1]):.2f}")
            if out is not None and checkpoint_freq > 0 and self.env_steps >= self.next_ckpt:
                self.next_ckpt += checkpoint_freq
                policy.save(
                    out / "checkpoints" / f"step_{self.env_steps:07d}.npz",
                    overwrite=True,
                    embed_base=False,
                )
            return self.env_steps < total_env_steps

        def _on_training_end(self) -> None:
            if self.bar is not None:
                self.bar.close()

    callback = _Progress()
    try:
        record(0)
        # Agent steps <= env steps, so the env-step budget (enforced by the callback) binds.
        model.learn(total_timesteps=total_env_steps, callback=callback, progress_bar=False)
        if not curve or curve[-1]["env_steps"] != callback.env_steps:
            record(callback.env_steps)
    finally:
        vec_env.close()
        if eval_env is not None:
            eval_env.close()
    if isinstance(policy.obs_normalizer, _LiveNormalizer):
        policy.obs_normalizer = policy.obs_normalizer.freeze()
    result = FinetuneResult(
        policy=policy,
        curve=curve,
        env_steps=callback.env_steps,
        agent_steps=int(model.num_timesteps),
        wall_time_s=time.perf_counter() - t0,
        out_dir=out,
    )
    if out is not None:
        policy.save(out / "residual_policy.npz", overwrite=overwrite)
        summary = {
            "algo": algo,
            "seed": seed,
            "scale": scale,
            "gate": policy.gate.to_config() if hasattr(policy.gate, "to_config") else None,
            "total_env_steps": total_env_steps,
            "env_steps": result.env_steps,
            "agent_steps": result.agent_steps,
            "wall_time_s": result.wall_time_s,
            "hyperparameters": hp,
            "curve": curve,
        }
        (out / "learning_curve.json").write_text(json.dumps(summary, indent=2))
        if curve:
            plot_learning_curve(curve, out / "learning_curve.png", title=f"residual {algo}")
    return result


def plot_learning_curve(
    curve: Sequence[Mapping[str, Any]], path: str | os.PathLike[str], *, title: str = ""
) -> Path:
    """Per-stage success on the held-out layouts versus training env steps."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    steps = [c["env_steps"] for c in curve]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    keys = [k for k in STAGE_KEYS if k in curve[0]["rates"]]
    if keys:
        for key in keys:
            ax.plot(steps, [c["rates"][key] for c in curve], marker="o", label=key)
        ax.set_ylabel(f"success on {curve[0]['episodes']} held-out layouts")
        ax.set_ylim(-0.02, 1.02)
        ax.axhline(0.95, color="grey", lw=0.8, ls="--")
        ax.legend(loc="lower right", fontsize=8)
    else:
        ax.plot(steps, [c["mean_return"] for c in curve], marker="o")
        ax.set_ylabel(f"mean return, {curve[0]['episodes']} held-out episodes")
    ax.set_xlabel("training env steps")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    path.write_bytes(buf.getvalue())
    return path
