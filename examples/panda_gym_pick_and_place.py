"""Learn panda-gym's ``PandaPickAndPlace-v3`` from a few scripted demonstrations.

A task this project did not write: the panda-gym Panda with end-effector actions
(``a[:3] * 0.05`` m Cartesian displacement, ``a[3]`` the gripper's width change). A scripted
expert (written here) records demonstrations; :class:`~lgp_policy.lfd.policy.GPDemonstrationPolicy`
learns them as a Cartesian point robot (the state is the end-effector position) with two frames,
``object`` and ``goal``, and is evaluated on held-out layouts next to the expert:

    python examples/panda_gym_pick_and_place.py [--demos 6] [--episodes 50]

The observation (panda-gym's dict, flattened by Gymnasium in key order) is
``[achieved_goal (3), desired_goal (3), ee position (3), ee velocity (3), finger width (1),
object position (3), object rotation (3), object velocities (6)]``; it has no clock, so the policy
counts control steps (pass ``episode_start``). The object frame follows the cube while it lies on
the table and is frozen once the fingers hold it; the phase waits (at most ``max_wait``) for the
``holding`` event the demonstrations show.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from lgp_policy.lfd.adapters import ArrayAdapter
from lgp_policy.lfd.demonstrations import Trajectory, TrajectorySet
from lgp_policy.lfd.policy import GPDemonstrationPolicy
from lgp_policy.lfd.robots import CartesianDeltaAction, CartesianPointRobot, GripperSpec

ENV_ID = "PandaPickAndPlace-v3"
MAX_STEP = 0.05  # m per step at action 1 (panda-gym's end-effector scaling)
CONTROL_DT = 0.04  # s per control step (panda-gym: 20 physics steps of 2 ms)
OBS_DIM = 25
GOAL = slice(3, 6)
EE = slice(6, 9)
WIDTH = 12
OBJECT = slice(13, 16)
TEACHER_SPEED = 0.6  # fraction of the top speed the expert uses
HOLD_WIDTH = 0.06  # m; fingers closer than this, around the cube, hold it
HOLD_DISTANCE = 0.02  # m; grasp point within this of the cube's centre


def holding(obs: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Per row of ``(n, OBS_DIM)``: the fingers hold the cube (closed on it, hand at its centre)."""
    near = np.linalg.norm(obs[:, EE] - obs[:, OBJECT], axis=1) < HOLD_DISTANCE
    return near & (obs[:, WIDTH] < HOLD_WIDTH) & (obs[:, WIDTH] > 0.02)


def make_env(**kwargs: Any) -> gym.Env:
    import panda_gym  # noqa: F401  (registers the environments)

    return gym.wrappers.FlattenObservation(gym.make(ENV_ID, **kwargs))


class ScriptedExpert:
    """Above the cube, down, close, carry to the goal (at ``TEACHER_SPEED`` of the top speed)."""

    def reset(self) -> None:
        self.stage, self.wait = "above", 0

    def act(self, obs: NDArray[np.float64]) -> NDArray[np.float32]:
        ee, obj, goal = obs[EE], obs[OBJECT], obs[GOAL]
        grip = 1.0
        if self.stage == "above":
            target = obj + np.array([0.0, 0.0, 0.06])
            if np.linalg.norm(target - ee) < 0.01:
                self.stage = "down"
        if self.stage == "down":
            target = obj.copy()
            if np.linalg.norm(target - ee) < 0.005:
                self.stage, self.wait = "close", 4
        if self.stage == "close":
            target, grip = obj.copy(), -1.0
            self.wait -= 1
            if self.wait <= 0:
                self.stage = "carry"
        if self.stage == "carry":
            target, grip = goal.copy(), -1.0
            if np.linalg.norm(target - ee) < 0.005:
                self.stage, self.wait = "hold", 2
        if self.stage == "hold":  # at the goal; the demonstration ends after two more steps
            target, grip = goal.copy(), -1.0
            self.wait -= 1
        step = target - ee
        dist = float(np.linalg.norm(step))
        if dist > TEACHER_SPEED * MAX_STEP:
            step *= TEACHER_SPEED * MAX_STEP / dist
        return np.array([*(step / MAX_STEP), grip], dtype=np.float32)


