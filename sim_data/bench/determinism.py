"""Is a closed-loop rollout bit-reproducible on this device between processes? Writes JSON.

    python -m sim_data.bench.determinism --out runs/bench/determinism.json [--task mug] [--states 64]
        [--policies runs/policies/full#mug+conv_noproprio] [--engine mjx] [--processes 2]
        [--flags=--xla_gpu_deterministic_ops=false --flags=--xla_gpu_deterministic_ops=true]

The evaluator's ground truth is a batch of closed-loop episodes: policies acting on the frames the
renderer draws, in a contact-rich simulation that amplifies the last bit of a float. For each XLA
flag set (`--flags`, repeatable; added to the project's own, `sim_data.util.XLA_DEFAULT_FLAGS`, which
name deterministic ops unless the set names them), `--processes` fresh processes record the same
batch (the same policies, initial states and keys), each twice; the episodes are compared bit for
bit against the first process's. Reported per flag set: whether every process and both records in a
process agree, how many episodes and final outcomes differ, the first step at which any episode
diverges, the largest proprioception difference, and the recording's steps per second (its second
record, compiled) so a flag's cost shows beside its effect.

The policies are registry checkpoints (`--policies`, as the evaluator names them: stacked, so
they must share one network), or by default the `full` zoo's conv network with fresh parameters.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from sim_data.bench.policy import identity_norm
from sim_data.policies.bc import BCPolicy, init_params, stacked
from sim_data.policies.registry import group_by_policy, resolve
from sim_data.policies.zoo import PRESETS as ZOO_PRESETS
from sim_data.sim.engines import default_engine
from sim_data.sim.env import cached_env
from sim_data.sim.render import HEAD_CAMERA, cached_renderers
from sim_data.sim.rollout import record_policies
from sim_data.util import device_name, run_cli, with_xla_flags, write_json_atomic

DEFAULT_FLAGS = ("--xla_gpu_deterministic_ops=false", "--xla_gpu_deterministic_ops=true")  # XLA's default, the project's


def batch_policies(spec: str, task: str) -> tuple:
    """(StackedPolicy, stacked params, names) of the registry checkpoints `spec` selects for task, or of
    two fresh `full`-zoo conv networks (seeds 0 and 1) where spec is empty."""
    if not spec:
        net = ZOO_PRESETS["full"].conv
        params = [init_params(net, jax.random.PRNGKey(k), identity_norm(), use_proprio=True) for k in range(2)]
        return (*stacked(BCPolicy(net), params), ["fresh_conv/0", "fresh_conv/1"])
    sources = [s for s in resolve([spec]) if s.task in (None, task)]
    if not sources:
        raise ValueError(f"{spec} selects no policy of task {task}")
    groups = group_by_policy(sources)
    if len(groups) > 1:
        raise ValueError(f"{spec} selects policies of {len(groups)} networks; select one lineage's checkpoints")
    return (*stacked(sources[0].policy, [s.params for s in sources]), [s.name for s in sources])


def record(task: str, states: int, engine: str, spec: str, seed: int = 0) -> dict:
    """One batch of P policies x `states` closed-loop episodes with the head camera rendered, recorded
    twice in this process. Returns {"outcome": (P*states,) bool, "proprio": (B, T+1, 37),
    "action": (B, T, 20), "in_process_identical": bool, "first_s", "second_s": seconds of each record
    (the first compiles), "names": [P]}."""
    policy, params, names = batch_policies(spec, task)
    env = cached_env(task, len(names) * states, engine, False)
    renderers = cached_renderers(ZOO_PRESETS["full"].conv.size, (HEAD_CAMERA,))
    reset_keys = np.stack([np.asarray(jax.random.PRNGKey(seed * 100003 + k)) for k in range(states)])
    out, seconds = [], []
    for _ in range(2):
        t0 = time.perf_counter()
        outcome, rec = record_policies(env, policy, params, reset_keys, jax.random.PRNGKey(seed), renderers)
        out.append({"outcome": np.asarray(outcome).reshape(-1), "proprio": np.asarray(rec.proprio),
                    "action": np.asarray(rec.action)})
        seconds.append(time.perf_counter() - t0)
    again = compare(out)
    return {**out[0], "in_process_identical": again["identical"], "first_s": seconds[0], "second_s": seconds[1],
            "names": names, "steps": env.episode_steps}


def _differs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(B, T) True where any component of step t differs; NaN in both counts as equal."""
    d = ~((a == b) | (np.isnan(a) & np.isnan(b)))
    return d.reshape(d.shape[0], d.shape[1], -1).any(-1)


