"""Statistics of a policy ranking: how far the world model's predicted success rates can be trusted.

Every function takes per-policy rates as 1-D arrays of equal length (`predicted`, `true`, in
[0, 1]) or per-episode outcomes as (P, N) arrays (policy x initial state; the same N initial
states for every policy of a task).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy import stats as sps

from sim_data.util import wilson_interval  # noqa: F401 (re-exported beside the statistics)


def _pair(predicted, true):
    p, t = np.asarray(predicted, np.float64), np.asarray(true, np.float64)
    if p.shape != t.shape or p.ndim != 1:
        raise ValueError(f"predicted and true must be 1-D of one length, got {p.shape} and {t.shape}")
    return p, t


MIN_CORRELATED = 3  # two points always lie on a line: a correlation of two policies says nothing


def pearson(predicted, true) -> tuple[float, tuple[float, float]]:
    """Pearson's r and its 95% interval by Fisher's z: tanh(atanh(r) -/+ 1.96 / sqrt(n - 3)).

    NaN when either side is constant or n < MIN_CORRELATED; the interval is (-1, 1) for n = 3.
    """
    p, t = _pair(predicted, true)
    if len(p) < MIN_CORRELATED or np.ptp(p) == 0 or np.ptp(t) == 0:
        return math.nan, (math.nan, math.nan)
    res = sps.pearsonr(p, t)
    r = float(np.clip(res.statistic, -1.0, 1.0))
    if len(p) <= 3:
        return r, (-1.0, 1.0)
    if abs(r) >= 1.0:
        return r, (r, r)
    ci = res.confidence_interval(0.95)
    return r, (float(ci.low), float(ci.high))


def rank(x) -> np.ndarray:
    """Ranks 1..n, tied values sharing their mean rank."""
    return sps.rankdata(np.asarray(x, np.float64))


def spearman(predicted, true) -> float:
    """Spearman's rho: Pearson's r of the ranks (ties at mean rank)."""
    p, t = _pair(predicted, true)
    return pearson(rank(p), rank(t))[0]


def kendall(predicted, true) -> float:
    """Kendall's tau-b (scipy); NaN when either side is constant or n < MIN_CORRELATED (as pearson)."""
    p, t = _pair(predicted, true)
    if len(p) < MIN_CORRELATED or np.ptp(p) == 0 or np.ptp(t) == 0:
        return math.nan
    return float(sps.kendalltau(p, t).statistic)


def mmrv(predicted, true) -> float:
    """SIMPLER's mean maximum rank violation:

        MMRV = 1/N sum_i max_j |true_i - true_j| * 1[(pred_i > pred_j) != (true_i > true_j)]

    each violation weighted by the true gap. Ties follow the strict comparisons of SIMPLER's code
    (simpler_env/utils/metrics.py): a pair tied in prediction but not in truth is a violation charged
    to the truly better policy (whose `true_i > true_j` the tie contradicts; which side takes it moves
    each side's max, and so MMRV); a pair tied in truth weighs 0. NaN where every policy's true rate is
    the same: there is no order to violate, and a 0 would read as a perfect ranking (as pairwise
    accuracy, undefined without a pair apart in truth).
    """
    p, t = _pair(predicted, true)
    return float(_masked_mmrv(p, t, np.ones(len(p), bool)))


def _violation_gaps(p, t) -> np.ndarray:
    """(..., N, N) |t_i - t_j| where the pair (i, j) is mis-ordered (mmrv's comparisons), else 0."""
    return np.abs(t[..., :, None] - t[..., None, :]) * (
        (p[..., :, None] > p[..., None, :]) != (t[..., :, None] > t[..., None, :]))


def mmrv_charges(predicted, true) -> tuple[np.ndarray, np.ndarray]:
    """Each policy's term of MMRV and the policy it is charged to: policy i's term is its largest
    violation (mmrv's max over j), charged to the j that attains it (the first where several tie; i
    itself where i has none). Returns (terms (N,), partner (N,) int); terms.mean() is mmrv."""
    gap = _violation_gaps(*_pair(predicted, true))
    terms = gap.max(axis=1)
    return terms, np.where(terms > 0, gap.argmax(axis=1), np.arange(len(terms)))


# what a rank violation carries of its policy's row: {its key: the row's field}
VIOLATION_READINGS = {"action_gap": "action_gap", "action_gap_largest": "action_gap_largest",
                      "closure_gap": "closure_gap", "closure_bias": "closure_bias",
                      "on_truth": "pred_rate_on_truth", "replayed": "pred_rate_replayed",
                      "imagined_in_sim": "true_rate_imagined_actions", "failed_peak_progress": "failed_peak_progress"}


