"""The policy zoo: behaviour-cloning policies (`sim_data.policies.bc`) trained from a dataset's scripted
demonstrations in several lineages, with checkpoints saved along training, and a registry.

    python -m sim_data.policies.zoo --config demo --data runs/data/demo --out runs/policies/demo [key=value ...]
    make policies CONFIG=demo DATA=runs/data/demo OUT=runs/policies/demo

A lineage is one training run of one task: an encoder (conv or vit), with or without
proprioception, and its demonstrations (how many, of which skills, successes only or all).
Checkpoints are taken at `checkpoints` steps spaced geometrically up to `steps`, so their quality
runs from poor to good.

Layout of OUT: `<task>/<lineage>/step-000123.msgpack` (parameters), `<task>/<lineage>/lineage.json`
(written when the lineage is complete; a rerun skips complete lineages), `config.json`, and
`policies.json`, the registry: one record per checkpoint {name, task, lineage, step, variant,
val_loss, train_loss, checkpoint, net} (checkpoint relative to OUT). `plan.json`, written before
training, holds the registry the zoo will write, its losses not yet known and its checkpoints not yet
saved: what a rollout needs to compile for the zoo's policies while they train (their names,
networks and parameters' shapes; `sim_data.dataset.generate --warm`).

The validation imitation loss of every checkpoint is measured on one fixed set per task: the
val-split scripted demonstrations of skill 1.0 that succeeded, whatever the lineage was trained on.

`--measure N` then measures every checkpoint's true success in the simulator (the head camera
rendered, as the evaluator does) from N initial states per task that no dataset of the zoo used,
into `OUT/success.json` (per checkpoint: successes, n, rate and its 95% Wilson interval), without a
world model; each task is saved when done and a rerun measures the rest.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from sim_data.config import as_json, preset_config, preset_help, save_or_check
from sim_data.dataset.cache import TrainingCache
from sim_data.parts import add_part_argument, config_and_part, take
from sim_data.policies.bc import (
    PolicyNetConfig,
    init_params,
    predict_chunk,
    save_params,
    stack_params,
)
from sim_data.policies.degrade import KNOBS, degrade_params
from sim_data.policies.registry import (
    PLAN,
    REGISTRY,
    fingerprint,
    group_by_policy,
    heldout_seeds,
    load_registry_sources,
    policy_chunks,
    reset_keys_of,
    stacked_sources,
    used_seeds,
)
from sim_data.sim.engines import default_engine
from sim_data.sim.env import cached_env
from sim_data.sim.render import HEAD_CAMERA, cached_renderers
from sim_data.sim.rollout import record_policies
from sim_data.util import make_output_dir, run_cli, wilson_interval, write_json_atomic


def joins(tasks: tuple, task: str) -> bool:
    """Whether a lineage or family whose `tasks` field is `tasks` takes part in `task` (empty: every task)."""
    return not tasks or task in tasks


@dataclasses.dataclass(frozen=True)
class Lineage:
    """One checkpoint series. encoder: "conv" or "vit"; proprio: the policy sees proprioception;
    demos: demonstrations trained on (0: all that qualify); skills: the scripted skills they come
    from; successes_only: leave out the demonstrations that failed; tasks: the zoo's tasks it is
    trained on (empty: all of them): a task every checkpoint of a lineage solves gives the ranking
    only ties at 1.0, episodes better spent on policies that differ."""

    name: str
    encoder: str = "conv"
    proprio: bool = True
    demos: int = 0
    skills: tuple = (1.0,)
    successes_only: bool = True
    tasks: tuple = ()


@dataclasses.dataclass(frozen=True)
class Family:
    """A counterfactual family (sim_data.policies.degrade): the last checkpoint of lineage `base`, its actions
    degraded by `knob` (noise, delay, grip or drive) at each of `levels`; no training of its own. tasks: the
    zoo's tasks it joins (empty: all of them); a knob a task never exercises (drive where the robot stands)
    would only repeat the base policy in that task's ranking."""

    name: str
    base: str
    knob: str
    levels: tuple = ()
    tasks: tuple = ()


