"""Training the world model: `make train CONFIG=<preset> DATA=<dataset> OUT=<dir>`.

    python -m wm.train --config demo --data runs/data/demo --out runs/wm/demo [key=value ...]

One jitted, donated step trains tokenizer, dynamics and heads together (bf16 compute, float32
parameters) on shuffled windows from the dataset's training cache, data parallel over a
`jax.sharding` mesh of every local device (`param_sharding=fsdp` also shards parameters and
optimiser state); `--distributed` calls `jax.distributed.initialize()` for several hosts.
Orbax keeps the latest checkpoint (model, optimiser and data-iterator state; rerunning the same
command resumes) and the kept parameters in `best/` (`select`: those of the lowest validation loss, or
the last step's). Metrics go to `metrics.jsonl`; a non-finite
loss stops the run before any checkpoint of it is written. The budget is `steps`; `max_minutes` is a
safety stop that marks the run cut short (`train_status.json`) and leaves the rest to a rerun of the
same command, so that a budget longer than one command trains over several. When `steps` are done
the episode judge is fitted (`wm.judge`) and `eval.json` written from the kept parameters
(`wm.quality`).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from jax.experimental import multihost_utils
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P
from tqdm import tqdm

from sim_data.config import as_json, preset_help, save_or_check
from sim_data.dataset.cache import TrainingCache, WindowLoader, epoch_episodes
from sim_data.policies.registry import resolve as resolve_policies
from sim_data.util import make_output_dir, run_cli, write_json_atomic
from wm import perceptual
from wm.carry import adopt_data_path, best_from_latest, check_data
from wm.checkpoint import restore_params
from wm.config import PRESETS, TrainConfig, check_dataset, make_config, to_dict
from wm.imagine import Norm, to_uint8
from wm.judge import dataset_policies, fit_judge, judges_fit, load_judge, warm_judge
from wm.metrics import action_contrast, gaussian_kl
from wm.model import INPUT_CLIP, REFINE_SIGMA, WorldModel, block_flow, init_params
from wm.probes import make_probes, probe_rows, probe_sources, read_dims, read_loss_from, readings
from wm.quality import evaluate


class TrainingDiverged(FloatingPointError):
    """The loss became NaN or infinite."""


# ---- data ------------------------------------------------------------------------------------------

def compute_norm(cache: TrainingCache, ids=None) -> Norm:
    """Mean and std of proprio, actions and the scene state over the episodes ids (default: the training
    split; std floored at 1e-2: a dimension constant in training must not blow a policy's small
    deviation up)."""
    eps = [cache.episodes[i] for i in (cache.select("train") if ids is None else ids)]
    if not eps:
        raise ValueError("the dataset has no training episodes")

    def rows(name, drop_last=0):
        return np.concatenate([cache.array(e["shard"], name)[e["start"]:e["start"] + e["length"] - drop_last]
                               for e in eps])

    prop, act, scene = rows("proprio"), rows("action", drop_last=1), rows("scene")
    return Norm(proprio_mean=jnp.asarray(prop.mean(0)), proprio_std=jnp.asarray(np.maximum(prop.std(0), 1e-2)),
                action_mean=jnp.asarray(act.mean(0)), action_std=jnp.asarray(np.maximum(act.std(0), 1e-2)),
                scene_mean=jnp.asarray(scene.mean(0)), scene_std=jnp.asarray(np.maximum(scene.std(0), 1e-2)))


ATTEMPT_KINDS = ("scripted", "learned", "weak_grip", "drive")  # episodes that try the task (not play, not programs)


def failed_attempts_repeated(times: int):
    """A WindowLoader `repeat`: a failed task attempt (ATTEMPT_KINDS, unsuccessful) `times`, any other episode once."""
    return lambda rec: times if rec.get("policy_kind") in ATTEMPT_KINDS and not rec["success"] else 1


def _repeat(cfg: TrainConfig):
    """The WindowLoader `repeat` of cfg's training episodes (None: each once)."""
    return failed_attempts_repeated(cfg.fail_repeat) if cfg.fail_repeat > 1 else None


def training_episodes(cfg: TrainConfig, cache: TrainingCache) -> list[int]:
    """The episodes of a training epoch of cfg (Run's loader's `episodes`), from which the episode judge
    draws its own."""
    return [int(i) for i in epoch_episodes(cache, cfg.window, "train", cfg.train_tasks or None, cfg.train_fraction,
                                           _repeat(cfg))]


def model_batch(batch: dict, camera: str, anchor: bool = False, scene: bool = False, read: bool = False,
                grip: bool = False) -> dict:
    """The loader's batch reduced to what the model trains on (with anchor: and the episodes' first
    frames, "anchor" (B, S, S, 3) uint8, and the windows' first steps in their episodes, "start" (B,)
    int32, for a model with ModelConfig.anchor; with scene: and "scene" (B, T, 24), for a model with
    ModelConfig.scene; with read: and the windows' tasks "task" (B,) int32 and first steps "start", for
    the read loss, TrainConfig.w_read; with grip: and the grip sites' image positions "grip_px"
    (B, T, 2, 2), for TrainConfig.grip_focus)."""
    out = {"frames": batch["frames"][camera], "proprio": batch["proprio"], "action": batch["action"],
           "success": batch["success"], "progress": batch["progress"], "outcome": batch["outcome"]}
    out |= {"scene": batch["scene"]} if scene else {}
    out |= {"grip_px": batch["grip_px"]} if grip else {}
    out |= {"task": batch["task"], "start": batch["start"]} if read else {}
    return out | ({"anchor": batch["first_frames"][camera], "start": batch["start"]} if anchor else {})


def training_batch(batch: dict, cfg: TrainConfig) -> dict:
    """model_batch with what cfg's model and losses read."""
    return model_batch(batch, cfg.camera, cfg.model.anchor, cfg.model.scene, cfg.w_read > 0, cfg.grip_focus > 0)


# ---- loss and step ---------------------------------------------------------------------------------

