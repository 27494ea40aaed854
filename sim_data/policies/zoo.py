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
val_loss, train_loss, checkpoint, net} (checkpoint relative to OUT).

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

from sim_data.config import preset_config, preset_help
from sim_data.dataset.cache import TrainingCache
from sim_data.dataset.generate import cached_env, cached_renderers
from sim_data.parts import add_part_argument, config_and_part, take
from sim_data.policies.bc import (
    PolicyNetConfig,
    StackedPolicy,
    init_params,
    predict_chunk,
    save_params,
    stack_params,
)
from sim_data.policies.degrade import KNOBS, degrade_params
from sim_data.policies.registry import (
    group_by_policy,
    heldout_seeds,
    load_registry_sources,
    padded_chunks,
    used_seeds,
)
from sim_data.sim.engines import default_engine
from sim_data.sim.rollout import record_policies
from sim_data.util import make_output_dir, run_cli, wilson_interval, write_json_atomic

CAMERA = "head_cam"


@dataclasses.dataclass(frozen=True)
class Lineage:
    """One checkpoint series. encoder: "conv" or "vit"; proprio: the policy sees proprioception;
    demos: demonstrations trained on (0: all that qualify); skills: the scripted skills they come
    from; successes_only: leave out the demonstrations that failed."""

    name: str
    encoder: str = "conv"
    proprio: bool = True
    demos: int = 0
    skills: tuple = (1.0,)
    successes_only: bool = True


@dataclasses.dataclass(frozen=True)
class Family:
    """A counterfactual family (sim_data.policies.degrade): the last checkpoint of lineage `base`, its actions
    degraded by `knob` (noise, delay, grip or drive) at each of `levels`; no training of its own."""

    name: str
    base: str
    knob: str
    levels: tuple = ()


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

    def validate(self) -> None:
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
        for fam in self.families:
            if fam.base not in names:
                raise ValueError(f"family {fam.name}: base lineage {fam.base!r} is not among {names}")
            if fam.name in names:
                raise ValueError(f"family {fam.name}: the name is a lineage's")
            if fam.knob not in KNOBS or not fam.levels:
                raise ValueError(f"family {fam.name}: knob must be one of {KNOBS} with at least one level")
            for level in fam.levels:
                degrade_params(None, **{fam.knob: level})  # raises on a level out of range
        self.conv.validate()
        self.vit.validate()

    def net(self, lineage: Lineage) -> PolicyNetConfig:
        return self.conv if lineage.encoder == "conv" else self.vit

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

PRESETS = {
    "smoke": ZooConfig(tasks=("mug",), lineages=LINEAGES_MAIN, steps=4, checkpoints=2, first_step=2, batch=8,
                       val_batches=1, conv=PolicyNetConfig(width=8, hidden=32),
                       vit=PolicyNetConfig(encoder="vit", width=16, depth=1, hidden=32),
                       families=(Family("conv_proprio~grip", "conv_proprio", "grip", (0.0, 1.0)),)),
    # 4 checkpoints a lineage and two families leave the evaluation 16 episodes a policy in the demo's time;
    # the families degrade conv_noproprio, the lineage that learns the mug (conv_proprio fails it)
    "demo": ZooConfig(tasks=("mug", "step_back"), lineages=LINEAGES_MAIN, steps=1000, checkpoints=4, first_step=5,
                      batch=32, val_batches=4, conv=PolicyNetConfig(width=16, hidden=128),
                      vit=PolicyNetConfig(encoder="vit", width=32, depth=2, hidden=128),
                      families=(Family("conv_noproprio~noise", "conv_noproprio", "noise", (0.1, 0.2, 0.4)),
                                Family("conv_noproprio~drive", "conv_noproprio", "drive", (0.5, 1.5, 2.0)))),
    "full": ZooConfig(tasks=("mug", "wipe", "airfryer"), steps=5000, checkpoints=8, first_step=20, batch=256,
                      val_batches=8, shift=4,
                      lineages=LINEAGES_MAIN + (Lineage("conv_noproprio_few", proprio=False, demos=24),
                                                Lineage("conv_noproprio_lowskill", proprio=False, skills=(0.5, 0.75),
                                                        successes_only=False)),
                      families=(Family("conv_noproprio~noise", "conv_noproprio", "noise", (0.05, 0.1, 0.2, 0.4)),
                                Family("conv_noproprio~delay", "conv_noproprio", "delay", (2, 4, 8)),
                                Family("conv_noproprio~grip", "conv_noproprio", "grip", (0.2, 0.5)),
                                Family("conv_noproprio~drive", "conv_noproprio", "drive", (0.5, 0.75, 1.5)))),
}