@dataclasses.dataclass(frozen=True)
class ZooConfig:
    """Attributes:
      tasks: tasks with one lineage series each. lineages: the Lineage records.
      conv, vit: the networks of the two encoders. steps: optimiser steps per lineage;
      checkpoints: checkpoints per lineage, at steps spaced geometrically from first_step to steps.
      batch, lr, weight_decay: AdamW. val_batches: validation batches of `batch` samples. seed.
      shift: random-shift augmentation of the training images (DrQ's: each image padded by `shift`
        pixels at its edges and cropped back at a random offset; 0: none).
      families: counterfactual families (Family) registered beside the lineages, so that each task's
        zoo spans the range of true success with policies whose differences are known.
      group: lineages of one network trained together as one batched program, at most this many (0:
        all of them; 1: one at a time, the CPU presets' choice, since a CPU runs the batched
        convolutions slower than one lineage at a time).
      sequential: encoders whose group runs its lineages one after another inside the one program
        (lax.map) rather than side by side (vmap): XLA lowers vmapped convolutions to grouped ones,
        which a GPU runs slower than the same convolutions in turn.
    """

    tasks: tuple = ("mug", "wipe")
    lineages: tuple = ()
    conv: PolicyNetConfig = PolicyNetConfig(encoder="conv")
    vit: PolicyNetConfig = PolicyNetConfig(encoder="vit", width=64, depth=3)
    steps: int = 2000
    checkpoints: int = 8
    first_step: int = 10
    batch: int = 64
    lr: float = 1e-3
    weight_decay: float = 1e-4
    val_batches: int = 8
    seed: int = 0
    shift: int = 0
    families: tuple = ()
    group: int = 1
    sequential: tuple = ()

    def validate(self) -> None:
        """Raises ValueError where a setting is out of range (group, sequential, checkpoints, steps, first_step, a
        lineage's encoder) or the zoo is inconsistent: no task or lineage, repeated lineage names, a lineage's or
        family's tasks outside the zoo's, a family whose base is not a lineage, whose name is a lineage's, whose
        knob or levels are out of range, or which joins tasks its base is not trained on; then validates both
        networks."""
        if self.group < 0:
            raise ValueError(f"group must be >= 0 (0: every lineage of a network together), got {self.group}")
        if not set(self.sequential) <= {"conv", "vit"}:
            raise ValueError(f"sequential names encoders (conv, vit), got {self.sequential}")
        if not self.tasks or not self.lineages:
            raise ValueError("a zoo needs at least one task and one lineage")
        if self.checkpoints < 1 or self.steps < self.checkpoints or self.first_step < 1:
            raise ValueError(f"need 1 <= checkpoints <= steps and first_step >= 1 (got {self.checkpoints}, "
                             f"{self.steps}, {self.first_step})")
        names = [lin.name for lin in self.lineages]
        if len(set(names)) != len(names):
            raise ValueError(f"lineage names repeat: {names}")
        for lin in self.lineages:
            if lin.encoder not in ("conv", "vit"):
                raise ValueError(f"lineage {lin.name}: encoder must be conv or vit, got {lin.encoder!r}")
            if not set(lin.tasks) <= set(self.tasks):
                raise ValueError(f"lineage {lin.name}: tasks {list(lin.tasks)} are not all among the zoo's "
                                 f"{list(self.tasks)}")
        for fam in self.families:
            if fam.base not in names:
                raise ValueError(f"family {fam.name}: base lineage {fam.base!r} is not among {names}")
            if fam.name in names:
                raise ValueError(f"family {fam.name}: the name is a lineage's")
            if fam.knob not in KNOBS or not fam.levels:
                raise ValueError(f"family {fam.name}: knob must be one of {KNOBS} with at least one level")
            for level in fam.levels:
                degrade_params(None, **{fam.knob: level})  # raises on a level out of range
            if not set(fam.tasks) <= set(self.tasks):
                raise ValueError(f"family {fam.name}: tasks {list(fam.tasks)} are not all among the zoo's "
                                 f"{list(self.tasks)}")
            base = next(lin for lin in self.lineages if lin.name == fam.base)
            if not set(fam.tasks or self.tasks) <= set(base.tasks or self.tasks):
                raise ValueError(f"family {fam.name}: joins tasks {list(fam.tasks or self.tasks)} where its base "
                                 f"lineage {fam.base} is trained only on {list(base.tasks)}")
        self.conv.validate()
        self.vit.validate()

    def net(self, lineage: Lineage) -> PolicyNetConfig:
        return self.conv if lineage.encoder == "conv" else self.vit

    def lineage_jobs(self) -> list[tuple[str, Lineage]]:
        """(task, lineage) of every lineage to train, task by task in the order of tasks and lineages."""
        return [(t, lin) for t in self.tasks for lin in self.lineages if joins(lin.tasks, t)]

    def checkpoint_steps(self) -> list[int]:
        steps = np.geomspace(min(self.first_step, self.steps), self.steps, self.checkpoints)
        return sorted({int(round(s)) for s in steps} | {self.steps})  # rounding may merge the first few


