"""A user's mistaken world-model inputs to experiments.evaluate end in one line naming them (no
simulation: each refusal comes before the first task)."""

import json

import numpy as np
import pytest

from experiments import evaluate as E
from sim_data.util import run_cli
from wm.checkpoint import load_trained, trained_tasks
from wm.config import TrainConfig
from wm.imagine import Norm


def test_a_damaged_json_file_of_a_run_or_bundle_is_named(tmp_path):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "bundle.json").write_text('{"format": 1, "sha256": {"params-0.msgpack": "ab')  # half copied
    with pytest.raises(ValueError, match=r"bundle/bundle.json is not valid JSON .*copy it again"):
        load_trained(bundle)
    with pytest.raises(ValueError, match=r"bundle/bundle.json is not valid JSON"):
        trained_tasks(bundle)
    run = tmp_path / "run"
    (run / "best").mkdir(parents=True)
    (run / "config.json").write_text('{"train": {"model": ')
    with pytest.raises(ValueError, match=r"run/config.json is not valid JSON"):
        load_trained(run)
    (tmp_path / "list").mkdir()
    (tmp_path / "list" / "bundle.json").write_text("[]")
    with pytest.raises(ValueError, match=r"list/bundle.json is not a JSON object"):
        trained_tasks(tmp_path / "list")


def test_an_ensemble_naming_one_directory_twice_however_spelled_is_refused(tmp_path):
    run = tmp_path / "wm"
    run.mkdir()
    (tmp_path / "link").symlink_to(run)
    for twice in (f"{run},{run}/", f"{run},{tmp_path}/./wm", f"{run},{tmp_path / 'link'}"):
        with pytest.raises(ValueError, match="wm names a run twice"):
            E.make_config("demo", [f"wm={twice}"])
    E.make_config("demo", [f"wm={run},{tmp_path / 'other'}"])  # two directories: an ensemble
    bundle = tmp_path / "bundle"  # the run's own bundle: the same model in bfloat16
    bundle.mkdir()
    (bundle / "bundle.json").write_text(json.dumps({"format": 1, "source": str(tmp_path / "link"), "sha256": {},
                                                    "files": {}}))
    with pytest.raises(ValueError, match="bundle of a run it also names: the same world model twice"):
        E.make_config("demo", [f"wm={run},{bundle}"])
    (run / "config.json").write_text("{}")  # another model trained since at the same path: an ensemble
    E.make_config("demo", [f"wm={run},{bundle}"])
    E.make_config("demo", [f"wm={tmp_path / 'other'},{bundle}"])  # a bundle beside another run


def test_tasks_a_bundle_never_learned_are_found_without_its_training_data(tmp_path):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    meta = {"format": 1, "sha256": {}, "files": {"judge.json": {"tasks": ["mug", "step_back"]},
                                                  "config.json": {"train": {}, "data": "/elsewhere/data"}}}
    (bundle / "bundle.json").write_text(json.dumps(meta))
    assert E.unlearned_tasks([str(bundle)], ["arcade", "mug"]) == ["arcade"]


def _model(scale: float):
    norm = Norm(*(np.full(n, scale, np.float32) for n in (37, 37, 20, 20)))
    return TrainConfig(), {"w": np.full((3,), scale, np.float32)}, norm, None


def test_a_rerun_with_another_world_model_at_the_same_path_is_refused(tmp_path):
    cfg = E.make_config("demo", ["policies=examples.plugin_policy:make", f"wm={tmp_path / 'wm'}"])
    out = tmp_path / "eval"
    (out / "tasks").mkdir(parents=True)
    E._check_config(cfg, out, [], [_model(1.0)])
    (out / "tasks" / "mug.npz").write_bytes(b"")  # a finished task, read back by a rerun
    E._check_config(cfg, out, [], [_model(1.0)])  # the same model: the rerun resumes
    with pytest.raises(ValueError, match="holds results of the world model .* as it was then"):
        E._check_config(cfg, out, [], [_model(2.0)])  # trained again, or another bundle copied there
    saved = json.loads((out / "config.json").read_text())
    saved.pop(E.WM_FINGERPRINTS)  # an OUT that records no world model's fingerprint resumes
    (out / "config.json").write_text(json.dumps(saved))
    E._check_config(cfg, out, [], [_model(2.0)])


def test_a_rerun_may_add_or_drop_a_truth_cache_that_keeps_the_frames_but_not_one_without(tmp_path):
    """A truth cache with its frames gives an evaluation's figures exactly (docs/benchmarks.md), so a rerun
    into the same OUT may read one or not; one without frames leaves the frame figures NaN, so a task
    saved with them is not resumed without (nor the other way) and neither is another episode count."""
    base = ["policies=examples.plugin_policy:make", "video_policies=0"]
    out = tmp_path / "eval"
    (out / "tasks").mkdir(parents=True)
    E._check_config(E.make_config("demo", base), out, [])
    (out / "tasks" / "mug.npz").write_bytes(b"")
    for extra in ([f"truth_cache={tmp_path / 'truth'}", "truth_frames=1"], ["max_minutes=3"], []):
        E._check_config(E.make_config("demo", base + extra), out, [])
    for extra, field in (([f"truth_cache={tmp_path / 'truth'}"], "truth_cache_without_frames"),
                         (["episodes=3"], "episodes")):
        with pytest.raises(ValueError, match=rf"another configuration \(differs: {field}\)"):
            E._check_config(E.make_config("demo", base + extra), out, [])


def test_the_demo_preset_ranks_as_make_demo_does_and_names_missing_geometric_models(tmp_path, monkeypatch, capsys):
    cfg = E.make_config("demo")
    assert (cfg.geometric, cfg.geometric_ranks) == ("runs/fill/demo", True)  # what `make demo`'s chain passes
    monkeypatch.chdir(tmp_path)  # no runs/fill/demo here
    args = ["--out", "o", "wm=no/such/wm", "policies=examples.plugin_policy:make"]
    assert run_cli(lambda: E.main(args)) == 2
    err = capsys.readouterr().err
    assert "geometric=runs/fill/demo holds no geometric models" in err and "geometric= geometric_ranks=0" in err
    assert run_cli(lambda: E.main(args + ["geometric=", "geometric_ranks=0"])) == 2  # the judge alone: on to the model
    assert "no/such/wm" in capsys.readouterr().err