def rank_violations(rows: list[dict], top: int = 5, rate: str = "pred_rate") -> dict:
    """Where each task's MMRV comes from (the rows' `rate` against their true_rate, as mmrv): every
    policy's term charged to the policy it is most mis-ordered with (mmrv_charges), so one policy read
    far from its truth shows as the partner of many. Returns {task: {"mmrv", "policies": the `top`
    policies charged the most, each {"name", "true_rate", "pred_rate", "share" (of the task's MMRV;
    all the task's policies' shares sum to 1), "against" (how many policies' largest violation is with
    it), and the row's VIOLATION_READINGS under their keys (None where it lacks them)}}}; a task
    whose MMRV is 0 or undefined (mmrv) lists none."""
    out = {}
    for task in sorted({r["task"] for r in rows}):
        rs = [r for r in rows if r["task"] == task]
        pred, true = [r[rate] for r in rs], [r["true_rate"] for r in rs]
        terms, partner = mmrv_charges(pred, true)
        charged = np.bincount(partner, weights=terms, minlength=len(rs))
        against = np.bincount(partner[terms > 0], minlength=len(rs))
        order = [int(k) for k in np.argsort(-charged, kind="stable") if charged[k] > 0][:top]
        out[task] = {"mmrv": mmrv(pred, true), "policies": [
            {"name": rs[k]["name"], "true_rate": rs[k]["true_rate"], "pred_rate": rs[k][rate],
             "share": float(charged[k] / terms.sum()), "against": int(against[k]),
             **{key: rs[k].get(field) for key, field in VIOLATION_READINGS.items()}} for k in order]}
    return out


def pairwise_accuracy(predicted, true, min_gap: float = 0.0) -> float:
    """Share of policy pairs ordered as the truth orders them, over pairs whose true rates differ by
    more than 0 and at least `min_gap`; a pair tied in prediction counts one half. NaN if no pair
    qualifies."""
    p, t = _pair(predicted, true)
    return float(_masked_pairwise(p, t, np.ones(len(p), bool), min_gap))


def alignment(pred_outcomes, true_outcomes) -> float:
    """Per-episode alignment: how often the world model's outcome from an initial state (bool) equals
    the simulator's from the same state; any shapes, equal."""
    a, b = np.asarray(pred_outcomes, bool), np.asarray(true_outcomes, bool)
    if a.shape != b.shape:
        raise ValueError(f"outcome arrays differ in shape: {a.shape} and {b.shape}")
    return float((a == b).mean())


def ranking_metrics(predicted, true) -> dict:
    """Every rate-level statistic of one ranking."""
    r, ci = pearson(predicted, true)
    return {"pearson": r, "pearson_ci": list(ci), "spearman": spearman(predicted, true),
            "kendall": kendall(predicted, true), "mmrv": mmrv(predicted, true),
            "pairwise_acc": pairwise_accuracy(predicted, true),
            "pairwise_acc_gap10": pairwise_accuracy(predicted, true, 0.10), "n_policies": len(np.asarray(true))}


def bootstrap_pearson(pred_episodes, true_episodes, draws: int = 2000, seed: int = 0) -> tuple[float, float]:
    """95% percentile interval of Pearson's r over initial states: resample the N columns of the
    (P, N) per-episode predictions (probabilities or outcomes) and truths together, recompute each
    policy's two rates and r."""
    pe, te = np.asarray(pred_episodes, np.float64), np.asarray(true_episodes, np.float64)
    if pe.shape != te.shape or pe.ndim != 2:
        raise ValueError(f"per-episode arrays must be (P, N) alike, got {pe.shape} and {te.shape}")
    rng = np.random.default_rng(seed)
    cols = rng.integers(0, pe.shape[1], (draws, pe.shape[1]))
    rs = []
    for c in cols:
        r = pearson(pe[:, c].mean(1), te[:, c].mean(1))[0]
        if not math.isnan(r):
            rs.append(r)
    if not rs:
        return math.nan, math.nan
    return float(np.percentile(rs, 2.5)), float(np.percentile(rs, 97.5))


# ---- the decision analysis ------------------------------------------------------------------------

