"""Scaling and transfer sweeps of the world model: `make sweep SWEEP=<name> SIZE=demo|full OUT=<dir>`.

    python -m experiments.sweep data_scaling --size demo --out runs/sweeps/data_scaling_demo

A sweep is a set of world-model trainings that differ in one thing (the swept value `x`), each
repeated over seeds, on datasets it generates or reuses (`make data` presets with overrides, under
`runs/data/`). Every run trains with `wm.train` in its own directory and is judged by the `eval.json`
it writes; the sweep collects the figures of every run into `OUT/results.json` (per run, and per
value: the mean over seeds with a 95% t-interval where there are several) and `OUT/sweep.png`.
Rerunning resumes: finished runs are read back, unfinished ones resume from their checkpoints.

Every piece of work runs in a subprocess pinned to one GPU (CUDA_VISIBLE_DEVICES's, or all of the
host's; one at a time without GPUs): the datasets side by side (the zoo after the base dataset it
trains on), then one chain per run (training, evaluation, measurements, ranking). Several sweeps
named together share the GPUs, in the order named, each into OUT/<sweep>:

    python -m experiments.sweep data_scaling held_out_object transfer --size full --out runs/sweeps/full

Sweeps:
- `data_scaling`: 1/8, 1/4, 1/2 and all of the training episodes (nested subsets).
- `task_scaling`: 1, 2, 4 tasks, always including the evaluated task (mug), evaluated on mug.
- `transfer`: shelf alone (x=1) against shelf and arcade (x=2), evaluated on shelf.
- `airfryer_transfer`: without (x=0: mug only, the air fryer standing in every scene) and with
  (x=1) air-fryer interaction data, evaluated on the air fryer; each run also gets
  `experiments.body_in_place` (does the imagined fryer's body stay in place while the tray slides).
- `held_out_object`: one model, evaluated on test scenes like its training ones (x=0) and on
  scenes with the plant it never saw (x=1).
- `autonomous_rollouts`: scripted demonstrations only (x=0) against the same number of episodes of
  which half are the zoo's `conv_noproprio` rollouts, failures included (x=0.5); both evaluated
  on the mixed dataset's test split.

The sweeps `data_scaling`, `task_scaling` and `autonomous_rollouts` also rank the zoo's mug
policies (the `Size`'s zoo preset, trained on the "base" dataset if missing) with each run's model
against the simulator (`experiments.evaluate` into `<run>/ranking/`): Pearson, Spearman, MMRV,
pairwise accuracy on gaps of 10 points and alignment join the run's figures, and per swept value
(and over the whole sweep) those of the ensemble of its seeds' models (`experiments.ensemble`: their
predicted rates averaged) as `ensemble_<statistic>`. The simulated side of the ranking is cached
(ROOT/cache/truth) and shared by every model ranked from the same states: the first ranking
simulates it while those on other GPUs wait, as the simulator on a GPU is not bit-reproducible and
models must be compared against the same outcomes.

A run whose `eval_data` is another dataset than its training data trains with `--no-eval` and is
evaluated by `python -m wm.quality` on that dataset; a run with `model_of` trains nothing and
evaluates the model of the named run.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from experiments import ensemble
from experiments import stats as S
from experiments.evaluate import WORLD_MODEL_ALONE
from sim_data.parts import local_gpus
from sim_data.util import run_cli, write_json_atomic

# eval.json figures compared across runs: (name in results.json, path in eval.json)
METRICS = (
    ("psnr_h8", ("summary", "psnr_h8")),
    ("gain_over_copy_last_h8_db", ("summary", "gain_over_copy_last_h8_db")),
    ("success_accuracy", ("summary", "success_accuracy")),
    ("success_auroc", ("summary", "success_auroc")),
    ("match_accuracy", ("summary", "match_accuracy")),
    ("delta_psnr_db", ("summary", "delta_psnr_db")),
    ("pooled_gain_h8_db", ("summary", "pooled_gain_over_copy_last_h8_db")),
    ("view_shift_h8_px", ("summary", "view_shift_h8_px")),
    ("success_follows_actions", ("summary", "success_follows_actions")),
    ("action_divergence_h8", ("summary", "action_divergence_h8")),
    # from BODY_FILE, where the sweep measures it (MEASURED)
    ("body_psnr_h8", ("body_in_place", "summary", "body_psnr_h8")),
    ("rest_psnr_h8", ("body_in_place", "summary", "rest_psnr_h8")),
    # from RANK_DIR's results.json (experiments.evaluate), where the sweep ranks the zoo (RANKED)
    ("pearson", ("ranking", "pearson")),
    ("spearman", ("ranking", "spearman")),
    ("mmrv", ("ranking", "mmrv")),
    ("pairwise_acc_gap10", ("ranking", "pairwise_acc_gap10")),
    ("alignment", ("ranking", "alignment")),
)
# the range of the metrics that have one: a t-interval over few seeds is clipped to it
BOUNDS = {**dict.fromkeys(("success_accuracy", "success_auroc", "match_accuracy", "mmrv", "pairwise_acc_gap10",
                           "alignment", "success_follows_actions"), (0.0, 1.0)),
          "pearson": (-1.0, 1.0), "spearman": (-1.0, 1.0), "view_shift_h8_px": (0.0, math.inf),
          "action_divergence_h8": (0.0, math.inf)}
BODY_FILE = "body_in_place.json"  # experiments.body_in_place's figures of a run
MEASURED = {"airfryer_transfer"}  # sweeps whose runs also get the body-in-place measurement
RANK_DIR = "ranking"  # experiments.evaluate's OUT within a run: the zoo's policies ranked by its model
RANKED = {"data_scaling": "mug", "task_scaling": "mug", "autonomous_rollouts": "mug"}  # sweep -> ranked task


@dataclasses.dataclass(frozen=True)
class SweepRun:
    """One training: its swept value x, seed, dataset key and `wm.train` overrides; eval_data: the
    dataset key it is evaluated on (None: its own); model_of: the run whose model it evaluates
    instead of training one."""

    x: float
    seed: int
    data: str
    overrides: tuple
    eval_data: str | None = None
    model_of: str | None = None

    @property
    def name(self) -> str:
        return f"x={self.x:g}/seed={self.seed}"

    @property
    def trains(self) -> bool:
        return self.model_of is None

    @property
    def evaluated_on(self) -> str:
        """The dataset key of its evaluation."""
        return self.eval_data or self.data

    @property
    def model_run(self) -> str:
        """The run whose model it evaluates: its own, or model_of."""
        return self.model_of or self.name

    @property
    def evaluated_apart(self) -> bool:
        return not self.trains or self.evaluated_on != self.data


@dataclasses.dataclass(frozen=True)
class Size:
    """A sweep's scale: the training preset and its optimiser steps per run, seeds, and dataset presets."""

    train: str
    steps: int
    seeds: int
    data: dict  # dataset key -> (generate preset, overrides); "{zoo}" in an override is the zoo's directory
    zoo: str = ""  # the zoo preset trained on the "base" dataset, for policy rollouts and rankings
    eval: str = ""  # the experiments.evaluate preset that ranks the zoo by each run's model