def _bce(logits, labels):
    return optax.sigmoid_binary_cross_entropy(logits, labels.astype(jnp.float32)).mean()


def _keep_loss(keep, target, prev):
    """Cross-entropy of the keep gate's logits (..., S, S) against the pixels whose 8-bit value the
    target frame shares with the previous one (frames (..., S, S, 3) in [0, 1])."""
    return _bce(keep, jnp.all(jnp.round(target * 255.0) == jnp.round(prev * 255.0), axis=-1))


def _lpips_loss(weights, pred, target):
    """Mean LPIPS of predicted frames (..., S, S, 3) in [0, 1] against the true ones."""
    flat = lambda x: x.reshape((-1,) + x.shape[-3:])
    return jnp.mean(perceptual.distance(weights, flat(pred), flat(jax.lax.stop_gradient(target))))


def read_inputs(batch: dict, frames: int) -> tuple:
    """(proprio (N, 37), steps (N,) int32, task (N,) int32) of every 4th predicted frame of a window of
    `frames` frames (frames 1, 5, ...), the rows of the batch's windows one after another: what the
    read loss's probes are given beside each frame."""
    b = batch["proprio"].shape[0]
    step = batch["start"][:, None] + 1 + jnp.arange(frames - 1)[None, ::4]
    n = step.shape[1]
    return (every_fourth(batch["proprio"][:, 1:]), step.reshape(b * n).astype(jnp.int32),
            jnp.broadcast_to(batch["task"][:, None], (b, n)).reshape(b * n))


def every_fourth(x):
    """Frames 0, 4, ... of x (B, T, ...) as (B * ceil(T / 4), ...)."""
    y = x[:, ::4]
    return y.reshape((-1,) + y.shape[2:])


REFINE_STREAM = 1 << 10  # the frame generator's draws: fold_in(rng, this + pass), apart from the counters above
PROPRIO_NOISE_STREAM = 1 << 11  # the input proprioception's noise (proprio_noise): fold_in(rng, this)


def with_window_noise(x, key, max_std: float, bound: float):
    """x (B, ...) plus Gaussian noise of a std each window (row) draws uniformly below max_std, clipped to
    +-bound: the context's and the proprioception's noise augmentation."""
    k1, k2 = jax.random.split(key)
    level = jax.random.uniform(k1, (x.shape[0],) + (1,) * (x.ndim - 1), maxval=max_std)
    return jnp.clip(x + level * jax.random.normal(k2, x.shape), -bound, bound)


def grip_weights(grip_px, size: int, focus: float, radius: float) -> jax.Array:
    """(B, T, S, S) float32 pixel weights of frames of size S x S whose hands' grip sites appear at grip_px
    (B, T, 2, 2) (image coordinates in [0, 1], NaN where a site is behind the camera): 1 + focus x
    exp(-d^2 / 2 radius^2), d each pixel centre's distance from the nearer site, in frame widths."""
    centres = (jnp.arange(size, dtype=jnp.float32) + 0.5) / size
    u, v = grip_px[..., 0][..., None, None], grip_px[..., 1][..., None, None]  # (B, T, 2, 1, 1)
    d2 = (centres[:, None] - v) ** 2 + (centres[None, :] - u) ** 2  # (B, T, 2, S, S): rows by v, columns by u
    near = jnp.where(jnp.isnan(d2), 0.0, jnp.exp(-d2 / (2 * radius**2))).max(axis=2)
    return 1.0 + focus * near


def weighted_mse(pred, target, weights=None) -> jax.Array:
    """The mean squared error of frames (..., S, S, 3), each pixel weighted by weights (..., S, S) normalised
    to a mean of 1 (None: the plain mean)."""
    if weights is None:
        return jnp.mean((pred - target) ** 2)
    w = jax.lax.stop_gradient(weights)
    return jnp.sum(w[..., None] * (pred - target) ** 2) / (jnp.sum(w) * pred.shape[-1])


def _refine_loss(model, params, decoded, z, target, k: int, passes: int, key, weights=None):
    """The frame generator's flow-matching loss on pass k's decoded frames (B, T, S, S, 3) in [0, 1]
    (predicted latents z (B, T, 8, 8, C), true frames target): every 2(passes + 1)-th frame from the
    k-th, a noise level drawn uniformly for each, the squared error of its estimate of the clean
    frame, in pixel units, weighted by weights (B, T, S, S) where given (weighted_mse). Decoded frames
    and latents enter with their gradient stopped."""
    pick = slice(k, None, 2 * (passes + 1))
    base, zc, goal = (jax.lax.stop_gradient(x[:, pick]) for x in (decoded, z, target))
    k_noise, k_time = jax.random.split(key)
    noise = REFINE_SIGMA * jax.random.normal(k_noise, base.shape)
    t = jax.random.uniform(k_time, base.shape[:2])
    s = t[..., None, None, None]
    noisy = (1.0 - s) * noise + s * (goal - base)
    clean = model.apply({"params": params}, noisy, t, base, zc, method=WorldModel.denoise)
    return weighted_mse(base + clean, goal, None if weights is None else weights[:, pick])


def _flow_loss(flow, true_flow, confidence):
    """The predicted flows' (B, T, 8, 8, 2) absolute distance from the block-matched ones (wm.model.block_flow),
    in latent cells, each cell weighed by its match's confidence (B, T, 8, 8): a mean over cells and frames."""
    return jnp.mean(confidence * jnp.abs(flow - true_flow).sum(-1))


