"""Statistics of a policy ranking: how far the world model's predicted success rates can be trusted.

Every function takes per-policy rates as 1-D arrays of equal length (`predicted`, `true`, in
[0, 1]) or per-episode outcomes as (P, N) arrays (policy x initial state; the same N initial
states for every policy of a task).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats as sps

from sim_data.success_table import wilson_interval  # noqa: F401 (the one Wilson interval, re-exported)

Z95 = 1.959963984540054


def _pair(predicted, true):
    p, t = np.asarray(predicted, np.float64), np.asarray(true, np.float64)
    if p.shape != t.shape or p.ndim != 1:
        raise ValueError(f"predicted and true must be 1-D of one length, got {p.shape} and {t.shape}")
    return p, t


def pearson(predicted, true) -> tuple[float, tuple[float, float]]:
    """Pearson's r and its 95% interval by Fisher's z: tanh(atanh(r) -/+ 1.96 / sqrt(n - 3)).

    NaN when either side is constant; the interval is (-1, 1) for n <= 3.
    """
    p, t = _pair(predicted, true)
    if len(p) < 2 or p.std() == 0 or t.std() == 0:
        return math.nan, (math.nan, math.nan)
    r = float(np.corrcoef(p, t)[0, 1])
    if len(p) <= 3:
        return r, (-1.0, 1.0)
    z, se = math.atanh(min(max(r, -0.999999), 0.999999)), 1.0 / math.sqrt(len(p) - 3)
    return r, (math.tanh(z - Z95 * se), math.tanh(z + Z95 * se))


def rank(x) -> np.ndarray:
    """Ranks 1..n, tied values sharing their mean rank."""
    x = np.asarray(x, np.float64)
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(1, len(x) + 1)
    for v in np.unique(x):
        tie = x == v
        ranks[tie] = ranks[tie].mean()
    return ranks


def spearman(predicted, true) -> float:
    """Spearman's rho: Pearson's r of the ranks (ties at mean rank)."""
    p, t = _pair(predicted, true)
    return pearson(rank(p), rank(t))[0]


def kendall(predicted, true) -> float:
    """Kendall's tau-b: (concordant - discordant) / sqrt((n0 - ties_p) (n0 - ties_t)) over all pairs."""
    p, t = _pair(predicted, true)
    i, j = np.triu_indices(len(p), 1)
    dp, dt = np.sign(p[i] - p[j]), np.sign(t[i] - t[j])
    n0 = len(i)
    ties_p, ties_t = int((dp == 0).sum()), int((dt == 0).sum())
    denom = math.sqrt((n0 - ties_p) * (n0 - ties_t))
    return float((dp * dt).sum() / denom) if denom else math.nan


def mmrv(predicted, true) -> float:
    """SIMPLER's mean maximum rank violation:

        MMRV = 1/N sum_i max_j |true_i - true_j| * 1[(pred_i < pred_j) != (true_i < true_j)]

    each violation weighted by the true gap. Ties follow the definition's strict comparisons: a pair
    tied in prediction but not in truth is a violation (from the side of the truly worse policy); a
    pair tied in truth weighs 0.
    """
    p, t = _pair(predicted, true)
    wrong = (p[:, None] < p[None, :]) != (t[:, None] < t[None, :])
    return float((np.abs(t[:, None] - t[None, :]) * wrong).max(axis=1).mean())


def pairwise_accuracy(predicted, true, min_gap: float = 0.0) -> float:
    """Share of policy pairs ordered as the truth orders them, over pairs whose true rates differ by
    more than 0 and at least `min_gap`; a pair tied in prediction counts one half. NaN if no pair
    qualifies."""
    p, t = _pair(predicted, true)
    i, j = np.triu_indices(len(p), 1)
    gap = np.abs(t[i] - t[j])
    keep = (gap > 0) & (gap >= min_gap - 1e-12)
    if not keep.any():
        return math.nan
    agree = np.sign(p[i] - p[j])[keep] * np.sign(t[i] - t[j])[keep]
    return float(((agree > 0) + 0.5 * (agree == 0)).mean())


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
