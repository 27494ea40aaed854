"""experiments.pipeline: the stages' order of work, an ensemble's members, a host's GPUs (no training here:
the modules' entry points are replaced by recorders)."""

import dataclasses
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import threading
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from jax._src import cache_key as jax_cache_key

from experiments import cache_keys as K
from experiments import pipeline as P
from sim_data import util
from wm.checkpoint import RUN_FILES, bundle_meta


@pytest.fixture(autouse=True)
def keep_caches(monkeypatch):
    """The stages clear JAX's caches; here that would cost the other tests of this process the programs
    they compiled."""
    monkeypatch.setattr(P.jax, "clear_caches", lambda: None)


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    """A pipeline of 3 members under tmp_path whose training entry point records its arguments and
    writes the eval.json a finished training leaves."""
    monkeypatch.setitem(P.PIPELINES, "tiny", P.Pipeline(data="d", policies="p", train="smoke", eval="demo",
                                                        root=str(tmp_path), members=3,
                                                        train_overrides=("max_minutes=1",)))
    calls = []

    def fake_train(argv):
        calls.append(argv)
        out = argv[argv.index("--out") + 1]
        (tmp_path / out).mkdir(parents=True, exist_ok=True)
        (tmp_path / out / "eval.json").write_text(json.dumps({}))

    import wm.train

    monkeypatch.setattr(wm.train, "main", fake_train)
    monkeypatch.setattr(P, "write_bundle", fake_bundle)
    return calls, P.PIPELINES["tiny"].dirs("tiny")


def fake_bundle(run, out):
    """Stands in for wm.checkpoint.write_bundle on the fake trainings: a bundle.json holding its run's files."""
    out.mkdir(parents=True, exist_ok=True)
    meta = {"files": {n: json.loads((run / n).read_text()) for n in RUN_FILES if (run / n).exists()}, "sha256": {}}
    (out / "bundle.json").write_text(json.dumps(meta))
    return meta


def test_without_gpus_the_train_stage_trains_one_member_a_run_and_eval_waits_for_all(tiny, monkeypatch):
    calls, d = tiny
    assert [m.name for m in d["members"]] == ["tiny", "tiny_seed1", "tiny_seed2"]
    with pytest.raises(SystemExit, match="not trained yet"):
        P.run_stage("tiny", "eval")
    assert P.run_stage("tiny", "train") is False and P.run_stage("tiny", "train") is False
    assert not any(b.exists() for b in d["bundles"])  # not before every member is trained
    assert P.run_stage("tiny", "train") is True and len(calls) == 3
    assert "seed=1" in calls[1] and "seed=2" in calls[2] and not any(a.startswith("seed=") for a in calls[0])
    assert all("max_minutes=1" in c for c in calls)
    assert P.run_stage("tiny", "train") is True and len(calls) == 3  # all trained: nothing more
    assert [b.name for b in d["bundles"]] == ["tiny", "tiny_seed1", "tiny_seed2"]
    logs = Path(P.PIPELINES["tiny"].root) / "logs" / "tiny"
    listed = json.loads((logs / P.BUNDLES).read_text())
    assert list(listed) == [str(b) for b in d["bundles"]]  # every member's, once all were trained
    (d["members"][1] / "eval.json").write_text(json.dumps({"trained": "again"}))
    assert P.bundle_members(d, logs) == [d["bundles"][1]]  # the others' bundles hold their trainings already
    assert [bundle_meta(b)["files"]["eval.json"] for b in d["bundles"]] == [{}, {"trained": "again"}, {}]
    assert json.loads((logs / P.BUNDLES).read_text()) != listed  # a new list for --follow --until-bundle
    got = []
    import experiments.evaluate

    monkeypatch.setattr(experiments.evaluate, "main", got.append)
    P.run_stage("tiny", "eval")
    assert f"wm={d['members'][0]},{d['members'][1]},{d['members'][2]}" in got[0]


def test_a_preset_with_geometric_tasks_fits_their_models_after_training_and_ranks_them_by_it(tiny, monkeypatch):
    """The train stage fits the geometric models at the world model's frame size once the members are
    trained (not before): the motion models and the fill of step_back on the data, then the grasp rule of
    the mug on the world model's data (the rollouts among it); the eval stage names them and ranks by
    them, and asks the fit again for what is missing (experiments.fill leaves what is fit), at the frame
    size of the model it is given where one is carried from another lease (wm=BUNDLE)."""
    _, d = tiny
    monkeypatch.setitem(P.PIPELINES, "tiny", dataclasses.replace(P.PIPELINES["tiny"], members=1,
                                                                 geometric="step_back,mug",
                                                                 geometric_args=("--steps", "7")))
    d = P.PIPELINES["tiny"].dirs("tiny")
    fits, evals, read = [], [], []
    sizes = {str(d["wm"]): 48, "carried/bundle": 64}

    def run_config(run):
        read.append(str(run))
        smoke = P.wm_config.make_config("smoke")
        return dataclasses.replace(smoke, model=dataclasses.replace(smoke.model, size=sizes[str(run)])), None

    monkeypatch.setattr(P.fill, "main", fits.append)
    monkeypatch.setattr(P, "load_run_config", run_config)
    assert P.run_stage("tiny", "train") is True

    def fit_at(size):
        return [["--data", str(d["data"]), "--tasks", "step_back", "--out", str(d["geometric"]), "--size", size,
                 "--steps", "7"],
                ["--data", str(d["wm_data"]), "--tasks", "mug", "--out", str(d["geometric"]), "--size", size,
                 "--steps", "7"]]

    assert fits == fit_at("48") and read == [str(d["wm"])]
    import experiments.evaluate

    monkeypatch.setattr(experiments.evaluate, "main", evals.append)
    P.run_stage("tiny", "eval")
    assert f"geometric={d['geometric']}" in evals[0] and "geometric_ranks=1" in evals[0]
    assert fits == fit_at("48") * 2
    P.run_stage("tiny", "eval", extra=["wm=carried/bundle,carried/other"])
    assert read[-1] == "carried/bundle" and fits[-2:] == fit_at("64")
    assert "wm=carried/bundle,carried/other" in evals[1]


def test_members_seeds_follow_a_seed_set_and_a_trained_member_refuses_changed_settings(tiny):
    """--set train:seed=5 gives the members 5, 6, 7 (each its own model, not three of seed 5); once they
    are trained, a train stage with other settings is refused rather than keeping the models as they are."""
    calls, d = tiny
    while not P.run_stage("tiny", "train", extra=["seed=5"]):
        pass
    assert [[a for a in c if a.startswith("seed=")][-1] for c in calls] == ["seed=5", "seed=6", "seed=7"]
    assert P.run_stage("tiny", "train", extra=["seed=5"])  # the same settings: trained, skipped
    with pytest.raises(ValueError, match=r"another configuration \(differs: train.steps\)"):
        P.run_stage("tiny", "train", extra=["seed=5", "steps=99"])


def test_every_stages_settings_are_checked_before_any_work(monkeypatch):
    ran = []
    monkeypatch.setattr(P, "run_stage", lambda *a, **k: ran.append(a) or True)
    monkeypatch.setattr(P, "use_compilation_cache", lambda root, key_log=None: "")
    for argv in (["--set", "eval:episodez=50"], ["--set", "train:stepz=3500"], ["--set", "eval:episodes=55"],
                 ["--set", "data:tasks=mug,mug"], ["--set", "report:x=1"], ["--stage", "report", "x=1"],
                 ["--stage", "policies", "stepz=1"]):
        with pytest.raises(SystemExit):
            P.main(["full", *argv])
    assert not ran


def test_with_several_gpus_stages_run_in_parts_and_members_side_by_side(tiny, monkeypatch):
    calls, d = tiny
    spawned = []
    monkeypatch.setattr(P, "run_parallel", lambda cmds, gpus, logs, label, on: spawned.append((cmds, gpus, label)))
    import sim_data.dataset.generate

    gathered = []
    monkeypatch.setattr(sim_data.dataset.generate, "main", gathered.append)
    P.run_stage("tiny", "data", gpus=["0", "1"])
    cmds, gpus, _ = spawned[0]
    assert gpus == ["0", "1"] and [c[c.index("--part") + 1] for c in cmds] == ["0/2", "1/2"]
    assert all(c[1:3] == ["-m", "experiments.timing"] and c[4] == "sim_data.dataset.generate" for c in cmds)
    assert [Path(c[3]).name for c in cmds] == ["data-part-0.timing.json", "data-part-1.timing.json"]
    assert "--part" not in gathered[0]
    P.run_stage("tiny", "train", gpus=["0", "1"])  # two members at once, the third in the next run
    cmds, gpus, label = spawned[1]
    assert label == "train-member" and len(cmds) == 2 and "seed=1" in cmds[1] and gpus == ["0", "1"]
    for m in d["members"][:2]:  # what a finished member leaves
        m.mkdir(parents=True, exist_ok=True)
        (m / "eval.json").write_text("{}")
    P.run_stage("tiny", "train", gpus=["0", "1"])  # the one member left trains on both GPUs
    cmds, gpus, _ = spawned[2]
    assert len(cmds) == 1 and "seed=2" in cmds[0] and gpus == ["0,1"]


