"""The evaluation report: one self-contained HTML file (figures and videos inlined) and a Markdown
summary, from an evaluation directory (experiments.evaluate).

    python -m experiments.report RUN          # writes RUN/report.html and RUN/report.md
    make report RUN=runs/eval/demo [SWEEPS=runs/sweeps]   # plus a section per sweep (make sweep)
"""

from __future__ import annotations

import argparse
import base64
import html
import io
import json
import math
import re
import sys
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from PIL import Image

from experiments.stats import MIN_CORRELATED, nonfinite_policies, policy_count, rank
from sim_data.util import read_json, run_cli

# each evaluation preset's own targets for the within-task means (docs/results.md)
TARGETS = {"demo": {"pearson": (">=", 0.7)},
           "full": {"pearson": (">=", 0.9), "mmrv": ("<=", 0.05), "pairwise_acc_gap10": (">=", 0.9)}}
TAB10 = colormaps["tab10"]
MAX_LEGEND = len(TAB10.colors)  # lineages named in a figure's legend: one colour each
HEADLINE = ("pearson", "spearman", "kendall", "mmrv", "pairwise_acc", "pairwise_acc_gap10", "alignment")
VIDEOS = "videos.npz"  # in the run: the kept episodes (experiments.evaluate)
LABELS = {"pearson": "Pearson r", "spearman": "Spearman rho", "mmrv": "MMRV (lower is better)",
          "pairwise_acc_gap10": "pairwise accuracy, gaps >= 10 points", "alignment": "per-episode alignment"}


