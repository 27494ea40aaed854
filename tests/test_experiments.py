"""The evaluator and the report end to end on the smoke world model and zoo (CPU, tiny)."""

import dataclasses
import json
import math
import shutil
import threading
import time
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import SMOKE_EVAL, build_once

from experiments import evaluate as E
from experiments import stats as S
from experiments.report import (
    UNSEEN_NETWORKS_TITLE,
    better_readout_note,
    decision_figure,
    family_table,
    md_table,
    partial_note,
    read_results,
    selection_summary,
    selection_table,
    verdict,
    violation_table,
    write_report,
)
from experiments.timing import compile_snapshot
from sim_data.parts import exclusive
from sim_data.policies.bc import MixedPolicy, StackedPolicy, stacked
from sim_data.policies.registry import resolve
from sim_data.sim.render import HEAD_CAMERA, RenderConfig, Renderer, episode_rgb
from sim_data.sim.rollout import SEGMENT
from sim_data.sim.tasks import TASKS
from wm import judge as J
from wm.checkpoint import load_run_config, load_trained, trained_tasks
from wm.checkpoint import main as checkpoint_main
from wm.imagine import FEATURE_GROUPS, feature_columns, feature_dim
from wm.judge import load_judge
from wm.metrics import psnr


@pytest.fixture(scope="module")
def evaluation(smoke_world_model, smoke_zoo, tmp_path_factory, worker_id):
    # the world model before the zoo: the other worker's `tests/test_wm.py` waits for it, for nothing else
    zoo_dir, _ = smoke_zoo
    # batches of 3 policies x 2 states: two batches, each mixing architectures (MixedPolicy)
    cfg = E.EvalConfig(policies=(f"{zoo_dir}#conv_proprio+conv_noproprio", "examples.plugin_policy:make"),
                       wm=str(smoke_world_model), **SMOKE_EVAL)
    out = build_once(tmp_path_factory, worker_id, "eval", lambda d: E.run(cfg, d / "run", progress=False)) / "run"
    return cfg, out, json.loads((out / "results.json").read_text())


@pytest.fixture
def own_evaluation(evaluation, tmp_path):
    """The evaluation fixture's (cfg, run, results) with the run copied: for a test that changes its files,
    since the fixture's run is shared by both workers."""
    cfg, shared, res = evaluation
    shutil.copytree(shared, tmp_path / "run")
    return cfg, tmp_path / "run", res


def test_results_hold_every_policy_with_statistics_from_the_episodes(evaluation, smoke_dataset, tmp_path):
    cfg, out, res = evaluation
    assert json.loads((out / "results.json").read_text())["tasks"] == ["mug"]
    names = [p["name"] for p in res["policies"]]
    assert len(names) == 5 and "examples.plugin_policy:make" in names
    with np.load(out / "tasks" / "mug.npz") as z:
        true, prob = z["true"].astype(bool), z["prob"]
        meta = json.loads(z["meta"].tobytes().decode())
    assert true.shape == prob.shape == (5, 2) and meta["names"] == names
    # results.json says what each kind of interval resamples
    assert res["metrics"]["intervals"] == S.INTERVALS and res["metrics"]["within_task"]["resamples"] in " ".join(
        S.INTERVALS.values())
    for row, t, p in zip(res["policies"], true, prob, strict=True):
        assert row["true_rate"] == t.mean() and row["n"] == 2
        assert row["true_ci"] == pytest.approx(list(S.wilson_interval(int(t.sum()), 2)))
        assert row["pred_rate"] == pytest.approx(p.mean()) and 0 <= row["pred_rate"] <= 1
        assert row["true_episodes"] == t.astype(int).tolist() and row["pred_episodes"] == pytest.approx(p, abs=1e-5)
    m = res["metrics"]["pooled"]
    assert m["alignment"] == pytest.approx(S.alignment(prob >= cfg.threshold, true))
    want = S.mmrv([p["pred_rate"] for p in res["policies"]], [p["true_rate"] for p in res["policies"]])
    # undefined (every true rate alike) is written null
    assert (m["mmrv"] is None and math.isnan(want)) or m["mmrv"] == pytest.approx(want)
    assert "baseline" in m and res["metrics"]["per_task"]["mug"]["n_policies"] == 5
    assert all(row["nonfinite_episodes"] == 0 for row in res["policies"])
    # replay=1: the loop's actions simulated; the plug-in ignores its frames, so its imagined actions are
    # its true ones and their simulated outcomes its true outcomes
    played = E.load_task(out / "tasks" / "mug.npz")["sim_imagined"]
    assert played.shape == (5, 2) and set(np.unique(played)) <= {0.0, 1.0}
    plug = names.index("examples.plugin_policy:make")
    np.testing.assert_array_equal(played[plug], true[plug])
    assert [row["true_rate_imagined_actions"] for row in res["policies"]] == pytest.approx(played.mean(1).tolist())
    dims = E.load_task(out / "tasks" / "mug.npz")["action_gap_dims"]
    assert dims.shape == (5, 2, 20)
    for row, d in zip(res["policies"], dims, strict=True):
        assert row["action_gap_largest"] == E.largest_action_gap(d)
        assert row["action_gap_largest"]["rms"] == pytest.approx(np.sqrt((d ** 2).mean(0)).max(), abs=1e-4)
    bias = E.load_task(out / "tasks" / "mug.npz")["action_bias_dims"]
    assert bias.shape == (5, 2, 20) and (np.abs(bias) <= dims + 1e-6).all()  # a mean within its RMS
    for row, d, b in zip(res["policies"], dims, bias, strict=True):
        assert {k: row[k] for k in ("closure_gap", "closure_bias")} == E.closure_gap(d, b)
    # a task file written before the signed difference: read back as unknown, at the width of a newer one
    with np.load(out / "tasks" / "mug.npz") as z:
        older = {k: z[k] for k in z.files if k != "action_bias_dims"}
    np.savez(tmp_path / "older.npz", **older)
    old = E.load_task(tmp_path / "older.npz")["action_bias_dims"]
    assert old.shape == bias.shape and np.isnan(old).all()
    assert "sim_imagined" in res["metrics"]["within_task"] and "loop_actions" in res["metrics"]
    assert res["timing"]["mug"]["nonfinite_sim_episodes"] == 0
    # where the world model's time went: every part ran (replay=1), within the batches' world-model time
    # what the ranked judge reads, for comparisons across runs (experiments.compare)
    wm_cfg = load_run_config(Path(res["world_model"]["run"]))[0]
    assert res["world_model"]["judge_inputs"] == list(wm_cfg.judge_inputs)
    parts = res["timing"]["mug"]["imagine_parts"]
    assert list(parts) == list(E.WM_PARTS) and parts.pop("geometric_s") == 0  # no geometric models named
    assert min(parts.values()) > 0
    assert sum(parts.values()) <= res["timing"]["mug"]["imagine_s"]
    # the initial states are held out from the training data
    used = {json.loads(line)["seed"] for line in (smoke_dataset[1] / "manifest.jsonl").read_text().splitlines()}
    assert not set(meta["seeds"]) & used and len(set(meta["seeds"])) == 2


def test_a_batch_runs_policies_of_different_architectures_side_by_side(evaluation):
    cfg, _, res = evaluation
    chunks = E.task_chunks(cfg, resolve(cfg.policies), cfg.episodes)
    assert [len(part) for part, _ in chunks] == [3, 2] and [len(padded) for _, padded in chunks] == [3, 3]
    assert [s.name for part, _ in chunks for s in part] == [p["name"] for p in res["policies"]]
    kinds = [len({s.policy for s in padded}) for _, padded in chunks]
    assert kinds[1] == 2  # a learned policy beside the plug-in
    for (_, padded), k in zip(chunks, kinds, strict=True):
        policy, params = E.chunk_policy(padded, cfg.episodes)
        if k == 1:
            assert isinstance(policy, StackedPolicy) and len(jax.tree_util.tree_leaves(params)[0]) == 3
        else:
            assert isinstance(policy, MixedPolicy) and policy.rows == (cfg.episodes, 2 * cfg.episodes)
            assert len(params) == len(policy.policies) == k


def test_rerun_resumes_and_other_config_is_refused(own_evaluation):
    cfg, out, res = own_evaluation
    stamp = (out / "tasks" / "mug.npz").stat().st_mtime_ns
    again = E.run(cfg, out, progress=False)
    assert (out / "tasks" / "mug.npz").stat().st_mtime_ns == stamp
    assert again["policies"] == res["policies"]
    with pytest.raises(ValueError, match="another configuration"):
        E.run(E.EvalConfig(**{**cfg.__dict__, "episodes": 3}), out, progress=False)


def test_saved_traces_agree_with_the_episodes_outcomes(evaluation):
    _, out, res = evaluation
    task = E.load_task(out / "tasks" / "mug.npz")
    p, n = task["true"].shape
    for key in E.TRACES:
        assert task[key].shape == (p, n, task["steps"]), key
    # the simulator's progress is 1 at the last step exactly where the episode succeeded
    np.testing.assert_array_equal(task["true_progress"][..., -1] == 1.0, task["true"])
    assert np.all((task["true_progress"] >= 0) & (task["true_progress"] <= 1))
    # the read-outs: the highest imagined success probability; the last imagined progress, clipped
    np.testing.assert_allclose(task["trace_success"].max(-1), task["readout_success"], atol=2e-3)
    np.testing.assert_allclose(np.clip(task["trace_progress"][..., -1], 0, 1), task["readout_progress"], atol=2e-3)
    np.testing.assert_array_equal(task["prob"], task["readout_judge"])  # the preset's read-out
    # how near each policy's failures came: from its saved progress, none where every episode succeeded
    by_name = {r["name"]: r for r in res["policies"]}
    for name, progress, true in zip(task["names"], task["true_progress"], task["true"], strict=True):
        peak = by_name[str(name)]["failed_peak_progress"]
        assert peak == E.failed_peak_progress(progress, true) and (peak is None) == bool(true.all())