def test_without_gpus_only_the_evaluation_spreads_over_the_cores(tiny, monkeypatch):
    calls, d = tiny
    spawned = []
    monkeypatch.setattr(P, "run_parallel",
                        lambda cmds, slots, logs, label, on: spawned.append((cmds, slots, label, on)))
    import experiments.evaluate
    import sim_data.dataset.generate

    gathered = []
    monkeypatch.setattr(sim_data.dataset.generate, "main", gathered.append)
    monkeypatch.setattr(experiments.evaluate, "main", gathered.append)
    P.run_stage("tiny", "data", cores=["0", "1"])
    assert spawned == [] and "--part" not in gathered[0]  # the generator runs its own workers
    for m in d["members"]:
        m.mkdir(parents=True, exist_ok=True)
        (m / "eval.json").write_text("{}")
    P.run_stage("tiny", "eval", cores=["0", "1"])
    cmds, slots, label, on = spawned[0]
    assert (slots, label, on) == (["0", "1"], "eval-part", "cpu")
    assert [c[c.index("--part") + 1] for c in cmds] == ["0/2", "1/2"]
    assert all(c[4] == "experiments.evaluate" for c in cmds) and "--part" not in gathered[1]
    rows = json.loads((d["eval"] / P.TIMING).read_text())
    assert rows[-1]["cores"] == 2
    table = P.report.timing_table(rows)
    assert [r[table[0].index("CPU processes")] for r in table[1:-1]] == ["-", "2"]
    P.run_stage("tiny", "eval", gpus=["0"], cores=["0", "1"])  # a GPU's process evaluates alone
    assert len(spawned) == 1 and "cores" not in json.loads((d["eval"] / P.TIMING).read_text())[-1]
    P.run_stage("tiny", "eval", ["keep_features=1"], cores=["0", "1"])  # one process keeps the features
    assert len(spawned) == 1 and "keep_features=1" in gathered[-1]


def test_gpus_are_shared_out_in_equal_groups():
    assert P.gpu_groups(["0", "1", "2", "3"], 2) == ["0,1", "2,3"]
    assert P.gpu_groups(["0", "1", "2"], 2) == ["0", "1"]  # the odd one left unused
    assert P.gpu_groups(["4", "7"], 1) == ["4,7"]
    with pytest.raises(ValueError, match="cannot be shared"):
        P.gpu_groups(["0"], 2)


def test_a_smaller_ensemble_trains_and_evaluates_only_its_members(tiny, monkeypatch):
    calls, d = tiny
    assert P.run_stage("tiny", "train", members=2) is False
    assert P.run_stage("tiny", "train", members=2) is True and len(calls) == 2
    got = []
    import experiments.evaluate

    monkeypatch.setattr(experiments.evaluate, "main", got.append)
    P.run_stage("tiny", "eval", members=2)
    assert f"wm={d['members'][0]},{d['members'][1]}" in got[0] and str(d["members"][2]) not in " ".join(got[0])
    with pytest.raises(SystemExit, match="not trained yet"):
        P.run_stage("tiny", "eval")  # the preset's three members
    with pytest.raises(ValueError, match="at least one"):
        P.pipeline("tiny", 0)


def test_the_eval_stage_evaluates_a_model_named_by_wm_though_no_member_was_trained_here(tiny, monkeypatch):
    got = []
    import experiments.evaluate

    monkeypatch.setattr(experiments.evaluate, "main", got.append)
    P.run_stage("tiny", "eval", ["wm=runs/bundles/elsewhere"])
    assert [a for a in got[0] if a.startswith("wm=")] == ["wm=runs/bundles/elsewhere"]


def test_the_eval_stage_is_done_only_once_its_results_hold_every_task(tiny, monkeypatch):
    """An evaluation its safety time limit stopped writes results.json marked cut short: the stage is to be
    continued (the chain stops there and its rerun finishes), as when it writes nothing."""
    _, d = tiny
    import experiments.evaluate

    def evaluates(cut_short):
        def main(argv):
            d["eval"].mkdir(parents=True, exist_ok=True)
            (d["eval"] / "results.json").write_text(json.dumps({"cut_short": cut_short, "timing": {}}))
        return main

    for cut_short, done in (({"max_minutes": 8.0, "tasks_left": ["wipe"]}, False), (None, True)):
        monkeypatch.setattr(experiments.evaluate, "main", evaluates(cut_short))
        assert P.run_stage("tiny", "eval", ["wm=runs/bundles/elsewhere"]) is done
    monkeypatch.setattr(experiments.evaluate, "main", lambda argv: None)  # stopped before its first task's end
    assert P.run_stage("tiny", "eval", ["wm=runs/bundles/elsewhere"]) is False


CACHE_KEY_PROGRAM = """
import sys
import jax, jax.numpy as jnp
from sim_data.util import run_cli
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
scale = float(sys.argv[2])
def main():
    def doubled(x):
        return x * 2.0
    jax.jit(doubled)(jnp.ones(3)).block_until_ready()  # the same program in both
    def scaled(x):
        return jnp.sin(x) * scale
    jax.jit(scaled)(jnp.ones(3)).block_until_ready()  # another constant: another program
run_cli(main)
"""


def test_the_cache_key_log_names_the_part_of_a_key_that_moved_between_two_processes(tmp_path):
    log = tmp_path / "logs" / "cache_keys.log"
    env = {**os.environ, P.CACHE_KEY_LOG_ENV: str(log)}
    for scale in ("1.0", "3.0"):
        subprocess.run([sys.executable, "-c", CACHE_KEY_PROGRAM, str(tmp_path / "cache"), scale], env=env, check=True)
    first, second = tmp_path / "first.log", tmp_path / "second.log"
    lines = log.read_text().splitlines()
    pids = list(dict.fromkeys(line.split("\t")[0] for line in lines))
    assert len(pids) == 2  # one run_cli process each, both logging through the environment
    for pid, path in zip(pids, (first, second)):
        path.write_text("\n".join(x for x in lines if x.startswith(pid + "\t")) + "\n")
    a, b = K.read_cache_keys(first), K.read_cache_keys(second)
    assert not a["jit_scaled"]["hit"] and not b["jit_scaled"]["hit"]
    assert not a["jit_doubled"]["hit"] and b["jit_doubled"]["hit"]  # the second found the first's program
    assert set(a["jit_scaled"]["parts"]) >= {"computation", "jax_lib version", "XLA flags", "compile_options"}
    rows = {r["program"]: r for r in K.compare(a, b)}
    assert rows["jit_scaled"]["differs"] == ["computation"] and not rows["jit_scaled"]["same_key"]
    assert rows["jit_doubled"] == {"program": "jit_doubled", "same_key": True, "differs": []}
    assert K.main([str(first), str(second)]) == 0
    with pytest.raises(FileNotFoundError, match="not a file"):
        K.main([str(first), str(tmp_path / "none.log")])


OTHER_HOST_PROGRAM = """
import sys
import jax, jax.numpy as jnp
from jax._src import cache_key
from sim_data.util import key_cache_by_device_kind, run_cli
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
class Topology:  # the same devices on a host whose topology's fingerprint differs
    def fingerprint(self):
        return int(sys.argv[2])
cache_key.xla_client.get_topology_for_devices = lambda devices: Topology()
def main():
    key_cache_by_device_kind(tuple(sys.argv[3].split(",")))  # "cpu" among them: this CPU stands for a GPU
    jax.jit(lambda x: x * 2.0)(jnp.ones(3)).block_until_ready()
run_cli(main)
"""


