"""The SB3 side: the optional dependency, default hyperparameters, model building, zero start.

stable-baselines3 and torch are imported lazily (:func:`require_rl`): the rest of
:mod:`lgp_policy.residual` works without the ``rl`` extra.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

__all__ = [
    "ALGOS",
    "DEFAULT_HYPERPARAMETERS",
    "RL_EXTRA_HINT",
    "build_model",
    "policy_arrays",
    "require_rl",
    "resolve_hyperparameters",
    "zero_init_residual_actor",
]

RL_EXTRA_HINT = 'pip install "gym-coffee[rl]"'
ALGOS = ("sac", "td3", "ppo")
ACTIVATIONS = ("relu", "tanh", "elu")

# Off-policy warm-up: ``learning_starts=0`` so that SB3 never samples the uniform "random warm-up"
# actions of ``action_space.sample()`` (full-scale residuals); exploration comes from the
# zero-initialised actor itself (SAC: its own Gaussian with a small initial std; TD3: Gaussian
# action noise of std ``action_noise_sigma``; PPO: its Gaussian with ``log_std_init``).
_OFF_POLICY: dict[str, Any] = {
    "buffer_size": 100_000,
    "batch_size": 256,
    "gamma": 0.98,
    "tau": 0.02,
    "train_freq": 1,
    "gradient_steps": 1,
    "learning_starts": 0,
    "policy_kwargs": {"net_arch": [64, 64], "activation_fn": "relu"},
}
DEFAULT_HYPERPARAMETERS: dict[str, dict[str, Any]] = {
    "sac": {**_OFF_POLICY, "learning_rate": 3e-4, "ent_coef": 0.01, "initial_std": 0.3},
    "td3": {**_OFF_POLICY, "learning_rate": 1e-3, "action_noise_sigma": 0.2},
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


def _activation(name: str) -> Any:
    _, torch = require_rl()
    table = {"relu": torch.nn.ReLU, "tanh": torch.nn.Tanh, "elu": torch.nn.ELU}
    if name not in table:
        raise ValueError(f"unknown activation_fn {name!r} (known: {sorted(table)})")
    return table[name]


def resolve_hyperparameters(algo: str, overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    """:data:`DEFAULT_HYPERPARAMETERS` for ``algo`` updated by ``overrides`` (``policy_kwargs``
    merged key by key); stays JSON-able, because it is written into the policy file."""
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    hp: dict[str, Any] = json.loads(json.dumps(DEFAULT_HYPERPARAMETERS[algo]))  # deep copy
    for key, value in (overrides or {}).items():
        if key == "policy_kwargs":
            hp["policy_kwargs"].update(value)
        else:
            hp[key] = value
    json.dumps(hp)
    return hp


def build_model(
    algo: str, env: Any, hyperparameters: Mapping[str, Any], seed: int | None, verbose: int = 0
) -> Any:
    """An SB3 algorithm on ``env`` with the residual actor zero-initialised
    (:func:`zero_init_residual_actor`)."""
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
    # SB3's own logger (made at learn() unless one is set) creates an empty SB3-<date> folder in
    # the system's temporary directory on every call; this one writes nowhere but the console.
    from stable_baselines3.common.logger import HumanOutputFormat, KVWriter, Logger

    formats: list[KVWriter] = [HumanOutputFormat(sys.stdout)] if verbose >= 1 else []
    model.set_logger(Logger(folder=None, output_formats=formats))
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


class SpacesEnv(gym.Env[Any, Any]):
    """A stand-in env that only carries spaces, to rebuild an SB3 model for prediction."""

    def __init__(self, observation_space: spaces.Box, action_space: spaces.Box) -> None:
        self.observation_space = observation_space
        self.action_space = action_space

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action: Any) -> Any:
        raise RuntimeError("SpacesEnv only carries spaces; it cannot be stepped")


def policy_arrays(model: Any) -> dict[str, NDArray[np.float32]]:
    """The SB3 policy's ``state_dict`` as named float32 arrays (what the policy file stores)."""
    return {
        name: tensor.detach().cpu().numpy().astype(np.float32, copy=True)
        for name, tensor in model.policy.state_dict().items()
    }
