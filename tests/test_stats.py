"""experiments.stats against values worked out by hand (and scipy where it has the same statistic)."""

import json
import math

import numpy as np
import pytest
from scipy import stats as sps

from experiments import stats as S


def test_pearson_and_fisher_interval_by_hand():
    # deviations (-2,-1,0,1,2) and (-2,0,1,0,1): sum of products 6, squares 10 and 6
    r, (lo, hi) = S.pearson([1, 2, 3, 4, 5], [2, 4, 5, 4, 5])
    assert r == pytest.approx(6 / math.sqrt(60))
    # tanh(atanh(r) -/+ 1.96 / sqrt(5 - 3))
    assert (lo, hi) == pytest.approx((-0.34008203518751035, 0.9842357551507267))
    assert math.isnan(S.pearson([1, 1, 1], [0, 1, 2])[0])
    assert math.isnan(S.pearson([0.2, 0.9], [0.0, 1.0])[0])  # two points lie on a line: no evidence
    assert S.pearson([0.2, 0.9, 0.55], [0.0, 1.0, 0.5]) == (pytest.approx(1.0), (-1.0, 1.0))
    with pytest.raises(ValueError, match="1-D"):
        S.pearson([1, 2], [1, 2, 3])


def test_spearman_and_kendall_with_ties_by_hand():
    pred, true = [1, 2, 2, 3], [1, 3, 2, 4]
    # ranks (1, 2.5, 2.5, 4) and (1, 3, 2, 4): products 4.5, squares 4.5 and 5
    assert S.spearman(pred, true) == pytest.approx(4.5 / math.sqrt(22.5))
    # 5 concordant pairs, 1 tied in prediction, none discordant: tau-b = 5 / sqrt(5 * 6)
    assert S.kendall(pred, true) == pytest.approx(5 / math.sqrt(30))
    assert S.spearman(pred, true) == pytest.approx(sps.spearmanr(pred, true).statistic)
    assert S.kendall(pred, true) == pytest.approx(sps.kendalltau(pred, true).statistic)
    # two policies always agree or disagree wholly: no rank correlation, as for Pearson and Spearman
    assert math.isnan(S.kendall([0.2, 0.9], [0.0, 1.0])) and math.isnan(S.spearman([0.2, 0.9], [0.0, 1.0]))


def test_mmrv_weights_violations_by_true_gap_and_counts_predicted_ties():
    # only the pair (0, 1) is misordered; its true gap 0.4 is the max for policies 0 and 1
    assert S.mmrv([0.3, 0.6, 0.1], [0.9, 0.5, 0.2]) == pytest.approx((0.4 + 0.4 + 0.0) / 3)
    assert S.mmrv([0.1, 0.5, 0.9], [0.2, 0.5, 0.8]) == 0.0
    # a predicted tie is a violation, charged to the truly better policy (SIMPLER's strict `>`)
    assert S.mmrv([0.5, 0.5], [0.2, 0.6]) == pytest.approx(0.4 / 2)
    # a true tie weighs nothing whatever the prediction
    assert S.mmrv([0.9, 0.1, 0.0], [0.5, 0.5, 0.9]) == pytest.approx((0.4 + 0.4 + 0.4) / 3)
    assert S.mmrv([0.9, 0.1, 0.95], [0.5, 0.5, 0.9]) == 0.0
    # where every true rate ties there is no order to violate: undefined, not a perfect 0
    assert math.isnan(S.mmrv([0.9, 0.1], [0.5, 0.5]))
    assert math.isnan(S.task_statistics([0.2, 0.7, 0.4], np.ones((3, 4)))["mmrv"])


def _simpler_mmrv(sim, real):
    """SIMPLER's own MMRV (simpler_env/utils/metrics.py: mean_maximum_rank_violation), loop for loop."""
    out = []
    for i in range(len(sim)):
        worst = 0.0
        for j in range(len(sim)):
            if (sim[i] > sim[j]) != (real[i] > real[j]):
                worst = max(worst, abs(real[i] - real[j]))
        out.append(worst)
    return float(np.mean(out))


def test_mmrv_is_simplers_with_ties_in_prediction():
    # a tie in prediction charged to the truly better policy, as SIMPLER's code does: here 0.9 + 1.0 + 0.9,
    # where charging the truly worse one would give 0.9 + 1.0 + 0.0
    assert S.mmrv([0.5, 0.5, 0.0], [0.0, 1.0, 0.9]) == pytest.approx(2.8 / 3)
    rng = np.random.default_rng(0)
    for _ in range(300):  # rates on a coarse grid: ties on both sides
        n = int(rng.integers(2, 8))
        p, t = rng.integers(0, 4, n) / 4, rng.integers(0, 4, n) / 4
        if np.ptp(t) > 0:
            assert S.mmrv(p, t) == pytest.approx(_simpler_mmrv(p, t)), (p, t)
            assert S.task_statistics(p[:, None], t[:, None])["mmrv"] == pytest.approx(_simpler_mmrv(p, t))