def test_a_cache_carried_to_a_host_with_the_same_devices_serves_although_its_topology_differs(tmp_path):
    """Keyed by device kind, a program compiled on one host is found on another whose topology fingerprints
    differently; a CPU (not among the platforms keyed by kind: its kind does not name its instruction set)
    keeps JAX's own accelerator part, and the same lookup misses."""
    log, cache = tmp_path / "cache_keys.log", tmp_path / "cache"
    env = {**os.environ, P.CACHE_KEY_LOG_ENV: str(log), "JAX_COMPILATION_CACHE_DIR": str(cache)}
    runs = [("gpu,cpu", "1"), ("gpu,cpu", "2"), ("gpu", "3"), ("gpu", "3"), ("gpu", "4")]
    for platforms, fingerprint in runs:
        subprocess.run([sys.executable, "-c", OTHER_HOST_PROGRAM, str(cache), fingerprint, platforms], env=env,
                       check=True)
    lines = log.read_text().splitlines()
    pids = list(dict.fromkeys(line.split("\t")[0] for line in lines))
    assert len(pids) == len(runs)
    hits = []
    for pid in pids:
        path = tmp_path / f"{pid}.log"
        path.write_text("\n".join(x for x in lines if x.startswith(pid + "\t")) + "\n")
        (entry,) = [v for k, v in K.read_cache_keys(path).items() if k.startswith("jit__lambda")]
        hits.append(entry["hit"])
    assert hits == [False, True, False, True, False]  # JAX's key: found on the same host, missed on another


def test_a_command_keys_the_cache_by_device_kind_where_the_cache_is_on(tmp_path, monkeypatch):
    own = jax_cache_key._hash_accelerator_config  # restored after the test by conftest's autouse fixture
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))  # run_cli sets XLA's flags: restored after
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    assert util.run_cli(lambda: 0) == 0 and jax_cache_key._hash_accelerator_config is own  # no cache: JAX's key
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path))
    assert util.run_cli(lambda: 0) == 0 and jax_cache_key._hash_accelerator_config.func is util._hash_device_kinds