# the proprioception ablation (conv_proprio against conv_noproprio) and the encoder A/B (conv_noproprio
# against vit_noproprio): proprioception invites causal confusion, so the A/B is run without it
LINEAGES_MAIN = (
    Lineage("conv_proprio"),
    Lineage("conv_noproprio", proprio=False),
    Lineage("vit_noproprio", encoder="vit", proprio=False),
)

LINEAGES_DEMO = tuple(lin if lin.name == "conv_noproprio" else dataclasses.replace(lin, tasks=("mug",))
                      for lin in LINEAGES_MAIN)

PRESETS = {
    "smoke": ZooConfig(tasks=("mug",), lineages=LINEAGES_MAIN, steps=4, checkpoints=2, first_step=2, batch=8,
                       val_batches=1, group=2, conv=PolicyNetConfig(width=8, hidden=32),
                       vit=PolicyNetConfig(encoder="vit", width=16, depth=1, hidden=32),
                       families=(Family("conv_proprio~grip", "conv_proprio", "grip", (0.0, 1.0)),)),
    # 4 checkpoints a lineage and two families (15 policies on mug, 10 on step_back) leave the evaluation
    # 16 episodes a policy in the demo's time; the families degrade conv_noproprio, the lineage that learns
    # the mug (conv_proprio fails it); the drive family only where the robot drives. On step_back every
    # checkpoint of every lineage succeeds in all 16 episodes (docs/results.md), so only conv_noproprio, the
    # families' base, is trained there. With 3 checkpoints the imitation-loss proxy has 9 points on mug,
    # too few for its interval to be told from the model's
    "demo": ZooConfig(tasks=("mug", "step_back"), lineages=LINEAGES_DEMO, steps=1000, checkpoints=4, first_step=5,
                      batch=32, val_batches=4, conv=PolicyNetConfig(width=16, hidden=128),
                      vit=PolicyNetConfig(encoder="vit", width=32, depth=2, hidden=128),
                      families=(Family("conv_noproprio~noise", "conv_noproprio", "noise", (0.1, 0.2, 0.4)),
                                Family("conv_noproprio~drive", "conv_noproprio", "drive", (0.5, 1.5, 2.0),
                                       tasks=("step_back",)))),
    "full": ZooConfig(tasks=("mug", "wipe", "airfryer"), steps=5000, checkpoints=8, first_step=20, batch=256,
                      val_batches=8, shift=4, group=0, sequential=("conv",),
                      lineages=LINEAGES_MAIN + (Lineage("conv_noproprio_few", proprio=False, demos=24),
                                                Lineage("conv_noproprio_lowskill", proprio=False, skills=(0.5, 0.75),
                                                        successes_only=False)),
                      families=(Family("conv_noproprio~noise", "conv_noproprio", "noise", (0.05, 0.1, 0.2, 0.4)),
                                Family("conv_noproprio~delay", "conv_noproprio", "delay", (2, 4, 8)),
                                Family("conv_noproprio~grip", "conv_noproprio", "grip", (0.2, 0.5)),
                                Family("conv_noproprio~drive", "conv_noproprio", "drive", (0.5, 0.75, 1.5)))),
}


def make_config(preset: str, overrides=()) -> ZooConfig:
    """The named preset of PRESETS with dotted `key=value` overrides applied, validated."""
    return preset_config(PRESETS, preset, overrides)


# ---- data ----------------------------------------------------------------------------------------

def _episodes(cache: TrainingCache, task: str, split: str, skills, successes_only: bool, limit: int) -> list[int]:
    skills = {round(float(s), 4) for s in skills}
    out = [i for i in cache.select(split, tasks=[task])
           if cache.episodes[i]["policy_kind"] == "scripted" and round(float(cache.episodes[i]["skill"]), 4) in skills
           and (cache.episodes[i]["success"] or not successes_only)]
    return out[:limit] if limit else out


def load_samples(cache: TrainingCache, episodes: list[int], chunk: int) -> dict:
    """Every (frame, proprio, time) of the episodes with the next `chunk` actions as targets.

    Returns {"image": (N, S, S, 3) uint8, "proprio": (N, 37), "t": (N,) int32, "target": (N, chunk, 20),
    "mask": (N, chunk) (0 past an episode's last action)}.
    """
    parts = {k: [] for k in ("image", "proprio", "t", "target", "mask")}
    for i in episodes:
        ep = cache.episode(i, cameras=[HEAD_CAMERA])
        n = ep["record"]["length"] - 1  # frames that are followed by an action
        idx = np.arange(n)[:, None] + np.arange(chunk)[None]
        parts["image"].append(ep["frames"][HEAD_CAMERA][:n])
        parts["proprio"].append(ep["proprio"][:n])
        parts["t"].append(np.arange(n, dtype=np.int32))
        parts["target"].append(ep["action"][np.minimum(idx, n - 1)])
        parts["mask"].append((idx < n).astype(np.float32))
    return {k: np.concatenate(v) for k, v in parts.items()}