SIZES = {
    "demo": Size(train="demo", steps=300, seeds=1, zoo="demo", eval="demo", data={
        "base": ("demo", ()),
        "tasks4": ("demo", ("tasks=mug,step_back,wipe,shelf", "episodes=6", "play=4")),
        "shelf_arcade": ("demo", ("tasks=shelf,arcade", "episodes=6", "play=4")),
        "airfryer_mug": ("demo", ("tasks=airfryer,mug", "episodes=6", "play=4")),
        "heldout": ("demo", ("heldout=true",)),
        "mixed": ("demo", ("episodes=4", "policies={zoo}#conv_noproprio", "policy_episodes=1")),
    }),
    "full": Size(train="full", steps=1000, seeds=3, zoo="full", eval="full", data={
        "base": ("wm_full", ()),
        "tasks4": ("wm_full", ("tasks=mug,wipe,shelf,arcade", "episodes=300", "play=300", "batch=600")),
        "shelf_arcade": ("wm_full", ("tasks=shelf,arcade", "episodes=300", "play=300", "batch=600")),
        "airfryer_mug": ("wm_full", ("tasks=airfryer,mug", "episodes=300", "play=300", "batch=600")),
        "heldout": ("wm_full", ("heldout=true", "episodes=100", "play=100", "programs=8")),
        # per task, wm_full's skills x 300 scripted episodes + 8 checkpoints x 150 rollouts, so that about half
        # of the task's episodes are the zoo's rollouts (4 skills: 1200 + 1200; the figures in docs/results.md
        # were measured with wm_full's earlier 5 skills: 1500 + 1200 = 2700 task episodes)
        "mixed": ("wm_full", ("episodes=300", "policies={zoo}#conv_noproprio", "policy_episodes=150")),
    }),
}