def test_the_pipeline_shares_one_compilation_cache_with_its_child_processes(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(jax.config, "update", lambda *a: calls.append(a))
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    path = P.use_compilation_cache(str(tmp_path))
    assert path == str(tmp_path.absolute() / "jax_cache") and calls == [("jax_compilation_cache_dir", path)]
    keyed = jax_cache_key._hash_accelerator_config  # keyed by device kind on GPUs
    assert keyed.func is util._hash_device_kinds and keyed.keywords == {"platforms": ("gpu",)}
    assert os.environ["JAX_COMPILATION_CACHE_DIR"] == path  # inherited by the stages' processes
    # XLA's autotuning results beside it, one flag appended to those already set
    assert os.environ["XLA_FLAGS"] == f"--xla_cpu_multi_thread_eigen=false {P.AUTOTUNE_FLAG}={tmp_path.absolute()}/xla_autotune"
    assert P.use_compilation_cache(str(tmp_path)) == path
    assert os.environ["XLA_FLAGS"].count(P.AUTOTUNE_FLAG) == 1  # not appended twice
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", "/elsewhere")
    monkeypatch.setenv("XLA_FLAGS", "")
    assert P.use_compilation_cache(str(tmp_path / "other")) == "/elsewhere"
    assert os.environ["XLA_FLAGS"] == f"{P.AUTOTUNE_FLAG}={tmp_path.absolute()}/other/xla_autotune"
    # with a key log: this process records there, and the commands it starts learn where
    logged = []
    monkeypatch.setattr(P, "record_cache_keys", logged.append)
    monkeypatch.delenv(P.CACHE_KEY_LOG_ENV, raising=False)
    P.use_compilation_cache(str(tmp_path), key_log=tmp_path / "logs" / P.CACHE_KEY_LOG)
    assert logged == [tmp_path / "logs" / P.CACHE_KEY_LOG]
    assert os.environ[P.CACHE_KEY_LOG_ENV] == str((tmp_path / "logs" / P.CACHE_KEY_LOG).absolute())


def test_each_stage_command_appends_its_wall_and_compile_seconds_to_the_timing_table(tiny, monkeypatch):
    import jax.numpy as jnp

    import wm.train
    from experiments.report import compile_table, timing_table

    calls, d = tiny

    def scaled_tanh(x, scale):
        return jnp.tanh(x) * scale

    def compiling_train(argv):  # compiles one new program, then leaves what a finished training leaves
        jax.jit(scaled_tanh, static_argnums=1)(jnp.ones(3), len(calls)).block_until_ready()
        calls.append(argv)
        out = d["members"][len(calls) - 1]
        out.mkdir(parents=True, exist_ok=True)
        (out / "eval.json").write_text("{}")
        (out / "train_status.json").write_text(json.dumps({"step": 7, "steps": 7, "cut_short": False}))

    monkeypatch.setattr(wm.train, "main", compiling_train)
    P.run_stage("tiny", "train")
    P.run_stage("tiny", "train")
    rows = json.loads((d["eval"] / P.TIMING).read_text())
    assert [r["stage"] for r in rows] == ["train", "train"] and [r["done"] for r in rows] == [False, False]
    assert all(r["programs_compiled"] >= 1 and 0 < r["compile_s"] <= r["wall_s"] for r in rows)
    assert rows[1]["train_steps"] == [7, 7, None]
    for r in rows:  # each command compiled scaled_tanh once, for its own scale
        named = [c for c in r["slowest_compiles"] if c["program"] == "scaled_tanh"]
        assert len(named) == 1 and named[0]["compiles"] == 1 and 0 < named[0]["s"] <= r["compile_s"]
        assert [c["s"] for c in r["slowest_compiles"]] == sorted((c["s"] for c in r["slowest_compiles"]), reverse=True)
    assert ["train", "scaled_tanh", "1"] in [row[:3] for row in compile_table(rows)]
    table = timing_table(rows)
    assert table[2][table[0].index("training steps")] == "7, 7, -"  # one figure a world model
    assert {r["gpus"] for r in rows} == {0}  # the CPU alone
    assert table[-1][:3] == ["total", f"{rows[0]['wall_s'] + rows[1]['wall_s']:.1f}",
                             f"{rows[0]['compile_s'] + rows[1]['compile_s']:.1f}"]


def test_a_time_slot_passes_what_is_left_to_train_and_eval_and_starts_no_stage_after_it(monkeypatch, capsys):
    clock = [0.0]
    ran = []

    def fake_stage(name, stage, extra=(), gpus=(), members=None, warm=None, warm_eval=None, warm_rollouts=None,
                   cores=()):
        ran.append((stage, list(extra)))
        clock[0] += {"data": 120.0, "policies": 150.0, "train": 180.0}.get(stage, 10.0)
        return stage != "train" or len([r for r in ran if r[0] == "train"]) > 1  # train ends on its second run

    monkeypatch.setattr(P, "run_stage", fake_stage)
    monkeypatch.setattr(P.time, "perf_counter", lambda: clock[0])
    monkeypatch.setattr(P, "use_compilation_cache", lambda root, key_log=None: "")
    assert P.main(["full", "--minutes", "9"]) == 0
    assert [s for s, _ in ran] == ["data", "policies", "rollouts", "train", "train"]
    assert [e for s, e in ran if s in ("data", "policies", "rollouts")] == [[], [], []]
    assert ran[3][1] == ["max_minutes=4.333"] and ran[4][1] == ["max_minutes=1.333"]
    assert "rerun the same command to continue from the eval stage" in capsys.readouterr().err
    ran.clear()
    clock[0] = 0.0
    assert P.main(["full", "--minutes", "9", "--stage", "eval", "episodes=100"]) == 0
    assert ran == [("eval", ["episodes=100", "max_minutes=9.000"])]


def test_a_member_paused_at_its_pause_at_is_not_called_left_to_train(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(P.PIPELINES, "tiny", P.Pipeline(data="d", policies="p", train="smoke", eval="demo",
                                                        root=str(tmp_path), members=2))
    status = {"step": 30, "steps": 60, "cut_short": True}

    def stopping_train(argv):
        out = Path(argv[argv.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        (out / "train_status.json").write_text(json.dumps(status))

    import wm.train

    monkeypatch.setattr(wm.train, "main", stopping_train)
    d = P.PIPELINES["tiny"].dirs("tiny")
    assert P.train_members("tiny") == (False, [])
    assert f"2 of 2 world models left to train ({d['members'][0]}, {d['members'][1]})" in capsys.readouterr().err
    status["paused"] = True  # the first member now paused: a rerun of the stage would not train it
    assert P.train_members("tiny") == (False, [])
    assert f"1 of 2 world models left to train ({d['members'][1]}): run the train stage again" in (
        capsys.readouterr().err)


def test_a_chain_restores_a_carried_run_before_training_and_ends_where_its_training_pauses(tiny, monkeypatch,
                                                                                          capsys):
    _, d = tiny
    ran, restored = [], []

    def fake_stage(name, stage, extra=(), gpus=(), members=None, warm=None, warm_eval=None, warm_rollouts=None,
                   cores=()):
        ran.append(stage)
        if stage == "train":  # trains to its pause_at: stopped, not finished
            d["members"][0].mkdir(parents=True, exist_ok=True)
            (d["members"][0] / "train_status.json").write_text(json.dumps(
                {"step": 8000, "steps": 13000, "cut_short": True, "paused": True}))
            return False
        return True

    def fake_restore(src, run, wait_s=0.0):
        restored.append((src, run, wait_s, list(ran)))
        return {"step": 8000, "steps": 13000}

    monkeypatch.setattr(P, "run_stage", fake_stage)
    monkeypatch.setattr(P.carry, "restore_run", fake_restore)
    monkeypatch.setattr(P, "check_settings", lambda *args: None)  # the tiny preset names no real configurations
    monkeypatch.setattr(P, "use_compilation_cache", lambda root, key_log=None: "")
    assert P.main(["tiny", "--members", "1", "--run-from", ".carry-run0,.carry-run1"]) == 0
    # restored once, after the stages before training (its parts arrive meanwhile), into the one member's run
    assert restored == [([".carry-run0", ".carry-run1"], d["members"][0], P.RUN_WAIT_S, ["data", "policies",
                                                                                         "rollouts"])]
    assert ran == ["data", "policies", "rollouts", "train"]  # no evaluation of a paused model, no retraining
    assert f"python -m wm.carry pack {d['members'][0]} DEST" in capsys.readouterr().err
    for argv in (["tiny", "--run-from", "x"], ["tiny", "--members", "1", "--stage", "eval", "--run-from", "x"]):
        with pytest.raises(SystemExit):
            P.main(argv)
    assert "one member" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        P.main(["tiny", "--members", "1", "--run-from", ","])
    assert "names no folder" in capsys.readouterr().err
    # a chain whose pause_at the restored run has reached would not train a step
    with pytest.raises(ValueError, match="at or past pause_at=8000"):
        P.restore_member("tiny", "x", ["steps=13000", "pause_at=8000"])
    P.restore_member("tiny", "x", ["steps=13000", "pause_at=10000"])


def test_a_stage_spread_over_gpus_counts_its_child_processes_compiling_and_frames(tiny, monkeypatch):
    from experiments.report import compile_table, timing_table

    _, d = tiny
    logs = P._logs(P.pipeline("tiny"), "tiny")
    logs.mkdir(parents=True)
    (logs / "data-part-1.timing.json").write_text(json.dumps({"compile_s": 99.0}))  # an earlier run's: not counted
    children = {"0": (12.5, 3, "_scan_recorded"), "1": (20.0, 4, "render")}  # (compile seconds, programs, slowest)

    def fake_children(cmds, gpus, logs_, label, on):  # each child writes its timing as experiments.timing does
        assert label == "data-part" and not (logs / "data-part-1.timing.json").exists()
        for cmd, gpu in zip(cmds, gpus):
            assert cmd[1:3] == ["-m", "experiments.timing"] and cmd[4] == "sim_data.dataset.generate"
            s, n, prog = children[gpu]
            Path(cmd[3]).write_text(json.dumps({
                "module": cmd[4], "wall_s": 100.0, "compile_s": s, "programs_compiled": n, "cache_hits": n,
                "cache_misses": 1,
                "slowest_compiles": [{"program": prog, "compiles": 1, "s": s}], "device": "cpu", "status": 0}))

    def gather(argv):  # the gathering command generates nothing; the parts' figures are in stats.json
        time.sleep(0.05)
        d["data"].mkdir(parents=True, exist_ok=True)
        parts = [{"frames_generated": 300, "wall_s": 50.0, "simulate_s": 40.0},
                 {"frames_generated": 500, "wall_s": 80.0, "simulate_s": 70.0}]
        (d["data"] / "stats.json").write_text(json.dumps({"throughput": {
            "frames_generated": 0, "frames_per_s": None, "simulate_s": 0.0, "cache_frames": 800, "parts": parts}}))

    import sim_data.dataset.generate

    monkeypatch.setattr(P, "run_parallel", fake_children)
    monkeypatch.setattr(sim_data.dataset.generate, "main", gather)
    P.run_stage("tiny", "data", gpus=["0", "1"])
    row = json.loads((d["eval"] / P.TIMING).read_text())[0]
    assert [p["compile_s"] for p in row["parts"]] == [12.5, 20.0] and [p["part"] for p in row["parts"]] == [0, 1]
    assert 20.0 <= row["compile_s"] < 20.0 + row["wall_s"]  # this process's own plus the slowest child's
    assert row["programs_compiled"] >= 7 and row["gpus"] == 2
    assert row["cache_hits"] >= 7 and row["cache_misses"] >= 2  # the children's (3 + 4, 1 + 1) and this process's
    assert [(c["program"], c["part"]) for c in row["slowest_compiles"][:2]] == [("render", 1), ("_scan_recorded", 0)]
    assert row["frames_generated"] == 800 and row["frames_per_s"] == 10.0 and row["simulate_s"] == 70.0
    assert row["end_to_end_frames_per_s"] == round(800 / row["wall_s"], 1)
    assert ["data", "render (part 1)", "1", "20.0"] in compile_table([row])
    assert timing_table([row])[1][5:7] == ["10.0", f"{800 / row['wall_s']:.1f}"]


@pytest.mark.slow
def test_a_child_process_writes_its_wall_and_compile_seconds_whether_it_succeeds_or_fails(tmp_path):
    import subprocess
    import sys

    (tmp_path / "jitting.py").write_text(
        "import jax, jax.numpy as jnp\n"
        "def doubled_sine(x):\n    return jnp.sin(x) * 2\n"
        "def main(argv):\n"
        "    if argv == ['bad']:\n        raise ValueError('bad argument: name a good one')\n"
        "    jax.jit(doubled_sine)(jnp.ones(int(argv[0]))).block_until_ready()\n"
        "    return 0\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(Path(__file__).resolve().parents[1]),
                                                     os.environ.get("PYTHONPATH", "")])}
    ok, bad = tmp_path / "ok.json", tmp_path / "bad.json"
    run = [sys.executable, "-m", "experiments.timing"]
    assert subprocess.run([*run, str(ok), "jitting", "5"], env=env, check=False).returncode == 0
    got = json.loads(ok.read_text())
    assert got["module"] == "jitting" and got["status"] == 0 and got["programs_compiled"] >= 1
    assert 0 < got["compile_s"] <= got["wall_s"]
    assert [c["compiles"] for c in got["slowest_compiles"] if c["program"] == "doubled_sine"] == [1]
    # with a persistent compilation cache, a second process finds the program the first compiled
    cached = {**env, "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "cache"), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
              "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0"}
    first, second = tmp_path / "first.json", tmp_path / "second.json"
    for out in (first, second):
        assert subprocess.run([*run, str(out), "jitting", "7"], env=cached, check=False).returncode == 0
    first, second = json.loads(first.read_text()), json.loads(second.read_text())
    assert first["cache_hits"] == 0 and first["cache_misses"] >= 1
    assert second["cache_hits"] == first["cache_misses"] and second["cache_misses"] == 0
    done = subprocess.run([*run, str(bad), "jitting", "bad"], env=env, check=False, capture_output=True, text=True)
    assert done.returncode == 2 and "bad argument" in done.stderr
    assert json.loads(bad.read_text())["status"] == 2


def test_set_gives_each_stage_its_own_overrides_and_refuses_what_names_no_stage(monkeypatch):
    assert P.stage_overrides(["train:steps=3500", "eval:episodes=50", "train:seed=1"]) == {
        "train": ["steps=3500", "seed=1"], "eval": ["episodes=50"]}
    for bad in ("steps=3500", "fit:steps=1", "train:steps", "train:=1"):
        with pytest.raises(ValueError, match="STAGE:key=value"):
            P.stage_overrides([bad])
    ran = []
    monkeypatch.setattr(P, "run_stage", lambda name, stage, extra=(), gpus=(), members=None, warm=None,
                        warm_eval=None, warm_rollouts=None, cores=():
                        ran.append((stage, extra)) or True)
    monkeypatch.setattr(P, "use_compilation_cache", lambda root, key_log=None: "")
    assert P.main(["full", "--set", "train:steps=3500", "--set", "eval:episodes=50", "--set", "train:seed=1"]) == 0
    assert dict(ran) == {"data": [], "policies": [], "rollouts": [], "train": ["steps=3500", "seed=1"],
                         "eval": ["episodes=50"], "report": []}
    with pytest.raises(SystemExit):
        P.main(["full", "--set", "fit:steps=1"])


def _fake_python(tmp_path, body: str) -> str:
    """An executable standing in for the interpreter a detached chain runs: it records its arguments."""
    exe = tmp_path / "fake_python"
    exe.write_text(f'#!/bin/sh\necho "args: $*"\n{body}\n')
    exe.chmod(0o755)
    return str(exe)


@pytest.mark.parametrize("body, status, says", [
    ('echo "report: /x/report.html (1 s)"; exit 0', 0, "ended well, report: /x/report.html (1 s)"),
    ('echo "error: data missing" >&2; exit 2', 1, "ended with exit status 2"),
])
def test_a_detached_chain_runs_in_the_background_and_follow_reports_how_it_ended(tmp_path, monkeypatch, body,
                                                                                    status, says):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(P.sys, "executable", _fake_python(tmp_path, body))
    monkeypatch.setattr(P, "FOLLOW_POLL_S", 0.05)
    log = P.detach("full", ["full", "--set", "train:steps=3500"])
    assert log == Path("runs/logs/full/pipeline.log")
    out = io.StringIO()
    assert P.follow("full", 60, out=out) == status
    text = out.getvalue()
    assert says in text
    # the background job ran the same command, the train and eval stages unbounded unless set otherwise
    assert ("args: -m experiments.pipeline --set train:max_minutes=0 --set eval:max_minutes=0 full "
            "--set train:steps=3500") in text
    assert P.detach("full", ["full"])  # an ended chain does not block the next


def test_follow_says_a_detached_chain_still_runs_and_a_second_detach_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(P.sys, "executable", _fake_python(tmp_path, "sleep 60"))
    monkeypatch.setattr(P, "FOLLOW_POLL_S", 0.05)
    with pytest.raises(ValueError, match="no detached full chain"):
        P.follow("full", 1)
    P.detach("full", ["full", "--members", "2"], members=2)
    pid = int(Path("runs/logs/full/pipeline.pid").read_text())
    try:
        out = io.StringIO()
        followed = []
        monkeypatch.setattr(P, "pipeline", lambda name, members=None: followed.append(members) or P.PIPELINES[name])
        assert P.follow("full", 0.2, out=out) == P.STILL_RUNNING
        assert followed[0] == 2  # the chain's ensemble, though this follow names none
        monkeypatch.undo()
        monkeypatch.chdir(tmp_path)
        monkeypatch.setattr(P, "FOLLOW_POLL_S", 0.05)
        assert "still running" in out.getvalue()
        with pytest.raises(ValueError, match=f"still runs \\(pid {pid}\\)"):
            P.detach("full", ["full"])
        restored = []
        monkeypatch.setattr(P, "restore_compile_cache", lambda *a: restored.append(a) or 0)
        with pytest.raises(SystemExit):  # refused before its caches are restored under the running chain
            P.main(["full", "--detach", "--cache-from", str(tmp_path / "carry")])
        assert not restored
    finally:
        os.killpg(pid, signal.SIGKILL)
    deadline = time.monotonic() + 10
    while P._detached_pid(Path("runs/logs/full")) is not None and time.monotonic() < deadline:
        time.sleep(0.05)
    out = io.StringIO()
    assert P.follow("full", 5, out=out) == 1 and "exit status None" in out.getvalue()  # killed: no exit status


def test_follow_until_bundle_returns_once_for_each_new_bundle_while_the_chain_runs_on(tmp_path, monkeypatch, capsys):
    """A chain that trains, lists its bundles, then evaluates: the follow that sees the list returns
    BUNDLED at once, the next one waits on, a new list (a model trained again) returns again; a list
    left by an earlier chain is cleared when the next one starts."""
    monkeypatch.chdir(tmp_path)
    logs = Path("runs/logs/full")
    logs.mkdir(parents=True)
    (logs / P.BUNDLES).write_text(json.dumps({"runs/bundles/old": "0"}))  # an earlier chain's
    listing = json.dumps({"runs/bundles/full": "1", "runs/bundles/full_seed1": "2"})
    body = f"sleep 0.5; echo '{listing}' > {logs / P.BUNDLES}; sleep 60"
    monkeypatch.setattr(P.sys, "executable", _fake_python(tmp_path, body))
    monkeypatch.setattr(P, "FOLLOW_POLL_S", 0.05)
    P.detach("full", ["full"])
    pid = int((logs / "pipeline.pid").read_text())
    try:
        out = io.StringIO()
        t0 = time.monotonic()
        assert P.follow("full", 30, out=out, until_bundle=True) == P.BUNDLED and time.monotonic() - t0 < 20
        assert ("copy runs/bundles/full runs/bundles/full_seed1 off the machine now (a later lease evaluates them "
                "with --stage eval --set eval:wm=runs/bundles/full,runs/bundles/full_seed1)") in out.getvalue()
        assert P.follow("full", 0.3, out=io.StringIO(), until_bundle=True) == P.STILL_RUNNING  # seen already
        (logs / P.BUNDLES).write_text(json.dumps({"runs/bundles/full": "3", "runs/bundles/full_seed1": "2"}))
        assert P.follow("full", 30, out=io.StringIO(), until_bundle=True) == P.BUNDLED
        assert P.follow("full", 0.3, out=io.StringIO()) == P.STILL_RUNNING
    finally:
        os.killpg(pid, signal.SIGKILL)
    with pytest.raises(SystemExit):
        P.main(["full", "--until-bundle"])
    assert "--until-bundle is an option of --follow" in capsys.readouterr().err


def test_follow_collects_a_finished_chains_outcome_in_the_command_that_sees_it_end(tmp_path, monkeypatch, capsys):
    """The follow that sees the chain end copies its evaluation's files and a tarball of its logs and the
    world model's figures (no checkpoints) into the folder given; a follow of a running chain collects
    what is written so far."""
    monkeypatch.chdir(tmp_path)
    body = ("sleep 0.5; mkdir -p runs/eval/full runs/wm/full/checkpoints/7; "
            "echo '{\"policies\": []}' > runs/eval/full/results.json; echo '# report' > runs/eval/full/report.md; "
            "echo '[]' > runs/eval/full/timing.json; echo '{\"psnr\": 1}' > runs/wm/full/eval.json; "
            "echo '{}' > runs/wm/full/metrics.jsonl; echo x > runs/wm/full/checkpoints/7/params; "
            "echo 'report: runs/eval/full/report.html (1 s)'; exit 0")
    monkeypatch.setattr(P.sys, "executable", _fake_python(tmp_path, body))
    monkeypatch.setattr(P, "FOLLOW_POLL_S", 0.05)
    P.detach("full", ["full"])
    out = tmp_path / "out"
    assert P.follow("full", 0.1, out=io.StringIO(), collect_to=out) == P.STILL_RUNNING
    assert [f.name for f in out.iterdir()] == ["runs.tgz"]  # the log so far, no results yet
    with tarfile.open(out / "runs.tgz") as tar:
        names = tar.getnames()
        assert "logs/full/pipeline.log" in names and not any(n.startswith("wm/") for n in names)
    text = io.StringIO()
    assert P.follow("full", 30, out=text, collect_to=out) == 0
    assert sorted(f.name for f in out.iterdir()) == ["report.md", "results.json", "runs.tgz", "timing.json"]
    assert json.loads((out / "results.json").read_text()) == {"policies": []}
    with tarfile.open(out / "runs.tgz") as tar:
        names = set(tar.getnames())
        assert {"logs/full/pipeline.log", "wm/full/eval.json", "wm/full/metrics.jsonl"} <= names
        assert not any("checkpoints" in n for n in names)
        assert b"report: runs/eval/full/report.html" in tar.extractfile("logs/full/pipeline.log").read()
    assert f"collected results.json, report.md, timing.json, runs.tgz into {out}" in text.getvalue()
    with pytest.raises(SystemExit):
        P.main(["full", "--collect", str(out)])
    assert "--collect is an option of --follow" in capsys.readouterr().err


def test_a_follow_collects_as_it_waits_so_a_command_cut_at_its_limit_leaves_what_was_finished(tmp_path,
                                                                                                 monkeypatch):
    """A lease's limit can kill the follow's command before it returns: the files it collects while it
    waits already hold the world model's figures written meanwhile; a file replaced while it is read is
    a message, the next collect takes it."""
    monkeypatch.chdir(tmp_path)
    body = ("sleep 0.5; mkdir -p runs/wm/full; echo '{\"auroc\": 0.9}' > runs/wm/full/eval.json.tmp; "
            "mv runs/wm/full/eval.json.tmp runs/wm/full/eval.json; sleep 60")
    monkeypatch.setattr(P.sys, "executable", _fake_python(tmp_path, body))
    monkeypatch.setattr(P, "FOLLOW_POLL_S", 0.05)
    monkeypatch.setattr(P, "COLLECT_EVERY_S", 0.1)
    P.detach("full", ["full"])
    pid = int(Path("runs/logs/full/pipeline.pid").read_text())
    out = tmp_path / "out"

    def collected():
        try:
            with tarfile.open(out / "runs.tgz") as tar:
                return json.loads(tar.extractfile("wm/full/eval.json").read())
        except (OSError, KeyError, tarfile.TarError):
            return None

    follower = threading.Thread(target=P.follow, args=("full", 30), kwargs=dict(out=io.StringIO(), collect_to=out))
    try:
        follower.start()
        deadline = time.monotonic() + 20
        while collected() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert follower.is_alive() and collected() == {"auroc": 0.9}  # the follow still waits
    finally:
        os.killpg(pid, signal.SIGKILL)
        follower.join()
    text = io.StringIO()
    with monkeypatch.context() as m:
        def replaced(*a, **k):
            raise OSError(2, "No such file or directory")
        m.setattr(P, "collect", replaced)
        assert P.collect_running(P.PIPELINES["full"], "full", out, text) == []
    assert "not collected this time: [Errno 2]" in text.getvalue()


def test_the_compilation_caches_pack_into_parts_that_restore_to_the_same_files(tmp_path, monkeypatch, capsys):
    """A lease's caches packed into parts of bounded size come back byte for byte on the next machine;
    a missing part, a foreign member, no parts, or a cache too large for the files a lease returns
    are each refused or skipped with a message."""
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)  # another test's chain may have set it
    rng = np.random.default_rng(0)
    root = tmp_path / "runs"
    files = {"jax_cache/jit_train_step-abc": rng.bytes(70_000), "jax_cache/jit_init-def": rng.bytes(30_000),
             "xla_autotune/fusion.textproto": b"autotune results\n" * 100}
    for name, data in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    (root / "data").mkdir()
    (root / "data" / "big.mcap").write_bytes(b"not a cache")
    out = tmp_path / "out"
    parts = P.pack_compile_cache(root, out, part_bytes=40_000)
    assert [p.name for p in parts] == [f"{P.CACHE_PART}{k:02d}" for k in range(len(parts))] and len(parts) == 3
    assert all(p.stat().st_size <= 40_000 for p in parts) and sorted(out.iterdir()) == parts
    fresh = tmp_path / "fresh" / "runs"
    assert P.restore_compile_cache(out, fresh) == 3
    assert {str(f.relative_to(fresh)): f.read_bytes() for f in fresh.rglob("*") if f.is_file()} == files
    # the parts split between two folders, as two lease calls carry them: joined in their numbers' order
    second = tmp_path / "second"
    second.mkdir()
    shutil.copy(out / f"{P.CACHE_PART}00", second)
    split = [tmp_path / "first", second]
    shutil.copytree(out, split[0], ignore=shutil.ignore_patterns(f"{P.CACHE_PART}00"))
    assert P.restore_compile_cache(split, tmp_path / "split" / "runs") == 3
    got = tmp_path / "split" / "runs"
    assert {str(f.relative_to(got)): f.read_bytes() for f in got.rglob("*") if f.is_file()} == files
    with pytest.raises(ValueError, match=r"parts are \[0, 0, 1, 2\].*given twice"):
        P.restore_compile_cache([out, second], tmp_path / "other")
    # one part lost on the way: refused, naming what is missing
    (out / f"{P.CACHE_PART}01").rename(tmp_path / "aside")
    with pytest.raises(ValueError, match="one is missing"):
        P.restore_compile_cache(out, tmp_path / "other")
    (tmp_path / "aside").write_bytes((tmp_path / "aside").read_bytes()[:-100])
    (tmp_path / "aside").rename(out / f"{P.CACHE_PART}01")
    with pytest.raises(ValueError, match="do not make one archive"):
        P.restore_compile_cache(out, tmp_path / "other")
    with pytest.raises(FileNotFoundError, match="--collect-cache"):
        P.restore_compile_cache(tmp_path / "empty", tmp_path / "other")
    # an archive holding anything but the caches is not extracted
    evil = tmp_path / "evil"
    evil.mkdir()
    with tarfile.open(evil / f"{P.CACHE_PART}00", "w:gz") as tar:
        tar.add(root / "data" / "big.mcap", arcname="data/big.mcap")
    with pytest.raises(ValueError, match="outside jax_cache, xla_autotune"):
        P.restore_compile_cache(evil, tmp_path / "other")
    assert not (tmp_path / "other" / "data").exists()
    # more than the lease's files allow: nothing packed, nothing left behind
    assert P.pack_compile_cache(root, tmp_path / "small", part_bytes=10_000, max_parts=3) == []
    assert list((tmp_path / "small").iterdir()) == [] and "not packed" in capsys.readouterr().err
    assert P.pack_compile_cache(tmp_path / "nothing", tmp_path / "none") == []


def test_the_caches_pack_from_and_restore_to_where_the_chain_keeps_them(tmp_path, monkeypatch, capsys):
    """JAX_COMPILATION_CACHE_DIR, where set, is the cache packed and restored; a packing replaces the parts
    of an earlier one; a packing that fails leaves nothing behind and says why."""
    root = tmp_path / "runs"
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "elsewhere"))
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "jit_step").write_bytes(b"compiled")
    (root / "jax_cache").mkdir(parents=True)
    (root / "jax_cache" / "stale").write_bytes(b"not this one")
    out = tmp_path / "out"
    out.mkdir()
    for k in range(3):  # an earlier packing's parts
        (out / f"{P.CACHE_PART}{k:02d}").write_bytes(b"old")
    assert [p.name for p in P.pack_compile_cache(root, out)] == [f"{P.CACHE_PART}00"]
    assert sorted(f.name for f in out.iterdir()) == [f"{P.CACHE_PART}00"]
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "next" / "cache"))
    assert P.restore_compile_cache(out, tmp_path / "next" / "runs") == 1
    assert (tmp_path / "next" / "cache" / "jit_step").read_bytes() == b"compiled"
    assert not (tmp_path / "next" / "runs" / "jax_cache").exists()

    def full_disk(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(P.tarfile, "open", full_disk)
    assert P.pack_compile_cache(root, out) == [] and list(out.iterdir()) == []
    assert "not packed: [Errno 28] No space left on device" in capsys.readouterr().err


def test_every_follow_of_a_running_chain_brings_back_the_caches_compiled_so_far(tmp_path, monkeypatch):
    """A machine may be taken back mid-chain: each follow with --collect-cache packs the caches' settled
    entries (not one written a moment ago, nor XLA's temporary files), the one that sees the end every
    entry; a follow that returns for the bundles leaves its files to them; a packing that fails is a
    message, not the follow's exit status."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    logs = Path("runs/logs/full")
    listing = json.dumps({"runs/bundles/full": "1"})
    body = f"sleep 4; echo '{listing}' > {logs / P.BUNDLES}; sleep 2; exit 0"  # the first two follows come well before
    monkeypatch.setattr(P.sys, "executable", _fake_python(tmp_path, body))
    monkeypatch.setattr(P, "FOLLOW_POLL_S", 0.05)
    old = time.time() - 3600
    for f in ("jax_cache/jit_data_step", "jax_cache/jit_zoo_step", "xla_autotune/tmp/tmp_per_fusion_cache_1"):
        Path("runs", f).parent.mkdir(parents=True, exist_ok=True)
        Path("runs", f).write_bytes(f.encode())
        os.utime(Path("runs", f), (old, old))
    Path("runs/jax_cache/jit_being_written").write_bytes(b"half")  # now: may still be written
    P.detach("full", ["full"])

    def packed(out):
        parts = sorted(out.glob(f"{P.CACHE_PART}*"))
        with tarfile.open(fileobj=io.BytesIO(b"".join(f.read_bytes() for f in parts)), mode="r:gz") as tar:
            return sorted(tar.getnames())

    text = io.StringIO()
    assert P.follow("full", 0.1, out=text, collect_to=tmp_path / "a", collect_cache=True) == P.STILL_RUNNING
    assert packed(tmp_path / "a") == ["jax_cache/jit_data_step", "jax_cache/jit_zoo_step"]
    assert "packed in 1 part" in text.getvalue()

    def failing(*a, **k):
        raise OSError(2, "No such file or directory")

    with monkeypatch.context() as m:
        m.setattr(P, "pack_compile_cache", failing)
        text = io.StringIO()
        assert P.follow("full", 0.1, out=text, collect_to=tmp_path / "b", collect_cache=True) == P.STILL_RUNNING
        assert "the compilation caches were not packed: [Errno 2]" in text.getvalue()
    assert P.follow("full", 30, out=io.StringIO(), until_bundle=True, collect_to=tmp_path / "c",
                    collect_cache=True) == P.BUNDLED
    assert not list((tmp_path / "c").glob(f"{P.CACHE_PART}*"))
    assert P.follow("full", 30, out=io.StringIO(), collect_to=tmp_path / "d", collect_cache=True) == 0
    assert packed(tmp_path / "d") == ["jax_cache/jit_being_written", "jax_cache/jit_data_step",
                                      "jax_cache/jit_zoo_step"]


def test_a_lease_collects_its_caches_and_the_next_starts_from_them(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    body = ("sleep 0.2; mkdir -p runs/eval/full runs/jax_cache; echo '{}' > runs/eval/full/results.json; "
            "echo compiled > runs/jax_cache/jit_step; exit 0")
    monkeypatch.setattr(P.sys, "executable", _fake_python(tmp_path, body))
    monkeypatch.setattr(P, "FOLLOW_POLL_S", 0.05)
    P.detach("full", ["full"])
    out = tmp_path / "out"
    text = io.StringIO()
    assert P.follow("full", 30, out=text, collect_to=out, collect_cache=True) == 0
    assert f"{P.CACHE_PART}00" in text.getvalue() and (out / f"{P.CACHE_PART}00").exists()
    assert "the compilation caches packed in 1 part, 0.0 MiB" in text.getvalue()
    shutil.rmtree("runs")
    seen = tmp_path / "argv"
    monkeypatch.setattr(P.sys, "executable", _fake_python(tmp_path, f'echo "$@" > {seen}'))
    (tmp_path / "carried_later").mkdir()  # a second call's folder, here without a part
    assert P.main(["full", "--detach", "--cache-from", f"{out},{tmp_path / 'carried_later'}"]) == 0
    assert Path("runs/jax_cache/jit_step").read_text() == "compiled\n"
    assert "restored 1 files of the compilation caches" in capsys.readouterr().out
    for _ in range(100):  # the detached command runs without the option: the caches are in place already
        if seen.exists() and seen.read_text().strip():
            break
        time.sleep(0.05)
    assert "--cache-from" not in seen.read_text() and str(out) not in seen.read_text()
    for argv, message in ((["full", "--follow", "1", "--collect-cache"], "--collect-cache is an option of --collect"),
                          (["full", "--follow", "1", "--cache-from", str(out)], "give it to the command that starts"),
                          (["full", "--cache-from", str(tmp_path / "none")], "holds no compile_cache.tgz.partNN")):
        with pytest.raises(SystemExit):
            P.main(argv)
        assert message in capsys.readouterr().err


def test_a_detached_chain_runs_the_pipeline_itself(tmp_path, monkeypatch):
    """The real command in the background: an eval stage with no trained model stops with its message."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(P, "FOLLOW_POLL_S", 0.2)
    P.detach("demo", ["demo", "--stage", "eval"])
    out = io.StringIO()
    assert P.follow("demo", 300, out=out) == 1
    assert "not trained yet: run the train stage" in out.getvalue()


def test_the_rollouts_stage_compiles_the_training_programs_beside_it_with_the_train_stage_overrides(tmp_path,
                                                                                                     monkeypatch):
    monkeypatch.setitem(P.PIPELINES, "roll", P.Pipeline(data="d", policies="p", train="t", eval="e", root=str(tmp_path),
                                                        rollouts="conv", rollout_episodes=2,
                                                        train_overrides=("w_success=0.5",)))
    order, started = [], []

    class FakeChild:
        def __init__(self, argv, env, **_):
            started.append((argv, env))
            order.append("warm starts")

        def wait(self, timeout=None):
            order.append("warm waited")
            return 0

    monkeypatch.setattr(P.subprocess, "Popen", FakeChild)
    monkeypatch.setattr(P.generate, "main", lambda args: order.append("rollouts"))
    monkeypatch.setattr(P, "device_name", lambda: "cpu")
    assert P.run_stage("roll", "rollouts", warm_train=["steps=3500"])
    assert order == ["warm starts", "rollouts", "warm waited"]
    argv, env = started[0]
    assert argv[1:] == ["-m", "wm.train", "--config", "t", "--data", str(tmp_path / "data" / "d"), "--warm",
                        "--probe-policies", f"{tmp_path / 'policies' / 'roll'}#conv", "w_success=0.5", "steps=3500"]
    assert env["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false" and env["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.35"
    started.clear()
    P.run_stage("roll", "rollouts")  # not asked for
    monkeypatch.setattr(P, "run_parts", lambda *a: [])
    P.run_stage("roll", "rollouts", warm_train=[], gpus=["0", "1"])  # several GPUs: members train apart
    assert not started
    (tmp_path / "wm" / "roll").mkdir(parents=True)
    (tmp_path / "wm" / "roll" / "eval.json").write_text("{}")
    P.run_stage("roll", "rollouts", warm_train=[])  # trained already: nothing to warm
    assert not started
    ran = []
    monkeypatch.setattr(P, "run_stage", lambda name, stage, extra=(), gpus=(), members=None, warm=None,
                        warm_eval=None, warm_rollouts=None, cores=():
                        ran.append((stage, warm)) or True)
    monkeypatch.setattr(P, "use_compilation_cache", lambda root, key_log=None: "")
    monkeypatch.setattr(P, "check_settings", lambda *a: None)  # the stand-in presets build no configuration
    P.main(["roll", "--warm-train", "--set", "train:steps=3500", "--set", "eval:episodes=50"])
    assert dict(ran)["rollouts"] == ["steps=3500"]


def test_options_are_checked_before_detaching_and_none_may_be_abbreviated(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(P, "local_gpus", lambda: [])
    for argv in (["demo", "--detach", "--gpus", "7"], ["demo", "--detach", "--minutes", "-1"], ["demo", "--det"],
                 ["demo", "--detach", "--cores", "0"], ["demo", "--detach", "--cores", "4096"],
                 ["demo", "--detach", "--minutes", "9", "--warm-eval"]):
        with pytest.raises(SystemExit):
            P.main(argv)
    monkeypatch.setattr(P, "local_gpus", lambda: ["0"])  # a GPU host evaluates on its GPU, whatever --gpus says
    with pytest.raises(SystemExit):
        P.main(["demo", "--detach", "--gpus", "0", "--cores", "1"])
    assert not Path("runs/logs/demo/pipeline.pid").exists()  # nothing was started


def test_data_overrides_reach_the_rollouts_stage_that_reuses_the_data(monkeypatch):
    ran = []
    monkeypatch.setattr(P, "run_stage", lambda name, stage, extra=(), gpus=(), members=None, warm=None,
                        warm_eval=None, warm_rollouts=None, cores=():
                        ran.append((stage, extra)) or True)
    monkeypatch.setattr(P, "use_compilation_cache", lambda root, key_log=None: "")
    P.main(["full", "--set", "data:batch=960", "--set", "rollouts:policy_episodes=8"])
    got = dict(ran)
    assert got["data"] == ["batch=960"] and got["rollouts"] == ["batch=960", "policy_episodes=8"]
    assert got["train"] == [] and got["eval"] == []


def test_a_failed_rollouts_stage_stops_its_warm_up_and_the_warm_up_takes_the_first_untrained_members_seed(
        tmp_path, monkeypatch):
    monkeypatch.setitem(P.PIPELINES, "roll2", P.Pipeline(data="d", policies="p", train="smoke", eval="e",
                                                         root=str(tmp_path), rollouts="conv", members=2))
    events = []

    class FakeChild:
        def __init__(self, argv, **_):
            events.append(("start", argv))

        def kill(self):
            events.append(("kill", None))

        def wait(self, timeout=None):
            return -9 if ("kill", None) in events else 0

    monkeypatch.setattr(P.subprocess, "Popen", FakeChild)
    (tmp_path / "wm" / "roll2").mkdir(parents=True)
    (tmp_path / "wm" / "roll2" / "eval.json").write_text("{}")  # member 0 trained: member 1 is next

    def failing(args):
        raise RuntimeError("simulation failed")

    monkeypatch.setattr(P.generate, "main", failing)
    with pytest.raises(RuntimeError, match="simulation failed"):
        P.run_stage("roll2", "rollouts", warm_train=[])
    assert events[0][1][-1] == "seed=1" and ("kill", None) in events


def test_the_train_stage_compiles_the_evaluations_programs_beside_it_with_the_eval_stage_overrides(tmp_path,
                                                                                                   monkeypatch):
    monkeypatch.setitem(P.PIPELINES, "ev", P.Pipeline(data="d", policies="p", train="t", eval="e", root=str(tmp_path),
                                                      rollouts="conv", eval_overrides=("readout=judge",)))
    events = []

    class FakeChild:
        def __init__(self, argv, env, **_):
            events.append(("start", argv, env))

        def kill(self):
            events.append(("kill",))

        def wait(self, timeout=None):
            events.append(("wait",))
            return -9 if ("kill",) in events else 0

    monkeypatch.setattr(P.subprocess, "Popen", FakeChild)
    monkeypatch.setattr(P, "train_members", lambda *a: events.append(("train",)) or (True, []))
    bundled = []
    monkeypatch.setattr(P, "bundle_members", lambda d, logs: bundled.append((d["bundles"], len(events))))
    monkeypatch.setattr(P, "device_name", lambda: "cpu")
    assert P.run_stage("ev", "train", warm_eval=["episodes=50"])
    assert [e[0] for e in events] == ["start", "train", "wait"]
    assert bundled == [([tmp_path / "bundles" / "ev"], 2)]  # after the training, before waiting for the warm-up
    _, argv, env = events[0]
    assert argv[1:] == ["-m", "experiments.evaluate", "--config", "e", "--warm", "--warm-after-training",
                        f"policies={tmp_path / 'policies' / 'ev'}", f"wm={tmp_path / 'wm' / 'ev'}", "readout=judge",
                        "episodes=50"]
    assert env["XLA_PYTHON_CLIENT_MEM_FRACTION"] == P.WARM_MEMORY_FRACTION
    events.clear()
    P.run_stage("ev", "train")  # not asked for
    P.run_stage("ev", "train", warm_eval=[], gpus=["0", "1"])  # several GPUs: the eval's parts compile their own
    assert [e[0] for e in events] == ["train", "train"]
    events.clear()

    def failing(*a):
        raise RuntimeError("training failed")

    monkeypatch.setattr(P, "train_members", failing)
    with pytest.raises(RuntimeError, match="training failed"):
        P.run_stage("ev", "train", warm_eval=[])
    assert [e[0] for e in events] == ["start", "kill", "wait"] and len(bundled) == 3  # none of a failed training
    events.clear()
    (tmp_path / "wm" / "ev").mkdir(parents=True)
    (tmp_path / "wm" / "ev" / "eval.json").write_text("{}")
    monkeypatch.setattr(P, "train_members", lambda *a: (True, []))
    P.run_stage("ev", "train", warm_eval=[])  # trained already: nothing to warm
    assert not events
    # one GPU, two members: the second's training finds the programs the first's warm-up compiled
    monkeypatch.setitem(P.PIPELINES, "ev", dataclasses.replace(P.PIPELINES["ev"], members=2))
    P.run_stage("ev", "train", warm_eval=[])
    assert not events
    ran = []
    monkeypatch.setattr(P, "run_stage", lambda name, stage, extra=(), gpus=(), members=None, warm=None,
                        warm_eval=None, warm_rollouts=None, cores=(): ran.append((stage, warm_eval)) or True)
    monkeypatch.setattr(P, "use_compilation_cache", lambda root, key_log=None: "")
    monkeypatch.setattr(P, "check_settings", lambda *a: None)  # the stand-in presets build no configuration
    P.main(["ev", "--warm-eval", "--set", "train:steps=3500", "--set", "eval:episodes=50"])
    assert dict(ran)["train"] == ["episodes=50"]


def test_a_warmed_stage_lowers_its_programs_from_cleared_caches(tmp_path, monkeypatch):
    """The stages run in one process; a stage whose programs a warm-up compiled clears JAX's caches
    before its work, so that they lower as in the warm-up's bare process (the same text, the same
    persistent-cache key): the rollouts stage after the data stage. Without a warm-up nothing is
    cleared (the stages keep the programs they share in memory)."""
    monkeypatch.setitem(P.PIPELINES, "rc", P.Pipeline(data="d", policies="p", train="t", eval="e", root=str(tmp_path),
                                                      rollouts="conv"))
    events = []
    monkeypatch.setattr(P.jax, "clear_caches", lambda: events.append("clear"))
    monkeypatch.setattr(P.generate, "main", lambda args: events.append("generate"))
    monkeypatch.setattr(P, "device_name", lambda: "cpu")
    assert P.run_stage("rc", "rollouts", warm_rollouts=[])
    assert events == ["clear", "generate"]
    events.clear()
    assert P.run_stage("rc", "rollouts", warm_train=None, warm_eval=[])
    assert events == ["generate"]


def test_the_policies_stage_compiles_the_rollouts_programs_beside_it_with_the_rollouts_stage_arguments(
        tmp_path, monkeypatch):
    monkeypatch.setitem(P.PIPELINES, "wr", P.Pipeline(data="d", policies="p", train="t", eval="e", root=str(tmp_path),
                                                      rollouts="conv+vit", rollout_episodes=8,
                                                      data_overrides=("engine=mjx",)))
    events = []

    class FakeChild:
        def __init__(self, argv, env, **_):
            events.append(("start", argv))

        def kill(self):
            events.append(("kill",))

        def wait(self, timeout=None):
            events.append(("wait",))
            return 0

    monkeypatch.setattr(P.subprocess, "Popen", FakeChild)
    monkeypatch.setattr(P.zoo, "main", lambda args: events.append(("zoo",)))
    monkeypatch.setattr(P, "device_name", lambda: "cpu")
    assert P.run_stage("wr", "policies", warm_rollouts=["batch=960"])
    assert [e[0] for e in events] == ["start", "zoo", "wait"]
    d = P.pipeline("wr").dirs("wr")
    assert events[0][1][1:] == ["-m", "sim_data.dataset.generate", "--warm", *P.rollouts_args(P.pipeline("wr"), "wr",
                                                                                                ["batch=960"])]
    assert P.rollouts_args(P.pipeline("wr"), "wr", ["batch=960"]) == [
        "--config", "d", "--out", str(d["wm_data"]), "--reuse", str(d["data"]), "engine=mjx",
        f"policies={d['policies']}#conv+vit", "policy_episodes=8", "batch=960"]
    events.clear()
    assert not P.warm_alone([], ["0", "1"], "--warm-rollouts")  # several GPUs: each part compiles its own
    d["wm_data"].mkdir(parents=True)
    (d["wm_data"] / "stats.json").write_text("{}")
    P.run_stage("wr", "policies", warm_rollouts=[])  # the rollouts are generated: nothing to warm
    assert [e[0] for e in events] == ["zoo"]
    ran = []
    monkeypatch.setattr(P, "run_stage", lambda name, stage, extra=(), gpus=(), members=None, warm=None,
                        warm_eval=None, warm_rollouts=None, cores=(): ran.append((stage, warm_rollouts)) or True)
    monkeypatch.setattr(P, "use_compilation_cache", lambda root, key_log=None: "")
    monkeypatch.setattr(P, "check_settings", lambda *a: None)  # the stand-in presets build no configuration
    P.main(["wr", "--warm-rollouts", "--set", "data:batch=960", "--set", "rollouts:policy_episodes=4"])
    assert dict(ran)["policies"] == ["batch=960", "policy_episodes=4"]
    with pytest.raises(SystemExit):
        P.main(["wr", "--warm-rollouts", "--minutes", "9"])