def loss_fn(params, batch: dict, norm: Norm, cfg: TrainConfig, rng=None, lpips_weights=None, probes=None):
    """Scalar loss and its parts for one batch (frames (B, T, S, S, 3) uint8, ...; with an anchor frame
    "anchor" (B, S, S, 3) uint8 and "start" (B,) int too: model_batch); rng draws the context noise, the
    proprioception's noise and the windows that train without their anchor (None: none of them, as in
    validation); lpips_weights: the perceptual network's (wm.perceptual.params()), needed where
    cfg.w_lpips > 0; probes: the read loss's checkpoints (wm.probes.Probes), needed where
    cfg.w_read > 0, with "task" and "start" in the batch (model_batch's read); "grip_px" (B, T, 2, 2) where
    cfg.grip_focus > 0 (model_batch's grip)."""
    if cfg.w_lpips > 0 and lpips_weights is None:
        raise ValueError("w_lpips > 0 needs the LPIPS network's weights (wm.perceptual.params())")
    if cfg.w_read > 0 and probes is None:
        raise ValueError("w_read > 0 needs probe checkpoints (wm.probes.make_probes)")
    model = WorldModel(cfg.model)
    frames = batch["frames"]
    pix = frames.astype(jnp.float32) / 255.0
    target = pix[:, 1:]
    focus = (grip_weights(batch["grip_px"][:, 1:], target.shape[2], cfg.grip_focus, cfg.grip_radius)
             if cfg.grip_focus > 0 else None)
    if cfg.w_read > 0:  # the probes read the true frames once; each pass's predictions are read against them
        read_proprio, read_t, read_task = read_inputs(batch, frames.shape[1])
        read_rows = probe_rows(probes, read_task)
        true_read = readings(probes, every_fourth(target), read_proprio, read_t, read_rows)
    z = model.apply({"params": params}, frames, method=WorldModel.encode)
    # reconstruction of every 4th frame from its true latents and the true previous frame; the
    # decoder also learns from every predicted frame below
    recon, keep = model.apply({"params": params}, z[:, 1::4], pix[:, 0:-1:4], with_keep=True, method=WorldModel.decode)
    parts = {"recon": jnp.mean((recon - pix[:, 1::4]) ** 2)}
    total = cfg.w_recon * parts["recon"]
    if keep is not None:
        parts["keep_recon"] = _keep_loss(keep, pix[:, 1::4], pix[:, 0:-1:4])
        total = total + cfg.w_keep * parts["keep_recon"]
    proprio, action = norm.proprio(batch["proprio"]), norm.action(batch["action"])
    scene = norm.scene(batch["scene"]) if cfg.model.scene else None
    z_in, p_in, prev = z, proprio, pix[:, :-1]
    anchor = time = keep_anchor = None
    if cfg.model.anchor:
        anchor = model.apply({"params": params}, batch["anchor"], method=WorldModel.encode)
        time = batch["start"][:, None] + jnp.arange(frames.shape[1])
        if rng is not None and cfg.anchor_drop > 0:
            # the noise below splits rng into counters 0 and 1 (fold_in(rng, 1) is its second key): 2 is the anchor's
            keep_anchor = jax.random.uniform(jax.random.fold_in(rng, 2), (frames.shape[0],)) >= cfg.anchor_drop
    if cfg.context_noise > 0 and rng is not None:  # corrupted inputs: the past cannot be copied forward exactly
        z_in = with_window_noise(z, rng, cfg.context_noise, 1.0)
    if cfg.proprio_noise > 0 and rng is not None:  # the body's present is not to be copied forward exactly
        p_in = with_window_noise(proprio, jax.random.fold_in(rng, PROPRIO_NOISE_STREAM), cfg.proprio_noise, INPUT_CLIP)
    z_target = jax.lax.stop_gradient(z[:, 1:])
    # the stochastic code's posterior reads prediction t's target, frame t+1 (the last prediction has none)
    code_target = jnp.concatenate([z_target, jnp.zeros_like(z[:, :1])], axis=1) if cfg.model.stochastic else None
    hold = (lambda x: x) if cfg.rollout_grad else jax.lax.stop_gradient
    if cfg.w_flow > 0:  # the true frames' motion, which every pass's flow should warp its previous frame by
        flat = lambda x: x.reshape((-1,) + x.shape[2:])
        true_flow, flow_conf = (x.reshape(target.shape[:2] + x.shape[1:])
                                for x in block_flow(flat(pix[:, :-1]), flat(target), cfg.flow_radius))
    for k in range(1 + cfg.rollout_passes):
        noise = None
        if cfg.model.stochastic and rng is not None:  # counters 0-2 are the context noise's and the anchor's
            noise = jax.random.normal(jax.random.fold_in(rng, 3 + k), z.shape[:2] + (cfg.model.stochastic,))
        pred = model.apply({"params": params}, z_in, p_in, action, anchor=anchor, time=time, anchor_keep=keep_anchor,
                           target=code_target, noise=noise, method=WorldModel.predict)
        zp = pred["z"][:, :-1]
        pixels, keep = model.apply({"params": params}, zp, prev, pred["flow"][:, :-1], with_keep=True,
                                   method=WorldModel.decode)
        latent = jnp.mean((zp - z_target) ** 2)
        pixel = weighted_mse(pixels, target, focus)
        prop = jnp.mean((pred["proprio"][:, :-1] - proprio[:, 1:]) ** 2)
        succ = _bce(pred["success"][:, :-1], batch["success"][:, 1:])
        outc = _bce(pred["outcome"], jnp.broadcast_to(batch["outcome"][:, None], pred["outcome"].shape))
        prog = _bce(pred["progress"][:, :-1], batch["progress"][:, 1:])
        total = (total + cfg.w_latent * latent + cfg.w_pixel * pixel + cfg.w_proprio * prop
                 + cfg.w_success * (succ + outc) + cfg.w_progress * prog)
        tag = "" if k == 0 else f"_pass{k}"
        parts.update({f"latent{tag}": latent, f"pixel{tag}": pixel, f"proprio{tag}": prop, f"success{tag}": succ,
                      f"outcome{tag}": outc, f"progress{tag}": prog})
        if cfg.model.scene:
            parts[f"scene{tag}"] = jnp.mean((pred["scene"][:, :-1] - scene[:, 1:]) ** 2)
            total = total + cfg.w_scene * parts[f"scene{tag}"]
        if cfg.model.stochastic:
            parts[f"kl{tag}"], balanced = _code_kl(pred, cfg.free_nats)
            total = total + cfg.w_kl * balanced
        if cfg.w_lpips > 0:
            parts[f"lpips{tag}"] = _lpips_loss(lpips_weights, pixels[:, ::4], target[:, ::4])
            total = total + cfg.w_lpips * parts[f"lpips{tag}"]
        if cfg.w_read > 0:
            parts[f"read{tag}"] = read_loss_from(probes, every_fourth(pixels), true_read, read_proprio, read_t,
                                                 read_rows, read_dims(cfg.read_closure))
            total = total + cfg.w_read * parts[f"read{tag}"]
        if k == 0 and cfg.w_contrast > 0:  # the same context under another window's actions
            other = model.apply({"params": params}, z_in, p_in, jnp.roll(action, 1, axis=0), anchor=anchor, time=time,
                                anchor_keep=keep_anchor, target=code_target, noise=noise, method=WorldModel.predict)
            parts["contrast"] = action_contrast(zp, other["z"][:, :-1], z_target)
            total = total + cfg.w_contrast * parts["contrast"]
        if cfg.w_flow > 0:
            parts[f"flow{tag}"] = _flow_loss(pred["flow"][:, :-1], true_flow, flow_conf)
            total = total + cfg.w_flow * parts[f"flow{tag}"]
        if keep is not None:
            parts[f"keep{tag}"] = _keep_loss(keep, target, prev)
            total = total + cfg.w_keep * parts[f"keep{tag}"]
        if cfg.model.refine:
            parts[f"refine{tag}"] = _refine_loss(model, params, pixels, zp, target, k, cfg.rollout_passes,
                                                 jax.random.fold_in(jax.random.PRNGKey(cfg.seed) if rng is None
                                                                    else rng, REFINE_STREAM + k), focus)
            total = total + cfg.w_refine * parts[f"refine{tag}"]
        # the next pass reads this pass's predictions of frames 1..T-1: latents and proprio (with their
        # gradient if rollout_grad, so earlier steps learn what later ones need), and the decoded
        # frames as the previous frames of the decoder (always stop-gradient)
        if cfg.model.reencode and cfg.reencode_passes:  # as imagination reads them: latents of the 8-bit frames
            seen = to_uint8(jax.lax.stop_gradient(pixels))
            z_in = jnp.concatenate([z[:, :1], model.apply({"params": params}, seen, method=WorldModel.encode)], axis=1)
        else:
            z_in = jnp.concatenate([z[:, :1], hold(zp)], axis=1)
        p_in = jnp.concatenate([proprio[:, :1], hold(pred["proprio"][:, :-1])], axis=1)
        prev = jnp.concatenate([pix[:, :1], jax.lax.stop_gradient(pixels[:, :-1])], axis=1)
    parts["loss"] = total
    return total, parts


