"""The whole chain in stages: data -> policies -> rollouts -> world model -> evaluation -> report.

    python -m experiments.pipeline demo                 # every stage, on the CPU (make demo)
    python -m experiments.pipeline full --stage data    # one stage (make full STAGE=data)

Each stage resumes what an earlier run of it left and skips what is finished, so a killed run, or
a GPU lease cut into 10-minute commands, continues where it stopped. The stages call the
modules' own entry points with the preset's configurations:

| stage    | module                 | writes            |
|----------|------------------------|-------------------|
| data     | sim_data.dataset.generate      | runs/data/<data>  |
| policies | sim_data.policies.zoo           | runs/policies/<p> |
| rollouts | sim_data.dataset.generate      | runs/data/<data>_<p>_rollouts (the data and the lineage's rollouts) |
| train    | wm.train; experiments.fill | runs/wm/<p> (runs/wm/<p>_seed<k>: an ensemble's members), their bundles in runs/bundles; runs/fill/<p> (the geometric models, where the preset names `geometric` tasks) |
| eval     | experiments.evaluate   | runs/eval/<p>     |
| report   | experiments.report     | runs/eval/<p>/report.html |

The world model learns from the scripted episodes and from the rollouts of some of the zoo's lineages,
failures included (the published work's most useful source: what the evaluated policies do, not
only what demonstrations do); the evaluation reports its statistics over every policy and over the
policies whose rollouts the world model never saw (`metrics.unseen`). A preset that names `geometric`
tasks (the demo: step_back) also fits, in its train stage, the robot's motion and the fill of what a
moved camera newly sees on the data's episodes of those tasks (experiments.fill; the eval stage fits
what is missing, for a model carried from another lease), and its evaluation ranks those tasks'
policies by the geometric read-out (wm.geometric: the policy acting on frames reprojected to its
imagined poses; experiments.evaluate's geometric_ranks).

A preset may train an ensemble (`members`): world models that differ only in their training seed,
whose mean probability ranks the policies (one model's seed moves its ranking more than most design
choices; experiments.ensemble). On a host with several GPUs (`--gpus`, default every visible GPU)
each stage spreads over them, one process per GPU (sim_data.parts): the data generator's chunks, the
zoo's lineages, the ensemble's members (the GPUs shared out among the members of a round, so that
one world model trains data-parallel on every GPU) and the evaluator's batches of policies; with one
GPU or none the stages run in this process, and the train stage trains one member a command (rerun
it for the next), so that each fits a 10-minute command. Without a GPU the evaluation spreads over
the CPU cores (`--cores`), one process pinned to each by `taskset` (not with `keep_features`, whose
imaginations one process keeps): one JAX process leaves a second core idle through much of its
simulating, imagining and judging (the demo's evaluation on 2 cores: 234 s against 337 s;
docs/benchmarks.md). Every stage shares JAX's persistent compilation cache
(`runs/jax_cache`, or JAX_COMPILATION_CACHE_DIR): what one process compiled, a rerun, a later stage
or another GPU's part loads; and XLA's GPU autotuning results (`runs/xla_autotune`), which programs
that share fusions reuse.

A GPU lease of 10-minute commands whose machine goes back when idle runs the chain best as one
background job, each stage with its own overrides (`--set STAGE:key=value`), followed by commands
that wait on it:

    python -m experiments.pipeline full_grip --detach --warm-rollouts --warm-train --warm-eval \
        --set train:steps=4500 --set eval:episodes=50
    python -m experiments.pipeline full_grip --follow 540 --collect $OUT   # again until it prints the report's path

`--detach` starts the same command detached from the terminal (setsid), its output in
runs/logs/<p>/pipeline.log (a background job is bound by no command's limit: its train and eval
stages run without their safety stop, max_minutes=0, unless `--set` or `--minutes` gives one);
`--cache-from DIR` first restores the compilation caches a previous lease packed with `--collect-cache`
(below); `--follow S` waits up to S seconds for it, then prints the stages' timing rows so far and the log's
last lines, and exits 0 once the command has ended well (a whole chain: with its report's path), 1 if
it failed, 3 while it still runs; with `--collect DIR` (on a lent GPU: `--collect $OUT`) the follow
copies the chain's results, report, timing table and the world models' figures and logs, as far as they
are written, into DIR (collect) as it starts, every COLLECT_EVERY_S seconds while it waits and as it
returns, so that a command cut short by its machine's lease still brings back what the chain had
finished, and the one that learns the chain is done brings its whole outcome;
with `--collect-cache` also the compilation caches (runs/jax_cache, runs/xla_autotune), packed into at
most three files of <= 15 MiB (pack_compile_cache) for the next lease on a machine of the same kind, by
every follow but one that returns 4 (whose files are the bundle's), the chain running or not: a machine
taken back mid-chain has left what it compiled so far.
With `--until-bundle` it also returns, with exit status 4, once this chain's train stage has written
the world models' bundles (below) and no earlier `--until-bundle` returned for them: copy
runs/bundles/<p> off the machine in the same command (a follow that returned 4 does not return it
again; deleting runs/logs/<p>/bundle.followed re-arms it), and a lease that ends
before the chain does still leaves a trained model (about 65 MB for `full`, five shards of <= 15 MiB
with the judge and bundle.json) that a later lease evaluates with `--stage eval --set eval:wm=...`
(the bundles, comma-separated) after its own data and policies stages (and rollouts, where the preset's
grasp rules learn from them).

A world model trained longer than one lease holds goes over several (wm.carry): the first lease's
chain trains to `--set train:pause_at=N` of `steps` and ends after its train stage; `python -m wm.carry
pack runs/wm/<p> DEST` packs the run exactly (carry.json and parts of <= 15 MiB: the `full` model's
parameters and optimiser state are 389 MB before compression, its kept parameters 130 MB more where
they are another step's than the latest),
copied off four a call (a call returns 64 MiB); the next lease starts its chain with the same settings
but a later pause_at or none, and `--run-from DIR[,DIR]`, the folders its later calls carry the parts
into (four a call) while the first stages run, and the train stage restores the run (waiting up to
RUN_WAIT_S for every part at its packed size) and trains on, its steps those of an uninterrupted run
on data whose fingerprint matches.

The train stage, once every member is trained, writes each one's portable bundle
(wm.checkpoint.write_bundle: bfloat16 parameters in hashed shards, configuration, normalisation,
judge) into runs/bundles/, unless one of the same training is there, and then lists them in
runs/logs/<p>/bundles.json, which `--detach` clears when it starts a chain.

With `--warm-rollouts` (one GPU), the policies stage starts `sim_data.dataset.generate --warm` beside
the zoo's training: once the zoo has written its plan (the registry it will write), each compiled
rollout of the lineages runs a few steps with stand-in parameters of their checkpoints' shapes, and
the rollouts stage loads those programs. With `--warm-train` (one GPU), the rollouts stage starts
`wm.train --warm` beside its simulation: the world model's training programs compile into the
persistent compilation cache on the data stage's dataset (the same shapes; the read loss's probes,
`w_read`, from the lineages' checkpoints the rollouts run), and the train stage loads them instead of
compiling. With `--warm-eval` (one GPU), the train stage starts
`experiments.evaluate --warm --warm-after-training` beside the training: first the programs the
training runs once trained (its episode judge's imaginations and fit, eval.json), then the
evaluation's simulator and imagination programs on its own batches, a few steps long, each with the
world model's shapes and parameters of zeros, and the train stage's end and the eval stage load
them. Each compiles on the host's cores while the GPU works. With `--set eval:truth_cache=DIR --set
eval:truth_frames=1` beside `--warm-eval`, that warm-up then also simulates every episode of the
evaluation into DIR, frames kept (about 30 GB for `full` at 100 states; the disk is checked first),
and the eval stage reads them instead of simulating: its simulator's share runs beside the training.

Each stage command appends a row to the evaluation directory's `timing.json`: its wall seconds, the
seconds spent compiling (JAX's compile events, experiments.timing; a stage spread over GPUs adds the
most any one of its child processes spent, and lists each child's in `parts`) and the programs
compiled, and what the stage has produced (frames, training steps, episodes). The report shows the
table.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import os
import shlex
import shutil
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import jax

from experiments import evaluate, fill, report
from experiments.ensemble import member_runs
from experiments.timing import (
    compile_snapshot,
    compiled_since,
    part_command,
    read_parts,
    record_timing,
    stage_row,
)
from sim_data.dataset import generate
from sim_data.parts import can_pin_cores, local_cores, local_gpus, run_parallel
from sim_data.policies import zoo
from sim_data.util import (
    CACHE_KEY_LOG_ENV,
    device_name,
    folder_list,
    join_parts,
    key_cache_by_device_kind,
    record_cache_keys,
    run_cli,
    unpacked_tar,
    with_xla_flags,
    write_json_atomic,
    write_parts,
)
from wm import carry, train
from wm import config as wm_config
from wm.checkpoint import BUNDLE, bundle_holds, load_run_config, training_status, write_bundle
from wm.grasp import GRASPED

STAGES = ("data", "policies", "rollouts", "train", "eval", "report")
TIMING = "timing.json"  # in the evaluation's directory: one row per stage command


@dataclasses.dataclass(frozen=True)
class Pipeline:
    """Presets of each stage and where they write (under root)."""

    data: str
    policies: str
    train: str
    eval: str
    root: str = "runs"
    rollouts: str = ""  # a zoo selector (sim_data.policies.registry) whose checkpoints' rollouts join the world model's data
    rollout_episodes: int = 0  # episodes per selected checkpoint
    perturbed: str = ""  # a zoo selector whose checkpoints' perturbed copies' rollouts join too (generate's perturbed)
    perturb_episodes: int = 0  # episodes per perturbed copy
    # world models trained with seeds s..s+members-1 (s: the train seed); their ensemble ranks the policies
    members: int = 1
    data_overrides: tuple = ()
    policies_overrides: tuple = ()
    train_overrides: tuple = ()
    eval_overrides: tuple = ()
    # tasks (comma-separated, of wm.geometric.PREDICTS and wm.grasp.GRASPED) ranked by the geometric read-out,
    # whose motion models, fill and grasp rule the train stage fits (experiments.fill, with geometric_args)
    geometric: str = ""
    geometric_args: tuple = ()

    def dirs(self, name: str) -> dict:
        """Where the stages of a pipeline run called name read and write, under root: {"data", "policies", "wm" (the
        first member's run), "members" (every member's run), "bundles", "eval", "wm_data" (the world model's data:
        the dataset with the rollouts added where there are rollouts, else the dataset), "geometric" (the
        geometric models)}."""
        r = Path(self.root)
        data = r / "data" / self.data
        wm = member_runs(r / "wm", name, self.members)
        return {"data": data, "policies": r / "policies" / name, "wm": wm[0], "members": wm,
                "bundles": [r / "bundles" / m.name for m in wm], "eval": r / "eval" / name,
                "geometric": r / "fill" / name,
                "wm_data": data.with_name(f"{self.data}_{name}_rollouts") if self.rollouts else data}


# the episode judge of the GPU presets learns from every imagined training episode (about 5,000), not
# the recipe's 1024: on the same world model it reads the zoo closer to the truth (docs/world-model.md)
JUDGE_ALL = 8192

PIPELINES = {
    # one world model whose data holds perturbed copies of conv_noproprio (16 episodes a checkpoint and task,
    # each one knob of sim_data.policies.degrade at its own level): over four seeds it reads the zoo and the
    # plug-ins closer than an ensemble of two models without the copies (docs/world-model.md), and fits
    # the 20 minutes on 2 cores that the ensemble's second model took it past
    # step_back's policies are ranked by the geometric read-out, its fill trained 500 steps (2-3 minutes on
    # 2 cores): on the zoo and on 14 plug-ins it reads their success from the robot's imagined motion
    # closer than the world model's judge (Pearson 0.98 against 0.90 and 1.00 against 0.40); mug's by the
    # grasp rule on the actions each policy takes in imagination (wm.grasp, fit on the data with the
    # rollouts: Pearson 0.97 against the judge's 0.93, mean abs error 0.04 against 0.21; docs/world-model.md)
    "demo": Pipeline(data="demo", policies="demo", train="demo", eval="demo", rollouts="conv_noproprio",
                     rollout_episodes=4, perturbed="conv_noproprio", perturb_episodes=16,
                     geometric="step_back,mug", geometric_args=("--steps", "500")),
    # the GPU preset: three tasks (mug, wipe, airfryer), scripted episodes of 4 skills, random play and the
    # controllability programs, the rollouts of three of the zoo's five lineages (the other two, the ViT
    # and the conv network of few demonstrations, and the degraded families stay unseen); the zoo's
    # lineages of 8 checkpoints evaluated from the evaluation preset's held-out initial states by one
    # world model trained about 20 minutes on one H200 (three runs of it in docs/world-model.md; an
    # ensemble of N costs N times the training: --members N; stage times: docs/benchmarks.md)
    "full": Pipeline(data="wm_full", policies="full", train="full", eval="full",
                     train_overrides=("w_success=0.5", "w_progress=0.5", f"judge_episodes={JUDGE_ALL}"),
                     rollouts="conv_noproprio+conv_noproprio_lowskill+conv_proprio", rollout_episodes=32),
    # `full` whose world model also learns from 112 weak-grip episodes a task (sim_data's wm_full_grip:
    # scripted grasps whose hand closes part-way, from the scripted episodes' initial states) and from
    # perturbed copies of conv_noproprio, the lineage that succeeds (32 episodes a checkpoint and task,
    # each one knob of sim_data.policies.degrade at its own level: what actions a little off a good
    # policy's do); the zoo learns from the same demonstrations as full's. Over two seeds the copies
    # raised every within-task figure and most the unseen networks' (docs/world-model.md); the
    # counterfactual families are degraded copies of the same lineage, so they are not unseen in kind: the
    # data holds that lineage's copies at other levels
    "full_grip": Pipeline(data="wm_full_grip", policies="full", train="full", eval="full",
                          train_overrides=("w_success=0.5", "w_progress=0.5", f"judge_episodes={JUDGE_ALL}"),
                          rollouts="conv_noproprio+conv_noproprio_lowskill+conv_proprio", rollout_episodes=32,
                          perturbed="conv_noproprio", perturb_episodes=32),
    # `full_grip` with every task ranked by its grasp rule (the mug lifted, the tray pulled, the cloth drawn
    # over the dirt) on the actions each policy takes in imagination (wm.grasp, fit on the world model's
    # data in the train stage, no fill), as the demo ranks mug
    "full_grasp": Pipeline(data="wm_full_grip", policies="full", train="full", eval="full",
                           train_overrides=("w_success=0.5", "w_progress=0.5", f"judge_episodes={JUDGE_ALL}"),
                           rollouts="conv_noproprio+conv_noproprio_lowskill+conv_proprio", rollout_episodes=32,
                           perturbed="conv_noproprio", perturb_episodes=32, geometric="mug,airfryer,wipe"),
    # `full_grip` with its perturbed copies taken from two other seen lineages, conv_noproprio_lowskill and
    # conv_proprio, instead of conv_noproprio, the counterfactual families' base (each episode one knob of
    # sim_data.policies.degrade at its own level, 32 a checkpoint). Measured over four seeds against
    # full_grip without any copies: MMRV lower in every seed, the unseen networks not helped; not adopted
    # (docs/world-model.md)
    "full_perturb": Pipeline(data="wm_full_grip", policies="full", train="full", eval="full",
                             train_overrides=("w_success=0.5", "w_progress=0.5", f"judge_episodes={JUDGE_ALL}"),
                             rollouts="conv_noproprio+conv_noproprio_lowskill+conv_proprio", rollout_episodes=32,
                             perturbed="conv_noproprio_lowskill+conv_proprio", perturb_episodes=32),
}


def pipeline(name: str, members: int | None = None) -> Pipeline:
    """The preset `name`, with an ensemble of `members` world models in place of the preset's where
    given (a smaller ensemble for a host with fewer GPUs or less time)."""
    p = PIPELINES[name]
    if members is None:
        return p
    if members < 1:
        raise ValueError(f"members={members}: an ensemble needs at least one world model")
    return dataclasses.replace(p, members=members)


def run_stage(name: str, stage: str, extra=(), gpus=(), members: int | None = None,
              warm_train: list | None = None, warm_eval: list | None = None,
              warm_rollouts: list | None = None, cores=()) -> bool:
    """Runs one stage of pipeline `name` (with `members` world models, see pipeline), spread over
    `gpus` (ids) where there are several, and without GPUs its evaluation over `cores` (CPU core ids)
    where there are several; returns False where the stage must run again to finish (an ensemble's
    members left to train). With warm_rollouts (the rollouts stage's overrides), the
    policies stage compiles the rollouts' programs beside it (start_warm_rollouts); with warm_train
    (the train stage's overrides), the rollouts stage compiles the world model's training programs
    beside it (start_warm_train); with warm_eval (the eval stage's overrides), the train stage
    compiles the evaluation's programs beside it (start_warm_eval)."""
    p = pipeline(name, members)
    d = p.dirs(name)
    if {"rollouts": warm_rollouts, "train": warm_train, "eval": warm_eval}.get(stage) is not None:
        # a warmed stage lowers its programs as a bare process would, as its warm-up's process did: a
        # program's text, and so its persistent-cache key, follows what the process traced before it (JAX
        # shares a module's private functions by the jaxprs its caches hold); what an earlier stage
        # compiled is then loaded from the persistent cache
        jax.clear_caches()
    t0 = time.perf_counter()
    compiled = compile_snapshot()
    spread = len(gpus) > 1 and stage != "report"
    on_cores = stage == "eval" and eval_on_cores(p, extra, gpus, cores)
    print(f"== {name}: {stage}" + (f" on {len(gpus)} GPUs" if spread else "") +
          (f" on {len(cores)} cores" if on_cores else ""), file=sys.stderr, flush=True)
    done, parts = True, []  # parts: the timing files of the stage's child processes
    if stage == "data":
        args = ["--config", p.data, "--out", str(d["data"]), *p.data_overrides, *extra]
        parts = _spread("sim_data.dataset.generate", args, gpus, _logs(p, name), "data")
        generate.main(args)
    elif stage == "policies":
        args = ["--config", p.policies, "--data", str(d["data"]), "--out", str(d["policies"]), *p.policies_overrides,
                *extra]
        parts = _spread("sim_data.policies.zoo", args, gpus, _logs(p, name), "policies")
        warming = start_warm_rollouts(p, name, warm_rollouts) \
            if warm_alone(warm_rollouts, gpus, "--warm-rollouts") else None
        with warm_beside(warming, "the rollouts' programs", "the rollouts stage"):
            zoo.main(args)
    elif stage == "rollouts":
        if not p.rollouts:
            print(f"{name} trains its world model on the data alone; skipping" +
                  (" (and --warm-train with it)" if warm_train is not None else ""), file=sys.stderr)
            return True
        args = rollouts_args(p, name, extra)
        parts = _spread("sim_data.dataset.generate", args, gpus, _logs(p, name), "rollouts")
        warming = start_warm_train(p, name, warm_train) if warm_alone(warm_train, gpus, "--warm-train") else None
        with warm_beside(warming, "the training programs", "the train stage"):
            generate.main(args)
    elif stage == "train":
        warming = start_warm_eval(p, name, warm_eval) if warm_alone(warm_eval, gpus, "--warm-eval") else None
        with warm_beside(warming, "the evaluation's programs", "the eval stage"):
            done, parts = train_members(name, extra, gpus, members)
            if done:  # before waiting for the warm-up: the model is what a lease that ends early keeps
                bundle_members(d, _logs(p, name))
            if done and p.geometric:
                fit_geometric(p, d, d["wm"])
    elif stage == "eval":
        # wm=... names the model to evaluate (a bundle carried from another lease): the members need not be here
        given = any(a.startswith("wm=") for a in extra)
        waiting = [] if given else [str(m) for _, m in untrained(d)]
        if waiting:
            raise SystemExit(f"{', '.join(waiting)} not trained yet: run the train stage (make full STAGE=train) "
                             "until it says every member is trained")
        members = [] if given else ["wm=" + ",".join(str(m) for m in d["members"])]
        if p.geometric:  # what the train stage fits, here too for a model carried from another lease
            fit_geometric(p, d, given_model(extra) or d["wm"])
        geometric = [f"geometric={d['geometric']}", "geometric_ranks=1"] if p.geometric else []
        args = ["--config", p.eval, "--out", str(d["eval"]), f"policies={d['policies']}", *members, *geometric,
                *p.eval_overrides, *extra]
        slots, on = (cores, "cpu") if on_cores else (gpus, "gpu")
        parts = _spread("experiments.evaluate", args, slots, _logs(p, name), "eval", on)
        results = d["eval"] / "results.json"
        before = results.stat().st_mtime_ns if results.exists() else None
        evaluate.main(args)
        # max_minutes may have stopped it before its last task: results.json then says so and the rerun finishes
        done = (results.exists() and results.stat().st_mtime_ns != before
                and not json.loads(results.read_text()).get("cut_short"))
    elif stage == "report":
        report.main([str(d["eval"])])
    wall = round(time.perf_counter() - t0, 3)
    compiling = stage_row(compiled_since(compiled), read_parts(parts))
    record_timing(d["eval"] / TIMING, {
        "stage": stage, "done": done, "wall_s": wall, **compiling,
        "gpus": len(gpus) if spread else int(bool(gpus) or jax.default_backend() != "cpu"),
        **({"cores": len(cores)} if on_cores else {}),
        "device": device_name(), **stage_throughput(p, name, stage, wall)})
    print(f"== {name}: {stage} {'done' if done else 'to be continued'} in {wall:.0f} s "
          f"({compiling['compile_s']:.0f} s compiling)", file=sys.stderr, flush=True)
    return done


def stage_throughput(p: Pipeline, name: str, stage: str, wall: float) -> dict:
    """What a stage produced, read from its outputs: a dataset's frames generated by this command
    (those of its parts, where it was spread over GPUs), the generator's rate and the rate over the
    stage's whole wall time (compiling, writing and caching included: end_to_end_frames_per_s), the
    world models' training steps so far, the evaluation's episodes."""
    d = p.dirs(name)
    if stage in ("data", "rollouts"):
        stats = d["data" if stage == "data" else "wm_data"] / "stats.json"
        if not stats.exists():
            return {}
        t = json.loads(stats.read_text())["throughput"]
        row = {k: t.get(k) for k in ("frames_generated", "frames_per_s", "simulate_s", "cache_frames")}
        if t.get("parts"):  # the gathering command generated nothing: the parts did, side by side
            row["frames_generated"] = sum(q["frames_generated"] for q in t["parts"])
            row["simulate_s"] = max(q["simulate_s"] for q in t["parts"])
            slowest = max(q["wall_s"] for q in t["parts"])
            row["frames_per_s"] = row["frames_generated"] / slowest if slowest > 0 else None
        frames = row["frames_generated"] or 0
        row["end_to_end_frames_per_s"] = round(frames / wall, 1) if frames and wall > 0 else None
        return row
    if stage == "train":
        status = [d_ / "train_status.json" for d_ in d["members"]]
        return {"train_steps": [json.loads(s.read_text())["step"] if s.exists() else None for s in status]}
    if stage == "eval" and (d["eval"] / "results.json").exists():
        timing = json.loads((d["eval"] / "results.json").read_text())["timing"]
        return {"episodes": sum(t["episodes"] for t in timing.values())}
    return {}


def eval_on_cores(p: Pipeline, extra, gpus, cores) -> bool:
    """Whether the eval stage spreads over the CPU `cores` (several, no GPU): not where the evaluation
    keeps its features (`keep_features`), whose imaginations one process keeps."""
    if gpus or len(cores) <= 1:
        return False
    overrides = [a for a in (*p.eval_overrides, *extra) if "=" in a and not a.startswith("-")]
    return not evaluate.make_config(p.eval, overrides).keep_features


def untrained(d: dict) -> list[tuple[int, Path]]:
    """(index, run directory) of the members of dirs `d` not yet trained (no eval.json), in order."""
    return [(k, m) for k, m in enumerate(d["members"]) if not (m / "eval.json").exists()]


def member_args(p: Pipeline, k: int, extra=()) -> list[str]:
    """Member k's wm.train overrides: the preset's, then extra, then seed = the seed they give plus k
    (member 0 keeps it), so that an ensemble's members differ whatever seed extra sets."""
    given = [*p.train_overrides, *extra]
    if not k:
        return given
    return [*given, f"seed={wm_config.make_config(p.train, _settings(given)).seed + k}"]


def _settings(args) -> list[str]:
    """The key=value settings among a module's arguments (its options and their values left out)."""
    return [a for a in args if "=" in a and not a.startswith("-")]


def check_trained_members(p: Pipeline, d: dict, extra=()) -> None:
    """Refuses a trained member (eval.json written) whose configuration differs from the one the train
    stage would give it now (`--set train:...` changed after it trained): it would be kept, bundled
    and evaluated as it is, the change silently ignored."""
    for k, m in enumerate(d["members"]):
        if (m / "eval.json").exists():
            train.check_run_config(wm_config.make_config(p.train, _settings(member_args(p, k, extra))),
                                   d["wm_data"], m)


RUN_WAIT_S = 1200.0  # how long a chain's train stage waits for a carried run's parts (--run-from)


def restore_member(name: str, src: str, extra=(), wait_s: float = RUN_WAIT_S) -> None:
    """Restores into the one world model's run directory of pipeline `name` the run packed in src
    (comma-separated folders: wm.carry.restore_run), waiting up to wait_s for its parts; refuses one at
    or past the pause_at that the train stage's overrides (extra) give, which would not train a step."""
    p = pipeline(name, 1)
    member = p.dirs(name)["members"][0]
    meta = carry.restore_run([d for d in src.split(",") if d], member, wait_s=wait_s)
    cfg = wm_config.make_config(p.train, _settings(member_args(p, 0, extra)))
    if cfg.pauses_at(meta["step"]):
        raise ValueError(f"{member} was restored at step {meta['step']}, at or past pause_at={cfg.pause_at}: rerun "
                         "the chain with a later --set train:pause_at=... or none")
    print(f"== {name}: {member} restored at step {meta['step']} of {meta['steps']} from {src}", file=sys.stderr,
          flush=True)


def paused_members(name: str, members: int | None = None) -> list[Path]:
    """The world models' run directories of pipeline `name` whose training stopped at its pause_at."""
    return [m for m in pipeline(name, members).dirs(name)["members"] if training_status(m).get("paused")]


def train_members(name: str, extra=(), gpus=(), members: int | None = None) -> tuple[bool, list[Path]]:
    """Trains the world models of pipeline `name` not yet trained: member k with its seed plus k
    (member_args), as many at a time as there are GPUs, the GPUs shared out among them (one member
    left on two GPUs trains on both, data-parallel; one in this process without several GPUs); a
    trained member whose settings the stage's overrides now change is refused (check_trained_members).
    Returns whether every member is trained, and the timing files of the child processes that trained
    them."""
    p = pipeline(name, members)
    d = p.dirs(name)
    check_trained_members(p, d, extra)
    todo = untrained(d)
    if not todo:
        print(f"{', '.join(str(m) for m in d['members'])}: trained (eval.json exists); skipping", file=sys.stderr)
        return True, []
    todo = todo[: max(len(gpus), 1)]  # a round that fits one command; the stage's next run trains the rest
    commands = [["--config", p.train, "--data", str(d["wm_data"]), "--out", str(m), *member_args(p, k, extra)]
                for k, m in todo]
    parts = []
    if len(gpus) > 1:
        parts = run_parts("wm.train", commands, gpu_groups(gpus, len(todo)), _logs(p, name), "train-member")
    else:
        print(f"member {todo[0][0]} of {p.members}: {todo[0][1]}", file=sys.stderr)
        train.main(commands[0])
    left = [m for _, m in untrained(d)]
    # a member paused at its pause_at is packed for a later lease, not trained on by a rerun here
    rerun = [str(m) for m in left if not training_status(m).get("paused")]
    if rerun:
        print(f"{len(rerun)} of {p.members} world models left to train ({', '.join(rerun)}): run the train stage again",
              file=sys.stderr)
    return not left, parts


def fit_geometric(p: Pipeline, d: dict, model: Path) -> None:
    """Fits the geometric models of p's geometric tasks at the frame size of the world model `model` (a
    run or a bundle; experiments.fill), what d["geometric"] holds already left as it is: the motion
    models and the fill on its data, then the grasp rule of its tasks of wm.grasp.GRASPED on the world
    model's data (the zoo's rollouts among them, whose grasps are the learned policies')."""
    size = load_run_config(model)[0].model.size
    tasks = p.geometric.split(",")
    drawn, grasped = [t for t in tasks if t not in GRASPED], [t for t in tasks if t in GRASPED]
    for data, group in ((d["data"], drawn), (d["wm_data"], grasped)):
        if group:
            fill.main(["--data", str(data), "--tasks", ",".join(group), "--out", str(d["geometric"]), "--size",
                       str(size), *p.geometric_args])


def given_model(extra) -> Path | None:
    """The first world model that an eval stage's last `wm=PATH[,PATH...]` override names (the one the
    evaluation reads), or None without one."""
    given = [a.split("=", 1)[1] for a in extra if a.startswith("wm=")]
    return Path(given[-1].split(",")[0]) if given else None


def bundle_members(d: dict, logs: Path) -> list[Path]:
    """Writes the bundle of each trained member of dirs `d` (Pipeline.dirs) where its bundle is
    missing or holds another training (wm.checkpoint.bundle_holds), then, every bundle current, lists
    them in logs/BUNDLES ({bundle path: its bundle.json's SHA-256}) for `--follow --until-bundle`.
    A bundle that cannot be written is warned of and left out: the evaluation does not need it.
    Returns the bundles written."""
    written, listed = [], {}
    for run, out in zip(d["members"], d["bundles"], strict=True):
        try:
            if not bundle_holds(run, out):
                meta = write_bundle(run, out)
                size = sum(f.stat().st_size for f in out.iterdir()) / 2**20
                print(f"{run}: bundled into {out} ({len(meta['sha256']) + 1} files, {size:.0f} MiB)", file=sys.stderr)
                written.append(out)
            listed[str(out)] = hashlib.sha256((out / BUNDLE).read_bytes()).hexdigest()
        except (OSError, ValueError) as e:
            print(f"warning: {run} not bundled ({e}); the chain goes on without its bundle", file=sys.stderr)
    if len(listed) == len(d["members"]):
        logs.mkdir(parents=True, exist_ok=True)
        write_json_atomic(logs / BUNDLES, listed)
    return written


def warm_alone(overrides: list | None, gpus, flag: str) -> bool:
    """Whether a warm-up asked for (overrides not None) runs: with one GPU or none. On several, each
    GPU's part compiles its own programs, whose shapes a warm-up of the whole would not give."""
    if overrides is not None and len(gpus) > 1:
        print(f"{flag}: several GPUs run their parts apart; the stage compiles for itself", file=sys.stderr)
    return overrides is not None and len(gpus) <= 1


WARM_MEMORY_FRACTION = "0.35"  # of the GPU's memory, for a warm-up beside a stage's own work


def rollouts_args(p: Pipeline, name: str, extra) -> list[str]:
    """sim_data.dataset.generate's arguments for the rollouts stage of pipeline p (named name): the
    data stage's settings, its episodes reused, the lineages' rollouts added; extra: overrides."""
    d = p.dirs(name)
    return ["--config", p.data, "--out", str(d["wm_data"]), "--reuse", str(d["data"]), *p.data_overrides,
            f"policies={d['policies']}#{p.rollouts}", f"policy_episodes={p.rollout_episodes}",
            *([f"perturbed={d['policies']}#{p.perturbed}", f"perturb_episodes={p.perturb_episodes}"]
              if p.perturbed else []), *extra]


def start_warm_rollouts(p: Pipeline, name: str, overrides) -> subprocess.Popen | None:
    """Starts `sim_data.dataset.generate --warm` for the preset's rollouts (the rollouts stage's
    overrides) in a child process beside the zoo's training, its output in the logs: once the zoo has
    written its plan it runs each compiled rollout of the lineages once, a few steps long, with stand-in
    parameters of their checkpoints' shapes, so that the rollouts stage loads the programs. None
    where the preset has no rollouts or they are generated."""
    d = p.dirs(name)
    if not p.rollouts or (d["wm_data"] / "stats.json").exists():
        return None
    log = _logs(p, name) / "warm-rollouts.log"
    argv = [sys.executable, "-m", "sim_data.dataset.generate", "--warm", *rollouts_args(p, name, overrides)]
    print(f"compiling the rollouts' programs beside the zoo's training ({log})", file=sys.stderr, flush=True)
    return _start_warm(argv, log)


def start_warm_train(p: Pipeline, name: str, overrides) -> subprocess.Popen | None:
    """Starts `wm.train --warm` for the preset's world model (the train stage's overrides) on the data
    stage's dataset, in a child process beside this one, its output in the logs: it compiles the
    training's programs into the persistent compilation cache while the rollouts stage simulates, so
    that the train stage loads them (compiling is the host's work; the GPU's share is autotuning): the
    first untrained member's program (its seed is in it). A child of its own memory share on the GPU,
    growing as it needs. None where every member is trained."""
    d = p.dirs(name)
    todo = untrained(d)
    if not todo:
        return None
    log = _logs(p, name) / "warm-train.log"
    # the member the train stage trains first (its seed is part of the step's program)
    # the read loss (w_read) probes with the rollouts' checkpoints, whose episodes the data stage's dataset lacks
    argv = [sys.executable, "-m", "wm.train", "--config", p.train, "--data", str(d["data"]), "--warm",
            *(["--probe-policies", f"{d['policies']}#{p.rollouts}"] if p.rollouts else []),
            *member_args(p, todo[0][0], overrides)]
    print(f"compiling the world model's training programs beside the rollouts ({log})", file=sys.stderr, flush=True)
    return _start_warm(argv, log)


def start_warm_eval(p: Pipeline, name: str, overrides) -> subprocess.Popen | None:
    """Starts `experiments.evaluate --warm` for the preset's evaluation (the eval stage's overrides) of
    the first untrained member, in a child process beside this one, its output in the logs: once the
    member's training has started (its config.json and norm.json written) it runs the programs that
    the training runs once trained (the judge's fit, eval.json), then the evaluation's, once each on
    their shapes, so that the train stage's end and the eval stage load them from the persistent
    compilation cache; the members of an ensemble share one configuration, hence these
    programs, so it runs beside the first member's training only. None where a member is trained."""
    d = p.dirs(name)
    todo = untrained(d)
    if len(todo) < len(d["members"]):
        return None
    log = _logs(p, name) / "warm-eval.log"
    argv = [sys.executable, "-m", "experiments.evaluate", "--config", p.eval, "--warm", "--warm-after-training",
            f"policies={d['policies']}",
            f"wm={todo[0][1]}", *p.eval_overrides, *overrides]
    print(f"compiling the evaluation's programs beside the training ({log})", file=sys.stderr, flush=True)
    return _start_warm(argv, log)


def _start_warm(argv: list[str], log: Path) -> subprocess.Popen:
    """argv in a child process of its own share of the GPU's memory, growing as it needs, its output in log."""
    log.parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false",
           "XLA_PYTHON_CLIENT_MEM_FRACTION": WARM_MEMORY_FRACTION}
    with open(log, "w") as f:
        return subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)


WARM_WAIT_S = 900  # a warm-up still compiling this long after the stage beside it is stopped


@contextlib.contextmanager
def warm_beside(child: subprocess.Popen | None, what: str, later: str):
    """Runs the stage in the with-block beside a warm-up child (None: none): a failed stage stops the
    warm-up, which is then of no use; a finished one waits for it (at most WARM_WAIT_S). A failed or
    stopped warm-up only leaves `later` to compile `what` itself."""
    if child is None:
        yield
        return
    try:
        yield
    except BaseException:
        child.kill()
        raise
    finally:
        t0 = time.perf_counter()
        try:
            rc = child.wait(timeout=WARM_WAIT_S)
        except subprocess.TimeoutExpired:
            child.kill()
            rc = child.wait()
    if rc:
        print(f"warning: compiling {what} ahead failed (exit status {rc}; see its log): {later} compiles them itself",
              file=sys.stderr, flush=True)
    else:
        print(f"{what} are compiled ({time.perf_counter() - t0:.0f} s waited after the stage)", file=sys.stderr,
              flush=True)


def gpu_groups(gpus, n: int) -> list[str]:
    """gpus (ids) shared out among n processes in equal contiguous groups, each a CUDA_VISIBLE_DEVICES
    value ("0,1"); the ids left over by an uneven share go unused, since a data-parallel world model
    splits its batch evenly over its devices."""
    if not 1 <= n <= len(gpus):
        raise ValueError(f"{len(gpus)} GPUs cannot be shared among {n} processes")
    k = len(gpus) // n
    return [",".join(gpus[i * k:(i + 1) * k]) for i in range(n)]


AUTOTUNE_FLAG = "--xla_gpu_per_fusion_autotune_cache_dir"


CACHE_DIRS = ("jax_cache", "xla_autotune")  # what use_compilation_cache fills, by their names in a packed cache
CACHE_PART = "compile_cache.tgz.part"  # pack_compile_cache's files: CACHE_PART + 00, 01, ...
CACHE_PART_BYTES = 15 * 2**20  # a lent GPU brings back files of <= 16 MiB
CACHE_MAX_PARTS = 3  # beside collect's five files: a lent GPU brings back eight
# JAX writes a cache entry in place: one this recent may still be half written while a chain runs
CACHE_SETTLED_S = 10.0
CACHE_KEY_LOG = "cache_keys.log"  # in the chain's logs: its programs' cache keys, part by part


def compile_cache_dirs(root) -> dict[str, Path]:
    """{name in CACHE_DIRS: the directory} of the caches use_compilation_cache(root) turns on: JAX's in
    JAX_COMPILATION_CACHE_DIR where set, else root/jax_cache; XLA's autotuning in root/xla_autotune."""
    jax_dir = os.environ.get("JAX_COMPILATION_CACHE_DIR") or Path(root) / "jax_cache"
    return {"jax_cache": Path(jax_dir), "xla_autotune": Path(root) / "xla_autotune"}


def use_compilation_cache(root: str, key_log: Path | None = None) -> str:
    """Turns on JAX's persistent compilation cache in root/jax_cache (or where JAX_COMPILATION_CACHE_DIR
    says), for this process and the stages' child processes: a stage run again, a later stage and
    the other GPUs' parts load what one process compiled, keyed by the devices' kind so that a cache
    carried from another host of the same GPU serves (sim_data.util.key_cache_by_device_kind). In
    root/xla_autotune XLA keeps its GPU autotuning results per fusion (XLA_FLAGS), which every program
    with the same fusions reuses where the whole program is not cached: most of a fresh train step's
    compile time. With key_log,
    this process and every command it starts log their programs' cache keys there, part by part
    (sim_data.util.record_cache_keys; experiments.cache_keys compares two leases'). Call it before
    JAX's backend starts (XLA reads its flags then). Returns the compilation cache's directory."""
    if key_log is not None:
        os.environ[CACHE_KEY_LOG_ENV] = str(Path(key_log).absolute())
        record_cache_keys(Path(key_log))
    dirs = compile_cache_dirs(Path(root).absolute())
    key_cache_by_device_kind()
    path = os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(dirs["jax_cache"]))
    jax.config.update("jax_compilation_cache_dir", path)
    os.environ["XLA_FLAGS"] = with_xla_flags(os.environ.get("XLA_FLAGS", ""), f"{AUTOTUNE_FLAG}={dirs['xla_autotune']}")
    return path


