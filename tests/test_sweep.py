"""Sweeps: the per-value statistics against hand-computed ones, results read back, bad names refused."""

import html
import json

import numpy as np
import pytest

from experiments import sweep as W


def test_collect_reads_every_finished_run(tmp_path):
    runs = W.data_scaling(W.Size(train="demo", steps=100, seeds=2, data={}))
    assert [r.x for r in runs] == [0.125, 0.125, 0.25, 0.25, 0.5, 0.5, 1.0, 1.0]
    assert "train_fraction=0.125" in runs[0].overrides and "seed=1" in runs[1].overrides
    for k, r in enumerate(runs[:-1]):  # the last run has not finished
        (tmp_path / r.name).mkdir(parents=True)
        summary = {"psnr_h8": 20.0 + k, "success_auroc": 0.5 + 0.05 * k}
        (tmp_path / r.name / "eval.json").write_text(json.dumps({"summary": summary}))
    (tmp_path / runs[0].name / W.BODY_FILE).write_text(json.dumps({"summary": {"body_psnr_h8": 18.0}}))
    true, preds = [0.1, 0.5, 0.9], ([0.2, 0.4, 0.9], [0.4, 0.2, 0.7])
    for k, r in enumerate(runs[:2]):  # experiments.evaluate's results.json of the zoo ranked by each model
        (tmp_path / r.name / W.RANK_DIR).mkdir()
        overall = {"pearson": 0.6 + 0.2 * k, "mmrv": 0.2, "alignment": 0.75}
        policies = [{"name": n, "task": "mug", "n": 64, "true_rate": t, "pred_rate": p}
                    for n, t, p in zip("abc", true, preds[k], strict=True)]
        (tmp_path / r.name / W.RANK_DIR / "results.json").write_text(
            json.dumps({"metrics": {"pooled": overall}, "policies": policies}))
    res = W.collect("data_scaling", "demo", runs, tmp_path, "share")
    assert [e["seeds"] for e in res["per_x"]] == [2, 2, 2, 1]
    assert res["runs"][0]["body_psnr_h8"] == 18.0 and res["per_x"][0]["body_psnr_h8"] == 18.0  # the other seed has none
    assert res["per_x"][1]["body_psnr_h8"] is None
    assert res["per_x"][0]["psnr_h8"] == pytest.approx(20.5) and res["per_x"][3]["psnr_h8"] == pytest.approx(26.0)
    assert res["per_x"][3]["psnr_h8_ci"] is None and res["per_x"][0]["match_accuracy"] is None
    assert res["per_x"][0]["pearson"] == pytest.approx(0.7) and res["per_x"][0]["mmrv_ci"] == pytest.approx([0.2, 0.2])
    assert res["runs"][2]["pearson"] is None and res["per_x"][1]["alignment"] is None
    assert "0.525 -> 0.8" in res["finding"]
    # the two seeds' models ranked together: their predicted rates averaged, (0.3, 0.3, 0.8)
    ens = np.corrcoef([0.3, 0.3, 0.8], true)[0, 1]
    assert res["per_x"][0]["ensemble_pearson"] == pytest.approx(ens) and res["per_x"][0]["ensemble_models"] == 2
    assert "ensemble_pearson" not in res["per_x"][1] and res["ensemble"]["ensemble_pearson"] == pytest.approx(ens)
    W.plot(res, tmp_path / "sweep.png", log_x=True)
    assert (tmp_path / "sweep.png").stat().st_size > 1000


def test_task_scaling_always_trains_on_the_evaluated_task():
    for r in W.task_scaling(W.SIZES["demo"]):
        tasks = next(o for o in r.overrides if o.startswith("train_tasks=")).split("=")[1].split(",")
        assert "mug" in tasks and len(tasks) == int(r.x) and "eval_tasks=mug" in r.overrides


def test_unknown_sweep_and_size_are_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown sweep"):
        W.run_sweeps(["data_scaling", "moon_scaling"], "demo", tmp_path)
    with pytest.raises(ValueError, match="unknown size"):
        W.run_sweeps(["data_scaling"], "huge", tmp_path)