def make_config(preset: str, overrides=()) -> ZooConfig:
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
        ep = cache.episode(i, cameras=[CAMERA])
        n = ep["record"]["length"] - 1  # frames that are followed by an action
        idx = np.arange(n)[:, None] + np.arange(chunk)[None]
        parts["image"].append(ep["frames"][CAMERA][:n])
        parts["proprio"].append(ep["proprio"][:n])
        parts["t"].append(np.arange(n, dtype=np.int32))
        parts["target"].append(ep["action"][np.minimum(idx, n - 1)])
        parts["mask"].append((idx < n).astype(np.float32))
    return {k: np.concatenate(v) for k, v in parts.items()}


def compute_norm(samples: dict) -> dict:
    a = samples["target"][:, 0]
    # floors: dimensions (nearly) constant in the demonstrations must not amplify small deviations
    return {"proprio_mean": samples["proprio"].mean(0), "proprio_std": np.maximum(samples["proprio"].std(0), 0.05),
            "action_mean": a.mean(0), "action_std": np.maximum(a.std(0), 0.02)}


# ---- training -----------------------------------------------------------------------------------

def imitation_loss(cfg: PolicyNetConfig, params, batch: dict):
    """Mean squared error of the predicted chunk against the demonstration, in normalised action units."""
    pred = predict_chunk(cfg, params, batch["image"], batch["proprio"], batch["t"])
    n = params["norm"]
    err = ((pred - batch["target"]) / n["action_std"]) ** 2
    return (err.mean(-1) * batch["mask"]).sum() / jnp.maximum(batch["mask"].sum(), 1.0)


def _make_step(cfg: PolicyNetConfig, opt, shift: int = 0):
    @jax.jit
    def step(params, opt_state, batch, key):
        if shift:  # augmented on the device: a host-side crop would hold up the step loop
            batch = {**batch, "image": random_shift(batch["image"], shift, key)}

        def loss(net):
            return imitation_loss(cfg, {**params, "net": net}, batch)

        value, grads = jax.value_and_grad(loss)(params["net"])
        updates, opt_state = opt.update(grads, opt_state, params["net"])
        return {**params, "net": optax.apply_updates(params["net"], updates)}, opt_state, value

    return step


def _batches(samples: dict, batch: int, rng: np.random.Generator, count: int):
    n = len(samples["t"])
    for _ in range(count):
        idx = np.sort(rng.integers(0, n, batch))
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


