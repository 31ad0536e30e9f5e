"""The one episode loop: every roll-out in this project (evaluation, serial or parallel, local or
on Ray; the video; the reproduction figure's trace; the residual evaluator; the benchmarks) runs
through :func:`run_episode`.

It knows nothing about the coffee task: the info flags to track are passed in (the application
passes ``gym_coffee.STAGES`` and ``"is_success"``), so the residual layer can import it without
importing the application layer.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["Episode", "run_episode"]


@dataclass
class Episode:
    """What one episode did.

    Attributes:
        seed: the ``reset`` seed.
        length: control steps taken.
        total_reward: undiscounted sum of the env's rewards.
        reached: for each tracked flag the env reported at least once (at the reset or at a
            step), whether it was ever true; flags the env never reported are absent.
        final_info: the ``info`` of the last step (of the reset for a zero-length episode).
        terminated: whether the episode ended by termination (not by the time limit).
        observations: ``(length + 1, obs_dim)``, the reset observation and one per step, when
            asked for (``keep_observations=True``).
        actions: ``(length, act_dim)``, the actions taken (with ``keep_observations=True``).
        frames: rendered RGB frames, when asked for (``render=True``).
    """

    seed: int
    length: int
    total_reward: float
    reached: dict[str, bool]
    final_info: dict[str, Any]
    terminated: bool
    observations: NDArray[np.float64] | None = None
    actions: NDArray[np.float64] | None = None
    frames: list[NDArray[np.uint8]] = field(default_factory=list)

    def record(self, flags: Sequence[str]) -> dict[str, Any]:
        """The JSON-ready summary used in evaluation results: ``seed``, ``length``, ``return``
        and one boolean per flag (``False`` where the env never reported it)."""
        out: dict[str, Any] = {
            "seed": self.seed,
            "length": self.length,
            "return": self.total_reward,
        }
        out.update({k: bool(self.reached.get(k, False)) for k in flags})
        return out


def run_episode(
    policy: Any,
    env: Any,
    seed: int,
    *,
    flags: Sequence[str] = (),
    deterministic: bool = True,
    options: Mapping[str, Any] | None = None,
    render: bool = False,
    render_every: int = 1,
    keep_observations: bool = False,
    on_step: Callable[[Any, Any, float, Mapping[str, Any]], None] | None = None,
) -> Episode:
    """Run ``policy`` for one episode on ``env.reset(seed=seed, options=options)``.

    Args:
        policy: anything with stable-baselines3's ``predict(observation, state, episode_start,
            deterministic) -> (action, state)``; it gets one (unbatched) observation per call,
            ``episode_start`` true on the first step, and its returned ``state`` back.
        env: a Gymnasium env (created by the caller and reused across episodes: each episode
            is defined by its seed alone).
        seed: the reset seed; it fixes the episode's layout.
        flags: ``info`` keys whose "ever true" value to track (e.g. task stages).
        deterministic: passed to ``predict``.
        options: passed to ``reset`` (e.g. ``{"layout": {...}}``).
        render: collect ``env.render()`` after the reset, every ``render_every`` steps, and
            after the last step (the env must have been made with ``render_mode="rgb_array"``).
        render_every: keep every ``render_every``-th step as a frame.
        keep_observations: keep every observation and action (for traces computed afterwards).
        on_step: called after each step as ``on_step(observation, action, reward, info)``.

    Returns:
        The :class:`Episode`.
    """
    if render_every < 1:
        raise ValueError(f"render_every must be >= 1, got {render_every}")
    obs, info = env.reset(seed=int(seed), options=None if options is None else dict(options))
    reached = {k: bool(info[k]) for k in flags if k in info}
    observations = [np.array(obs, dtype=float)] if keep_observations else None
    actions: list[NDArray[np.float64]] = []
    frames = [env.render()] if render else []
    action_shape = getattr(getattr(env, "action_space", None), "shape", None)
    state: Any = None
    start = True
    length, total, terminated, done = 0, 0.0, False, False
    while not done:
        action, state = policy.predict(
            obs, state=state, episode_start=np.array([start]), deterministic=deterministic
        )
        action = np.asarray(action)
        if action_shape is not None and action.shape != action_shape and len(action) == 1:
            action = action[0]  # a policy that always answers with a batch
        start = False
        obs, reward, term, trunc, info = env.step(action)
        length += 1
        total += float(reward)
        for k in flags:
            if k in info:
                reached[k] = reached.get(k, False) or bool(info[k])
        terminated, done = bool(term), bool(term or trunc)
        if observations is not None:
            observations.append(np.array(obs, dtype=float))
            actions.append(np.array(action, dtype=float))
        if render and (done or length % render_every == 0):
            frames.append(env.render())
        if on_step is not None:
            on_step(obs, action, float(reward), info)
    return Episode(
        seed=int(seed),
        length=length,
        total_reward=total,
        reached=reached,
        final_info=dict(info),
        terminated=terminated,
        observations=None if observations is None else np.stack(observations),
        actions=np.stack(actions) if observations is not None and actions else None,
        frames=frames,
    )