def record(env: gym.Env, seed: int) -> Trajectory:
    """One expert episode on ``reset(seed=seed)`` as a :class:`Trajectory`.

    The expert's whole motion is recorded: the env's success termination (the cube within 5 cm
    of the goal) is not where the expert stops, so recording runs on until the expert has put the
    cube on the goal (or the time limit); the policy is evaluated with the env's own rule.
    """
    expert = ScriptedExpert()
    expert.reset()
    obs, _ = env.reset(seed=seed)
    rows, actions, done = [obs], [], False
    info: dict[str, Any] = {}
    while not done:
        a = expert.act(obs)
        actions.append(a)
        obs, _r, _terminated, truncated, info = env.step(a)
        rows.append(obs)
        done = truncated or (expert.stage == "hold" and expert.wait <= 0)
    actions.append(actions[-1])
    o = np.asarray(rows, dtype=float)
    a = np.asarray(actions, dtype=float)
    return Trajectory(
        time=np.arange(len(o)) * CONTROL_DT,
        state=o[:, EE],
        gripper=a[:, 3],  # the commanded width change: -1 closes, +1 opens
        actions=a,
        frames={"object": (o[0, OBJECT], np.eye(3)), "goal": (o[0, GOAL], np.eye(3))},
        events={"holding": holding(o)},
        success=bool(info.get("is_success", False)),
    )


def make_adapter() -> ArrayAdapter:
    """How the policy reads the flattened panda-gym observation."""
    grip = GripperSpec(closed=-1.0, open=1.0)
    return ArrayAdapter(
        OBS_DIM,
        state=EE,
        frames={"object": (OBJECT, None), "goal": (GOAL, None)},
        robot=CartesianPointRobot(3),
        action_map=CartesianDeltaAction(MAX_STEP, grip),
        gripper=grip,
        control_dt=CONTROL_DT,
        valid={"object": lambda obs: ~holding(obs)},
        events={"holding": holding},
        name="panda_gym_pick_and_place",
    )


def collect(env: gym.Env, n: int, seed: int) -> TrajectorySet:
    """``n`` successful expert demonstrations from seeds ``seed, seed + 1, ...``."""
    demos: list[Trajectory] = []
    s = seed
    while len(demos) < n:
        tr = record(env, s)
        s += 1
        if tr.success:
            demos.append(tr)
        if s - seed > 10 * n:
            raise RuntimeError("the expert keeps failing; check the environment version")
    return TrajectorySet(demos, {"env_id": ENV_ID})


def success_rate(env: gym.Env, act: Any, n: int, seed: int) -> float:
    """Success of ``act(obs, first) -> action`` on ``n`` layouts ``seed, seed + 1, ...``."""
    ok = 0
    for i in range(n):
        obs, _ = env.reset(seed=seed + i)
        done, first = False, True
        info: dict[str, Any] = {}
        while not done:
            obs, _r, terminated, truncated, info = env.step(act(obs, first))
            first = False
            done = terminated or truncated
        ok += bool(info.get("is_success", False))
    return ok / n


def run(n_demos: int, n_episodes: int, seed: int = 0) -> dict[str, float]:
    """Record, fit, evaluate policy and expert on the same held-out layouts (seeds >= 10000)."""
    env = make_env()
    try:
        demos = collect(env, n_demos, seed)
        t = time.process_time()
        policy = GPDemonstrationPolicy(adapter=make_adapter()).fit(demos)
        fit_s = time.process_time() - t
        held_out = 10_000 + seed

        def gp(obs: NDArray[np.float64], first: bool) -> NDArray[np.float32]:
            return policy.predict(obs, episode_start=np.array([first]))[0]

        expert = ScriptedExpert()

        def teach(obs: NDArray[np.float64], first: bool) -> NDArray[np.float32]:
            if first:
                expert.reset()
            return expert.act(obs)

        return {
            "policy": success_rate(env, gp, n_episodes, held_out),
            "expert": success_rate(env, teach, n_episodes, held_out),
            "fit_cpu_s": fit_s,
        }
    finally:
        env.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--demos", type=int, default=6)
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    for name in ("demos", "episodes"):
        if getattr(args, name) < 1:
            ap.error(f"argument --{name}: expected an integer >= 1, got {getattr(args, name)}")
    if args.seed < 0:
        ap.error(f"argument --seed: expected an integer >= 0, got {args.seed}")
    r = run(args.demos, args.episodes, args.seed)
    print(
        f"{ENV_ID}, {args.demos} demonstrations, {args.episodes} held-out layouts: "
        f"GP policy {r['policy']:.0%}, scripted expert {r['expert']:.0%} "
        f"(fit {r['fit_cpu_s']:.1f} CPU s)"
    )


if __name__ == "__main__":
    main()