def _subplots(nrows: int = 1, ncols: int = 1, figsize=None, **kw):
    """(figure, axes) drawn off screen: a bare matplotlib Figure, no pyplot state or backend."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(nrows, ncols, **kw)


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _missing(x) -> bool:
    return x is None or (isinstance(x, float) and math.isnan(x))


def _tx(s) -> str:
    """A name as matplotlib text: its "$" literal (a pair would be read as TeX, and bad TeX fails the figure)."""
    return str(s).replace("$", r"\$")


def _fmt(x, digits=3) -> str:
    if _missing(x):
        return "n/a"
    return f"{x:.{digits}f}" if isinstance(x, float) else str(x)


# ---- figures -----------------------------------------------------------------------------------------

def scatter_figure(policies: list[dict], metrics: dict, tasks: list[str]) -> str:
    """Predicted vs true success per policy with 95% intervals, one panel per task, then the tasks
    pooled (secondary: the gap between tasks correlates for free)."""
    panels = [(t, [p for p in policies if p["task"] == t], metrics["per_task"][t]) for t in tasks]
    panels += [("pooled over tasks", policies, metrics["pooled"])]
    fig, axes = _subplots(1, len(panels), figsize=(4.2 * len(panels), 4.2), squeeze=False)
    lineages = sorted({p["lineage"] for p in policies})
    colors = {lin: TAB10(i % 10) for i, lin in enumerate(lineages)}
    markers = {t: "osD^vP*X"[i % 8] for i, t in enumerate(tasks)}
    for ax, (title, rows, m) in zip(axes[0], panels, strict=True):
        rows = [p for p in rows if p["pred_rate"] is not None]
        for p in rows:
            x, y = p["true_rate"], p["pred_rate"]
            xe = [[x - p["true_ci"][0]], [p["true_ci"][1] - x]]
            ye = [[y - p["pred_ci"][0]], [p["pred_ci"][1] - y]] if None not in p["pred_ci"] else None
            ax.errorbar(x, y, xerr=xe, yerr=ye, fmt=markers.get(p["task"], "o"), color=colors[p["lineage"]],
                        ms=5, alpha=0.8, elinewidth=0.7, capsize=0)
        ax.plot([0, 1], [0, 1], ls="--", color="grey", lw=0.8)
        xs, ys = np.array([p["true_rate"] for p in rows]), np.array([p["pred_rate"] for p in rows])
        if len(rows) > 1 and xs.std() > 0:
            a, b = np.polyfit(xs, ys, 1)
            ax.plot([0, 1], [b, a + b], color="black", lw=1)
        ax.set_xlim(-0.03, 1.03)
        ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel("true success (simulator)")
        ax.set_ylabel("predicted success (world model)")
        ax.set_title(f"{_tx(title)}: r={_fmt(m.get('pearson'), 2)}, MMRV={_fmt(m.get('mmrv'), 3)}", fontsize=10)
    handles = _lineage_handles(lineages, colors, marker="o", ls="")
    handles += [Line2D([], [], color="grey", marker=markers[t], ls="", label=_tx(t)) for t in tasks][:MAX_LEGEND]
    axes[0][-1].legend(handles=handles, fontsize=7, loc="lower right")
    return _png(fig)


def _lineage_handles(lineages: list[str], colors: dict, **style) -> list[Line2D]:
    """Legend entries of the first MAX_LEGEND lineages, each in its colour, and a line saying how many
    more: past them colours repeat, and a longer list would cover the panels and mislead."""
    handles = [Line2D([], [], color=colors[lin], label=_tx(lin), **style) for lin in lineages[:MAX_LEGEND]]
    if len(lineages) > MAX_LEGEND:
        handles.append(Line2D([], [], ls="", label=f"... {len(lineages) - MAX_LEGEND} more lineages"))
    return handles


def baseline_figure(policies: list[dict], tasks: list[str]) -> str | None:
    """True success against validation imitation loss (the baseline predictor), per task."""
    rows = [p for p in policies if p["val_loss"] is not None]
    if not rows:
        return None
    fig, axes = _subplots(1, len(tasks), figsize=(4.2 * len(tasks), 3.6), squeeze=False)
    for ax, t in zip(axes[0], tasks, strict=True):
        rs = [p for p in rows if p["task"] == t]
        ax.scatter([p["val_loss"] for p in rs], [p["true_rate"] for p in rs], s=14)
        ax.set_xscale("log")
        ax.set_xlabel("validation imitation loss")
        ax.set_ylabel("true success")
        ax.set_title(f"{_tx(t)}: the imitation-loss baseline", fontsize=10)
    return _png(fig)


def progress_figure(policies: list[dict], tasks: list[str], per_task: int = 4) -> str | None:
    """Each task's progress over the episode, the simulator's (solid) beside the world model's
    imagination (dashed), averaged over the episodes of a few policies spread over the true success
    rates (lowest to highest); None where the results hold no progress curves."""
    panels = []
    for t in tasks:
        rows = sorted((p for p in policies if p["task"] == t and p.get("progress_true")), key=lambda p: p["true_rate"])
        if rows:
            pick = sorted({round(i * (len(rows) - 1) / max(per_task - 1, 1)) for i in range(per_task)})
            panels.append((t, [rows[i] for i in pick]))
    if not panels:
        return None
    fig, axes = _subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4), squeeze=False)
    for ax, (t, rows) in zip(axes[0], panels, strict=True):
        for k, p in enumerate(rows):
            c = f"C{k}"
            label = _tx(f"{p['name'].removeprefix(t + '/')} (true {p['true_rate']:.2f})")
            ax.plot(np.array(p["progress_true"], float), color=c, label=label)
            ax.plot(np.array(p["progress_imagined"], float), color=c, linestyle="--")  # None (no episode) -> NaN
        ax.set(title=f"{_tx(t)}: true (solid), imagined (dashed)", xlabel="step", ylabel="mean progress",
               ylim=(-0.05, 1.05))
        ax.legend(fontsize=6, loc="upper left")
    return _png(fig)


def rank_figure(policies: list[dict], tasks: list[str]) -> str:
    """True rank against predicted rank per task (a perfect ranking lies on the diagonal)."""
    fig, axes = _subplots(1, len(tasks), figsize=(4.2 * len(tasks), 4), squeeze=False)
    for ax, t in zip(axes[0], tasks, strict=True):
        rs = [p for p in policies if p["task"] == t]
        rs = [p for p in rs if p["pred_rate"] is not None]
        if not rs:
            ax.set_title(f"{_tx(t)}: no finite predicted rate", fontsize=10)
            continue
        tr, pr = rank([p["true_rate"] for p in rs]), rank([p["pred_rate"] for p in rs])
        ax.scatter(tr, pr, s=14)
        ax.plot([1, len(rs)], [1, len(rs)], ls="--", color="grey", lw=0.8)
        ax.set_xlabel("true rank (1 = worst)")
        ax.set_ylabel("world model's rank")
        ax.set_title(f"{_tx(t)}: ranks", fontsize=10)
    return _png(fig)


def decision_figure(decision: dict) -> str:
    """The decision analysis (experiments.evaluate.decision_analysis's dict) as a PNG data URI: per true gap, the
    chance of picking the truly better policy against episodes per policy, the binomial model's curve and the
    resampled pairs' points."""
    fig, ax = _subplots(figsize=(5.5, 3.8))
    eps = decision["episodes"]
    for i, (g, curve) in enumerate(decision["model"].items()):
        c = TAB10(i)
        if curve:
            ax.plot(eps, curve, color=c, label=f"binomial model, gap {float(g):.0%}")
        res = decision["resampled"].get(g)
        if res:
            ax.plot(eps, res, "o", color=c, ms=5, label=f"resampled ({decision['pairs'][g]} pairs), gap {float(g):.0%}")
    ax.set_xscale("log")
    ax.axhline(0.5, color="grey", lw=0.8, ls="--")  # a coin's choice
    shown = [v for curve in (*decision["model"].values(), *decision["resampled"].values()) if curve for v in curve]
    ax.set_ylim(min(0.45, min(shown, default=0.45) - 0.03), 1.01)  # resampled pairs may pick worse than a coin
    ax.set_xlabel("episodes per policy in the world model")
    ax.set_ylabel("P(pick the truly better policy)")
    ax.set_title(f"decision analysis at alignment {_fmt(decision['alignment'], 2)}", fontsize=10)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    else:  # one policy a task, or none read: no pair to decide between and no alignment to model
        ax.text(0.5, 0.5, "no pairs of policies to decide between", ha="center", va="center", transform=ax.transAxes)
    ax.grid(alpha=0.3)
    return _png(fig)


def animation(real: np.ndarray, imagined: np.ndarray, every: int = 2) -> str:
    """An animated WebP (data URI; a sixth of a GIF's size): real | imagined side by side, every
    `every`-th frame at the control rate's pace."""
    n = min(len(real), len(imagined))
    gap = np.full((real.shape[1], 2, 3), 255, np.uint8)
    frames = [Image.fromarray(np.concatenate([real[t], gap, imagined[t]], axis=1)) for t in range(0, n, every)]
    buf = io.BytesIO()
    frames[0].save(buf, format="WEBP", save_all=True, append_images=frames[1:], duration=50 * every, loop=0,
                   quality=80, method=4)
    return "data:image/webp;base64," + base64.b64encode(buf.getvalue()).decode()


def strip_figure(panel: dict, times=(0, 8, 16, 24, 32, 48)) -> str:
    """The controllability panel: one start, each program; rows real and imagined at several times."""
    progs = sorted(panel)
    times = [t for t in times if t < len(panel[progs[0]]["real"])]
    fig, axes = _subplots(2 * len(progs), len(times), figsize=(1.3 * len(times), 1.35 * 2 * len(progs)),
                             squeeze=False)
    for r, p in enumerate(progs):
        for k, kind in enumerate(("real", "imagined")):
            for c, t in enumerate(times):
                ax = axes[2 * r + k, c]
                ax.imshow(panel[p][kind][t])
                ax.set_xticks([])
                ax.set_yticks([])
                if c == 0:
                    ax.set_ylabel(f"{p}\n{kind}", fontsize=6)
                if r == 0 and k == 0:
                    ax.set_title(f"t={t}", fontsize=7)
    fig.tight_layout()
    return _png(fig)


# ---- verdicts ------------------------------------------------------------------------------------------

def verdicts(policies: list[dict], tasks: list[str]) -> list[dict]:
    """The proprioception ablation and the encoder A/B: the final checkpoints of two lineages, which
    one the world model prefers and which one is truly better."""
    pairs = [("proprioception", "conv_proprio", "conv_noproprio"), ("encoder", "conv_noproprio", "vit_noproprio")]
    out = []
    for t in tasks:
        final = {}
        for p in policies:
            if p["task"] == t and p["step"] is not None and p["step"] >= final.get(p["lineage"], {}).get("step", -1):
                final[p["lineage"]] = p
        for what, a, b in pairs:
            if a not in final or b not in final:
                continue
            pa, pb = final[a], final[b]
            if pa["pred_rate"] is None or pb["pred_rate"] is None:
                pred = "n/a (a prediction is undefined)"
            else:
                pred = a if pa["pred_rate"] > pb["pred_rate"] else b if pb["pred_rate"] > pa["pred_rate"] else "tie"
            true = a if pa["true_rate"] > pb["true_rate"] else b if pb["true_rate"] > pa["true_rate"] else "tie"
            overlap = pa["true_ci"][0] <= pb["true_ci"][1] and pb["true_ci"][0] <= pa["true_ci"][1]
            out.append({"task": t, "comparison": what, "a": pa["name"], "b": pb["name"], "true": [pa["true_rate"],
                        pb["true_rate"]], "pred": [pa["pred_rate"], pb["pred_rate"]], "world_model_prefers": pred,
                        "truly_better": true,
                        # None: nothing to agree on (a prediction undefined, or the two truly tie)
                        "agree": None if pred.startswith("n/a") or true == "tie" else pred == true,
                        "true_intervals_overlap": overlap})
    return out


AGREE = {True: ("yes", "agree"), False: ("no", "disagree"), None: ("n/a", "n/a")}


# ---- the documents ------------------------------------------------------------------------------------

def _metrics_table(metrics: dict) -> list[list[str]]:
    """Rate-level statistics of one set of policies beside the world model's every read-out and the
    proxy's; with an ensemble's, each member's alone beside them."""
    members = metrics.get("members", {})
    k = len(next(iter(members.values()))) if members else 0
    readouts = metrics.get("readouts", {})
    rows = [["statistic", f"ensemble of {k} world models" if k else "world model",
             *[f"read-out: {r}" for r in readouts], "imitation-loss proxy"]]
    if k:
        rows[0].insert(2, "each model alone: mean (min..max)")
    base = metrics.get("baseline", {})
    for s in HEADLINE:
        val = _fmt(metrics.get(s))
        if s == "pearson":
            ci, bs = metrics.get("pearson_ci", [None, None]), metrics.get("pearson_ci_bootstrap", [None, None])
            val += (f" (Fisher {_fmt(ci[0], 2)}..{_fmt(ci[1], 2)}; bootstrap of initial states "
                    f"{_fmt(bs[0], 2)}..{_fmt(bs[1], 2)})")
        row = [s, val, *[_fmt(r.get(s)) if s in r else "-" for r in readouts.values()],
               _fmt(base.get(s)) if s != "alignment" else "-"]
        if k:
            each = [v for v in members.get(s, ()) if v is not None and not math.isnan(v)]  # NaN: null in JSON
            row.insert(2, f"{_fmt(metrics['members_mean'][s])} ({_fmt(min(each), 2)}..{_fmt(max(each), 2)})"
                       if each else "-")
        rows.append(row)
    return rows


def _models_phrase(res: dict, code, capital: bool = False) -> str:
    """'world model X', or 'an ensemble of K world models (their mean probability): X, Y, Z'."""
    runs = res["world_model"].get("runs") or [res["world_model"]["run"]]
    if len(runs) == 1:
        out = f"world model {code(runs[0])}"
    else:
        out = f"an ensemble of {len(runs)} world models (their mean probability): {', '.join(code(r) for r in runs)}"
    return out[0].upper() + out[1:] if capital else out


def _policy_table(rows: list[dict]) -> list[list[str]]:
    out = [["policy", "lineage", "step", "true (95% CI)", "predicted (95% CI)", "thresholded", "alignment",
            "val loss"]]
    for p in sorted(rows, key=lambda r: (r["lineage"], r["step"] or 0)):
        out.append([p["name"], p["lineage"], _fmt(p["step"]),
                    f"{p['true_rate']:.2f} ({p['true_ci'][0]:.2f}-{p['true_ci'][1]:.2f})",
                    f"{_fmt(p['pred_rate'], 2)} ({_fmt(p['pred_ci'][0], 2)}-{_fmt(p['pred_ci'][1], 2)})",
                    _fmt(p["pred_rate_thresholded"], 2), _fmt(p["alignment"], 2), _fmt(p["val_loss"])])
    return out


PLUGIN_NOTE = ("Each plug-in beside the task's other policies: its true and predicted success with their 95% "
               "intervals (episodes), the error, and its place when the task's policies are ordered by true and by "
               "predicted success (1: the best; ties share the better place). The same read-out applied to the "
               "plug-in's simulated episodes splits the error in two: predicted minus that reading is imagination's "
               "part (the world model plays the policy otherwise than the simulator), that reading minus the true "
               "rate the read-out's (the judge does not recognise what the policy did); the larger part of a "
               "prediction outside the true interval names where it lies. The judge learns from imagined episodes, "
               "so it may read true episodes lower or higher across the board: compare with the task's other "
               "policies' readings in results.json (pred_rate_on_truth). A task ranked by its rule (the geometric "
               "read-out: results.json's geometric_ranks) has no such reading, as the judge's reading of the "
               "simulated episodes is not the rule's: n/a there.")


def error_parts(p: dict, ruled=()) -> tuple[float, float] | None:
    """(imagination's part, the read-out's part) of a policy row's error pred_rate - true_rate: pred_rate -
    pred_rate_on_truth and pred_rate_on_truth - true_rate (they sum to the error); None where either rate
    was not read, or where the row's task is among `ruled` (ranked by the geometric read-out, whose reading of
    the simulated episodes pred_rate_on_truth is not)."""
    pred, seen = p.get("pred_rate"), _on_truth(p, ruled)
    if _missing(pred) or _missing(seen):
        return None
    return pred - seen, seen - p["true_rate"]


def _on_truth(p: dict, ruled=()):
    """A policy row's reading of its simulated episodes by the read-out it is ranked by; None where its task is
    among `ruled` (ranked by the geometric read-out, which results.json's pred_rate_on_truth is not)."""
    return None if p.get("task") in ruled else p.get("pred_rate_on_truth")


def error_source(p: dict, ruled=()) -> str:
    """Where a policy row's prediction outside its true interval goes wrong: "imagination" or "read-out",
    whichever part of the error (error_parts) is larger; "-" for a prediction inside the interval, "n/a" where
    either rate was not read (or its task is among `ruled`, error_parts)."""
    lo, hi = p["true_ci"]
    if _missing(p.get("pred_rate")):
        return "n/a"
    if lo <= p["pred_rate"] <= hi:
        return "-"
    parts = error_parts(p, ruled)
    if parts is None:
        return "n/a"
    return "imagination" if abs(parts[0]) > abs(parts[1]) else "read-out"


def plugin_table(policies: list[dict], ruled=()) -> list[list[str]] | None:
    """Per plug-in and task: true and predicted rate with intervals (the true one marked where some of its
    simulated episodes went non-finite: their outcomes are doubtful), the error, the read-out of its simulated
    episodes, the error's two parts (error_parts) and where it lies (error_source), and the plug-in's place among
    the task's policies by true and by predicted rate; None where no policy is a plug-in. ruled: the tasks
    ranked by the geometric read-out (results.json's world_model.geometric_ranks)."""
    mine = [p for p in policies if p.get("kind") == "plugin"]
    if not mine:
        return None

    def place(p, key):
        others = [q[key] for q in policies if q["task"] == p["task"] and not _missing(q[key])]
        return "n/a" if _missing(p[key]) else str(1 + sum(v > p[key] for v in others))

    rows = [["plug-in", "task", "true (95% CI)", "predicted (95% CI)", "|predicted - true|", "inside the true interval",
             "read from its simulated episodes", "error: imagination + read-out", "where the error lies",
             "place by true / predicted"]]
    for p in sorted(mine, key=lambda r: (r["name"], r["task"])):
        n = sum(q["task"] == p["task"] for q in policies)
        err = None if _missing(p["pred_rate"]) else abs(p["pred_rate"] - p["true_rate"])
        inside = "n/a" if err is None else "yes" if p["true_ci"][0] <= p["pred_rate"] <= p["true_ci"][1] else "no"
        bad = p.get("nonfinite_episodes") or 0
        doubt = f", {bad} of {p['n']} episodes non-finite" if bad else ""
        rows.append([p["name"], p["task"], f"{p['true_rate']:.2f} ({p['true_ci'][0]:.2f}-{p['true_ci'][1]:.2f}{doubt})",
                     f"{_fmt(p['pred_rate'], 2)} ({_fmt(p['pred_ci'][0], 2)}-{_fmt(p['pred_ci'][1], 2)})",
                     _fmt(err, 2), inside, _fmt(_on_truth(p, ruled), 2), _parts_text(error_parts(p, ruled)),
                     error_source(p, ruled),
                     f"{place(p, 'true_rate')} / {place(p, 'pred_rate')} of {n}"])
    return rows


def _parts_text(parts) -> str:
    return "n/a" if parts is None else f"{parts[0]:+.2f} {parts[1]:+.2f}"


def _html_table(rows) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in rows[0])
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows[1:])
    return f"<table><tr>{head}</tr>{body}</table>"


