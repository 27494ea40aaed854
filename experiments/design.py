"""Decide a world-model design: seeds of a preset's recipe against the same seeds with the design's
settings, each trained and evaluated on the preset's zoo, then compared within each task.

    python -m experiments.design full_grip anchor model.anchor=true --seeds 2 --steps 4000
    python -m experiments.design full_grip patch1 model.patch=1 --seeds 2 --steps 4000 --design-steps 1750

The preset's data, zoo and rollouts must exist (`python -m experiments.pipeline PRESET --stage
data|policies|rollouts`). Every run trains with `wm.train` on the preset's world-model data and
training settings (seed k, the given steps; the design's runs add its key=value settings, and may
train a different number of steps for the same training time) and is evaluated by
`experiments.evaluate` on the preset's zoo from the same held-out states, without videos, against
the same simulated outcomes: the first evaluation simulates each batch into a truth cache
(runs/designs/PRESET/truth) that the others read (on several GPUs they wait for it), so the
simulator runs once per decision and no run is compared against outcomes another GPU drew. The runs go into
runs/designs/PRESET/{NAME,recipe}/<steps>steps_s<k>/ (`wm/`, `eval_e<episodes>/`, `timing.json`): the
recipe's are shared by every design compared against it with the same steps. `experiments.compare`
then writes compare.json, compare.md and compare.png into runs/designs/PRESET/NAME/: each run's
within-task figures, each design's mean and range over its seeds, and the design's gain with a 95%
interval from a bootstrap of policies and states, beside each run's held-out figures and timing.
A finished run trained with other settings than the command's (the same name given other settings)
stops the command before anything runs.

On a host with GPUs every run goes to a child process with one GPU, as many at a time as there are
GPUs (two seeds of each design on four GPUs run side by side; the design's runs first where they
take longer); without one they run here one after the other. A rerun resumes: finished trainings
and evaluations are skipped, a training cut off resumes from its checkpoints. Decide a design on
models trained >= 15 minutes with >= 2 seeds each (docs/world-model.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from experiments import compare, evaluate
from experiments.ensemble import read_results
from experiments.pipeline import PIPELINES, pipeline, use_compilation_cache
from experiments.timing import compile_snapshot, compiled_since, record_timing
from sim_data.parts import exclusive, local_gpus, run_parallel
from sim_data.util import device_name, run_cli, write_json_atomic
from wm import train
from wm.config import make_config
from wm.train import check_run_config

BASE = "recipe"


@dataclasses.dataclass(frozen=True)
class DesignRun:
    """One run: a world model trained (`wm.train` preset `config` on `data` with `settings`) into wm,
    evaluated with eval_argv into eval."""

    design: str
    seed: int
    wm: Path
    eval: Path
    config: str
    data: Path
    settings: tuple
    eval_argv: tuple

    @property
    def train_argv(self) -> tuple:
        return ("--config", self.config, "--data", str(self.data), "--out", str(self.wm), *self.settings)


def plan(preset: str, name: str, overrides=(), seeds: int = 2, steps: int = 4000, design_steps: int | None = None,
         episodes: int = 50, root: Path | None = None) -> list[DesignRun]:
    """The runs of a design decision, the design's first: for each seed k < seeds, the preset's
    recipe (`steps` steps) and the recipe with `overrides` (`design_steps`, default `steps`); root
    (default runs/designs/PRESET) holds them as the module's docstring says."""
    if preset not in PIPELINES:
        raise ValueError(f"unknown preset {preset!r}: one of {', '.join(sorted(PIPELINES))}")
    if not name or name.startswith(BASE) or "/" in name:
        raise ValueError(f"name the design (not starting with {BASE!r}, no '/'), got {name!r}")
    if not overrides:
        raise ValueError("a design is the recipe with some key=value settings changed: give at least one")
    if any("=" not in o for o in overrides):
        raise ValueError(f"settings are key=value, got {[o for o in overrides if '=' not in o]}")
    if seeds < 1 or steps < 1 or (design_steps is not None and design_steps < 1) or episodes < 1:
        raise ValueError("seeds, steps, design_steps and episodes must be >= 1")
    p = pipeline(preset)
    make_config(p.train, [*p.train_overrides, *overrides])  # an unknown or invalid setting fails here, not in a run
    d = p.dirs(preset)
    root = Path(root or Path(p.root) / "designs" / preset)
    jobs = []
    for design, n, extra in ((name, design_steps or steps, tuple(overrides)), (BASE, steps, ())):
        for k in range(seeds):
            run = root / design / f"{n}steps_s{k}"
            jobs.append(DesignRun(design, k, run / "wm", run / f"eval_e{episodes}", p.train, d["wm_data"],
                            (*p.train_overrides, f"seed={k}", f"steps={n}", "max_minutes=0", *extra),
                            ("--config", p.eval, "--out", str(run / f"eval_e{episodes}"), f"policies={d['policies']}",
                             f"wm={run / 'wm'}", f"episodes={episodes}", "max_minutes=0", *p.eval_overrides,
                             "video_policies=0", f"truth_cache={root / 'truth'}", *evaluate.WORLD_MODEL_ALONE)))
    # the evaluations' settings too, before any model trains for them (episodes a state batch must divide)
    evaluate.make_config(p.eval, [a for a in jobs[0].eval_argv if "=" in a and not a.startswith("-")])
    return jobs