def test_one_policy_has_a_per_episode_alignment_but_no_ranking():
    # a plug-in evaluated alone: nothing to rank, but its episodes agree or not, as its row and the pooled
    # figures say (the within-task headline read n/a)
    got = S.task_statistics(np.array([[0.9, 0.2, 0.7]]), np.array([[1, 0, 0]]))
    assert got["alignment"] == pytest.approx(2 / 3)
    assert all(math.isnan(got[k]) for k in ("pearson", "spearman", "mmrv", "pairwise_acc_gap10"))
    assert math.isnan(S.task_statistics(np.array([[math.nan, 0.2, 0.7]]), np.array([[1, 0, 0]]))["alignment"])
    w = S.within_task({"t": np.array([[1, 0, 0]])}, {"wm": {"t": np.array([[0.9, 0.2, 0.7]])}}, draws=50)
    assert w["wm"]["mean"]["alignment"] == pytest.approx(2 / 3) and not math.isnan(w["wm"]["mean_ci"]["alignment"][0])


def test_rank_violations_charge_each_policys_mmrv_term_to_its_worst_partner():
    # by hand: a (true 0.1) read above b (0.5) and d (0.8): a's term 0.7 (against d), b's 0.4 (against
    # a), d's 0.7 (against a), c none; MMRV (0.7 + 0.4 + 0 + 0.7) / 4, a charged 1.1 of the 1.8, d 0.7
    names, pred, true = "abcd", [0.9, 0.5, 0.1, 0.6], [0.1, 0.5, 0.0, 0.8]
    terms, partner = S.mmrv_charges(pred, true)
    np.testing.assert_allclose(terms, [0.7, 0.4, 0.0, 0.7])
    assert partner.tolist() == [3, 0, 2, 0]
    rows = [{"task": "t", "name": n, "pred_rate": p, "true_rate": t} for n, p, t in zip(names, pred, true)]
    rows += [{"task": "u", "name": "e", "pred_rate": 0.2, "true_rate": 0.1},
             {"task": "u", "name": "f", "pred_rate": 0.4, "true_rate": 0.3}]
    v = S.rank_violations(rows)
    assert v["t"]["mmrv"] == pytest.approx(S.mmrv(pred, true)) == pytest.approx(1.8 / 4)
    got = [(x["name"], round(x["share"], 4), x["against"]) for x in v["t"]["policies"]]
    assert got == [("a", round(1.1 / 1.8, 4), 2), ("d", round(0.7 / 1.8, 4), 1)]
    assert v["u"] == {"mmrv": 0.0, "policies": []}
    assert [x["name"] for x in S.rank_violations(rows, top=1)["t"]["policies"]] == ["a"]


def test_pairwise_accuracy_all_pairs_and_gap_filter():
    pred, true = [0.3, 0.6, 0.1], [0.9, 0.5, 0.2]
    assert S.pairwise_accuracy(pred, true) == pytest.approx(2 / 3)
    assert S.pairwise_accuracy(pred, true, min_gap=0.35) == pytest.approx(1 / 2)  # pairs (0,1), (0,2)
    assert S.pairwise_accuracy([0.5, 0.5, 0.1], true) == pytest.approx(2.5 / 3)  # a predicted tie: one half
    assert math.isnan(S.pairwise_accuracy([0.1, 0.2], [0.5, 0.5]))


def test_alignment_and_ranking_metrics_bundle():
    assert S.alignment([[1, 0, 1, 1]], [[1, 1, 1, 0]]) == 0.5
    with pytest.raises(ValueError, match="shape"):
        S.alignment([1, 0], [1, 0, 1])
    m = S.ranking_metrics([0.1, 0.5, 0.9], [0.2, 0.5, 0.8])
    assert m["pearson"] == pytest.approx(1.0) and m["spearman"] == pytest.approx(1.0) and m["mmrv"] == 0.0
    assert m["pairwise_acc"] == 1.0 and m["pairwise_acc_gap10"] == 1.0 and m["n_policies"] == 3


