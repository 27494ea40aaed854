"""Policy rankings by an ensemble of world models: `python -m experiments.ensemble RUN RUN ... --out DIR`.

    python -m experiments.ensemble runs/eval/seed0 runs/eval/seed1 runs/eval/seed2 --out runs/eval/ensemble

Each RUN is an `experiments.evaluate` OUT (its results.json) over the same policies from the same
held-out states, by a different world model (another seed, size or dataset). A policy's ensemble
prediction is the mean of the models' predicted rates; as each rate is the mean success
probability over the states, this is the rate of the per-episode mean probability. The true rate
is the mean of the runs' (identical where they share `truth_cache`; `true_spread` says by how much
they differ otherwise). DIR/results.json holds per policy its rates, and pooled over tasks and per task the
rate-level statistics of the ensemble (`experiments.stats.ranking_metrics`) beside those of each
model alone against the same true rates. Where every run keeps each episode's probability and
outcome (`pred_episodes`, `true_episodes`; evaluations written before those fields existed lack
them) and the runs share the true outcomes, the ensemble's per-episode probability is the models'
mean, and the per-episode alignment (at the first run's `threshold`) and Pearson's bootstrap
interval over initial states join the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

import numpy as np

from experiments import stats as S
from sim_data.util import run_cli, write_json_atomic

MEMBER_STATS = ("pearson", "spearman", "mmrv", "pairwise_acc_gap10")


def combine(results: list[dict]) -> dict:
    """The ensemble's results.json from K >= 2 `experiments.evaluate` results over the same
    policies: {"models": K, "policies": [{name, task, lineage, n, true_rate, true_spread, pred_rate,
    pred_rates (K,)}], "metrics": {"pooled" and per task: ranking_metrics + "members"}, "intervals": what
    its Pearson intervals resample (stats.INTERVALS)}."""
    if len(results) < 2:
        raise ValueError(f"an ensemble needs at least two evaluations, got {len(results)}")
    by_key = [{(p["task"], p["name"]): p for p in r["policies"]} for r in results]
    first = [(p["task"], p["name"]) for p in results[0]["policies"]]
    for i, b in enumerate(by_key[1:], 1):
        if set(b) != set(first):
            missing = sorted(set(first) ^ set(b))[:3]
            raise ValueError(f"evaluation {i} ranks other policies than evaluation 0 (for instance {missing}): "
                             "evaluate the same policies on the same tasks with every model")
    rows = []
    for key in first:
        ps = [b[key] for b in by_key]
        if len({p["n"] for p in ps}) != 1:
            raise ValueError(f"{key[1]} on {key[0]} was evaluated over {sorted({p['n'] for p in ps})} states: "
                             "use the same held-out states (episodes, seed) with every model")
        true = [p["true_rate"] for p in ps]
        pred = [p["pred_rate"] for p in ps]
        row = {"name": key[1], "task": key[0], "lineage": ps[0].get("lineage"), "n": ps[0]["n"],
               "true_rate": float(np.mean(true)), "true_spread": float(np.ptp(true)),
               "pred_rate": float(np.mean(pred)), "pred_rates": pred}
        if all("pred_episodes" in p for p in ps) and all(p["true_episodes"] == ps[0]["true_episodes"] for p in ps):
            row["true_episodes"] = ps[0]["true_episodes"]
            row["pred_episodes_each"] = [p["pred_episodes"] for p in ps]
            row["pred_episodes"] = np.mean(row["pred_episodes_each"], axis=0).tolist()
        rows.append(row)
    threshold = results[0].get("config", {}).get("threshold", 0.5)
    metrics = {"pooled": ensemble_metrics(rows, threshold)}
    for task in dict.fromkeys(r["task"] for r in rows):
        mine = [r for r in rows if r["task"] == task]
        if len(mine) >= 3:
            metrics[task] = ensemble_metrics(mine, threshold)
    intervals = {k: v for k, v in S.INTERVALS.items() if "pearson_ci" in k}  # what its intervals resample
    return {"models": len(results), "policies": rows, "metrics": metrics, "intervals": intervals,
            **shared_reader(results)}


READER_KEYS = ("readout", "judge_inputs", "judge2_inputs")  # what a results.json's ranking read with


def shared_reader(results: list[dict]) -> dict:
    """{"world_model": READER_KEYS' values} where every result's ranking read alike (so that
    experiments.compare can tell what an ensemble ranked with), else {}."""
    readers = {json.dumps({k: r.get("world_model", {}).get(k) for k in READER_KEYS}) for r in results}
    return {"world_model": json.loads(readers.pop())} if len(readers) == 1 else {}


def ensemble_metrics(rows: list[dict], threshold: float = 0.5) -> dict:
    """ranking_metrics of the rows' ensemble predictions, and "members": each model's alone and
    their mean, against the same true rates; with the per-episode alignment (each episode's mean
    probability at `threshold`) and Pearson's bootstrap interval where every row has its episodes."""
    true = [r["true_rate"] for r in rows]
    out = S.ranking_metrics([r["pred_rate"] for r in rows], true)
    member_rates = np.array([r["pred_rates"] for r in rows]).T
    if all("pred_episodes" in r for r in rows):
        true_eps = np.array([r["true_episodes"] for r in rows], bool)
        prob_eps = np.array([r["pred_episodes"] for r in rows])
        out["alignment"] = S.alignment(prob_eps >= threshold, true_eps)
        out["pearson_ci_bootstrap"] = list(S.bootstrap_pearson(prob_eps, true_eps, draws=1000))
        member_eps = np.array([r["pred_episodes_each"] for r in rows]).transpose(1, 0, 2)
        return out | member_metrics(member_rates, true, member_eps, true_eps, threshold)
    return out | member_metrics(member_rates, true)


def member_runs(wm_root: Path, name: str, members: int) -> list[Path]:
    """The training runs of an ensemble of `members` world models named `name` under wm_root: seed 0's
    run is wm_root/name, seed k's wm_root/name_seed<k>."""
    return [Path(wm_root) / name] + [Path(wm_root) / f"{name}_seed{k}" for k in range(1, members)]


def member_metrics(member_rates, true_rates, member_eps=None, true_eps=None, threshold: float = 0.5) -> dict:
    """Each ensemble member's ranking alone against the same true rates, and the members' mean.

    member_rates: (K, P) predicted rates; true_rates: (P,); member_eps: (K, P, N) per-episode
    probabilities and true_eps (P, N) outcomes, for each member's alignment at `threshold`.
    Returns {"members": {stat: [K]}, "members_mean": {stat: float}} over MEMBER_STATS (+ alignment)."""
    members = [S.ranking_metrics(list(m), list(true_rates)) for m in np.asarray(member_rates)]
    stats = MEMBER_STATS
    if member_eps is not None:
        for m, eps in zip(members, member_eps, strict=True):
            m["alignment"] = S.alignment(np.asarray(eps) >= threshold, np.asarray(true_eps, bool))
        stats = (*MEMBER_STATS, "alignment")
    table = {s: [m[s] for m in members] for s in stats}
    mean = {s: float(np.nanmean(v)) if np.isfinite(np.asarray(v, float)).any() else math.nan for s, v in table.items()}
    return {"members": table, "members_mean": mean}


def read_results(run: Path) -> dict:
    """An evaluate OUT's results.json (run may be the directory or the file)."""
    path = run / "results.json" if run.is_dir() else run
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: give experiments.evaluate OUT directories (make eval OUT=...)")
    res = json.loads(path.read_text())
    if "policies" not in res:
        raise ValueError(f"{path} is not an experiments.evaluate results.json (no 'policies')")
    return res


# the fields of an evaluation's policy row that hold no world model's reading
TRUTH_FIELDS = ("name", "task", "lineage", "step", "kind", "n", "true_rate", "true_ci", "true_episodes", "in_wm_data")


def member_results(run: Path, k: int) -> dict:
    """Ensemble member k's reading alone, from an `experiments.evaluate` OUT that an ensemble of world
    models evaluated: its results.json whose policy rows keep their truth (TRUTH_FIELDS) and carry
    member k's per-episode probabilities (`pred_episodes`, from OUT/tasks/<task>.npz's prob_members,
    (K, P, N)) and their mean (`pred_rate`); the ensemble's other figures are left out. Lets
    experiments.compare set an ensemble against its members, or members of two ensembles against
    each other. `in_wm_data` stays the ensemble's (any member learned from the policy's rollouts):
    the members of one pipeline's ensemble share their data, so it is each member's too."""
    res = read_results(run)
    out = Path(run) if Path(run).is_dir() else Path(run).parent
    rows = []
    for task in sorted({p["task"] for p in res["policies"]}):
        path = out / "tasks" / f"{task}.npz"
        if not path.exists():
            raise FileNotFoundError(f"{path} not found: member {k} is read from the evaluation's per-task results")
        with np.load(path) as z:
            names = json.loads(z["meta"].tobytes().decode())["names"]
            members = z["prob_members"] if "prob_members" in z.files else z["prob"][None]
        if not 0 <= k < len(members):
            raise ValueError(f"{run} was evaluated by {len(members)} world model(s): member {k} is not among them")
        by_name = dict(zip(names, members[k], strict=True))
        for p in (p for p in res["policies"] if p["task"] == task):
            if p["name"] not in by_name:
                raise ValueError(f"{path} holds no {p['name']}, which {run}'s results.json ranks: the two are of "
                                 "different evaluations (rerun experiments.evaluate to gather them again)")
            probs = np.asarray(by_name[p["name"]], np.float64)
            rows.append({**{f: p[f] for f in TRUTH_FIELDS if f in p},
                         "pred_episodes": np.round(probs, 5).tolist(), "pred_rate": float(probs.mean())})
    return {"policies": rows, "member": k, "ensemble_run": str(run), **shared_reader([res])}


def read_run(spec: str) -> dict:
    """An evaluation named on a command line: OUT (its results.json, read_results) or OUT#K (ensemble
    member K of OUT alone, member_results)."""
    member = re.fullmatch(r"(.+)#([0-9]+)", str(spec))
    if member is None or Path(spec).exists():
        return read_results(Path(spec))
    return member_results(Path(member.group(1)), int(member.group(2)))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="experiments.evaluate OUT directories, one per world model")
    p.add_argument("--out", type=Path, required=True, help="where results.json of the ensemble goes")
    a = p.parse_args(argv)
    res = combine([read_results(r) for r in a.runs]) | {"runs": [str(r) for r in a.runs]}
    a.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(a.out / "results.json", res)
    m = res["metrics"]["pooled"]
    print(json.dumps({"models": res["models"], **{s: m[s] for s in (*MEMBER_STATS, "alignment") if s in m},
                      "members_mean": m["members_mean"]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
