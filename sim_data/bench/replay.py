"""What playing action sequences open loop in the simulator costs, per task; writes JSON.

    python -m sim_data.bench.replay --out runs/bench/replay.json [--batch 1024] [--tasks airfryer,mug,wipe]

`sim_data.policies.scripted.simulate_actions` plays a batch of action sequences, each a task's whole
episode, from their initial states and returns the outcomes, without rendering: what the world
model's judge does with `judge_labels=replayed` (the closed-loop training imaginations' actions) and
the evaluator with `replay=1`. Each task is called twice with zero actions: the first call compiles
the task's program (each episode length is its own scan) and runs it, the second only runs it. The
first call's compile is cold unless JAX_COMPILATION_CACHE_DIR names a cache that already holds it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import numpy as np

from sim_data.policies.scripted import simulate_actions
from sim_data.sim.engines import default_engine
from sim_data.sim.robot import ACTION_DIM
from sim_data.sim.tasks import TASK_NAMES, get_task
from sim_data.util import device_name, run_cli, write_json_atomic


def replay_cost(task: str, batch: int, engine: str) -> dict:
    """Two calls of simulate_actions on `batch` zero-action episodes of task: {"task", "steps",
    "first_call_s" (compiling and running), "second_call_s" (running), "env_steps_per_s" (the
    second call's control steps, all episodes)}."""
    steps = get_task(task).episode_steps
    keys = np.stack([np.asarray(jax.random.PRNGKey(i)) for i in range(batch)])
    actions = np.zeros((batch, steps, ACTION_DIM), np.float32)
    t0 = time.perf_counter()
    simulate_actions(task, actions, keys, engine)
    t1 = time.perf_counter()
    simulate_actions(task, actions, keys, engine)
    t2 = time.perf_counter()
    return {"task": task, "steps": steps, "first_call_s": t1 - t0, "second_call_s": t2 - t1,
            "env_steps_per_s": batch * steps / (t2 - t1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--batch", type=int, default=1024, help="episodes a call (the judge's replay: at most 1024)")
    p.add_argument("--tasks", default="airfryer,mug,wipe", help="comma-separated task names")
    p.add_argument("--engine", default=None, help="cpu or mjx (default: mjx where a GPU is present)")
    a = p.parse_args(argv)
    tasks = [t.strip() for t in a.tasks.split(",") if t.strip()]
    unknown = sorted(set(tasks) - set(TASK_NAMES))
    if unknown or not tasks:
        p.error(f"unknown tasks {unknown}; choose from {', '.join(TASK_NAMES)}")
    if a.batch < 1:
        p.error(f"--batch must be >= 1, got {a.batch}")
    engine = a.engine or default_engine()
    rows = []
    for task in tasks:
        r = replay_cost(task, a.batch, engine)
        rows.append(r)
        print(f"{task}: {r['steps']} steps x {a.batch}: first call {r['first_call_s']:.1f} s, second "
              f"{r['second_call_s']:.1f} s ({r['env_steps_per_s']:.0f} env steps/s)", file=sys.stderr)
    write_json_atomic(a.out, {"batch": a.batch, "engine": engine, "device": device_name(), "tasks": rows})
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
