"""Physics throughput of the full home scene on both engines; writes JSON.

    python -m sim_data.bench.physics --out runs/bench/physics.json [--engines cpu,mjx] [--batches 64,256]

A "step" is one physics substep (5 ms of simulated time) of one simulation. The simulations start
from the `mug` task's initial states (every object of the scene present, resting on its support)
and hold the ready pose under small random arm targets, so the solver works on real contacts.
The `cpu` figure is the `cpu` engine (`mujoco.batch` over all cores); `mjx` is
`vmap(MjxEngine.step)` (`mjx.step`, free bodies' gyroscopic term implicit) inside a jitted `lax.scan` on
the default JAX device.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from sim_data.sim import robot as R
from sim_data.sim import scene as S
from sim_data.sim.env import HomeEnv
from sim_data.util import device_name, run_cli, write_json_atomic


def ready_controls(idx: R.RobotIndex, b: int, seed: int = 0) -> np.ndarray:
    """(b, 23) controls holding the ready pose under small random arm targets."""
    a = np.zeros((b, R.ACTION_DIM), np.float32)
    a[:, R.ARMS] = np.concatenate([S.READY_ARM, S.READY_ARM]) + 0.1 * np.random.default_rng(seed).standard_normal((b, 14))
    a[:, R.NECK.start + 1] = S.READY_NECK_PITCH
    return np.asarray(R.action_to_ctrl(jnp.asarray(a), jnp.zeros(b), idx))


def time_mjx(engine, physics, ctrl, mocap_pos, nsteps: int, repeats: int = 1):
    """Compiles and times nsteps MJX substeps of a batch; returns (best seconds, compile seconds, physics)."""
    run = jax.jit(lambda d: engine.advance(d, ctrl, mocap_pos, nsteps)[0])
    t0 = time.perf_counter()
    d = jax.block_until_ready(run(physics))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        d = jax.block_until_ready(run(d))
        times.append(time.perf_counter() - t0)
    return min(times), compile_s, d


def bench_cpu(batch: int, seconds: float = 3.0, nthread: int | None = None) -> dict:
    """Physics substeps per second of `batch` mug scenes on the cpu engine (nthread threads; None: its default),
    stepped in runs of 50 for about `seconds` after a warm-up. Returns {"engine", "batch", "nthread",
    "steps_per_s", "seconds", "mean_contacts" (per scene, after the last step)}."""
    env = HomeEnv("mug", batch, engine="cpu", nthread=nthread)
    st = env.reset(jax.random.PRNGKey(0))
    ctrl = ready_controls(env.idx.robot, batch)
    phys = st.physics
    ncon = env.engine.batch.bind("ncon")  # bound before stepping: refreshed by every call
    phys, _, _ = env.engine.advance(phys, ctrl, np.asarray(st.mocap_pos), 10)  # warm-up
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        phys, _, _ = env.engine.advance(phys, ctrl, np.asarray(st.mocap_pos), 50)
        n += 50
    dt = time.perf_counter() - t0
    return {"engine": "cpu", "batch": batch, "nthread": env.engine.batch.nthread, "steps_per_s": batch * n / dt,
            "seconds": dt, "mean_contacts": float(np.mean(ncon))}


def bench_mjx(batch: int, nsteps: int = 200, repeats: int = 3) -> dict:
    """Physics substeps per second of `batch` mug scenes on the mjx engine: nsteps substeps in one jitted program,
    best of `repeats` after the compiling call. Returns {"engine", "batch", "device", "steps_per_s", "seconds",
    "compile_s", "active_contacts" (penetrating contacts per scene at the end; None where MJX hides them)}."""
    env = HomeEnv("mug", batch, engine="mjx")
    st = env.reset(jax.random.PRNGKey(0))
    ctrl = jnp.asarray(ready_controls(env.idx.robot, batch))
    best, compile_s, d = time_mjx(env.engine, st.physics, ctrl, st.mocap_pos, nsteps, repeats)
    ncon = int(jnp.sum(d._impl.contact.dist < 0) / batch) if hasattr(d, "_impl") else None
    return {"engine": "mjx", "batch": batch, "device": device_name(), "steps_per_s": batch * nsteps / best,
            "seconds": best, "compile_s": compile_s, "active_contacts": ncon}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--engines", default=None, help="comma list of cpu,mjx (default: cpu, and mjx if a GPU is present)")
    p.add_argument("--cpu-batches", default="8,32,128")
    p.add_argument("--mjx-batches", default="256,1024,4096,8192,16384")
    a = p.parse_args(argv)
    has_gpu = any(d.platform == "gpu" for d in jax.devices())
    engines = a.engines.split(",") if a.engines else (["cpu", "mjx"] if has_gpu else ["cpu"])
    model = S.load_model()
    report = {
        "what": "physics substeps per second, full home scene (5 ms substeps)",
        "host": platform.node(), "cpu_count": os.cpu_count(), "jax_device": device_name(),
        "mujoco": mujoco.__version__, "jax": jax.__version__,
        "model": {"nq": model.nq, "nv": model.nv, "nu": model.nu, "ngeom": model.ngeom, "npair": model.npair,
                  "timestep": model.opt.timestep, "solver_iterations": model.opt.iterations},
        "results": [],
    }
    for eng in engines:
        batches = [int(x) for x in (a.cpu_batches if eng == "cpu" else a.mjx_batches).split(",")]
        for b in batches:
            r = bench_cpu(b) if eng == "cpu" else bench_mjx(b)
            report["results"].append(r)
            print(json.dumps(r), flush=True)
            write_json_atomic(a.out, report)
    best = {e: max((r["steps_per_s"] for r in report["results"] if r["engine"] == e), default=None) for e in engines}
    report["best_steps_per_s"] = best
    write_json_atomic(a.out, report)
    print(f"best: {best}; wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
