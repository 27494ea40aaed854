"""What share of a rendered rollout's time the learned policies take; writes JSON.

    python -m sim_data.bench.policy --out runs/bench/policy.json [--task mug] [--batch 64] [--engine cpu] [--repeats 2]

For each policy network of the zoo (`conv` and `vit` at the `full` preset's sizes, fresh
parameters: speed does not depend on what was learned) one batch of whole episodes is recorded with
the head camera rendered, as the evaluator and the data generator do. The same rollout under an
action program (a table lookup, no network) is the reference: the policy's share is
`1 - program time / policy time`. The policy's `act` alone, jitted on the same batch, is timed too
(`act_ms`), and `act_share` is its time over all steps relative to the whole rollout.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

from sim_data.policies.bc import BCPolicy, init_params
from sim_data.policies.scripted import ProgramPolicy, program_params
from sim_data.policies.zoo import PRESETS as ZOO_PRESETS
from sim_data.sim import robot as R
from sim_data.sim.engines import default_engine
from sim_data.sim.env import cached_env
from sim_data.sim.render import HEAD_CAMERA, cached_renderers
from sim_data.sim.rollout import record_episodes
from sim_data.util import device_name, run_cli, write_json_atomic


def identity_norm() -> dict:
    """A policy's normalisation that leaves proprioception and actions as they are (fresh networks)."""
    return {"proprio_mean": np.zeros(R.PROPRIO_DIM), "proprio_std": np.ones(R.PROPRIO_DIM),
            "action_mean": np.zeros(R.ACTION_DIM), "action_std": np.ones(R.ACTION_DIM)}


def _timed_rollout(env, policy, params, renderers, repeats: int) -> float:
    """Best wall seconds of recording one batch of episodes (after one warm-up run that compiles)."""
    rng = jax.random.PRNGKey(0)
    jax.block_until_ready(record_episodes(env, policy, params, rng, renderers)[1].frames)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(record_episodes(env, policy, params, rng, renderers)[1].frames)
        best = min(best, time.perf_counter() - t0)
    return best


def _timed_act(policy: BCPolicy, params, batch: int, size: int, repeats: int = 20) -> float:
    """Best seconds of one jitted `act` on a batch of observations."""
    obs = {"image": np.zeros((batch, size, size, 3), np.uint8), "proprio": np.zeros((batch, R.PROPRIO_DIM), np.float32)}
    carry = np.zeros((batch,), np.int32)
    act = jax.jit(policy.act)
    jax.block_until_ready(act(params, obs, carry, None))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(act(params, obs, carry, None))
        best = min(best, time.perf_counter() - t0)
    return best


def bench(task: str, batch: int, engine: str, repeats: int = 2) -> dict:
    """Times a rendered rollout of `batch` episodes of task under each zoo network (the full preset's conv and vit,
    fresh parameters) against the same rollout under an action program, best of `repeats`. Returns {"task",
    "batch", "steps", "engine", "camera", "results": per encoder {"encoder", "rollout_s", "program_rollout_s",
    "policy_share", "act_ms", "act_share", "env_steps_per_s"}}."""
    env = cached_env(task, batch, engine, False)
    zoo = ZOO_PRESETS["full"]
    renderers = cached_renderers(zoo.conv.size, (HEAD_CAMERA,))
    steps = env.episode_steps
    program_s = _timed_rollout(env, ProgramPolicy(steps), program_params(["reach_mug"] * batch, steps), renderers,
                               repeats)
    norm = identity_norm()
    rows = []
    for net_cfg in (zoo.conv, zoo.vit):
        policy = BCPolicy(net_cfg)
        params = init_params(net_cfg, jax.random.PRNGKey(0), norm, use_proprio=True)
        policy_s = _timed_rollout(env, policy, params, renderers, repeats)
        act_s = _timed_act(policy, params, batch, net_cfg.size)
        rows.append({"encoder": net_cfg.encoder, "rollout_s": policy_s, "program_rollout_s": program_s,
                     "policy_share": max(0.0, 1.0 - program_s / policy_s), "act_ms": 1e3 * act_s,
                     "act_share": min(1.0, act_s * steps / policy_s),
                     "env_steps_per_s": batch * steps / policy_s})
        print(f"{net_cfg.encoder}: rollout {policy_s:.2f} s (program {program_s:.2f} s), policy share "
              f"{rows[-1]['policy_share']:.1%}, act {1e3 * act_s:.2f} ms x {steps} steps = "
              f"{rows[-1]['act_share']:.1%}", flush=True)
    return {"task": task, "batch": batch, "steps": steps, "engine": engine, "camera": HEAD_CAMERA, "results": rows}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--task", default="mug")
    p.add_argument("--batch", type=int, default=0, help="episodes per batch (0: 16 on cpu, 1024 on mjx)")
    p.add_argument("--engine", default="", help="cpu or mjx (default: mjx where a GPU is present)")
    p.add_argument("--repeats", type=int, default=2, help="timed rollouts per variant after the compiling one")
    a = p.parse_args(argv)
    engine = a.engine or default_engine()
    batch = a.batch or (1024 if engine == "mjx" else 16)
    res = bench(a.task, batch, engine, a.repeats)
    res.update(device=device_name(), host=platform.node(), jax=jax.__version__)
    write_json_atomic(a.out, res)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