def train_lineage(cfg: ZooConfig, cache: TrainingCache, task: str, lineage: Lineage, out: Path, val: dict,
                  progress: bool = True) -> list[dict]:
    """Trains one lineage, saving its checkpoints; returns their registry records."""
    net = cfg.net(lineage)
    eps = _episodes(cache, task, "train", lineage.skills, lineage.successes_only, lineage.demos)
    if not eps:
        raise ValueError(f"{task}/{lineage.name}: the dataset has no train-split scripted demonstrations of skills "
                         f"{lineage.skills}{' that succeeded' if lineage.successes_only else ''}")
    samples = load_samples(cache, eps, net.chunk)
    norm = compute_norm(samples)
    seed = cfg.seed + 1000 * cfg.tasks.index(task) + [lin.name for lin in cfg.lineages].index(lineage.name)
    params = init_params(net, jax.random.PRNGKey(seed), norm, lineage.proprio)
    opt = optax.adamw(optax.cosine_decay_schedule(cfg.lr, cfg.steps, alpha=0.05), weight_decay=cfg.weight_decay)
    opt_state = opt.init(params["net"])
    step_fn = _make_step(net, opt, cfg.shift)
    shift_key = jax.random.PRNGKey(seed + 17)
    val_loss = jax.jit(functools.partial(imitation_loss, net))
    rng = np.random.default_rng(seed)
    val_batches = list(_batches(val, cfg.batch, np.random.default_rng(7), cfg.val_batches))
    marks = set(cfg.checkpoint_steps())
    records, losses = [], []
    bar = tqdm(total=cfg.steps, desc=f"{task}/{lineage.name}", unit="step", disable=not progress, leave=False)
    t0 = time.perf_counter()
    for step, batch in enumerate(_batches(samples, cfg.batch, rng, cfg.steps), start=1):
        params, opt_state, loss = step_fn(params, opt_state, batch, jax.random.fold_in(shift_key, step))
        losses.append(loss)
        bar.update(1)
        if step not in marks:
            continue
        train_loss = float(np.mean(jax.device_get(losses[-20:])))
        if not np.isfinite(train_loss):
            raise FloatingPointError(f"{task}/{lineage.name}: the imitation loss is {train_loss} at step {step}; "
                                     f"lower lr and rerun")
        rel = Path(task) / lineage.name / f"step-{step:06d}.msgpack"
        save_params(out / rel, params)
        records.append({
            "name": f"{task}/{lineage.name}/{step}", "task": task, "lineage": lineage.name, "step": step,
            "variant": {**dataclasses.asdict(lineage), "demos_used": len(eps)},
            "val_loss": _val_loss(val_loss, params, val_batches), "train_loss": train_loss,
            "checkpoint": str(rel), "net": dataclasses.asdict(net)})
        bar.set_postfix(loss=f"{train_loss:.3f}", val=f"{records[-1]['val_loss']:.3f}")
    bar.close()
    for r in records:
        r["train_s"] = time.perf_counter() - t0
    write_json_atomic(out / task / lineage.name / "lineage.json", records)
    return records


def train_zoo(cfg: ZooConfig, data: Path, out: Path, progress: bool = True,
              part: tuple[int, int] | None = None) -> list[dict] | None:
    """Trains (or completes) every lineage of every task; writes and returns the registry. part:
    (K, N) trains every N-th (task, lineage) from the K-th and returns None, leaving the registry
    to a run without a part (sim_data.parts: one process per GPU)."""
    cfg.validate()
    out = Path(out)
    make_output_dir(out)
    _check_config(cfg, data, out)
    cache = TrainingCache(data)
    if CAMERA not in cache.cameras:
        raise ValueError(f"the policies see {CAMERA}, which the dataset's cache lacks ({cache.cameras})")
    missing = [t for t in cfg.tasks if t not in cache.tasks]
    if missing:
        raise ValueError(f"tasks {missing} are not in the dataset {data} (it has {cache.tasks})")
    registry = []
    jobs = [(t, lin) for t in cfg.tasks for lin in cfg.lineages]
    for n, (task, lin) in take(enumerate(jobs, start=1), part):
        done = out / task / lin.name / "lineage.json"
        if done.exists():
            registry += json.loads(done.read_text())
            continue
        if progress:
            print(f"[{n}/{len(jobs)}] {task}/{lin.name}", file=sys.stderr)
        val_eps = _episodes(cache, task, "val", (1.0,), True, 0) or _episodes(cache, task, "train", (1.0,), True, 0)
        val = load_samples(cache, val_eps, cfg.net(lin).chunk)
        registry += train_lineage(cfg, cache, task, lin, out, val, progress)
    if part is not None:
        return None
    registry += family_records(cfg, registry)
    write_json_atomic(out / "policies.json", {"data": str(Path(data)), "policies": registry})
    return registry