def test_imagination_fidelity_against_hand_computed_frames_and_actions():
    rng = np.random.default_rng(0)
    real = rng.integers(0, 256, (2, 11, 4, 4, 3), dtype=np.uint8)
    imagined = real[:, 1:].copy()
    imagined[1, 7] = 255 - imagined[1, 7]  # episode 1's frame after 8 steps is wrong
    true_actions = rng.normal(size=(2, 10, 20)).astype(np.float32)
    actions = true_actions.copy()
    actions[0, 3] += 2.0  # episode 0 acts differently at step 3
    got = E.imagination_fidelity({"frames": real, "action": true_actions}, imagined, actions, 10)
    assert E.fidelity_horizons(10) == (1, 8, 10)
    want = np.minimum(psnr(imagined[:, [0, 7, 9]], real[:, [1, 8, 10]]), 100.0)
    np.testing.assert_allclose(got["frame_psnr"], want, rtol=1e-6)
    assert got["frame_psnr"][0].tolist() == [100.0] * 3 and got["frame_psnr"][1, 1] < 10
    np.testing.assert_allclose(got["copy_first_psnr"], psnr(real[:, :1], real[:, [1, 8, 10]]), rtol=1e-6)
    expect_gap = np.zeros((2, 10))
    expect_gap[0, 3] = 2.0
    np.testing.assert_allclose(got["action_gap"], expect_gap, atol=1e-6)
    # per dimension over the 10 steps: every dimension of episode 0 off by 2 at one step of ten
    np.testing.assert_allclose(got["action_gap_dims"], [[2.0 / np.sqrt(10)] * 20, [0.0] * 20], atol=1e-6)
    np.testing.assert_allclose(got["action_bias_dims"], [[0.2] * 20, [0.0] * 20], atol=1e-6)  # +2 at one step of ten
    closer = true_actions.copy()
    closer[1, :4, 17] -= 0.5  # episode 1's right hand closes 0.5 less for 4 of its 10 steps in imagination
    hands = E.imagination_fidelity({"frames": real, "action": true_actions}, imagined, closer, 10)
    assert E.closure_gap(hands["action_gap_dims"], hands["action_bias_dims"]) == {
        "closure_gap": round(float(np.sqrt(0.5 ** 2 * 4 / 10 / 2)), 4), "closure_bias": -0.1}
    assert E.closure_gap(np.full((2, 20), np.nan), np.zeros((2, 0))) == {"closure_gap": None, "closure_bias": None}
    dims = np.zeros((3, 20))
    dims[:, 18] = [0.3, 0.0, 0.4]  # the base's speed off in two of three episodes
    dims[1, 0] = 0.1
    assert E.largest_action_gap(dims) == {"dim": "forward_speed", "rms": round(np.sqrt(0.25 / 3), 4)}
    assert E.largest_action_gap(np.full((2, 20), np.nan)) is None
    summary = E.fidelity_summary({"steps": 10, **{k: v[None] for k, v in got.items()}})
    assert summary["horizons"] == [1, 8, 10] and summary["action_gap"] == [0.0, 0.0, 0.0]
    assert summary["frame_psnr"][0] == 100.0 and summary["gain_over_copy_first_db"][1] == pytest.approx(
        summary["frame_psnr"][1] - summary["copy_first_psnr"][1], abs=2e-3)
    cached = E.imagination_fidelity({"frames0": real[:, :1]}, imagined, actions, 10)  # from the truth cache
    assert np.isnan(cached["frame_psnr"]).all() and cached["action_gap"].shape == (2, 10)
    assert np.isnan(cached["action_bias_dims"]).all() and cached["action_bias_dims"].shape == (2, 20)


def test_family_table_lists_each_family_under_each_readout():
    rows = [{"task": "mug", "lineage": "conv", "step": 9, "true_rate": 0.9, "pred_rate": 0.8,
             "pred_rate_readouts": {"progress": 0.8, "judge": 0.7, "success": 0.9}},
            *({"task": "mug", "lineage": "conv~noise", "step": None, "true_rate": t, "pred_rate": p,
               "pred_rate_readouts": {"progress": p, "judge": 0.5, "success": t}} for t, p in ((0.5, 0.4), (0.1, 0.3)))]
    fams = S.family_statistics(rows) | {"by_readout": {
        r: S.family_statistics([dict(x, rate=x["pred_rate_readouts"][r]) for x in rows], "rate")
        for r in E.read_readouts(rows)}}
    table = family_table({"families": json.loads(json.dumps(fams))})
    assert table[0][-3:] == ["r, progress read-out", "r, judge read-out", "r, success read-out"]
    family, mean = table[1], table[2]
    assert family[:4] == ["mug", "conv~noise", "3", "0.10-0.90"]
    assert float(family[4]) == pytest.approx(np.corrcoef([0.8, 0.4, 0.3], [0.9, 0.5, 0.1])[0, 1], abs=0.005)
    assert family[5] == "n/a" and family[6] == "0.13" and family[-1] == "1.00" and mean[0] == "mean"
    counted = S.family_statistics([dict(x, n=8) for x in rows])  # rows with their episodes: the ceiling
    ceiling = family_table({"families": json.loads(json.dumps(counted))})[1][5]
    assert float(ceiling) == pytest.approx(S.pearson_ceiling([0.5, 0.1, 0.9], [8] * 3), abs=0.005)
    assert family_table({"families": {"families": []}}) is None


@pytest.mark.slow
def test_parts_share_out_a_tasks_batches_and_merge_into_the_unsplit_results(evaluation, tmp_path):
    cfg, out, res = evaluation
    assert E.balance_chunks({"a": 5, "b": 3, "c": 3, "d": 1}, 2) == {"a": 0, "b": 1, "c": 1, "d": 0}
    with pytest.raises(ValueError, match="without --part"):
        E.run(cfg, tmp_path / "kept", progress=False, part=(0, 2))
    cfg = dataclasses.replace(cfg, keep_features=False)  # the step features are kept by unsplit runs only
    split = tmp_path / "split"
    for k in range(2):
        assert E.run(cfg, split, progress=False, part=(k, 2)) is None
    shares = [E.load_task(split / "tasks" / f"mug.part{k}of2.npz")["names"] for k in range(2)]
    assert all(shares) and sorted(shares[0] + shares[1]) == sorted(p["name"] for p in res["policies"])
    assert not (split / "tasks" / "mug.npz").exists()
    got = E.run(cfg, split, progress=False)  # merges the parts
    whole, merged = E.load_task(out / "tasks" / "mug.npz"), E.load_task(split / "tasks" / "mug.npz")
    assert merged["names"] == whole["names"] and merged["seeds"] == whole["seeds"]
    for key in ("true", "prob", "prob_members") + E.TRACES + E.READOUT_KEYS:
        np.testing.assert_allclose(merged[key], whole[key], atol=1e-3, err_msg=key)
    for mine, theirs in zip(got["policies"], res["policies"], strict=True):
        assert mine["name"] == theirs["name"] and mine["true_rate"] == theirs["true_rate"]
        assert mine["pred_rate"] == pytest.approx(theirs["pred_rate"], abs=1e-5)
    filmed = {v["policy"] for v in merged["video_index"]}
    assert 0 < len(filmed) <= cfg.video_policies and set(merged["videos"]) == {
        f"{v['key']}/{kind}" for v in merged["video_index"] for kind in ("real", "imagined")}
    (split / "tasks" / "mug.npz").unlink()
    # more parts than batches: the batches go to parts 0 and 1 as above, part 2 gets none
    assert E.balance_chunks({0: 3, 1: 2}, 3) == {0: 0, 1: 1}
    three = tmp_path / "three"
    (three / "tasks").mkdir(parents=True)
    for k in range(2):
        (three / "tasks" / f"mug.part{k}of3.npz").write_bytes((split / "tasks" / f"mug.part{k}of2.npz").read_bytes())
    assert E.run(cfg, three, progress=False, part=(2, 3)) is None
    assert E.load_task(three / "tasks" / "mug.part2of3.npz")["names"] == []
    E.run(cfg, three, progress=False)
    np.testing.assert_allclose(E.load_task(three / "tasks" / "mug.npz")["prob"], whole["prob"], atol=1e-3)
    (split / "tasks" / "mug.part1of2.npz").unlink()
    with pytest.raises(ValueError, match="rerun the parts"):
        E.merge_task_parts(cfg, [E.load_task(split / "tasks" / "mug.part0of2.npz")], whole["names"])


@pytest.mark.slow
def test_state_slices_share_one_program_and_parts_join_them_into_the_unsliced_results(evaluation, tmp_path,
                                                                                    monkeypatch):
    """state_batch=1 runs the fixture's 2 states as two slices of one batch shape: the second compiles
    nothing; the outcomes, predictions and kept features are those of the unsliced run; two parts,
    one slice each, join into the same."""
    from experiments.timing import compile_snapshot, compiled_since

    cfg, out, res = evaluation
    with pytest.raises(ValueError, match="state_batch must divide"):
        dataclasses.replace(cfg, state_batch=3).validate()
    sliced = dataclasses.replace(cfg, state_batch=1)
    assert [(k, j, len(part)) for k, j, part, _ in E.task_batches(sliced, resolve(cfg.policies), 2)] == [
        (0, 0, 5), (0, 1, 5)]
    starts = []
    simulate = E.simulate_truth

    def noting(*a, **k):
        starts.append(compile_snapshot())
        return simulate(*a, **k)

    monkeypatch.setattr(E, "simulate_truth", noting)
    E.run(sliced, tmp_path / "sliced", progress=False)
    assert len(starts) == 2 and compiled_since(starts[1])["programs_compiled"] == 0
    whole, got = E.load_task(out / "tasks" / "mug.npz"), E.load_task(tmp_path / "sliced" / "tasks" / "mug.npz")
    assert got["names"] == whole["names"] and np.array_equal(got["true"], whole["true"])
    for key in ("prob", "prob_members", "prob_observed", "prob_replayed") + E.TRACES + E.READOUT_KEYS + E.FIDELITY:
        np.testing.assert_allclose(got[key], whole[key], atol=2e-3, err_msg=key)
    for observed in (False, True):
        np.testing.assert_allclose(E.load_features(tmp_path / "sliced", "mug", observed).astype(np.float32),
                                   E.load_features(out, "mug", observed).astype(np.float32), atol=0.02)
    parts = tmp_path / "parts"
    split = dataclasses.replace(sliced, keep_features=False)
    for k in range(2):
        assert E.run(split, parts, progress=False, part=(k, 2)) is None
        share = E.load_task(parts / "tasks" / f"mug.part{k}of2.npz")
        assert share["slices"] == [k] * 5 and share["true"].shape == (5, 1)  # every policy, one state
    E.run(split, parts, progress=False)
    merged = E.load_task(parts / "tasks" / "mug.npz")
    assert merged["names"] == whole["names"] and np.array_equal(merged["true"], whole["true"])
    np.testing.assert_allclose(merged["prob_members"], whole["prob_members"], atol=2e-3)
    (parts / "tasks" / "mug.npz").unlink()
    with pytest.raises(ValueError, match="of the task's 2 states"):
        E.merge_task_parts(split, [E.load_task(parts / "tasks" / "mug.part0of2.npz")], whole["names"])


