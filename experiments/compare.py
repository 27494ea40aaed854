"""Two designs of world model, each trained with several seeds, ranking the same policies:

    python -m experiments.compare --base runs/eval/base_s0 runs/eval/base_s1 \\
        --design runs/eval/patch1_s0 runs/eval/patch1_s1 --names recipe,patch1 --out runs/compare/patch1.json

Each RUN is an `experiments.evaluate` OUT (its results.json) over the same policies from the same
held-out initial states, with the same true outcomes (the same zoo, evaluation preset and seed);
the runs differ only in their world model. A design is decided on the mean over its seeds: one
seed moves the ranking about as much as most design choices (docs/world-model.md). A RUN written
OUT#K is member K of the ensemble that evaluated OUT, alone (experiments.ensemble.member_results):
for an evaluation by `wm=runs/wm/a,runs/wm/b`,

    python -m experiments.compare --base runs/eval/ab#0 runs/eval/ab#1 --design runs/eval/ab \\
        --names one_model,ensemble

For each group the output gives every run's within-task statistics (experiments.stats: the mean
over tasks of Pearson, Spearman, MMRV, pairwise accuracy at gaps >= 10 points and per-episode
alignment), their mean over the group's runs and their range; and the design's gain, the
difference of the two group means (design minus base; for MMRV a negative gain is better), with a
95% interval from one bootstrap that resamples, within each task, policies and initial states, the
same draw for every run (stats.within_task_draws); beside them each run's mean absolute error of
the predicted success rates (the mean over tasks of the mean over policies; for the families, over
their members alone, where the report's family table also counts each family's undegraded base and
averages over families). The same over the policies that no run's world model learned from
(`in_wm_data` false), over those of them that are lineages of their own rather than counterfactual
families (degraded copies of a zoo checkpoint, whose knobs a design's data may share: the policies a
new user brings are of the first kind), and over the counterfactual families' members, each where
there are at least three a task. Last, the policies whose predicted success rate moved most between
the two designs (each design's mean over its runs), and the largest such move: with one run a side
of the same command, on the same commit and machine kind, it checks that the evaluation reproduces
(every predicted rate within 0.01).

With `--states A:B` every run counts only its held-out initial states A to B-1 of each task: the
evaluation draws its states as a prefix of one sequence (sim_data.policies.registry.heldout_seeds,
which skips the world model's training seeds), and with a preset's `state_batch` (`full`: 50) each
slice of states runs with its own key and shape, so an evaluation of 100 states holds that of 50 as
its first 50 (where the draws differ, as with state_batch=0, the simulated outcomes do and compare
refuses the pair), and

    python -m experiments.compare --base runs/eval/s50 --design runs/eval/s100 --states 0:50

compares two models on the states both ran, or one run with itself over 0:50 and 50:100 to see how
far the figures move with the episodes counted.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from experiments import stats as S
from experiments.ensemble import read_run
from sim_data.util import run_cli, write_json_atomic

GROUPS = ("base", "design")
REPRODUCED = 0.01  # predicted rates of two runs of one command that agree within this are the same figures
SHIFTS_SHOWN = 8  # the table lists the policies whose predicted rates moved most
MIN_PER_TASK = 3  # policies a task in a subset, as the evaluation's own unseen block
SUBSETS = ("all", "unseen", "unseen_networks", "families")


def episode_tables(results: list[dict]) -> tuple[dict, dict, dict, dict]:
    """The runs' per-episode tables over their common policies, each task's policies sorted by name:
    (true {task: (P, N) outcomes}, pred [{task: (P, N) probabilities}] one per run, unseen {task: (P,)
    bool}: no run's world model learned from the policy's rollouts, family {task: (P,) bool}: a
    counterfactual family's member, stats.is_family). Raises ValueError where the runs rank other
    policies, over other initial states or against other true outcomes."""
    if not results:
        raise ValueError("no evaluations to compare")
    keyed = [{(p["task"], p["name"]): p for p in r["policies"]} for r in results]
    keys = sorted(keyed[0])
    for i, k in enumerate(keyed[1:], 1):
        if sorted(k) != keys:
            diff = sorted(set(keys) ^ set(k))[:3]
            raise ValueError(f"evaluation {i} ranks other policies than evaluation 0 (for instance {diff}): "
                             "evaluate the same zoo with every world model")
    true, preds, unseen, family = {}, [{} for _ in results], {}, {}
    for task in sorted({t for t, _ in keys}):
        names = [n for t, n in keys if t == task]
        rows = [[k[(task, n)] for n in names] for k in keyed]
        for i, run in enumerate(rows):
            for p in run:
                if "pred_episodes" not in p or "true_episodes" not in p:
                    raise ValueError(f"evaluation {i} keeps no per-episode results for {p['name']}: rerun "
                                     "experiments.evaluate (its results.json predates pred_episodes)")
        t0 = np.asarray([p["true_episodes"] for p in rows[0]], np.float64)
        for i, run in enumerate(rows[1:], 1):
            t = np.asarray([p["true_episodes"] for p in run], np.float64)
            if t.shape != t0.shape or not np.array_equal(t, t0):
                raise ValueError(f"evaluation {i} has other true outcomes than evaluation 0 on {task}: compare "
                                 "evaluations of the same zoo from the same initial states (same preset, "
                                 "episodes and seed)")
        true[task] = t0
        for i, run in enumerate(rows):
            preds[i][task] = np.asarray([p["pred_episodes"] for p in run], np.float64)
        unseen[task] = np.asarray([not any(run[j].get("in_wm_data", True) for run in rows)
                                   for j in range(len(names))])
        family[task] = np.asarray([S.is_family(p) for p in rows[0]])
    return true, preds, unseen, family


def parse_states(text: str) -> tuple[int, int]:
    """"A:B" -> (A, B), the held-out initial states A to B-1; ValueError unless 0 <= A < B."""
    lo, sep, hi = text.partition(":")
    try:
        a, b = int(lo), int(hi)
    except ValueError:
        a = b = -1
    if not sep or not 0 <= a < b:
        raise ValueError(f"--states {text!r}: give A:B with 0 <= A < B, the states A to B-1 (for instance 0:50)")
    return a, b


def state_range(results: list[dict], lo: int, hi: int, labels=None) -> list[dict]:
    """Each experiments.evaluate results.json with every policy's per-episode outcomes and predictions
    (true_episodes, pred_episodes) cut to its held-out initial states lo..hi-1, in the evaluation's
    order of states; the rest of each policy's row as it was. labels: each run's name for errors.
    Raises ValueError, naming the run and policy, where a policy ran fewer than hi states."""
    out = []
    for i, r in enumerate(results):
        rows = []
        for p in r["policies"]:
            if "true_episodes" not in p or "pred_episodes" not in p:
                rows.append(p)  # episode_tables names what is missing
                continue
            n = min(len(p["true_episodes"]), len(p["pred_episodes"]))
            if n < hi:
                name = labels[i] if labels else f"evaluation {i}"
                raise ValueError(f"{name}: {p['name']} ran {n} initial states, fewer than --states' end {hi}")
            rows.append(p | {"true_episodes": p["true_episodes"][lo:hi], "pred_episodes": p["pred_episodes"][lo:hi]})
        out.append(r | {"policies": rows})
    return out


def _task_mean(per_task: dict) -> dict:
    """{task: {stat: x or (draws,)}} -> {stat: mean over tasks}, NaN-skipping."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return {k: np.nanmean(np.stack([np.asarray(v[k], np.float64) for v in per_task.values()]), 0)
                for k in S.WITHIN_TASK}