def demonstration_norm(samples: dict) -> dict:
    """A policy's input and output normalisation from its demonstrations: samples {"proprio": (N, 37),
    "target": (N, chunk, 20)} -> {"proprio_mean", "proprio_std": (37,), "action_mean", "action_std": (20,)},
    over each sample's first target action; the stds floored, so that dimensions (nearly) constant in the
    demonstrations do not amplify small deviations (the world model's normalisation: wm.train.compute_norm)."""
    a = samples["target"][:, 0]
    return {"proprio_mean": samples["proprio"].mean(0), "proprio_std": np.maximum(samples["proprio"].std(0), 0.05),
            "action_mean": a.mean(0), "action_std": np.maximum(a.std(0), 0.02)}


# ---- training -----------------------------------------------------------------------------------

def imitation_loss(cfg: PolicyNetConfig, params, batch: dict):
    """Mean squared error of the predicted chunk against the demonstration, in normalised action units."""
    pred = predict_chunk(cfg, params, batch["image"], batch["proprio"], batch["t"])
    n = params["norm"]
    err = ((pred - batch["target"]) / n["action_std"]) ** 2
    return (err.mean(-1) * batch["mask"]).sum() / jnp.maximum(batch["mask"].sum(), 1.0)


def _step_fn(cfg: PolicyNetConfig, opt, shift: int = 0):
    """One optimiser step of one lineage: (params, opt_state, batch, key) -> (params, opt_state, loss)."""

    def step(params, opt_state, batch, key):
        if shift:  # augmented on the device: a host-side crop would hold up the step loop
            batch = {**batch, "image": random_shift(batch["image"], shift, key)}

        def loss(net):
            return imitation_loss(cfg, {**params, "net": net}, batch)

        value, grads = jax.value_and_grad(loss)(params["net"])
        updates, opt_state = opt.update(grads, opt_state, params["net"])
        return {**params, "net": optax.apply_updates(params["net"], updates)}, opt_state, value

    return step


def _make_group_step(cfg: PolicyNetConfig, opt, shift: int = 0, sequential: bool = False):
    """The step of L lineages of one network as one program: (params, opt_state) stacked (L, ...), the
    samples' pool on the device, idx (L, B) rows of the pool, keys (L, 2) -> the same and the (L,)
    losses. The batches are gathered on the device, so a step moves only indices. sequential: the
    lineages' steps run in turn (lax.map) instead of as one batched step (vmap)."""
    step = _step_fn(cfg, opt, shift)

    def one(params, opt_state, pool, idx, key):
        return step(params, opt_state, {k: v[idx] for k, v in pool.items()}, key)

    def in_turn(params, opt_state, pool, idx, keys):
        return jax.lax.map(lambda a: one(a[0], a[1], pool, a[2], a[3]), (params, opt_state, idx, keys))

    return jax.jit(in_turn if sequential else jax.vmap(one, in_axes=(0, 0, None, 0, 0)))


def _make_group_val_loss(cfg: PolicyNetConfig):
    """(params stacked (L, ...), pool, idx (L, K, B)) -> (L,) mean imitation loss over each lineage's K batches."""

    def one(params, pool, idx):
        return jax.lax.map(lambda i: imitation_loss(cfg, params, {k: v[i] for k, v in pool.items()}), idx).mean()

    return jax.jit(jax.vmap(one, in_axes=(0, None, 0)))


def _batch_rows(n: int, batch: int, rng: np.random.Generator) -> np.ndarray:
    """`batch` sorted rows of n drawn with replacement (sorted: the host reads them in order)."""
    return np.sort(rng.integers(0, n, batch))


def _batches(samples: dict, batch: int, rng: np.random.Generator, count: int):
    n = len(samples["t"])
    for _ in range(count):
        idx = _batch_rows(n, batch, rng)
        yield {k: v[idx] for k, v in samples.items()}