def test_bootstrap_interval_over_initial_states():
    rng = np.random.default_rng(0)
    true = (rng.random((6, 40)) < np.linspace(0.1, 0.9, 6)[:, None]).astype(float)
    lo, hi = S.bootstrap_pearson(true, true, draws=300)
    assert lo == pytest.approx(1.0) and hi == pytest.approx(1.0)  # a perfect predictor stays perfect
    noisy = np.where(rng.random(true.shape) < 0.3, 1 - true, true)
    lo, hi = S.bootstrap_pearson(noisy, true, draws=300)
    r = S.pearson(noisy.mean(1), true.mean(1))[0]
    assert -1 <= lo < r < hi <= 1


def test_decision_analysis_by_hand_and_against_resampling():
    # a = 1, rates 0.6 and 0.4, one episode each: P(A > B) = 0.6 * 0.6, P(tie) = 0.6 * 0.4 + 0.4 * 0.6
    assert S.p_pick_better(1.0, 0.2, 1)[0] == pytest.approx(0.36 + 0.5 * 0.48)
    # a = 0.5: the world model's outcomes are coin flips whatever the policy
    assert S.p_pick_better(0.5, 0.4, [1, 10, 100]) == pytest.approx([0.5, 0.5, 0.5])
    curve = S.p_pick_better(0.9, 0.1, [5, 20, 80, 320])
    assert np.all(np.diff(curve) > 0) and curve[-1] > 0.95
    # resampling outcomes with exactly these rates agrees with the binomial model
    better, worse = np.r_[np.ones(60), np.zeros(40)], np.r_[np.ones(40), np.zeros(60)]
    got = S.resampled_pick_better(better, worse, [1, 10], draws=20000)
    assert got == pytest.approx(S.p_pick_better(1.0, 0.2, [1, 10]), abs=0.015)
    with pytest.raises(ValueError, match="base"):
        S.p_pick_better(0.9, 0.5, 10, base=0.7)


def _evaluation(pred, true, names=("a", "b", "c", "d"), n=64):
    return {"policies": [{"name": k, "task": "mug", "lineage": "conv", "n": n, "true_rate": t, "pred_rate": p}
                         for k, p, t in zip(names, pred, true, strict=True)]}


def test_an_ensemble_ranks_by_the_mean_of_its_models_predicted_rates(tmp_path):
    from experiments import ensemble as ENS

    true = [0.1, 0.5, 0.9, 0.3]
    one, two = [0.2, 0.4, 0.9, 0.5], [0.4, 0.2, 0.7, 0.1]
    res = ENS.combine([_evaluation(one, true), _evaluation(two, [0.1, 0.5, 0.9, 0.4])])
    rows = res["policies"]
    assert res["models"] == 2 and [r["pred_rate"] for r in rows] == pytest.approx([0.3, 0.3, 0.8, 0.3])
    assert rows[3]["true_rate"] == pytest.approx(0.35) and rows[3]["true_spread"] == pytest.approx(0.1)
    mean_true = [0.1, 0.5, 0.9, 0.35]
    m = res["metrics"]["pooled"]
    assert m["pearson"] == pytest.approx(np.corrcoef([0.3, 0.3, 0.8, 0.3], mean_true)[0, 1])
    assert m["members"]["pearson"] == pytest.approx([np.corrcoef(one, mean_true)[0, 1], np.corrcoef(two, mean_true)[0, 1]])
    assert m["members_mean"]["pearson"] == pytest.approx(np.mean(m["members"]["pearson"]))
    assert res["metrics"]["mug"]["pearson"] == pytest.approx(m["pearson"])
    assert set(res["intervals"]) == {k for k in S.INTERVALS if "pearson_ci" in k}  # what they resample
    with pytest.raises(ValueError, match="at least two"):
        ENS.combine([_evaluation(one, true)])
    with pytest.raises(ValueError, match="other policies"):
        ENS.combine([_evaluation(one, true), _evaluation(two, true, names=("a", "b", "c", "e"))])
    with pytest.raises(ValueError, match="same held-out states"):
        ENS.combine([_evaluation(one, true), _evaluation(two, true, n=32)])
    for k, pred in enumerate((one, two)):  # the command line reads evaluate OUT directories
        (tmp_path / f"m{k}").mkdir()
        (tmp_path / f"m{k}" / "results.json").write_text(json.dumps(_evaluation(pred, true)))
    assert ENS.main([str(tmp_path / "m0"), str(tmp_path / "m1"), "--out", str(tmp_path / "ens")]) == 0
    back = json.loads((tmp_path / "ens" / "results.json").read_text())
    assert back["models"] == 2 and back["runs"] == [str(tmp_path / "m0"), str(tmp_path / "m1")]
    with pytest.raises(FileNotFoundError, match="experiments.evaluate OUT"):
        ENS.read_results(tmp_path / "nothing")


