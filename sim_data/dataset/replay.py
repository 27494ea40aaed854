"""Replay: re-simulate recorded episodes from their initial seed and recorded actions, and check
that the simulator reproduces what the files say (initial state, per-step success, final outcome).

    python -m sim_data.dataset.replay OUT                 # every episode of a dataset
    python -m sim_data.dataset.replay OUT --limit 20 --engine cpu

The initial state comes from `env.reset` with the episode's seed and is checked against the
recorded `/sim_state` at t = 0; the recorded actions then drive the simulator open loop (the
policy is not needed). Episodes of one task are replayed together in one batch.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from sim_data.dataset.episodes import read_episode
from sim_data.sim.env import HomeEnv
from sim_data.util import run_cli


def replay_files(paths, engine: str | None = None, progress: bool = False) -> list[dict]:
    """Replays episode files; one result per file, in order.

    Args:
      paths: MCAP episode files.
      engine: "cpu" or "mjx" (default: the engine each episode was recorded with).
    Returns:
      [{"file", "episode_id", "task", "engine", "success_recorded", "success_replayed",
        "flags_agree" (share of steps whose success flag matches), "initial_state_error" (max |qpos|
        difference at t = 0), "max_qpos_error" (over the episode)}].
    """
    episodes = [read_episode(p, cameras=()) for p in paths]
    groups: dict = {}
    for i, ep in enumerate(episodes):
        m = ep["meta"]
        key = (m["task"], bool(m.get("heldout", False)), engine or m["engine"], int(m["num_steps"]))
        groups.setdefault(key, []).append(i)
    results: list = [None] * len(episodes)
    for (task, heldout, eng, steps), members in tqdm(groups.items(), desc="replay", disable=not progress):
        eps = [episodes[i] for i in members]
        env = HomeEnv(task, len(eps), engine=eng, heldout=heldout)
        state = env.reset(jax.numpy.stack([jax.random.PRNGKey(int(e["meta"]["seed"])) for e in eps]))
        qpos = [np.asarray(state.qpos)]
        flags = [np.asarray(state.success)]
        actions = np.stack([e["action"] for e in eps])
        for t in range(steps):
            state = env.step(state, actions[:, t])
            qpos.append(np.asarray(state.qpos))
            flags.append(np.asarray(state.success))
        qpos, flags = np.stack(qpos, 1), np.stack(flags, 1)
        for row, (i, e) in enumerate(zip(members, eps)):
            err = np.abs(qpos[row] - e["qpos"]).max(axis=1)
            results[i] = {
                "file": str(paths[i]), "episode_id": e["meta"]["episode_id"], "task": task, "engine": eng,
                "success_recorded": bool(e["meta"]["success"]), "success_replayed": bool(flags[row, -1]),
                "flags_agree": float((flags[row] == e["success"]).mean()),
                "initial_state_error": float(err[0]), "max_qpos_error": float(err.max()),
            }
    return results


def summarize(results: list[dict]) -> dict:
    """replay_files' results summed up: {"episodes", "outcome_agreement" (share of episodes whose replayed outcome
    is the recorded one), "mean_flags_agree", "max_initial_state_error", "max_qpos_error"}; results not empty."""
    n = len(results)
    return {
        "episodes": n,
        "outcome_agreement": sum(r["success_recorded"] == r["success_replayed"] for r in results) / n,
        "mean_flags_agree": float(np.mean([r["flags_agree"] for r in results])),
        "max_initial_state_error": max(r["initial_state_error"] for r in results),
        "max_qpos_error": max(r["max_qpos_error"] for r in results),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, help="a dataset directory, or one .mcap file")
    p.add_argument("--engine", choices=("cpu", "mjx"), default=None, help="default: each episode's own engine")
    p.add_argument("--limit", type=int, default=None, help="replay the first N episodes only")
    p.add_argument("--json", type=Path, default=None, help="write per-episode results here")
    a = p.parse_args(argv)
    files = [a.out] if a.out.suffix == ".mcap" else sorted((a.out / "episodes").glob("*.mcap"))[: a.limit]
    if not files:
        p.error(f"no episode files under {a.out}")
    results = replay_files(files, a.engine, progress=True)
    for r in results:
        mark = "ok " if r["success_recorded"] == r["success_replayed"] else "DIFF"
        print(f"{mark} {r['episode_id']}: recorded {r['success_recorded']}, replayed {r['success_replayed']}, "
              f"flags agree {r['flags_agree']:.3f}, max qpos error {r['max_qpos_error']:.2e}")
    summary = summarize(results)
    print(json.dumps(summary, indent=1))
    if a.json:
        a.json.write_text(json.dumps({"summary": summary, "episodes": results}, indent=1))
    return 0 if summary["outcome_agreement"] == 1.0 else 1


if __name__ == "__main__":
    sys.exit(run_cli(main))