def random_shift(images, shift: int, key):
    """(B, S, S, C) images, each padded by `shift` edge pixels and cropped back at an offset drawn
    uniformly from [0, 2 shift] on each axis (jax.random.randint(key, (B, 2), 0, 2 shift + 1))."""
    b, s, _, c = images.shape
    padded = jnp.pad(images, ((0, 0), (shift, shift), (shift, shift), (0, 0)), mode="edge")
    off = jax.random.randint(key, (b, 2), 0, 2 * shift + 1)
    return jax.vmap(lambda im, o: jax.lax.dynamic_slice(im, (o[0], o[1], 0), (s, s, c)))(padded, off)


def _val_loss(loss, params, val_batches: list) -> float:
    """loss: the jitted imitation loss of the lineage's network (compiled once per lineage)."""
    return float(np.mean([float(loss(params, b)) for b in val_batches]))


@dataclasses.dataclass(frozen=True)
class _Job:
    """One lineage of one task in a batched group: its training episodes and seed."""

    task: str
    lineage: Lineage
    episodes: tuple
    seed: int


def _job(cfg: ZooConfig, cache: TrainingCache, task: str, lineage: Lineage) -> _Job:
    eps = _episodes(cache, task, "train", lineage.skills, lineage.successes_only, lineage.demos)
    if not eps:
        raise ValueError(f"{task}/{lineage.name}: the dataset has no train-split scripted demonstrations of skills "
                         f"{lineage.skills}{' that succeeded' if lineage.successes_only else ''}")
    seed = cfg.seed + 1000 * cfg.tasks.index(task) + [lin.name for lin in cfg.lineages].index(lineage.name)
    return _Job(task, lineage, tuple(eps), seed)


def _record(job, step: int, net: PolicyNetConfig, val_loss: float, train_loss: float) -> dict:
    return {"name": f"{job.task}/{job.lineage.name}/{step}", "task": job.task, "lineage": job.lineage.name,
            "step": step, "variant": {**dataclasses.asdict(job.lineage), "demos_used": len(job.episodes)},
            "val_loss": val_loss, "train_loss": train_loss,
            "checkpoint": str(Path(job.task) / job.lineage.name / f"step-{step:06d}.msgpack"),
            "net": dataclasses.asdict(net)}


def _finish(jobs: list, records: list, out: Path, t0: float) -> list[dict]:
    """Stamps the training time on each job's records and writes its lineage.json (its completion mark)."""
    for job, recs in zip(jobs, records, strict=True):
        for r in recs:
            r["train_s"] = time.perf_counter() - t0
        write_json_atomic(out / job.task / job.lineage.name / "lineage.json", recs)
    return [r for recs in records for r in recs]


def _check_finite(jobs: list, train_loss, step: int) -> None:
    bad = [f"{j.task}/{j.lineage.name}" for j, x in zip(jobs, np.atleast_1d(train_loss), strict=True)
           if not np.isfinite(x)]
    if bad:
        raise FloatingPointError(f"{', '.join(bad)}: the imitation loss is not finite at step {step}; lower lr and rerun")


def train_lineage(cfg: ZooConfig, cache: TrainingCache, job: _Job, out: Path, val: dict,
                  progress: bool = True) -> list[dict]:
    """Trains one lineage on its own, its batches gathered on the host, saving its checkpoints; returns
    their registry records. val: the samples of its task's validation set."""
    net = cfg.net(job.lineage)
    samples = load_samples(cache, list(job.episodes), net.chunk)
    params = init_params(net, jax.random.PRNGKey(job.seed), demonstration_norm(samples), job.lineage.proprio)
    opt = optax.adamw(optax.cosine_decay_schedule(cfg.lr, cfg.steps, alpha=0.05), weight_decay=cfg.weight_decay)
    opt_state = jax.jit(opt.init)(params["net"])  # one program, not an eager zeros per parameter shape
    step_fn = jax.jit(_step_fn(net, opt, cfg.shift))
    shift_key = jax.random.PRNGKey(job.seed + 17)
    val_loss = jax.jit(functools.partial(imitation_loss, net))
    rng = np.random.default_rng(job.seed)
    val_batches = list(_batches(val, cfg.batch, np.random.default_rng(7), cfg.val_batches))
    marks = set(cfg.checkpoint_steps())
    records, losses = [], []
    bar = tqdm(total=cfg.steps, desc=f"{job.task}/{job.lineage.name}", unit="step", disable=not progress, leave=False)
    t0 = time.perf_counter()
    for step, batch in enumerate(_batches(samples, cfg.batch, rng, cfg.steps), start=1):
        params, opt_state, loss = step_fn(params, opt_state, batch, jax.random.fold_in(shift_key, step))
        losses.append(loss)
        bar.update(1)
        if step not in marks:
            continue
        train_loss = float(np.mean(jax.device_get(losses[-20:])))
        _check_finite([job], train_loss, step)
        records.append(_record(job, step, net, _val_loss(val_loss, params, val_batches), train_loss))
        save_params(out / records[-1]["checkpoint"], params)
        bar.set_postfix(loss=f"{train_loss:.3f}", val=f"{records[-1]['val_loss']:.3f}")
    bar.close()
    return _finish([job], [records], out, t0)