def data_scaling(size: Size) -> list[SweepRun]:
    """Runs on the base dataset trained on 1/8, 1/4, 1/2 and all of its training episodes (x: the share), per seed."""
    return [SweepRun(f, s, "base", (f"train_fraction={f}", f"seed={s}"))
            for f in (0.125, 0.25, 0.5, 1.0) for s in range(size.seeds)]


TASK_SETS = {1: "mug", 2: "mug,step_back", 4: "mug,step_back,wipe,shelf"}
TASK_SETS_FULL = {1: "mug", 2: "mug,wipe", 4: "mug,wipe,shelf,arcade"}


def _task_sets(size: Size, data: str, sets: dict, evaluated: str) -> list[SweepRun]:
    return [SweepRun(float(x), s, data, (f"train_tasks={tasks}", f"eval_tasks={evaluated}", f"seed={s}"))
            for x, tasks in sets.items() for s in range(size.seeds)]


def task_scaling(size: Size) -> list[SweepRun]:
    """Runs trained on 1, 2 and 4 tasks of the tasks4 dataset, mug always among them (x: the number of tasks),
    each evaluated on mug, per seed."""
    return _task_sets(size, "tasks4", TASK_SETS_FULL if size.train == "full" else TASK_SETS, "mug")


def transfer(size: Size) -> list[SweepRun]:
    """Runs trained on shelf alone (x=1) and on shelf and arcade (x=2), each evaluated on shelf, per seed."""
    return _task_sets(size, "shelf_arcade", {1: "shelf", 2: "shelf,arcade"}, "shelf")


def airfryer_transfer(size: Size) -> list[SweepRun]:
    """Runs trained on mug alone (x=0) and on the air fryer and mug (x=1), each evaluated on the air fryer, per
    seed."""
    return _task_sets(size, "airfryer_mug", {0: "mug", 1: "airfryer,mug"}, "airfryer")


def held_out_object(size: Size) -> list[SweepRun]:
    """Per seed, a run trained on the base dataset and evaluated on its own test scenes (x=0), and one evaluating
    that run's model on the heldout dataset's scenes with the unseen plant (x=1)."""
    seen = [SweepRun(0.0, s, "base", (f"seed={s}",)) for s in range(size.seeds)]
    return seen + [SweepRun(1.0, r.seed, "base", r.overrides, eval_data="heldout", model_of=r.name) for r in seen]


def autonomous_rollouts(size: Size) -> list[SweepRun]:
    """Runs trained on the base dataset's scripted demonstrations (x=0) and on the mixed dataset, about half of
    it the zoo's rollouts (x=0.5), both evaluated on the mixed dataset, per seed."""
    return [SweepRun(x, s, data, (f"seed={s}",), eval_data="mixed")
            for x, data in ((0.0, "base"), (0.5, "mixed")) for s in range(size.seeds)]


SWEEPS = {
    "data_scaling": (data_scaling, "share of the training episodes", True),
    "task_scaling": (task_scaling, "tasks trained on (evaluated on mug)", False),
    "transfer": (transfer, "tasks trained on (1: shelf, 2: + arcade; evaluated on shelf)", False),
    "airfryer_transfer": (airfryer_transfer, "air-fryer data (0: mug only, 1: + air fryer; evaluated on it)", False),
    "held_out_object": (held_out_object, "test scenes (0: as in training, 1: with the unseen plant)", False),
    "autonomous_rollouts": (autonomous_rollouts, "share of policy rollouts in the training data", False),
}


# ---- running ---------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Job:
    """A piece of work for one GPU: fn(gpu) -> True on success; it starts once every job named in
    `needs` has succeeded, and is dropped (failed) when one of them failed."""

    name: str
    fn: object
    needs: frozenset = frozenset()


