"""experiments.design: the runs of a design decision, resumed, and their comparison."""

import json

import numpy as np
import pytest

from experiments import design as D
from experiments.pipeline import pipeline
from wm.config import make_config

TASKS = ("mug", "step_back")


def test_the_plan_trains_each_seed_of_both_designs_on_the_presets_data_and_evaluates_them_alike(tmp_path):
    jobs = D.plan("demo", "anchor", ["model.anchor=true"], seeds=2, steps=300, design_steps=200, episodes=8,
                  root=tmp_path)
    assert [(j.design, j.seed) for j in jobs] == [("anchor", 0), ("anchor", 1), ("recipe", 0), ("recipe", 1)]
    d = pipeline("demo").dirs("demo")
    for j in jobs:
        t = list(j.train_argv)
        assert t[t.index("--data") + 1] == str(d["wm_data"]) and t[t.index("--out") + 1] == str(j.wm)
        assert f"seed={j.seed}" in t and ("model.anchor=true" in t) == (j.design == "anchor")
        assert f"steps={200 if j.design == 'anchor' else 300}" in t
        e = list(j.eval_argv)
        assert e[e.index("--out") + 1] == str(j.eval) and f"wm={j.wm}" in e and "episodes=8" in e
        assert f"policies={d['policies']}" in e
        assert e[-4:-2] == ["video_policies=0", f"truth_cache={tmp_path / 'truth'}"]  # one simulation for every run
        assert e[-2:] == ["geometric=", "geometric_ranks=0"]  # the designs' own read-out, not the demo's rules
    assert [j.wm.parent.relative_to(tmp_path) for j in jobs] == [
        D.Path("anchor/200steps_s0"), D.Path("anchor/200steps_s1"), D.Path("recipe/300steps_s0"),
        D.Path("recipe/300steps_s1")]
    assert len({j.wm for j in jobs}) == 4 and all(j.eval.name == "eval_e8" for j in jobs)
    with pytest.raises(ValueError, match="unknown setting"):
        D.plan("demo", "typo", ["model.anchr=true"])
    with pytest.raises(ValueError, match="state_batch must divide episodes"):  # full's state batch is 50
        D.plan("full", "anchor", ["model.anchor=true"], episodes=30)
    for bad in ({"name": "recipe"}, {"name": "recipe2"}, {"overrides": []}, {"overrides": ["model.anchor"]}, {"seeds": 0}):
        with pytest.raises(ValueError):
            D.plan("demo", **({"name": "x", "overrides": ["a=1"]} | bad))


def _results(true, rates, seen):
    return {"policies": [{"task": t, "name": f"{t}/p{i}", "true_episodes": true[t][i].tolist(),
                          "pred_episodes": [float(rates[t][i])] * true[t].shape[1], "in_wm_data": i in seen}
                         for t in TASKS for i in range(len(rates[t]))]}


def test_runs_resume_share_the_recipe_and_the_comparison_is_written(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    levels = np.linspace(0.05, 0.95, 8)
    true = {t: (rng.random((8, 10)) < levels[:, None]).astype(int) for t in TASKS}
    calls = []

    def fake_train(argv):
        out = D.Path(argv[argv.index("--out") + 1])
        out.mkdir(parents=True)
        D.check_run_config(make_config(argv[1], argv[6:]), D.Path(argv[3]), out)  # config.json, as a run writes
        auroc = 0.9 if "/anchor/" in str(out) else 0.8
        (out / "eval.json").write_text(json.dumps({"summary": {"success_auroc": auroc, "psnr_h8": 22.0}}))
        calls.append(("train", out))

    def fake_eval(argv):
        out = D.Path(argv[argv.index("--out") + 1])
        noise = 0.02 if "/anchor/" in str(out) else 0.3
        out.mkdir(parents=True, exist_ok=True)
        rates = {t: np.clip(true[t].mean(1) + noise * rng.standard_normal(8), 0, 1) for t in TASKS}
        (out / "results.json").write_text(json.dumps(_results(true, rates, seen=(0, 1))))
        calls.append(("eval", out))

    monkeypatch.setattr(D.train, "main", fake_train)
    monkeypatch.setattr(D.evaluate, "main", fake_eval)
    monkeypatch.setattr(D, "check_inputs", lambda preset: None)
    monkeypatch.setattr(D, "local_gpus", list)
    monkeypatch.setattr(D, "use_compilation_cache", lambda root: None)
    args = ["demo", "anchor", "model.anchor=true", "--seeds", "2", "--root", str(tmp_path), "--draws", "50"]
    assert D.main(args) == 0
    assert len(calls) == 8
    res = json.loads((tmp_path / "anchor" / "compare.json").read_text())
    assert res["names"] == ["recipe", "anchor"] and len(res["all"]["design"]["runs"]) == 2
    assert res["all"]["gain"]["mean"]["pearson"] > 0
    assert "| all | anchor - recipe |" in (tmp_path / "anchor" / "compare.md").read_text()
    assert json.loads((tmp_path / "anchor" / "plan.json").read_text())["overrides"] == ["model.anchor=true"]
    assert (tmp_path / "anchor" / "compare.png").stat().st_size > 0
    assert [r["stage"] for r in res["timing"]["anchor_s0"]] == ["train", "eval"]
    assert "| recipe_s1 | eval |" in (tmp_path / "anchor" / "compare.md").read_text()
    assert res["held_out"]["anchor_s1"]["success_auroc"] == 0.9
    assert "| recipe (mean) | 22.000 |  |  | 0.800 |" in (tmp_path / "anchor" / "compare.md").read_text()
    D.main(args)  # everything finished: nothing runs again
    assert len(calls) == 8
    D.main(["demo", "other", "model.dim=64", "--seeds", "2", "--root", str(tmp_path), "--draws", "50"])
    assert len(calls) == 12 and all("/other/" in str(out) for _, out in calls[8:])  # the recipe's runs are shared
    with pytest.raises(SystemExit, match="name the design anew"):  # the same name, other settings
        D.main(["demo", "anchor", "model.dim=64", "--seeds", "2", "--root", str(tmp_path), "--draws", "50"])


def test_missing_data_names_the_stage_to_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit, match="--stage rollouts"):
        D.check_inputs("demo")