def p_pick_better(accuracy: float, gap: float, episodes, base: float | None = None) -> np.ndarray:
    """Probability that comparing two policies in the world model picks the truly better one.

    Model: each imagined episode's outcome equals the real one with probability `accuracy` (a),
    independently; the better policy's true rate is base + gap, the other's base (default centred:
    base = 0.5 - gap / 2). An imagined episode then succeeds with q = a p + (1 - a)(1 - p), so
    with n episodes per policy the counts are Binomial(n, q_better) and Binomial(n, q_worse); the
    better is picked when its count is higher, and on a tie with probability 1/2.

    episodes: an int or array of n. Returns an array of probabilities (one per n).
    """
    if not 0 <= accuracy <= 1 or not 0 <= gap <= 1:
        raise ValueError(f"accuracy and gap must be in [0, 1], got {accuracy}, {gap}")
    base = 0.5 - gap / 2 if base is None else base
    if not 0 <= base <= 1 - gap:
        raise ValueError(f"base {base} and gap {gap} must keep both rates in [0, 1]")
    q = lambda p: accuracy * p + (1 - accuracy) * (1 - p)
    qa, qb = q(base + gap), q(base)
    out = []
    for n in np.atleast_1d(episodes):
        k = np.arange(int(n) + 1)
        pa, pb = sps.binom.pmf(k, n, qa), sps.binom.pmf(k, n, qb)
        cb = np.cumsum(pb)  # P(B <= k)
        win = (pa[1:] * cb[:-1]).sum()  # P(A > B)
        tie = (pa * pb).sum()
        out.append(win + 0.5 * tie)
    return np.asarray(out)


def resampled_pick_better(pred_better, pred_worse, episodes, draws: int = 2000, seed: int = 0) -> np.ndarray:
    """The same probability by resampling actual results: draw n initial states (with replacement)
    for each policy, compare the world model's mean predicted outcomes (ties: one half).

    pred_better, pred_worse: (N,) the world model's outcomes (0/1) of the truly better and worse
    policy. Returns one probability per n of `episodes`.
    """
    a, b = np.asarray(pred_better, np.float64), np.asarray(pred_worse, np.float64)
    rng = np.random.default_rng(seed)
    out = []
    for n in np.atleast_1d(episodes):
        ma = a[rng.integers(0, len(a), (draws, int(n)))].mean(1)
        mb = b[rng.integers(0, len(b), (draws, int(n)))].mean(1)
        out.append(float(((ma > mb) + 0.5 * (ma == mb)).mean()))
    return np.asarray(out)


# ---- the within-task headline ------------------------------------------------------------------------

WITHIN_TASK = ("pearson", "spearman", "mmrv", "pairwise_acc_gap10", "alignment")
LOWER_IS_BETTER = ("mmrv",)
DRAW_CHUNK = 1 << 22  # resampled outcomes held at once by within_task_draws
WITHIN_TASK_RESAMPLES = "policies and initial states, within each task (the same states for each policy)"

# what each kind of 95% interval in results.json resamples or assumes (an evaluation's
# metrics["intervals"]; an ensemble's "intervals", its Pearson intervals')
INTERVALS = {
    "policies[].true_ci, pred_thresholded_ci": "Wilson score interval of the policy's successes over its episodes "
                                               "(initial states)",
    "policies[].pred_ci": "t-interval of the policy's mean predicted probability over its episodes (initial states)",
    "within_task.*.mean_ci, per_task_ci, difference": f"percentile bootstrap resampling {WITHIN_TASK_RESAMPLES}",
    "pooled, per_task, unseen: pearson_ci": "Fisher's z over the policies, their rates taken as measured "
                                            "(nothing resampled)",
    "pooled, per_task, unseen: pearson_ci_bootstrap": "percentile bootstrap resampling initial states (every "
                                                      "policy's episodes of a state together), the policies fixed",
}


def task_statistics(pred, true, threshold: float = 0.5) -> dict:
    """The within-task statistics (WITHIN_TASK) of one task's ranking.

    pred: (P, N) per-episode predicted probabilities (a world model; a policy with a non-finite one is
    left out: the imagination of its episodes diverged), or (P,) one score per policy (a proxy such as
    minus the imitation loss; NaN where a policy has none: left out, and alignment is NaN). true: (P, N)
    per-episode outcomes (bool or 0/1) from the same N initial states.
    """
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    if pred.ndim == 2 and pred.shape != true.shape:
        raise ValueError(f"per-episode predictions {pred.shape} and outcomes {true.shape} differ in shape")
    return {k: float(v[0]) for k, v in draw_statistics(pred[None], true[None], threshold).items()}


