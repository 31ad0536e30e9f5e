"""Seeded evaluation of a policy on held-out coffee-task layouts, per stage, with Wilson intervals.

Layouts come from ``reset(seed=EVAL_SEED_OFFSET + seed + i)``, ``i = 0..n_episodes-1``;
demonstrations use ``seed, seed + 1, ...`` below the offset, so the two never share a layout
(``docs/CONTRACTS.md``). An episode counts a stage as reached if its ``info`` flag was true at any
step (``cup_grasped``, ``cup_placed``, ``button_pressed``, ``is_success``).

With ``workers > 1`` the episodes run in a Gymnasium ``AsyncVectorEnv`` (one process per worker)
with autoreset disabled: a finished sub-environment is reset with the next seed through
``reset_mask``, so each episode's layout is exactly the one of its seed, whatever the worker count.
The policy runs in the calling process and gets the batch of observations.
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "DEFAULT_ENV_ID",
    "EVAL_SEED_OFFSET",
    "STAGES",
    "evaluate_policy_stages",
    "format_results",
    "wilson_interval",
]

EVAL_SEED_OFFSET = 10_000
"""Evaluation layouts use seeds ``EVAL_SEED_OFFSET + seed + i`` (disjoint from demonstrations)."""
DEFAULT_ENV_ID = "gym_coffee/CoffeeTask-v0"
STAGES = ("cup_grasped", "cup_placed", "button_pressed", "is_success")
"""Per-episode flags, in task order; an episode reached a stage if the flag was ever true."""


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion.

    Args:
        successes: number of successes ``k``.
        n: number of trials (``0`` gives ``(0, 1)``).
        confidence: two-sided level.

    Returns:
        ``(low, high)`` in ``[0, 1]``.
    """
    if n <= 0:
        return 0.0, 1.0
    if not 0 <= successes <= n:
        raise ValueError(f"successes must be in [0, {n}], got {successes}")
    from scipy.stats import norm

    z = float(norm.ppf(0.5 + confidence / 2.0))
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    lo = 0.0 if successes == 0 else max(0.0, centre - half)  # exact at the ends (no round-off)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return lo, hi


def _make_env(env_id: str, env_kwargs: Mapping[str, Any] | None, render: bool = False) -> Any:
    import gymnasium as gym

    import gym_coffee  # noqa: F401  (registers the env ids)

    kwargs = dict(env_kwargs or {})
    if render:
        kwargs["render_mode"] = "rgb_array"
    return gym.make(env_id, **kwargs)


class _EnvFactory:
    """Picklable env constructor for ``AsyncVectorEnv`` workers."""

    def __init__(self, env_id: str, env_kwargs: Mapping[str, Any] | None) -> None:
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs or {})

    def __call__(self) -> Any:
        return _make_env(self.env_id, self.env_kwargs)


def _run_episode(policy, env, seed: int, on_step=None) -> dict[str, Any]:
    """One deterministic episode on ``reset(seed=seed)``: its length and the stages it reached.

    ``on_step(length)`` is called after the reset (length 0) and after every control step (the
    video recorder renders there).
    """
    obs, info = env.reset(seed=int(seed))
    reached = {k: bool(info.get(k, False)) for k in STAGES}
    length, done = 0, False
    if on_step is not None:
        on_step(length)
    while not done:
        action, _ = policy.predict(obs, deterministic=True)
        obs, _r, terminated, truncated, info = env.step(action)
        length += 1
        for k in STAGES:
            reached[k] |= bool(info.get(k, False))
        if on_step is not None:
            on_step(length)
        done = bool(terminated or truncated)
    return {"seed": int(seed), "length": length, **reached}


def _run_serial(policy, env, seeds, bar) -> list[dict[str, Any]]:
    episodes = []
    for seed in seeds:
        episodes.append(_run_episode(policy, env, seed))
        if bar is not None:
            bar.update(1)
    return episodes


def _run_vector(policy, env_id, env_kwargs, seeds, workers, bar) -> list[dict[str, Any]]:
    from gymnasium.vector import AsyncVectorEnv, AutoresetMode

    n_envs = min(workers, len(seeds))
    envs = AsyncVectorEnv(
        [_EnvFactory(env_id, env_kwargs) for _ in range(n_envs)],
        autoreset_mode=AutoresetMode.DISABLED,
    )
    episodes: list[dict[str, Any]] = []
    try:
        next_i = n_envs
        current = list(range(n_envs))  # index into seeds, or -1 when idle
        obs, infos = envs.reset(seed=[int(seeds[i]) for i in current])
        reached = [{k: bool(_info_at(infos, k, j)) for k in STAGES} for j in range(n_envs)]
        lengths = [0] * n_envs
        while any(c >= 0 for c in current):
            actions, _ = policy.predict(obs, deterministic=True)
            obs, _r, terminated, truncated, infos = envs.step(actions)
            done = np.logical_or(terminated, truncated)
            mask = np.zeros(n_envs, dtype=bool)
            new_seeds: list[int | None] = [None] * n_envs
            for j in range(n_envs):
                if current[j] < 0:
                    continue
                lengths[j] += 1
                for k in STAGES:
                    reached[j][k] |= bool(_info_at(infos, k, j))
                if done[j]:
                    episodes.append(
                        {"seed": int(seeds[current[j]]), "length": lengths[j], **reached[j]}
                    )
                    if bar is not None:
                        bar.update(1)
                    if next_i < len(seeds):
                        current[j] = next_i
                        next_i += 1
                        mask[j] = True
                        new_seeds[j] = int(seeds[current[j]])
                    else:
                        current[j] = -1
            if mask.any():
                obs_new, infos_new = envs.reset(seed=new_seeds, options={"reset_mask": mask})
                obs = np.where(mask[:, None], obs_new, obs)
                for j in np.flatnonzero(mask):
                    reached[j] = {k: bool(_info_at(infos_new, k, j)) for k in STAGES}
                    lengths[j] = 0
    finally:
        envs.close()
    order = {int(s): i for i, s in enumerate(seeds)}
    return sorted(episodes, key=lambda e: order[e["seed"]])