def test_failed_peak_progress_is_the_mean_of_the_failed_episodes_highest_progress():
    progress = np.array([[0.0, 0.5, 1.0, 1.0],     # succeeded: left out
                         [0.0, 0.6, 0.975, 0.9],   # failed within 2.5% of the line, then slid back
                         [0.0, 0.2, np.nan, 0.4],  # failed; a NaN step is skipped
                         [np.nan] * 4], np.float16)  # failed, no progress kept: left out
    outcomes = np.array([True, False, False, False])
    assert E.failed_peak_progress(progress, outcomes) == round((float(np.float16(0.975)) + float(np.float16(0.4))) / 2, 3)
    assert E.failed_peak_progress(progress[:1], outcomes[:1]) is None  # none failed
    assert E.failed_peak_progress(progress[3:], outcomes[3:]) is None  # the failure kept no progress


def test_violation_table_lists_the_policies_that_carry_each_tasks_mmrv():
    rows = [{"task": "mug", "name": n, "pred_rate": p, "true_rate": t, "action_gap": g}
            for n, p, t, g in zip("abcd", [0.9, 0.5, 0.1, 0.6], [0.1, 0.5, 0.0, 0.8], [0.1, 0.2, 0.3, 0.4])]
    table = violation_table({"rank_violations": json.loads(json.dumps(S.rank_violations(rows))), "policies": rows})
    assert table[1] == ["mug", "0.45", "a", "0.10", "0.90", "61%", "2", "0.100 (0.250)"]
    assert table[2] == ["", "", "d", "0.80", "0.60", "39%", "1", "0.400 (0.250)"] and len(table) == 3
    # where measured, what the read-out gives on the true actions replayed and on the true episodes
    for r, rep, obs in zip(rows, [0.8, 0.5, 0.1, 0.7], [0.2, 0.5, 0.0, None], strict=True):
        r.update(pred_rate_replayed=rep, pred_rate_on_truth=obs)
    table = violation_table({"rank_violations": json.loads(json.dumps(S.rank_violations(rows))), "policies": rows})
    assert table[0][5:7] == ["read on its true actions replayed", "read on its true episodes"]
    assert table[1] == ["mug", "0.45", "a", "0.10", "0.90", "0.80", "0.20", "61%", "2", "0.100 (0.250)"]
    assert table[2][5:7] == ["0.70", "n/a"]
    # where measured, the action dimension whose gap is largest
    rows[0]["action_gap_largest"] = {"dim": "forward_speed", "rms": 0.213}
    table = violation_table({"rank_violations": json.loads(json.dumps(S.rank_violations(rows))), "policies": rows})
    assert table[0][-1] == "largest in one dimension" and table[1][-1] == "0.213 (forward_speed)"
    assert table[2][-1] == "n/a"
    # where measured, the right hand's closure in imagination against on true frames
    rows[0].update(closure_bias=0.031, closure_gap=0.0874)
    table = violation_table({"rank_violations": json.loads(json.dumps(S.rank_violations(rows))), "policies": rows})
    assert table[0][-2:] == ["largest in one dimension", "right hand's closure, imagined minus true (mean; RMS)"]
    assert table[1][-1] == "0.031; 0.087" and table[2][-1] == "n/a; n/a"
    # where measured, how near the failed episodes came to success in the simulator
    rows[0]["failed_peak_progress"] = 0.975
    table = violation_table({"rank_violations": json.loads(json.dumps(S.rank_violations(rows))), "policies": rows})
    assert table[0][-1] == "its failed episodes' highest true progress (1: success)"
    assert table[1][-1] == "0.97" and table[2][-1] == "n/a"
    assert violation_table({}) is None  # results written before the table existed
    assert violation_table({"rank_violations": {"mug": {"mmrv": 0.0, "policies": []}}}) is None


def test_a_partial_gather_reports_the_finished_tasks_and_names_the_rest(evaluation, tmp_path):
    cfg, out, res = evaluation
    both = dataclasses.replace(cfg, tasks=("mug", "step_back"))
    cut = tmp_path / "cut"
    with pytest.raises(ValueError, match="no task is finished"):
        E.run(both, cut, progress=False, partial=True)
    shutil.copy(out / "tasks" / "mug.npz", cut / "tasks" / "mug.npz")  # as a run stopped after mug leaves it
    got = E.run(both, cut, progress=False, partial=True)
    assert got["tasks"] == ["mug"] and got["missing_tasks"] == ["step_back"]
    assert [p["name"] for p in got["policies"]] == [p["name"] for p in res["policies"]]
    assert got["metrics"]["pooled"]["alignment"] == pytest.approx(res["metrics"]["pooled"]["alignment"])
    assert not (cut / "tasks" / "step_back.npz").exists() and res["missing_tasks"] == []
    assert got["cut_short"] is None  # gathered on request, not stopped
    md = write_report(cut).with_suffix(".md").read_text()
    assert "**Partial: tasks step_back were not evaluated" in md and "safety time limit" not in md


def test_an_evaluation_its_time_limit_stops_writes_the_finished_tasks_marked_cut_short(evaluation, tmp_path,
                                                                                      capsys):
    """max_minutes is a safety stop: the command stops before a task that would end past it, writes
    results.json over the tasks finished, marked cut short in it and in the report, and exits with
    EXIT_CUT_SHORT, so that a script knows to rerun it (the fixture's settings: its programs serve)."""
    cfg, _, res = evaluation
    args = ["--config", "demo", "--out", str(tmp_path / "cut"), f"policies={','.join(cfg.policies)}", f"wm={cfg.wm}",
            "geometric=", "geometric_ranks=0", "tasks=mug,step_back", "max_minutes=1e-9",
            *(f"{k}={v}" for k, v in SMOKE_EVAL.items() if k != "tasks")]
    args = [a.replace("(5, 50)", "5,50").replace("True", "1") for a in args]
    assert E.main(args) == E.EXIT_CUT_SHORT == 3
    assert "rerun the same command to evaluate step_back" in capsys.readouterr().err
    got = json.loads((tmp_path / "cut" / "results.json").read_text())
    assert got["tasks"] == ["mug"] and got["missing_tasks"] == ["step_back"]
    assert got["cut_short"] == {"max_minutes": 1e-9, "tasks_left": ["step_back"]}
    assert [(p["name"], p["true_rate"]) for p in got["policies"]] == [(p["name"], p["true_rate"]) for p in res["policies"]]
    assert not (tmp_path / "cut" / "tasks" / "step_back.npz").exists()
    md = write_report(tmp_path / "cut").with_suffix(".md").read_text()
    assert ("**Partial: tasks step_back were not evaluated; every statistic below leaves them out. The evaluation "
            "stopped at its safety time limit (max_minutes=1e-09): rerun the same command to evaluate them.**") in md
    # a hand-edited limit that is no number is left out of the sentence, not a traceback
    assert partial_note({"missing_tasks": ["wipe"], "cut_short": {"max_minutes": "soon"}}).endswith(
        "safety time limit: rerun the same command to evaluate them.")
    assert partial_note({"missing_tasks": []}) == ""