def compare(runs: list[dict]) -> dict:
    """Every run's episodes against runs[0]'s, bit for bit. runs: [{"outcome": (B,) bool, "proprio":
    (B, T+1, D), "action": (B, T, A)}]. Returns {"identical", "episodes", "differing_episodes",
    "differing_outcomes", "first_divergent_step" (the earliest proprioception step that differs in any
    run; None where none does), "max_abs_proprio_diff"}."""
    ref = runs[0]
    episodes = len(ref["outcome"])
    episode_differs = np.zeros(episodes, bool)
    outcome_differs = np.zeros(episodes, bool)
    first, largest = None, 0.0
    for r in runs[1:]:
        steps = _differs(r["proprio"], ref["proprio"])
        episode_differs |= steps.any(1) | _differs(r["action"], ref["action"]).any(1)
        outcome_differs |= np.asarray(r["outcome"]) != np.asarray(ref["outcome"])
        if steps.any():
            k = int(np.argmax(steps.any(0)))
            first = k if first is None else min(first, k)
            largest = max(largest, float(np.nanmax(np.abs(r["proprio"] - ref["proprio"]))))
    return {"identical": not episode_differs.any() and not outcome_differs.any(), "episodes": episodes,
            "differing_episodes": int(episode_differs.sum()), "differing_outcomes": int(outcome_differs.sum()),
            "first_divergent_step": first, "max_abs_proprio_diff": largest}


def run_setting(flags: str, processes: int, child_args: list[str], workdir: Path) -> dict:
    """`processes` child processes with `flags` added to XLA_FLAGS, at once (each allocating GPU memory
    as it needs it), compared (compare). Raises RuntimeError with a child's log where one fails."""
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false",
           "XLA_FLAGS": with_xla_flags(os.environ.get("XLA_FLAGS", ""), flags, override=True)}
    files = [workdir / f"run{k}.npz" for k in range(processes)]
    logs = [workdir / f"run{k}.log" for k in range(processes)]
    procs = []
    for f, log in zip(files, logs, strict=True):
        with open(log, "w") as fh:
            procs.append(subprocess.Popen([sys.executable, "-m", "sim_data.bench.determinism", *child_args,
                                           "--child", str(f)], env=env, stdout=fh, stderr=subprocess.STDOUT))
    for p, log in zip(procs, logs, strict=True):
        if p.wait() != 0:
            raise RuntimeError(f"a process with XLA_FLAGS '{flags}' failed:\n{log.read_text()[-3000:]}")
    runs = []
    for f in files:
        with np.load(f) as z:
            runs.append({k: z[k] for k in z.files})
    result = compare(runs)
    steps = int(runs[0]["steps"])
    return {"flags": flags, **result,
            "identical": result["identical"] and all(bool(r["in_process_identical"]) for r in runs),
            "in_process_identical": [bool(r["in_process_identical"]) for r in runs],
            "first_s": [float(r["first_s"]) for r in runs], "second_s": [float(r["second_s"]) for r in runs],
            "env_steps_per_s": result["episodes"] * steps / float(np.median([r["second_s"] for r in runs]))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, help="the JSON report (required unless --child)")
    p.add_argument("--task", default="mug")
    p.add_argument("--states", type=int, default=64, help="initial states a policy")
    p.add_argument("--policies", default="", help="registry checkpoints of one network (default: fresh conv networks)")
    p.add_argument("--engine", default="", help="cpu or mjx (default: mjx where a GPU is present)")
    p.add_argument("--processes", type=int, default=2, help="processes per flag set (>= 2)")
    p.add_argument("--flags", action="append", default=None,
                   help="XLA flags of one setting, repeatable, written --flags=VALUE since VALUE begins with dashes "
                        f"(default: {' and '.join(repr(f) for f in DEFAULT_FLAGS)})")
    p.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    engine = a.engine or default_engine()
    if a.states < 1:
        raise ValueError(f"--states must be >= 1, got {a.states}")
    if a.child:
        res = record(a.task, a.states, engine, a.policies)
        np.savez(a.child, **{k: np.asarray(v) for k, v in res.items()})
        return 0
    if a.out is None:
        raise ValueError("--out is required: where the JSON report goes")
    if a.processes < 2:
        raise ValueError(f"--processes must be >= 2 to compare processes, got {a.processes}")
    batch_policies(a.policies, a.task)  # a bad selection fails here, before any process starts
    child_args = ["--task", a.task, "--states", str(a.states), "--engine", engine, "--policies", a.policies]
    settings = []
    with tempfile.TemporaryDirectory(prefix="determinism-") as tmp:
        for k, flags in enumerate(a.flags if a.flags is not None else DEFAULT_FLAGS):
            work = Path(tmp) / f"setting{k}"
            work.mkdir()
            settings.append(run_setting(flags, a.processes, child_args, work))
            s = settings[-1]
            print(f"XLA_FLAGS '{flags}': {'identical' if s['identical'] else 'DIFFERENT'}; episodes differing "
                  f"{s['differing_episodes']} of {s['episodes']}, outcomes {s['differing_outcomes']}, first at step "
                  f"{s['first_divergent_step']}; {s['env_steps_per_s']:.0f} env steps/s", flush=True)
    res = {"task": a.task, "states": a.states, "policies": a.policies or "fresh conv networks", "engine": engine,
           "processes": a.processes, "settings": settings, "device": device_name(), "host": platform.node(),
           "jax": jax.__version__}
    write_json_atomic(a.out, res)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
