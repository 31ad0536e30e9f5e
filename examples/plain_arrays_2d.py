"""Learn a 2-D pick-and-place from plain numpy arrays with ``GPDemonstrationPolicy``.

No simulator and no gym-coffee: a point "hand" in the plane moves by at most ``MAX_STEP`` per
control step, closes its gripper on an object when near it, carries it and lets go. A scripted
teacher demonstrates the task on a few random layouts (object and goal positions); the policy
learns it from the arrays alone (the hand relative to the frames ``object`` and ``goal``) and is
evaluated on held-out layouts:

    python examples/plain_arrays_2d.py [--demos 4] [--episodes 50]

What the library needs, in order (see ``docs/own-robot.md``):

1. demonstrations as :class:`~lgp_policy.lfd.demonstrations.Trajectory` (time, robot state,
   gripper command, named frames with position and rotation, events, success);
2. a robot model (:class:`~lgp_policy.lfd.robots.CartesianPointRobot`: the state is the hand
   position) and an action map (:class:`~lgp_policy.lfd.robots.CartesianDeltaAction`);
3. an adapter that reads the observation (:class:`~lgp_policy.lfd.adapters.ArrayAdapter`).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lgp_policy.lfd.adapters import ArrayAdapter
from lgp_policy.lfd.demonstrations import Trajectory, TrajectorySet
from lgp_policy.lfd.policy import GPDemonstrationPolicy
from lgp_policy.lfd.robots import CartesianDeltaAction, CartesianPointRobot, GripperSpec

DT = 0.1  # s per control step
MAX_STEP = 0.05  # m per step at action 1
MAX_STEPS = 120
GRASP_RADIUS = 0.02  # the gripper catches the object within this distance
SUCCESS_RADIUS = 0.02
TEACHER_SPEED = 0.5  # the teacher moves at half the top speed, leaving the policy room to catch up
RETREAT = np.array([0.0, 0.12])  # m; where the teacher backs off to after letting go
#: observation = [time, hand x, y, gripper closed (0/1), holding (0/1), object x, y, goal x, y]
OBS_DIM = 9


class PickPlace2D:
    """The task: ``reset(seed)`` draws a layout, ``step(action)`` with ``action = [dx, dy, g]`` in
    ``[-1, 1]`` (``g < 0`` closes the gripper, ``g > 0`` opens it)."""

    def reset(self, seed: int) -> NDArray[np.float64]:
        rng = np.random.default_rng(seed)
        self.t = 0
        self.hand = np.array([0.0, 0.0]) + rng.uniform(-0.02, 0.02, 2)
        self.object = rng.uniform([0.2, 0.2], [0.5, 0.6])
        self.goal = rng.uniform([0.6, -0.3], [0.9, 0.1])
        self.closed = False
        self.holding = False
        return self.observe()

    def observe(self) -> NDArray[np.float64]:
        return np.concatenate(
            [[self.t * DT], self.hand, [self.closed, self.holding], self.object, self.goal]
        )

    def step(self, action: NDArray[Any]) -> tuple[NDArray[np.float64], bool]:
        a = np.clip(np.asarray(action, dtype=float), -1.0, 1.0)
        self.hand = self.hand + a[:2] * MAX_STEP
        was_closed, self.closed = self.closed, bool(a[2] < 0)
        if self.closed and not was_closed:
            self.holding = bool(np.linalg.norm(self.hand - self.object) < GRASP_RADIUS)
        if not self.closed:
            self.holding = False
        if self.holding:
            self.object = self.hand.copy()
        self.t += 1
        return self.observe(), self.t >= MAX_STEPS

    def success(self) -> bool:
        return (not self.holding) and bool(np.linalg.norm(self.object - self.goal) < SUCCESS_RADIUS)


def teacher(obs: NDArray[np.float64], state: dict) -> NDArray[np.float64]:
    """A scripted expert: go to the object, close, carry to the goal, open, back away."""
    hand, obj, goal = obs[1:3], obs[5:7], obs[7:9]
    stage = state.setdefault("stage", "reach")
    target, grip = hand, 1.0
    if stage == "reach":
        target = obj
        if np.linalg.norm(obj - hand) < 1e-3:
            state["stage"], state["wait"] = "close", 3
    if state["stage"] == "close":
        target, grip = obj, -1.0
        state["wait"] -= 1
        if state["wait"] <= 0:
            state["stage"] = "carry"
    if state["stage"] == "carry":
        target, grip = goal, -1.0
        if np.linalg.norm(goal - hand) < 1e-3:
            state["stage"], state["wait"] = "release", 3
    if state["stage"] == "release":
        target, grip = goal, 1.0
        state["wait"] -= 1
        if state["wait"] <= 0:
            state["stage"] = "retreat"
    if state["stage"] == "retreat":
        target = goal + RETREAT
    step = target - hand  # at most TEACHER_SPEED of the robot's top speed
    dist = float(np.linalg.norm(step))
    if dist > TEACHER_SPEED * MAX_STEP:
        step *= TEACHER_SPEED * MAX_STEP / dist
    return np.array([*(step / MAX_STEP), grip])


def record(seed: int) -> Trajectory:
    """One teacher demonstration as a :class:`Trajectory` (plain arrays)."""
    env = PickPlace2D()
    state: dict[str, Any] = {}
    obs, done = env.reset(seed), False
    rows, actions = [obs], []
    while not done:
        a = teacher(obs, state)
        actions.append(a)
        obs, done = env.step(a)
        rows.append(obs)
        if (
            state.get("stage") == "retreat"
            and np.linalg.norm(obs[1:3] - (obs[7:9] + RETREAT)) < 1e-3
        ):
            break
    actions.append(actions[-1])
    o = np.array(rows)
    a = np.array(actions)
    return Trajectory(
        time=o[:, 0],
        state=o[:, 1:3],
        gripper=a[:, 2],  # the commanded gripper, in the action's units: -1 closed, 1 open
        actions=a,
        frames={"object": (o[0, 5:7], np.eye(2)), "goal": (o[0, 7:9], np.eye(2))},
        events={"holding": o[:, 4] > 0.5},
        success=env.success(),
    )


def make_adapter() -> ArrayAdapter:
    """How the policy reads this task's observation."""
    return ArrayAdapter(
        OBS_DIM,
        time=slice(0, 1),
        state=slice(1, 3),
        frames={"object": (slice(5, 7), None), "goal": (slice(7, 9), None)},
        robot=CartesianPointRobot(2),
        action_map=CartesianDeltaAction(MAX_STEP, GripperSpec(closed=-1.0, open=1.0)),
        gripper=GripperSpec(closed=-1.0, open=1.0),
        control_dt=DT,
        # the object is tracked while it lies on the table; once held it moves with the hand
        valid={"object": lambda obs: obs[:, 4] < 0.5},
        events={"holding": lambda obs: obs[:, 4] > 0.5},
        name="pick_place_2d",
    )


