"""The JAX renderer against MuJoCo's OpenGL renderer: geom ids and depth on states of every task.

`python -m sim_data.bench.render_check --states 50` prints and writes the agreement per task and camera;
`tests/test_render.py` runs a smaller version.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import jax
import mujoco
import numpy as np

from sim_data.policies.scripted import ScriptedPolicy
from sim_data.sim import scene as S
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import (
    CAMERAS,
    RenderConfig,
    Renderer,
    episode_rgb,
    poses_of,
)
from sim_data.sim.rollout import run_episodes
from sim_data.sim.tasks import TASK_NAMES
from sim_data.util import run_cli, write_json_atomic

ID_TARGET, DEPTH_TARGET = 0.98, 0.01


def sample_states(task: str, n: int, seed: int = 0, heldout: bool = False):
    """n states from scripted episodes of task (cpu engine), one at a random step of each episode.

    Returns qpos (n, nq), mocap_pos (n, nmocap, 3), colors (n, 4, 3) as numpy arrays.
    """
    env = HomeEnv(task, n, engine="cpu", heldout=heldout)
    policy = ScriptedPolicy.create(task, env.model)
    final, traj = run_episodes(env, policy, {"skill": np.ones((n,), np.float32)}, jax.random.PRNGKey(seed), record=True)
    steps = np.random.default_rng(seed).integers(0, env.episode_steps, n)
    rows = np.arange(n)
    colors = np.asarray(final.task.colors)  # drawn at reset, constant over the episode
    return np.asarray(traj.qpos)[rows, steps], np.asarray(traj.mocap_pos)[rows, steps], colors


def random_states(task: str, n: int, seed: int = 0, heldout: bool = False):
    """n initial states of task with the arms and neck moved to uniformly random targets (cheap:
    no episode is run). Returns qpos (n, nq), mocap_pos (n, nmocap, 3), colors (n, 4, 3)."""
    env = HomeEnv(task, n, engine="cpu", heldout=heldout)
    st = env.reset(jax.random.PRNGKey(seed))
    idx = env.idx.robot
    rng = np.random.default_rng(seed)
    qpos = np.array(st.qpos)
    lo, hi = idx.action_low[:16], idx.action_high[:16]
    qpos[:, idx.posed_qpos] = rng.uniform(lo, hi, (n, 16))
    return qpos, np.asarray(st.mocap_pos), np.asarray(st.task.colors)


def mujoco_reference(model: mujoco.MjModel, qpos, mocap_pos, camera: str, height: int, width: int):
    """MuJoCo's segmentation geom ids (B, H, W) (-1 background) and depth (B, H, W) in metres."""
    data = mujoco.MjData(model)
    ids, depths = [], []
    with mujoco.Renderer(model, height, width) as r:
        for q, mp in zip(qpos, mocap_pos):
            data.qpos[:], data.mocap_pos[:] = q, mp
            mujoco.mj_forward(model, data)
            r.update_scene(data, camera)
            r.enable_segmentation_rendering()
            seg = r.render()
            r.disable_segmentation_rendering()
            r.enable_depth_rendering()
            depths.append(r.render().copy())
            r.disable_depth_rendering()
            ids.append(np.where(seg[..., 1] == mujoco.mjtObj.mjOBJ_GEOM, seg[..., 0], -1))
    return np.stack(ids), np.stack(depths)


def compare(ids, depth, ref_ids, ref_depth) -> dict:
    """Share of pixels whose geom id agrees, and of those (on geoms) whose depth is within 1%."""
    same = ids == ref_ids
    on_geom = same & (ref_ids >= 0)
    rel = np.abs(depth - ref_depth) / np.maximum(ref_depth, 1e-6)
    return {
        "id_agreement": float(same.mean()),
        "id_agreement_min_frame": float(same.reshape(len(ids), -1).mean(1).min()),
        "depth_within_1pct": float((rel[on_geom] <= DEPTH_TARGET).mean()) if on_geom.any() else 1.0,
        "depth_max_rel_err": float(rel[on_geom].max()) if on_geom.any() else 0.0,
    }


def agreement(states, cfg: RenderConfig, renderer: Renderer | None = None) -> dict:
    """Renders states (qpos, mocap_pos, colors) with both renderers (camera, size of cfg) and compares them."""
    model = S.load_model()
    qpos, mocap, colors = states
    r = renderer or Renderer(model, cfg)
    out = r.render(poses_of(model, qpos, mocap), episode_rgb(r.geometry, colors))
    ref_ids, ref_depth = mujoco_reference(model, qpos, mocap, cfg.camera, cfg.height, cfg.width)
    return compare(np.asarray(out["geom_id"]), np.asarray(out["depth"]), ref_ids, ref_depth)


def side_by_side(task: str, n: int, cfg: RenderConfig, seed: int = 0) -> np.ndarray:
    """(H, n*W*2, 3) uint8: each state drawn by MuJoCo (left) and by the JAX renderer (right)."""
    model = S.load_model()
    qpos, mocap, colors = sample_states(task, n, seed)
    r = Renderer(model, cfg)
    ours = np.asarray(r.render(poses_of(model, qpos, mocap), episode_rgb(r.geometry, colors))["rgb"])
    painted = copy.deepcopy(model)
    data = mujoco.MjData(painted)
    tiles = []
    with mujoco.Renderer(painted, cfg.height, cfg.width) as mr:
        for i in range(n):
            S.paint(painted, colors[i])
            data.qpos[:], data.mocap_pos[:] = qpos[i], mocap[i]
            mujoco.mj_forward(painted, data)
            mr.update_scene(data, cfg.camera)
            tiles += [mr.render().copy(), ours[i]]
    return np.concatenate(tiles, axis=1)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--states", type=int, default=50, help="states per task")
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--tasks", default=",".join(TASK_NAMES))
    p.add_argument("--out", type=Path, default=Path("runs/render_check.json"))
    a = p.parse_args(argv)
    results = {}
    renderers = {c: Renderer(S.load_model(), RenderConfig(height=a.size, width=a.size, camera=c)) for c in CAMERAS}
    for task in a.tasks.split(","):
        states = sample_states(task, a.states)
        for camera, r in renderers.items():
            res = agreement(states, r.cfg, renderer=r)
            results[f"{task}/{camera}"] = res
            print(f"{task:10s} {camera:8s} ids {res['id_agreement']:.4f} (worst frame {res['id_agreement_min_frame']:.3f})"
                  f"  depth within 1% {res['depth_within_1pct']:.4f}", flush=True)
    write_json_atomic(a.out, {"states_per_task": a.states, "size": a.size, "targets": {"id": ID_TARGET, "depth_rel": DEPTH_TARGET},
                              "results": results})
    print(json.dumps({"min_id_agreement": min(r["id_agreement"] for r in results.values())}))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