def test_report_renders_figures_and_videos(own_evaluation):
    _, out, res = own_evaluation
    page = write_report(out).read_text()
    assert page.count("data:image/png;base64,") >= 5  # scatter, progress, ranks, baseline, decision (+ controllability)
    assert "Task progress, true and imagined" in page and "Imagination against the simulated episode" in page
    # the smoke evaluation runs no counterfactual family: no section for it
    assert res["families"]["families"] == [] and "Counterfactual families" not in page
    fid = res["imagination"]["mug"]
    assert fid["horizons"][-1] == res["timing"]["mug"]["steps"] and all(v is not None for v in fid["frame_psnr"])
    mug = [p for p in res["policies"] if p["task"] == "mug"]
    assert all(len(p["progress_true"]) == len(p["progress_imagined"]) == res["timing"]["mug"]["steps"] for p in mug)
    assert page.count("data:image/webp;base64,") == len(res["videos"]) + len(res["controllability"])
    assert "Decision analysis" in page and "imitation-loss baseline" in page and "Checkpoint selection" in page
    md = (out / "report.md").read_text()
    assert "| pearson |" in md and "examples.plugin_policy:make" in md
    assert "played in the simulator from the same states" in md and "the simulator on the actions taken" in md
    # the verdict first, then the within-task table with the proxy beside the world model, the pooled row last
    first, within, pooled = (md.index(x) for x in (f"**{verdict(res)}**", "## Within-task ranking",
                                                   "## Pooled over tasks (secondary)"))
    assert first < within < pooled and "| imitation-loss proxy |" in md
    # rows of the per-task table: the other read-outs, and the read-out of the true episodes
    assert "| world model, progress read-out |" in md and "| world model, success read-out |" in md
    assert "| the read-out of the true episodes |" in md
    floor, table = res["metrics"]["mmrv_floor"]["mean"], md.split("## Within-task ranking")[1].split("\n\n")[1]
    # undefined (null) where every true rate ties, as in a smoke zoo that fails every episode
    if floor is None:
        assert "a perfect predictor" not in table
    else:
        assert f"(a perfect predictor: {floor:.3f}) |" in table
    assert "Cut short" not in md
    viol = res["rank_violations"]["mug"]
    want = S.mmrv([p["pred_rate"] for p in mug], [p["true_rate"] for p in mug])
    assert (viol["mmrv"] is None and math.isnan(want)) or viol["mmrv"] == pytest.approx(want)
    assert ("## Rank violations" in md) == bool(viol["policies"])
    with np.load(out / "tasks" / "mug.npz") as z:  # each row's action gap: its episodes' mean over steps
        np.testing.assert_allclose([p["action_gap"] for p in mug],
                                   np.nanmean(z["action_gap"].astype(np.float64), axis=(1, 2)), atol=2e-3)
    cut = dict(res, world_model=dict(res["world_model"], cut_short=True))
    (out / "results.json").write_text(json.dumps(cut))
    assert "Cut short" in write_report(out).with_suffix(".md").read_text()
    # the unseen policies' within-task tables, all of them and the networks alone, where results hold them
    w = res["metrics"]["within_task"]
    unseen = dict(res, metrics=dict(res["metrics"], unseen_within_task=w, unseen_networks_within_task=w))
    (out / "results.json").write_text(json.dumps(unseen))
    page = write_report(out)
    md = page.with_suffix(".md").read_text()
    assert "## Within task, policies whose rollouts the world model never saw" in md
    assert f"## {UNSEEN_NETWORKS_TITLE}" in md and UNSEEN_NETWORKS_TITLE in page.read_text()
    assert md.count("| mug | imitation-loss proxy |") == 3
    floored = dict(res, metrics=dict(res["metrics"], mmrv_floor={"per_task": {"mug": 0.123}, "mean": 0.123}))
    (out / "results.json").write_text(json.dumps(floored))
    table = write_report(out).with_suffix(".md").read_text().split("## Within-task ranking")[1].split("\n\n")[1]
    assert "(a perfect predictor: 0.123) |" in table


def test_a_report_of_results_copied_without_their_videos_says_so(evaluation, tmp_path):
    _, out, res = evaluation
    run = tmp_path / "copied"
    shutil.copytree(out / "tasks", run / "tasks")
    shutil.copyfile(out / "results.json", run / "results.json")
    page = write_report(run).read_text()
    assert "No episodes kept in" in page and "data:image/webp;base64," not in page
    assert page.count("data:image/png;base64,") >= 5


@pytest.mark.slow
def test_an_ensemble_averages_its_members_probabilities(evaluation, smoke_world_model, tmp_path):
    cfg, out, res = evaluation
    # a second member: the same network reading the actions on another scale, so that it predicts otherwise
    other = tmp_path / "other"
    shutil.copytree(smoke_world_model, other)
    norm = json.loads((other / "norm.json").read_text())
    norm["action_std"] = [0.25 * s for s in norm["action_std"]]
    (other / "norm.json").write_text(json.dumps(norm))
    E.run(dataclasses.replace(cfg, wm=f"{smoke_world_model},{other}"), tmp_path / "ens", progress=False)
    got = json.loads((tmp_path / "ens" / "results.json").read_text())
    with np.load(out / "tasks" / "mug.npz") as z:
        true, prob = z["true"].astype(bool), z["prob"]
    with np.load(tmp_path / "ens" / "tasks" / "mug.npz") as z:
        assert (z["true"] == true).all()
        members, mean = z["prob_members"], z["prob"]
    assert members.shape == (2, *prob.shape) and np.abs(members[1] - members[0]).max() > 1e-3
    np.testing.assert_allclose(members[0], prob, atol=1e-6)  # the first member alone is the single evaluation
    np.testing.assert_allclose(mean, members.mean(0), atol=1e-6)
    for row, each in zip(got["policies"], members.transpose(1, 0, 2), strict=True):
        assert row["pred_rates"] == pytest.approx(each.mean(1)) and row["pred_rate"] == pytest.approx(each.mean())
    m, single = got["metrics"]["pooled"], res["metrics"]["pooled"]
    for stat in ("pearson", "mmrv", "alignment"):
        assert m["members"][stat][0] == single[stat] or m["members"][stat][0] == pytest.approx(single[stat])
    assert m["members"]["alignment"][1] == pytest.approx(S.alignment(members[1] >= cfg.threshold, true))
    assert m["alignment"] == pytest.approx(S.alignment(mean >= cfg.threshold, true))
    assert got["world_model"]["runs"] == [str(smoke_world_model), str(other)]
    page = write_report(tmp_path / "ens").read_text()
    assert "an ensemble of 2 world models" in page and "each model alone" in page
    with pytest.raises(ValueError, match="twice"):
        E.make_config("demo", [f"wm={other},{other}"])


def test_an_episode_whose_simulation_went_non_finite_is_flagged():
    proprio = np.zeros((3, 5, 37), np.float32)
    action = np.zeros((3, 4, 20), np.float32)
    proprio[1, 4, 7] = np.nan
    action[2, 0, 3] = np.inf
    truth = {"frames0": np.zeros((3, 1, 8, 8, 3), np.uint8), "proprio": proprio, "action": action}
    assert E.simulated_finite(truth).tolist() == [True, False, False]
    cached = {"frames0": truth["frames0"]}  # read back from the truth cache: nothing to check
    assert E.simulated_finite(cached).tolist() == [True, True, True]


def test_decision_analysis_resamples_pairs_spread_over_every_task():
    cfg = E.make_config("demo")
    true = (np.arange(20)[None, :] < 2 * np.arange(10)[:, None]).astype(float)  # policy i succeeds 2i times of 20
    tasks = {t: {"true": true, "prob": true} for t in ("a", "b")}  # a world model that agrees on every episode
    out = E.decision_analysis(cfg, tasks, alignment=1.0, most=6)
    assert out["pairs"] == {"0.1": 6, "0.2": 6}  # of 9 and 8 pairs per task
    assert out["pair_tasks"]["0.1"] == {"a": 3, "b": 3} and out["pair_tasks"]["0.2"] == {"a": 3, "b": 3}
    # the pairs spread over the 18 (16): the 1st, 4th, 8th, ... of task a's then b's, worse policy's rate as
    # `base`; with episodes that agree, resampling them is the binomial model at alignment 1 at that base
    worse = {"0.1": [0.0, 0.3, 0.7, 0.1, 0.5, 0.8], "0.2": [0.0, 0.3, 0.6, 0.1, 0.4, 0.7]}
    for g, bases in worse.items():
        hand = np.mean([S.p_pick_better(1.0, float(g), cfg.decision_episodes, base=b) for b in bases], axis=0)
        np.testing.assert_allclose(out["resampled"][g], hand, atol=0.03)


def test_bad_evaluation_settings_are_refused():
    with pytest.raises(ValueError, match="policy spec"):
        E.make_config("demo", ["policies="])
    with pytest.raises(ValueError, match="episodes"):
        E.make_config("demo", ["episodes=1"])
    with pytest.raises(ValueError, match="unknown preset"):
        E.make_config("huge")
    with pytest.raises(ValueError, match=r"unknown tasks \['mugg'\]; choose among mug, wipe"):
        E.make_config("demo", ["tasks=mug,mugg"])
    with pytest.raises(ValueError, match="imagine must be one of window, cache or empty"):
        E.make_config("demo", ["imagine=kv"])


def test_imagine_replaces_the_models_own_imagination_setting(smoke_world_model):
    runs = [str(smoke_world_model)]
    own = E.load_models(runs)[0][0].model.imagine
    assert own == "cache"
    assert E.load_models(runs, "window")[0][0].model.imagine == "window"
    assert E.load_models(runs, "")[0][0].model.imagine == own


@pytest.mark.slow
def test_air_fryer_body_mask_covers_the_body_pixels_of_the_frame():
    """The body's pixels found from a recorded state are the fryer's colour in the rendered frame
    (chromaticity, which the scene's white lights keep), and the pixels bordering them are not."""
    import jax
    from scipy.ndimage import binary_dilation

    from experiments.body_in_place import _scene, body_masks
    from sim_data.sim.env import HomeEnv

    env = HomeEnv("airfryer", 1, engine="cpu")
    state = env.reset(jax.random.PRNGKey(3))
    renderer = Renderer(_scene()[0], RenderConfig(camera=HEAD_CAMERA))
    colors = episode_rgb(renderer.geometry, state.task.colors)
    frame = np.asarray(renderer.render(env.poses(state), colors)["rgb"])[0].astype(np.float64)
    mask = body_masks(np.asarray(state.qpos), np.asarray(state.mocap_pos))[0]
    assert mask.mean() > 0.02
    fryer = np.asarray(colors)[0, _scene()[1][0]]

    def chroma(x):
        return x / np.maximum(x.sum(-1, keepdims=True), 1e-6)

    near = np.abs(chroma(frame) - chroma(fryer)).sum(-1) < 0.05
    ring = binary_dilation(mask) & ~mask  # a mask one pixel off puts about 0.3 of its ring on the body
    assert near[mask].mean() > 0.9 and near[ring].mean() < 0.1