def family_records(cfg: ZooConfig, registry: list[dict]) -> list[dict]:
    """The registry records of cfg.families: per task and family, one record per level, sharing the
    checkpoint of the base lineage's last step ("degrade": {knob: level}, "base": its name; no step
    and no imitation loss: the network is the base's, which the loss alone cannot tell apart)."""
    out = []
    for task in cfg.tasks:
        for fam in cfg.families:
            base = max((r for r in registry if r["task"] == task and r["lineage"] == fam.base),
                       key=lambda r: r["step"])
            for level in fam.levels:
                out.append({"name": f"{task}/{fam.name}/{level:g}", "task": task, "lineage": fam.name, "step": None,
                            "variant": {**base["variant"], "family": fam.name, "base": base["name"], fam.knob: level},
                            "degrade": {fam.knob: level}, "base": base["name"], "val_loss": None,
                            "train_loss": None, "checkpoint": base["checkpoint"], "net": base["net"]})
    return out


def _check_config(cfg: ZooConfig, data: Path, out: Path) -> None:
    mine = json.loads(json.dumps({"data": str(Path(data)), "config": dataclasses.asdict(cfg)}))
    path = out / "config.json"
    if path.exists():
        theirs = json.loads(path.read_text())
        # a setting added since that zoo was trained counts as its default there
        defaults = json.loads(json.dumps(dataclasses.asdict(ZooConfig())))
        theirs["config"] = {**{k: v for k, v in defaults.items() if k not in theirs.get("config", {})},
                            **theirs.get("config", {})}
        if theirs != mine:
            raise ValueError(f"{out} holds a zoo of another configuration or dataset; use another OUT")
    else:
        write_json_atomic(path, mine)


# ---- the registry ---------------------------------------------------------------------------------

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
        if part_path.exists():
            rows += json.loads(part_path.read_text())
            continue
        task_sources = [s for s in sources if s.task == task]
        seeds = heldout_seeds(task, episodes, seed, used)
        keys = np.stack([np.asarray(jax.random.PRNGKey(x)) for x in seeds])
        got = []
        bar = tqdm(total=len(task_sources) * episodes, desc=f"measure {task}", unit="ep", disable=not progress)
        for k, (part, padded) in enumerate(p for g in group_by_policy(task_sources)
                                           for p in padded_chunks(g, episodes, batch)):
            env = cached_env(task, len(padded) * episodes, engine, False)
            renderers = cached_renderers(part[0].policy.cfg.size, ("head_cam",))
            outcome, _ = record_policies(env, StackedPolicy(part[0].policy), stack_params([s.params for s in padded]),
                                         keys, jax.random.PRNGKey(seed * 7919 + k), renderers)
            for j, src in enumerate(part):
                n_ok = int(outcome[j].sum())
                got.append({"name": src.name, "task": task, "lineage": src.record["lineage"],
                            "step": src.record["step"], "successes": n_ok, "n": episodes, "rate": n_ok / episodes,
                            "ci95": list(wilson_interval(n_ok, episodes))})
            bar.update(len(part) * episodes)
        bar.close()
        write_json_atomic(part_path, got)
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
    a = p.parse_args(argv)
    cfg, part = config_and_part(p, a, make_config)
    t0 = time.perf_counter()
    registry = train_zoo(cfg, a.data, a.out, part=part)
    if registry is None:
        print(f"part {a.part} done; run without --part to write the registry", file=sys.stderr)
        return 0
    print(f"{len(registry)} checkpoints in {time.perf_counter() - t0:.0f} s; registry {a.out / 'policies.json'}")
    if a.measure:
        t0 = time.perf_counter()
        report = measure_success(a.out, a.measure, engine=a.engine)
        for r in report["policies"]:
            print(f"{r['name']:40s} {r['rate']:.3f} [{r['ci95'][0]:.3f}, {r['ci95'][1]:.3f}]")
        print(f"measured in {time.perf_counter() - t0:.0f} s: {a.out / 'success.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
