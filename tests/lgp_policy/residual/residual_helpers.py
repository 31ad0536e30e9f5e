"""Shared helpers of the residual tests: small bases, envs and a curve evaluation."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import TimeAwareObservation

TIME_INDEX = 3  # Pendulum (cos, sin, thetadot) + normalised time


class PendulumPD:
    """A stateless PolicyPredictor for Pendulum-v1 (+ normalised time); exposes its phase."""

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        obs = np.asarray(observation, dtype=np.float64)
        o = np.atleast_2d(obs)
        theta = np.arctan2(o[:, 1], o[:, 0])
        a = np.clip((-2.0 * theta - 0.5 * o[:, 2]) / 2.0, -1.0, 1.0)[:, None].astype(np.float32)
        return (a if obs.ndim == 2 else a[0]), state

    def phase(self, observation):
        return np.atleast_2d(observation)[:, TIME_INDEX]


def make_pendulum() -> gym.Env:
    return TimeAwareObservation(gym.make("Pendulum-v1"), normalize_time=True)


def pendulum_curve(policy):
    """A learning-curve point through the app's episode loop (Pendulum has no stage flags)."""
    from lgp_policy.rollout import run_episode

    env = make_pendulum()
    lengths = [run_episode(policy, env, seed).length for seed in (20_000, 20_001)]
    env.close()
    return {"episodes": 2, "rates": {}, "mean_length": float(np.mean(lengths))}


class Recorder(gym.Wrapper):
    """Records the actions the inner env receives."""

    def __init__(self, env):
        super().__init__(env)
        self.actions = []

    def step(self, action):
        self.actions.append(np.array(action, copy=True))
        return self.env.step(action)


def rollout_base(env, base, seed, n_steps):
    obs, _ = env.reset(seed=seed)
    observations, rewards = [obs], []
    for _ in range(n_steps):
        action, _ = base.predict(obs[None, :], deterministic=True)
        obs, reward, terminated, truncated, _ = env.step(action[0])
        observations.append(obs)
        rewards.append(reward)
        if terminated or truncated:
            break
    return np.array(observations), np.array(rewards)


class CoffeeSway:
    """A cheap stateless base for the coffee env: joint targets swaying with time."""

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        from gym_coffee.env import OBS_SLICES
        from gym_coffee.robot import NEUTRAL_JOINTS, action_from_targets

        obs = np.atleast_2d(np.asarray(observation, dtype=np.float64))
        t = obs[:, OBS_SLICES["time"]]
        q = obs[:, OBS_SLICES["joint_pos"]]
        target = NEUTRAL_JOINTS + 0.3 * np.sin(2.0 * t + np.arange(7))
        a = action_from_targets(q, target, 0.04)
        return (a if np.ndim(observation) == 2 else a[0]), state


class TeacherBase:
    """The scripted teacher of one env as a base policy (it reads the env's true task points)."""

    def __init__(self, env):
        from gym_coffee.teacher import ScriptedTeacher

        self.teacher = ScriptedTeacher(env, rng=0, variation=0.0)

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        obs = np.asarray(observation)
        if obs.ndim == 2:
            return self.teacher.act(obs[0])[None, :], state
        return self.teacher.act(obs), state


def make_coffee(**kwargs):
    import gym_coffee

    return gym.make(gym_coffee.ENV_ID, **kwargs)


def coffee_gate(start=0.5):
    from gym_coffee.env import OBS_SLICES
    from lgp_policy.residual import PhaseGate

    return PhaseGate(
        start=start,
        ramp=0.1,
        source="observation",
        time_index=OBS_SLICES["time"].start,
        time_scale=4.0,
    )