def _pool(cache: TrainingCache, episode_sets: list, chunk: int) -> tuple[dict, list[np.ndarray]]:
    """The samples of the union of episode_sets, loaded once, and for each set its rows in the pool,
    in the order load_samples(cache, that set) would give them."""
    union = sorted({i for eps in episode_sets for i in eps})
    lengths = [cache.episodes[i]["length"] - 1 for i in union]
    start = dict(zip(union, np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64), strict=True))
    size = dict(zip(union, lengths, strict=True))
    rows = [np.concatenate([np.arange(start[i], start[i] + size[i]) for i in eps]) for eps in episode_sets]
    return load_samples(cache, union, chunk), rows


def train_group(cfg: ZooConfig, cache: TrainingCache, jobs: list[_Job], out: Path, val_eps: dict,
                progress: bool = True) -> list[dict]:
    """Trains lineages that share one network as one program (vmap over lineages, or lax.map where
    cfg.sequential names the network's encoder), each on its own demonstrations, seed and batches,
    saving every lineage's checkpoints; returns their registry records. val_eps: per task, the
    episodes of its fixed validation set."""
    net = cfg.net(jobs[0].lineage)
    assert all(cfg.net(j.lineage) == net for j in jobs), "a group shares one network"
    pool, rows = _pool(cache, [j.episodes for j in jobs], net.chunk)
    tasks = sorted({j.task for j in jobs})
    val_pool, val_rows = _pool(cache, [val_eps[t] for t in tasks], net.chunk)
    val_idx = {}  # every lineage of a task is scored on the same batches of its task's validation set
    for t, r in zip(tasks, val_rows, strict=True):
        vrng = np.random.default_rng(7)
        val_idx[t] = np.stack([r[_batch_rows(len(r), cfg.batch, vrng)] for _ in range(cfg.val_batches)])
    val_idx = jnp.asarray(np.stack([val_idx[j.task] for j in jobs]))
    norms = [demonstration_norm({k: pool[k][r] for k in ("proprio", "target")}) for r in rows]
    params = stack_params([init_params(net, jax.random.PRNGKey(j.seed), norm, j.lineage.proprio)
                           for j, norm in zip(jobs, norms, strict=True)])
    opt = optax.adamw(optax.cosine_decay_schedule(cfg.lr, cfg.steps, alpha=0.05), weight_decay=cfg.weight_decay)
    opt_state = jax.jit(jax.vmap(opt.init))(params["net"])
    step_fn = _make_group_step(net, opt, cfg.shift, sequential=net.encoder in cfg.sequential)
    val_loss = _make_group_val_loss(net)
    pool, val_pool = jax.device_put(pool), jax.device_put(val_pool)
    shift_keys = jnp.stack([jax.random.PRNGKey(j.seed + 17) for j in jobs])
    fold = jax.jit(jax.vmap(jax.random.fold_in, in_axes=(0, None)))
    rngs = [np.random.default_rng(j.seed) for j in jobs]
    marks = set(cfg.checkpoint_steps())
    records, losses = [[] for _ in jobs], []
    bar = tqdm(total=cfg.steps, desc=f"{net.encoder} x{len(jobs)}", unit="step", disable=not progress, leave=False)
    t0 = time.perf_counter()
    for step in range(1, cfg.steps + 1):
        idx = np.stack([r[_batch_rows(len(r), cfg.batch, g)] for r, g in zip(rows, rngs, strict=True)])
        params, opt_state, loss = step_fn(params, opt_state, pool, jnp.asarray(idx), fold(shift_keys, step))
        losses.append(loss)
        bar.update(1)
        if step not in marks:
            continue
        train_loss = np.mean(np.asarray(jax.device_get(losses[-20:])), axis=0)
        _check_finite(jobs, train_loss, step)
        vals = np.asarray(val_loss(params, val_pool, val_idx))
        host = jax.device_get(params)  # each lineage's slice taken on the host: no program per leaf shape
        for k, j in enumerate(jobs):
            records[k].append(_record(j, step, net, float(vals[k]), float(train_loss[k])))
            save_params(out / records[k][-1]["checkpoint"], jax.tree_util.tree_map(lambda x, k=k: x[k], host))
        bar.set_postfix(loss=f"{train_loss.mean():.3f}", val=f"{vals.mean():.3f}")
    bar.close()
    return _finish(jobs, records, out, t0)