def on_gpus(jobs: list, gpus: list) -> dict:
    """Runs the jobs, one per GPU at a time (threads; the work itself is in subprocesses), each GPU
    taking, of the jobs whose needs are met, the one that heads the longest chain of jobs waiting on
    it (the first in the list among equals), so that a GPU trains the run whose evaluation and
    ranking wait on it before it ranks another; returns name -> succeeded."""
    cond, pending, done = threading.Condition(), list(jobs), {}
    known = {j.name for j in jobs}
    for j in jobs:
        if j.needs - known:
            raise ValueError(f"job {j.name} needs {sorted(j.needs - known)}, which no job makes")
    chain = chain_lengths(jobs)

    def take():
        with cond:
            while pending:
                for j in [j for j in pending if any(done.get(n) is False for n in j.needs)]:
                    pending.remove(j)
                    done[j.name] = False
                    print(f"{j.name}: skipped, as {', '.join(n for n in j.needs if done.get(n) is False)} failed",
                          flush=True)
                ready = max((j for j in pending if all(done.get(n) for n in j.needs)),
                            key=lambda j: chain[j.name], default=None)
                if ready is not None:
                    pending.remove(ready)
                    return ready
                if pending:
                    cond.wait()
            return None

    def worker(gpu):
        while (job := take()) is not None:
            try:
                ok = bool(job.fn(gpu))
            except Exception as e:  # noqa: BLE001 -- one job's failure must not stop the others
                print(f"{job.name}: {type(e).__name__}: {e}", flush=True)
                ok = False
            with cond:
                done[job.name] = ok
                cond.notify_all()

    threads = [threading.Thread(target=worker, args=(g,)) for g in gpus]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return done


def chain_lengths(jobs: list) -> dict:
    """name -> the number of jobs in the longest chain that starts at it (1: nothing waits on it)."""
    waiting = {j.name: [k.name for k in jobs if j.name in k.needs] for j in jobs}
    out = {}

    def length(name):
        if name not in out:
            out[name] = 1 + max((length(w) for w in waiting[name]), default=0)
        return out[name]

    for j in jobs:
        length(j.name)
    return out


def data_dir(size: Size, key: str, root: Path) -> Path:
    """Where a sweep's dataset lives: a preset as it is is the pipeline's own (runs/data/<preset>), shared."""
    preset, overrides = size.data[key]
    return root / "data" / (preset if not overrides else f"sweep_{preset}_{key}")


def data_jobs(size: Size, keys, root: Path, zoo_needed: bool = False) -> tuple[dict, list]:
    """The jobs that generate (or complete) each dataset the sweeps need (job "data:<key>"), and the
    zoo trained on "base" (job "zoo") where one needs policy rollouts or where zoo_needed. Returns
    (key -> directory, jobs). Each one's log is <its directory>.log."""
    needs_zoo = {k for k in size.data if any("{zoo}" in o for o in size.data[k][1])}
    keys = set(keys) | ({"base"} if zoo_needed or needs_zoo & set(keys) else set())
    dirs = {k: data_dir(size, k, root) for k in keys}
    zoo_dir = root / "policies" / size.zoo

    def generate(key, gpu):
        preset, overrides = size.data[key]
        overrides = [o.replace("{zoo}", str(zoo_dir)) for o in overrides]
        log = dirs[key].parent / f"{dirs[key].name}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        rc = _subprocess(["-m", "sim_data.dataset.generate", "--config", preset, "--out", str(dirs[key]), *overrides], gpu, log)
        return _announce(f"dataset {key}", rc, f"ready in {dirs[key]}", log)

    jobs = [Job(f"data:{k}", functools.partial(generate, k), frozenset({"zoo"} if k in needs_zoo else ()))
            for k in sorted(keys)]  # their order is in_sweep_order's, by what needs them
    if zoo_needed or needs_zoo & keys:
        jobs.append(Job("zoo", functools.partial(ensure_zoo, size, dirs["base"], zoo_dir), frozenset({"data:base"})))
    return dirs, jobs


def ensure_zoo(size: Size, data: Path, zoo_dir: Path, gpu=None) -> bool:
    """Trains the size's zoo on `data` into zoo_dir unless its registry is there; True on success."""
    if (zoo_dir / "policies.json").exists():
        return True
    log = zoo_dir.parent / f"{zoo_dir.name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    rc = _subprocess(["-m", "sim_data.policies.zoo", "--config", size.zoo, "--data", str(data), "--out", str(zoo_dir)], gpu, log)
    return _announce("zoo", rc, f"trained into {zoo_dir}", log)


def _announce(what: str, rc: int, success: str, log: Path) -> bool:
    """Prints how a subprocess ended (its success, or its exit code and log); True on success."""
    print(f"{what}: {success if rc == 0 else f'failed (exit {rc}), see {log}'}", flush=True)
    return rc == 0


