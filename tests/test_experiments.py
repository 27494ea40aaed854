"""The evaluator and the report end to end on the smoke world model and zoo (CPU, tiny)."""

import json

import numpy as np
import pytest

from experiments import evaluate as E
from experiments import stats as S
from experiments.report import write_report

from conftest import build_once


@pytest.fixture(scope="module")
def evaluation(smoke_zoo, smoke_world_model, tmp_path_factory, worker_id):
    zoo_dir, _ = smoke_zoo
    cfg = E.EvalConfig(policies=(f"{zoo_dir}#conv_proprio+conv_noproprio", "examples.plugin_policy:make"),
                       wm=str(smoke_world_model), tasks=("mug",), episodes=2, batch=64, video_policies=2,
                       video_episodes=1, decision_episodes=(5, 50))
    out = build_once(tmp_path_factory, worker_id, "eval", lambda d: E.run(cfg, d / "run", progress=False)) / "run"
    return cfg, out, json.loads((out / "results.json").read_text())


def test_results_hold_every_policy_with_statistics_from_the_episodes(evaluation, smoke_dataset):
    cfg, out, res = evaluation
    assert json.loads((out / "results.json").read_text())["tasks"] == ["mug"]
    names = [p["name"] for p in res["policies"]]
    assert len(names) == 5 and "examples.plugin_policy:make" in names
    with np.load(out / "tasks" / "mug.npz") as z:
        true, prob = z["true"].astype(bool), z["prob"]
        meta = json.loads(z["meta"].tobytes().decode())
    assert true.shape == prob.shape == (5, 2) and meta["names"] == names
    for row, t, p in zip(res["policies"], true, prob, strict=True):
        assert row["true_rate"] == t.mean() and row["n"] == 2
        assert row["true_ci"] == pytest.approx(list(S.wilson_interval(int(t.sum()), 2)))
        assert row["pred_rate"] == pytest.approx(p.mean()) and 0 <= row["pred_rate"] <= 1
    m = res["metrics"]["overall"]
    assert m["alignment"] == pytest.approx(S.alignment(prob >= cfg.threshold, true))
    assert m["mmrv"] == pytest.approx(S.mmrv([p["pred_rate"] for p in res["policies"]],
                                             [p["true_rate"] for p in res["policies"]]))
    assert "baseline" in m and res["metrics"]["per_task"]["mug"]["n_policies"] == 5
    # the initial states are held out from the training data
    used = {json.loads(line)["seed"] for line in (smoke_dataset[1] / "manifest.jsonl").read_text().splitlines()}
    assert not set(meta["seeds"]) & used and len(set(meta["seeds"])) == 2


def test_rerun_resumes_and_other_config_is_refused(evaluation):
    cfg, out, res = evaluation
    stamp = (out / "tasks" / "mug.npz").stat().st_mtime_ns
    again = E.run(cfg, out, progress=False)
    assert (out / "tasks" / "mug.npz").stat().st_mtime_ns == stamp
    assert again["policies"] == res["policies"]
    with pytest.raises(ValueError, match="another configuration"):
        E.run(E.EvalConfig(**{**cfg.__dict__, "episodes": 3}), out, progress=False)


def test_report_renders_figures_and_videos(evaluation):
    _, out, res = evaluation
    page = write_report(out).read_text()
    assert page.count("data:image/png;base64,") >= 4  # scatter, ranks, baseline, decision (+ controllability)
    assert page.count("data:image/webp;base64,") == len(res["videos"]) + len(res["controllability"])
    assert "Decision analysis" in page and "imitation-loss baseline" in page
    md = (out / "report.md").read_text()
    assert "| pearson |" in md and "examples.plugin_policy:make" in md


def test_bad_evaluation_settings_are_refused():
    with pytest.raises(ValueError, match="policy spec"):
        E.make_config("demo", ["policies="])
    with pytest.raises(ValueError, match="episodes"):
        E.make_config("demo", ["episodes=1"])
    with pytest.raises(ValueError, match="unknown preset"):
        E.make_config("huge")