def _code_kl(pred: dict, free_nats: float):
    """The stochastic code's divergence over predictions 0..T-2 (those with a target): (its mean in nats
    a frame, the balanced loss: 0.8 x KL(sg(posterior) || prior) + 0.2 x KL(posterior || sg(prior)), the
    second counted per frame only above free_nats). The prior always learns: left untrained below the
    free nats, it gave imagination codes the posterior never gave (docs/world-model.md)."""
    q = tuple(pred[k][:, :-1] for k in ("post_mean", "post_logstd"))
    p = tuple(pred[k][:, :-1] for k in ("prior_mean", "prior_logstd"))
    sg = jax.lax.stop_gradient
    to_prior = gaussian_kl(*(sg(x) for x in q), *p)
    to_post = gaussian_kl(*q, *(sg(x) for x in p))
    balanced = 0.8 * to_prior + 0.2 * jnp.maximum(to_post, free_nats)
    return jnp.mean(to_prior), jnp.mean(balanced)


def learning_rate(cfg: TrainConfig):
    """The learning rate by step (an optax schedule). Without cooldown: a linear warmup to cfg.lr,
    then a cosine decay to 5% of it at cfg.steps. With cooldown: warmup-stable-decay, the rate held at
    cfg.lr after the warmup and falling linearly to 0 over the last cfg.cooldown share of cfg.steps."""
    warmup = max(cfg.warmup, 1)
    if not cfg.cooldown:
        return optax.warmup_cosine_decay_schedule(0.0, cfg.lr, warmup, max(cfg.steps, cfg.warmup + 1),
                                                  end_value=cfg.lr * 0.05)
    decay = max(round(cfg.cooldown * cfg.steps), 1)
    stable = max(cfg.steps - decay - warmup, 0)
    return optax.join_schedules(
        [optax.linear_schedule(0.0, cfg.lr, warmup), optax.constant_schedule(cfg.lr),
         optax.linear_schedule(cfg.lr, 0.0, decay)], [warmup, warmup + stable])


def make_optimizer(cfg: TrainConfig):
    """AdamW after clipping the gradient's global norm; with model.refine the frame generator's
    parameters are clipped and updated apart, so that its gradients leave the rest of the model's
    updates as they would be without it."""
    def adamw():
        return optax.chain(optax.clip_by_global_norm(cfg.grad_clip),
                           optax.adamw(learning_rate(cfg), weight_decay=cfg.weight_decay))
    if not cfg.model.refine:
        return adamw()
    return optax.multi_transform({"model": adamw(), "refiner": adamw()}, parameter_groups)


def parameter_groups(params) -> dict:
    """The optimiser's group of each top-level module: "refiner" for the frame generator, else "model"."""
    return {name: "refiner" if name == "refiner" else "model" for name in params}


def initial_state(cfg: TrainConfig, params) -> dict:
    """A run's state at step 0: {"params", "opt", "step"}, and "ema" (a copy of params) where cfg.ema > 0."""
    state = {"params": params, "opt": make_optimizer(cfg).init(params), "step": jnp.zeros((), jnp.int32)}
    if cfg.ema:
        state["ema"] = jax.tree_util.tree_map(jnp.copy, params)
    return state


def ema_update(ema, params, decay: float, step):
    """The moving average after optimiser step `step` (0-based): decay warmed up as min(decay, (1+t)/(10+t))."""
    d = jnp.minimum(decay, (1.0 + step) / (10.0 + step))
    return jax.tree_util.tree_map(lambda e, p: e + (1.0 - d) * (p - e), ema, params)