def rank_run(model: Path, zoo: Path, task: str, size: Size, out: Path, gpu, log: Path, truth: Path) -> int:
    """Writes out/results.json: the zoo's policies on task ranked by the model in `model` against
    the simulator (experiments.evaluate; no videos; the simulated side cached in `truth` and shared
    by every model ranked from the same held-out states)."""
    return _subprocess(["-m", "experiments.evaluate", "--config", size.eval, "--out", str(out), f"wm={model}",
                        f"policies={zoo}", f"tasks={task}", "video_policies=0", f"truth_cache={truth}",
                        *WORLD_MODEL_ALONE], gpu, log)


def train_run(run: SweepRun, size: Size, data: Path, out: Path, gpu, log: Path) -> int:
    """Trains (or resumes) one run in a subprocess; returns its exit code."""
    cmd = ["-m", "wm.train", "--config", size.train, "--data", str(data), "--out", str(out),
           f"steps={size.steps}", *run.overrides, *(["--no-eval"] if run.evaluated_apart else [])]
    return _subprocess(cmd, gpu, log)


def evaluate_run(model: Path, data: Path, out: Path, gpu, log: Path) -> int:
    """Writes out/eval.json: the trained model in `model` evaluated on the dataset `data`."""
    return _subprocess(["-m", "wm.quality", "--wm", str(model), "--data", str(data), "--out", str(out)], gpu, log)


def _subprocess(args: list, gpu, log: Path) -> int:
    env = dict(os.environ)
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = str(gpu)
    with open(log, "a") as f:
        return subprocess.run([sys.executable, *args], env=env, stdout=f, stderr=subprocess.STDOUT,
                              check=False).returncode


@dataclasses.dataclass
class Plan:
    """One sweep under way: its name, size, runs, output directory, x label and scale."""

    name: str
    size_name: str
    runs: list
    out: Path
    x_label: str
    log_x: bool
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock)

    @property
    def size(self) -> Size:
        return SIZES[self.size_name]

    def write_results(self) -> dict:
        """Collects the finished runs into out/results.json and out/sweep.png (thread-safe)."""
        with self.lock:
            results = collect(self.name, self.size_name, self.runs, self.out, self.x_label)
            write_json_atomic(self.out / "results.json", results)
            plot(results, self.out / "sweep.png", self.log_x)
        return results


def run_jobs(plan: Plan, data: dict, root: Path, t0: float) -> list:
    """The jobs of one sweep: per run, its training (or resuming) and its evaluation where it is judged
    apart or evaluates another run's model (job "<sweep>/<run>"; a run that trains and is judged
    apart trains in a job of its own, "<sweep>/<run>:train", which needs only its training data),
    then the body-in-place measurement and the zoo's ranking where the sweep has them. Each step is
    skipped when its output is there."""
    jobs, by_name = [], {r.name: r for r in plan.runs}

    def trained_by(run: SweepRun) -> str:
        key = f"{plan.name}/{run.name}"
        return f"{key}:train" if run.trains and run.evaluated_apart else key

    for run in plan.runs:
        key = f"{plan.name}/{run.name}"
        needs = {f"data:{run.evaluated_on}"}
        if run.model_of:
            needs.add(trained_by(by_name[run.model_of]))
        elif run.evaluated_apart:
            jobs.append(Job(f"{key}:train", functools.partial(train_only, plan, run, data), frozenset({f"data:{run.data}"})))
            needs.add(f"{key}:train")
        else:
            needs.add(f"data:{run.data}")
        jobs.append(Job(key, functools.partial(train_and_evaluate, plan, run, data, t0), frozenset(needs)))
        if plan.name in MEASURED:
            jobs.append(Job(f"{key}:body", functools.partial(measure_body, plan, run, data), frozenset({key})))
        if plan.name in RANKED:
            jobs.append(Job(f"{key}:ranking", functools.partial(rank, plan, run, root, t0), frozenset({key, "zoo"})))
    return jobs


