"""Random-policy rollouts of r2g_gym in process: steps per second per gym over N steps (resets
as episodes end), beside the native episode stepped alone with the same actions (controller and
physics, no gymnasium wrapper, no evaluator, no observation arrays) in the same run.

    .venv/bin/python bench/py/gym_rollout.py [--steps 1000] [--control joint|joint_delta|ee_pose]

Prints a table and, as the last line, one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np

import r2g_gym


def rollout(gym_name: str, steps: int, control: str, seed: int) -> dict[str, float]:
    env = gym.make(r2g_gym.env_id(gym_name), control=control)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(steps)]
    statuses: dict[str, int] = {}
    env.reset(seed=seed)
    t0 = time.perf_counter()
    episodes = 1
    for a in actions:
        _, _, term, trunc, info = env.step(a)
        statuses[info["action_status"]] = statuses.get(info["action_status"], 0) + 1
        if term or trunc:
            env.reset()
            episodes += 1
    wall = time.perf_counter() - t0
    # Baseline: the native episode alone, the same absolute targets (joint_delta: from the
    # first state, so the arm moves comparably), the same period.
    native = env.unwrapped._native
    ticks = env.unwrapped.period_ticks
    state = native.reset(seed)
    t1 = time.perf_counter()
    for k, a in enumerate(actions):
        target = a if control != "joint_delta" else np.append(np.array(state["joint"]) + a[:7], a[7])
        state, _ = native.step([float(v) for v in target], ticks)
        if (k + 1) % r2g_gym.MAX_EPISODE_STEPS == 0:
            state = native.reset(seed + k)
    base = time.perf_counter() - t1
    sim_s = steps * env.unwrapped.period_s
    env.close()
    return {
        "steps_per_s": steps / wall,
        "native_steps_per_s": steps / base,
        "real_time_factor": sim_s / wall,
        "episodes": episodes,
        **{f"status_{k}": v for k, v in sorted(statuses.items())},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--control", default="joint", choices=["joint", "joint_delta", "ee_pose"])
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rows = {}
    print(f"random policy, {a.steps} steps per gym, in process, control={a.control}")
    print(f"{'gym':<18} {'steps/s':>9} {'native':>9} {'x real time':>11}  action status counts")
    for g in r2g_gym.gym_names():
        r = rollout(g, a.steps, a.control, a.seed)
        rows[g] = r
        counts = ", ".join(f"{k[7:]} {v}" for k, v in r.items() if k.startswith("status_"))
        print(f"{g:<18} {r['steps_per_s']:>9.0f} {r['native_steps_per_s']:>9.0f} {r['real_time_factor']:>11.1f}  {counts}")
    print(json.dumps({"steps": a.steps, "control": a.control, "per_gym": rows}))


if __name__ == "__main__":
    main()
