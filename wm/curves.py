"""Training curves of several runs compared step by step: does a run (another device count, another
parameter sharding) follow a reference run as closely as a second seed of the reference does?

    python -m wm.curves REF RUN [RUN ...] --seed-run REF_SEED1 [--key loss] [--after 100]
                        [--out curves.json] [--plot curves.png]

Each run is a `wm.train` output folder (its metrics.jsonl). For each run the distance to REF is the
mean of |run - ref| / |ref| over the logged steps (after --after) that REF, the seed run and that run
all share; the seed run's distance over the same steps is the spread it is held to, and the run is
within it when its distance is at most the seed run's. Validation losses (`val_<key>`) are compared
the same way where logged (runs without them are left out of that comparison).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from sim_data.util import run_cli, write_json_atomic


def read_curve(run: Path, key: str = "loss") -> dict[int, float]:
    """{step: value} of `key` in run/metrics.jsonl (rows without the key are skipped)."""
    path = Path(run) / "metrics.jsonl"
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing: {run} is not a wm.train output folder")
    curve = {}
    for line in path.read_text().splitlines():
        row = json.loads(line)
        if key in row:
            curve[int(row["step"])] = float(row[key])
    if not curve:
        raise ValueError(f"{path} logs no {key!r}")
    return curve


def curve_distance(ref: dict, other: dict, after: int = 0, steps=None) -> dict:
    """Mean and largest relative difference |other - ref| / |ref| over the steps > after both logged
    (and among `steps` where given), and both curves' last such value. Raises when there is none."""
    steps = sorted(s for s in set(ref) & set(other) & set(ref if steps is None else steps) if s > after)
    if not steps:
        raise ValueError(f"the curves share no logged step after {after}")
    rel = np.array([abs(other[s] - ref[s]) / max(abs(ref[s]), 1e-12) for s in steps])
    return {"steps": len(steps), "mean_rel": float(rel.mean()), "max_rel": float(rel.max()),
            "last_step": steps[-1], "ref_last": ref[steps[-1]], "last": other[steps[-1]]}


def compare(ref: Path, runs: list[Path], seed_run: Path, key: str = "loss", after: int = 0) -> dict:
    """Each run's curve_distance to ref, and the seed run's over the same steps (`seed`), for `key` and,
    where logged, `val_<key>`; `within_seed_spread`: the run's mean_rel <= the seed run's."""
    out = {"key": key, "after": after, "reference": str(ref), "seed_run": str(seed_run), "runs": {}}
    for k in (key, f"val_{key}"):
        cut = after if k == key else 0
        try:
            r, s = read_curve(ref, k), read_curve(seed_run, k)
        except ValueError:
            if k == key:
                raise
            continue  # no validation curve logged
        for run in runs:
            try:
                c = read_curve(run, k)
            except ValueError:
                if k == key:
                    raise
                continue
            d = curve_distance(r, c, cut, steps=set(s))
            d["seed"] = curve_distance(r, s, cut, steps=set(c))
            d["within_seed_spread"] = d["mean_rel"] <= d["seed"]["mean_rel"]
            out["runs"].setdefault(str(run), {})[k] = d
    return out


def plot_curves(ref: Path, runs: list[Path], seed_run: Path, path: Path, key: str = "loss") -> None:
    """A PNG of `key` against step for the reference, the seed run and every run (log scale)."""
    fig = Figure(figsize=(7, 4.2))
    ax = fig.add_subplot()
    for run, style in [(ref, "-"), (seed_run, ":"), *((r, "--") for r in runs)]:
        c = read_curve(run, key)
        steps = sorted(c)
        label = Path(run).name + (" (reference)" if run == ref else " (other seed)" if run == seed_run else "")
        ax.plot(steps, [c[s] for s in steps], style, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel(key)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("ref", type=Path, help="the reference run (for instance one GPU, seed 0)")
    p.add_argument("runs", type=Path, nargs="+", help="runs to compare with it (same seed, other placement)")
    p.add_argument("--seed-run", type=Path, required=True, help="the reference's configuration with another seed")
    p.add_argument("--key", default="loss")
    p.add_argument("--after", type=int, default=0, help="compare only steps after this one (warm-up)")
    p.add_argument("--out", type=Path, help="write the comparison as JSON")
    p.add_argument("--plot", type=Path, help="write the curves as a PNG")
    a = p.parse_args(argv)
    res = compare(a.ref, a.runs, a.seed_run, a.key, a.after)
    if a.out:
        write_json_atomic(a.out, res)
    if a.plot:
        plot_curves(a.ref, a.runs, a.seed_run, a.plot, a.key)
    for k in (a.key, f"val_{a.key}"):
        print(f"{k}: mean relative difference from {a.ref}, against the other seed's over the same steps")
        for run, d in res["runs"].items():
            if k not in d:
                continue
            e = d[k]
            verdict = "within" if e["within_seed_spread"] else "OUTSIDE"
            print(f"  {run}: {e['mean_rel']:.4f} against {e['seed']['mean_rel']:.4f} ({verdict} the seed spread, "
                  f"{e['steps']} steps; last {e['last']:.4f} against {e['ref_last']:.4f} at step {e['last_step']})")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