def draw_statistics(pred, true, threshold: float = 0.5, distinct=None) -> dict:
    """task_statistics of D resamplings of one task at once: pred (D, P, N) probabilities (a policy with
    a non-finite one left out) or (D, P) scores (NaN: no score, left out), true (D, P, N) outcomes.
    Returns {stat: (D,) float64}; every ranking statistic of a draw with fewer than 2 scored policies is
    NaN (alignment, per episode, is defined for one policy: a plug-in evaluated alone has it, as its row
    and the pooled figures do; NaN with none), and Pearson and Spearman with fewer than MIN_CORRELATED
    or where either side is constant (pearson, spearman); MMRV, pairwise accuracy and alignment as mmrv,
    pairwise_accuracy and alignment over the scored policies. distinct: (D,) how many different policies
    each draw's scored ones are (a policy drawn twice counts once: two policies drawn as three lie on a
    line, r = +-1); default, every scored one is another policy."""
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    t = true.mean(-1)
    if pred.ndim == 3:
        keep = np.isfinite(pred).all(-1)
        # rounded: a policy drawn twice must tie with itself, whatever order its sum was taken in
        p = np.round(pred.mean(-1), 12)
        hits = ((pred >= threshold) == (true > 0.5)).mean(-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            aligned = np.where(keep, hits, 0.0).sum(-1) / keep.sum(-1)
    else:
        p, keep = pred, ~np.isnan(pred)
        aligned = np.full(len(p), math.nan)
    n = keep.sum(-1) if distinct is None else np.asarray(distinct)
    few = n < MIN_CORRELATED
    out = {"pearson": np.where(few, math.nan, _masked_pearson(p, t, keep)),
           "spearman": np.where(few, math.nan, _masked_pearson(_masked_rank(p, keep), _masked_rank(t, keep), keep)),
           "mmrv": _masked_mmrv(p, t, keep), "pairwise_acc_gap10": _masked_pairwise(p, t, keep, 0.10),
           "alignment": aligned}
    return {k: v if k == "alignment" else np.where(n >= 2, v, math.nan) for k, v in out.items()}


def _masked_pearson(x, y, keep) -> np.ndarray:
    """Pearson's r along the last axis over the kept entries: (D, P) -> (D,); NaN where a side is constant
    or fewer than MIN_CORRELATED entries are kept (as pearson)."""
    n = np.maximum(keep.sum(-1, keepdims=True), 1)
    dx = np.where(keep, x - np.where(keep, x, 0).sum(-1, keepdims=True) / n, 0.0)
    dy = np.where(keep, y - np.where(keep, y, 0).sum(-1, keepdims=True) / n, 0.0)
    undefined = (_masked_ptp(x, keep) == 0) | (_masked_ptp(y, keep) == 0) | (keep.sum(-1) < MIN_CORRELATED)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (dx * dy).sum(-1) / np.sqrt((dx * dx).sum(-1) * (dy * dy).sum(-1))
    return np.where(undefined, math.nan, np.clip(r, -1.0, 1.0))


def _masked_ptp(x, keep) -> np.ndarray:
    return np.where(keep, x, -np.inf).max(-1) - np.where(keep, x, np.inf).min(-1)


def _masked_rank(x, keep) -> np.ndarray:
    """Ranks 1..k of the kept entries along the last axis (ties at mean rank; the others rank above)."""
    return sps.rankdata(np.where(keep, x, np.inf), axis=-1)


def _masked_mmrv(p, t, keep) -> np.ndarray:
    """mmrv along the last axis over the kept entries: (D, P) -> (D,); NaN where the kept true rates are
    all equal."""
    gap = _violation_gaps(p, t) * keep[..., None, :]
    worst = np.where(keep, gap.max(-1), 0.0)
    return np.where(_masked_ptp(t, keep) > 0, worst.sum(-1) / np.maximum(keep.sum(-1), 1), math.nan)


def _masked_pairwise(p, t, keep, min_gap: float) -> np.ndarray:
    """pairwise_accuracy along the last axis over the kept entries: (D, P) -> (D,); NaN where no pair qualifies."""
    i, j = np.triu_indices(p.shape[-1], 1)
    gap = np.abs(t[..., i] - t[..., j])
    counted = keep[..., i] & keep[..., j] & (gap > 0) & (gap >= min_gap - 1e-12)
    agree = np.sign(p[..., i] - p[..., j]) * np.sign(t[..., i] - t[..., j])
    score = np.where(counted, (agree > 0) + 0.5 * (agree == 0), 0.0).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counted.any(-1), score / counted.sum(-1), math.nan)