def kept_params(state: dict):
    """The parameters a run validates and keeps: the moving average where the state has one, else params."""
    return state.get("ema", state["params"])


def train_step(cfg: TrainConfig, state: dict, batch: dict, norm: Norm, lpips_weights=None, probes=None):
    """One optimiser step: state (initial_state's) -> (state, metrics); lpips_weights, probes as loss_fn's."""
    rng = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), state["step"])
    (_, parts), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["params"], batch, norm, cfg, rng,
                                                                 lpips_weights, probes)
    updates, opt = make_optimizer(cfg).update(grads, state["opt"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    rest = {k: v for k, v in grads.items() if k != "refiner"}
    parts["grad_norm"] = optax.tree.norm(rest)
    if "refiner" in grads:
        parts["grad_norm_refiner"] = optax.tree.norm(grads["refiner"])
    new = {"params": params, "opt": opt, "step": state["step"] + 1}
    if "ema" in state:
        new["ema"] = ema_update(state["ema"], params, cfg.ema, state["step"])
    return new, parts


def perceptual_weights(cfg: TrainConfig):
    """The LPIPS network's weights where cfg.w_lpips > 0 (train_step's lpips_weights), else None."""
    return perceptual.params() if cfg.w_lpips > 0 else None


def validation_loss(cfg: TrainConfig, params, batch, norm, lpips_weights=None, probes=None) -> dict:
    """The loss's parts (loss_fn's second output) on a batch, without gradients."""
    return loss_fn(params, batch, norm, cfg, lpips_weights=lpips_weights, probes=probes)[1]


def read_probes(cfg: TrainConfig, cache: TrainingCache, data: Path, policies: dict | None = None):
    """The read loss's probes (wm.probes) for cfg on the dataset `data` (its cache `cache`) where
    cfg.w_read > 0, else None: checkpoints of `policies` ({name: PolicySource}; None: those whose
    rollouts the dataset holds, wm.judge.dataset_policies). Raises ValueError where there are none."""
    if cfg.w_read <= 0:
        return None
    policies = dataset_policies(data) if policies is None else policies
    sources = probe_sources(policies, cache.tasks, cfg.model.size, cfg.read_probes)
    if not sources:
        raise ValueError(f"w_read={cfg.w_read:g} needs rollouts of behaviour-cloning checkpoints in {data} "
                         "(the chain's rollouts stage), to read the frames with; set w_read=0 to train without")
    print(f"read loss: {len(sources)} probes ({', '.join(s.name for s in sources)})")
    return make_probes(sources, cache.tasks, cfg.model.dtype)


jitted_train_step = jax.jit(train_step, static_argnums=(0,), donate_argnums=(1,))
# named, so that the pipeline's timing table names its compile
jitted_validation_loss = jax.jit(validation_loss, static_argnums=(0,))


# ---- devices ---------------------------------------------------------------------------------------

def make_mesh(devices=None):
    """A 1-D mesh ("data") over the given devices (default: every device of every process)."""
    devices = jax.devices() if devices is None else list(devices)
    # Auto axes: XLA propagates the batch sharding (Explicit axes would type every reshape)
    return jax.make_mesh((len(devices),), ("data",), axis_types=(jax.sharding.AxisType.Auto,), devices=devices)


def param_spec(x, n: int, fsdp: bool) -> P:
    """Replicated, or (fsdp) sharded on the largest axis divisible by the device count."""
    if not fsdp or n == 1 or x.ndim == 0:
        return P()
    axes = sorted(range(x.ndim), key=lambda a: -x.shape[a])
    for a in axes:
        if x.shape[a] % n == 0 and x.shape[a] >= n:
            spec = [None] * x.ndim
            spec[a] = "data"
            return P(*spec)
    return P()


def state_shardings(state, mesh, fsdp: bool):
    """NamedShardings of the state's leaves on mesh (a Mesh, or an AbstractMesh to plan without devices)."""
    n = mesh.size
    return jax.tree_util.tree_map(lambda x: NamedSharding(mesh, param_spec(x, n, fsdp)), state)


def init_distributed(coordinator: str | None = None, num_processes: int | None = None,
                     process_id: int | None = None) -> None:
    """Joins this process to a multi-process run (`jax.distributed.initialize`), before any device is
    touched. Arguments left None are read from the cluster (SLURM, Open MPI, Kubernetes) or from
    JAX_COORDINATOR_ADDRESS. CPU devices exchange gradients through gloo (GPUs use NCCL regardless)."""
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator, num_processes, process_id)


def put_batch(batch: dict, mesh) -> dict:
    """Host arrays -> global arrays sharded over the batch axis (each process passes its own rows)."""
    sh = NamedSharding(mesh, P("data"))
    if jax.process_count() == 1:
        return jax.device_put(batch, sh)
    return jax.tree_util.tree_map(lambda x: jax.make_array_from_process_local_data(sh, x), batch)


# ---- the run ---------------------------------------------------------------------------------------

def kept_at(select: str, last: bool, val_loss: float, best_val: float) -> bool:
    """Whether the parameters of a step, validated at val_loss, replace the run's kept ones (best/):
    select "best" keeps the lowest validation loss so far (best_val), "last" the parameters of the
    last step this command trains (`last`: the run's last, or the one a safety stop cuts it at)."""
    return val_loss < best_val if select == "best" else last


class Run:
    """Everything one training run holds: config, data, model state, checkpoints, logs. probe_policies:
    the read loss's checkpoints to choose from (read_probes; None: those the data's rollouts ran)."""

    def __init__(self, cfg: TrainConfig, data: Path, out: Path, probe_policies: dict | None = None):
        # the safety stop counts from here: loading the data, compiling and restoring take a share of
        # the command slot that max_minutes is meant to fit
        self.t_created = time.perf_counter()
        self.cfg, self.data, self.out = cfg, Path(data), Path(out)
        make_output_dir(self.out)
        check_run_config(cfg, data, self.out)
        self.cache = TrainingCache(self.data)
        check_dataset(cfg, self.cache)
        bad = self.cache.non_finite()
        if bad:
            print(f"warning: {len(bad)} episodes hold NaN or inf in proprio or actions and are left out "
                  f"(first: {', '.join(bad[:5])})", file=sys.stderr)
        if cfg.batch % jax.device_count():
            raise ValueError(f"batch {cfg.batch} must be a multiple of the device count {jax.device_count()}")
        # every process draws the same global batches and gathers its own rows of them, so the data
        # order, and the losses, do not depend on how many processes share the work
        part = (jax.process_index(), jax.process_count())
        self.loader = WindowLoader(self.cache, cfg.window, cfg.batch, split="train", seed=cfg.seed, part=part,
                                   first_frames=cfg.model.anchor,
                                   cameras=[cfg.camera], tasks=cfg.train_tasks or None, fraction=cfg.train_fraction,
                                   repeat=_repeat(cfg), first_windows=cfg.first_windows)
        norm_path = self.out / "norm.json"
        if norm_path.exists():
            self.norm = Norm.from_dict(json.loads(norm_path.read_text()))
        else:
            self.norm = compute_norm(self.cache, [int(i) for i in self.loader.distinct])
            write_json_atomic(norm_path, self.norm.to_dict())
        # validated on the tasks it trains on: a held-out task must not choose the kept step
        val_tasks = cfg.train_tasks or None
        self.val = WindowLoader(self.cache, cfg.window, cfg.batch, split="val", seed=1234, cameras=[cfg.camera],
                                part=part, first_frames=cfg.model.anchor, tasks=val_tasks) \
            if self.cache.select("val", tasks=val_tasks) else None
        self.mesh = make_mesh()
        params = init_params(cfg.model, jax.random.PRNGKey(cfg.seed), window=cfg.window)
        # the optimiser's state made by one program, not an eager zeros per parameter shape
        state = jax.jit(functools.partial(initial_state, cfg))(params)
        self.shardings = state_shardings(state, self.mesh, cfg.param_sharding == "fsdp")
        self.state = jax.device_put(state, self.shardings)
        opts = ocp.CheckpointManagerOptions(max_to_keep=1, create=True)
        self.latest = ocp.CheckpointManager(self.out.absolute() / "checkpoints", options=opts)
        self.best = ocp.CheckpointManager(self.out.absolute() / "best", options=opts)
        self.best_val = math.inf
        self._val_batches = None
        lpips_weights, probes = perceptual_weights(cfg), read_probes(cfg, self.cache, self.data, probe_policies)
        # on the devices once, not copied from the host at every step
        probes = None if probes is None else jax.device_put(probes, NamedSharding(self.mesh, P()))
        self._step = lambda state, batch, norm: jitted_train_step(cfg, state, batch, norm, lpips_weights, probes)
        self._loss = lambda params, batch, norm: jitted_validation_loss(cfg, params, batch, norm, lpips_weights,
                                                                        probes)

    # ---- checkpoints ----
    def restore(self) -> int:
        """Loads the latest checkpoint, if any, into this run (state, the training loader's position, the best
        validation loss so far) and returns its step; 0 when there is none."""
        step = self.latest.latest_step()
        if step is None:
            return 0
        abstract = jax.tree_util.tree_map(lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
                                          self.state, self.shardings)
        got = self.latest.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                                                                 loader=ocp.args.JsonRestore()))
        self.state = got["state"]
        self.loader.restore(got["loader"]["train"])
        self.best_val = got["loader"].get("best_val", math.inf)
        if self.best.latest_step() is None and best_from_latest(self.out) == step:
            self.keep(int(step))  # the pack left out the kept parameters, this step's own (wm.carry)
        return int(step)

    def save(self, step: int, best: bool) -> None:
        """Checkpoints the state at step in checkpoints/ with the loader's position and best_val, waiting until
        written; when best, first also keeps the parameters (kept_params) in best/ unless that step is there."""
        meta = {"train": self.loader.state(), "best_val": self.best_val}
        # best before latest: a run killed between the two resumes before this step and, retracing the
        # same steps, finds the same best again, whose checkpoint is then already there (and the same)
        if best:
            self.keep(step, meta)
        self.latest.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(self.state),
                                                       loader=ocp.args.JsonSave(meta)), force=True)
        self.latest.wait_until_finished()

    def keep(self, step: int, meta: dict | None = None) -> None:
        """Keeps the parameters of step (kept_params) in best/ with meta (the loader's position and
        best_val, as save writes them), unless that step is there already."""
        if step in self.best.all_steps():
            return
        meta = meta or {"train": self.loader.state(), "best_val": self.best_val}
        self.best.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave({"params": kept_params(self.state)}),
                                                     loader=ocp.args.JsonSave(meta)), force=True)
        self.best.wait_until_finished()

    def validate(self) -> dict:
        """The validation loss's parts, each averaged over the first val_batches validation batches (the same ones
        every call) and keyed "val_<part>"; {} when the data has no validation split."""
        if self.val is None:
            return {}
        if self._val_batches is None:  # the same batches at every evaluation: gathered once
            self._val_batches = [put_batch(training_batch(self.val.batch_at(0, k), self.cfg), self.mesh)
                                 for k in range(min(self.cfg.val_batches, self.val.batches_per_epoch))]
        parts = [jax.device_get(self._loss(kept_params(self.state), b, self.norm)) for b in self._val_batches]
        return {f"val_{k}": float(np.mean([p[k] for p in parts])) for k in parts[0]}

    # ---- the loop ----
    def train(self, progress: bool = True) -> dict:
        """Trains from the latest checkpoint (or step 0) to cfg.steps, or until max_minutes is spent, logging mean
        losses every log_every steps, validating every eval_every, and checkpointing every ckpt_every and at each
        newly kept step. Writes train_status.json and returns its fields (step, steps, cut_short) merged with the
        last logged metrics; raises TrainingDiverged on a non-finite loss. progress shows a progress bar."""
        cfg = self.cfg
        start = self.restore()
        log = MetricLog(self.out)
        bar = tqdm(total=cfg.steps, initial=start, unit="step", desc="train", disable=not progress)
        t_start = self.t_created
        schedule = learning_rate(cfg)
        t_log, acc, n_acc, waited = time.perf_counter(), None, 0, 0.0
        step = start
        last = {}
        # a run resumed where it paused stays paused: its command is rerun with a later pause_at or none
        while step < cfg.steps and not cfg.pauses_at(start):
            t_wait = time.perf_counter()
            batch = self.next_batch()
            waited += time.perf_counter() - t_wait
            self.state, parts = self._step(self.state, batch, self.norm)
            acc = parts if acc is None else jax.tree_util.tree_map(jnp.add, acc, parts)
            n_acc += 1
            step += 1
            bar.update(1)
            if step % cfg.log_every and step != cfg.steps:
                continue
            means = {k: float(v) / n_acc for k, v in jax.device_get(acc).items()}
            if not all(math.isfinite(v) for v in means.values()):
                bad = sorted(k for k, v in means.items() if not math.isfinite(v))
                raise TrainingDiverged(
                    f"non-finite {', '.join(bad)} between steps {step - n_acc + 1} and {step}; the last good checkpoint "
                    f"(step {self.latest.latest_step()}) in {self.out / 'checkpoints'} is untouched. Lower lr or "
                    f"raise warmup, and rerun.")
            dt = time.perf_counter() - t_log
            # input_wait: the share of the interval the host spent getting batches onto the devices;
            # steps are dispatched asynchronously, so a fed device keeps this near 0
            means.update(step=step, lr=float(schedule(step - 1)), steps_per_s=n_acc / dt,
                         frames_per_s=n_acc * cfg.batch * cfg.window / dt, input_wait=waited / dt)
            acc, n_acc, t_log, waited = None, 0, time.perf_counter(), 0.0
            out_of_time = bool(cfg.max_minutes and (time.perf_counter() - t_start) / 60 >= cfg.max_minutes)
            if jax.process_count() > 1:  # process 0's clock decides, or one process would wait on the others forever
                out_of_time = bool(multihost_utils.broadcast_one_to_all(np.bool_(out_of_time)))
            out_of_time = out_of_time or cfg.pauses_at(step)  # a pause stops as the safety stop does, at a set step
            is_best = False
            # validated on the eval_every grid alone, so that a run a safety stop cuts and a rerun finishes
            # keeps the step an uninterrupted run keeps; cut short, "last" keeps where it stopped
            if step % cfg.eval_every == 0 or step == cfg.steps:
                means.update(self.validate())
                v = means.get("val_loss", means["loss"])
                if not math.isfinite(v):
                    raise TrainingDiverged(f"non-finite validation loss {v} at step {step}; the last good checkpoint "
                                           f"(step {self.latest.latest_step()}) in {self.out / 'checkpoints'} is "
                                           "untouched. Lower lr or raise warmup, and rerun.")
                is_best = kept_at(cfg.select, step == cfg.steps or out_of_time, v, self.best_val)
                self.best_val = min(self.best_val, v)
            elif out_of_time:
                is_best = kept_at(cfg.select, True, math.inf, self.best_val)
            log.write(means)
            bar.set_postfix(loss=f"{means['loss']:.4f}", fps=f"{means['frames_per_s']:.0f}")
            last = means
            if step % cfg.ckpt_every == 0 or step == cfg.steps or out_of_time or is_best:
                self.save(step, is_best)
            if out_of_time:
                break
        bar.close()
        self.loader.close()
        if self.best.latest_step() is None:  # e.g. a run that resumed at its last step
            self.keep(step)
        paused = cfg.pauses_at(step)
        status = {"step": step, "steps": cfg.steps, "cut_short": step < cfg.steps, **({"paused": True} if paused else {})}
        if jax.process_index() == 0:
            write_json_atomic(self.out / "train_status.json", status)
        if paused:
            print(f"paused at step {step} of {cfg.steps} (pause_at={cfg.pause_at}): pack the run for a later lease "
                  f"(python -m wm.carry pack {self.out} DEST) or rerun with a later pause_at or none",
                  file=sys.stderr)
        elif status["cut_short"]:
            print(f"stopped by the safety limit max_minutes={cfg.max_minutes:g} at step {step} of {cfg.steps}: "
                  "the model is marked cut short; rerun the same command to finish it", file=sys.stderr)
        return {**status, **last}

    def next_batch(self) -> dict:
        """The loader's next training batch as the step takes it, placed on this run's devices."""
        cfg = self.cfg
        return put_batch(training_batch(next(self.loader), cfg), self.mesh)

    def warm(self) -> None:
        """Runs the training's programs once each (a step on the first training batch; the validation
        loss), so that JAX's persistent compilation cache holds them for a run of the same
        configuration on data of the same shapes, which then loads instead of compiling. The step's
        new state replaces the old, whose buffers the step donated (on a GPU they are gone)."""
        self.state, parts = self._step(self.state, self.next_batch(), self.norm)
        jax.block_until_ready(parts)
        self.validate()
        self.loader.close()

    def best_params(self):
        """The kept parameters (best/, TrainConfig.select), placed as this run's state is (a run trained by several
        processes is judged and evaluated by one)."""
        params = self.state["params"]
        return restore_params(self.best, self.best.latest_step(), params,
                              jax.tree_util.tree_map(lambda x: x.sharding, params))