def test_truth_cache_returns_the_simulated_batch_waits_for_a_writer_and_misses_on_other_parameters(smoke_zoo, tmp_path, monkeypatch):
    from sim_data.policies.bc import StackedPolicy, stack_params
    from sim_data.policies.registry import resolve
    from sim_data.sim.render import cached_renderers

    zoo_dir, _ = smoke_zoo
    # the evaluation fixture's first batch (3 checkpoints of one architecture, 2 states): its compiled programs
    sources = resolve([f"{zoo_dir}#conv_proprio+conv_noproprio"])[:3]
    assert len({s.policy for s in sources}) == 1
    cfg = E.EvalConfig(policies=("x",), wm="y", truth_cache=str(tmp_path / "truth"), video_policies=0)
    policy, params = StackedPolicy(sources[0].policy), stack_params([s.params for s in sources])
    seeds = [11, 12]
    keys = np.stack([np.asarray(E.jax.random.PRNGKey(s)) for s in seeds])
    renderer = cached_renderers(64, (HEAD_CAMERA,))
    rng = E.jax.random.PRNGKey(3)
    first = E.simulate_truth(cfg, "mug", policy, params, seeds, keys, rng, "cpu", renderer)
    assert first["outcome"].shape == (3, 2) and first["frames0"].shape == (6, 1, 64, 64, 3)
    assert np.array_equal(first["frames0"][:, 0], np.asarray(first["frames"][:, 0]))
    assert len(list((tmp_path / "truth").glob("mug-*.npz"))) == 1

    def no_simulation(*a, **k):
        raise AssertionError("simulated although the cache holds this batch")

    monkeypatch.setattr(E, "record_policies", no_simulation)
    again = E.simulate_truth(cfg, "mug", policy, params, seeds, keys, rng, "cpu", renderer)
    for k in ("outcome", "frames0", "proprio0", "steps"):
        assert np.array_equal(again[k], first[k])
    # a ranking that finds another simulating the batch (holding its lock) waits and reads its outcomes
    (entry,) = (tmp_path / "truth").glob("mug-*.npz")
    held = entry.read_bytes()
    entry.unlink()
    got = {}
    with exclusive(entry.with_suffix(".lock")):
        assert E.simulate_truth(cfg, "mug", policy, params, seeds, keys, rng, "cpu", renderer, wait=False) is None
        waiting = threading.Thread(target=lambda: got.update(E.simulate_truth(
            cfg, "mug", policy, params, seeds, keys, rng, "cpu", renderer)))
        waiting.start()
        time.sleep(1.0)
        assert waiting.is_alive() and not got
        entry.write_bytes(held)
    waiting.join(60)
    assert np.array_equal(got["outcome"], first["outcome"])
    other = E.jax.tree_util.tree_map(lambda x: x + 1e-3 if x.dtype.kind == "f" else x, params)
    with pytest.raises(AssertionError, match="simulated although"):
        E.simulate_truth(cfg, "mug", policy, other, seeds, keys, rng, "cpu", renderer)
    monkeypatch.setattr(E, "PHYSICS_REVISION", E.PHYSICS_REVISION + 1)  # outcomes of older physics are not read
    with pytest.raises(AssertionError, match="simulated although"):
        E.simulate_truth(cfg, "mug", policy, params, seeds, keys, rng, "cpu", renderer)
    with pytest.raises(ValueError, match="video_policies=0"):
        E.make_config("demo", ["truth_cache=/tmp/t"])
    with pytest.raises(ValueError, match="name it"):
        E.make_config("demo", ["truth_frames=1"])
    assert E.make_config("demo", ["truth_cache=/tmp/t", "truth_frames=1"]).video_policies  # films from the cache

    # with truth_frames the entry keeps the simulated episodes: one kept without them is simulated again
    monkeypatch.undo()
    framed = dataclasses.replace(cfg, truth_frames=True)
    whole = E.simulate_truth(framed, "mug", policy, params, seeds, keys, rng, "cpu", renderer)
    monkeypatch.setattr(E, "record_policies", no_simulation)
    kept = E.simulate_truth(framed, "mug", policy, params, seeds, keys, rng, "cpu", renderer)
    for k in ("outcome", "frames0", "proprio0", "progress", *E.TRUTH_ARRAYS):
        assert kept[k].dtype == np.asarray(whole[k]).dtype and np.array_equal(kept[k], np.asarray(whole[k])), k
    assert kept["frames"].shape == (6, kept["steps"] + 1, 64, 64, 3)
    assert E.simulate_truth(framed, "mug", policy, params, seeds, keys, rng, "cpu", renderer, read=False) == {}
    assert "frames" not in E.simulate_truth(cfg, "mug", policy, params, seeds, keys, rng, "cpu", renderer)


