"""How closely policies read a world model's predicted frames, beside frames that know nothing of the future.

    python -m experiments.probe_study --runs runs/wm/demo runs/wm/demo_read [--batches 12] [--out F.json]

The read loss's probes (wm.probes: behaviour-cloning checkpoints whose rollouts the run's data holds,
each frame read by one checkpoint of its task) read every 4th frame of held-out training windows. For
each run the read term of its predictions (the teacher-forced pass and each rollout pass of wm.train's
loss, read as the run would be trained with `w_read=1`), and beside them, on the same windows and
probes, the term of four stand-ins for the prediction: the previous true frame (copy-last), the
window's first frame held, a grey frame, and another window's true frames. Where a model reads no
closer than copy-last, the read loss has little left to train that the frames' unpredictable detail
does not hold; another window's frames show how far the probes move with the frames at all.

Writes OUT (JSON: per run its terms and the stand-ins') where --out is given, and prints a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sim_data.dataset.cache import TrainingCache, WindowLoader
from sim_data.util import run_cli, write_json_atomic
from wm.checkpoint import load_run_config, load_trained
from wm.probes import Probes, read_loss
from wm.train import every_fourth, jitted_validation_loss, model_batch, read_inputs, read_probes

STAND_INS = ("copy_last", "first_held", "grey", "other_window")
_read = jax.jit(read_loss)


def stand_in_terms(probes: Probes, batch: dict) -> dict:
    """The read term (wm.probes.read_loss) of each stand-in for the predicted frames of a batch
    (model_batch's with read=True: frames (B, T, S, S, 3) uint8, proprio, task, start), against its
    true frames 1..T-1: {"copy_last", "first_held", "grey", "other_window"} floats."""
    pix = jnp.asarray(batch["frames"]).astype(jnp.float32) / 255.0
    target = pix[:, 1:]
    proprio, t, task = read_inputs(batch, pix.shape[1])
    true = every_fourth(target)
    stand_in = {
        "copy_last": every_fourth(pix[:, :-1]),
        "first_held": every_fourth(jnp.broadcast_to(pix[:, :1], target.shape)),
        "grey": jnp.full_like(true, 0.5),
        "other_window": every_fourth(jnp.roll(target, 1, axis=0)),
    }
    return {k: float(_read(probes, v, true, proprio, t, task)) for k, v in stand_in.items()}



def study_run(run: Path, batches: int) -> dict:
    """Mean over the first `batches` held-out batches of the run's read terms ("read", "read_pass1", ...)
    and the stand-ins' (stand_in_terms), with the probes' names and the batch count."""
    cfg, params, norm = load_trained(run)
    _, data = load_run_config(run)
    cfg = dataclasses.replace(cfg, w_read=1.0)
    cache = TrainingCache(data)
    if not cache.select("val"):
        raise ValueError(f"{data} holds no held-out episodes to read")
    probes = read_probes(cfg, cache, data)
    val = WindowLoader(cache, cfg.window, cfg.batch, split="val", seed=1234, cameras=[cfg.camera])
    n = min(batches, val.batches_per_epoch)
    model, stand = [], []
    for k in range(n):
        b = model_batch(val.batch_at(0, k), cfg.camera, cfg.model.anchor, cfg.model.scene, read=True,
                        grip=cfg.grip_focus > 0)
        parts = jax.device_get(jitted_validation_loss(cfg, params, jax.device_put(b), norm, None, probes))
        model.append({key: float(v) for key, v in parts.items() if key.startswith("read")})
        stand.append(stand_in_terms(probes, b))
    mean = lambda rows: {key: float(np.mean([r[key] for r in rows])) for key in rows[0]}  # noqa: E731
    return {"batches": n, "model": mean(model), "stand_ins": mean(stand)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", nargs="+", type=Path, required=True, help="world-model runs or bundles (wm.train OUT)")
    p.add_argument("--batches", type=int, default=12, help="held-out batches to average over")
    p.add_argument("--out", type=Path, help="where to write the JSON")
    a = p.parse_args(argv)
    if a.batches < 1:
        p.error("--batches must be >= 1")
    missing = [str(r) for r in a.runs if not r.exists()]
    if missing:
        p.error(f"no such run: {', '.join(missing)}")
    result = {}
    for run in a.runs:
        try:
            result[str(run)] = study_run(run, a.batches)
        except (ValueError, FileNotFoundError) as e:
            print(f"{run}: {e}", file=sys.stderr)
            return 1
    print("| run | model: " + ", ".join(next(iter(result.values()))["model"]) + " | " + " | ".join(STAND_INS) + " |")
    print("|---|---|" + "---|" * len(STAND_INS))
    for run, r in result.items():
        print(f"| {run} | " + ", ".join(f"{v:.4f}" for v in r["model"].values()) + " | "
              + " | ".join(f"{r['stand_ins'][k]:.4f}" for k in STAND_INS) + " |")
    if a.out:
        write_json_atomic(a.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