class MetricLog:
    """metrics.jsonl, one JSON object per logged step, appended (a resumed run continues the file)."""

    def __init__(self, out: Path):
        self.path = out / "metrics.jsonl"

    def write(self, metrics: dict) -> None:
        if jax.process_index() != 0:  # every process holds the same global figures
            return
        with open(self.path, "a") as f:
            f.write(json.dumps(metrics) + "\n")


def warm_after_training(cfg: TrainConfig, data: Path, norm: Norm) -> None:
    """Runs the programs that a finished run of cfg on `data` runs after its training (the episode
    judge's imaginations and fit, eval.json's figures: main) once each, with parameters of zeros placed
    as the run places its own (Run.best_params), so that JAX's persistent compilation cache holds them
    and the run, finishing beside or after this, loads them. norm: the run's (its norm.json). Writes
    nothing but the cache (the placeholder judge and eval.json go to a scratch directory)."""
    cache = TrainingCache(data)
    check_dataset(cfg, cache)
    shapes = jax.eval_shape(functools.partial(init_params, cfg.model, window=cfg.window), jax.random.PRNGKey(0))
    zeros = jax.tree_util.tree_map(lambda x: np.zeros(x.shape, x.dtype), shapes)  # made on the host, no programs
    params = jax.device_put(zeros, state_shardings(zeros, make_mesh(), cfg.param_sharding == "fsdp"))
    judge = warm_judge(cfg, params, norm, cache, training_episodes(cfg, cache)) if cfg.judge_episodes else None
    with tempfile.TemporaryDirectory(prefix="warm-") as scratch:
        evaluate(cfg, params, norm, cache, Path(scratch), judge)


