"""The whole chain in stages: data -> policies -> rollouts -> world model -> evaluation -> report.

    python -m experiments.pipeline demo                 # every stage, on the CPU (make demo)
    python -m experiments.pipeline full --stage data    # one stage (make full STAGE=data)

Each stage resumes what an earlier run of it left and skips what is finished, so a killed run, or
a GPU session cut into 10-minute commands, continues where it stopped. The stages call the
modules' own entry points with the preset's configurations:

| stage    | module                 | writes            |
|----------|------------------------|-------------------|
| data     | sim_data.generate      | runs/data/<data>  |
| policies | sim_data.zoo           | runs/policies/<p> |
| rollouts | sim_data.generate      | runs/data/<data>_<p>_rollouts (the data and the lineage's rollouts) |
| train    | wm.train               | runs/wm/<p>       |
| eval     | experiments.evaluate   | runs/eval/<p>     |
| report   | experiments.report     | runs/eval/<p>/report.html |

The world model learns from the scripted episodes and from the rollouts of one lineage of the zoo,
failures included (the published work's most useful source: what the evaluated policies do, not
only what demonstrations do); the evaluation reports its statistics over every policy and over the
policies whose rollouts the world model never saw (`metrics.unseen`).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

STAGES = ("data", "policies", "rollouts", "train", "eval", "report")


@dataclasses.dataclass(frozen=True)
class Pipeline:
    """Presets of each stage and where they write (under root)."""

    data: str
    policies: str
    train: str
    eval: str
    root: str = "runs"
    rollouts: str = ""  # a zoo selector (sim_data.sources) whose checkpoints' rollouts join the world model's data
    rollout_episodes: int = 0  # episodes per selected checkpoint
    data_overrides: tuple = ()
    policies_overrides: tuple = ()
    train_overrides: tuple = ()
    eval_overrides: tuple = ()

    def dirs(self, name: str) -> dict:
        r = Path(self.root)
        data = r / "data" / self.data
        return {"data": data, "policies": r / "policies" / name, "wm": r / "wm" / name, "eval": r / "eval" / name,
                "wm_data": data.with_name(f"{self.data}_{name}_rollouts") if self.rollouts else data}


PIPELINES = {
    "demo": Pipeline(data="demo", policies="demo", train="demo", eval="demo", rollouts="conv_noproprio",
                     rollout_episodes=4),
    # the GPU preset: two tasks, scripted episodes of 5 skills, random play and the controllability
    # programs, the conv_noproprio lineage's rollouts; the zoo's five lineages of 8 checkpoints
    # evaluated over 64 held-out initial states per task; sized so that the whole chain fits one
    # 30-minute GPU session (H200, session 8: data 341 s, policies 206 s, rollouts 181 s, train 381 s,
    # eval 364 s for both tasks, report 9 s)
    "full": Pipeline(data="wm_full", policies="full", train="full", eval="full",
                     train_overrides=("w_success=0.5", "max_minutes=3.5"),
                     rollouts="conv_noproprio", rollout_episodes=64),
}


def run_stage(name: str, stage: str, extra=()) -> None:
    p = PIPELINES[name]
    d = p.dirs(name)
    t0 = time.perf_counter()
    print(f"== {name}: {stage}", file=sys.stderr, flush=True)
    if stage == "data":
        from sim_data import generate

        generate.main(["--config", p.data, "--out", str(d["data"]), *p.data_overrides, *extra])
    elif stage == "policies":
        from sim_data import zoo

        zoo.main(["--config", p.policies, "--data", str(d["data"]), "--out", str(d["policies"]),
                  *p.policies_overrides, *extra])
    elif stage == "rollouts":
        if not p.rollouts:
            print(f"{name} trains its world model on the data alone; skipping", file=sys.stderr)
            return
        from sim_data import generate

        generate.main(["--config", p.data, "--out", str(d["wm_data"]), "--reuse", str(d["data"]), *p.data_overrides,
                       f"policies={d['policies']}#{p.rollouts}", f"policy_episodes={p.rollout_episodes}", *extra])
    elif stage == "train":
        if (d["wm"] / "eval.json").exists():
            print(f"{d['wm']} is trained (eval.json exists); skipping", file=sys.stderr)
            return
        from wm import train

        train.main(["--config", p.train, "--data", str(d["wm_data"]), "--out", str(d["wm"]), *p.train_overrides,
                    *extra])
    elif stage == "eval":
        from experiments import evaluate

        evaluate.main(["--config", p.eval, "--out", str(d["eval"]), f"policies={d['policies']}", f"wm={d['wm']}",
                       *p.eval_overrides, *extra])
    elif stage == "report":
        from experiments import report

        report.main([str(d["eval"])])
    print(f"== {name}: {stage} done in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pipeline", choices=sorted(PIPELINES))
    ap.add_argument("--stage", choices=STAGES + ("all",), default="all")
    ap.add_argument("overrides", nargs="*", help="key=value overrides passed to the one stage run")
    a = ap.parse_intermixed_args(argv)
    if a.stage == "all" and a.overrides:
        ap.error("overrides need one --stage")
    t0 = time.perf_counter()
    for stage in STAGES if a.stage == "all" else (a.stage,):
        run_stage(a.pipeline, stage, a.overrides)
    if a.stage in ("all", "report"):
        print(f"report: {(PIPELINES[a.pipeline].dirs(a.pipeline)['eval'] / 'report.html').absolute()} "
              f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
