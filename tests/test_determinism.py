"""The same command gives the same figures: a second training of the smoke world model, and one killed
with SIGKILL at a random point and rerun, give the parameters, judge and evaluation of the first."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import SMOKE_EVAL

from experiments import evaluate as E
from sim_data.policies.registry import resolve
from wm.checkpoint import load_trained, training_status

ROOT = Path(__file__).resolve().parents[1]


def _same_params(a: Path, b: Path) -> None:
    (_, pa, _), (_, pb, _) = load_trained(a), load_trained(b)
    for x, y in zip(jax.tree_util.tree_leaves(pa), jax.tree_util.tree_leaves(pb), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert (a / "norm.json").read_text() == (b / "norm.json").read_text()


def _train_command(data: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "wm.train", "--config", "smoke", "--data", str(data), "--out", str(out)]


@pytest.mark.slow
def test_a_killed_and_rerun_training_equals_an_uninterrupted_one(smoke_dataset, smoke_world_model, tmp_path):
    _, data, _ = smoke_dataset
    out = tmp_path / "killed"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    delay = np.random.default_rng(int(time.time())).uniform(3.0, 15.0)  # a random point of the run
    proc = subprocess.Popen(_train_command(data, out), cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        proc.wait(timeout=delay)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    done = subprocess.run(_train_command(data, out), cwd=ROOT, env=env, capture_output=True, text=True)
    assert done.returncode == 0, f"killed after {delay:.1f} s, the rerun failed:\n{done.stderr[-3000:]}"
    assert training_status(out) == {"step": 30, "steps": 30, "cut_short": False}
    _same_params(smoke_world_model, out)
    assert (out / "judge.json").exists() == (smoke_world_model / "judge.json").exists()
    if (out / "judge.json").exists():
        assert (out / "judge.json").read_text() == (smoke_world_model / "judge.json").read_text()
    mine, theirs = (json.dumps(json.loads((d / "eval.json").read_text())["summary"]) for d in (out, smoke_world_model))
    assert mine == theirs, f"killed after {delay:.1f} s"


def test_the_same_evaluation_twice_gives_the_same_figures(smoke_zoo, smoke_world_model, tmp_path):
    zoo_dir, _ = smoke_zoo
    # the evaluation fixture's first batch (3 checkpoints of one architecture from 2 states) with its
    # settings: the programs it compiles, not a batch of its own
    sources = resolve([f"{zoo_dir}#conv_proprio+conv_noproprio"])[:3]
    assert len({s.policy for s in sources}) == 1
    cfg = E.EvalConfig(policies=(f"{zoo_dir}#" + "+".join(s.name for s in sources),), wm=str(smoke_world_model),
                       **SMOKE_EVAL)
    assert len(E.task_chunks(cfg, resolve(cfg.policies), cfg.episodes)) == 1
    one, two = (E.run(cfg, tmp_path / name, progress=False) for name in ("one", "two"))
    for a, b in zip(one["policies"], two["policies"], strict=True):
        assert a["true_episodes"] == b["true_episodes"]
        assert a["pred_rate"] == pytest.approx(b["pred_rate"], abs=1e-9)
    assert json.dumps(one["metrics"]) == json.dumps(two["metrics"])


def test_a_policy_in_a_batch_of_its_own_reads_the_same_whatever_else_is_evaluated(smoke_zoo, smoke_world_model,
                                                                                   tmp_path):
    """With batch = episodes every policy runs alone (the demo's setting): its true and imagined episodes
    are then those of the policy itself, not of the batch it shares."""
    zoo_dir, _ = smoke_zoo
    sources = resolve([f"{zoo_dir}#conv_proprio+conv_noproprio"])[:3]
    settings = {**SMOKE_EVAL, "batch": SMOKE_EVAL["episodes"], "replay": False, "keep_features": False}
    runs = {}
    for name, part in (("alone", sources[1:2]), ("beside", sources)):
        cfg = E.EvalConfig(policies=(f"{zoo_dir}#" + "+".join(s.name for s in part),), wm=str(smoke_world_model),
                           **settings)
        assert len(E.task_chunks(cfg, resolve(cfg.policies), cfg.episodes)) == len(part)
        runs[name] = {p["name"]: p for p in E.run(cfg, tmp_path / name, progress=False)["policies"]}
    a, b = runs["alone"][sources[1].name], runs["beside"][sources[1].name]
    assert a["true_episodes"] == b["true_episodes"]
    assert a["pred_episodes"] == b["pred_episodes"]
