"""Does the world model keep the air fryer's body in place while the tray slides?

    python -m experiments.body_in_place --wm runs/sweeps/airfryer_transfer_demo/x=1/seed=0 \
        --data runs/data/sweep_demo_airfryer_mug --out runs/body_in_place.json

The published failure with too little interaction data is a model that pulls the whole air fryer
off the counter instead of sliding out its tray. The fryer's body is welded to the world, so in
the simulator its pixels move only when the head camera does. For each test episode of the air
fryer, the true frames' pixels of the fryer's body (geoms of body `fryer`, not of `fryer_tray`) are
found by rendering the recorded simulator state with the project's renderer (its per-pixel geom
ids), and the world model imagines the episode open loop under its logged actions from `context`
observations at four starts, as `wm.quality` does. Per horizon, over the samples whose body
pixels did not change since the last context frame (the camera still), it reports the PSNR of
the imagined frame inside the body's pixels ("body") and outside them ("rest"), both pooled over
samples: a model that keeps the body in place draws it at least as well as the rest of the scene,
one that moves it draws it worse.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import mujoco
import numpy as np

from sim_data.dataset.cache import TrainingCache
from sim_data.dataset.episodes import read_episode
from sim_data.sim.render import HEAD_CAMERA, RenderConfig, Renderer, poses_from_arrays
from sim_data.sim.scene import load_model
from sim_data.util import run_cli, write_json_atomic
from wm.checkpoint import load_trained
from wm.imagine import context_sample, open_loop_chunked
from wm.metrics import psnr
from wm.quality import sample_starts

BODY, TRAY = "fryer", "fryer_tray"
TASK = "airfryer"


@functools.cache
def _scene():
    model = load_model()
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, BODY)
    return model, np.flatnonzero(model.geom_bodyid == body)


def body_masks(qpos, mocap_pos, camera: str = HEAD_CAMERA, size: int = 64) -> np.ndarray:
    """Pixels of the air fryer's body in the frames of a recorded state sequence: qpos (T, nq),
    mocap_pos (T, nmocap, 3) -> (T, size, size) bool."""
    model, geoms = _scene()
    data = mujoco.MjData(model)
    arrays = {k: [] for k in ("geom_xpos", "geom_xmat", "cam_xpos", "cam_xmat")}
    for q, m in zip(np.asarray(qpos, np.float64), np.asarray(mocap_pos, np.float64).reshape(len(qpos), -1, 3),
                    strict=True):
        data.qpos[:] = q
        data.mocap_pos[:] = m
        mujoco.mj_kinematics(model, data)
        mujoco.mj_camlight(model, data)
        for k in arrays:
            arrays[k].append(getattr(data, k).copy())
    poses = poses_from_arrays(*(np.stack(arrays[k]) for k in ("geom_xpos", "geom_xmat", "cam_xpos", "cam_xmat")))
    return np.isin(np.asarray(_renderer(camera, size).render(poses)["geom_id"]), geoms)


@functools.cache
def _renderer(camera: str, size: int) -> Renderer:
    return Renderer(_scene()[0], RenderConfig(height=size, width=size, camera=camera))


def _pooled_psnr(pred, true, mask) -> float | None:
    """PSNR of the squared error pooled over the masked pixels of every sample (None if none)."""
    return float(psnr(pred[mask], true[mask], axis=None)) if mask.any() else None


def measure(wm_run: Path, data: Path, horizons=(1, 4, 8, 16), context: int = 4, max_episodes: int = 64) -> dict:
    """The body-in-place figures of one trained world model on the air-fryer test episodes of data."""
    cfg, params, norm = load_trained(Path(wm_run))
    cache = TrainingCache(data)
    test = cache.select("test", [TASK])[:max_episodes]
    if not test:
        raise ValueError(f"{data} has no {TASK} test episodes")
    context = min(context, cfg.model.context)
    hmax = max(horizons)
    samples, truths, masks = [], [], []
    for i in test:
        e = cache.episodes[i]
        starts = sample_starts(e["length"], context, hmax)
        if not starts:
            continue
        ep = cache.episode(i, cameras=[cfg.camera])
        sim = read_episode(Path(data) / e["file"], cameras=[])
        body = body_masks(sim["qpos"], sim["mocap_pos"], cfg.camera, cfg.model.size)
        for start in starts:
            samples.append(context_sample(ep, cfg.camera, start, context, hmax))
            truths.append(ep["frames"][cfg.camera][start + context:start + context + hmax])
            masks.append(body[start + context - 1:start + context + hmax])  # the last context frame first
    if not samples:
        raise ValueError(f"no {TASK} test episode is long enough for context {context} + horizon {hmax}")
    pred = open_loop_chunked(cfg.model, params, norm, samples, hmax)["frames"]
    truth, mask = np.stack(truths), np.stack(masks)
    out = {"wm": str(wm_run), "data": str(data), "episodes": len(test), "samples": len(samples), "context": context,
           "horizons": list(horizons), "still_share": [], "body_pixels": [], "body_psnr": [], "rest_psnr": []}
    for h in horizons:
        still = (mask[:, h] == mask[:, 0]).all(axis=(1, 2)) & mask[:, h].any(axis=(1, 2))
        m = mask[still, h][..., None].repeat(3, -1)
        out["still_share"].append(float(still.mean()))
        out["body_pixels"].append(float(mask[still, h].mean()) if still.any() else None)
        out["body_psnr"].append(_pooled_psnr(pred[still, h - 1], truth[still, h - 1], m))
        out["rest_psnr"].append(_pooled_psnr(pred[still, h - 1], truth[still, h - 1], ~m))
    at = {h: k for k, h in enumerate(horizons)}
    out["summary"] = {f"{k}_h8": out[k][at[8]] if 8 in at else None for k in ("body_psnr", "rest_psnr")}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--wm", type=Path, required=True, help="a training run's directory (make train OUT)")
    p.add_argument("--data", type=Path, required=True, help="a dataset with air-fryer test episodes")
    p.add_argument("--out", type=Path, required=True, help="the JSON file to write")
    p.add_argument("--max-episodes", type=int, default=64)
    a = p.parse_args(argv)
    res = measure(a.wm, a.data, max_episodes=a.max_episodes)
    write_json_atomic(a.out, res)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