def test_transfer_held_out_and_rollout_sweeps_are_built_as_described():
    size = W.SIZES["demo"]
    runs = W.transfer(size)
    assert [(r.x, r.data) for r in runs] == [(1.0, "shelf_arcade"), (2.0, "shelf_arcade")]
    assert all("eval_tasks=shelf" in r.overrides for r in runs) and "train_tasks=shelf" in runs[0].overrides
    held = W.held_out_object(size)
    assert [(r.x, r.trains, r.evaluated_apart, r.eval_data) for r in held] == [
        (0.0, True, False, None), (1.0, False, True, "heldout")]
    assert held[1].model_of == held[0].name  # the same model, judged on the unseen scenes
    auto = W.autonomous_rollouts(size)
    assert [(r.x, r.data, r.eval_data, r.evaluated_apart) for r in auto] == [
        (0.0, "base", "mixed", True), (0.5, "mixed", "mixed", False)]
    assert any("{zoo}" in o for o in size.data["mixed"][1])  # the rollouts come from the zoo


def test_evaluating_elsewhere_refuses_training_settings(capsys):
    from wm import quality

    with pytest.raises(SystemExit):
        quality.main(["--wm", "x", "--data", "y", "--out", "z", "lr=0.1"])
    assert "only evaluation settings" in capsys.readouterr().err


def test_report_gains_a_section_per_sweep(tmp_path):
    from experiments.report import sweep_sections

    runs = W.held_out_object(W.Size(train="demo", steps=100, seeds=1, data={}))
    d = tmp_path / "held_out_object_demo"
    for k, r in enumerate(runs):
        (d / r.name).mkdir(parents=True)
        (d / r.name / "eval.json").write_text(json.dumps({"summary": {"psnr_h8": 18.0 - k, "success_auroc": 0.7}}))
    assert W.main(["held_out_object", "--size", "demo", "--out", str(d), "--collect"]) == 0  # runs nothing
    res = json.loads((d / "results.json").read_text())
    assert res == W.collect("held_out_object", "demo", runs, d, W.SWEEPS["held_out_object"][1])
    (d / runs[1].name / "eval_frames.png").write_bytes((d / "sweep.png").read_bytes())
    parts, md = sweep_sections(tmp_path)
    page = "\n".join(parts)
    assert "Sweep held_out_object (demo)" in page and html.escape(res["finding"]) in page
    assert page.count("data:image/png;base64,") == 2  # the curves and the last value's frames
    assert "| 1 | 1 | 17.000 |" in "\n".join(md)


def test_jobs_wait_for_what_they_need_and_are_dropped_when_it_failed():
    order, lock = [], __import__("threading").Lock()

    def job(name, ok=True):
        def fn(gpu):
            with lock:
                order.append((name, gpu))
            return ok
        return fn

    jobs = [W.Job("run", job("run"), frozenset({"data", "zoo"})),
            W.Job("data", job("data")),
            W.Job("zoo", job("zoo", ok=False), frozenset({"data"})),
            W.Job("train", job("train"), frozenset({"data"})),
            W.Job("rank", job("rank"), frozenset({"train", "zoo"}))]
    done = W.on_gpus(jobs, ["0", "1"])
    assert done == {"data": True, "zoo": False, "train": True, "run": False, "rank": False}
    names = [n for n, _ in order]
    assert names[0] == "data" and set(names) == {"data", "zoo", "train"}  # run and rank never started
    assert {g for _, g in order} <= {"0", "1"}
    with pytest.raises(ValueError, match="which no job makes"):
        W.on_gpus([W.Job("a", job("a"), frozenset({"b"}))], [None])