def test_the_truth_cache_refuses_frames_the_disk_cannot_hold(smoke_zoo, tmp_path, monkeypatch):
    zoo_dir, _ = smoke_zoo
    sources = resolve([f"{zoo_dir}#conv_proprio+conv_noproprio"])
    cfg = E.EvalConfig(policies=("x",), wm="y", tasks=("mug",), episodes=4, batch=6, state_batch=2,
                       truth_cache=str(tmp_path / "truth"), truth_frames=True)
    # 4 checkpoints of mug in batches of 2 (no padding) from 4 states in 2 slices: 16 episodes of 121
    # frames of 64 x 64 x 3 bytes
    assert len(sources) == 4 and all(len(b[3]) == 2 for b in E.task_batches(cfg, sources, 4))
    need = 16 * (TASKS["mug"].episode_steps + 1) * 64 * 64 * 3
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(E.shutil, "disk_usage", lambda _: usage._replace(free=need))
    with pytest.raises(ValueError, match=rf"about {need / 1e9:.1f} GB more .* {need / 1e9:.1f} GB free"):
        E.truth_space(cfg, ["mug"], sources, 64)
    # a killed writer's temporary file is not what the cache holds
    (tmp_path / "truth" / "mug-held.tmp4242.npz").write_bytes(bytes(need // 10))
    with pytest.raises(ValueError, match="GB more"):
        E.truth_space(cfg, ["mug"], sources, 64)
    (tmp_path / "truth" / "mug-held.npz").write_bytes(bytes(need // 10))  # what the cache holds counts
    E.truth_space(cfg, ["mug"], sources, 64)
    E.truth_space(dataclasses.replace(cfg, truth_frames=False), ["mug"], sources, 64)


def test_a_truth_cache_entry_clears_a_killed_writers_file_and_is_skipped_where_the_disk_is_full(tmp_path, monkeypatch,
                                                                                             capsys):
    """A warm-up killed mid-write (SIGKILL: its stage's wait ran out) leaves its temporary file: the next
    writer of the entry removes it, and the disk check does not count it as held. An entry the disk has
    no room for, or whose write fails, is not kept: the evaluation goes on with the episodes in hand."""
    cfg = E.EvalConfig(policies=("x",), wm="y", truth_cache=str(tmp_path / "truth"), truth_frames=True)
    root = tmp_path / "truth"
    root.mkdir()
    path = root / "mug-0123456789abcdef0123.npz"
    stale = root / f"{path.stem}.tmp999999.npz"
    stale.write_bytes(bytes(1000))
    truth = {"outcome": np.ones((2, 3), bool), "frames0": np.zeros((6, 1, 4, 4, 3), np.uint8),
             "proprio0": np.zeros((6, 1, 37), np.float32), "steps": 5,
             "frames": np.zeros((6, 6, 4, 4, 3), np.uint8), "proprio": np.zeros((6, 6, 37), np.float32),
             "action": np.zeros((6, 5, 20), np.float32), "progress": np.zeros((6, 5), np.float32)}
    E._keep_truth(cfg, path, truth)
    assert not stale.exists() and sorted(f.name for f in root.iterdir()) == [path.name]
    with np.load(path) as z:
        assert sorted(z.files) == sorted(truth) and np.array_equal(z["frames"], truth["frames"])
    path.unlink()
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(E.shutil, "disk_usage", lambda _: usage._replace(free=E.TRUTH_RESERVE))
    E._keep_truth(cfg, path, truth)
    assert not any(root.iterdir()) and "not kept" in capsys.readouterr().err
    monkeypatch.undo()

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(E.np, "savez", full)
    E._keep_truth(cfg, path, truth)
    assert not any(root.iterdir()) and "No space left" in capsys.readouterr().err


def test_auto_readout_picks_the_judge_only_where_every_model_saw_learned_policies_rollouts(smoke_world_model,
                                                                                         monkeypatch):
    runs = [str(smoke_world_model)]
    models = E.load_models(runs)
    assert models[0][3] is None and E.auto_readout("auto", runs, models) == "progress"  # no judge, no rollouts
    assert E.auto_readout("success", runs, models) == "success"
    judged = [(*m[:3], object()) for m in models]
    assert E.auto_readout("auto", runs, judged) == "progress"  # a judge fit to scripted episodes alone
    monkeypatch.setattr(E, "training_policies", lambda run: {"mug/conv_proprio/10"})
    assert E.auto_readout("auto", runs, judged) == "judge"
    assert E.auto_readout("auto", runs * 2, [judged[0], models[0]]) == "progress"  # one member without a judge
    with pytest.raises(ValueError, match="readout must be one of"):
        E.make_config("demo", ["readout=final"])


@pytest.mark.parametrize("setting, says", [
    ("gaps=1.5", r"gaps are .* each in \(0, 1\]; got \(1.5,\)"), ("gaps=0.1,-0.2", "gaps are"),
    ("gaps=", r"got \(\)"), ("video_policies=-1", "video_policies and video_episodes count"),
    ("video_episodes=-3", "count what the report films"), ("decision_episodes=0", "each >= 1; got \\(0,\\)"),
    ("max_minutes=-1", "max_minutes is a safety stop")])
def test_settings_that_only_the_analysis_after_the_episodes_reads_are_refused_before_any_runs(setting, says):
    with pytest.raises(ValueError, match=says):
        E.make_config("demo", [setting, *E.WORLD_MODEL_ALONE])


def test_within_task_headline_and_checkpoint_selection_from_the_episodes(evaluation):
    from wm.quality import no_nan

    cfg, out, res = evaluation
    with np.load(out / "tasks" / "mug.npz") as z:
        true, prob, observed, replayed = z["true"].astype(bool), z["prob"], z["prob_observed"], z["prob_replayed"]
        progress, success, played = z["readout_progress"], z["readout_success"], z["sim_imagined"]
    # the read-out (the judge, here the per-step rule: the smoke model has none) on the simulated episodes,
    # and on their actions replayed open loop
    assert cfg.readout == "judge" and observed.shape == prob.shape and np.all((observed >= 0) & (observed <= 1))
    assert cfg.replay and replayed.shape == prob.shape and np.all((replayed >= 0) & (replayed <= 1))
    for row, o, r in zip(res["policies"], observed, replayed, strict=True):
        assert row["pred_rate_on_truth"] == pytest.approx(o.mean()) and row["pred_rate_replayed"] == pytest.approx(r.mean())
    proxy = np.array([np.nan if p["val_loss"] is None else -p["val_loss"] for p in res["policies"]])
    want = S.within_task({"mug": true}, {"world_model": {"mug": prob}, "proxy": {"mug": proxy},
                                         "readout_progress": {"mug": progress}, "readout_success": {"mug": success},
                                         "on_truth": {"mug": observed}, "replayed": {"mug": replayed},
                                         "sim_imagined": {"mug": played}}, cfg.threshold)
    assert res["metrics"]["within_task"] == json.loads(json.dumps(no_nan(want)))
    # the model against the simulator's outcomes of the actions taken in its imagination
    loop = S.within_task({"mug": played > 0.5}, {"world_model": {"mug": prob}}, cfg.threshold)["world_model"]
    assert res["metrics"]["loop_actions"] == json.loads(json.dumps(no_nan(loop)))
    assert res["metrics"]["mmrv_floor"] == json.loads(json.dumps(no_nan(S.mmrv_floor({"mug": true}))))
    assert res["checkpoint_selection"] == json.loads(json.dumps(no_nan(S.checkpoint_selection(res["policies"]))))
    assert res["world_model"]["cut_short"] is False and res["world_model"]["training"][0]["steps"] == 30


def test_a_replayed_episode_is_imagined_as_the_judge_imagines_its_training_episodes(smoke_world_model, smoke_dataset):
    """The evaluation's replay (a simulated episode's own actions, open loop from its first frame) and
    the judge's imagination of a logged training episode (wm.judge.imagine_episodes) read the same."""
    from sim_data.dataset.cache import TrainingCache
    from wm.checkpoint import load_trained
    from wm.judge import imagine_episodes

    wm_cfg, params, norm = load_trained(smoke_world_model)
    cache = TrainingCache(smoke_dataset[1])
    ep = cache.episode(0, cameras=[HEAD_CAMERA])
    n = ep["record"]["length"]
    frames, proprio = ep["frames"][HEAD_CAMERA][None], ep["proprio"][None]
    truth = {"frames0": frames[:, :1], "proprio0": proprio[:, :1], "frames": frames, "proprio": proprio,
             "action": ep["action"][None, : n - 1]}
    logged = imagine_episodes(wm_cfg.model, params, norm, cache, [0], HEAD_CAMERA, False)["features"]
    for readout in ("success", "progress"):
        want = E.read_episodes(None, "mug", logged)[readout]
        assert E._read_replay((wm_cfg, params, norm, None, None), "mug", truth, readout) == pytest.approx(want, abs=1e-5)
    assert np.isnan(E._read_replay((wm_cfg, params, norm, None, None), "mug", {"frames0": frames[:, :1]}, "success")).all()


def test_kept_features_are_the_imaginations_the_read_outs_read(evaluation):
    cfg, out, _ = evaluation
    task = E.load_task(out / "tasks" / "mug.npz")
    x = E.load_features(out, "mug")
    p, n = task["true"].shape
    assert x.dtype == np.float16 and x.shape[:2] == (p, n) and x.shape[2] == task["trace_success"].shape[-1]
    got = E.read_episodes(None, "mug", x.reshape((p * n,) + x.shape[2:]).astype(np.float32))
    for r in ("success", "progress"):
        assert got[r].reshape(p, n) == pytest.approx(task[f"readout_{r}"], abs=2e-3)
    # the simulated episodes' own features: the read-out of them is the evaluation's on-truth figure
    seen = E.load_features(out, "mug", observed=True)
    assert seen.dtype == np.float16 and seen.shape == x.shape
    on_truth = E.read_episodes(load_judge(Path(cfg.wm)), "mug", seen.reshape((p * n,) + x.shape[2:]).astype(np.float32))
    assert on_truth[cfg.readout].reshape(p, n) == pytest.approx(task["prob_observed"], abs=0.02)
    with pytest.raises(FileNotFoundError, match="keep_features=1"):
        E.load_features(out, "wipe")


def _within(wm_r, proxy_r):
    """A one-task within_task block whose mean Pearson r is wm_r for the world model, proxy_r for the proxy."""
    def stat(r):
        ci = [None, None] if r is None else [r - 0.1, r + 0.1]
        return {"mean": {"pearson": r}, "mean_ci": {"pearson": ci}}

    return {"tasks": ["mug"], "resamples": "policies and initial states", "world_model": stat(wm_r),
            "proxy": stat(proxy_r), "difference": {"proxy": {**stat(None), "per_task_ci": {"mug": {"pearson": [None, None]}}}}}


def test_the_verdict_says_when_there_is_no_ranking_or_no_proxy_to_compare():
    one = {"policies": [{"task": "mug"}], "metrics": {"within_task": _within(None, None)}}
    assert verdict(one).startswith("No within-task ranking to judge") and "mug 1" in verdict(one)
    assert "at least 3 of its policies" in verdict(one)
    plugins = {"policies": [{"task": "mug"}] * 3, "metrics": {"within_task": _within(0.5, float("nan"))}}
    assert verdict(plugins).startswith("The imitation-loss proxy has no within-task figure")
    assert "0.50 [0.40, 0.60]" in verdict(plugins)


def test_the_verdict_says_which_tasks_each_mean_is_over():
    within = _within(0.8, -0.2)
    within["tasks"] = ["mug", "step_back"]
    within["world_model"]["per_task"] = {"mug": {"pearson": 0.7}, "step_back": {"pearson": 0.9}}
    within["proxy"]["per_task"] = {"mug": {"pearson": -0.2}, "step_back": {"pearson": None}}  # its true rates tie
    within["difference"]["proxy"] |= {"mean": {"pearson": 0.9}, "mean_ci": {"pearson": [0.1, 1.5]},
                                      "per_task": {"mug": {"pearson": 0.9}, "step_back": {"pearson": None}},
                                      "per_task_ci": {"mug": {"pearson": [0.1, 1.5]},
                                                      "step_back": {"pearson": [None, None]}}}
    got = verdict({"policies": [{"task": "mug"}] * 3 + [{"task": "step_back"}] * 3, "metrics": {"within_task": within}})
    assert ("(means over the tasks where Pearson r is defined: the world model's over mug and step_back; "
            "the proxy's over mug; the difference over mug)") in got
    assert "lies above 0 in 1 of 1 (mug)" in got


def test_the_verdict_quotes_both_sides_over_the_policies_its_difference_compares():
    """Plug-ins the world model reads backwards beside checkpoints it reads well: the difference to the
    proxy is taken over the checkpoints (the proxy scores no plug-in), so the verdict quotes both over
    them, not the world model's figure over every policy."""
    rng = np.random.default_rng(5)
    rates = np.array([0.95, 0.8, 0.6, 0.4, 0.2, 0.05] * 2)
    true = {t: (rng.random((12, 32)) < rates[:, None]).astype(float) for t in ("mug", "wipe")}
    wm = {t: np.concatenate([np.repeat(rates[:6, None], 32, 1), np.repeat(1 - rates[6:, None], 32, 1)])
          for t in true}
    proxy = {t: np.concatenate([-np.arange(6.0) + rng.normal(0, 2, 6), np.full(6, np.nan)]) for t in true}
    within = S.within_task(true, {"world_model": wm, "proxy": proxy}, draws=200)
    shared = within["difference"]["proxy"]["shared"]
    got = verdict({"policies": [{"task": t} for t in true for _ in range(12)], "metrics": {"within_task": within}})
    assert "over the 12 of 24 policies both rank" in got
    wm_shared = shared["first"]
    assert f"Pearson r {wm_shared['mean']['pearson']:.2f}" in got
    assert within["world_model"]["mean"]["pearson"] < 0.5 < wm_shared["mean"]["pearson"]


def test_a_read_out_that_ranks_better_than_the_ranked_one_is_named_with_how_to_rank_by_it():
    within = _within(0.80, 0.2)
    within["readout_judge2"] = {"mean": {"pearson": 0.90}, "mean_ci": {"pearson": [0.85, 0.95]}}
    within["readout_progress"] = {"mean": {"pearson": 0.85}, "mean_ci": {"pearson": [0.7, 0.9]}}
    within["difference"]["readout_judge2"] = {"mean": {"pearson": -0.10}, "mean_ci": {"pearson": [-0.15, -0.05]}}
    # ahead on the mean but within the interval: not named
    within["difference"]["readout_progress"] = {"mean": {"pearson": -0.05}, "mean_ci": {"pearson": [-0.2, 0.1]}}
    res = {"config": {"readout": "judge"}, "metrics": {"within_task": within}}
    got = better_readout_note(res)
    assert "the judge2 read-out's mean within-task Pearson r 0.90 [0.85, 0.95]" in got
    assert "the ranked read-out (judge) minus it -0.10 [-0.15, -0.05]" in got and "readout=judge2." in got
    assert "progress" not in got
    within["difference"]["readout_judge2"]["mean_ci"]["pearson"] = [-0.15, 0.01]
    assert better_readout_note(res) is None
    within["difference"]["readout_judge2"]["mean_ci"]["pearson"] = [None, None]  # no bootstrap: nothing claimed
    assert better_readout_note(res) is None
    # the geometric read-out is ranked by with its own switch, not as a readout
    within["readout_geometric"] = {"mean": {"pearson": 0.95}, "mean_ci": {"pearson": [0.9, 0.98]}}
    within["difference"]["readout_geometric"] = {"mean": {"pearson": -0.15}, "mean_ci": {"pearson": [-0.2, -0.1]}}
    got = better_readout_note(res)
    assert "the geometric read-out's mean within-task Pearson r 0.95" in got and "geometric_ranks=1." in got
    assert "readout=geometric" not in got


def test_the_decision_figure_draws_without_an_alignment():
    # every imagination diverged: no alignment, no binomial curve, the resampled pairs alone
    decision = {"alignment": None, "episodes": [1, 4, 16], "model": {"0.1": None, "0.3": None},
                "resampled": {"0.3": [0.5, 0.6, 0.7]}, "pairs": {"0.3": 2}}
    assert decision_figure(decision).startswith("data:image/png;base64,")


def test_a_headline_figure_says_whether_it_meets_its_target():
    from experiments.report import target_status

    assert target_status(0.76, (">=", 0.7)) == ": met" and target_status(0.69, (">=", 0.7)) == ": not met"
    assert target_status(0.178, ("<=", 0.05)) == ": not met" and target_status(0.05, ("<=", 0.05)) == ": met"
    assert target_status(float("nan"), (">=", 0.9)) == "" and target_status(None, (">=", 0.9)) == ""


def test_the_decision_figure_says_when_there_is_nothing_to_decide():
    # one policy alone on its task: no pair and no alignment
    decision = {"alignment": None, "episodes": [1, 4, 16], "model": {"0.1": None}, "resampled": {"0.1": None},
                "pairs": {"0.1": 0}}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # matplotlib warns of a legend without entries
        assert decision_figure(decision).startswith("data:image/png;base64,")


def test_a_checkpoint_pick_among_equal_ratings_is_flagged():
    # a constant predictor: every checkpoint rated 0.5, the truly best (step 20) one of three
    rows = [{"task": "mug", "lineage": "conv", "step": s, "pred_rate": 0.5, "true_rate": t,
             "true_ci": [t - 0.1, t + 0.1]} for s, t in ((10, 0.2), (20, 0.8), (30, 0.5))]
    sel = S.checkpoint_selection(rows)
    (x,) = sel["lineages"]
    assert (x["tied"], x["picked_step"], x["best_step"]) == (3, 30, 20)
    assert x["exact"] == pytest.approx(1 / 3) and x["regret"] == pytest.approx(0.8 - 0.5)
    assert "In 1 of them the world model rated several checkpoints equally highest" in selection_summary(sel)
    assert "3 rated equally: 33% of them the best" in md_table(selection_table(sel))
    assert selection_table(sel)[1][2:4] == ["30 (one of 3 rated equally)", "20"]
    ties = [dict(r, true_rate=1.0, true_ci=[0.8, 1.0]) for r in rows]  # every checkpoint truly as good
    assert selection_table(S.checkpoint_selection(ties))[1][3] == "30 (one of 3 truly equal)"
    rows[1]["pred_rate"] = 0.6
    sel = S.checkpoint_selection(rows)
    assert "equally highest" not in selection_summary(sel) and sel["lineages"][0]["exact"] == 1


def test_a_results_file_the_report_cannot_read_is_named_with_what_is_wrong(evaluation, tmp_path):
    _, out, res = evaluation
    run = tmp_path / "run"
    run.mkdir()
    (run / "results.json").write_text(json.dumps(res)[:-40])
    with pytest.raises(ValueError, match=r"results.json is not valid JSON.*cut short"):
        read_results(run)
    (run / "results.json").write_text(json.dumps({k: v for k, v in res.items() if k != "metrics"}))
    with pytest.raises(ValueError, match="lacks metrics"):
        read_results(run)
    rows = [dict(p) for p in res["policies"]]
    del rows[1]["true_ci"]
    (run / "results.json").write_text(json.dumps(res | {"policies": rows}))
    with pytest.raises(ValueError, match=rf"policy '{rows[1]['name']}' \(mug\) lacks true_ci"):
        read_results(run)
    rows = [dict(p) for p in res["policies"]]
    rows[0]["pred_rate"] = float("nan")  # json.dumps writes the token NaN: read as an undefined figure
    (run / "results.json").write_text(json.dumps(res | {"policies": rows}))
    assert read_results(run)["policies"][0]["pred_rate"] is None
    for key, value, says in (("pred_rate", "0.5", r"pred_rate '0.5' is neither a rate in \[0, 1\] nor null"),
                             ("pred_rate", 1.5, r"pred_rate 1.5 is neither"),
                             ("pred_ci", None, r"pred_ci None is not a pair of rates in \[0, 1\] or nulls"),
                             ("true_ci", [0.1], r"true_ci \[0.1\] is not a pair of rates in \[0, 1\] \(edited by hand\?\)"),
                             ("true_rate", True, r"true_rate True is not a rate")):
        rows = [dict(p) for p in res["policies"]]
        rows[0][key] = value
        (run / "results.json").write_text(json.dumps(res | {"policies": rows}))
        with pytest.raises(ValueError, match=rf"policy '{rows[0]['name']}' \(mug\): {says}"):
            read_results(run)
    n = len(res["policies"])
    (run / "results.json").write_text(json.dumps(res | {"policies": res["policies"][1:]}))
    with pytest.raises(ValueError, match=rf"rows do not match the statistics of tasks mug \({n - 1} rows, {n} in"):
        read_results(run)
    (run / "results.json").write_text(json.dumps(res | {"tasks": "mug"}))
    with pytest.raises(ValueError, match="tasks and policies must be lists, got str and list"):
        read_results(run)


def test_names_with_tex_and_markup_render_as_written(own_evaluation):
    _, out, res = own_evaluation
    rows = [dict(p) for p in res["policies"]]
    for p in rows:
        p["lineage"] = "$\\frac{$<b>"  # a pair of "$" is TeX to matplotlib, and this TeX does not parse
    (out / "results.json").write_text(json.dumps(res | {"policies": rows}))
    md = write_report(out).with_suffix(".md").read_text()
    assert "&lt;b>" in md and "<b>" not in md.split("## Within-task ranking")[1]


def test_a_bad_policy_spec_fails_before_out_records_a_configuration(tmp_path):
    cfg = E.EvalConfig(policies=("no_such_package.policies:make",), wm="runs/wm/none", tasks=("mug",))
    with pytest.raises(ValueError, match="cannot import"):
        E.run(cfg, tmp_path / "out", progress=False)
    assert not (tmp_path / "out" / "config.json").exists()


def test_played_actions_give_the_simulated_outcomes_back():
    """simulate_actions, the replay=1 check of the loop's actions: the actions of simulated episodes
    (a plug-in backing away long enough to succeed on step_back, and standing still, from two initial
    states each) played open loop from the same states give the same outcomes."""
    from examples.plugin_policy import make

    policy, params = make()
    still = dict(params, seconds=params["seconds"] * 0)
    keys = np.stack([np.asarray(jax.random.PRNGKey(s)) for s in (11, 12)])
    env = E.cached_env("step_back", 4, "cpu", False)
    outcome, rec = E.record_policies(env, *stacked(policy, [params, still]), keys, jax.random.PRNGKey(0))
    assert outcome.tolist() == [[True, True], [False, False]]
    np.testing.assert_array_equal(E.simulate_actions("step_back", rec.action, keys, "cpu"), outcome)
    with pytest.raises(ValueError, match="actions an episode"):
        E.simulate_actions("step_back", np.asarray(rec.action)[:, :5], keys, "cpu")


def test_plug_ins_alone_are_evaluated_on_every_task_the_world_model_learned(smoke_world_model, tmp_path):
    sources = resolve(["examples.plugin_policy:make"])
    cfg = E.EvalConfig(policies=("examples.plugin_policy:make",), wm=str(smoke_world_model), tasks=())
    # the smoke model has no episode judge: the tasks of its training data's cache
    assert load_judge(smoke_world_model) is None
    assert E.evaluation_tasks(cfg, sources) == ["mug"]
    assert E.evaluation_tasks(dataclasses.replace(cfg, tasks=("step_back",)), sources) == ["step_back"]
    bare = tmp_path / "bare"
    bare.mkdir()
    config = json.loads((Path(smoke_world_model) / "config.json").read_text())
    (bare / "config.json").write_text(json.dumps(config))
    assert trained_tasks(bare) == ("mug",)
    # a judge names the tasks it learned, and an ensemble evaluates those every member learned
    (bare / "judge.json").write_text(json.dumps({"tasks": ["mug", "step_back"]}))
    assert trained_tasks(bare) == ("mug", "step_back")
    assert E.evaluation_tasks(dataclasses.replace(cfg, wm=f"{bare},{smoke_world_model}"), sources) == ["mug"]
    (bare / "judge.json").unlink()
    # nor data at hand: nothing to guess, the error says what to name
    (bare / "config.json").write_text(json.dumps(dict(config, data=str(tmp_path / "gone"))))
    assert trained_tasks(bare) == ()
    with pytest.raises(ValueError, match="name tasks="):
        E.evaluation_tasks(dataclasses.replace(cfg, wm=f"{smoke_world_model},{bare}"), sources)


def test_a_step_limit_records_the_first_segments_of_the_same_episodes():
    """record_policies(steps=...), the warm-up's simulation: the first segment of the same episodes
    (same states, actions and proprioception as the whole episodes' first steps); a limit that is not
    whole segments of the episode is refused."""
    from examples.plugin_policy import make

    policy, params = make()
    keys = np.stack([np.asarray(jax.random.PRNGKey(s)) for s in (11, 12)])
    env = E.cached_env("step_back", 2, "cpu", False)
    _, whole = E.record_policies(env, *stacked(policy, [params]), keys, jax.random.PRNGKey(0))
    _, first = E.record_policies(env, *stacked(policy, [params]), keys, jax.random.PRNGKey(0), steps=SEGMENT)
    assert first.action.shape[1] == SEGMENT and first.proprio.shape[1] == SEGMENT + 1
    np.testing.assert_array_equal(np.asarray(first.action), np.asarray(whole.action)[:, :SEGMENT])
    np.testing.assert_array_equal(np.asarray(first.proprio), np.asarray(whole.proprio)[:, :SEGMENT + 1])
    for bad in (SEGMENT + 1, env.episode_steps + SEGMENT, 0):
        with pytest.raises(ValueError, match=f"multiple of {SEGMENT}"):
            E.record_policies(env, *stacked(policy, [params]), keys, jax.random.PRNGKey(0), steps=bad)


@pytest.mark.slow  # what only the GPU chain uses (pipeline --warm-eval)
def test_the_warm_up_runs_the_programs_the_evaluation_then_runs(smoke_world_model, smoke_zoo, tmp_path):
    """E.warm on a world model that has only started training (its config.json and norm.json) runs
    the evaluation's simulator and imagination programs once each: the evaluation that follows, of
    the trained model on the same policies and states, compiles none of them again (shapes no other
    test evaluates: 3 states a policy). It writes no evaluation."""
    zoo_dir, _ = smoke_zoo
    started = tmp_path / "started"
    started.mkdir()
    for f in ("config.json", "norm.json"):
        shutil.copy(smoke_world_model / f, started / f)
    # the default read-out ("auto", chosen once the judges are fit)
    settings = dict(SMOKE_EVAL, episodes=3, batch=9, keep_features=False, replay=False, video_policies=0,
                    readout=E.AUTO)
    cfg = E.EvalConfig(policies=(f"{zoo_dir}#conv_proprio+conv_noproprio",), wm=str(started), **settings)

    def compiled(step) -> set:  # the programs `step` compiled
        before = compile_snapshot()
        step()
        return {name for name, (count, _) in compile_snapshot()["by_program"].items()
                if count > before["by_program"].get(name, (0, 0.0))[0]}

    assert "_closed_loop_segment" in compiled(lambda: E.warm(cfg, progress=False))  # new shapes: compiled here
    assert list(tmp_path.iterdir()) == [started]
    evaluated = compiled(lambda: E.run(dataclasses.replace(cfg, wm=str(smoke_world_model)), tmp_path / "out",
                                       progress=False))
    assert not evaluated & {"act", "observe", "init_carry", "_closed_loop_start", "_closed_loop_segment",
                            "_observed_segment", "_open_loop_segment"}
    with pytest.raises(FileNotFoundError, match="no started training run"):
        E.warm(dataclasses.replace(cfg, wm=str(tmp_path / "none")), progress=False)


@pytest.mark.slow  # what only the GPU chain uses (the truth simulated beside the training)
def test_a_warm_up_with_a_truth_cache_simulates_the_episodes_the_evaluation_then_reads(evaluation, tmp_path,
                                                                                      monkeypatch):
    """E.warm with truth_cache and truth_frames simulates every batch of the evaluation into the cache;
    the evaluation of the same settings then simulates nothing, and every array it saves (outcomes,
    every read-out, the read-out of the simulated episodes, the frames' fidelity, the videos) is that
    of the evaluation fixture, which simulated its own."""
    cfg, out, _ = evaluation
    kept = dataclasses.replace(cfg, truth_cache=str(tmp_path / "truth"), truth_frames=True)
    E.warm(kept, progress=False)
    batches = E.task_batches(kept, resolve(kept.policies), kept.episodes)
    assert len(list((tmp_path / "truth").glob("mug-*.npz"))) == len(batches) == 2

    def no_simulation(*a, **k):
        raise AssertionError("simulated although the warm-up filled the cache")

    monkeypatch.setattr(E, "record_policies", no_simulation)
    E.run(kept, tmp_path / "run", progress=False)
    with np.load(out / "tasks" / "mug.npz") as want, np.load(tmp_path / "run" / "tasks" / "mug.npz") as got:
        assert sorted(got.files) == sorted(want.files)
        for k in want.files:
            if k != "meta":  # its timings differ
                assert np.array_equal(got[k], want[k], equal_nan=got[k].dtype.kind == "f"), k
        assert np.isfinite(got["prob_observed"]).all()


@pytest.mark.slow  # the GPU presets' option (judge2_inputs), as the other paths only they take
def test_a_second_judge_is_read_beside_the_first_on_the_same_imaginations(evaluation, smoke_world_model, tmp_path):
    """A run with a second episode judge (judge2.*, wm.config's judge2_inputs): the evaluation reads
    the same imaginations with both, reports the second's read-out beside the others, and a bundle
    carries it; a model without one reports no such read-out and cannot rank by it."""
    cfg, _, res = evaluation
    assert all("judge2" not in p["pred_rate_readouts"] and p["pred_rate_on_truth_judge2"] is None
               for p in res["policies"])
    assert "readout_judge2" not in res["metrics"]["within_task"]
    assert "on_truth_judge2" not in res["metrics"]["within_task"]
    assert "judge2" not in res["metrics"]["pooled"]["readouts"]
    with pytest.raises(ValueError, match="readout=judge2 ranks by a second episode judge"):
        E.run(dataclasses.replace(cfg, readout="judge2"), tmp_path / "refused", progress=False)
    run = tmp_path / "wm"
    shutil.copytree(smoke_world_model, run)
    model = load_trained(run)[0].model
    rng = np.random.default_rng(0)
    episodes = {"features": rng.normal(size=(16, 5, feature_dim(model))).astype(np.float32),
                "mask": np.ones((16, 5), bool), "task": ["mug"] * 16, "label": np.arange(16) % 2 == 0}
    for name, inputs in ((J.JUDGE, [g for g in FEATURE_GROUPS if g != "scene"]), (J.SECOND_JUDGE, ["proprio", "action"])):
        judge, metrics = J.fit(episodes, None, ("mug",), steps=3, progress=False, columns=feature_columns(model, inputs))
        J.save_judge(judge, metrics, run, name)
    out = tmp_path / "out"
    got = E.run(dataclasses.replace(cfg, wm=str(run)), out, progress=False)
    task = E.load_task(out / "tasks" / "mug.npz")
    x = E.load_features(out, "mug")
    p, n = task["true"].shape
    read = E.read_episodes(load_judge(run), "mug", x.reshape((p * n,) + x.shape[2:]).astype(np.float32),
                           load_judge(run, J.SECOND_JUDGE))
    assert read["judge2"].reshape(p, n) == pytest.approx(task["readout_judge2"], abs=2e-3)
    assert not np.allclose(task["readout_judge2"], task["readout_judge"])  # other inputs, another reading
    # its reading of the simulated episodes themselves, beside the first judge's
    seen = E.load_features(out, "mug", observed=True).reshape((p * n,) + x.shape[2:]).astype(np.float32)
    on_truth = E.read_episodes(load_judge(run), "mug", seen, load_judge(run, J.SECOND_JUDGE))
    assert on_truth["judge2"].reshape(p, n) == pytest.approx(task[E.OBSERVED_SECOND], abs=0.02)
    assert on_truth[cfg.readout].reshape(p, n) == pytest.approx(task["prob_observed"], abs=0.02)
    assert not np.allclose(task[E.OBSERVED_SECOND], task["prob_observed"])
    for row, r, o in zip(got["policies"], task["readout_judge2"], task[E.OBSERVED_SECOND], strict=True):
        assert row["pred_rate_readouts"]["judge2"] == pytest.approx(r.mean())
        assert row["pred_rate_on_truth_judge2"] == pytest.approx(o.mean())
    assert "readout_judge2" in got["metrics"]["within_task"] and "judge2" in got["metrics"]["pooled"]["readouts"]
    assert "on_truth_judge2" in got["metrics"]["within_task"]
    md = write_report(out).with_suffix(".md").read_text()
    assert "world model, judge2 read-out" in md and "the judge2 read-out of the true episodes" in md
    bundle = tmp_path / "bundle"
    assert checkpoint_main([str(run), str(bundle)]) == 0
    assert load_judge(bundle, J.SECOND_JUDGE).columns.tolist() == feature_columns(model, ["proprio", "action"]).tolist()
    # a second judge that never learned the evaluated task would read it as nothing: ranking by it is refused
    other = dict(episodes, task=["step_back"] * 16)
    judge, metrics = J.fit(other, None, ("step_back",), steps=3, progress=False,
                           columns=feature_columns(model, ["proprio", "action"]))
    J.save_judge(judge, metrics, run, J.SECOND_JUDGE)
    with pytest.raises(ValueError, match=r"second episode judge never learned tasks \['mug'\]"):
        E.run(dataclasses.replace(cfg, wm=str(run), readout="judge2"), tmp_path / "unknown", progress=False)


def test_a_second_judge_that_reads_some_tasks_only_is_left_out_of_the_means_over_tasks():
    """Its mean over tasks would cover fewer tasks than the other read-outs' beside it: it is reported
    only where it reads every task, as in the pooled statistics (read_readouts)."""
    cfg = E.EvalConfig(policies=("x",), wm="w", episodes=4, readout="judge")
    rng = np.random.default_rng(0)
    results = {}
    for t in ("mug", "step_back"):
        results[t] = {"names": [f"p{i}" for i in range(4)], "true": rng.random((4, 4)) < np.linspace(0.1, 0.9, 4)[:, None],
                      "prob": rng.random((4, 4)), **{k: np.full((4, 4), np.nan) for k in
                                                     ("prob_observed", E.OBSERVED_SECOND, "prob_replayed",
                                                      "sim_imagined")},
                      **{f"readout_{r}": rng.random((4, 4)) for r in E.READOUTS}}
    rows = [{"name": f"p{i}", "task": t, "val_loss": 1.0 + i} for t in results for i in range(4)]
    assert "readout_judge2" in E.within_task_block(results, list(results), rows, cfg, lambda n: True)
    results["step_back"]["readout_judge2"] = np.full((4, 4), np.nan)  # a task the second judge does not know
    block = E.within_task_block(results, list(results), rows, cfg, lambda n: True)
    assert "readout_judge2" not in block and "readout_progress" in block
