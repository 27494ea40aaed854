"""`wmlab`: one command whose subcommands are the project's modules (each takes its own --help).

    wmlab demo                      # the whole chain on the CPU (make demo)
    wmlab data --config demo --out runs/data/demo
    wmlab eval --config demo --out runs/eval/demo wm=runs/wm/demo
"""

from __future__ import annotations

import importlib
import sys

from sim_data.util import run_cli

# subcommand -> (module, what it does); the module is imported only when its subcommand runs, so that
# `wmlab --help` answers without loading JAX
COMMANDS = {
    "demo": ("experiments.pipeline", "the whole chain at a preset's scale (`wmlab demo` = pipeline demo)"),
    "pipeline": ("experiments.pipeline", "the chain's stages: data, policies, rollouts, train, eval, report"),
    "data": ("sim_data.dataset.generate", "generate a dataset (MCAP episodes, manifest, training cache)"),
    "policies": ("sim_data.policies.zoo", "train the policy zoo and register its checkpoints and families"),
    "train": ("wm.train", "train a world model"),
    "wm-eval": ("wm.quality", "a world model's frame, success and controllability figures (eval.json)"),
    "eval": ("experiments.evaluate", "rank policies in the world model against the simulator"),
    "report": ("experiments.report", "the HTML and Markdown report of an evaluation"),
    "videos": ("experiments.videos", "MP4 files of an evaluation's real and imagined episodes"),
    "export-lerobot": ("sim_data.dataset.lerobot", "a dataset in LeRobot's layout v3.0 (parquet, mp4)"),
    "sweep": ("experiments.sweep", "sweeps over data, tasks and sources"),
    "ensemble": ("experiments.ensemble", "combine the rankings of several world models"),
    "cache": ("sim_data.dataset.cache", "build or check a dataset's training cache"),
    "replay": ("sim_data.dataset.replay", "replay a recorded episode in the simulator"),
    "success-table": ("sim_data.bench.success_table", "scripted policies' success at several skills"),
    "render-check": ("sim_data.bench.render_check", "the JAX renderer against MuJoCo's"),
    "bench-physics": ("sim_data.bench.physics", "physics steps per second"),
    "bench-render": ("sim_data.bench.render", "rendering frames per second"),
    "bench-data": ("sim_data.bench.data", "dataset generation end to end"),
    "bench-policy": ("sim_data.bench.policy", "a policy's share of a rollout's time"),
    "bench-wm": ("wm.bench", "world-model training and imagination speed"),
}


def usage() -> str:
    """The help text of `wmlab`: the module doc and one line per subcommand, with what it does and its module."""
    width = max(map(len, COMMANDS))
    lines = [__doc__.strip(), "", "commands:"]
    lines += [f"  {name:<{width}}  {what}  ({module})" for name, (module, what) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"wmlab: unknown command {name!r}; choose from {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    if name == "demo":
        rest = ["demo", *rest]
    sys.argv = [f"wmlab {name}", *rest]
    return module.main(rest) or 0


def entry() -> None:
    """The console script."""
    sys.exit(run_cli(main))