def unlearned_warning(res: dict) -> str:
    """A warning naming the evaluated tasks missing from the world model's training data ("" if none):
    its predictions there are not those of a model that learned the task."""
    learned = res["world_model"].get("train_tasks")
    unseen = [t for t in res["tasks"] if learned is not None and t not in learned]
    if not unseen:
        return ""
    return (f"The world model never saw {', '.join(unseen)} in training (it learned {', '.join(learned) or 'none'}): "
            "its predictions there are guesses about a task it does not know.")


def _tasks_by_rule(res: dict) -> dict:
    """{what a task's policies are ranked by: [its tasks]} from results.json's world_model.rule ({} in
    results written without it)."""
    groups = {}
    for t, rule in (res["world_model"].get("rule") or {}).items():
        if t in res["tasks"]:
            groups.setdefault(rule, []).append(t)
    return groups


def ranked_by(res: dict) -> str:
    """A sentence saying what ranks each task's policies ("" in results written without it), and, for the
    tasks the geometric read-out ranks, that it starts from the simulator's first state and applies the
    task's own rule, so that its figures are not those of the learned network's reading of its frames."""
    groups = _tasks_by_rule(res)
    if not groups:
        return ""
    said = "; ".join(f"{', '.join(ts)} by {rule if rule.startswith('the ') else 'the ' + rule}"
                     for rule, ts in groups.items())
    ruled = ruled_tasks(res)
    return (f"Ranked: {said}." + (f" The geometric read-out ({', '.join(ruled)}) moves the robot by models of its "
                                  "motion from the simulator's first state and decides success by the task's own "
                                  "rule on the predicted states: it is a model of the robot and its grasp, not the "
                                  "learned network's reading of the frames it imagines." if ruled else ""))


def md_text(s: str) -> str:
    """s as literal Markdown text: each character Markdown reads as syntax (a link's brackets and
    parentheses, emphasis, code, HTML's angle brackets) escaped with a backslash, so that a policy's name
    cannot open a link or a tag."""
    return re.sub(r"([\\`*_\[\]()<>#!|~$])", r"\\\1", s)


def md_table(rows) -> str:
    """A Markdown table of rows of strings, the first row the header; "|" in a cell is escaped."""
    # a policy's name may hold "|", a line break or an HTML tag's "<" ("<=" in a target stays as it is)
    cell = lambda c: re.sub(r"<(?=[A-Za-z/!?])", "&lt;", c.replace("|", "\\|").replace("\n", " "))  # noqa: E731
    lines = ["| " + " | ".join(map(cell, rows[0])) + " |", "|" + "---|" * len(rows[0])]
    lines += ["| " + " | ".join(map(cell, r)) + " |" for r in rows[1:]]
    return "\n".join(lines)


def _ci(x, ci, digits=2) -> str:
    return f"{_fmt(x, digits)} [{_fmt(ci[0], digits)}, {_fmt(ci[1], digits)}]"


def _signed(x, digits=2) -> str:
    """x as _fmt writes it, but a non-zero x that would read 0.00 with one significant digit, so that an
    interval said to lie above or below 0 is not printed touching it."""
    if not _missing(x) and x != 0 and round(x, digits) == 0:
        return f"{x:.1g}"
    return _fmt(x, digits)


def _difference_ci(x, ci, digits=2) -> str:
    """A difference and its interval (_ci), each bound written with its sign kept (_signed)."""
    return f"{_fmt(x, digits)} [{_signed(ci[0], digits)}, {_signed(ci[1], digits)}]"


def _defined_tasks(block: dict, tasks) -> list[str]:
    """The tasks where a within-task block's (a predictor's or a difference's) Pearson r is defined (every
    task where the block gives no per-task figures)."""
    per = block.get("per_task")
    return list(tasks) if per is None else [t for t in tasks if not _missing(per.get(t, {}).get("pearson"))]


def _coverage(w: dict, tasks, who=("world_model", "proxy")) -> str:
    """An empty string where every predictor's mean covers every task, else which tasks each mean is
    over: a mean over tasks skips those where the statistic is undefined, so two means may cover
    different tasks."""
    cover = {k: _defined_tasks(w[k], tasks) for k in who}
    if all(len(c) == len(tasks) for c in cover.values()):
        return ""
    label = {"world_model": "the world model's", "proxy": "the proxy's"}
    over = lambda ts: " and ".join(ts) or "no task"  # noqa: E731
    parts = [f"{label[k]} over {over(c)}" for k, c in cover.items()]
    if len(who) > 1:
        parts.append(f"the difference over {over(_defined_tasks(w['difference']['proxy'], tasks))}")
    return " (means over the tasks where Pearson r is defined: " + "; ".join(parts) + ")"