def test_an_ensemble_with_episodes_aligns_by_the_mean_probability_of_each_episode():
    from experiments import ensemble as ENS

    true = {"a": [1, 0, 1, 0], "b": [0, 0, 0, 0], "c": [1, 1, 1, 1]}
    probs = ({"a": [0.9, 0.6, 0.4, 0.1], "b": [0.1, 0.2, 0.3, 0.7], "c": [0.9, 0.9, 0.9, 0.9]},
             {"a": [0.7, 0.2, 0.8, 0.3], "b": [0.1, 0.1, 0.1, 0.1], "c": [0.4, 0.6, 0.6, 0.6]})

    def evaluation(prob):
        return {"config": {"threshold": 0.5}, "policies": [
            {"name": k, "task": "mug", "n": 4, "true_rate": float(np.mean(t)), "pred_rate": float(np.mean(prob[k])),
             "true_episodes": t, "pred_episodes": prob[k]} for k, t in true.items()]}

    res = ENS.combine([evaluation(p) for p in probs])
    assert res["policies"][0]["pred_episodes"] == pytest.approx([0.8, 0.4, 0.6, 0.2])
    m = res["metrics"]["pooled"]
    # the mean probabilities threshold to every true outcome; model 1 alone to 9 of 12, model 2 to 11
    assert m["alignment"] == 1.0 and m["members"]["alignment"] == pytest.approx([9 / 12, 11 / 12])
    assert len(m["pearson_ci_bootstrap"]) == 2
    other = evaluation(probs[1])
    other["policies"][0]["true_episodes"] = [0, 1, 1, 0]  # another simulated truth: no per-episode figures
    assert "alignment" not in ENS.combine([evaluation(probs[0]), other])["metrics"]["pooled"]


def _two_tasks():
    # task a: the world model's rates (0.9, 0.5, 0.1) = 0.1 + 0.8 x true (1, 0.5, 0): a perfect ranking;
    # task b: its rates (0.2, 0.8, 0.5) against true (1, 0, 0.5): exactly reversed
    true = {"a": np.array([[1, 1], [1, 0], [0, 0]], bool), "b": np.array([[1, 1], [0, 0], [1, 0]], bool)}
    wm = {"a": np.array([[0.9, 0.9], [0.7, 0.3], [0.1, 0.1]]), "b": np.array([[0.2, 0.2], [0.8, 0.8], [0.5, 0.5]])}
    proxy = {"a": np.array([-1.0, -2.0, -3.0]), "b": np.array([3.0, np.nan, 1.0])}  # b's second has no loss
    return true, wm, proxy


def test_task_statistics_by_hand():
    true, wm, proxy = _two_tasks()
    a = S.task_statistics(wm["a"], true["a"])
    assert a == pytest.approx({"pearson": 1.0, "spearman": 1.0, "mmrv": 0.0, "pairwise_acc_gap10": 1.0,
                               "alignment": 1.0})
    b = S.task_statistics(wm["b"], true["b"])
    # every pair misordered: the max violations 1, 1 and 0.5; thresholded at 0.5, one episode of six agrees
    assert b == pytest.approx({"pearson": -1.0, "spearman": -1.0, "mmrv": 2.5 / 3, "pairwise_acc_gap10": 0.0,
                               "alignment": 1 / 6})
    # a per-policy score leaves out the policy without one and has no per-episode alignment; of the two
    # policies left, the order counts and a correlation does not (MIN_CORRELATED)
    p = S.task_statistics(proxy["b"], true["b"])
    assert math.isnan(p["pearson"]) and math.isnan(p["spearman"]) and math.isnan(p["alignment"])
    assert p["mmrv"] == 0.0 and p["pairwise_acc_gap10"] == 1.0
    two = S.task_statistics(wm["b"][:2], true["b"][:2])
    assert math.isnan(two["pearson"]) and two["pairwise_acc_gap10"] == 0.0 and two["mmrv"] > 0
    with pytest.raises(ValueError, match="shape"):
        S.task_statistics(wm["a"][:, :1], true["a"])


