"""Fine-tuning: an unmodified SB3 algorithm learns the residual on top of a base policy."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from lgp_policy._io import atomic_write_text
from lgp_policy.residual.files import check_hyperparameters
from lgp_policy.residual.gates import PhaseGate
from lgp_policy.residual.models import build_model, require_rl, resolve_hyperparameters
from lgp_policy.residual.policy import ObsNormalizer, ResidualPolicy
from lgp_policy.residual.wrapper import (
    ResidualWrapper,
    RewardFn,
    check_residual_dims,
    check_scale,
)

__all__ = ["FinetuneResult", "finetune"]

Evaluate = Callable[[ResidualPolicy], Mapping[str, Any]]
"""``evaluate(policy) -> {"rates": {...}, ...}``: one point of the learning curve, supplied by
the caller (the application layer rolls episodes out with its one episode loop)."""


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


@dataclass
class FinetuneResult:
    """What :func:`finetune` returns."""

    policy: ResidualPolicy
    curve: list[dict[str, Any]] = field(default_factory=list)
    env_steps: int = 0
    agent_steps: int = 0
    wall_time_s: float = 0.0
    cpu_time_s: float = 0.0
    out_dir: Path | None = None
    #: With ``keep_best``: the env steps of the curve point whose policy was kept.
    kept_env_steps: int | None = None


class _WrappedEnvFactory:
    """Picklable: makes one training env (``SubprocVecEnv`` workers call it)."""

    def __init__(self, env_fn: Callable[[], gym.Env[Any, Any]], base: Any, **settings: Any):
        self.env_fn, self.base, self.settings = env_fn, base, settings

    def __call__(self) -> gym.Env[Any, Any]:
        from stable_baselines3.common.monitor import Monitor

        return Monitor(ResidualWrapper(self.env_fn(), self.base, **self.settings))


def _positive_int(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def finetune(
    base: Any,
    env_fn: Callable[[], gym.Env[Any, Any]],
    *,
    algo: str = "sac",
    total_env_steps: int = 100_000,
    seed: int = 0,
    scale: float = 0.5,
    gate: Any = None,
    residual_dims: Sequence[int] | None = None,
    include_gate_obs: bool = True,
    skip_ungated: bool = True,
    reward_fn: RewardFn | None = None,
    normalize_obs: bool = True,
    n_envs: int = 1,
    hyperparameters: Mapping[str, Any] | None = None,
    evaluate: Evaluate | None = None,
    eval_freq: int = 10_000,
    keep_best: bool = False,
    checkpoint_freq: int = 25_000,
    out_dir: str | Path | None = None,
    force: bool = False,
    base_path: str | Path | None = None,
    progress: bool = True,
    verbose: int = 0,
) -> FinetuneResult:
    """Fine-tune a residual on top of ``base`` with an unmodified SB3 algorithm.

    Arguments:
        base: the base ``PolicyPredictor``.
        env_fn: makes one training env (the plain task env; it is wrapped here).
        algo: ``"sac"``, ``"td3"`` or ``"ppo"`` (defaults in
            :data:`~lgp_policy.residual.models.DEFAULT_HYPERPARAMETERS`).
        total_env_steps: budget in **env** steps (skipped ungated steps count).
        seed: seeds the model and the training envs (``seed + i`` for env ``i``).
        n_envs: training envs; more than one runs them in ``SubprocVecEnv`` processes (the base
            must pickle), one uses ``DummyVecEnv`` (best on a 2-core machine: the SAC update
            dominates, not the env).
        reward_fn: ``reward_fn(env_reward, info, previous_info)``, the agent's reward per env
            step (default: the env's own reward; the coffee env's dense reward pays its stage
            bonus once per stage change, +1 on reaching a stage and -1 on losing one).
        evaluate, eval_freq: the learning curve: ``evaluate(policy)`` at the start, every
            ``eval_freq`` env steps and at the end (its steps are not counted in the budget).
        keep_best: return and save the policy of the curve point with the highest
            ``rates["is_success"]`` (the latest of equals; the start's, before any update, is a
            candidate) instead of the last one: model selection on ``evaluate``'s layouts, which
            must then be disjoint from those the result is judged on. Needs ``evaluate``.
        checkpoint_freq: every that many env steps a checkpoint ``checkpoints/step_<N>.npz``
            (a full policy file, base embedded).
        out_dir: where ``residual_policy.npz``, ``learning_curve.json`` and the checkpoints go
            (nothing is written without it); an existing ``residual_policy.npz`` is refused
            before any work unless ``force``.
        base_path: the base's file, embedded into the saved policies.
        normalize_obs: wrap the training envs in SB3's ``VecNormalize`` (observations only;
            the agent observation mixes seconds, radians, metres and a 0-8 mm button travel);
            its statistics are frozen into the returned policy and saved with it.

    Returns:
        :class:`FinetuneResult` with the policy, the curve, the step counts and the times.
    """
    total_env_steps = _positive_int("total_env_steps", total_env_steps)
    n_envs = _positive_int("n_envs", n_envs)
    scale = check_scale(scale)
    for name, value in (("eval_freq", eval_freq), ("checkpoint_freq", checkpoint_freq)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name} must be an integer >= 0 (0: never), got {value!r}")
    if keep_best and evaluate is None:
        raise ValueError("keep_best needs evaluate (the learning curve it selects on)")
    hp = resolve_hyperparameters(algo, hyperparameters)
    check_hyperparameters(algo, hp)
    gate = gate if gate is not None else PhaseGate()
    out = None if out_dir is None else Path(out_dir)
    if out is not None:
        final = out / "residual_policy.npz"
        if final.exists() and not force:
            raise FileExistsError(f"{final} exists; pass force=True (CLI: --force)")
    _, torch = require_rl()
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

    torch.set_num_threads(1)
    if algo in ("sac", "td3"):
        hp["buffer_size"] = int(min(hp["buffer_size"], total_env_steps))
    if out is not None:
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    probe = env_fn()
    act_space = probe.action_space
    probe.close()
    if not (isinstance(act_space, spaces.Box) and len(act_space.shape) == 1):
        raise TypeError(f"finetune needs a flat Box action space, got {act_space}")
    dims = check_residual_dims(residual_dims, int(act_space.shape[0]))
    shared = {
        "scale": scale,
        "gate": gate,
        "residual_dims": dims.tolist(),
        "include_gate_obs": include_gate_obs,
    }
    factory = _WrappedEnvFactory(
        env_fn, base, skip_ungated=skip_ungated, reward_fn=reward_fn, **shared
    )
    fns: list[Callable[[], gym.Env[Any, Any]]] = [factory] * n_envs
    vec_env: Any = SubprocVecEnv(fns) if n_envs > 1 else DummyVecEnv(fns)
    vec_env.seed(seed)
    normalizer = None
    if normalize_obs:
        vec_env = VecNormalize(vec_env, norm_obs=True, norm_reward=False, clip_obs=10.0)
        normalizer = _LiveNormalizer(vec_env)
    model = build_model(algo, vec_env, hp, seed=seed, verbose=verbose)
    policy = ResidualPolicy(
        base,
        model,
        **shared,
        action_space=act_space,
        algo=algo,
        hyperparameters=hp,
        base_path=base_path,
        obs_normalizer=normalizer,
    )
    curve: list[dict[str, Any]] = []
    kept: dict[str, Any] = {}  # keep_best: the best curve point's score, steps, weights, normaliser

    def record(env_steps: int) -> None:
        if evaluate is None:
            return
        entry = dict(evaluate(policy))
        entry["env_steps"] = env_steps
        entry["wall_time_s"] = time.perf_counter() - t0
        curve.append(entry)
        if not keep_best:
            return
        score = float(entry["rates"]["is_success"])
        if score >= kept.get("score", -1.0):
            norm = policy.obs_normalizer
            kept.update(
                score=score,
                env_steps=env_steps,
                weights={k: v.detach().clone() for k, v in model.policy.state_dict().items()},
                normalizer=norm.freeze() if isinstance(norm, _LiveNormalizer) else norm,
            )

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
                    total=total_env_steps,
                    unit="step",
                    desc=f"finetune {algo} seed {seed}",
                    mininterval=0.5,
                )

        def _on_step(self) -> bool:
            n = sum(int(i.get("env_steps", 1)) for i in self.locals.get("infos", []))
            self.env_steps += n
            if self.bar is not None:
                self.bar.update(min(n, max(total_env_steps - self.bar.n, 0)))
            if eval_freq > 0 and self.env_steps >= self.next_eval:
                self.next_eval += eval_freq
                record(self.env_steps)
            if out is not None and checkpoint_freq > 0 and self.env_steps >= self.next_ckpt:
                self.next_ckpt += checkpoint_freq
                policy.save(out / "checkpoints" / f"step_{self.env_steps:07d}.npz", force=True)
            return self.env_steps < total_env_steps

        def _on_training_end(self) -> None:
            if self.bar is not None:
                self.bar.close()

    callback = _Progress()
    try:
        record(0)
        # Agent steps <= env steps, so the env-step budget (enforced by the callback) binds.
        model.learn(total_timesteps=total_env_steps, callback=callback, progress_bar=False)
        if evaluate is not None and curve[-1]["env_steps"] != callback.env_steps:
            record(callback.env_steps)
    finally:
        vec_env.close()
    if isinstance(policy.obs_normalizer, _LiveNormalizer):
        policy.obs_normalizer = policy.obs_normalizer.freeze()
    if keep_best:
        model.policy.load_state_dict(kept["weights"])
        policy.obs_normalizer = kept["normalizer"]
    result = FinetuneResult(
        policy=policy,
        curve=curve,
        env_steps=callback.env_steps,
        agent_steps=int(model.num_timesteps),
        wall_time_s=time.perf_counter() - t0,
        cpu_time_s=time.process_time() - c0,
        out_dir=out,
        kept_env_steps=kept.get("env_steps"),
    )
    if out is not None:
        policy.save(out / "residual_policy.npz", force=force)
        summary = {
            "algo": algo,
            "seed": seed,
            "scale": scale,
            "gate": policy.gate.to_config() if hasattr(policy.gate, "to_config") else None,
            "total_env_steps": total_env_steps,
            "env_steps": result.env_steps,
            "agent_steps": result.agent_steps,
            "wall_time_s": result.wall_time_s,
            "cpu_time_s": result.cpu_time_s,
            "hyperparameters": hp,
            "reward_fn": "env reward" if reward_fn is None else repr(reward_fn),
            "curve": curve,
            "kept_env_steps": result.kept_env_steps,
        }
        atomic_write_text(out / "learning_curve.json", json.dumps(summary, indent=2), force=True)
    return result
