"""experiments.compare: two designs' seeds ranking one zoo, against the within-task statistics."""

import json
import math

import numpy as np
import pytest

from experiments import compare as C
from experiments import ensemble as E
from experiments import stats as S

TASKS = ("mug", "wipe")
P, N = 8, 12


def _truth(seed=0):
    rng = np.random.default_rng(seed)
    levels = np.linspace(0.05, 0.95, P)
    return {t: (rng.random((P, N)) < levels[:, None]).astype(int) for t in TASKS}


def _results(true, pred, seen=(), families=()):
    """An evaluate results.json of per-episode predictions pred {task: (P, N)}; seen: policy indices in the
    world model's data; families: those that are a counterfactual family's members."""
    return {"policies": [{"task": t, "name": f"{t}/p{i}", "lineage": "p~grip" if i in families else f"p{i}",
                          "true_episodes": true[t][i].tolist(), "pred_episodes": pred[t][i].tolist(),
                          "in_wm_data": i in seen}
                         for t in TASKS for i in range(P)]}


def _noisy(true, scale, seed):
    rng = np.random.default_rng(seed)
    return {t: np.clip(true[t].mean(1, keepdims=True) + scale * rng.standard_normal((P, 1)), 0, 1)
            * np.ones((1, N)) for t in TASKS}


def test_each_runs_figures_are_the_within_task_statistics_and_the_gain_their_difference_of_means():
    true = _truth()
    base = [_noisy(true, 0.3, s) for s in (1, 2)]
    design = [_noisy(true, 0.1, s) for s in (3, 4)]
    got = C.compare_groups(true, {"base": base, "design": design}, draws=50)
    for g, runs in (("base", base), ("design", design)):
        for i, run in enumerate(runs):
            want = S.within_task(true, {"wm": run}, draws=2)["wm"]["mean"]
            for k in S.WITHIN_TASK:
                assert got[g]["runs"][i][k] == pytest.approx(want[k])
        for k in S.WITHIN_TASK:
            vals = [r[k] for r in got[g]["runs"]]
            assert got[g]["mean"][k] == pytest.approx(np.mean(vals))
            assert got[g]["range"][k] == [min(vals), max(vals)]
    for k in S.WITHIN_TASK:
        assert got["gain"]["mean"][k] == pytest.approx(got["design"]["mean"][k] - got["base"]["mean"][k])
        per_task = np.mean([got["gain"]["per_task"][t][k] for t in TASKS])
        assert got["gain"]["mean"][k] == pytest.approx(per_task)


def test_a_design_that_reads_the_true_rates_wins_with_an_interval_that_excludes_zero():
    true = _truth(1)
    exact = {t: true[t].mean(1, keepdims=True) * np.ones((1, N)) for t in TASKS}
    shuffled = [{t: exact[t][np.random.default_rng(s).permutation(P)] for t in TASKS} for s in (5, 6)]
    got = C.compare_groups(true, {"base": shuffled, "design": [exact, exact]}, draws=200)
    assert got["design"]["mean"]["pearson"] == pytest.approx(1.0)
    assert got["design"]["mean"]["mmrv"] == pytest.approx(0.0)
    lo, hi = got["gain"]["mean_ci"]["pearson"]
    assert 0 < lo <= got["gain"]["mean"]["pearson"] <= hi
    assert got["gain"]["mean_ci"]["mmrv"][1] < 0


def test_evaluations_of_other_truth_or_other_policies_are_refused_and_unseen_means_unseen_by_every_run():
    true = _truth()
    a, b = _results(true, _noisy(true, 0.2, 1), seen=(0, 1)), _results(true, _noisy(true, 0.2, 2), seen=(1, 2))
    _, preds, unseen, family = C.episode_tables([a, b])
    assert len(preds) == 2 and unseen["mug"].tolist() == [False, False, False] + [True] * (P - 3)
    assert not family["mug"].any()
    other = _results({t: 1 - v for t, v in true.items()}, _noisy(true, 0.2, 2))
    with pytest.raises(ValueError, match="other true outcomes"):
        C.episode_tables([a, other])
    fewer = dict(b, policies=b["policies"][1:])
    with pytest.raises(ValueError, match="other policies"):
        C.episode_tables([a, fewer])
    with pytest.raises(ValueError, match="both groups"):
        C.compare_groups(true, {"base": [], "design": [true]})


