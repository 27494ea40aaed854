"""wm.quality.action_sensitivity: does the predicted success move with the actions (hand-made model)."""

import numpy as np
import pytest

from wm import quality as E
from wm.config import make_config
from wm.imagine import SUCCESS_FEATURE

CFG = make_config("smoke")
N = 5  # frames an episode


class FakeCache:
    """Episodes of one task: start value in the frames, constant action `a`, success as given."""

    def __init__(self, rows):
        self.episodes = [{"task": t, "length": N, "success": ok} for t, _, _, ok in rows]
        self._eps = [{"frames": {CFG.camera: np.full((N, 4, 4, 3), start, np.uint8)},
                      "proprio": np.zeros((N, 37), np.float32),
                      "action": np.full((N, 20), a, np.float32)} for _, start, a, _ in rows]

    def episode(self, i, cameras=None):
        return self._eps[i]


def fake_imagination(read):
    """open_loop_chunked whose success feature at every step is read(first frame's value, actions); it is
    asked for the features alone (the frames stay on the device)."""
    def imagine(model, params, norm, samples, horizon, keys):
        assert keys == ("features",)
        feats = np.zeros((len(samples), horizon, 8), np.float32)
        for k, s in enumerate(samples):
            feats[k, :, SUCCESS_FEATURE] = read(float(s["frames"][0, 0, 0, 0]), float(s["actions"].mean()))
        return {"features": feats}
    return imagine


ROWS = [("mug", 10, 0.9, True), ("mug", 20, 0.8, True), ("mug", 30, 0.1, False),
        ("step_back", 40, 0.7, True), ("step_back", 50, 0.2, False), ("step_back", 60, 0.3, False)]


def test_a_model_that_reads_the_actions_follows_them(monkeypatch):
    monkeypatch.setattr(E, "open_loop_chunked", fake_imagination(lambda start, a: a))
    got = E.action_sensitivity(CFG, None, None, FakeCache(ROWS), list(range(6)))
    # mug: successes 0.9, 0.8 given the failure's 0.1; the failure 0.1 given 0.9.
    # step_back: the success 0.7 given 0.2; failures 0.2, 0.3 given 0.7 each
    assert got["swaps"] == 6 and got["follows_actions"] == 1.0
    assert got["success_own"] == pytest.approx((0.9 + 0.8 + 0.7) / 3)
    assert got["success_swapped"] == pytest.approx((0.1 + 0.1 + 0.2) / 3)
    assert got["failure_own"] == pytest.approx((0.1 + 0.2 + 0.3) / 3)
    assert got["failure_swapped"] == pytest.approx((0.9 + 0.7 + 0.7) / 3)
    assert got["mean_abs_change"] == pytest.approx((0.8 + 0.7 + 0.8 + 0.5 + 0.5 + 0.4) / 6)


def test_a_model_that_reads_the_start_ignores_the_actions(monkeypatch):
    monkeypatch.setattr(E, "open_loop_chunked", fake_imagination(lambda start, a: start / 100))
    got = E.action_sensitivity(CFG, None, None, FakeCache(ROWS), list(range(6)))
    assert got["follows_actions"] == 0.0 and got["mean_abs_change"] == 0.0
    assert got["success_own"] == got["success_swapped"]


def test_tasks_with_one_outcome_give_no_swaps(monkeypatch):
    monkeypatch.setattr(E, "open_loop_chunked", fake_imagination(lambda start, a: a))
    got = E.action_sensitivity(CFG, None, None, FakeCache(ROWS[:2]), [0, 1])
    assert got["swaps"] == 0 and "both successes and failures" in got["note"]


def test_imaginations_under_the_own_actions_are_read_from_those_given(monkeypatch):
    seen = []

    def swapped_only(model, params, norm, samples, horizon, keys):
        seen.extend(float(s["actions"].mean()) for s in samples)
        return fake_imagination(lambda start, a: a)(model, params, norm, samples, horizon, keys)

    monkeypatch.setattr(E, "open_loop_chunked", swapped_only)
    # the given imaginations (one row an episode, padded a step longer) read 0.6 for every episode
    own = np.zeros((6, N, 8), np.float32)
    own[:, : N - 1, SUCCESS_FEATURE] = 0.6
    got = E.action_sensitivity(CFG, None, None, FakeCache(ROWS), list(range(6)), imagined={"features": own})
    assert got["success_own"] == pytest.approx(0.6) and got["failure_own"] == pytest.approx(0.6)
    assert got["success_swapped"] == pytest.approx((0.1 + 0.1 + 0.2) / 3)
    assert sorted(seen) == pytest.approx(sorted([0.1, 0.1, 0.9, 0.2, 0.7, 0.7]))  # the donors' actions only