def test_within_task_mean_intervals_and_difference():
    true, wm, proxy = _two_tasks()
    got = S.within_task(true, {"world_model": wm, "proxy": proxy}, draws=200, seed=3)
    m = got["world_model"]["mean"]
    assert m == pytest.approx({"pearson": 0.0, "spearman": 0.0, "mmrv": 2.5 / 6, "pairwise_acc_gap10": 0.5,
                               "alignment": 7 / 12})
    assert got["proxy"]["mean"]["pearson"] == pytest.approx(1.0)
    # on task b the proxy scores two policies, too few for a correlation: the difference is task a's alone
    assert math.isnan(got["proxy"]["per_task"]["b"]["pearson"])
    assert got["difference"]["proxy"]["mean"]["pearson"] == pytest.approx(0.0)
    assert math.isnan(got["difference"]["proxy"]["per_task"]["b"]["pearson"])
    # resampled, every pair of task a whose true rates differ stays ordered, and task b stays reversed
    assert got["world_model"]["per_task_ci"]["a"]["pairwise_acc_gap10"] == pytest.approx([1.0, 1.0])
    assert got["world_model"]["per_task_ci"]["b"]["pearson"][1] < 0
    for k in S.WITHIN_TASK:
        lo, hi = got["world_model"]["mean_ci"][k]
        assert lo <= m[k] + 1e-9 and m[k] <= hi + 1e-9, k
    assert got["draws"] == 200 and "initial states" in got["resamples"]
    again = S.within_task(true, {"world_model": wm, "proxy": proxy}, draws=200, seed=3)
    assert again["world_model"]["mean_ci"] == got["world_model"]["mean_ci"]  # seeded: reproducible
    with pytest.raises(ValueError, match="covers tasks"):
        S.within_task(true, {"world_model": {"a": wm["a"]}})


def test_bootstrap_draws_match_the_statistics_one_draw_at_a_time():
    # each draw's figures against the scalar statistics of the same resampling, drawn in the documented
    # order (a draw at a time, task by task: rows then states); ties (predictions on a 0.1 grid, a
    # policy drawn twice) and a proxy with unscored policies included
    rng = np.random.default_rng(5)
    true = {t: rng.uniform(size=(9, 7)) < rng.uniform(size=(9, 1)) for t in "ab"}
    wm = {t: np.round(np.clip(true[t] * 0.6 + rng.uniform(0, 0.4, (9, 7)), 0, 1), 1) for t in "ab"}
    proxy = {t: np.where(rng.uniform(size=9) < 0.3, np.nan, rng.normal(size=9)) for t in "ab"}
    draws = 40
    _, boot = S.within_task_draws(true, {"wm": wm, "proxy": proxy}, draws=draws, seed=11)
    pick = np.random.default_rng(11)
    for d in range(draws):
        for t in "ab":
            rows, cols = pick.integers(0, 9, 9), pick.integers(0, 7, 7)
            tr = true[t][rows][:, cols]
            pw = wm[t][rows][:, cols]
            ps = proxy[t][rows]
            keep = ~np.isnan(ps)
            for name, p, rates, aligned in (
                    ("wm", np.round(pw.mean(1), 12), tr.mean(1), S.alignment(pw >= 0.5, tr)),
                    ("proxy", ps[keep], tr[keep].mean(1), math.nan)):
                want = {"pearson": S.pearson(p, rates)[0], "spearman": S.spearman(p, rates), "mmrv": S.mmrv(p, rates),
                        "pairwise_acc_gap10": S.pairwise_accuracy(p, rates, 0.10), "alignment": aligned}
                for k, v in want.items():
                    got = boot[name][t][k][d]
                    assert (math.isnan(v) and math.isnan(got)) or got == pytest.approx(v, abs=1e-9), (d, t, name, k)