def _info_at(infos: Mapping[str, Any], key: str, j: int) -> bool:
    if key not in infos:
        return False
    present = infos.get(f"_{key}")
    if present is not None and not present[j]:
        return False
    return bool(infos[key][j])


def record_rollout(
    policy: Any,
    path: str | Path,
    seed: int,
    *,
    env_id: str = DEFAULT_ENV_ID,
    env_kwargs: Mapping[str, Any] | None = None,
    fps: float | None = None,
    every: int = 3,
) -> dict[str, Any]:
    """Roll out ``policy`` on the layout of ``reset(seed=seed)`` and write a video (.mp4 or .gif).

    Args:
        every: keep every ``every``-th control step as a frame (rendering costs ~0.17 s a
            frame with PyBullet's TinyRenderer; the video still plays in real time).

    Returns:
        The episode's record (stages reached, length) plus ``"video"``: the path written.
    """
    from gym_coffee.video import write_video

    env = _make_env(env_id, env_kwargs, render=True)
    try:
        frames: list[Any] = []

        def grab(length: int) -> None:
            if length == 0 or length % every == 0:
                frames.append(env.render())

        record = _run_episode(policy, env, seed, on_step=grab)
        frames.append(env.render())
        for _ in range(5):  # hold the last frame a moment
            frames.append(frames[-1])
        if fps is None:
            from gym_coffee.env import CONTROL_DT

            fps = 1.0 / (every * CONTROL_DT)
        written = write_video(path, frames, fps=fps)
    finally:
        env.close()
    return {**record, "video": str(written)}


def evaluate_policy_stages(
    policy: Any,
    n_episodes: int,
    seed: int = 0,
    workers: int = 1,
    video: str | Path | None = None,
    progress: bool = True,
    *,
    env_id: str = DEFAULT_ENV_ID,
    env_kwargs: Mapping[str, Any] | None = None,
    confidence: float = 0.95,
) -> dict[str, Any]:
    """Run ``policy`` on ``n_episodes`` held-out layouts and report per-stage success.

    Args:
        policy: anything with SB3's ``predict(observation, state, episode_start, deterministic)``
            accepting ``(OBS_DIM,)`` and, for ``workers > 1``, ``(n, OBS_DIM)``.
        n_episodes: number of layouts.
        seed: layouts use ``EVAL_SEED_OFFSET + seed + i``.
        workers: parallel environments (``AsyncVectorEnv`` subprocesses) when ``> 1``.
        video: if given, also record the first evaluation layout to this ``.mp4``/``.gif``.
        progress: show a tqdm progress bar.
        env_id, env_kwargs: the environment.
        confidence: level of the Wilson intervals.

    Returns:
        ``{"n_episodes", "seed", "seeds", "workers", "stages": {stage: {"successes", "rate",
        "ci_low", "ci_high"}}, "episode_length": {"mean", "std", "min", "max"},
        "episodes": [...], "wall_time_s", "video"}``.
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be >= 1, got {n_episodes}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    seeds = [EVAL_SEED_OFFSET + int(seed) + i for i in range(int(n_episodes))]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(seeds), desc="evaluating", unit="episode")
    start = _time.perf_counter()
    try:
        if workers > 1 and len(seeds) > 1:
            episodes = _run_vector(policy, env_id, env_kwargs, seeds, workers, bar)
        else:
            env = _make_env(env_id, env_kwargs)
            try:
                episodes = _run_serial(policy, env, seeds, bar)
            finally:
                env.close()
    finally:
        if bar is not None:
            bar.close()
    wall = _time.perf_counter() - start
    n = len(episodes)
    stages = {}
    for k in STAGES:
        k_succ = sum(bool(e[k]) for e in episodes)
        lo, hi = wilson_interval(k_succ, n, confidence)
        stages[k] = {"successes": k_succ, "rate": k_succ / n, "ci_low": lo, "ci_high": hi}
    lengths = np.array([e["length"] for e in episodes], dtype=float)
    result: dict[str, Any] = {
        "n_episodes": n,
        "seed": int(seed),
        "seeds": seeds,
        "workers": int(workers),
        "confidence": confidence,
        "stages": stages,
        "episode_length": {
            "mean": float(lengths.mean()),
            "std": float(lengths.std()),
            "min": int(lengths.min()),
            "max": int(lengths.max()),
        },
        "episodes": episodes,
        "wall_time_s": wall,
        "video": None,
    }
    if video is not None:
        rec = record_rollout(policy, video, seeds[0], env_id=env_id, env_kwargs=env_kwargs)
        result["video"] = rec["video"]
    return result


def format_results(result: Mapping[str, Any]) -> str:
    """The per-stage table of :func:`evaluate_policy_stages` as text."""
    pct = round(100 * result.get("confidence", 0.95))
    lines = [f"{'stage':<16}{'success':>10}{'rate':>8}   {pct}% Wilson interval"]
    for k, v in result["stages"].items():
        lines.append(
            f"{k:<16}{v['successes']:>5}/{result['n_episodes']:<4}{100 * v['rate']:>7.1f}%"
            f"   [{100 * v['ci_low']:.1f}%, {100 * v['ci_high']:.1f}%]"
        )
    el = result["episode_length"]
    lines.append(
        f"episode length: {el['mean']:.1f} +- {el['std']:.1f} steps "
        f"(min {el['min']}, max {el['max']})"
    )
    return "\n".join(lines)