def check_inputs(preset: str) -> None:
    """Raises SystemExit naming the pipeline stage to run where the preset's data or zoo is missing."""
    p = pipeline(preset)
    d = p.dirs(preset)
    for path, stage in ((d["wm_data"] / "stats.json", "rollouts" if p.rollouts else "data"),
                        (d["policies"] / "policies.json", "policies")):
        if not path.exists():
            raise SystemExit(f"{path} not found: run `python -m experiments.pipeline {preset} --stage {stage}` "
                             "(and the stages before it) first")


def check_trained_as_planned(job: DesignRun) -> None:
    """Raises SystemExit where the run's directory holds a model trained with other settings or data
    than the job's (the same name given other settings, or other steps)."""
    try:
        check_run_config(make_config(job.config, job.settings), job.data, job.wm)
    except ValueError as e:
        raise SystemExit(f"{e}: name the design anew, or remove {job.wm.parent}") from None


def run_job(job: DesignRun) -> None:
    """Trains (unless its eval.json says it is trained, with the job's settings) and evaluates (unless
    results.json exists from this model) one run, under a lock on its directory (two commands may share
    the recipe's runs), each command's wall and compile seconds appended to the run's timing.json."""
    job.wm.parent.mkdir(parents=True, exist_ok=True)
    with exclusive(job.wm.parent / "run.lock"):
        trained = (job.wm / "eval.json").exists()
        if trained:
            check_trained_as_planned(job)
        evaluated = trained and (job.eval / "results.json").exists()  # a model trained now is evaluated anew
        for stage, main, argv, done in (("train", train.main, job.train_argv, trained),
                                        ("eval", evaluate.main, job.eval_argv, evaluated)):
            if done:
                continue
            before, t0 = compile_snapshot(), time.perf_counter()
            main(list(argv))
            record_timing(job.wm.parent / "timing.json",
                          {"stage": stage, "wall_s": round(time.perf_counter() - t0, 3), **compiled_since(before),
                           "device": device_name(), "argv": list(argv)})


# wm.train's eval.json figures (held-out episodes of its data) shown beside the ranking
HELD_OUT = ("psnr_h8", "gain_over_copy_last_h8_db", "lpips_h8", "success_auroc", "match_accuracy", "delta_psnr_db",
            "success_follows_actions")


def held_out_table(jobs: list[DesignRun]) -> tuple[dict, str]:
    """Each run's held-out figures (its eval.json summary, HELD_OUT) and a markdown table of them, a row
    per run and per design's mean."""
    rows = {f"{j.design}_s{j.seed}": json.loads((j.wm / "eval.json").read_text()).get("summary", {}) for j in jobs}
    lines = ["| run | " + " | ".join(HELD_OUT) + " |", "|" + "---|" * (len(HELD_OUT) + 1)]
    fmt = lambda x: "" if x is None else f"{x:.3f}"
    for run, summary in rows.items():
        lines.append(f"| {run} | " + " | ".join(fmt(summary.get(k)) for k in HELD_OUT) + " |")
    for design in dict.fromkeys(j.design for j in jobs):
        vals = [rows[f"{j.design}_s{j.seed}"] for j in jobs if j.design == design]
        # a figure eval.json could not compute (one class, no programs) is None: the mean is then missing too
        means = [np.mean([v[k] for v in vals]) if all(v.get(k) is not None for v in vals) else None
                 for k in HELD_OUT]
        lines.append(f"| {design} (mean) | " + " | ".join(fmt(m) for m in means) + " |")
    return rows, "\n".join(lines)