def train_zoo(cfg: ZooConfig, data: Path, out: Path, progress: bool = True,
              part: tuple[int, int] | None = None) -> list[dict] | None:
    """Trains (or completes) every lineage of every task, the lineages of one network together
    (train_group); writes and returns the registry. part: (K, N) trains every N-th (task, lineage)
    from the K-th and returns None, leaving the registry to a run without a part (sim_data.parts:
    one process per GPU)."""
    cfg.validate()
    out = Path(out)
    make_output_dir(out)
    _check_config(cfg, data, out)
    cache = TrainingCache(data)
    if HEAD_CAMERA not in cache.cameras:
        raise ValueError(f"the policies see {HEAD_CAMERA}, which the dataset's cache lacks ({cache.cameras})")
    missing = [t for t in cfg.tasks if t not in cache.tasks]
    if missing:
        raise ValueError(f"tasks {missing} are not in the dataset {data} (it has {cache.tasks})")
    jobs = cfg.lineage_jobs()
    todo = [(t, lin) for _, (t, lin) in take(enumerate(jobs), part)
            if not (out / t / lin.name / "lineage.json").exists()]
    val_eps = {t: _episodes(cache, t, "val", (1.0,), True, 0) or _episodes(cache, t, "train", (1.0,), True, 0)
               for t in cfg.tasks}
    write_json_atomic(out / PLAN, {"data": str(Path(data)), "policies": planned_registry(cfg, cache)})
    for net in dict.fromkeys(cfg.net(lin) for _, lin in todo):
        same = [_job(cfg, cache, t, lin) for t, lin in todo if cfg.net(lin) == net]
        size = cfg.group or len(same)
        for group in (same[i:i + size] for i in range(0, len(same), size)):
            if progress:
                print(f"training {', '.join(f'{j.task}/{j.lineage.name}' for j in group)} "
                      f"({net.encoder} network{', together' if len(group) > 1 else ''})", file=sys.stderr)
            if len(group) == 1:
                val = load_samples(cache, val_eps[group[0].task], net.chunk)
                train_lineage(cfg, cache, group[0], out, val, progress)
            else:
                train_group(cfg, cache, group, out, val_eps, progress)
    if part is not None:
        return None
    registry = [r for t, lin in jobs for r in json.loads((out / t / lin.name / "lineage.json").read_text())]
    registry += family_records(cfg, registry)
    write_json_atomic(out / REGISTRY, {"data": str(Path(data)), "policies": registry})
    return registry


def planned_registry(cfg: ZooConfig, cache: TrainingCache) -> list[dict]:
    """The registry train_zoo writes for cfg, before any training: the same records in the same
    order, with no losses (None)."""
    records = [_record(_job(cfg, cache, t, lin), step, cfg.net(lin), None, None)
               for t, lin in cfg.lineage_jobs() for step in cfg.checkpoint_steps()]
    return records + family_records(cfg, records)


def family_records(cfg: ZooConfig, registry: list[dict]) -> list[dict]:
    """The registry records of cfg.families: per task and family, one record per level, sharing the
    checkpoint of the base lineage's last step ("degrade": {knob: level}, "base": its name; no step
    and no imitation loss: the network is the base's, which the loss alone cannot tell apart)."""
    out = []
    for task in cfg.tasks:
        for fam in (f for f in cfg.families if joins(f.tasks, task)):
            base = max((r for r in registry if r["task"] == task and r["lineage"] == fam.base),
                       key=lambda r: r["step"])
            for level in fam.levels:
                out.append({"name": f"{task}/{fam.name}/{level:g}", "task": task, "lineage": fam.name, "step": None,
                            "variant": {**base["variant"], "family": fam.name, "base": base["name"], fam.knob: level},
                            "degrade": {fam.knob: level}, "base": base["name"], "val_loss": None,
                            "train_loss": None, "checkpoint": base["checkpoint"], "net": base["net"]})
    return out


def _check_config(cfg: ZooConfig, data: Path, out: Path) -> None:
    """Saves the zoo's configuration and dataset on first use; refuses to resume a zoo of others."""
    save_or_check(out / "config.json", as_json({"data": str(Path(data)), "config": cfg}), "a zoo",
                  defaults=as_json({"config": ZooConfig()}))