def compare_groups(true: dict, groups: dict, draws: int = 1000, seed: int = 0, threshold: float = 0.5) -> dict:
    """The comparison of groups of predictors over one truth (the module's docstring).

    true: {task: (P, N) outcomes}; groups: {"base": [{task: (P, N) probabilities}] one per run,
    "design": [...]}. Returns {"base", "design": {"runs": [{stat: x}], "mean": {stat}, "range":
    {stat: [min, max]}, "mean_ci": {stat: [lo, hi]}, "per_task": {task: {stat: mean over runs}},
    "runs_per_task": [{task: {stat: x}}] one per run, "abs_error": [x] one per run (mean_abs_error)},
    "gain": {"mean": {stat: design - base}, "mean_ci", "per_task", "per_task_ci"}, and "left_out": {task:
    [policy indices]} where some run's predictions are not finite (its imagination diverged): those
    policies are left out of every run's statistics}."""
    if sorted(groups) != sorted(GROUPS) or any(not runs for runs in groups.values()):
        raise ValueError(f"give both groups {GROUPS}, each with at least one run")
    # every run over the policies that all runs read: a policy one run's imagination diverged on (left out
    # of its statistics, stats.draw_statistics) is left out of every run's, so the gain compares like with like
    common = {t: np.logical_and.reduce([S.scored_policies(run[t]) for g in GROUPS for run in groups[g]])
              for t in true}
    predictors = {f"{g}{i}": {t: S.without_policies(run[t], ~common[t]) for t in true}
                  for g in GROUPS for i, run in enumerate(groups[g])}
    point, boot = S.within_task_draws(true, predictors, threshold, draws=draws, seed=seed)
    tasks = list(true)
    out, task_draws, mean_draws = {}, {}, {}
    for g in GROUPS:
        names = [f"{g}{i}" for i in range(len(groups[g]))]
        runs = [{k: float(v) for k, v in _task_mean(point[n]).items()} for n in names]
        drawn = [_task_mean(boot[n]) for n in names]
        # per draw: the group's mean over runs of each run's mean over tasks (the point estimate's recipe),
        # and per task the mean over runs
        mean_draws[g] = {k: np.mean([d[k] for d in drawn], 0) for k in S.WITHIN_TASK}
        task_draws[g] = {t: {k: np.mean([boot[n][t][k] for n in names], 0) for k in S.WITHIN_TASK} for t in tasks}
        out[g] = {"runs": runs,
                  "mean": {k: float(np.mean([r[k] for r in runs])) for k in S.WITHIN_TASK},
                  "range": {k: [min(r[k] for r in runs), max(r[k] for r in runs)] for k in S.WITHIN_TASK},
                  "mean_ci": {k: S.percentile_interval(mean_draws[g][k]) for k in S.WITHIN_TASK},
                  "per_task": {t: {k: float(np.mean([point[n][t][k] for n in names])) for k in S.WITHIN_TASK}
                               for t in tasks},
                  "runs_per_task": [{t: {k: float(point[n][t][k]) for k in S.WITHIN_TASK} for t in tasks}
                                    for n in names],
                  "abs_error": [mean_abs_error(_kept(true, common), _kept(run, common)) for run in groups[g]]}
    if not all(c.all() for c in common.values()):
        out["left_out"] = {t: np.flatnonzero(~c).tolist() for t, c in common.items() if not c.all()}
    d, b = "design", "base"
    out["gain"] = {"mean": {k: out[d]["mean"][k] - out[b]["mean"][k] for k in S.WITHIN_TASK},
                   "mean_ci": {k: S.percentile_interval(mean_draws[d][k] - mean_draws[b][k]) for k in S.WITHIN_TASK},
                   "per_task": {t: {k: out[d]["per_task"][t][k] - out[b]["per_task"][t][k] for k in S.WITHIN_TASK}
                                for t in tasks},
                   "per_task_ci": {t: {k: S.percentile_interval(task_draws[d][t][k] - task_draws[b][t][k])
                                       for k in S.WITHIN_TASK} for t in tasks}}
    return out