def verdict(res: dict) -> str:
    """One sentence: does the world model rank policies within a task better than the imitation-loss
    proxy, by the mean within-task Pearson r and the paired bootstrap of the difference."""
    w = res["metrics"]["within_task"]
    wm, px, diff = w["world_model"], w["proxy"], w["difference"]["proxy"]
    tasks = w["tasks"]
    ruled = ruled_tasks(res)
    by = f" (by its geometric read-out on {', '.join(ruled)})" if ruled else ""
    if _missing(wm["mean"]["pearson"]):
        counts = ", ".join(f"{t} {sum(p['task'] == t for p in res['policies'])}" for t in tasks)
        return (f"No within-task ranking to judge: a task's Pearson r needs at least {MIN_CORRELATED} of its "
                f"policies, whose true and predicted rates both vary (policies per task: {counts}).")
    if _missing(px["mean"]["pearson"]):
        return (f"The imitation-loss proxy has no within-task figure here (it needs at least {MIN_CORRELATED} "
                "policies of a task with a validation loss and differing true rates; plug-ins have none): the "
                f"world model{by} alone ranks at a "
                f"mean within-task Pearson r {_ci(wm['mean']['pearson'], wm['mean_ci']['pearson'])} (95% interval "
                f"resampling {w['resamples']}){_coverage(w, tasks, ('world_model',))}.")
    both = _defined_tasks(diff, tasks)
    if not both:
        return (f"The world model and the imitation-loss proxy have no task where both rank (world model: "
                f"{', '.join(_defined_tasks(wm, tasks))}; proxy: {', '.join(_defined_tasks(px, tasks))}): their "
                "difference is undefined. Mean within-task Pearson r "
                f"{_ci(wm['mean']['pearson'], wm['mean_ci']['pearson'])}"
                f" against {_ci(px['mean']['pearson'], px['mean_ci']['pearson'])}, over different tasks.")
    ahead = [t for t in both if (diff["per_task_ci"][t]["pearson"][0] or -1) > 0]
    behind = [t for t in both if (diff["per_task_ci"][t]["pearson"][1] or 1) < 0]
    over, covered = "", w
    if "shared" in diff:  # the difference compares fewer policies than the world model's own figure
        sh = diff["shared"]
        wm, px = sh["first"], sh["other"]
        covered = {**w, "world_model": wm, "proxy": px} if "per_task" in wm else w
        over = (f" over the {sh['policies']} of {sh['of']} policies both rank (the proxy ranks only checkpoints "
                "with a validation loss, the world model no policy whose imagination diverged)")
    lo = diff["mean_ci"]["pearson"][0]
    hi = diff["mean_ci"]["pearson"][1]
    if lo is not None and lo > 0:
        head = f"The world model{by} ranks policies within a task better than the imitation-loss proxy"
    elif hi is not None and hi < 0:
        head = f"The world model{by} ranks policies within a task worse than the imitation-loss proxy"
    else:
        head = f"Within a task, the world model's ranking{by} cannot be told apart from the imitation-loss proxy's"
    return (f"{head}{over}: mean within-task Pearson r {_ci(wm['mean']['pearson'], wm['mean_ci']['pearson'])} against "
            f"{_ci(px['mean']['pearson'], px['mean_ci']['pearson'])} (difference "
            f"{_difference_ci(diff['mean']['pearson'], diff['mean_ci']['pearson'])}; 95% intervals resampling "
            f"{w['resamples']}){_coverage(covered, tasks)}. Per task, the difference's interval lies above 0 in "
            f"{len(ahead)} of {len(both)}"
            f"{' (' + ', '.join(ahead) + ')' if ahead else ''} and below 0 in {len(behind)}"
            f"{' (' + ', '.join(behind) + ')' if behind else ''}.")


def better_readout_note(res: dict) -> str | None:
    """A sentence naming each other read-out of the same imagined episodes that ranks policies within a
    task better than the one the world model is ranked by (the paired difference's interval of the mean
    within-task Pearson r lies below 0), with how to rank by it; None where none does."""
    w = res["metrics"]["within_task"]
    ranked = res.get("config", {}).get("readout", "the ranked one")
    better = [k for k in w if k.startswith("readout_") and k in w.get("difference", {})
              and not _missing(hi := w["difference"][k]["mean_ci"]["pearson"][1]) and hi < 0]
    if not better:
        return None
    parts = [f"the {k[len('readout_'):]} read-out's mean within-task Pearson r "
             f"{_ci(w[k]['mean']['pearson'], w[k]['mean_ci']['pearson'])}, the ranked read-out ({ranked}) minus it "
             f"{_ci(w['difference'][k]['mean']['pearson'], w['difference'][k]['mean_ci']['pearson'])}"
             for k in better]
    how = " or ".join("geometric_ranks=1" if k == "readout_geometric" else f"readout={k[len('readout_'):]}"
                      for k in better)
    return (f"Another read-out of the same imagined episodes ranks the policies better within a task: {'; '.join(parts)} "
            f"(paired, resampling {w['resamples']}). The evaluation ranks by it with {how}.")


UPPER = "the read-out of the true episodes"
UPPER_SECOND = "the judge2 read-out of the true episodes"
REPLAYED = "the read-out of the true actions replayed"
SIM_IMAGINED = "the simulator on the actions taken in imagination"


def _other_readouts(w: dict, res: dict | None = None) -> list[tuple[str, str]]:
    """(key, label) of the world model's read-outs other than the one it ranks by, in results' order,
    then, where measured, its read-out of the true episodes (and the second judge's), of their actions
    replayed, and the simulator's outcomes of the actions the policies took in imagination. Where res ranks
    some tasks by the geometric read-out, the true episodes' reading names the read-out it is (not the rules')."""
    upper = UPPER
    if res and ruled_tasks(res) and (readout := res.get("world_model", {}).get("readout")):
        upper = f"the {readout} read-out of the true episodes (every task's)"
    return ([(k, f"world model, {k[len('readout_'):]} read-out") for k in w if k.startswith("readout_")]
            + [(k, label) for k, label in (("on_truth", upper), ("on_truth_judge2", UPPER_SECOND),
                                           ("replayed", REPLAYED), ("sim_imagined", SIM_IMAGINED)) if k in w])


def target_status(value, target) -> str:
    """": met" or ": not met" for a figure against a preset's target (op, threshold); "" where the figure
    is undefined."""
    if _missing(value):
        return ""
    op, x = target
    return ": met" if (value >= x if op == ">=" else value <= x) else ": not met"


def within_task_table(res: dict) -> list[list[str]]:
    """The headline: each within-task statistic's mean over tasks for the world model and the proxy,
    their difference, the world model's other read-outs, its read-out applied to the simulated
    episodes themselves (where measured; with a judge that learnt from imaginations no bound on
    exact imagination: experiments.judge_study's observed bound is one) and to their actions replayed open loop (where measured: imagination without the policy
    in the loop), and the preset's target, with MMRV's floor (stats.mmrv_floor) beside its target."""
    w = res["metrics"]["within_task"]
    others = _other_readouts(w, res)
    targets = TARGETS.get(res.get("preset", ""), {})
    readout = res.get("world_model", {}).get("readout")
    groups = _tasks_by_rule(res)
    if len(groups) > 1:
        model = "world model (" + "; ".join(f"{', '.join(ts)}: {rule}" for rule, ts in groups.items()) + ")"
    elif groups:
        model = f"world model ({next(iter(groups))})"
    else:
        model = f"world model ({readout} read-out)" if readout else "world model"
    rows = [["statistic (mean over tasks)", model,
             "imitation-loss proxy", "world model - proxy (paired, over the policies both score)",
             *[label for _, label in others], f"target ({res.get('preset') or 'none'} preset)"]]
    floor = res["metrics"].get("mmrv_floor")
    for k in w["world_model"]["mean"]:
        tgt = targets.get(k)
        goal = f"{tgt[0]} {tgt[1]}{target_status(w['world_model']['mean'][k], tgt)}" if tgt else "-"
        # MMRV's floor: what the truth's own sampling noise leaves to any predictor
        if k == "mmrv" and floor and not _missing(floor["mean"]):
            goal = (f"{goal} " if tgt else "") + f"(a perfect predictor: {floor['mean']:.3f})"
        px = "-" if k == "alignment" else _ci(w["proxy"]["mean"][k], w["proxy"]["mean_ci"][k])
        df = "-" if k == "alignment" else _ci(w["difference"]["proxy"]["mean"][k], w["difference"]["proxy"]["mean_ci"][k])
        more = [_ci(w[o]["mean"][k], w[o]["mean_ci"][k]) for o, _ in others]
        rows.append([LABELS.get(k, k), _ci(w["world_model"]["mean"][k], w["world_model"]["mean_ci"][k]), px, df,
                     *more, goal])
    return rows


def per_task_table(res: dict, key: str = "within_task") -> list[list[str]]:
    """Every task's within-task statistics (95% bootstrap intervals), the world model's row above the
    proxy's, its other read-outs' and, where measured, its read-out's of the true episodes."""
    w = res["metrics"][key]
    stats = list(w["world_model"]["mean"])
    rows = [["task", "predictor", *[LABELS.get(k, k) for k in stats]]]
    who_label = [("world_model", "world model"), ("proxy", "imitation-loss proxy")]
    who_label += _other_readouts(w, res)
    for t in w["tasks"]:
        for who, label in who_label:
            rows.append([t, label, *[_ci(w[who]["per_task"][t][k], w[who]["per_task_ci"][t][k])
                                     if not (who == "proxy" and k == "alignment") else "-" for k in stats]])
    return rows


def _picks_the_best(x: dict) -> str:
    """A selection row's verdict: yes, within the best's interval, no; for a pick among equally rated
    checkpoints, the shares of them that are each."""
    if x.get("tied", 1) > 1:
        return (f"{x['tied']} rated equally: {x['exact']:.0%} of them the best, {x['within_ci']:.0%} within its "
                "interval")
    return "yes" if x["exact"] else "within the best's interval" if x["within_ci"] else "no"


def selection_table(sel: dict) -> list[list[str]]:
    """The checkpoint selection (experiments.stats.checkpoint_selection's dict) as rows of strings, a header first:
    per task and lineage, the step the world model picks, the truly best step, their true rates and the regret."""
    rows = [["task", "lineage", "world model picks step", "truly best step", "true rate of the pick",
             "best true rate", "regret", "picks the best"]]
    for x in sel["lineages"]:
        picked = f"{x['picked_step']} (one of {x['tied']} rated equally)" if x.get("tied", 1) > 1 else str(x["picked_step"])
        best = (f"{x['best_step']} (one of {x['best_tied']} truly equal)" if x.get("best_tied", 1) > 1
                else str(x["best_step"]))
        rows.append([x["task"], x["lineage"], picked, best, f"{x['picked_true']:.2f}",
                     f"{x['best_true']:.2f}", f"{x['regret']:.2f}",
                     _picks_the_best(x)])
    return rows