def test_checkpoint_selection_by_hand():
    def row(task, lineage, step, true, pred):
        return {"task": task, "lineage": lineage, "step": step, "true_rate": true, "pred_rate": pred,
                "true_ci": [true - 0.1, true + 0.1]}

    rows = [row("mug", "a", 10, 0.2, 0.1), row("mug", "a", 100, 0.9, 0.3), row("mug", "a", 1000, 0.85, 0.8),
            row("mug", "b", 10, 0.5, 0.5), row("mug", "b", 100, 0.7, 0.6),
            row("mug", "c", 10, 0.4, 0.4),  # one checkpoint: nothing to pick
            row("mug", "d", 5, 1.0, 0.9), row("mug", "d", 1000, 1.0, 0.2),  # a pick that ties the truly best is it
            {"task": "mug", "lineage": "plugin", "step": None, "true_rate": 1.0, "pred_rate": 1.0, "true_ci": [0, 1]}]
    got = S.checkpoint_selection(rows)
    a, b, d = got["lineages"]
    assert (a["picked_step"], a["best_step"], a["exact"], a["within_ci"]) == (1000, 100, False, True)
    assert a["regret"] == pytest.approx(0.05)
    assert (b["picked_step"], b["best_step"], b["exact"], b["regret"]) == (100, 100, True, 0.0)
    assert (d["picked_step"], d["best_step"], d["exact"], d["regret"]) == (5, 5, True, 0.0)
    assert (a["best_tied"], b["best_tied"], d["best_tied"]) == (1, 1, 2)
    assert got["n"] == 3 and got["exact_share"] == pytest.approx(2 / 3) and got["within_ci_share"] == 1.0
    assert got["mean_regret"] == pytest.approx(0.05 / 3)
    assert math.isnan(S.checkpoint_selection(rows[-2:])["exact_share"])
    diverged = rows[:2] + [row("mug", "a", 1000, 0.85, math.nan)]  # a checkpoint whose imagination diverged
    assert S.checkpoint_selection(diverged)["lineages"][0]["picked_step"] == 100
    best_diverged = [row("mug", "a", 10, 0.2, 0.1), row("mug", "a", 100, 0.9, math.nan),
                     row("mug", "a", 1000, 0.5, 0.3)]
    (got,) = S.checkpoint_selection(best_diverged)["lineages"]  # the truly best is still the best, though unread
    assert (got["picked_step"], got["best_step"], got["regret"]) == (1000, 100, pytest.approx(0.4))
    unread = S.checkpoint_selection([row("mug", "a", s, 0.5, math.nan) for s in (10, 100)] + rows[3:5])
    assert (unread["n"], unread["unread"]) == (1, 1)  # lineage a has two checkpoints, neither read


def test_family_statistics_by_hand():
    def row(lineage, step, true, pred, task="mug"):
        return {"task": task, "lineage": lineage, "step": step, "true_rate": true, "pred_rate": pred}

    rows = [row("conv", 100, 0.3, 0.5), row("conv", 1000, 0.9, 0.8),  # the base: conv's last checkpoint
            row("conv~noise", None, 0.6, 0.7), row("conv~noise", None, 0.1, 0.4),
            row("conv~grip", None, 0.5, 0.5), row("other", 5, 0.2, 0.2)]
    got = S.family_statistics(rows)
    noise, grip = (next(f for f in got["families"] if f["family"] == k) for k in ("conv~noise", "conv~grip"))
    # noise: base (0.9, 0.8), (0.6, 0.7), (0.1, 0.4)
    assert noise["n"] == 3 and noise["true_range"] == [0.1, 0.9]
    assert noise["pearson"] == pytest.approx(np.corrcoef([0.8, 0.7, 0.4], [0.9, 0.6, 0.1])[0, 1])
    assert noise["mean_abs_error"] == pytest.approx((0.1 + 0.1 + 0.3) / 3)
    # grip: base and one level, two points, which always lie on a line: no r, but an error
    assert grip["n"] == 2 and math.isnan(grip["pearson"]) and grip["mean_abs_error"] == pytest.approx(0.05)
    assert got["mean_pearson"] == pytest.approx(noise["pearson"])
    assert got["mean_abs_error"] == pytest.approx((noise["mean_abs_error"] + 0.05) / 2)
    assert math.isnan(S.family_statistics([row("conv", 1, 0.1, 0.2)])["mean_pearson"])
    # without the rows' episodes no ceiling; with them, the perfect predictor's r against that truth
    assert math.isnan(noise["pearson_ceiling"]) and math.isnan(got["mean_pearson_ceiling"])
    counted = S.family_statistics([dict(r, n=4) for r in rows])
    noise, grip = (next(f for f in counted["families"] if f["family"] == k) for k in ("conv~noise", "conv~grip"))
    assert noise["pearson_ceiling"] == S.pearson_ceiling([0.6, 0.1, 0.9], [4, 4, 4])
    assert math.isnan(grip["pearson_ceiling"]) and counted["mean_pearson_ceiling"] == noise["pearson_ceiling"]
    # a level whose imagination diverged is left out of its family, not the family out of the figures
    diverged = rows + [row("conv~noise", None, 0.0, math.nan)]
    again = S.family_statistics(diverged)
    noise_again = next(f for f in again["families"] if f["family"] == "conv~noise")
    assert noise_again["n"] == 3 and noise_again["unread"] == 1
    assert noise_again["pearson"] == pytest.approx(noise["pearson"])
    assert again["mean_abs_error"] == pytest.approx(got["mean_abs_error"])