def train_only(plan: Plan, run: SweepRun, data: dict, gpu) -> bool:
    """Trains a run judged apart (its evaluation is the next job) unless it has been; True on success."""
    d, log = plan.out / run.name, plan.out / run.name / "train.log"
    d.mkdir(parents=True, exist_ok=True)
    if (d / "eval.json").exists() or (d / "trained").exists():
        return True
    if not _ran(plan, run, "training", train_run(run, plan.size, data[run.data], d, gpu, log), log):
        return False
    (d / "trained").touch()  # its evaluation apart may fail or be stopped: a rerun does not train again
    return True


def train_and_evaluate(plan: Plan, run: SweepRun, data: dict, t0: float, gpu) -> bool:
    """A run's job on gpu: unless its eval.json is there, trains it (evaluated as it trains) or, for a run judged
    apart, evaluates its model (trained by the run's ":train" job or model_of's) on its evaluation dataset;
    then rewrites the sweep's results. True on success; t0 times the progress message."""
    d, log = plan.out / run.name, plan.out / run.name / "train.log"
    d.mkdir(parents=True, exist_ok=True)
    if not (d / "eval.json").exists():
        # a run judged apart was trained by its ":train" job (or is another run's model)
        if not run.evaluated_apart:
            if not _ran(plan, run, "training", train_run(run, plan.size, data[run.data], d, gpu, log), log):
                return False
        elif not _ran(plan, run, "evaluation", evaluate_run(
                plan.out / run.model_run, data[run.evaluated_on], d, gpu, log), log):
            return False
    print(f"{plan.name} {run.name}: evaluated ({time.perf_counter() - t0:.0f} s)", flush=True)
    plan.write_results()
    return True


def measure_body(plan: Plan, run: SweepRun, data: dict, gpu) -> bool:
    """Measures the run's model with experiments.body_in_place on its evaluation dataset into <run>/BODY_FILE on
    gpu unless it is there, then rewrites the sweep's results; True on success."""
    d = plan.out / run.name
    if not (d / BODY_FILE).exists():
        rc = _subprocess(["-m", "experiments.body_in_place", "--wm", str(plan.out / run.model_run),
                          "--data", str(data[run.evaluated_on]), "--out", str(d / BODY_FILE)],
                         gpu, d / "train.log")
        if not _ran(plan, run, "body in place", rc, d / "train.log"):
            return False
    plan.write_results()
    return True


def rank(plan: Plan, run: SweepRun, root: Path, t0: float, gpu) -> bool:
    """Ranks the zoo's policies (root/policies/<zoo preset>) on the sweep's ranked task with the run's model
    (experiments.evaluate into <run>/RANK_DIR, the simulator's side cached under root/cache/truth) on gpu unless
    done, then rewrites the sweep's results; True on success; t0 times the progress message."""
    d = plan.out / run.name
    if not (d / RANK_DIR / "results.json").exists():
        rc = rank_run(plan.out / run.model_run, root / "policies" / plan.size.zoo, RANKED[plan.name],
                      plan.size, d / RANK_DIR, gpu, d / "train.log", root / "cache" / "truth")
        if not _ran(plan, run, "ranking", rc, d / "train.log"):
            return False
        print(f"{plan.name} {run.name}: ranked ({time.perf_counter() - t0:.0f} s)", flush=True)
    plan.write_results()
    return True


def _ran(plan: Plan, run: SweepRun, what: str, rc: int, log: Path) -> bool:
    if rc:
        print(f"{plan.name} {run.name}: {what} failed (exit {rc}), see {log}", flush=True)
    return rc == 0


def in_sweep_order(data: list, sweeps: list) -> list:
    """The data jobs and each sweep's jobs in one list, each data job just before the first sweep that
    needs it (the zoo's with the base dataset's), so that an earlier sweep's work comes first."""
    placed, out = set(), []
    by_name = {j.name: j for j in data}

    def place(name):
        if name in by_name and name not in placed:
            placed.add(name)
            for need in sorted(by_name[name].needs):
                place(need)
            out.append(by_name[name])

    for jobs in sweeps:
        for j in jobs:
            for need in sorted(j.needs):
                place(need)
        out += jobs
    return out + [j for j in data if j.name not in placed]