# ---- the registry ---------------------------------------------------------------------------------

def recorded_chunks(task: str, sources, keys, engine: str, seed: int, batch: int):
    """Each chunk of task's sources (those stacked together, at most `batch` episodes a chunk) run in the
    simulator from the initial states of keys (n, 2), the head camera rendered: yields (the chunk's sources,
    their (P, n) bool final successes, the chunk's Recording, padded sources included after them)."""
    n = len(keys)
    for part, padded in (p for g in group_by_policy(sources) for p in policy_chunks(g, n, batch)):
        env = cached_env(task, len(padded) * n, engine, False)
        renderers = cached_renderers(part[0].policy.cfg.size, (HEAD_CAMERA,))
        outcome, rec = record_policies(env, *stacked_sources(padded), keys, jax.random.PRNGKey(seed), renderers)
        yield part, outcome, rec


def measure_success(out: Path, episodes: int, seed: int = 0, engine: str = "", batch: int = 2048,
                    progress: bool = True) -> dict:
    """True success of every checkpoint of the zoo in out over `episodes` held-out initial states per
    task; writes and returns OUT/success.json {"episodes", "engine", "seed", "policies": [{name, task,
    lineage, step, successes, n, rate, ci95}]}."""
    out, engine = Path(out), engine or default_engine()
    sources = load_registry_sources(str(out))
    used = used_seeds(*{s.record["data"] for s in sources if s.record.get("data")})
    rows = []
    for task in sorted({s.task for s in sources}):
        part_path = out / f"success_{task}.json"
        task_sources = [s for s in sources if s.task == task]
        # a task measured before is read back only where it measured these policies as they are now
        alike = {"episodes": episodes, "seed": seed, "engine": engine,
                 "policies": {s.name: fingerprint(s) for s in task_sources}}
        if part_path.exists() and isinstance(done := json.loads(part_path.read_text()), dict) \
                and {k: done.get(k) for k in alike} == alike:
            rows += done["rows"]
            continue
        seeds = heldout_seeds(task, episodes, seed, used)
        keys = reset_keys_of(seeds)
        got = []
        bar = tqdm(total=len(task_sources) * episodes, desc=f"measure {task}", unit="ep", disable=not progress)
        for part, outcome, _ in recorded_chunks(task, task_sources, keys, engine, seed, batch):
            for j, src in enumerate(part):
                n_ok = int(outcome[j].sum())
                got.append({"name": src.name, "task": task, "lineage": src.record["lineage"],
                            "step": src.record["step"], "successes": n_ok, "n": episodes, "rate": n_ok / episodes,
                            "ci95": list(wilson_interval(n_ok, episodes))})
            bar.update(len(part) * episodes)
        bar.close()
        write_json_atomic(part_path, alike | {"rows": got})
        rows += got
    report = {"episodes": episodes, "engine": engine, "seed": seed, "policies": rows}
    write_json_atomic(out / "success.json", report)
    return report


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=preset_help(PRESETS))
    p.add_argument("--config", default="demo", help=f"preset: {', '.join(PRESETS)}")
    p.add_argument("--data", type=Path, required=True, help="a dataset directory with its cache")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--measure", type=int, default=0, metavar="N",
                   help="then measure each checkpoint's true success over N held-out initial states per task")
    p.add_argument("--engine", default="", choices=["", "cpu", "mjx"],
                   help="the engine of --measure (default: mjx where a GPU is, else cpu)")
    add_part_argument(p, "train every N-th lineage", "write the registry")
    p.add_argument("overrides", nargs="*", help="key=value overrides (e.g. steps=500 conv.width=32)")
    a = p.parse_intermixed_args(argv)  # key=value overrides before or after the options
    cfg, part = config_and_part(p, a, make_config)
    t0 = time.perf_counter()
    registry = train_zoo(cfg, a.data, a.out, part=part)
    if registry is None:
        print(f"part {a.part} done; run without --part to write the registry", file=sys.stderr)
        return 0
    print(f"{len(registry)} checkpoints in {time.perf_counter() - t0:.0f} s; registry {a.out / REGISTRY}")
    if a.measure:
        t0 = time.perf_counter()
        report = measure_success(a.out, a.measure, engine=a.engine)
        for r in report["policies"]:
            print(f"{r['name']:40s} {r['rate']:.3f} [{r['ci95'][0]:.3f}, {r['ci95'][1]:.3f}]")
        print(f"measured in {time.perf_counter() - t0:.0f} s: {a.out / 'success.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