def cache_files(root: Path, settled_s: float = 0.0) -> list[tuple[str, Path]]:
    """[(name in the packed cache, file)] of the compilation caches of a pipeline rooted at root
    (compile_cache_dirs), sorted; with settled_s > 0 only files last written more than settled_s seconds
    ago (a running chain's entry being written is left for a later packing). XLA's temporary files (in
    `tmp` folders, `tmp_*`: renamed into place once whole) are left out, and so is a file that goes
    while it is listed."""
    now, out = time.time(), []
    for name, d in compile_cache_dirs(root).items():
        for f in d.rglob("*") if d.is_dir() else ():
            rel = f.relative_to(d)
            if any(part == "tmp" or part.startswith("tmp_") for part in rel.parts):
                continue
            try:
                if f.is_file() and now - f.stat().st_mtime > settled_s:
                    out.append((f"{name}/{rel.as_posix()}", f))
            except OSError:
                continue
    return sorted(out)


def pack_compile_cache(root: Path, dest: Path, part_bytes: int = CACHE_PART_BYTES,
                       max_parts: int = CACHE_MAX_PARTS, settled_s: float = 0.0) -> list[Path]:
    """The compilation caches of a pipeline rooted at root (compile_cache_dirs: JAX's compiled programs,
    XLA's autotuning; with settled_s, cache_files' settled ones) as one tar.gz in dest/CACHE_PART00, 01,
    ... of <= part_bytes each (parts of an earlier packing in dest removed first), for a later lease on a
    machine of the same kind (restore_compile_cache), whose stages then load what this one compiled.
    Returns the parts written: none where there is no cache, where it would take more than max_parts, or
    where packing fails (a message says which; no part and no temporary file is left in dest)."""
    files = cache_files(root, settled_s)
    dest.mkdir(parents=True, exist_ok=True)
    for old in dest.glob(CACHE_PART + "*"):
        old.unlink()
    if not files:
        return []
    whole = dest / (CACHE_PART + ".tmp")
    try:
        with tarfile.open(whole, "w:gz") as tar:
            for name, f in files:
                tar.add(f, arcname=name)
        size = whole.stat().st_size
        if -(-size // part_bytes) > max_parts:
            print(f"the compilation cache takes {size / 2**20:.1f} MiB packed, more than {max_parts} files of "
                  f"{part_bytes / 2**20:g} MiB: not packed", file=sys.stderr)
            return []
        return write_parts(whole, dest, CACHE_PART, part_bytes)
    except OSError as e:
        print(f"the compilation cache was not packed: {e}", file=sys.stderr)
        return []
    finally:
        whole.unlink(missing_ok=True)


def restore_compile_cache(src, root: Path) -> int:
    """Extracts pack_compile_cache's parts found in src (a folder, or several: a packing larger than one
    lease call carries beside the wheels travels in two calls, its parts split between two folders) into
    the caches of a pipeline rooted at root (compile_cache_dirs; beside what they hold, entries of the
    same name replaced). Raises FileNotFoundError where src holds no part, and ValueError where the parts
    do not join into one archive (one missing, cut short or given twice) or it holds anything outside
    CACHE_DIRS. Returns the files restored."""
    folders = folder_list(src)
    joined, parts = join_parts(folders, CACHE_PART, "pack one with --follow ... --collect DIR --collect-cache on a "
                                                    "lease's follows")
    broken = f"the cache's {len(parts)} parts do not make one archive: is a part cut short or from another lease?"
    with unpacked_tar(joined, CACHE_DIRS, root, ", ".join(map(str, folders)), broken) as (unpacked, members):
        for name, d in compile_cache_dirs(root).items():
            if (unpacked / name).is_dir():
                shutil.copytree(unpacked / name, d, dirs_exist_ok=True)
    return sum(m.isfile() for m in members)


def _spread(module: str, args, slots, logs: Path, stage: str, on: str = "gpu") -> list[Path]:
    """With several slots (GPU ids, or CPU core ids with on="cpu"), module's main(args --part K/N) on
    each of them (sim_data.parts), in child processes; the caller then runs the module once more
    without a part to gather. Returns the children's timing files (none without several)."""
    if len(slots) <= 1:
        return []
    n = len(slots)
    return run_parts(module, [[*args, "--part", f"{k}/{n}"] for k in range(n)], slots, logs, f"{stage}-part", on)


def run_parts(module: str, argvs: list[list[str]], slots, logs: Path, label: str, on: str = "gpu") -> list[Path]:
    """Runs module's main(argv) for each argv in a child process on one of `slots` (GPU ids, or CPU
    core ids with on="cpu": run_parallel), each writing its wall and compile seconds to
    logs/<label>-<i>.timing.json (experiments.timing); returns those paths. A file left by an earlier
    run is removed first, so that only this run's children count."""
    paths = [logs / f"{label}-{i}.timing.json" for i in range(len(argvs))]
    for path in paths:
        path.unlink(missing_ok=True)
    run_parallel([part_command(path, module, argv) for path, argv in zip(paths, argvs)], slots, logs, label, on)
    return paths


def _logs(p: Pipeline, name: str) -> Path:
    return Path(p.root) / "logs" / name


def stage_overrides(sets: list[str]) -> dict:
    """`--set STAGE:key=value` options as {stage: [key=value, ...]}, in the order given; a malformed
    one, or one naming no stage, raises ValueError naming it."""
    out = {}
    for item in sets:
        stage, sep, kv = item.partition(":")
        if not sep or stage not in STAGES or "=" not in kv or kv.startswith("="):
            raise ValueError(f"--set {item!r}: give STAGE:key=value with STAGE one of {', '.join(STAGES)} "
                             "(e.g. --set train:steps=3500)")
        out.setdefault(stage, []).append(kv)
    return out


def check_settings(name: str, stage: str, per_stage: dict, overrides=(), members: int | None = None) -> None:
    """Builds the configuration of every stage the command runs (`stage`, or all) from the preset's and
    the user's settings (per_stage: --set's; overrides: the one stage's), so that an unknown key or a
    value out of range stops the command before any work: found by its own stage, it would stop the
    chain after the stages before it had run (a training of twenty minutes before an evaluation's
    typo). The report stage takes no settings."""
    p = pipeline(name, members)
    d = p.dirs(name)
    if per_stage.get("report") or (stage == "report" and overrides):
        raise ValueError("the report stage takes no settings: it renders the evaluation's results.json")

    def mine(s):
        return [*per_stage.get(s, []), *(overrides if stage == s else [])]

    for s in STAGES if stage == "all" else (stage,):
        if s == "data":
            generate.make_config(p.data, _settings([*p.data_overrides, *mine("data")]))
        elif s == "policies":
            zoo.make_config(p.policies, _settings([*p.policies_overrides, *mine("policies")]))
        elif s == "rollouts" and p.rollouts:
            generate.make_config(p.data, _settings(rollouts_args(p, name, [*per_stage.get("data", []), *mine("rollouts")])))
        elif s == "train":
            for k in range(p.members):
                wm_config.make_config(p.train, _settings(member_args(p, k, mine("train"))))
        elif s == "eval":
            evaluate.make_config(p.eval, _settings([f"policies={d['policies']}", *p.eval_overrides, *mine("eval")]))


DETACHED_LOG, DETACHED_PID, DETACHED_RC = "pipeline.log", "pipeline.pid", "pipeline.rc"
DETACHED_MEMBERS = "pipeline.members"  # the --members of the detached chain, where given
FOLLOW_POLL_S = 5.0
COLLECT_EVERY_S = 60.0  # a follow's collect interval: a lease's limit may cut its command before it returns
STILL_RUNNING = 3  # --follow's exit status while the detached chain runs on
BUNDLED = 4  # --follow --until-bundle's exit status once the world models' bundles are new
BUNDLES = "bundles.json"  # in the logs: the chain's bundles once all are written (bundle_members)
BUNDLE_SEEN = "bundle.followed"  # in the logs: the hash of the BUNDLES that --until-bundle last returned for


def detach(name: str, argv: list[str], members: int | None = None) -> Path:
    """Starts `python -m experiments.pipeline argv` (without --detach; the train and eval stages
    without their safety stop unless argv sets one) detached from the terminal (setsid), its output
    in runs/logs/<name>/pipeline.log and its exit status, when it ends, in pipeline.rc beside it;
    refuses while an earlier detached run of the preset still runs. Returns the log's path."""
    logs = _logs(PIPELINES[name], name)
    logs.mkdir(parents=True, exist_ok=True)
    pid = _detached_pid(logs)
    if pid is not None:
        raise ValueError(f"a detached {name} chain still runs (pid {pid}): follow it with "
                         f"`python -m experiments.pipeline {name} --follow 540`, or stop it with kill -- -{pid}")
    for f in (DETACHED_LOG, DETACHED_RC, BUNDLES, BUNDLE_SEEN, DETACHED_MEMBERS):
        (logs / f).unlink(missing_ok=True)
    if members is not None:  # a follow without --members collects this ensemble's members
        (logs / DETACHED_MEMBERS).write_text(str(members))
    unbounded = ["--set", "train:max_minutes=0", "--set", "eval:max_minutes=0"]  # before the user's: theirs win
    cmd = " ".join(shlex.quote(a) for a in [sys.executable, "-m", "experiments.pipeline", *unbounded, *argv])
    rc, tmp = shlex.quote(str(logs / DETACHED_RC)), shlex.quote(str(logs / (DETACHED_RC + ".tmp")))
    script = f"PYTHONUNBUFFERED=1 {cmd} > {shlex.quote(str(logs / DETACHED_LOG))} 2>&1; echo $? > {tmp}; mv {tmp} {rc}"
    child = subprocess.Popen(["/bin/sh", "-c", script], start_new_session=True, stdin=subprocess.DEVNULL,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    (logs / DETACHED_PID).write_text(f"{child.pid}\n")
    return logs / DETACHED_LOG


def _without_option(argv: list[str], option: str) -> list[str]:
    """argv without `option VALUE` and `option=VALUE`."""
    out, skip = [], False
    for x in argv:
        if skip:
            skip = False
        elif x == option:
            skip = True
        elif not x.startswith(option + "="):
            out.append(x)
    return out


def _detached_pid(logs: Path) -> int | None:
    """The pid of the preset's detached chain while it runs, else None."""
    path = logs / DETACHED_PID
    if not path.exists() or (logs / DETACHED_RC).exists():
        return None
    pid = int(path.read_text())
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        return pid
    proc = Path(f"/proc/{pid}")  # where /proc exists: an ended child not yet reaped, or a reused pid
    if proc.exists():
        try:
            state = (proc / "stat").read_text().rpartition(")")[2].split()[0]
            command = (proc / "cmdline").read_bytes()  # empty while the process starts
        except FileNotFoundError:  # it ended while read
            return None
        if state == "Z" or (command and DETACHED_RC.encode() not in command):
            return None
    return pid


def new_bundles(logs: Path) -> tuple[str, list[str]] | None:
    """(the hash of logs/BUNDLES, the bundles it lists) where the chain's train stage has listed its
    bundles (bundle_members) and no `--follow --until-bundle` has returned for that list yet, else None."""
    path = logs / BUNDLES
    if not path.exists():
        return None
    text = path.read_bytes()
    digest = hashlib.sha256(text).hexdigest()
    seen = logs / BUNDLE_SEEN
    return None if seen.exists() and seen.read_text().strip() == digest else (digest, list(json.loads(text)))


COLLECTED = ("results.json", "report.md", "report.html", "timing.json")  # the evaluation's files --collect copies
RUN_FILES = ("*.json", "metrics.jsonl")  # of each world model's run: its figures, not its parameters


def collect(p: Pipeline, name: str, dest: Path) -> list[Path]:
    """Copies a chain's outcome into dest: the evaluation's COLLECTED files that exist, and runs.tgz holding
    the logs and each world model's RUN_FILES (eval.json, judge.json, config.json, train_status.json, the
    training curves; no checkpoints or bundles). A few MB in all, in at most five files, so that the command
    which sees the chain end brings its results back from a machine that may go before the next command.
    Returns the files written."""
    d = p.dirs(name)
    dest.mkdir(parents=True, exist_ok=True)
    written = []
    for f in COLLECTED:
        if (d["eval"] / f).exists():
            shutil.copyfile(d["eval"] / f, dest / f)
            written.append(dest / f)
    root = Path(p.root)
    members = [f for run in d["members"] for pattern in RUN_FILES for f in sorted(run.glob(pattern))]
    with tarfile.open(dest / "runs.tgz.tmp", "w:gz") as tar:
        for f in [_logs(p, name), *members]:
            if f.exists():
                tar.add(f, arcname=str(f.relative_to(root)) if f.is_relative_to(root) else f.name)
    os.replace(dest / "runs.tgz.tmp", dest / "runs.tgz")
    return written + [dest / "runs.tgz"]


def collect_running(p: Pipeline, name: str, dest: Path, out) -> list[Path]:
    """collect of a chain that may still write its files: a file replaced while it is read is a line on
    `out` saying so, never an exception (the next collect takes it). Returns the files written."""
    try:
        return collect(p, name, dest)
    except (OSError, tarfile.TarError) as e:
        print(f"== {name}: not collected this time: {e}", file=out)
        return []


def follow(name: str, seconds: float, members: int | None = None, out=sys.stdout, until_bundle: bool = False,
           collect_to: Path | None = None, collect_cache: bool = False) -> int:
    """Waits up to `seconds` for the preset's detached command to end; prints the timing rows written
    so far and the log's last lines. Returns 0 once it ended well (exit status 0), 1 if it failed or
    was killed, STILL_RUNNING while it runs; with until_bundle, BUNDLED as soon as the world models'
    bundles are listed and no earlier call returned for them (new_bundles), whether the chain runs on
    or has ended, so that they are copied off the machine before a lease ends (by the same command:
    the next call does not return for them again). With collect_to (and not until_bundle, whose
    command's files are the bundle's), the chain's outcome as far as it is written is copied there
    (collect) as the call starts, every COLLECT_EVERY_S while it waits and before it returns, so that a
    command killed at a lease's limit leaves what the chain had finished; with collect_cache the
    compilation caches are packed beside it before the call returns (pack_compile_cache: of the entries
    settled, CACHE_SETTLED_S, while the chain runs), for the next lease's --cache-from.
    members: the ensemble's size, by default the detached chain's (its --members, else the preset's)."""
    logs = _logs(PIPELINES[name], name)
    if members is None and (logs / DETACHED_MEMBERS).exists():
        members = int((logs / DETACHED_MEMBERS).read_text())
    p = pipeline(name, members)
    if not (logs / DETACHED_PID).exists():
        raise ValueError(f"no detached {name} chain in {logs}: start one with --detach")
    t0 = time.monotonic()
    ready = None
    collecting = collect_to is not None and not until_bundle
    next_collect = t0
    while _detached_pid(logs) is not None and time.monotonic() - t0 < seconds:
        if until_bundle and (ready := new_bundles(logs)) is not None:
            break
        if collecting and time.monotonic() >= next_collect:
            collect_running(p, name, Path(collect_to), out)
            next_collect = time.monotonic() + COLLECT_EVERY_S
        time.sleep(FOLLOW_POLL_S)
    if until_bundle and ready is None:
        ready = new_bundles(logs)
    timing = p.dirs(name)["eval"] / TIMING
    if timing.exists():
        print(report.md_table(report.timing_table(json.loads(timing.read_text()))), file=out)
    log = logs / DETACHED_LOG
    text = log.read_text(errors="replace") if log.exists() else ""
    lines = [line.split("\r")[-1] for line in text.split("\n")]  # a progress bar's last state
    print("\n".join(lines[-15:]), file=out)
    if ready is not None:
        digest, bundles = ready
        (logs / BUNDLE_SEEN).write_text(digest + "\n")
        print(f"== {name}: the world models' bundles are written: copy {' '.join(bundles)} off the machine now "
              f"(a later lease evaluates them with --stage eval --set eval:wm={','.join(bundles)})", file=out)
        return BUNDLED  # its command's files are the bundle's: the caches come with the next follow
    if _detached_pid(logs) is not None:
        print(f"== {name}: still running after {time.monotonic() - t0:.0f} s of following", file=out)
        if collecting:
            files = collect_running(p, name, Path(collect_to), out)
            print(f"== {name}: collected so far {', '.join(f.name for f in files)} into {collect_to}", file=out)
        if collect_cache:
            pack_cache(p, name, Path(collect_to), out, CACHE_SETTLED_S)
        return STILL_RUNNING
    rc_path = logs / DETACHED_RC
    rc = int(rc_path.read_text()) if rc_path.exists() else None
    written = next((line for line in lines if line.startswith("report: ")), None)
    ended = f"well, {written}" if rc == 0 and written else "well" if rc == 0 else f"with exit status {rc}"
    print(f"== {name}: the detached command ended {ended}", file=out)
    if collect_to is not None:
        files = collect(p, name, Path(collect_to))
        if collect_cache:
            files += pack_cache(p, name, Path(collect_to), out)
        print(f"== {name}: collected {', '.join(f.name for f in files)} into {collect_to}", file=out)
    return 0 if rc == 0 else 1


def pack_cache(p: Pipeline, name: str, dest: Path, out, settled_s: float = 0.0) -> list[Path]:
    """The chain's compilation caches packed into dest (pack_compile_cache, of the files settled_s seconds
    old), with a line on `out` saying what was packed; a failure is that line, never an exception: a
    follow's exit status says how the chain runs. Returns the parts written."""
    try:
        parts = pack_compile_cache(Path(p.root), dest, settled_s=settled_s)
    except OSError as e:
        print(f"== {name}: the compilation caches were not packed: {e}", file=out)
        return []
    if parts:
        print(f"== {name}: the compilation caches packed in {len(parts)} part{'s' * (len(parts) > 1)}, "
              f"{sum(f.stat().st_size for f in parts) / 2**20:.1f} MiB", file=out)
    return parts


def main(argv=None) -> int:
    # no abbreviated options: --detach reruns the command without the exact "--detach"
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                 allow_abbrev=False)
    ap.add_argument("pipeline", choices=sorted(PIPELINES))
    ap.add_argument("--stage", choices=STAGES + ("all",), default="all")
    ap.add_argument("--gpus", type=int, default=None,
                    help="how many of the visible GPUs the stages spread over (default: all of them)")
    ap.add_argument("--cores", type=int, default=None,
                    help="without GPUs, how many CPU processes the eval stage spreads over, one pinned to each "
                         "core (default: one per core this process may use; 1: a single process)")
    ap.add_argument("--members", type=int, default=None,
                    help="world models in the ensemble (default: the preset's); give the same to every stage")
    ap.add_argument("--minutes", type=float, default=0.0,
                    help="a command's time slot (0: none): no stage starts after it, and the train and eval "
                         "stages stop at it by their safety limit (max_minutes), so that the same command, "
                         "rerun, continues the chain (a GPU lease of 10-minute commands)")
    ap.add_argument("--set", action="append", default=[], metavar="STAGE:KEY=VALUE",
                    help="an override for one stage (repeatable), e.g. --set train:steps=3500 --set eval:episodes=50")
    ap.add_argument("--detach", action="store_true",
                    help="run the command as a background job (runs/logs/<p>/pipeline.log) and return at once")
    ap.add_argument("--follow", type=float, default=None, metavar="SECONDS",
                    help="wait up to SECONDS for the detached command; exit 0 once it ended well, 1 if it "
                         "failed, 3 while it runs")
    ap.add_argument("--until-bundle", action="store_true",
                    help="with --follow, also return (exit 4) once the world models' bundles are written, the "
                         "first time a follow sees them")
    ap.add_argument("--collect", type=Path, default=None, metavar="DIR",
                    help="with --follow, copy the chain's results, report, timing and the world models' "
                         "figures and logs, as far as written, into DIR (e.g. $OUT) as it starts, every "
                         f"{COLLECT_EVERY_S:.0f} s and as it returns: a command cut at a lease's limit brings "
                         "back what the chain had finished")
    ap.add_argument("--collect-cache", action="store_true",
                    help="with --collect, also pack the compilation caches (runs/jax_cache, runs/xla_autotune) into "
                         f"DIR/{CACHE_PART}NN (<= 15 MiB each), for the next lease's --cache-from: by every follow "
                         "but one that returns 4, the chain running or ended")
    ap.add_argument("--cache-from", default=None, metavar="DIR[,DIR]",
                    help=f"first restore the compilation caches from DIR/{CACHE_PART}NN (--collect-cache's, from a "
                         "lease on a machine of the same kind; its parts may lie in several folders, comma-separated, "
                         "carried by different calls), so that the stages load what it compiled")
    ap.add_argument("--run-from", default=None, metavar="DIR[,DIR]",
                    help="before the train stage, restore the world model's run that a previous lease paused and "
                         f"packed (wm.carry: carry.json and its parts, in one folder or several), waiting up to "
                         f"{RUN_WAIT_S:.0f} s for them to arrive (carried in by later calls while the first stages "
                         "run); the train stage then resumes it (one member)")
    ap.add_argument("--warm-rollouts", action="store_true",
                    help="with the policies stage (one GPU or none), compile the rollouts' programs beside it (with "
                         "the data and rollouts stages' --set overrides), for the rollouts stage to load")
    ap.add_argument("--warm-train", action="store_true",
                    help="with the rollouts stage (one GPU or none), compile the world model's training programs "
                         "beside it (with the train stage's --set overrides), for the train stage to load")
    ap.add_argument("--warm-eval", action="store_true",
                    help="with the train stage (one GPU or none), compile the evaluation's programs beside it (with "
                         "the eval stage's --set overrides), for the eval stage to load")
    ap.add_argument("overrides", nargs="*", help="key=value overrides passed to the one stage run")
    raw = list(sys.argv[1:] if argv is None else argv)
    a = ap.parse_intermixed_args(raw)
    if a.stage == "all" and a.overrides:
        ap.error("overrides need one --stage (or --set STAGE:key=value)")
    try:
        per_stage = stage_overrides(a.set)
    except ValueError as e:
        ap.error(str(e))
    if a.members is not None and a.members < 1:
        ap.error(f"--members {a.members}: an ensemble needs at least one world model")
    gpus = host_gpus = local_gpus()
    if a.gpus is not None:
        if not 0 <= a.gpus <= len(gpus):
            ap.error(f"--gpus {a.gpus}: this host shows {len(gpus)} GPUs")
        gpus = gpus[: a.gpus]
    # the evaluation spreads over the cores only on a host without GPUs (not with --gpus 0 on one), pinned
    cores = local_cores() if not host_gpus and can_pin_cores() else []
    if a.cores is not None:
        if not cores:
            ap.error("--cores spreads the evaluation on a host without GPUs, with taskset to pin each process")
        if not 1 <= a.cores <= len(cores):
            ap.error(f"--cores {a.cores}: this process may use {len(cores)} cores")
        cores = cores[: a.cores]
    if a.minutes < 0:
        ap.error(f"--minutes {a.minutes}: give a positive time slot, or 0 for none")
    if a.minutes and (a.warm_train or a.warm_eval or a.warm_rollouts):
        # a stage waits for its warm-up (up to WARM_WAIT_S), which a command's slot does not bound
        ap.error("--warm-rollouts, --warm-train and --warm-eval run beside a whole stage: use them in a background "
                 "job (--detach), not in a time slot (--minutes)")
    for option, given in (("--until-bundle", a.until_bundle), ("--collect", a.collect)):
        if given and a.follow is None:
            ap.error(f"{option} is an option of --follow")
    if a.collect_cache and a.collect is None:
        ap.error("--collect-cache is an option of --collect")
    if a.follow is not None:
        if a.detach:
            ap.error("--follow waits on a chain started by --detach: give them in two commands")
        for option, given in (("--cache-from", a.cache_from), ("--run-from", a.run_from)):
            if given is not None:
                ap.error(f"{option} restores for a chain to come: give it to the command that starts it")
        return follow(a.pipeline, a.follow, a.members, until_bundle=a.until_bundle, collect_to=a.collect,
                      collect_cache=a.collect_cache)
    try:
        check_settings(a.pipeline, a.stage, per_stage, a.overrides, a.members)
    except ValueError as e:
        ap.error(str(e))
    if a.run_from is not None and not folder_list(a.run_from):
        ap.error("--run-from names no folder: give the folders the packed run's parts are carried into")
    if a.run_from is not None and (a.stage not in ("all", "train") or pipeline(a.pipeline, a.members).members != 1):
        ap.error("--run-from restores one world model's run for the train stage: give it to a chain or to --stage "
                 "train of a pipeline with one member")
    # before restoring the caches, which a running chain reads and writes
    if a.detach and (running := _detached_pid(_logs(PIPELINES[a.pipeline], a.pipeline))) is not None:
        ap.error(f"a detached {a.pipeline} chain still runs (pid {running}): follow it with "
                 f"`python -m experiments.pipeline {a.pipeline} --follow 540`, or stop it with kill -- -{running}")
    if a.cache_from is not None:
        try:
            restored = restore_compile_cache(a.cache_from, Path(PIPELINES[a.pipeline].root))
        except (FileNotFoundError, ValueError) as e:
            ap.error(str(e))
        print(f"restored {restored} files of the compilation caches from {a.cache_from}")
        raw = _without_option(raw, "--cache-from")
    if a.detach:
        print(f"started in the background; log: {detach(a.pipeline, [x for x in raw if x != '--detach'], a.members)}\n"
              f"follow it with: python -m experiments.pipeline {a.pipeline} --follow 520 --until-bundle --collect DIR")
        return 0
    use_compilation_cache(PIPELINES[a.pipeline].root, key_log=_logs(PIPELINES[a.pipeline], a.pipeline) / CACHE_KEY_LOG)
    t0 = time.perf_counter()
    restored = a.run_from is None
    for stage in STAGES if a.stage == "all" else (a.stage,):
        while True:
            left = a.minutes - (time.perf_counter() - t0) / 60
            if a.minutes and left < 1.0:  # no stage starts, compiles and loads its inputs in less
                print(f"== {a.pipeline}: the {a.minutes:g}-minute slot is used; rerun the same command to continue "
                      f"from the {stage} stage", file=sys.stderr)
                return 0
            if stage == "train" and not restored:
                restore_member(a.pipeline, a.run_from, per_stage.get("train", []) + list(a.overrides),
                               min(RUN_WAIT_S, 60 * left) if a.minutes else RUN_WAIT_S)
                restored = True
            slot = [f"max_minutes={left:.3f}"] if a.minutes and stage in ("train", "eval") else []
            warm = per_stage.get("train", []) if a.warm_train else None
            warm_eval = per_stage.get("eval", []) if a.warm_eval else None
            # the rollouts stage reuses the data stage's episodes, which it checks were made with its settings
            rollouts = [*per_stage.get("data", []), *per_stage.get("rollouts", [])]
            warm_rollouts = rollouts if a.warm_rollouts else None
            mine = rollouts if stage == "rollouts" else per_stage.get(stage, [])
            if run_stage(a.pipeline, stage, [*mine, *a.overrides, *slot], gpus, a.members, warm, warm_eval,
                         warm_rollouts, cores) or a.stage != "all":
                break
            if stage == "train" and (paused := paused_members(a.pipeline, a.members)):
                print(f"== {a.pipeline}: {', '.join(map(str, paused))} paused at its pause_at step: pack it for a "
                      f"later lease (python -m wm.carry pack {paused[0]} DEST), which restores it with --run-from",
                      file=sys.stderr)
                return 0
    if a.stage in ("all", "report"):
        print(f"report: {(pipeline(a.pipeline).dirs(a.pipeline)['eval'] / 'report.html').absolute()} "
              f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