def test_pearson_ceiling_is_a_perfect_predictors_r_against_the_truth_measured_again():
    assert S.pearson_ceiling([0.0, 1.0, 1.0], [5, 5, 5]) == 1.0  # rates of 0 and 1 are measured exactly again
    # the middle policy measured again from one episode reads 0 or 1; either way r = sqrt(3) / 2
    assert S.pearson_ceiling([0.0, 0.5, 1.0], [9, 1, 9], draws=50) == pytest.approx(np.sqrt(3) / 2)
    assert math.isnan(S.pearson_ceiling([0.9, 0.9], [50, 50]))  # no spread: r undefined for any predictor
    close = [0.8, 0.85, 0.9, 0.95]
    assert S.pearson_ceiling(close, [20] * 4) < S.pearson_ceiling(close, [2000] * 4) <= 1.0


def test_mmrv_floor_is_a_perfect_predictors_mmrv_against_resampled_truth():
    # two policies at 0.5 measured on 2 episodes each: every rate is 0, 0.5 or 1 (1/4, 1/2, 1/4);
    # the tied prediction charges each pair its true gap once, so MMRV = |a - b| / 2; the draws where
    # the two measure alike (3/8) leave it undefined, and over the others (a gap of 0.5 with
    # probability 1/2, of 1 with 1/8) its expectation is (0.5 * 0.5 + 0.125 * 1) / (5 / 8) / 2 = 0.3
    half = {"t": np.array([[1, 0], [0, 1]])}
    got = S.mmrv_floor(half, draws=4000, seed=1)
    assert got["per_task"]["t"] == pytest.approx(0.3, abs=0.01) and got["draws"] == 4000
    # rates of 0 and 1 are measured exactly again: no violation is possible
    sure = {"a": np.array([[0, 0, 0], [1, 1, 1]]), "b": np.array([[1, 1], [1, 1], [0, 0]])}
    assert S.mmrv_floor(sure, draws=50) == {"per_task": {"a": 0.0, "b": 0.0}, "mean": 0.0, "draws": 50}
    both = S.mmrv_floor({**half, **sure}, draws=4000, seed=1)
    assert both["mean"] == pytest.approx(np.mean(list(both["per_task"].values())))
    # a task whose policies all succeed alike has no floor, and the mean leaves it out
    alike = S.mmrv_floor({**sure, "c": np.ones((3, 4))}, draws=50)
    assert math.isnan(alike["per_task"]["c"]) and alike["mean"] == 0.0
    # more episodes, a lower floor
    many = {"t": np.array([[1, 0] * 50, [0, 1] * 50])}
    assert S.mmrv_floor(many, draws=400)["mean"] < got["mean"] / 3


def test_mean_interval_is_a_t_interval():
    mean, ci = S.mean_interval([0.5, 0.7, 0.9, None])
    # mean 0.7, sd 0.2, n 3: t(0.975, 2) = 4.302653
    half = 4.302653 * 0.2 / np.sqrt(3)
    assert mean == pytest.approx(0.7) and ci == pytest.approx([0.7 - half, 0.7 + half], abs=1e-5)
    assert S.mean_interval([0.3]) == (0.3, None) and S.mean_interval([None]) == (None, None)
    assert S.mean_interval([0.5, 0.7, 0.9], (0.0, 0.8))[1] == pytest.approx([0.7 - half, 0.8])  # a rate's range


def test_a_policy_whose_predictions_diverged_is_left_out_as_a_proxys_unscored_one():
    """A world model's NaN probability (an imagination that diverged) leaves its policy out of every
    statistic, alignment included, as a proxy's missing score does: the figures of the other policies,
    not a NaN Pearson dropped from the mean or a NaN read as a predicted failure."""
    rng = np.random.default_rng(3)
    true = (rng.random((5, 8)) < np.array([0.9, 0.7, 0.5, 0.3, 0.1])[:, None]).astype(float)
    pred = np.clip(true.mean(1)[:, None] + 0.1 * rng.standard_normal((5, 8)), 0, 1)
    broken = pred.copy()
    broken[2, 3] = math.nan
    keep = [0, 1, 3, 4]
    got, ref = S.task_statistics(broken, true), S.task_statistics(pred[keep], true[keep])
    for k in S.WITHIN_TASK:
        assert got[k] == pytest.approx(ref[k]), k
    # and in every bootstrap draw, whichever of its episodes the draw picks: the draws of a row all NaN
    whole = broken.copy()
    whole[2] = math.nan
    _, some = S.within_task_draws({"t": true}, {"p": {"t": broken}}, draws=200)
    _, every = S.within_task_draws({"t": true}, {"p": {"t": whole}}, draws=200)
    for k in S.WITHIN_TASK:
        np.testing.assert_array_equal(some["p"]["t"][k], every["p"]["t"][k])
    # the reviewer's case: rates 1, 0.5, 0 with the middle one unread ranks the other two perfectly
    three = S.task_statistics(np.array([[1.0], [math.nan], [0.0]]), np.array([[1.0], [1.0], [0.0]]))
    assert three["mmrv"] == 0 and three["pairwise_acc_gap10"] == 1