def ranked_reader(res: dict) -> str:
    """What a results.json's ranking read: its read-out, and for a judge the feature groups it reads
    ("judge: proprio,action"); "judge: inputs not recorded" where the results name none."""
    wm = res.get("world_model", {})
    readout = wm.get("readout") or "judge"
    if readout not in ("judge", "judge2"):
        return readout
    inputs = wm.get("judge_inputs" if readout == "judge" else "judge2_inputs")
    return f"{readout}: {','.join(inputs) if inputs else 'inputs not recorded'}"


def reader_warning(runs: list[dict], labels: list[str]) -> str | None:
    """A warning where the runs' rankings read with different judges (ranked_reader), which a
    comparison would credit to the world models; None where they all read alike."""
    readers = [ranked_reader(r) for r in runs]
    if len(set(readers)) < 2:
        return None
    return ("warning: the runs rank by different read-outs, so the comparison holds the judges' difference too: "
            + "; ".join(f"{label}: {reader}" for label, reader in zip(labels, readers, strict=True)))


def compare(base: list[dict], design: list[dict], draws: int = 1000, seed: int = 0) -> dict:
    """Two groups of experiments.evaluate results.json over one zoo and one truth -> {"draws",
    "resamples", "tasks", "policies": {task: P}, "all": compare_groups over every policy, "unseen": the
    same over the policies no world model learned from, "unseen_networks": over those of them that are
    lineages of their own, not counterfactual families (whose knobs a design's data may share; absent
    where no family is unseen), "families": over the counterfactual families' members, each subset
    absent with fewer than MIN_PER_TASK a task, with "<subset>_policies": {task: P} beside each}."""
    true, preds, unseen, family = episode_tables(base + design)
    # alignment at the evaluations' own threshold (their results.json's), as experiments.ensemble reads it
    thresholds = {r.get("config", {}).get("threshold", 0.5) for r in base + design}
    if len(thresholds) > 1:
        raise ValueError(f"the evaluations threshold predictions differently ({sorted(thresholds)}): their "
                         "alignments would not compare")
    threshold = thresholds.pop()
    k = len(base)
    out = {"draws": draws, "resamples": S.WITHIN_TASK_RESAMPLES, "tasks": list(true),
           "policies": {t: int(v.shape[0]) for t, v in true.items()},
           "all": compare_groups(true, {"base": preds[:k], "design": preds[k:]}, draws, seed, threshold)}
    subsets = {"unseen": unseen}
    rows = (base + design)[0]["policies"]  # every run ranks the same policies (episode_tables)
    seen = {p["name"] for r in base + design for p in r["policies"] if p.get("in_wm_data", True)}
    networks = S.unseen_networks(rows, seen)
    names = {t: sorted(p["name"] for p in rows if p["task"] == t) for t in true}  # episode_tables' order
    if networks:  # else the networks are the unseen block
        subsets["unseen_networks"] = {t: np.asarray([n in networks for n in names[t]]) for t in true}
    subsets["families"] = family
    out["shifts"] = rate_shifts(true, preds[:k], preds[k:], names)
    for name, keep in subsets.items():
        if all(u.sum() >= MIN_PER_TASK for u in keep.values()):
            out[f"{name}_policies"] = {t: int(u.sum()) for t, u in keep.items()}
            out[name] = compare_groups(_kept(true, keep), {"base": [_kept(p, keep) for p in preds[:k]],
                                                           "design": [_kept(p, keep) for p in preds[k:]]},
                                       draws, seed, threshold)
    return out


