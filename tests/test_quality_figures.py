"""eval.json's figures against hand computations: which held-out episodes are drawn, the success
AUROC within each task beside the pooled one, and the horizons of the frame figures."""

import dataclasses

import numpy as np
import pytest

import wm.quality as Q
from wm.config import TrainConfig
from wm.judge import spread
from wm.metrics import auroc, auroc_within_groups


def test_the_held_out_episodes_are_drawn_over_the_whole_list_not_its_head():
    ids = list(range(190))  # the cache's order: task a's 95 episodes, then task b's 95
    got = spread(ids, 96)  # a stride of 190 // 96 = 1 cut at 96 would take one episode of task b
    assert len(got) == len(set(got)) == 96
    assert sum(i < 95 for i in got) == 48 and sum(i >= 95 for i in got) == 48
    assert got[:4] == [0, 1, 3, 5] and got[-1] == 95 * 190 // 96
    assert spread(ids[:10], 96) == ids[:10]
    assert spread(list(range(6000)), 600) == list(range(0, 6000, 10))  # a whole stride: every tenth


def test_a_score_that_only_knows_the_task_scores_one_half_within_each_task():
    tasks = np.array(["a"] * 8 + ["b"] * 8)
    labels = np.array([1, 1, 1, 1, 1, 1, 0, 0] + [1, 1, 0, 0, 0, 0, 0, 0], bool)
    rate = np.where(tasks == "a", labels[:8].mean(), labels[8:].mean())  # the task's success rate alone
    pos, neg = rate[labels], rate[~labels]
    hand = ((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum()) / (len(pos) * len(neg))
    assert auroc(rate, labels) == pytest.approx(hand) and hand > 0.7  # pooled: credited for the task
    within, each = auroc_within_groups(rate, labels, tasks)
    assert within == pytest.approx(0.5) and each == {"a": 0.5, "b": 0.5}
    # a task with one outcome is undefined and left out of the mean
    within, each = auroc_within_groups([0.9, 0.1, 0.5, 0.6], [1, 0, 1, 1], ["a", "a", "b", "b"])
    assert within == 1.0 and np.isnan(each["b"])


def test_success_summary_reports_the_headlines_auroc_within_task():
    rules = {"per_step_rule_": np.array([0.9, 0.8, 0.2, 0.95, 0.6, 0.7])}
    labels = np.array([1, 1, 0, 1, 0, 1], bool)
    tasks = ["a", "a", "a", "b", "b", "b"]
    out = Q._success_summary(rules, labels, tasks)
    assert out["auroc"] == pytest.approx(auroc(rules["per_step_rule_"], labels))
    assert out["auroc_within_task"] == pytest.approx(1.0)
    assert out["per_step_rule_auroc_per_task"] == {"a": 1.0, "b": 1.0}


def test_frame_figures_score_the_hth_imagined_frame_and_copy_last_at_the_same_frame(monkeypatch):
    """A perfect model scores 100 dB at every horizon; copy-last at horizon h is the last context
    frame against the frame h steps after it (frame t is a flat grey of level t: PSNR 20 log10(255 / h))."""
    cfg = dataclasses.replace(TrainConfig(), eval_context=4, eval_horizons=(1, 4, 8))
    length = 40
    frames = np.stack([np.full((8, 8, 3), t, np.uint8) for t in range(length)])
    actions = np.repeat(np.arange(length, dtype=np.float32)[:, None], 20, axis=1)  # action t follows frame t

    class Cache:
        episodes = [{"length": length}]

        def episode(self, i, cameras=None):
            return {"frames": {cfg.camera: frames}, "proprio": np.zeros((length, 37), np.float32), "action": actions,
                    "record": {"length": length}}

    def perfect(mcfg, params, norm, samples, horizon, keys=None):
        return {"frames": np.stack([frames[s["actions"][:horizon, 0].astype(int) + 1] for s in samples])}

    monkeypatch.setattr(Q, "open_loop_chunked", perfect)
    monkeypatch.setattr(Q, "available", lambda: False)
    res, _ = Q.frame_quality(cfg, None, None, Cache(), [0])
    assert res["psnr"] == [100.0, 100.0, 100.0]
    np.testing.assert_allclose(res["copy_last_psnr"], [20 * np.log10(255 / h) for h in cfg.eval_horizons])
