"""Rendering throughput: the JAX ray-cast renderer and MuJoCo's OpenGL renderer side by side.

    python -m sim_data.bench.render --out runs/bench/render.json [--batches 64,256] [--sizes 64,128]

Frames are of the full home scene from initial states of every task with the arms and neck at
random targets (poses from MuJoCo's kinematics, tiled up to the batch size). The JAX figure is a jitted batched call on the
default JAX device; MuJoCo's figure is one `mujoco.Renderer` (shadows on, as by default)
drawing states one after another, read back to host memory. `variants` records each culling
design tried, with its speed and its geom-id agreement with the un-culled renderer.
With `--e2e`, MJX physics + this renderer + a small convolutional policy run in one jitted
scan, and the figure is rendered control steps per second.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from sim_data.bench.render_check import random_states
from sim_data.sim import scene as S
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import HEAD_CAMERA, Poses, RenderConfig, Renderer, episode_rgb, poses_of
from sim_data.sim.tasks import TASK_NAMES
from sim_data.util import device_name, run_cli, write_json_atomic


def state_pool(per_task: int = 8, seed: int = 0):
    """qpos, mocap_pos, colors of per_task states of every task, arms and neck at random targets
    (numpy, stacked over tasks)."""
    parts = [random_states(t, per_task, seed) for t in TASK_NAMES]
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))


def _tile_to(x, b):
    reps = -(-b // x.shape[0])
    return jnp.concatenate([x] * reps)[:b]


def batch_inputs(geo, pool_poses: Poses, colors, b: int):
    """A render batch of b frames from the state pool, tiled to b rows: (poses, per-geom colours (b, ngeom, 3)
    float32), the pool's drawn colours (P, 4, 3) painted into geo's."""
    poses = jax.tree_util.tree_map(lambda x: _tile_to(x, b), pool_poses)
    return poses, _tile_to(episode_rgb(geo, colors), b)


def time_jax_renderer(renderer: Renderer, poses: Poses, rgb, min_seconds: float = 1.0) -> dict:
    """Best-of-repeats frames/s of one jitted batched render call (compile timed apart)."""
    fn = jax.jit(renderer.render_batch)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(poses, rgb))
    compile_s = time.perf_counter() - t0
    best, spent = np.inf, 0.0
    while spent < min_seconds:
        t0 = time.perf_counter()
        jax.block_until_ready(fn(poses, rgb))
        dt = time.perf_counter() - t0
        best, spent = min(best, dt), spent + dt
    b = poses.geom_xpos.shape[0]
    return {"frames_per_s": b / best, "seconds_per_batch": best, "compile_s": compile_s}


def time_mujoco_renderer(model, qpos, mocap, camera: str, size: int, min_seconds: float = 1.0) -> dict:
    """Frames/s of one `mujoco.Renderer` (shadows on) over the given states, looping."""
    data = mujoco.MjData(model)
    datas = []
    for q, mp in zip(qpos, mocap):
        data.qpos[:], data.mocap_pos[:] = q, mp
        mujoco.mj_forward(model, data)
        datas.append(data.__copy__())
    with mujoco.Renderer(model, size, size) as r:
        r.update_scene(datas[0], camera)
        r.render()
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < min_seconds:
            r.update_scene(datas[n % len(datas)], camera)
            r.render()
            n += 1
        dt = time.perf_counter() - t0
        shadows = bool(r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW])
    return {"frames_per_s": n / dt, "shadows": shadows}


def id_agreement(a, b) -> float:
    """The share of pixels whose geom id is the same in two renders (Renderer.render's dicts)."""
    return float(np.mean(np.asarray(a["geom_id"]) == np.asarray(b["geom_id"])))


VARIANTS = (
    ("all geoms per ray (tile=0)", dict(tile=0)),
    ("tiles 8px, 8 per type", dict(tile=8, max_per_tile=8)),
    ("tiles 8px, 16 per type", dict(tile=8, max_per_tile=16)),
    ("tiles 4px, 8 per type", dict(tile=4, max_per_tile=8)),
    ("tiles 16px, 16 per type", dict(tile=16, max_per_tile=16)),
    ("tiles 16px, 24 per type (default)", dict(tile=16, max_per_tile=24)),
    ("tiles 16px, 32 per type", dict(tile=16, max_per_tile=32)),
    ("tiles 32px, 32 per type", dict(tile=32, max_per_tile=32)),
    ("tiles 16px, 24 per type, shadows off", dict(tile=16, max_per_tile=24, shadows=False)),
)


def bench_variants(model, pool_poses, colors, b: int, size: int = 64, camera: str = HEAD_CAMERA) -> list:
    """Each culling design at one batch size: frames/s and agreement with the un-culled frames."""
    out, ref = [], None
    for name, kw in VARIANTS:
        cfg = RenderConfig(height=size, width=size, camera=camera, **kw)
        r = Renderer(model, cfg)
        poses, rgb = batch_inputs(r.geometry, pool_poses, colors, b)
        res = time_jax_renderer(r, poses, rgb)
        frames = r.render(poses, rgb)
        ref = ref or frames
        res.update(variant=name, batch=b, size=size, camera=camera, id_agreement_vs_unculled=id_agreement(frames, ref),
                   **kw)
        out.append(res)
        print(json.dumps(res), flush=True)
    return out


def bench_e2e(batch: int, size: int = 64, steps: int = 100, task: str = "mug") -> dict:
    """MJX physics + JAX renderer (head camera) + a small CNN policy, one jitted scan of `steps` control steps."""
    class SmallCNN(nn.Module):
        @nn.compact
        def __call__(self, image, proprio):
            x = image.astype(jnp.float32) / 255.0
            for ch in (16, 32, 32):
                x = nn.relu(nn.Conv(ch, (3, 3), strides=2)(x))
            x = jnp.concatenate([x.reshape(x.shape[0], -1), proprio], -1)
            return jnp.tanh(nn.Dense(20)(nn.relu(nn.Dense(128)(x))))

    env = HomeEnv(task, batch, engine="mjx")
    r = Renderer(env.model, RenderConfig(height=size, width=size, camera=HEAD_CAMERA))
    net = SmallCNN()
    st = env.reset(jax.random.PRNGKey(0))
    params = net.init(jax.random.PRNGKey(1), jnp.zeros((1, size, size, 3), jnp.uint8), jnp.zeros((1, 37)))
    rgb = episode_rgb(r.geometry, st.task.colors)
    ready = jnp.zeros((20,)).at[:14].set(jnp.concatenate([jnp.asarray(S.READY_ARM)] * 2)).at[15].set(S.READY_NECK_PITCH)

    @jax.jit
    def episode(params, state):
        def body(s, _):
            image = r.render_batch(env.poses(s), rgb)["rgb"]
            action = ready + 0.1 * net.apply(params, image, s.obs["proprio"])
            return env.core.mjx_step(s, action), jnp.mean(image)
        return jax.lax.scan(body, state, None, length=steps)

    t0 = time.perf_counter()
    jax.block_until_ready(episode(params, st))
    compile_s = time.perf_counter() - t0
    best = np.inf
    for _ in range(2):
        t0 = time.perf_counter()
        jax.block_until_ready(episode(params, st))
        best = min(best, time.perf_counter() - t0)
    return {"what": "rendered control steps/s (10 physics substeps + head-camera frame + CNN policy)", "batch": batch,
            "size": size, "control_steps_per_s": batch * steps / best, "frames_per_s": batch * steps / best,
            "physics_substeps_per_s": batch * steps * 10 / best, "compile_s": compile_s}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--batches", default=None, help="JAX renderer batch sizes (default: 16,64 on CPU; 1024..16384 on GPU)")
    p.add_argument("--sizes", default="64,128")
    p.add_argument("--cameras", default="head_cam,ext_cam")
    p.add_argument("--variants", type=int, default=0, help="time every culling design at this batch size too")
    p.add_argument("--e2e", default="", help="batch sizes for the end-to-end MJX + renderer + policy scan")
    a = p.parse_args(argv)
    gpu = any(d.platform == "gpu" for d in jax.devices())
    batches = [int(x) for x in (a.batches or ("1024,4096,16384" if gpu else "16,64")).split(",")]
    model = S.load_model()
    qpos, mocap, colors = state_pool()
    pool = poses_of(model, qpos, mocap)
    report = {"what": "frames per second, full home scene; JAX ray-cast renderer vs MuJoCo's OpenGL renderer",
              "jax_device": device_name(), "jax": jax.__version__, "mujoco": mujoco.__version__,
              "ngeom_visible": int(sum(len(ids) for _, ids in Renderer(model).geometry.groups)),
              "mujoco_renderer": [], "jax_renderer": [], "variants": [], "e2e": []}
    for size in (int(s) for s in a.sizes.split(",")):
        for camera in a.cameras.split(","):
            res = dict(size=size, camera=camera, **time_mujoco_renderer(model, qpos, mocap, camera, size))
            report["mujoco_renderer"].append(res)
            print(json.dumps(res), flush=True)
            r = Renderer(model, RenderConfig(height=size, width=size, camera=camera))
            for b in batches:
                poses, rgb = batch_inputs(r.geometry, pool, colors, b)
                res = dict(size=size, camera=camera, batch=b, tile=r.cfg.tile, max_per_tile=r.cfg.max_per_tile)
                try:
                    res.update(time_jax_renderer(r, poses, rgb))
                except Exception as e:  # out of device memory at the largest sizes: recorded, not fatal
                    res.update(error=f"{type(e).__name__}: {str(e)[:200]}", frames_per_s=0.0)
                report["jax_renderer"].append(res)
                print(json.dumps(res), flush=True)
            write_json_atomic(a.out, report)
    if a.variants:
        report["variants"] = bench_variants(model, pool, colors, a.variants)
        write_json_atomic(a.out, report)
    for b in (int(x) for x in a.e2e.split(",") if x):
        res = bench_e2e(b)
        report["e2e"].append(res)
        print(json.dumps(res), flush=True)
        write_json_atomic(a.out, report)
    summary = {}
    for m in report["mujoco_renderer"]:
        ours = max(r.get("frames_per_s", 0.0) for r in report["jax_renderer"] if r["size"] == m["size"] and r["camera"] == m["camera"])
        summary[f"{m['camera']}@{m['size']}"] = {"jax_fps": ours, "mujoco_fps": m["frames_per_s"], "ratio": ours / m["frames_per_s"]}
    report["summary"] = summary
    write_json_atomic(a.out, report)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