def rate_shifts(true: dict, base: list[dict], design: list[dict], names: dict) -> list[dict]:
    """Every policy's predicted success rate under each design (the mean over its runs of the mean over
    episodes) and the shift from base to design, largest |shift| first: [{"task", "name", "true",
    "base", "design", "shift"}]. true: {task: (P, N)}; base, design: [{task: (P, N)}] one per run;
    names: {task: [P names]} in the tables' order."""
    rows = []
    for t in true:
        b = np.mean([run[t].mean(1) for run in base], 0)
        d = np.mean([run[t].mean(1) for run in design], 0)
        rows += [{"task": t, "name": n, "true": float(true[t][i].mean()), "base": float(b[i]),
                  "design": float(d[i]), "shift": float(d[i] - b[i])} for i, n in enumerate(names[t])]
    # a shift that is NaN (a run's imagination diverged on the policy) last: a NaN key would leave the sort unordered
    return sorted(rows, key=lambda r: (math.isnan(r["shift"]), -abs(r["shift"])))


def shifts_markdown(shifts: list[dict], names: tuple[str, str] = GROUPS, shown: int = SHIFTS_SHOWN) -> str:
    """A sentence on the largest shift of a predicted rate and how many exceed REPRODUCED, then a table of
    the `shown` largest."""
    top = shifts[0]
    moved = sum(not abs(r["shift"]) <= REPRODUCED for r in shifts)  # a rate one side cannot read moved too
    lines = [f"Predicted success rates, {names[1]} against {names[0]}: the largest shift {top['shift']:+.3f} "
             f"({top['name']}); {moved} of {len(shifts)} policies moved by more than {REPRODUCED}"
             + (" (the same figures)." if moved == 0 else "."), "",
             f"| policy | true | {names[0]} | {names[1]} | shift |", "|---|---|---|---|---|"]
    lines += [f"| {r['name']} | {r['true']:.2f} | {r['base']:.3f} | {r['design']:.3f} | {r['shift']:+.3f} |"
              for r in shifts[:shown]]
    return "\n".join(lines)