def runs_timing_markdown(timing: dict) -> str:
    """The runs' timing rows (run_job) as a markdown table."""
    lines = ["| run | stage | wall s | compile s | device |", "|---|---|---|---|---|"]
    for run, rows in timing.items():
        lines += [f"| {run} | {r['stage']} | {r['wall_s']:.0f} | {r['compile_s']:.0f} | {r['device']} |" for r in rows]
    return "\n".join(lines)


def write_comparison(jobs: list[DesignRun], out: Path, draws: int = 1000) -> dict:
    """compare.json, compare.md and compare.png in out from the finished runs' evaluations: the ranking
    within each task (experiments.compare) and each run's held-out figures."""
    name = jobs[0].design
    groups = {g: [read_results(j.eval) for j in jobs if j.design == g] for g in (BASE, name)}
    res = compare.compare(groups[BASE], groups[name], draws)
    held_out, held_table = held_out_table(jobs)
    timing = {f"{j.design}_s{j.seed}": json.loads(t.read_text()) if (t := j.wm.parent / "timing.json").exists()
              else [] for j in jobs}
    res |= {"names": [BASE, name], "held_out": held_out, "timing": timing,
            "runs": {j.design + f"_s{j.seed}": {"train": list(j.train_argv)} for j in jobs}}
    write_json_atomic(out / "compare.json", res)
    table = (compare.markdown(res, (BASE, name)) + "\n\n" + compare.shifts_markdown(res["shifts"], (BASE, name))
             + "\n\nHeld-out episodes (`eval.json`):\n\n" + held_table
             + "\n\nCommands (wall and compile seconds; a run finished by an earlier command lists it there):\n\n"
             + runs_timing_markdown(timing))
    (out / "compare.md").write_text(table + "\n")
    compare.plot(res, out / "compare.png", (BASE, name))
    return res | {"table": table}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("preset", choices=sorted(PIPELINES), help="the pipeline preset whose recipe, data and zoo are used")
    p.add_argument("name", help="the design's name (its runs' directories)")
    p.add_argument("overrides", nargs="+", help="the design's key=value training settings")
    p.add_argument("--seeds", type=int, default=2, help="seeds of each design")
    p.add_argument("--steps", type=int, default=4000, help="training steps of the recipe's runs")
    p.add_argument("--design-steps", type=int, default=None,
                   help="training steps of the design's runs (default --steps; fewer for a costlier step at the "
                        "same training time)")
    p.add_argument("--episodes", type=int, default=50, help="held-out initial states a policy")
    p.add_argument("--root", type=Path, default=None, help="where the runs go (default runs/designs/PRESET)")
    p.add_argument("--draws", type=int, default=1000, help="bootstrap draws of the comparison")
    p.add_argument("--job", type=int, default=None, help=argparse.SUPPRESS)  # one run, in a child process
    a = p.parse_intermixed_args(argv)
    try:
        jobs = plan(a.preset, a.name, a.overrides, a.seeds, a.steps, a.design_steps, a.episodes, a.root)
    except ValueError as e:
        p.error(str(e))
    if a.draws < 1:
        p.error(f"--draws {a.draws}: give at least one")
    out = jobs[0].wm.parent.parent  # the design's directory: its plan, logs and comparison
    use_compilation_cache(pipeline(a.preset).root)
    if a.job is not None:
        run_job(jobs[a.job])
        return 0
    check_inputs(a.preset)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "plan.json", {"preset": a.preset, "name": a.name, "overrides": a.overrides,
                                          "jobs": [{"design": j.design, "seed": j.seed, "train": list(j.train_argv),
                                                    "eval": list(j.eval_argv)} for j in jobs]})
    for job in jobs:  # finished runs must be the planned ones before any is skipped or compared
        if (job.wm / "eval.json").exists():
            check_trained_as_planned(job)
    todo = [i for i, j in enumerate(jobs) if not (j.eval / "results.json").exists()]
    gpus = local_gpus()
    if len(gpus) > 1 and todo:
        base = [sys.executable, "-m", "experiments.design", *(argv if argv is not None else sys.argv[1:])]
        run_parallel([[*base, "--job", str(i)] for i in todo], gpus, out / "logs", "run")
    else:
        for i in todo:
            print(f"run {i + 1} of {len(jobs)}: {jobs[i].design}, seed {jobs[i].seed}", file=sys.stderr, flush=True)
            run_job(jobs[i])
    res = write_comparison(jobs, out, a.draws)
    print(res["table"])
    print(f"comparison: {out / 'compare.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
