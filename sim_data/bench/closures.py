"""How firmly a zoo's policies close the right hand, in episodes that succeed and in those that fail.

    python -m sim_data.bench.closures --policies runs/policies/demo#mug --episodes 32 --out runs/bench/closures.json

A grasp holds above a threshold on the closure command (`sim_data.bench.success_table --grip`), so a
policy that fails could close too weakly or close well in the wrong place or at the wrong time. Each
selected checkpoint runs from the evaluation's held-out initial states in the simulator (the head camera
rendered, as the evaluator runs it); per policy the JSON holds its successes and, over its succeeding
and its failing episodes, the mean of each episode's firmest closure and of its `--firmest` firmest
steps' mean, and how many failures stay below `--threshold` over those steps.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sim_data.policies.registry import heldout_seeds, reset_keys_of, resolve, used_seeds
from sim_data.policies.zoo import recorded_chunks
from sim_data.sim import robot as R
from sim_data.sim.engines import ENGINES, default_engine
from sim_data.util import run_cli, write_json_atomic


def closure_summary(closure, success, firmest: int, threshold: float) -> dict:
    """Per policy from its episodes' right-hand closure commands (N, T) and final successes (N,) bool:
    {"successes", "n", "max_success", "max_failure" (the mean over those episodes of each one's firmest
    closure), "firmest_success", "firmest_failure" (of each one's `firmest` firmest steps' mean),
    "weak_failures" (failures whose firmest steps' mean is below threshold)}; None where no episode
    of that outcome."""
    closure, success = np.asarray(closure, np.float64), np.asarray(success, bool)
    top = np.sort(closure, axis=1)[:, -min(firmest, closure.shape[1]):].mean(1)
    peak = closure.max(1)

    def mean(x, rows):
        return round(float(x[rows].mean()), 4) if rows.any() else None

    return {"successes": int(success.sum()), "n": len(success),
            "max_success": mean(peak, success), "max_failure": mean(peak, ~success),
            "firmest_success": mean(top, success), "firmest_failure": mean(top, ~success),
            "weak_failures": int(((top < threshold) & ~success).sum())}


def measure_closures(spec: str, episodes: int, engine: str, firmest: int, threshold: float, seed: int = 0,
                     batch: int = 2048, progress: bool = True) -> list[dict]:
    """closure_summary of every policy that the selector spec names (a zoo, `ZOO#lineage+task`, ...) over
    `episodes` held-out initial states of its task: [{"name", "task", ...closure_summary}]."""
    sources = resolve([spec], world_model=False)
    used = used_seeds(*{s.record["data"] for s in sources if s.record.get("data")})
    rows = []
    bar = tqdm(total=len(sources) * episodes, desc="closures", unit="ep", disable=not progress, file=sys.stderr)
    for task in sorted({s.task for s in sources}):
        seeds = heldout_seeds(task, episodes, seed, used)
        keys = reset_keys_of(seeds)
        task_sources = [s for s in sources if s.task == task]
        for part, outcome, rec in recorded_chunks(task, task_sources, keys, engine, seed, batch):
            hand = np.asarray(rec.action)[..., R.RIGHT_HAND].reshape(len(outcome), episodes, -1)
            for j, src in enumerate(part):
                rows.append({"name": src.name, "task": task,
                             **closure_summary(hand[j], outcome[j], firmest, threshold)})
                bar.update(episodes)
    bar.close()
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policies", required=True, help="a policy selector: a zoo, ZOO#lineage+task, names")
    p.add_argument("--episodes", type=int, default=32, help="held-out initial states per policy")
    p.add_argument("--engine", choices=ENGINES, default=None, help="physics engine (default: mjx on GPU, else cpu)")
    p.add_argument("--firmest", type=int, default=40, help="steps of each episode's firmest closure averaged")
    p.add_argument("--threshold", type=float, default=0.45, help="a failure whose firmest steps stay below it is weak")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True, help="JSON file to write")
    a = p.parse_args(argv)
    if a.episodes < 1 or a.firmest < 1:
        raise SystemExit("--episodes and --firmest must be >= 1")
    rows = measure_closures(a.policies, a.episodes, a.engine or default_engine(), a.firmest, a.threshold, a.seed)
    write_json_atomic(a.out, {"episodes": a.episodes, "firmest": a.firmest, "threshold": a.threshold, "policies": rows})
    print(f"{'policy':<36}{'success':>9}{'firmest, succeeding':>22}{'firmest, failing':>19}{'weak failures':>15}")
    for r in rows:
        cells = [f"{r['successes']}/{r['n']}", str(r["firmest_success"]), str(r["firmest_failure"]),
                 f"{r['weak_failures']}/{r['n'] - r['successes']}"]
        print(f"{r['name']:<36}{cells[0]:>9}{cells[1]:>22}{cells[2]:>19}{cells[3]:>15}")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