def evaluate(policy: GPDemonstrationPolicy, n: int, seed: int) -> float:
    """Success rate of ``policy`` on ``n`` layouts ``seed, seed + 1, ...``."""
    ok = 0
    for i in range(n):
        env = PickPlace2D()
        obs, done, first = env.reset(seed + i), False, True
        while not done:
            action, _ = policy.predict(obs, episode_start=np.array([first]))
            first = False
            obs, done = env.step(action)
        ok += env.success()
    return ok / n


def teacher_success(n: int, seed: int) -> float:
    return float(np.mean([record(seed + i).success for i in range(n)]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--demos", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    for name in ("demos", "episodes"):
        if getattr(args, name) < 1:
            ap.error(f"argument --{name}: expected an integer >= 1, got {getattr(args, name)}")
    if args.seed < 0:
        ap.error(f"argument --seed: expected an integer >= 0, got {args.seed}")
    demos = TrajectorySet([record(args.seed + i) for i in range(args.demos)])
    t = time.process_time()
    policy = GPDemonstrationPolicy(adapter=make_adapter()).fit(demos)
    fit_s = time.process_time() - t
    held_out = 10_000 + args.seed
    rate = evaluate(policy, args.episodes, held_out)
    print(f"fit: {fit_s:.2f} CPU s, tight: {[iv['label'] for iv in policy.constraint_intervals()]}")
    print(
        f"held-out success ({args.episodes} layouts): policy {rate:.0%}, "
        f"teacher {teacher_success(args.episodes, held_out):.0%}"
    )


if __name__ == "__main__":
    main()