def mean_abs_error(true: dict, pred: dict) -> float:
    """The mean over tasks of the mean over policies of |predicted - true success rate|; true, pred:
    {task: (P, N)} per-episode outcomes and probabilities."""
    return float(np.mean([np.abs(pred[t].mean(1) - true[t].mean(1)).mean() for t in true]))


def _kept(table: dict, keep: dict) -> dict:
    """{task: (P, ...)} -> the rows of each task that keep {task: (P,) bool} marks."""
    return {t: v[keep[t]] for t, v in table.items()}


def markdown(res: dict, names: tuple[str, str] = GROUPS) -> str:
    """The comparison as a markdown table: a row per group (mean over its runs [bootstrap interval],
    range over the runs; the mean absolute error, the mean over its runs) and the gain, over every
    policy, the unseen ones, the unseen networks and the counterfactual families."""
    stats = ("pearson", "mmrv", "pairwise_acc_gap10", "spearman")
    fmt = lambda x: "nan" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.3f}"
    lines = ["| policies | " + " | ".join(["model", *stats, "abs error"]) + " |", "|" + "---|" * (len(stats) + 3)]
    for subset in SUBSETS:
        if subset not in res:
            continue
        r = res[subset]
        for g, label in zip(GROUPS, names):
            n = len(r[g]["runs"])
            cells = [f"{fmt(r[g]['mean'][s])} [{fmt(r[g]['mean_ci'][s][0])}, {fmt(r[g]['mean_ci'][s][1])}] "
                     f"({fmt(r[g]['range'][s][0])}-{fmt(r[g]['range'][s][1])})" for s in stats]
            cells.append(fmt(float(np.mean(r[g]["abs_error"]))))
            lines.append(f"| {subset} | {label} ({n} runs) | " + " | ".join(cells) + " |")
        cells = [f"{r['gain']['mean'][s]:+.3f} [{r['gain']['mean_ci'][s][0]:+.3f}, {r['gain']['mean_ci'][s][1]:+.3f}]"
                 for s in stats]
        cells.append(f"{np.mean(r['design']['abs_error']) - np.mean(r['base']['abs_error']):+.3f}")
        lines.append(f"| {subset} | {names[1]} - {names[0]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


PLOTTED = ("pearson", "mmrv")


def plot(res: dict, path: Path, names: tuple[str, str] = GROUPS, subset: str = "all") -> None:
    """A PNG of the comparison: per statistic (Pearson, MMRV) a panel with each task and the mean over
    tasks, each run a dot and each design's mean over its runs a bar with its 95% bootstrap interval
    (on the mean over tasks)."""
    r = res[subset]
    tasks = list(r["base"]["per_task"])
    fig = Figure(figsize=(4.2 * len(PLOTTED), 3.4))
    axes = fig.subplots(1, len(PLOTTED))
    x = np.arange(len(tasks) + 1)
    for ax, stat in zip(axes, PLOTTED):
        for j, (g, label) in enumerate(zip(GROUPS, names)):
            off = (j - 0.5) * 0.36
            means = [r[g]["per_task"][t][stat] for t in tasks] + [r[g]["mean"][stat]]
            lo, hi = r[g]["mean_ci"][stat]
            err = np.zeros((2, len(means)))
            err[:, -1] = np.maximum([means[-1] - lo, hi - means[-1]], 0.0)  # a percentile interval may miss the point
            ax.bar(x + off, means, 0.34, yerr=err, capsize=3, color=f"C{j}", alpha=0.55, label=f"{label} (mean)")
            for run in r[g]["runs_per_task"]:
                vals = [run[t][stat] for t in tasks]
                ax.plot(x[:-1] + off, vals, "o", color=f"C{j}", ms=4)
            for run in r[g]["runs"]:
                ax.plot(x[-1] + off, run[stat], "o", color=f"C{j}", ms=4)
        if stat not in S.LOWER_IS_BETTER:  # correlations near 1: show the differences, not the distance from 0
            shown = [v for g in GROUPS for v in [*(r[g]["per_task"][t][stat] for t in tasks), r[g]["mean_ci"][stat][0]]]
            ax.set_ylim(max(-1.0, np.nanmin(shown) - 0.1), 1.0)
        ax.set_xticks(x, [*tasks, "mean"])
        ax.set_title(f"within-task {stat} ({subset} policies; lower is better)" if stat in S.LOWER_IS_BETTER
                     else f"within-task {stat} ({subset} policies)", fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8, loc="lower left")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--base", nargs="+", required=True, metavar="RUN",
                   help="evaluations by the base design's world models (OUT, or OUT#K: member K of OUT's ensemble)")
    p.add_argument("--design", nargs="+", required=True, metavar="RUN",
                   help="evaluations by the new design's world models (OUT or OUT#K)")
    p.add_argument("--names", default="base,design", help="the two designs' names in the table: BASE,DESIGN")
    p.add_argument("--draws", type=int, default=1000, help="bootstrap draws")
    p.add_argument("--out", type=Path, help="where the comparison's JSON goes (optional; with it, a PNG beside it)")
    p.add_argument("--states", metavar="A:B",
                   help="count only each task's held-out initial states A to B-1 of every run (default: all)")
    a = p.parse_args(argv)
    names = tuple(a.names.split(","))
    if len(names) != 2 or not all(names):
        p.error(f"--names takes two names separated by a comma, got {a.names!r}")
    if a.draws < 1:
        p.error(f"--draws {a.draws}: give at least one")
    try:
        states = parse_states(a.states) if a.states else None
    except ValueError as e:
        p.error(str(e))
    runs = [read_run(r) for r in a.base + a.design]
    if states:
        runs = state_range(runs, *states, labels=a.base + a.design)
    warning = reader_warning(runs, a.base + a.design)
    if warning:
        print(warning, file=sys.stderr)
    res = compare(runs[:len(a.base)], runs[len(a.base):], a.draws)
    res |= {"names": list(names), "base_runs": [str(r) for r in a.base], "design_runs": [str(r) for r in a.design],
            "states": list(states) if states else None}
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(a.out, res)
        plot(res, a.out.with_suffix(".png"), names)
    if states:
        print(f"Each task's held-out initial states {states[0]} to {states[1] - 1} of every run.\n")
    print(markdown(res, names) + "\n\n" + shifts_markdown(res["shifts"], names))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