def plans_of(names: list, size_name: str, out: Path) -> list[Plan]:
    """The named sweeps' plans: one sweep into `out`, several into out/<name> (checked against what
    each directory holds)."""
    for name in names:
        if name not in SWEEPS:
            raise ValueError(f"unknown sweep {name!r}; choose from {', '.join(SWEEPS)}")
    if size_name not in SIZES:
        raise ValueError(f"unknown size {size_name!r}; choose from {', '.join(SIZES)}")
    plans = []
    for name in dict.fromkeys(names):
        make_runs, x_label, log_x = SWEEPS[name]
        plan = Plan(name, size_name, make_runs(SIZES[size_name]), Path(out) if len(names) == 1 else Path(out) / name,
                    x_label, log_x)
        plan.out.mkdir(parents=True, exist_ok=True)
        _check_sweep(plan.out, name, size_name)
        plans.append(plan)
    return plans


def collect_sweeps(names: list, size_name: str, out: Path) -> dict:
    """Rewrites each named sweep's results.json and sweep.png from the runs' files that are there,
    running nothing (after a change to what is collected, or where only the figures were copied).
    Returns name -> results."""
    return {plan.name: plan.write_results() for plan in plans_of(names, size_name, out)}


def run_sweeps(names: list, size_name: str, out: Path, root: Path = Path("runs")) -> dict:
    """Runs the named sweeps as one pool of jobs over the GPUs (sim_data.parts.local_gpus): the datasets, the zoo and
    every run's steps, each starting once what it needs is there, earlier sweeps first: one sweep
    into `out`, several into out/<name>. Returns name -> results."""
    plans, size = plans_of(names, size_name, out), SIZES[size_name]
    for plan in plans:
        print(f"{plan.name} ({size_name}): {len(plan.runs)} runs into {plan.out}", flush=True)
    runs = [r for p in plans for r in p.runs]
    data, jobs = data_jobs(size, [r.data for r in runs] + [r.evaluated_on for r in runs], root,
                           zoo_needed=any(p.name in RANKED for p in plans))
    t0 = time.perf_counter()
    jobs = in_sweep_order(jobs, [run_jobs(plan, data, root, t0) for plan in plans])
    gpus = local_gpus() or [None]  # without GPUs: one job at a time, devices left as they are
    print(f"{len(jobs)} jobs, {len(gpus)} at a time", flush=True)
    done = on_gpus(jobs, gpus)
    failed = [name for name, ok in done.items() if not ok]
    if failed:
        print(f"{len(failed)} jobs failed or were skipped: {', '.join(failed)}; rerun to retry them", flush=True)
    results = {}
    for plan in plans:
        results[plan.name] = plan.write_results()
        print(results[plan.name]["finding"])
    return results


def _check_sweep(out: Path, name: str, size: str) -> None:
    path = out / "sweep.json"
    mine = {"sweep": name, "size": size}
    if path.exists() and json.loads(path.read_text()) != mine:
        raise ValueError(f"{out} holds another sweep ({json.loads(path.read_text())}); use another OUT")
    write_json_atomic(path, mine)


# ---- results ---------------------------------------------------------------------------------------

def _get(d: dict, path):
    for k in path:
        if not isinstance(d, dict) or d.get(k) is None:
            return None
        d = d[k]
    return d


def collect(name: str, size: str, runs: list[SweepRun], out: Path, x_label: str) -> dict:
    """results.json: every run's figures, and per swept value their mean and interval over seeds."""
    rows = []
    rankings = {r.name: json.loads(p.read_text()) for r in runs
                if (p := out / r.name / RANK_DIR / "results.json").exists()}
    for r in runs:
        path, body = out / r.name / "eval.json", out / r.name / BODY_FILE
        ev = json.loads(path.read_text()) if path.exists() else None
        if ev is not None and body.exists():
            ev["body_in_place"] = json.loads(body.read_text())
        if ev is not None and r.name in rankings:
            ev["ranking"] = rankings[r.name]["metrics"]["pooled"]  # one task: pooled is within the task
        rows.append({"x": r.x, "seed": r.seed, "run": r.name, "finished": ev is not None,
                     **{m: _get(ev, p) if ev else None for m, p in METRICS}})
    xs = sorted({r.x for r in runs})
    per_x = []
    for x in xs:
        mine = [row for row in rows if row["x"] == x]
        entry = {"x": x, "seeds": sum(row["finished"] for row in mine)}
        for m, _ in METRICS:
            entry[m], entry[f"{m}_ci"] = S.mean_interval([row[m] for row in mine], BOUNDS.get(m))
        entry |= ensemble_figures([rankings[r.name] for r in runs if r.x == x and r.name in rankings])
        per_x.append(entry)
    return {"sweep": name, "size": size, "x_label": x_label, "runs": rows, "per_x": per_x,
            "ensemble": ensemble_figures(list(rankings.values())), "finding": finding(name, x_label, per_x)}


