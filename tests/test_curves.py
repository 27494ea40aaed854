"""wm.curves: loss curves compared step by step against a second seed's distance (hand-computed)."""

import json

import pytest

from wm import curves


def write_run(path, losses, val=None):
    path.mkdir()
    rows = [{"step": s, "loss": v} for s, v in losses.items()]
    for row in rows:
        if val and row["step"] in val:
            row["val_loss"] = val[row["step"]]
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


@pytest.fixture
def runs(tmp_path):
    ref = write_run(tmp_path / "ref", {10: 1.0, 20: 0.5, 30: 0.25}, val={20: 2.0})
    seed = write_run(tmp_path / "seed", {10: 1.1, 20: 0.45, 30: 0.25}, val={20: 2.2})
    close = write_run(tmp_path / "close", {10: 1.0, 20: 0.5, 30: 0.3}, val={20: 2.1})
    far = write_run(tmp_path / "far", {10: 1.3, 20: 0.5, 30: 0.25}, val={20: 1.5})
    return ref, seed, close, far


def test_distances_and_verdicts_match_hand_computed_values(runs):
    ref, seed, close, far = runs
    res = curves.compare(ref, [close, far], seed)
    # relative differences: seed 0.1, 0.1, 0; close 0, 0, 0.2; far 0.3, 0, 0
    c, f = res["runs"][str(close)]["loss"], res["runs"][str(far)]["loss"]
    assert c["seed"]["mean_rel"] == f["seed"]["mean_rel"] == pytest.approx(0.2 / 3)
    assert c["mean_rel"] == pytest.approx(0.2 / 3) and c["within_seed_spread"]
    assert f["mean_rel"] == pytest.approx(0.1) and f["max_rel"] == pytest.approx(0.3)
    assert not f["within_seed_spread"]
    # validation at step 20: seed 0.1, close 0.05, far 0.25
    assert res["runs"][str(close)]["val_loss"]["within_seed_spread"]
    assert res["runs"][str(far)]["val_loss"]["mean_rel"] == pytest.approx(0.25)
    assert not res["runs"][str(far)]["val_loss"]["within_seed_spread"]


def test_after_leaves_out_the_warm_up(runs):
    ref, seed, close, far = runs
    res = curves.compare(ref, [close, far], seed, after=10)
    c, f = res["runs"][str(close)]["loss"], res["runs"][str(far)]["loss"]
    assert c["seed"]["mean_rel"] == pytest.approx(0.05)
    assert c["mean_rel"] == pytest.approx(0.1) and not c["within_seed_spread"]
    assert f["mean_rel"] == 0.0


def test_a_shorter_run_is_held_to_the_seed_over_its_own_steps(runs, tmp_path):
    ref, seed, _, _ = runs
    # stopped after step 10, where the seed is 0.1 off and this run 0.05 off; no validation logged
    short = write_run(tmp_path / "short", {10: 1.05})
    res = curves.compare(ref, [short], seed)
    d = res["runs"][str(short)]
    assert d["loss"]["steps"] == d["loss"]["seed"]["steps"] == 1
    assert d["loss"]["seed"]["mean_rel"] == pytest.approx(0.1) and d["loss"]["within_seed_spread"]
    assert "val_loss" not in d


def test_errors_name_the_problem(runs, tmp_path):
    ref, seed, close, _ = runs
    with pytest.raises(FileNotFoundError, match="not a wm.train output folder"):
        curves.read_curve(tmp_path / "nowhere")
    late = write_run(tmp_path / "late", {40: 0.2})
    with pytest.raises(ValueError, match="share no logged step"):
        curves.compare(ref, [late], seed)
    with pytest.raises(ValueError, match="logs no 'grad_norm'"):
        curves.compare(ref, [close], seed, key="grad_norm")


def test_cli_writes_json_and_plot(runs, tmp_path, capsys):
    ref, seed, close, far = runs
    out, png = tmp_path / "c.json", tmp_path / "c.png"
    assert curves.main([str(ref), str(close), str(far), "--seed-run", str(seed), "--out", str(out),
                        "--plot", str(png)]) == 0
    assert json.loads(out.read_text())["runs"][str(far)]["loss"]["within_seed_spread"] is False
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "0.1000 against 0.0667 (OUTSIDE the seed spread, 3 steps" in capsys.readouterr().out
