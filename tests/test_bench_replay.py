import json

import pytest

from sim_data.bench import replay as R
from sim_data.sim.tasks import get_task


def test_the_replay_bench_times_two_calls_of_each_tasks_whole_episodes(tmp_path, monkeypatch):
    calls = []

    def simulate(task, actions, keys, engine):
        calls.append((task, actions.shape, keys.shape, engine, float(abs(actions).sum())))
        return [[False] * len(actions)]

    monkeypatch.setattr(R, "simulate_actions", simulate)
    out = tmp_path / "replay.json"
    assert R.main(["--out", str(out), "--batch", "3", "--tasks", "mug, wipe", "--engine", "cpu"]) == 0
    steps = {t: get_task(t).episode_steps for t in ("mug", "wipe")}
    assert calls == [(t, (3, steps[t], 20), (3, 2), "cpu", 0.0) for t in ("mug", "mug", "wipe", "wipe")]
    got = json.loads(out.read_text())
    assert got["batch"] == 3 and got["engine"] == "cpu" and [r["task"] for r in got["tasks"]] == ["mug", "wipe"]
    for r in got["tasks"]:
        assert r["steps"] == steps[r["task"]] and r["first_call_s"] >= 0 and r["second_call_s"] > 0
        assert r["env_steps_per_s"] == pytest.approx(3 * r["steps"] / r["second_call_s"])


def test_the_replay_bench_refuses_unknown_tasks_and_empty_batches(tmp_path, capsys):
    for args, says in ((["--tasks", "mug,dishes"], "unknown tasks ['dishes']"), (["--batch", "0"], "--batch must be")):
        with pytest.raises(SystemExit):
            R.main(["--out", str(tmp_path / "r.json"), *args])
        assert says in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()