def check_run_config(cfg: TrainConfig, data: Path, out: Path) -> None:
    """Saves the resolved configuration; refuses to resume a run of another one or of another dataset
    (a safety time limit or a pause aside, which change nothing computed), or a run carried from another
    lease (wm.carry) on data other than the data it trained on there (the same data at another path is
    that run's data)."""
    check_data(out, data)
    adopt_data_path(out, data)
    save_or_check(out / "config.json", as_json({"train": to_dict(cfg), "data": str(Path(data).absolute())}),
                  "a run", defaults=as_json({"train": to_dict(TrainConfig())}),
                  ignore=("train.max_minutes", "train.pause_at"))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=preset_help(PRESETS))
    p.add_argument("--config", default="demo")
    p.add_argument("--data", type=Path, required=True, help="a dataset directory (make data) with its cache")
    p.add_argument("--out", type=Path, help="the run's directory (required unless --warm)")
    p.add_argument("--warm", action="store_true",
                   help="compile the training's programs into JAX's persistent compilation cache (one step and "
                        "the validation loss on --data's first batches, in a scratch directory) and stop")
    p.add_argument("--probe-policies", metavar="SPEC",
                   help="with --warm: the policies (a registry spec, as the dataset's policies=) whose checkpoints "
                        "the read loss probes with, where the data to warm on holds none of their rollouts yet")
    p.add_argument("--distributed", action="store_true",
                   help="one of several processes (several hosts): jax.distributed.initialize(); the cluster "
                        "names the processes unless --coordinator, --num-processes and --process-id do")
    p.add_argument("--coordinator", help="HOST:PORT of process 0 (with --distributed)")
    p.add_argument("--num-processes", type=int, help="how many processes train together (with --distributed)")
    p.add_argument("--process-id", type=int, help="this process's index, 0 .. num-processes - 1 (with --distributed)")
    p.add_argument("--no-eval", action="store_true", help="skip eval.json at the end")
    p.add_argument("overrides", nargs="*", help="dotted key=value overrides, e.g. model.dim=256 batch=32")
    a = p.parse_intermixed_args(argv)  # key=value overrides before or after the options
    try:
        cfg = make_config(a.config, a.overrides)
    except ValueError as e:
        p.error(str(e))
    if (a.coordinator or a.num_processes is not None or a.process_id is not None) and not a.distributed:
        p.error("--coordinator, --num-processes and --process-id go with --distributed")
    if a.probe_policies and not a.warm:
        p.error("--probe-policies goes with --warm (a run probes with its data's rollouts' checkpoints)")
    if a.warm:
        if a.distributed:
            p.error("--warm compiles for this process's devices: leave out --distributed")
        pols = None
        if cfg.w_read > 0:  # loaded once, only where the read loss needs them
            pols = ({s.name: s for s in resolve_policies(a.probe_policies.split(","), world_model=False)}
                    if a.probe_policies else dataset_policies(a.data))
        if cfg.w_read > 0 and not probe_sources(pols, TrainingCache(a.data).tasks, cfg.model.size, cfg.read_probes):
            print(f"warning: no checkpoints to probe with ({a.data} holds none of their rollouts; --probe-policies "
                  "names them): warming without the read loss, whose step the run then compiles itself",
                  file=sys.stderr)
            cfg = dataclasses.replace(cfg, w_read=0.0)
        with tempfile.TemporaryDirectory(prefix="warm-") as scratch:
            Run(cfg, a.data, Path(scratch), pols).warm()
        print(f"compiled the training programs of {a.config} for {jax.devices()[0].device_kind}", file=sys.stderr)
        return 0
    if a.out is None:
        p.error("--out is required (the run's directory)")
    if a.distributed:
        init_distributed(a.coordinator, a.num_processes, a.process_id)
    run = Run(cfg, a.data, a.out)
    summary = run.train(progress=jax.process_index() == 0)
    if jax.process_count() > 1:
        # the judge and eval.json imagine on one process's devices: a rerun of the same command
        # without --distributed restores the finished run, fits the judge and evaluates
        if jax.process_index() == 0:
            print(json.dumps(summary, indent=1))
            print("trained on several processes; fit the judge and write eval.json by rerunning the same "
                  "command as one process, without --distributed", file=sys.stderr)
        return 0
    print(json.dumps(summary, indent=1))
    if summary["cut_short"]:
        return 0  # a run cut short is fitted and evaluated by the rerun that finishes it
    best = run.best_params() if (cfg.judge_episodes or not a.no_eval) else None
    if cfg.judge_episodes and not judges_fit(cfg, a.out):
        print(json.dumps({"judge": fit_judge(cfg, best, run.norm, run.cache, [int(i) for i in run.loader.episodes],
                                             a.out)}, indent=1))
    if not a.no_eval:
        report = evaluate(cfg, best, run.norm, run.cache, a.out, load_judge(a.out))
        print(json.dumps(report["summary"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