def ensemble_figures(ranked: list[dict]) -> dict:
    """The ranking statistics of the ensemble of the models whose rankings (experiments.evaluate's
    results.json) are given (experiments.ensemble: their predicted rates averaged), as
    ensemble_<statistic> and ensemble_models; {} for fewer than two, and the reason alone where they
    cannot be combined."""
    if len(ranked) < 2:
        return {}
    try:
        m = ensemble.combine(ranked)["metrics"]["pooled"]
    except ValueError as e:  # say why in results.json rather than fail the job that collects
        return {"ensemble_not_combined": str(e)}
    return {"ensemble_models": len(ranked),
            **{f"ensemble_{s}": m[s] for s in (*ensemble.MEMBER_STATS, "alignment") if s in m}}


def finding(name: str, x_label: str, per_x: list[dict]) -> str:
    """One sentence of what the figures do from the smallest to the largest swept value."""
    if len(per_x) < 2:
        return f"{name}: fewer than two values finished."
    a, b = per_x[0], per_x[-1]
    parts = []
    for m in ("success_auroc", "psnr_h8", "match_accuracy", "view_shift_h8_px", "pearson", "mmrv", "ensemble_pearson"):
        if a.get(m) is not None and b.get(m) is not None:
            parts.append(f"{m} {a[m]:.3g} -> {b[m]:.3g}")
    return f"{name}: from {x_label} = {a['x']:g} to {b['x']:g}: " + ", ".join(parts) + "."


def plot(results: dict, path: Path, log_x: bool) -> None:
    """Writes the sweep's figure to path: one panel per metric with any value, each run's figure as a grey dot,
    the per-value mean with its interval, and the seeds' ensemble where there is one; log_x: x on a log2 scale."""
    per_x = results["per_x"]
    shown = [m for m, _ in METRICS if any(e[m] is not None for e in per_x)] or [METRICS[0][0]]
    cols = min(5, len(shown))
    rows = -(-len(shown) // cols)
    fig = Figure(figsize=(3.0 * cols, 2.8 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax in axes.flat[len(shown):]:
        ax.set_visible(False)
    for ax, m in zip(axes.flat, shown, strict=False):
        pts = [(e["x"], e[m], e[f"{m}_ci"]) for e in per_x if e[m] is not None]
        for row in results["runs"]:
            if row[m] is not None:
                ax.plot(row["x"], row[m], ".", color="0.6", ms=4)
        if pts:
            x, y, ci = zip(*pts, strict=True)
            lo = [c[0] if c else v for c, v in zip(ci, y, strict=True)]
            hi = [c[1] if c else v for c, v in zip(ci, y, strict=True)]
            ax.errorbar(x, y, yerr=[np.subtract(y, lo), np.subtract(hi, y)], marker="o", capsize=3)
        ens = [(e["x"], e[f"ensemble_{m}"]) for e in per_x if e.get(f"ensemble_{m}") is not None]
        if ens:
            ax.plot(*zip(*ens, strict=True), "D--", color="tab:red", ms=5, label="seeds' ensemble")
            ax.legend(fontsize=7)
        if log_x:
            ax.set_xscale("log", base=2)
        xs = sorted({e["x"] for e in per_x})
        ax.set_xticks(xs, [f"{x:g}" for x in xs])
        ax.set_title(m, fontsize=9)
    fig.suptitle(f"{results['sweep']} ({results['size']})", fontsize=10)
    fig.supxlabel(results["x_label"], fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sweep", nargs="+", choices=sorted(SWEEPS), help="one sweep, or several sharing the GPUs")
    p.add_argument("--size", default="demo", choices=sorted(SIZES))
    p.add_argument("--out", type=Path, required=True, help="the sweep's directory; with several, OUT/<sweep>")
    p.add_argument("--root", type=Path, default=Path("runs"), help="where the sweep's datasets go (ROOT/data/...)")
    p.add_argument("--collect", action="store_true",
                   help="only rewrite results.json and sweep.png from the runs' files that are there")
    a = p.parse_args(argv)
    if a.collect:
        for res in collect_sweeps(a.sweep, a.size, a.out).values():
            print(res["finding"])
    else:
        run_sweeps(a.sweep, a.size, a.out, a.root)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