def mean_interval(values, bounds=None) -> tuple[float | None, list | None]:
    """Mean of the finite values, and a 95% t-interval of it when there are two or more, clipped to
    bounds (lo, hi) where given."""
    v = np.array([x for x in values if x is not None and np.isfinite(x)], np.float64)
    if len(v) == 0:
        return None, None
    if len(v) == 1:
        return float(v[0]), None
    half = sps.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v))
    lo, hi = bounds or (-math.inf, math.inf)
    return float(v.mean()), [float(max(lo, v.mean() - half)), float(min(hi, v.mean() + half))]


def percentile_interval(x) -> list:
    """[2.5th, 97.5th] percentiles of bootstrap draws x, NaN draws left out ([nan, nan] if none is left)."""
    x = np.asarray(x, np.float64)
    x = x[~np.isnan(x)]
    return [float(np.percentile(x, 2.5)), float(np.percentile(x, 97.5))] if len(x) else [math.nan, math.nan]


def within_task_draws(true: dict, predictors: dict, threshold: float = 0.5, draws: int = 1000,
                      seed: int = 0) -> tuple[dict, dict]:
    """Each predictor's within-task statistics and their bootstrap draws: each draw resamples, within
    every task, its policies and its initial states (with replacement; the same states for each policy
    of the task, as they were run), the same draw for every predictor, and recomputes every statistic.

    true: {task: (P, N) outcomes}. predictors: {name: {task: (P, N) probabilities or (P,) scores}}
    (task_statistics). Returns (point {name: {task: {stat: x}}}, samples {name: {task: {stat: (draws,)}}}).
    """
    tasks = list(true)
    names = list(predictors)
    for name in names:
        if sorted(predictors[name]) != sorted(tasks):
            raise ValueError(f"predictor {name!r} covers tasks {sorted(predictors[name])}, not {sorted(tasks)}")
    point = {n: {t: task_statistics(predictors[n][t], true[t], threshold) for t in tasks} for n in names}
    rng = np.random.default_rng(seed)
    picks = {t: ([], []) for t in tasks}  # drawn in the order a draw at a time, task by task, gives
    for _ in range(draws):
        for t in tasks:
            policies, states = np.shape(true[t])
            picks[t][0].append(rng.integers(0, policies, policies))
            picks[t][1].append(rng.integers(0, states, states))
    boot = {n: {t: {k: np.empty(draws) for k in WITHIN_TASK} for t in tasks} for n in names}
    for t in tasks:
        tt = np.asarray(true[t], np.float64)
        rows, cols = np.stack(picks[t][0]), np.stack(picks[t][1])
        # a policy with any non-finite probability is left out whichever of its episodes a draw picks
        scored = {n: without_policies(predictors[n][t], ~scored_policies(predictors[n][t])) for n in names}
        step = max(1, DRAW_CHUNK // tt.size)  # draws at once: bounds the (draws, P, N) gathers
        for d in range(0, draws, step):
            r, c = rows[d:d + step, :, None], cols[d:d + step, None, :]
            drawn = np.zeros((len(r), tt.shape[0]), bool)  # which policies each draw holds, once each
            np.put_along_axis(drawn, r[..., 0], True, axis=1)
            for n in names:
                pr = scored[n]
                distinct = (drawn & scored_policies(pr)).sum(-1)
                got = draw_statistics(pr[r[..., 0]] if pr.ndim == 1 else pr[r, c], tt[r, c], threshold, distinct)
                for k, v in got.items():
                    boot[n][t][k][d:d + step] = v
    return point, boot


def within_task(true: dict, predictors: dict, threshold: float = 0.5, draws: int = 1000, seed: int = 0) -> dict:
    """Each predictor's within-task statistics, per task and their mean over tasks, with 95% percentile
    intervals from one bootstrap shared by every predictor (within_task_draws); a mean over tasks skips
    a task whose statistic is undefined (NaN) in that draw.

    true: {task: (P, N) outcomes}. predictors: {name: {task: (P, N) probabilities or (P,) scores}}
    (task_statistics). Returns {"tasks", "draws", "resamples", name: {"mean": {stat: x}, "mean_ci":
    {stat: [lo, hi]}, "per_task": {task: {stat: x}}, "per_task_ci": {task: {stat: [lo, hi]}}}, and for
    every later predictor the paired difference of the first minus it: "difference": {name: {"mean",
    "mean_ci", "per_task", "per_task_ci"}} (for mmrv a negative difference favours the first), both
    over the policies that both score (a proxy scores no plug-in; a world model none whose
    imagination diverged), in the same bootstrap draws; where that leaves policies out, also
    "shared": {"policies", "of": how many it compares of all, "first", "other": each side's "mean",
    "mean_ci" and "per_task" over those policies alone}.
    """
    tasks, names = list(true), list(predictors)
    point, boot = within_task_draws(true, predictors, threshold, draws, seed)

    def summary(stat_of, samples_of) -> dict:
        # a task whose statistic is undefined (every policy at one true rate, or one predicted) is left
        # out of the draws as of the point: a resampled draw may define it, from what the point lacks
        drawn = {t: {k: samples_of(t)[k] if not math.isnan(stat_of(t)[k]) else np.full(draws, math.nan)
                     for k in WITHIN_TASK} for t in tasks}
        with warnings.catch_warnings():  # a mean over nothing but NaN stays NaN, silently
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = {k: float(np.nanmean([stat_of(t)[k] for t in tasks])) for k in WITHIN_TASK}
            mean_ci = {k: percentile_interval(np.nanmean(np.stack([drawn[t][k] for t in tasks]), 0))
                       for k in WITHIN_TASK}
        return {"mean": mean, "mean_ci": mean_ci, "per_task": {t: stat_of(t) for t in tasks},
                "per_task_ci": {t: {k: percentile_interval(drawn[t][k]) for k in WITHIN_TASK} for t in tasks}}

    out = {"tasks": tasks, "draws": draws, "resamples": WITHIN_TASK_RESAMPLES}
    for n in names:
        out[n] = summary(lambda t, n=n: point[n][t], lambda t, n=n: boot[n][t])
    first = names[0]
    out["difference"] = {}
    for n in names[1:]:
        pa, ba, pb, bb = point[first], boot[first], point[n], boot[n]
        common = {t: scored_policies(predictors[first][t]) & scored_policies(predictors[n][t]) for t in tasks}
        shared = None
        if any((common[t] != scored_policies(predictors[m][t])).any() for t in tasks for m in (first, n)):
            pair = {"a": {t: without_policies(predictors[first][t], ~common[t]) for t in tasks},
                    "b": {t: without_policies(predictors[n][t], ~common[t]) for t in tasks}}
            pp, bp = within_task_draws(true, pair, threshold, draws, seed)  # the same seed: the same draws
            pa, ba, pb, bb = pp["a"], bp["a"], pp["b"], bp["b"]
            # each side over the policies the difference compares, which a reader quotes beside it
            sides = {side: summary(lambda t, p=p: p[t], lambda t, b=b: b[t])
                     for side, p, b in (("first", pa, ba), ("other", pb, bb))}
            shared = {"policies": int(sum(common[t].sum() for t in tasks)),
                      "of": int(sum(np.shape(true[t])[0] for t in tasks)),
                      **{side: {k: v[k] for k in ("mean", "mean_ci", "per_task")} for side, v in sides.items()}}
        out["difference"][n] = summary(
            lambda t, pa=pa, pb=pb: {k: pa[t][k] - pb[t][k] for k in WITHIN_TASK},
            lambda t, ba=ba, bb=bb: {k: ba[t][k] - bb[t][k] for k in WITHIN_TASK})
        if shared is not None:
            out["difference"][n]["shared"] = shared
    return out


def scored_policies(pred) -> np.ndarray:
    """(P,) bool: the policies a predictor scores (draw_statistics): a (P,) score that is not NaN, or
    (P, N) probabilities that are all finite."""
    pred = np.asarray(pred, np.float64)
    return np.isfinite(pred).all(-1) if pred.ndim == 2 else ~np.isnan(pred)


def without_policies(pred, drop) -> np.ndarray:
    """pred with the policies `drop` ((P,) bool) unscored: their rows NaN."""
    pred = np.array(pred, np.float64)
    pred[np.asarray(drop, bool)] = math.nan
    return pred



# ---- checkpoint selection ------------------------------------------------------------------------------

def mmrv_floor(true: dict, draws: int = 200, seed: int = 0) -> dict:
    """The MMRV that a perfect predictor scores against ground truth measured from a finite number of
    episodes: each task's policies' success probabilities taken to be their measured rates p (P,),
    each draw measures them again from the same number of episodes (Binomial(N, p) / N) and scores p
    against that measurement (mmrv); the mean over the draws where it is defined (a draw whose rates all
    tie has none). A target below it cannot be met at that many episodes, whatever the world model.
    true: {task: (P, N) outcomes}. Returns {"per_task": {task: float, NaN where every draw ties},
    "mean": the mean over the tasks where it is defined, "draws"}."""
    rng = np.random.default_rng(seed)
    per = {}
    for t, outcomes in true.items():
        o = np.asarray(outcomes, float)
        p, n = o.mean(1), o.shape[1]
        per[t] = _defined_mean([mmrv(p, rng.binomial(n, p) / n) for _ in range(draws)])
    return {"per_task": per, "mean": _defined_mean(list(per.values())), "draws": draws}


def _defined_mean(x) -> float:
    """The mean of the non-NaN values of x; NaN where there are none."""
    x = np.asarray(x, np.float64)
    return float(x[~np.isnan(x)].mean()) if (~np.isnan(x)).any() else math.nan


def checkpoint_selection(rows: list[dict]) -> dict:
    """Does the world model pick each training run's best checkpoint? Per (task, lineage) with two or
    more checkpoints (rows: {"task", "lineage", "step", "true_rate", "pred_rate", "true_ci"} per
    policy; rows without a step, such as plug-ins, are left out): the checkpoint with the highest
    predicted rate (a checkpoint whose predicted rate is missing or NaN, its imagination diverged, is
    not picked) against the truly best one of all (the picked one where it ties for the highest true
    rate, else the later step among those that tie). Where the world model rates several checkpoints
    equally highest it cannot choose between them: the pick is scored as one drawn at random among
    them (its true rate, exact and within_ci their means over the tied), so that a constant predictor
    scores chance, not the later checkpoint's luck.

    Returns {"lineages": [{"task", "lineage", "picked_step" (the latest of the tied), "tied" (how many
    share the highest rating), "best_step", "best_tied" (how many share the highest true rate),
    "picked_true", "best_true", "regret" (best_true - picked_true), "exact" (the share of the tied whose true rate is the highest: 1 or 0 without a
    tie), "within_ci" (the share of them whose true rate lies inside the best one's 95% interval)}],
    "exact_share", "within_ci_share", "mean_regret", "n", "unread" (runs of two or more checkpoints
    none of which the world model could read: imagination diverged)} (shares and mean NaN when no
    lineage qualifies).
    """
    groups: dict = {}
    for r in rows:
        if r.get("step") is not None:
            groups.setdefault((r["task"], r["lineage"]), []).append(r)
    out, unread = [], 0
    for (task, lineage), rs in sorted(groups.items()):
        read = [r for r in rs if r.get("pred_rate") is not None and not math.isnan(r["pred_rate"])]
        unread += len(rs) >= 2 and not read
        if len(rs) < 2 or not read:
            continue
        top = max(r["pred_rate"] for r in read)
        tied = [r for r in read if r["pred_rate"] == top]
        picked = max(tied, key=lambda r: r["step"])
        best = max(rs, key=lambda r: (r["true_rate"], r is picked, r["step"]))
        picked_true = float(np.mean([r["true_rate"] for r in tied]))
        out.append({"task": task, "lineage": lineage, "picked_step": picked["step"], "tied": len(tied),
                    "best_step": best["step"], "best_tied": sum(r["true_rate"] == best["true_rate"] for r in rs),
                    "picked_true": picked_true, "best_true": best["true_rate"],
                    "regret": best["true_rate"] - picked_true,
                    "exact": float(np.mean([r["true_rate"] >= best["true_rate"] for r in tied])),
                    "within_ci": float(np.mean([r["true_rate"] >= best["true_ci"][0] for r in tied]))})
    share = (lambda k: float(np.mean([x[k] for x in out]))) if out else (lambda k: math.nan)
    return {"lineages": out, "exact_share": share("exact"), "within_ci_share": share("within_ci"),
            "mean_regret": share("regret"), "n": len(out), "unread": unread}


def is_family(row: dict) -> bool:
    """Whether a results row is a counterfactual family's member: a checkpoint degraded by a known knob,
    its lineage "<base lineage>~<knob>" (sim_data.policies.zoo's Family)."""
    return "~" in row.get("lineage", "")


def unseen_networks(rows: list[dict], seen: set) -> set:
    """The names of the unseen policies (not in `seen`) that are lineages of their own rather than
    counterfactual families (is_family: degraded copies of a zoo checkpoint, whose knobs a world
    model's data may share): the kind a new user's policies are. Empty where there are no families
    among the unseen (the unseen block is then this one)."""
    unseen = [r for r in rows if r["name"] not in seen]
    if not any(is_family(r) for r in unseen):
        return set()
    return {r["name"] for r in unseen if not is_family(r)}


def pearson_ceiling(true, episodes, draws: int = 200, seed: int = 0) -> float:
    """The Pearson r that a perfect predictor reaches against true rates measured from a finite number
    of episodes, as mmrv_floor's MMRV: the policies' success probabilities taken to be their measured
    rates p (P,), each draw measures them again from the same episodes (Binomial(episodes, p) /
    episodes, episodes (P,)) and scores p against that measurement; the mean over the draws where r is
    defined. NaN where p is constant (r is undefined for every predictor)."""
    p, n = np.asarray(true, float), np.asarray(episodes)
    rng = np.random.default_rng(seed)
    return _defined_mean([pearson(p, rng.binomial(n, p) / n)[0] for _ in range(draws)])


def family_statistics(rows: list[dict], rate: str = "pred_rate", ceiling: bool = True) -> dict:
    """Do predictions follow known degradations? Per task and counterfactual family (rows whose
    lineage is "<base lineage>~<knob>": one checkpoint degraded at several levels), the family's
    levels together with their undegraded base (the base lineage's last checkpoint): Pearson r of
    the predicted rate (the row's `rate` key) against the true rate, the mean |predicted - true|, and,
    where the rows give their episodes ("n") and `ceiling`, the r a perfect predictor reaches against
    that truth (pearson_ceiling: how high r can be against this truth, however narrow its span; it
    depends on the truth alone, so one read-out's statistics carry it for all).

    Returns {"families": [{"task", "family", "n" (policies read, base included), "unread" (members left
    out: no finite prediction, their imagination diverged), "pearson", "mean_abs_error",
    "true_range": [lowest, highest], "pearson_ceiling"}], "mean_pearson" (over families where r is
    defined), "mean_pearson_ceiling" (over the same families), "mean_abs_error" (over families)}; NaN
    means where there is no family.
    """
    last = {}
    for r in rows:
        if r.get("step") is not None:
            key = (r["task"], r["lineage"])
            if key not in last or r["step"] > last[key]["step"]:
                last[key] = r
    groups: dict = {}
    for r in rows:
        if is_family(r):
            groups.setdefault((r["task"], r["lineage"]), []).append(r)
    out = []
    for (task, family), rs in sorted(groups.items()):
        base = last.get((task, family.split("~", 1)[0]))
        everyone = rs + ([base] if base is not None else [])
        # a member whose imagination diverged has no prediction: left out, and counted
        members = [r for r in everyone if r.get(rate) is not None and math.isfinite(r[rate])]
        if not members:
            continue
        pred = [r[rate] for r in members]
        true = [r["true_rate"] for r in members]
        episodes = [r.get("n") for r in members]
        top = pearson_ceiling(true, episodes) if ceiling and all(episodes) else math.nan
        out.append({"task": task, "family": family, "n": len(members), "unread": len(everyone) - len(members),
                    "pearson": pearson(pred, true)[0],
                    "mean_abs_error": float(np.mean(np.abs(np.subtract(pred, true)))),
                    "true_range": [min(true), max(true)], "pearson_ceiling": top})
    defined = [x for x in out if not math.isnan(x["pearson"])]
    mean = lambda key: float(np.mean([x[key] for x in defined])) if defined else math.nan
    return {"families": out, "mean_pearson": mean("pearson"), "mean_pearson_ceiling": mean("pearson_ceiling"),
            "mean_abs_error": _defined_mean([x["mean_abs_error"] for x in out])}


def policy_count(rows: list[dict]) -> str:
    """How many policies the rows (one a policy and task) hold: "31 policies, 37 policy-task pairs" where
    a policy runs on several tasks (a plug-in: the same name on each), "25 policies" where each runs on one."""
    names = len({r["name"] for r in rows})
    return f"{names} {'policy' if names == 1 else 'policies'}" + (f", {len(rows)} policy-task pairs"
                                                                   if names != len(rows) else "")


def nonfinite_policies(rows: list[dict]) -> str:
    """A sentence naming the policies whose simulated episodes or imagined predictions went non-finite
    (a policy's NaN or infinite actions, most often), "" if none."""
    names = sorted({r["name"] for r in rows if r.get("nonfinite_episodes") or r.get("nonfinite_predictions")})
    if not names:
        return ""
    return (f"policies {', '.join(names)} ran into non-finite values (NaN or infinite actions?): where the "
            "simulator's state went non-finite their true outcomes are doubtful, and where the world model's "
            "predictions did, their predicted rates cannot be read and the ranking statistics leave them out")