def test_a_gpu_takes_the_ready_job_that_heads_the_longest_chain():
    order = []
    job = lambda name: lambda gpu: order.append(name) or True
    jobs = [W.Job("rank_a", job("rank_a"), frozenset({"eval_a"})),
            W.Job("eval_a", job("eval_a"), frozenset({"train_a"})),
            W.Job("lone", job("lone")),
            W.Job("train_a", job("train_a")),
            W.Job("train_b", job("train_b")),
            W.Job("eval_b", job("eval_b"), frozenset({"train_b"}))]
    assert W.chain_lengths(jobs) == {"rank_a": 1, "eval_a": 2, "lone": 1, "train_a": 3, "train_b": 2, "eval_b": 1}
    W.on_gpus(jobs, [None])
    # longest chain first; among equals the first in the list (eval_a before train_b, lone before eval_b)
    assert order == ["train_a", "eval_a", "train_b", "rank_a", "lone", "eval_b"]


def test_a_run_evaluating_another_runs_model_waits_for_it(tmp_path):
    plan = W.Plan("held_out_object", "demo", W.held_out_object(W.SIZES["demo"]), tmp_path, "x", False)
    data, jobs = W.data_jobs(W.SIZES["demo"], ["base", "heldout"], tmp_path)
    jobs += W.run_jobs(plan, data, tmp_path, 0.0)
    needs = {j.name: j.needs for j in jobs}
    assert needs["held_out_object/x=1/seed=0"] == {"data:heldout", "held_out_object/x=0/seed=0"}
    assert needs["held_out_object/x=0/seed=0"] == {"data:base"} and "zoo" not in needs
    ranked = W.Plan("autonomous_rollouts", "demo", W.autonomous_rollouts(W.SIZES["demo"]), tmp_path, "x", False)
    data, jobs = W.data_jobs(W.SIZES["demo"], ["base", "mixed"], tmp_path, zoo_needed=True)
    needs = {j.name: j.needs for j in jobs + W.run_jobs(ranked, data, tmp_path, 0.0)}
    assert needs["zoo"] == {"data:base"} and needs["data:mixed"] == {"zoo"}  # the mixed data hold the zoo's rollouts
    assert needs["autonomous_rollouts/x=0/seed=0:ranking"] == {"autonomous_rollouts/x=0/seed=0", "zoo"}
    # judged on the mixed data, the scripted-only run trains while the zoo and the mixed data are made
    assert needs["autonomous_rollouts/x=0/seed=0:train"] == {"data:base"}
    assert needs["autonomous_rollouts/x=0/seed=0"] == {"autonomous_rollouts/x=0/seed=0:train", "data:mixed"}


def test_data_jobs_come_just_before_the_first_sweep_that_needs_them(tmp_path):
    size = W.SIZES["demo"]
    plans = [W.Plan(n, "demo", W.SWEEPS[n][0](size), tmp_path / n, "x", False)
             for n in ("held_out_object", "transfer", "data_scaling")]
    data, jobs = W.data_jobs(size, ["base", "heldout", "shelf_arcade"], tmp_path, zoo_needed=True)
    names = [j.name for j in W.in_sweep_order(jobs, [W.run_jobs(p, data, tmp_path, 0.0) for p in plans])]
    assert names[:4] == ["data:base", "data:heldout", "held_out_object/x=0/seed=0", "held_out_object/x=1/seed=0"]
    assert names[4:6] == ["data:shelf_arcade", "transfer/x=1/seed=0"]
    assert names.index("zoo") == names.index("data_scaling/x=0.125/seed=0") - 1
    assert len(names) == len(set(names)) == len(jobs) + 2 + 2 + 8


def test_a_sweep_ranks_by_each_models_own_read_out_not_the_demo_presets_rules(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(W, "_subprocess", lambda args, gpu, log: calls.append(args) or 0)
    assert W.rank_run(tmp_path / "wm", tmp_path / "zoo", "step_back", W.SIZES["demo"], tmp_path / "out", None,
                      tmp_path / "log", tmp_path / "truth") == 0
    args = calls[0]
    assert args[args.index("--config") + 1] == "demo" and f"wm={tmp_path / 'wm'}" in args
    assert args[-2:] == ["geometric=", "geometric_ranks=0"]  # the demo preset's own default ranks by the rules