def test_the_difference_to_a_proxy_compares_the_policies_both_score():
    """A plug-in has no imitation loss: the world model minus the proxy is taken over the checkpoints
    the proxy scores, so adding a plug-in the world model reads well does not move the difference."""
    rng = np.random.default_rng(4)
    rates = np.array([0.9, 0.6, 0.4, 0.1, 0.0])
    true = {"t": (rng.random((5, 10)) < rates[:, None]).astype(float)}
    wm = {"t": rng.random((5, 10))}  # a poor world model
    wm["t"][4] = 0.0  # the plug-in (last), truly 0: read exactly
    proxy = {"t": np.array([3.0, 1.0, 2.0, 0.0, math.nan])}
    both = S.within_task(true, {"world_model": wm, "proxy": proxy}, draws=50)
    alone = S.within_task({"t": true["t"][:4]}, {"world_model": {"t": wm["t"][:4]}, "proxy": {"t": proxy["t"][:4]}},
                          draws=50)
    for k in S.WITHIN_TASK:
        want = alone["difference"]["proxy"]["per_task"]["t"][k]
        got = both["difference"]["proxy"]["per_task"]["t"][k]
        assert got == pytest.approx(want, nan_ok=True), k
    # the world model's own row keeps every policy it scores, the plug-in included
    own = both["world_model"]["per_task"]["t"]["pearson"]
    assert own != pytest.approx(alone["world_model"]["per_task"]["t"]["pearson"])
    # and the difference says what it compares: each side over the four policies both score
    shared = both["difference"]["proxy"]["shared"]
    assert (shared["policies"], shared["of"]) == (4, 5) and "shared" not in alone["difference"]["proxy"]
    for side, name in (("first", "world_model"), ("other", "proxy")):
        assert shared[side]["mean"]["pearson"] == pytest.approx(alone[name]["mean"]["pearson"])


def test_a_task_whose_statistic_is_undefined_is_left_out_of_its_draws_too():
    """Every policy of "flat" succeeds on half its states, other states each: Pearson r is undefined
    there, and a resampled draw that happens to define it must not count in the intervals."""
    rng = np.random.default_rng(2)
    flat = np.zeros((5, 16))
    for i in range(5):
        flat[i, rng.permutation(16)[:8]] = 1.0
    true = {"flat": flat, "t": (rng.random((5, 16)) < np.array([0.9, 0.7, 0.5, 0.3, 0.1])[:, None]).astype(float)}
    wm = {t: np.clip(v + rng.normal(0, 0.3, v.shape), 0, 1) for t, v in true.items()}
    got = S.within_task(true, {"world_model": wm}, draws=200)["world_model"]
    assert math.isnan(got["per_task"]["flat"]["pearson"])
    assert all(math.isnan(x) for x in got["per_task_ci"]["flat"]["pearson"])
    assert got["mean"]["pearson"] == pytest.approx(got["per_task"]["t"]["pearson"])
    assert got["mean_ci"]["pearson"] == pytest.approx(got["per_task_ci"]["t"]["pearson"])


def test_a_bootstrap_draw_of_fewer_than_three_distinct_policies_has_no_correlation():
    # three policies: most draws hold one of them twice, and two policies drawn as three lie on a line
    rng = np.random.default_rng(1)
    levels = np.array([0.25, 0.5, 0.75])
    true = {"t": (rng.random((3, 16)) < levels[:, None]).astype(float)}
    wm = {"t": np.clip(levels[:, None] + rng.normal(0, 0.3, (3, 16)), 0, 1)}
    _, boot = S.within_task_draws(true, {"wm": wm}, draws=300, seed=0)
    pick = np.random.default_rng(0)
    for d in range(300):
        rows, _ = pick.integers(0, 3, 3), pick.integers(0, 16, 16)
        for k in ("pearson", "spearman"):
            got = boot["wm"]["t"][k][d]
            assert math.isnan(got) == (len(set(rows.tolist())) < S.MIN_CORRELATED), (d, k, rows)


def test_policy_count_says_policy_for_one_and_counts_pairs_where_a_policy_runs_on_several_tasks():
    assert S.policy_count([{"name": "a", "task": "mug"}]) == "1 policy"
    assert S.policy_count([{"name": "a", "task": "mug"}, {"name": "b", "task": "mug"}]) == "2 policies"
    assert S.policy_count([{"name": "a", "task": "mug"}, {"name": "a", "task": "step_back"}]) == (
        "1 policy, 2 policy-task pairs")