def test_the_command_writes_both_subsets_and_prints_the_table(tmp_path, capsys):
    true = _truth(2)
    runs = []
    for i, scale in enumerate((0.3, 0.3, 0.05, 0.05)):
        d = tmp_path / f"run{i}"
        d.mkdir()
        (d / "results.json").write_text(json.dumps(_results(true, _noisy(true, scale, i), seen=(0, 1),
                                                            families=(6, 7))))
        runs.append(str(d))
    out = tmp_path / "cmp" / "c.json"
    assert C.main(["--base", *runs[:2], "--design", *runs[2:], "--names", "recipe,sharp", "--draws", "20",
                   "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert res["names"] == ["recipe", "sharp"] and res["unseen_policies"] == {"mug": P - 2, "wipe": P - 2}
    # the networks among the unseen: the two family members left out
    assert res["unseen_networks_policies"] == {"mug": P - 4, "wipe": P - 4}
    assert len(res["all"]["base"]["runs"]) == 2 and "gain" in res["unseen"]
    plain = [_results(true, _noisy(true, 0.05, i), seen=(0, 1)) for i in (2, 3)]
    direct = C.compare(plain[:1], plain[1:], draws=20)
    assert "unseen" in direct and "unseen_networks" not in direct  # no families: the unseen block is it
    sub = {t: v[2:6] for t, v in true.items()}
    want = S.within_task(sub, {"sharp": {t: _noisy(true, 0.05, 2)[t][2:6] for t in TASKS}}, draws=20)
    got = res["unseen_networks"]["design"]["runs"][0]
    assert got["pearson"] == pytest.approx(want["sharp"]["mean"]["pearson"])
    table = capsys.readouterr().out
    assert "| all | sharp - recipe |" in table and "| unseen | recipe (2 runs) |" in table
    assert "| unseen_networks | sharp - recipe |" in table
    assert "families" not in res and "| families |" not in table  # two members a task: too few to rank
    with pytest.raises(SystemExit):
        C.main(["--base", runs[0], "--design", runs[1], "--names", "one"])


def test_the_families_subset_ranks_their_members_alone_and_each_run_carries_its_mean_abs_error():
    true = _truth(3)
    fam = (4, 5, 6, 7)
    base = [_results(true, _noisy(true, 0.3, i), seen=fam, families=fam) for i in (0, 1)]
    design = [_results(true, _noisy(true, 0.05, i), seen=fam, families=fam) for i in (2, 3)]
    res = C.compare(base, design, draws=20)
    assert res["families_policies"] == {"mug": 4, "wipe": 4} and "unseen_networks" not in res  # no family unseen
    pred = _noisy(true, 0.05, 3)
    want = S.within_task({t: v[4:] for t, v in true.items()}, {"d": {t: pred[t][4:] for t in TASKS}}, draws=20)
    assert res["families"]["design"]["runs"][1]["pearson"] == pytest.approx(want["d"]["mean"]["pearson"])
    # |predicted - true rate| by hand: per task the mean over its family members, then over tasks
    by_hand = np.mean([np.abs(pred[t][4:].mean(1) - true[t][4:].mean(1)).mean() for t in TASKS])
    assert res["families"]["design"]["abs_error"][1] == pytest.approx(by_hand)
    assert res["all"]["base"]["abs_error"][0] > res["all"]["design"]["abs_error"][0]  # the noisier run errs more


def test_shifts_are_the_moves_of_each_policys_mean_predicted_rate_and_a_rerun_moves_none(tmp_path, capsys):
    true = _truth(4)
    base = [_noisy(true, 0.2, s) for s in (1, 2)]
    design = [{t: v.copy() for t, v in run.items()} for run in base]
    design[0]["wipe"][3] = np.clip(design[0]["wipe"][3] + 0.3, 0, 1)  # one run of one policy moved
    res = C.compare([_results(true, b) for b in base], [_results(true, d) for d in design], draws=5)
    top = res["shifts"][0]
    by_hand = (design[0]["wipe"][3].mean() - base[0]["wipe"][3].mean()) / 2  # the mean over the two runs
    assert (top["task"], top["name"]) == ("wipe", "wipe/p3") and top["shift"] == pytest.approx(by_hand)
    assert top["true"] == pytest.approx(true["wipe"][3].mean())
    assert top["base"] == pytest.approx(np.mean([b["wipe"][3].mean() for b in base]))
    assert len(res["shifts"]) == 2 * P and all(r["shift"] == 0 for r in res["shifts"][1:])
    assert f"1 of {2 * P} policies moved by more than 0.01." in C.shifts_markdown(res["shifts"])
    # the same evaluation twice: every rate where it was
    d = tmp_path / "run"
    d.mkdir()
    (d / "results.json").write_text(json.dumps(_results(true, base[0])))
    assert C.main(["--base", str(d), "--design", str(d), "--names", "first,again", "--draws", "5"]) == 0
    printed = capsys.readouterr().out
    assert f"the largest shift +0.000 (mug/p0); 0 of {2 * P} policies moved by more than 0.01 (the same figures)." \
        in printed
    assert "| policy | true | first | again | shift |" in printed


def _ensemble_run(path, true, members):
    """An evaluate OUT by an ensemble: results.json holding the members' mean, and OUT/tasks/<task>.npz
    with each member's per-episode probabilities (prob_members, (K, P, N)) in another policy order."""
    mean = {t: np.mean([m[t] for m in members], 0) for t in TASKS}
    path.mkdir()
    (path / "results.json").write_text(json.dumps(_results(true, mean, seen=(0,))))
    (path / "tasks").mkdir()
    for t in TASKS:
        order = list(range(P))[::-1]
        meta = json.dumps({"names": [f"{t}/p{i}" for i in order]}).encode()
        np.savez(path / "tasks" / f"{t}.npz", prob_members=np.stack([m[t][order] for m in members]),
                 prob=mean[t][order], meta=np.frombuffer(meta, np.uint8))


def _episode_noise(pred, seed):
    """pred with noise of its own on every episode, so that an episode read against another's outcome shows."""
    rng = np.random.default_rng(seed)
    return {t: np.clip(v + 0.02 * rng.standard_normal(v.shape), 0, 1) for t, v in pred.items()}


def test_a_member_of_an_ensemble_is_read_alone_and_compared_against_the_ensemble(tmp_path, capsys):
    true = _truth(4)
    members = [_episode_noise(_noisy(true, 0.3, 10), 12), _episode_noise(_noisy(true, 0.05, 11), 13)]
    _ensemble_run(tmp_path / "ens", true, members)
    for k, m in enumerate(members):
        got = E.read_run(f"{tmp_path / 'ens'}#{k}")
        rows = {(p["task"], p["name"]): p for p in got["policies"]}
        for t in TASKS:
            for i in range(P):
                row = rows[(t, f"{t}/p{i}")]
                assert row["pred_episodes"] == pytest.approx(m[t][i], abs=1e-5)
                assert row["pred_rate"] == pytest.approx(m[t][i].mean(), abs=1e-5)
                assert row["true_episodes"] == true[t][i].tolist() and row["in_wm_data"] == (i == 0)
    # member 1 alone is the sharper reading, the ensemble between the two: compare finds both so
    out = tmp_path / "cmp.json"
    assert C.main(["--base", f"{tmp_path / 'ens'}#0", "--design", f"{tmp_path / 'ens'}#1", "--names", "m0,m1",
                   "--draws", "20", "--out", str(out)]) == 0
    assert "| all | m1 - m0 |" in capsys.readouterr().out
    res = json.loads(out.read_text())
    assert res["base_runs"] == [f"{tmp_path / 'ens'}#0"] and res["all"]["gain"]["mean"]["pearson"] > 0
    ens = str(tmp_path / "ens")
    for worse, better in ((f"{ens}#0", ens), (ens, f"{ens}#1")):
        gain = C.compare([E.read_run(worse)], [E.read_run(better)], draws=20)["all"]["gain"]["mean"]
        assert gain["pearson"] > 0 and gain["mmrv"] <= 0
    with pytest.raises(ValueError, match="member 2 is not among them"):
        E.read_run(f"{tmp_path / 'ens'}#2")
    with pytest.raises(FileNotFoundError, match="not found"):  # no member's index: read as a path, absent
        E.read_run(f"{tmp_path / 'ens'}#last")
    odd = tmp_path / "run#1"  # a directory whose own name holds '#' is read as itself
    odd.mkdir()
    (odd / "results.json").write_text(json.dumps(_results(true, members[0])))
    assert E.read_run(odd)["policies"][0]["pred_episodes"] == pytest.approx(members[0]["mug"][0])
    (tmp_path / "solo").mkdir()
    (tmp_path / "solo" / "results.json").write_text(json.dumps(_results(true, members[0])))
    with pytest.raises(FileNotFoundError, match="tasks"):
        E.read_run(f"{tmp_path / 'solo'}#0")
    stale = json.loads((tmp_path / "ens" / "results.json").read_text())
    stale["policies"][0]["name"] = "mug/renamed"
    (tmp_path / "ens" / "results.json").write_text(json.dumps(stale))
    with pytest.raises(ValueError, match="holds no mug/renamed"):
        E.read_run(f"{tmp_path / 'ens'}#0")


def test_states_cut_every_run_to_the_same_initial_states_and_a_run_too_short_is_named(tmp_path, capsys):
    true = _truth(3)
    pred = _noisy(true, 0.2, 7)
    long_run, short_run = tmp_path / "s12", tmp_path / "s6"
    long_run.mkdir()
    short_run.mkdir()
    (long_run / "results.json").write_text(json.dumps(_results(true, pred)))
    # an evaluation of the first 6 states: the prefix of the 12-state one, as heldout_seeds draws them
    first = {t: v[:, :6] for t, v in true.items()}
    (short_run / "results.json").write_text(json.dumps(_results(first, {t: v[:, :6] for t, v in pred.items()})))
    with pytest.raises(ValueError, match="other true outcomes"):  # uncut, their truth differs in shape
        C.compare([E.read_run(str(short_run))], [E.read_run(str(long_run))], draws=5)
    out = tmp_path / "c.json"
    assert C.main(["--base", str(short_run), "--design", str(long_run), "--states", "0:6", "--draws", "20",
                   "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["states"] == [0, 6]
    want = S.within_task(first, {"wm": {t: v[:, :6] for t, v in pred.items()}}, draws=2)["wm"]["mean"]
    for g in ("base", "design"):
        assert res["all"][g]["runs"][0]["pearson"] == pytest.approx(want["pearson"])
        assert res["all"][g]["runs"][0]["mmrv"] == pytest.approx(want["mmrv"])
    assert res["all"]["gain"]["mean"]["pearson"] == 0.0
    assert "states 0 to 5" in capsys.readouterr().out
    # the later states alone: the same model's figures over another draw of states
    assert C.main(["--base", str(long_run), "--design", str(long_run), "--states", "6:12", "--draws", "5",
                   "--out", str(out)]) == 0
    later = S.within_task({t: v[:, 6:] for t, v in true.items()}, {"wm": {t: v[:, 6:] for t, v in pred.items()}},
                          draws=2)["wm"]["mean"]
    assert json.loads(out.read_text())["all"]["base"]["runs"][0]["pearson"] == pytest.approx(later["pearson"])
    with pytest.raises(ValueError, match=r"s6: mug/p0 ran 6 initial states, fewer than --states' end 12"):
        C.main(["--base", str(short_run), "--design", str(long_run), "--states", "0:12"])
    for bad in ("50", "5:5", "a:b", "-1:4"):
        with pytest.raises(SystemExit):
            C.main(["--base", str(short_run), "--design", str(long_run), "--states", bad])



def test_runs_ranked_by_judges_of_other_inputs_are_named_before_the_comparison(tmp_path, capsys):
    true = _truth(5)
    recorded = lambda readout, inputs, second: {"readout": readout, "judge_inputs": inputs, "judge2_inputs": second}
    old, new = recorded("judge", ["proprio", "action", "latent"], []), recorded("judge", ["proprio", "action"], [])
    assert C.ranked_reader({"world_model": new}) == "judge: proprio,action"
    assert C.ranked_reader({"world_model": recorded("judge2", ["latent"], ["proprio"])}) == "judge2: proprio"
    assert C.ranked_reader({"world_model": {"readout": "judge"}}) == "judge: inputs not recorded"
    assert C.ranked_reader({"world_model": {"readout": None}}) == C.ranked_reader({}) == "judge: inputs not recorded"
    assert C.ranked_reader({"world_model": recorded("progress", [], [])}) == "progress"
    assert C.reader_warning([{"world_model": new}] * 2, ["a", "b"]) is None
    runs = []
    for i, wm in enumerate((old, new)):
        d = tmp_path / f"run{i}"
        d.mkdir()
        (d / "results.json").write_text(json.dumps({**_results(true, _noisy(true, 0.1, i)), "world_model": wm}))
        runs.append(str(d))
    assert C.main(["--base", runs[0], "--design", runs[1], "--draws", "5"]) == 0
    err = capsys.readouterr().err
    assert "rank by different read-outs" in err
    assert f"{runs[0]}: judge: proprio,action,latent; {runs[1]}: judge: proprio,action" in err


def test_an_ensemble_and_its_members_keep_what_their_ranking_read(tmp_path):
    true = _truth(6)
    wm = {"readout": "judge", "judge_inputs": ["proprio", "action"], "judge2_inputs": []}
    def rated(res):  # the per-policy rates combine reads beside the episodes
        return {"policies": [{**p, "n": N, "true_rate": float(np.mean(p["true_episodes"])),
                              "pred_rate": float(np.mean(p["pred_episodes"]))} for p in res["policies"]]}

    runs = [{**rated(_results(true, _noisy(true, 0.1, s))), "world_model": wm} for s in (1, 2)]
    assert E.combine(runs)["world_model"] == wm
    other = {**runs[1], "world_model": {**wm, "judge_inputs": ["latent"]}}
    assert "world_model" not in E.combine([runs[0], other])
    members = [_noisy(true, 0.1, s) for s in (1, 2)]
    _ensemble_run(tmp_path / "ens", true, members)
    res = json.loads((tmp_path / "ens" / "results.json").read_text())
    (tmp_path / "ens" / "results.json").write_text(json.dumps({**res, "world_model": wm}))
    assert C.ranked_reader(E.read_run(f"{tmp_path / 'ens'}#1")) == "judge: proprio,action"


def test_a_policy_one_run_cannot_read_is_left_out_of_every_runs_statistics_and_shifts_stay_ordered():
    true = _truth()
    base = _noisy(true, 0.2, 1)
    base["mug"][0] = 1.0  # the base reads the worst policy as a sure success ...
    design = {t: v.copy() for t, v in base.items()}
    design["mug"][0] = np.nan  # ... and the design, otherwise the same, diverges there
    got = C.compare_groups(true, {"base": [base], "design": [design]}, draws=50)
    for k in S.WITHIN_TASK:
        assert got["gain"]["mean"][k] == pytest.approx(0.0), k
        assert got["gain"]["mean_ci"][k] == pytest.approx([0.0, 0.0]), k
    assert got["left_out"] == {"mug": [0]}
    assert got["design"]["abs_error"] == pytest.approx(got["base"]["abs_error"])  # finite, the same policies
    names = {t: [f"{t}/p{i}" for i in range(P)] for t in TASKS}
    moved = {t: base[t] + (0.3 if t == "wipe" else 0.0) for t in TASKS}
    moved["mug"] = design["mug"]
    shifts = C.rate_shifts(true, [base], [moved], names)
    assert shifts[0]["shift"] == pytest.approx(0.3) and math.isnan(shifts[-1]["shift"])


def test_alignment_is_read_at_the_evaluations_own_threshold():
    true = _truth()
    pred = _noisy(true, 0.2, 1)
    runs = [_results(true, pred) | {"config": {"threshold": 0.3}} for _ in range(2)]
    got = C.compare(runs[:1], runs[1:], draws=5)
    want = S.within_task(true, {"wm": pred}, threshold=0.3, draws=2)["wm"]["mean"]["alignment"]
    assert got["all"]["base"]["mean"]["alignment"] == pytest.approx(want)
    with pytest.raises(ValueError, match="threshold"):
        C.compare(runs[:1], [runs[1] | {"config": {"threshold": 0.5}}], draws=5)