def selection_figure(policies: list[dict], tasks: list[str]) -> str | None:
    """True and predicted success against training step, one panel per task, one colour per lineage."""
    rows = [p for p in policies if p["step"] is not None and p["pred_rate"] is not None]
    if not rows:
        return None
    fig, axes = _subplots(1, len(tasks), figsize=(4.6 * len(tasks), 3.8), squeeze=False)
    lineages = sorted({p["lineage"] for p in rows})
    colors = {lin: TAB10(i % 10) for i, lin in enumerate(lineages)}
    for ax, t in zip(axes[0], tasks, strict=True):
        for lin in lineages:
            rs = sorted((p for p in rows if p["task"] == t and p["lineage"] == lin), key=lambda p: p["step"])
            if not rs:
                continue
            steps = [p["step"] for p in rs]
            ax.plot(steps, [p["true_rate"] for p in rs], "-o", color=colors[lin], ms=3)
            ax.plot(steps, [p["pred_rate"] for p in rs], "--x", color=colors[lin], ms=4)
        ax.set_xscale("log")
        ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel("training step of the checkpoint")
        ax.set_ylabel("success")
        ax.set_title(f"{_tx(t)}: true (solid) and predicted (dashed)", fontsize=10)
    handles = _lineage_handles(lineages, colors)  # every panel's
    handles += [Line2D([], [], color="grey", marker="o", ms=3, label="true"),
                Line2D([], [], color="grey", ls="--", marker="x", ms=4, label="predicted")]
    axes[0][-1].legend(handles=handles, fontsize=6, loc="lower right")
    return _png(fig)


CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:13px;margin:0.5em 0 1.5em}td,th{border:1px solid #ccc;padding:3px 7px}
th{background:#f3f3f3}img{max-width:100%}img.anim{width:300px;image-rendering:pixelated}.vid{display:inline-block;margin:6px;text-align:center;font-size:12px}
.ok{color:#070}.bad{color:#b00}.warn{color:#b00;font-weight:bold}code{background:#f3f3f3;padding:1px 4px}"""


CUT_SHORT = ("Cut short: a world model stopped at its safety time limit before its budget of steps, or one whose "
             "training has not finished a command (no train_status.json); these figures are not those of the "
             "preset (rerun its training to finish it).")


def partial_note(res: dict) -> str:
    """The tasks a partial results.json lacks and, where the evaluation's safety time limit stopped it,
    how to finish them ("" where every task was evaluated)."""
    if not res.get("missing_tasks"):
        return ""
    note = f"Partial: tasks {', '.join(res['missing_tasks'])} were not evaluated; every statistic below leaves them out."
    if cut := res.get("cut_short"):
        limit = cut.get("max_minutes") if isinstance(cut, dict) else None
        setting = f" (max_minutes={limit:g})" if isinstance(limit, (int, float)) else ""
        note += f" The evaluation stopped at its safety time limit{setting}: rerun the same command to evaluate them."
    return note


def selection_summary(sel: dict) -> str:
    """One paragraph on checkpoint selection (results.json's checkpoint_selection), saying how many of
    its picks were made among checkpoints the world model rated equally."""
    if not sel["n"]:
        if sel.get("unread"):
            return (f"No checkpoint of the {sel['unread']} training runs of two or more could be read by the world "
                    "model (its imagination diverged on every one): no selection to judge.")
        return "No training run has two or more checkpoints here."
    tied = sum(x.get("tied", 1) > 1 for x in sel["lineages"])
    runs = "training run" if sel["n"] == 1 else "training runs"
    return (f"Over {sel['n']} {runs} (task x lineage), the world model's highest-rated checkpoint is the "
            f"truly best in {_fmt_share(sel['exact_share'])}, within the best one's 95% interval in "
            f"{_fmt_share(sel['within_ci_share'])}; mean regret {_fmt(sel['mean_regret'], 2)} of true success."
            + (f" In {tied} of them the world model rated several checkpoints equally highest: each such pick is "
               "scored as one drawn at random among them." if tied else ""))


def _fmt_share(x) -> str:
    return "n/a" if _missing(x) else f"{x:.0%}"


def _selection_html(res: dict, policies: list[dict], tasks: list[str]) -> list[str]:
    sel = res.get("checkpoint_selection")
    if sel is None:
        return []
    fig = selection_figure(policies, tasks)
    return ([f"<p>{html.escape(selection_summary(sel))}</p>"] + ([f"<img src='{fig}'>"] if fig else [])
            + ([_html_table(selection_table(sel))] if sel["n"] else []))


def _selection_md(res: dict) -> str:
    sel = res.get("checkpoint_selection")
    if sel is None:
        return "n/a"
    return selection_summary(sel) + ("\n\n" + md_table(selection_table(sel)) if sel["n"] else "")


TIMING_COLUMNS = (("stage", "stage"), ("wall_s", "wall s"), ("compile_s", "compiling s"),
                  ("programs_compiled", "programs compiled"), ("frames_generated", "frames"),
                  ("frames_per_s", "frames/s"), ("end_to_end_frames_per_s", "frames/s end to end"),
                  ("train_steps", "training steps"), ("episodes", "episodes"), ("gpus", "GPUs"),
                  ("cores", "CPU processes"), ("device", "device"))


def fidelity_table(res: dict) -> list[list[str]] | None:
    """Per task and horizon: the imagined frame's PSNR against the simulated episode's, the first
    true frame's (copy-first), their difference, and the RMS gap between the policy's actions in
    imagination and in the simulator at that step (the step's action, which led to its frame: at step
    1 the action on the true first frame); None where the results hold none."""
    imag = res.get("imagination")
    if not imag:
        return None
    rows = [["task", "step", "imagined frame PSNR (dB)", "copy-first PSNR (dB)", "gain over copy-first (dB)",
             "action gap of the step's action (RMS)"]]
    for t, f in imag.items():
        for k, h in enumerate(f["horizons"]):
            rows.append([t, str(h), _fmt(f["frame_psnr"][k], 2), _fmt(f["copy_first_psnr"][k], 2),
                         _fmt(f["gain_over_copy_first_db"][k], 2), _fmt(f["action_gap"][k], 3)])
    return rows


def family_table(res: dict) -> list[list[str]] | None:
    """Per task and counterfactual family (a checkpoint degraded at several levels, with its base):
    Pearson r of predicted against true success and the mean |error| by the ranked read-out, and r by
    each read-out; None where the results hold no family."""
    fam = res.get("families")
    if not fam or not fam["families"]:
        return None
    by = fam.get("by_readout", {})
    rows = [["task", "family", "policies", "true range", "Pearson r", "r of a perfect predictor",
             "mean |predicted - true|", *[f"r, {r} read-out" for r in by]]]
    for k, f in enumerate(fam["families"]):
        rows.append([f["task"], f["family"], str(f["n"]), f"{f['true_range'][0]:.2f}-{f['true_range'][1]:.2f}",
                     _fmt(f["pearson"], 2), _fmt(f.get("pearson_ceiling"), 2), _fmt(f["mean_abs_error"], 2),
                     *[_fmt(b["families"][k]["pearson"], 2) for b in by.values()]])
    rows.append(["mean", "", "", "", _fmt(fam["mean_pearson"], 2), _fmt(fam.get("mean_pearson_ceiling"), 2),
                 _fmt(fam["mean_abs_error"], 2), *[_fmt(b["mean_pearson"], 2) for b in by.values()]])
    return rows


# a rank violation's readings by the ranked read-out (the simulator's outcome of its imagined actions is none)
JUDGE_READINGS = ("replayed", "on_truth")


def ruled_tasks(res: dict) -> tuple:
    """The tasks results ranked by the geometric read-out (world_model.geometric_ranks; none in older results)."""
    return tuple(res.get("world_model", {}).get("geometric_ranks") or ())


def _violation_reading(p: dict, key: str, task: str, ruled) -> float | None:
    """A rank violation row's reading `key`; None for a judge's reading (JUDGE_READINGS) on a task in `ruled`,
    which its rule ranks, not the judge."""
    return None if task in ruled and key in JUDGE_READINGS else p.get(key)


def violation_table(res: dict) -> list[list[str]] | None:
    """Per task, the policies that carry its MMRV (results.json's rank_violations): each policy's
    term charged to the policy it is most mis-ordered with; None where the results hold none (older
    results) or no task has a violation."""
    viol = res.get("rank_violations")
    if not viol or not any(v["policies"] for v in viol.values()):
        return None
    ruled = ruled_tasks(res)
    # a reading kept where some row shows it (_violation_reading: the judge's only on tasks it ranks)
    extra = [(k, label) for k, label in (("replayed", "read on its true actions replayed"),
                                         ("on_truth", "read on its true episodes"),
                                         ("imagined_in_sim", "simulated on its imagined actions"))
             if any(_violation_reading(p, k, t, ruled) is not None for t, v in viol.items() for p in v["policies"])]
    rows = [["task", "MMRV", "policy", "true", "predicted", *[label for _, label in extra], "share of the task's MMRV",
             "policies mis-ordered with it", "action gap (RMS; the task's median)"]]
    def shown(key):  # a column where some row has its reading
        return any(p.get(key) is not None for v in viol.values() for p in v["policies"])

    largest = any(p.get("action_gap_largest") for v in viol.values() for p in v["policies"])
    closure, near = shown("closure_bias"), shown("failed_peak_progress")
    rows[0] += ["largest in one dimension"] if largest else []
    rows[0] += ["right hand's closure, imagined minus true (mean; RMS)"] if closure else []
    rows[0] += [NEAR_MISS_COLUMN] if near else []
    for t, v in viol.items():
        gaps = [g for p in res.get("policies", []) if p["task"] == t and (g := p.get("action_gap")) is not None]
        median = f" ({_fmt(float(np.median(gaps)), 3)})" if gaps else ""
        for k, p in enumerate(v["policies"]):
            read = [_violation_reading(p, key, t, ruled) for key, _ in extra]
            rows.append([t if k == 0 else "", _fmt(v["mmrv"], 2) if k == 0 else "", p["name"],
                         _fmt(p["true_rate"], 2), _fmt(p["pred_rate"], 2), *[_fmt(r, 2) for r in read],
                         f"{100 * p['share']:.0f}%",
                         str(p["against"]), _fmt(p.get("action_gap"), 3) + median,
                         *([_largest_gap(p)] if largest else []),
                         *([f"{_fmt(p.get('closure_bias'), 3)}; {_fmt(p.get('closure_gap'), 3)}"] if closure else []),
                         *([_near_miss(p)] if near else [])])
    return rows


NEAR_MISS_COLUMN = "its failed episodes' highest true progress (1: success)"


def _near_miss(row: dict) -> str:
    """A violation row's failed_peak_progress, "none failed" where every episode succeeded, or n/a."""
    if row.get("failed_peak_progress") is not None:
        return _fmt(row["failed_peak_progress"], 2)
    return "none failed" if row.get("true_rate") == 1 else "n/a"


def _largest_gap(row: dict) -> str:
    """A violation row's largest one-dimension action gap as "rms (dimension)", or n/a."""
    g = row.get("action_gap_largest")
    if not g:
        return "n/a"
    return f"{_fmt(g['rms'], 3)} ({g['dim']})" if g["rms"] > 0 else f"{_fmt(g['rms'], 3)} (none differs)"


def loop_note(res: dict) -> str | None:
    """One sentence (results with replay=1 only): the world model's within-task figures against the
    simulator's outcomes of the actions taken in its own imagination, beside those against the truth
    and the simulator's own figures on those actions: which part of the ranking error is the model's
    reading of its loop, which the policies acting on imagined frames."""
    loop, w = res["metrics"].get("loop_actions"), res["metrics"]["within_task"]
    if loop is None or "sim_imagined" not in w:
        return None
    wm, sim = w["world_model"], w["sim_imagined"]
    r = _ci(loop["mean"]["pearson"], loop["mean_ci"]["pearson"])
    return (f"The actions the policies took in imagination, played in the simulator from the same states: the world "
            f"model reads their simulated outcomes at mean within-task Pearson {r}, "
            f"MMRV {_fmt(loop['mean']['mmrv'], 3)} (against the truth {_fmt(wm['mean']['pearson'], 2)}, MMRV "
            f"{_fmt(wm['mean']['mmrv'], 3)}); those outcomes themselves rank the policies at "
            f"{_ci(sim['mean']['pearson'], sim['mean_ci']['pearson'])}, MMRV {_fmt(sim['mean']['mmrv'], 3)}: the "
            "first is the model's own dynamics and judge on its loop, the second what acting on imagined frames "
            "instead of true ones changes.")


VIOLATION_NOTE = ("Where MMRV comes from: each policy's term (its largest rank violation, weighted by the true gap) "
                  "is charged to the policy it is most mis-ordered with, so one policy read far from its truth "
                  "shows up as the partner of many. The action gap says how far its actions on imagined frames "
                  "stray from those on true frames, beside the task's median policy, and in the one action "
                  "dimension where they stray most (a base that does not stop shows there, diluted in the mean); "
                  "the right hand's closure beside it, in imagination minus on true frames (a grasp holds "
                  "above a threshold on the closure, so a few hundredths firmer can turn a failure into a success); and how near "
                  "its failed episodes came to success in the simulator (their highest progress, where 1 is the "
                  "task's success line: near 1, its true rate turns on millimetres of the task's measure, which the "
                  "world model must imagine to that precision to rank it; at 1, its failures reached success and "
                  "left it, as a drive past its band).")


UNSEEN_NETWORKS_TITLE = ("Within-task ranking of the unseen policies that are lineages of their own "
                         "(the counterfactual families left out: the kind of policy a new user brings)")

FAMILY_NOTE = ("Counterfactual families: one checkpoint with its actions degraded by known amounts (noise, delay, "
               "a weak grip, driving scaled), beside the undegraded checkpoint. True success moves with the "
               "degradation; a world model that reads the actions must move its prediction the same way. The r "
               "of a perfect predictor is what the true rates, measured from this many episodes, allow: a "
               "family whose truth spans a few points may still be resolved.")


FIDELITY_NOTE = ("The same policy from the same start, in the simulator and in the world model: how far the "
                 "imagined episode stays with the true one (the last row of each task is its last step), and how "
                 "far the policy's actions on imagined frames drift from those it took on true ones.")


def timing_table(rows: list[dict]) -> list[list[str]]:
    """The pipeline's timing.json (experiments.pipeline): one row per stage command, and the total."""
    def cell(v):
        if isinstance(v, list):  # one figure a world model (train_steps)
            return ", ".join(cell(x) for x in v) or "-"
        return "-" if v is None else _fmt(v, 1) if isinstance(v, float) else str(v)

    out = [[label for _, label in TIMING_COLUMNS]]
    out += [[cell(r.get(k)) for k, _ in TIMING_COLUMNS] for r in rows]
    total = lambda k: sum(r[k] for r in rows if r.get(k) is not None)  # noqa: E731  (a stage cut short has no time)
    out.append(["total", cell(total("wall_s")), cell(total("compile_s")),
                *["" for _ in TIMING_COLUMNS[3:]]])
    return out


def compile_table(rows: list[dict]) -> list[list[str]] | None:
    """Per stage command, the programs that cost the most compile time (timing.json's
    `slowest_compiles`); None where no row names them."""
    out = [["stage", "program", "compiles", "compiling s"]]
    out += [[r["stage"], c["program"] + (f" (part {c['part']})" if "part" in c else ""), str(c["compiles"]),
             _fmt(c["s"], 1)]
            for r in rows for c in r.get("slowest_compiles", [])]
    return out if len(out) > 1 else None


def read_index(run: Path) -> dict | None:
    """RUN/videos/index.json (what experiments.videos wrote), or None where the run has no videos yet."""
    path = Path(run) / "videos" / "index.json"
    return json.loads(path.read_text()) if path.exists() else None


def video_links(index: dict | None) -> list[tuple[str, str]]:
    """(label, path relative to the run) of each MP4 file of `make videos` (experiments.videos's
    index.json): the policies' files, then the controllability panel's; [] without an index."""
    if index is None:
        return []
    links = [(e["policy"], "videos/" + e["file"]) for e in index["policies"]]
    if index["controllability"] is not None:
        links.append(("controllability panel", "videos/" + index["controllability"]["file"]))
    return links


def read_videos(run: Path) -> dict:
    """{key: (T+1, S, S, 3) uint8} of RUN/videos.npz (the kept real and imagined episodes and the
    controllability panel); {} where the run has none (results copied back without it)."""
    path = Path(run) / VIDEOS
    if not path.exists():
        return {}
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _ab_verdicts_html(verd: list[dict]) -> list[str]:
    """The report's section of A/B verdicts between lineages (verdicts), as HTML."""
    h = ["<h2>Ablation and A/B verdicts</h2>"]
    if not verd:
        return h + ["<p>The evaluated policies hold no conv_proprio / conv_noproprio / vit_noproprio lineages.</p>"]
    vrows = [["task", "comparison", "A", "B", "true A/B", "predicted A/B", "world model prefers", "truly better",
              "agree"]]
    vrows += [[v["task"], v["comparison"], v["a"], v["b"], f"{v['true'][0]:.2f} / {v['true'][1]:.2f}",
               f"{_fmt(v['pred'][0], 2)} / {_fmt(v['pred'][1], 2)}", v["world_model_prefers"], v["truly_better"],
               AGREE[v["agree"]][0] + (" (true intervals overlap)" if v["true_intervals_overlap"] else "")]
              for v in verd]
    return h + [_html_table(vrows)]


def _video_div(src: str, label: str) -> str:
    """One animated real-against-imagined pair (a data URI) with its label."""
    return f"<div class='vid'><img class='anim' src='{src}'><br>{html.escape(label)}</div>"


def _videos_html(run: Path, res: dict, videos: dict, mp4: list[tuple[str, str]]) -> list[str]:
    """The report's real-against-imagined episodes and controllability panel, as HTML (animated images)."""
    h = ["<h2>Real (left) and imagined (right) episodes</h2>"]
    kept = [v for v in res["videos"] if v["key"] + "/real" in videos]
    if not kept:
        h.append(f"<p>No episodes kept in {html.escape(str(run / VIDEOS))} (an evaluation with "
                 "video_policies=0, or results copied without that file).</p>")
    if mp4:
        h.append("<p>MP4 files (<code>make videos</code>): " + ", ".join(
            f"<a href='{html.escape(href)}'>{html.escape(label)}</a>" for label, href in mp4) + "</p>")
    for v in kept:
        key = v["key"]
        label = (f"{v['policy']} ep {v['episode']}: truly {'success' if v['true_success'] else 'failure'}, "
                 f"predicted {_fmt(v['pred_prob'], 2)}")
        h.append(_video_div(animation(videos[key + "/real"], videos[key + "/imagined"]), label))
    panel = {k.split("/")[1]: None for k in videos if k.startswith("controllability/")}
    if panel:
        panel = {p: {kind: videos[f"controllability/{p}/{kind}"] for kind in ("real", "imagined")} for p in panel}
        h += ["<h2>Controllability: one start, four action programs</h2>", f"<img src='{strip_figure(panel)}'>"]
        for p, v in sorted(panel.items()):
            h.append(_video_div(animation(v["real"], v["imagined"]), p))
    return h


def _timing_html(timing: list[dict], compiles: list[list[str]] | None) -> list[str]:
    """The report's pipeline timing section (timing.json's rows, and compile_table's of them), as HTML;
    empty without rows."""
    if not timing:
        return []
    h = ["<h2>Pipeline timing</h2>", "<p>Per stage command: wall seconds and the seconds spent compiling "
         "(the pipeline's own process, plus for a stage spread over GPUs the most any one of its child "
         "processes spent); frames/s end to end: the frames a data stage generated over its whole wall "
         "time.</p>", _html_table(timing_table(timing))]
    if compiles:
        h += [("<p>Where the compile time goes: per stage command, the jitted functions that took the most "
               "seconds to trace, lower and compile.</p>"), _html_table(compiles)]
    return h


RESULTS_KEYS = ("config", "engine", "device", "versions", "world_model", "tasks", "policies", "metrics", "decision",
                "videos", "timing")
ROW_KEYS = ("name", "task", "lineage", "step", "n", "true_rate", "true_ci", "pred_rate", "pred_ci",
            "pred_rate_thresholded", "alignment", "val_loss")


def read_results(run: Path) -> dict:
    """RUN/results.json, checked for what the report reads; NaN or Infinity tokens (json.dump's default)
    read as null, as experiments.evaluate writes an undefined figure. Raises ValueError naming the file
    and the field where it is not an evaluation's results."""
    path = Path(run) / "results.json"
    res = read_json(path, "a file cut short? copy it again or rerun make eval", nan_as_none=True)
    what = f"{path} is not an experiments.evaluate results.json"
    if missing := [k for k in RESULTS_KEYS if k not in res]:
        raise ValueError(f"{what}: it lacks {', '.join(missing)} (written by an older version? rerun make eval)")
    if not isinstance(res["tasks"], list) or not isinstance(res["policies"], list):
        raise ValueError(f"{what}: tasks and policies must be lists, got {type(res['tasks']).__name__} and "
                         f"{type(res['policies']).__name__}")
    if not res["tasks"]:
        missing = ", ".join(res.get("missing_tasks") or []) or "none"
        raise ValueError(f"{path} holds no evaluated task (missing: {missing}):"
                         " let make eval finish a task first")
    metrics = res["metrics"]
    for k in ("within_task", "pooled", "per_task"):
        if k not in metrics:
            raise ValueError(f"{what}: metrics lacks {k}")
    if lack := [t for t in res["tasks"] if t not in metrics["per_task"] or t not in metrics["within_task"]["tasks"]]:
        raise ValueError(f"{path}: tasks {', '.join(lack)} have no statistics in metrics (edited by hand?)")
    # a task's statistics count its rows whose prediction is defined (or all of them, where fewer than two are)
    rows = {t: [p for p in res["policies"] if isinstance(p, dict) and p.get("task") == t] for t in res["tasks"]}
    read = {t: sum(p.get("pred_rate") is not None for p in rows[t]) for t in res["tasks"]}
    if wrong := [f"{t} ({len(rows[t])} rows, {n} in its statistics)" for t in res["tasks"]
                 if (n := metrics["per_task"][t].get("n_policies")) is not None and not read[t] <= n <= len(rows[t])]:
        raise ValueError(f"{path}: the policy rows do not match the statistics of tasks {', '.join(wrong)} "
                         "(edited by hand? rerun make eval, or leave policies out with its policies= selection)")
    for p in res["policies"]:
        if lack := [k for k in ROW_KEYS if k not in p]:
            raise ValueError(f"{path}: policy {p.get('name')!r} ({p.get('task')}) lacks {', '.join(lack)}")
        if p["task"] not in res["tasks"]:
            raise ValueError(f"{path}: policy {p['name']!r} is on task {p['task']!r}, not among tasks {res['tasks']}")
        if not p["n"] or p["true_rate"] is None or (isinstance(p["true_ci"], list) and None in p["true_ci"]):
            raise ValueError(f"{path}: policy {p['name']!r} ({p['task']}) has no simulated outcome (n={p['n']}, "
                             f"true_rate {p['true_rate']}): leave it out or evaluate it")
        if wrong := _misread_rates(p):
            raise ValueError(f"{path}: policy {p['name']!r} ({p['task']}): {wrong} (edited by hand?)")
    return res


def _is_rate(x) -> bool:
    """Whether x is a success rate as results.json holds one: a number in [0, 1] (JSON true/false are not)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and 0.0 <= x <= 1.0


def _misread_rates(p: dict) -> str:
    """What is wrong with a results row's rates and intervals ("" where nothing): true_rate a rate,
    true_ci two rates, pred_rate a rate or null (its imagination diverged), pred_ci two rates or nulls."""
    if not _is_rate(p["true_rate"]):
        return f"true_rate {p['true_rate']!r} is not a rate in [0, 1]"
    for key, may_be_null in (("true_ci", False), ("pred_ci", True)):
        ci = p[key]
        if not (isinstance(ci, list) and len(ci) == 2
                and all(_is_rate(x) or (may_be_null and x is None) for x in ci)):
            return f"{key} {ci!r} is not a pair of rates in [0, 1]" + (" or nulls" if may_be_null else "")
    if not (p["pred_rate"] is None or _is_rate(p["pred_rate"])):
        return f"pred_rate {p['pred_rate']!r} is neither a rate in [0, 1] nor null"
    return ""


def _sentence(s: str) -> str:
    """s with its first letter a capital (str.capitalize would lower the rest: policy names, NaN)."""
    return s[:1].upper() + s[1:]


def build(run: Path, sweeps: Path | None = None) -> tuple[str, str]:
    """(HTML, Markdown) of the evaluation in run, with a section per sweep under `sweeps` if given."""
    res = read_results(run)
    tasks, policies, metrics = res["tasks"], res["policies"], res["metrics"]
    videos = read_videos(run)
    verd = verdicts(policies, tasks)
    unlearned, unread = unlearned_warning(res), nonfinite_policies(policies)
    plug = plugin_table(policies, ruled_tasks(res))
    h = [f"<html><head><meta charset='utf-8'><title>World-model policy evaluation</title><style>{CSS}</style>"
         "</head><body>", "<h1>Policy evaluation in the world model against the simulator</h1>",
         f"<p>{policy_count(policies)} on {html.escape(', '.join(tasks))}; {res['config']['episodes']} held-out "
         "initial states "
         f"per task; {_models_phrase(res, lambda r: f'<code>{html.escape(r)}</code>')}; engine {res['engine']}; "
         f"device {html.escape(str(res['device']))}.</p>",
         *([f"<p class='warn'>{html.escape(partial)}</p>"] if (partial := partial_note(res)) else []),
         *([f"<p>{html.escape(ranking)}</p>"] if (ranking := ranked_by(res)) else []),
         *([f"<p class='warn'>{html.escape(unlearned)}</p>"] if unlearned else []),
         *([f"<p class='warn'>{html.escape(_sentence(unread))}.</p>"] if unread else []),
         *([f"<p class='warn'>{html.escape(CUT_SHORT)}</p>"] if res["world_model"].get("cut_short") else []),
         f"<p><b>{html.escape(verdict(res))}</b></p>",
         "<h2>Predicted against true success, per task</h2>", f"<img src='{scatter_figure(policies, metrics, tasks)}'>",
         "<h2>Within-task ranking (the headline)</h2>", _html_table(within_task_table(res)),
         *([f"<p>{html.escape(better)}</p>"] if (better := better_readout_note(res)) else []),
         *([f"<h2>Your policies (plug-ins)</h2><p>{html.escape(PLUGIN_NOTE)}</p>", _html_table(plug)]
           if plug else []),
         *([f"<h2>Task progress, true and imagined</h2><img src='{fig}'>"]
           if (fig := progress_figure(policies, tasks)) else []),
         *([f"<h2>Imagination against the simulated episode</h2><p>{html.escape(FIDELITY_NOTE)}</p>",
            _html_table(fid)] if (fid := fidelity_table(res)) else []),
         *([f"<h2>Counterfactual families</h2><p>{html.escape(FAMILY_NOTE)}</p>", _html_table(fam)]
           if (fam := family_table(res)) else []),
         *([f"<h2>Rank violations</h2><p>{html.escape(VIOLATION_NOTE)}</p>", _html_table(viol)]
           if (viol := violation_table(res)) else []),
         *([f"<p>{html.escape(loop)}</p>"] if (loop := loop_note(res)) else []),
         _html_table(per_task_table(res)),
         *(["<h2>Within-task ranking of the policies whose rollouts the world model never saw</h2>",
            _html_table(per_task_table(res, "unseen_within_task"))] if "unseen_within_task" in metrics else []),
         *([f"<h2>{UNSEEN_NETWORKS_TITLE}</h2>", _html_table(per_task_table(res, "unseen_networks_within_task"))]
           if "unseen_networks_within_task" in metrics else []),
         "<h2>Pooled over tasks (secondary)</h2>",
         "<p>Tasks of different difficulty correlate for free when pooled: a per-task prior scores well here.</p>",
         _html_table(_metrics_table(metrics["pooled"])),
         *(["<h2>Pooled, policies whose rollouts the world model never saw</h2>",
            _html_table(_metrics_table(metrics["unseen"]))] if "unseen" in metrics else []),
         "<h2>Checkpoint selection</h2>", *_selection_html(res, policies, tasks),
         "<h2>Rank comparison</h2>", f"<img src='{rank_figure(policies, tasks)}'>"]
    base = baseline_figure(policies, tasks)
    if base:
        h += ["<h2>The imitation-loss baseline</h2>", f"<img src='{base}'>"]
    h += _ab_verdicts_html(verd)
    h += ["<h2>Decision analysis</h2>", f"<img src='{decision_figure(res['decision'])}'>"]
    for t in tasks:
        h += [f"<h2>Task {html.escape(t)}</h2>", _html_table(_metrics_table(metrics["per_task"][t])),
              _html_table(_policy_table([p for p in policies if p["task"] == t]))]
    mp4 = video_links(read_index(run))
    h += _videos_html(run, res, videos, mp4)
    sweep_html, sweep_md = sweep_sections(Path(sweeps)) if sweeps is not None else ([], [])
    if sweeps is not None and not sweep_html:
        raise FileNotFoundError(f"{sweeps} holds no sweep results (make sweep OUT=...)")
    h += sweep_html
    timing = json.loads((run / "timing.json").read_text()) if (run / "timing.json").exists() else []
    compiles = compile_table(timing)
    h += _timing_html(timing, compiles)
    h += ["<h2>Configuration and versions</h2>", f"<pre>{html.escape(json.dumps(res['config'], indent=1))}</pre>",
          f"<pre>{html.escape(json.dumps(res['versions'], indent=1))}</pre>",
          f"<pre>{html.escape(json.dumps(res['timing'], indent=1))}</pre>", "</body></html>"]
    md = [f"# Policy evaluation: {policy_count(policies)} on {', '.join(tasks)}", "",
          f"{_models_phrase(res, lambda r: f'`{r}`', capital=True)}, {res['config']['episodes']} held-out initial states per task, "
          f"engine {res['engine']}, device {res['device']}. Full report: `report.html`.", "",
          *([f"**{partial}**", ""] if partial else []),
          *([ranking, ""] if ranking else []),
          *([f"**{unlearned}**", ""] if unlearned else []),
          *([f"**{_sentence(unread)}.**", ""] if unread else []),
          *([f"**{CUT_SHORT}**", ""] if res["world_model"].get("cut_short") else []),
          f"**{verdict(res)}**", "", "## Within-task ranking (the headline)", "", md_table(within_task_table(res)), "",
          *([better, ""] if (better := better_readout_note(res)) else []),
          md_table(per_task_table(res)), "",
          *(["## Your policies (plug-ins)", "", PLUGIN_NOTE, "", md_table(plug), ""] if plug else []),
          "## Checkpoint selection", "", _selection_md(res), "",
          "## Pooled over tasks (secondary)", "", md_table(_metrics_table(metrics["pooled"])), ""]
    if fid := fidelity_table(res):
        md += ["## Imagination against the simulated episode", "", FIDELITY_NOTE, "", md_table(fid), ""]
    if fam := family_table(res):
        md += ["## Counterfactual families", "", FAMILY_NOTE, "", md_table(fam), ""]
    if viol := violation_table(res):
        md += ["## Rank violations", "", VIOLATION_NOTE, "", md_table(viol), ""]
    if loop := loop_note(res):
        md += [loop, ""]
    if "unseen_within_task" in metrics:
        md += ["## Within task, policies whose rollouts the world model never saw", "",
               md_table(per_task_table(res, "unseen_within_task")), ""]
    if "unseen_networks_within_task" in metrics:
        md += [f"## {UNSEEN_NETWORKS_TITLE}", "", md_table(per_task_table(res, "unseen_networks_within_task")), ""]
    if "unseen" in metrics:
        md += ["## Pooled, policies whose rollouts the world model never saw", "",
               md_table(_metrics_table(metrics["unseen"])), ""]
    for t in tasks:
        md += [f"## {t}", "", md_table(_metrics_table(metrics["per_task"][t])), "",
               md_table(_policy_table([p for p in policies if p["task"] == t])), ""]
    if verd:
        md += ["## Verdicts", ""] + [
            f"- {v['task']}, {v['comparison']}: the world model prefers {v['world_model_prefers']}, truly better is "
            f"{v['truly_better']} ({AGREE[v['agree']][1]}"
            f"{'; true intervals overlap' if v['true_intervals_overlap'] else ''})" for v in verd] + [""]
    if mp4:
        md += ["## Videos", "", "Real (left) and imagined (right), MP4:", ""]
        md += [f"- [{md_text(label)}](<{href}>)" for label, href in mp4] + [""]
    if timing:
        md += ["## Pipeline timing", "", md_table(timing_table(timing)), ""]
        if compiles:
            md += ["Where the compile time goes:", "", md_table(compiles), ""]
    return "\n".join(h), "\n".join(md + sweep_md)


SWEEP_COLUMNS = (("psnr_h8", "PSNR h8"), ("pooled_gain_h8_db", "pooled gain h8 (dB)"),
                 ("success_auroc", "success AUROC"), ("match_accuracy", "match acc"), ("delta_psnr_db", "delta-PSNR"),
                 ("view_shift_h8_px", "view shift h8 (px)"), ("action_divergence_h8", "policy action divergence h8"),
                 ("body_psnr_h8", "air-fryer body PSNR h8"),
                 ("rest_psnr_h8", "rest of frame PSNR h8"), ("pearson", "ranking Pearson"), ("mmrv", "ranking MMRV"),
                 ("pairwise_acc_gap10", "pairwise acc (gap >= 10)"), ("alignment", "alignment"),
                 ("ensemble_pearson", "seeds' ensemble Pearson"), ("ensemble_mmrv", "seeds' ensemble MMRV"))


def _file_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode()


def sweep_sections(root: Path) -> tuple[list[str], list[str]]:
    """(HTML, Markdown) parts with one section per sweep under root (`make sweep` OUT directories,
    each with results.json and sweep.png): its finding, a table per swept value (mean over seeds),
    its curves, and the real-against-imagined strip of its largest value's first run."""
    h, md = [], []
    for res_path in sorted(Path(root).glob("*/results.json")):
        d = res_path.parent
        res = json.loads(res_path.read_text())
        if "per_x" not in res:
            continue
        cols = [(k, label) for k, label in SWEEP_COLUMNS if any(e.get(k) is not None for e in res["per_x"])]
        rows = [[res["x_label"], "seeds"] + [label for _, label in cols]]
        rows += [[f"{e['x']:g}", str(e["seeds"])] + [_fmt(e.get(k)) for k, _ in cols] for e in res["per_x"]]
        title = f"Sweep {res['sweep']} ({res['size']})"
        h += [f"<h2>{html.escape(title)}</h2>", f"<p>{html.escape(res['finding'])}</p>", _html_table(rows)]
        md += [f"## {title}", "", res["finding"], "", md_table(rows), ""]
        if (d / "sweep.png").exists():
            h.append(f"<img src='{_file_uri(d / 'sweep.png')}'>")
        last = [r["run"] for r in res["runs"] if r["x"] == res["per_x"][-1]["x"] and r["finished"]]
        strip = d / last[0] / "eval_frames.png" if last else None
        if strip is not None and strip.exists():
            h += [f"<p>True and imagined frames of {html.escape(last[0])}:</p>", f"<img src='{_file_uri(strip)}'>"]
    return h, md


def write_report(run: Path, sweeps: Path | None = None) -> Path:
    """report.html and report.md of the evaluation in run, with a section per sweep under `sweeps`."""
    run = Path(run)
    if not (run / "results.json").exists():
        raise FileNotFoundError(f"{run}/results.json is missing: run make eval first")
    page, md = build(run, sweeps)
    for name, text in (("report.html", page), ("report.md", md)):
        tmp = run / (name + ".tmp")
        tmp.write_text(text)
        tmp.replace(run / name)
    return run / "report.html"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="an evaluation directory (make eval OUT), or its results.json")
    p.add_argument("--sweeps", type=Path, help="a directory of sweeps (make sweep OUT=DIR/<name>) to add a section each")
    a = p.parse_args(argv)
    run = a.run.parent if a.run.name == "results.json" and a.run.is_file() else a.run
    print(write_report(run, a.sweeps).absolute())
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
