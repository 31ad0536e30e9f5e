"""The residual agent's env: an env plus a base policy, the residual composed on top."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from lgp_policy.residual.gates import PhaseGate

__all__ = [
    "ResidualWrapper",
    "RewardFn",
    "agent_observation_space",
    "check_residual_dims",
    "check_scale",
    "compose",
]

RewardFn = Callable[[float, Mapping[str, Any], Mapping[str, Any]], float]
"""``reward_fn(env_reward, info, previous_info) -> float``: the agent's reward per env step."""


def check_scale(scale: float) -> float:
    """``scale`` as a float, or a ValueError: finite, positive and at most 2 action ranges."""
    value = float(scale)
    if not (math.isfinite(value) and 0.0 < value <= 2.0):
        raise ValueError(f"scale must be a finite number in (0, 2] (action units), got {scale!r}")
    return value


def check_residual_dims(dims: Sequence[int] | None, act_dim: int) -> NDArray[np.intp]:
    """The action entries the residual changes (default all), validated against ``act_dim``."""
    out = np.arange(act_dim) if dims is None else np.asarray(list(dims))
    if (
        out.ndim != 1
        or out.size == 0
        or not np.issubdtype(out.dtype, np.integer)
        or np.any((out < 0) | (out >= act_dim))
    ):
        raise ValueError(f"residual_dims must index the {act_dim} action entries, got {dims}")
    if len(set(out.tolist())) != out.size:
        raise ValueError(f"residual_dims has repeated entries: {out.tolist()}")
    return out.astype(np.intp)


def compose(
    base_action: NDArray[Any],
    gate: NDArray[Any],
    residual: NDArray[Any],
    scale: float,
    dims: NDArray[np.intp],
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
    applied[:, dims] += delta
    return np.clip(applied, low, high).astype(np.float32)


def agent_observation_space(
    obs_space: spaces.Box, act_space: spaces.Box, include_gate: bool
) -> spaces.Box:
    """``[env observation, base action, gate]``'s space (the gate entry only if included)."""
    lows = [obs_space.low.astype(np.float32), act_space.low.astype(np.float32)]
    highs = [obs_space.high.astype(np.float32), act_space.high.astype(np.float32)]
    if include_gate:
        lows.append(np.zeros(1, np.float32))
        highs.append(np.ones(1, np.float32))
    return spaces.Box(np.concatenate(lows), np.concatenate(highs), dtype=np.float32)


class ResidualWrapper(gym.Wrapper[Any, Any, Any, Any]):
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
            (default :class:`~lgp_policy.residual.gates.PhaseGate`).
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
    """

    def __init__(
        self,
        env: gym.Env[Any, Any],
        base: Any,
        *,
        scale: float = 0.5,
        gate: Callable[..., NDArray[Any]] | None = None,
        residual_dims: Sequence[int] | None = None,
        include_gate_obs: bool = True,
        skip_ungated: bool = False,
        reward_fn: RewardFn | None = None,
    ) -> None:
        super().__init__(env)
        if not hasattr(base, "predict"):
            raise TypeError(f"base must have a predict() method, got {type(base).__name__}")
        obs_space, act_space = env.observation_space, env.action_space
        if not (isinstance(obs_space, spaces.Box) and len(obs_space.shape) == 1):
            raise TypeError(f"ResidualWrapper needs a flat Box observation space, got {obs_space}")
        if not (isinstance(act_space, spaces.Box) and len(act_space.shape) == 1):
            raise TypeError(f"ResidualWrapper needs a flat Box action space, got {act_space}")
        self.base = base
        self.scale = check_scale(scale)
        self.gate = gate if gate is not None else PhaseGate()
        dims = check_residual_dims(residual_dims, act_space.shape[0])
        self.residual_dims = dims
        self.include_gate_obs = bool(include_gate_obs)
        self.skip_ungated = bool(skip_ungated)
        self.reward_fn = reward_fn
        self._prev_info: Mapping[str, Any] = {}
        self._act_low = act_space.low.astype(np.float32)
        self._act_high = act_space.high.astype(np.float32)
        self.observation_space = agent_observation_space(obs_space, act_space, include_gate_obs)
        self.action_space = spaces.Box(-1.0, 1.0, (dims.size,), np.float32)
        self._obs: NDArray[Any] | None = None
        self._base_action: NDArray[np.float32] | None = None
        self._gate_value = np.float32(0.0)
        self._base_state: Any = None
        self._episode_start = True

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
        applied = compose(
            self._base_action[None, :],
            np.array([self._gate_value]),
            residual,
            self.scale,
            self.residual_dims,
            self._act_low,
            self._act_high,
        )[0]
        obs, reward, terminated, truncated, info = self.env.step(applied)
        total_reward = self._reward(float(reward), info)
        env_steps = 1
        # The base is also asked in a final state: the agent's last observation must hold the
        # base action there (SB3 bootstraps truncated episodes from it); it is never applied.
        self._query_base(obs)
        while self.skip_ungated and self._gate_value == 0.0 and not (terminated or truncated):
            obs, reward, terminated, truncated, info = self.env.step(
                np.clip(self._base_action, self._act_low, self._act_high)
            )
            total_reward += self._reward(float(reward), info)
            env_steps += 1
            self._query_base(obs)
        info = dict(info)
        info["env_steps"] = env_steps
        info["residual_gate"] = gate_applied
        info["base_action"] = base_applied
        return self._agent_obs(), total_reward, bool(terminated), bool(truncated), info
