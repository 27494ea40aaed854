"""Data-parallel training over several devices and processes, on CPU devices: the loader's parts
tile each global batch, fsdp plans a quarter of each parameter for each of 4 devices, and two
processes (fsdp) train with the same per-step losses and parameters as one process on one device."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from sim_data.dataset.cache import TrainingCache, WindowLoader
from wm.checkpoint import load_trained, training_status
from wm.config import make_config
from wm.model import init_params
from wm.train import state_shardings

ROOT = Path(__file__).resolve().parents[1]


def _train(data: Path, out: Path, *options: str) -> list[str]:
    """The command of the suite's smoke world model (conftest), with parameters sharded (fsdp)."""
    return [sys.executable, "-m", "wm.train", "--config", "smoke", "--data", str(data), "--out", str(out), *options,
            "param_sharding=fsdp"]


def _env() -> dict:
    return {**os.environ, "JAX_PLATFORMS": "cpu"}  # one CPU device a process


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _losses(out: Path) -> list[float]:
    return [json.loads(line)["loss"] for line in (out / "metrics.jsonl").read_text().splitlines()]


def _check(procs) -> None:
    for p in procs:
        _, err = p.communicate(timeout=900)
        assert p.returncode == 0, err[-3000:]


def test_loader_parts_tile_each_global_batch_and_resume(smoke_dataset):
    _, data, _ = smoke_dataset
    cache = TrainingCache(data)
    whole = WindowLoader(cache, 4, 6, split=None, seed=5)
    parts = [WindowLoader(cache, 4, 6, split=None, seed=5, part=(i, 3)) for i in range(3)]
    for _ in range(whole.batches_per_epoch + 2):  # into the second epoch
        want = next(whole)
        got = [next(p) for p in parts]
        assert all(len(g["episode"]) == 2 for g in got)
        for key in ("episode", "start", "proprio"):
            np.testing.assert_array_equal(np.concatenate([g[key] for g in got]), want[key])
    # a part resumes where a part's state says, whichever part wrote it
    again = WindowLoader(cache, 4, 6, split=None, seed=5, part=(1, 3))
    again.restore(parts[0].state())
    np.testing.assert_array_equal(next(again)["start"], next(parts[1])["start"])
    for loader in [whole, again, *parts]:
        loader.close()
    with pytest.raises(ValueError, match="part"):
        WindowLoader(cache, 4, 6, split=None, part=(0, 4))  # 4 does not divide 6
    with pytest.raises(ValueError, match="part"):
        WindowLoader(cache, 4, 6, split=None, part=(3, 3))


def test_fsdp_shards_each_parameter_over_its_largest_divisible_axis():
    params = jax.eval_shape(lambda: init_params(make_config("smoke", []).model, jax.random.PRNGKey(0), window=6))
    mesh = jax.sharding.AbstractMesh((4,), ("data",))  # the plan for 4 devices, without them
    leaves = jax.tree_util.tree_leaves(params)
    whole = jax.tree_util.tree_leaves(state_shardings(params, mesh, False))
    assert all(s.shard_shape(x.shape) == x.shape for x, s in zip(leaves, whole))  # replicated: whole on each
    sharded = 0
    for x, s in zip(leaves, jax.tree_util.tree_leaves(state_shardings(params, mesh, True)), strict=True):
        full, shard = x.shape, s.shard_shape(x.shape)
        divisible = [a for a in range(len(full)) if full[a] % 4 == 0]
        if not divisible:
            assert shard == full
            continue
        axis = max(divisible, key=lambda a: full[a])  # the largest such axis holds a quarter on each device
        assert shard[axis] * 4 == full[axis]
        assert [d for i, d in enumerate(shard) if i != axis] == [d for i, d in enumerate(full) if i != axis]
        sharded += 1
    assert sharded >= len(leaves) // 2


@pytest.fixture(scope="module")
def two_processes(smoke_dataset, tmp_path_factory):
    """The smoke world model trained by two processes of one CPU device each, parameters fsdp-sharded
    over both (launched side by side, joined through jax.distributed, gradients reduced by gloo)."""
    _, data, _ = smoke_dataset
    out = tmp_path_factory.mktemp("parallel") / "two"
    port = _free_port()
    procs = [subprocess.Popen(_train(data, out, "--distributed", "--coordinator", f"localhost:{port}",
                                     "--num-processes", "2", "--process-id", str(i)),
                              cwd=ROOT, env=_env(), text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for i in range(2)]
    _check(procs)
    return out


# slow: two more processes, each importing jax, joining jax.distributed and compiling the fsdp train step
# for itself (about 250 s of the 2-core machine); the fsdp plan and the loader's parts are checked above
@pytest.mark.slow
def test_two_processes_train_as_one_process_with_the_whole_batch(two_processes, smoke_world_model):
    """The same per-step losses and parameters as the suite's one-device smoke model (same command,
    one process): each process loads its own rows of the same global batches."""
    mine, theirs = _losses(two_processes), _losses(smoke_world_model)
    assert len(mine) == len(theirs) == 30 // 5  # one line per log step: the second process writes none
    assert len(set(np.round(theirs, 4))) == len(theirs)  # the loss moves: a real comparison
    np.testing.assert_allclose(mine, theirs, rtol=1e-4)  # only the order of the gradient sums differs
    assert all(0.0 <= json.loads(line)["input_wait"] < 1.0
               for line in (two_processes / "metrics.jsonl").read_text().splitlines())
    assert training_status(two_processes) == {"step": 30, "steps": 30, "cut_short": False}
    # the fsdp checkpoint of two processes restores on one device
    (_, pa, _), (_, pb, _) = load_trained(two_processes), load_trained(smoke_world_model)
    # within one step of the learning rate (3e-3): Adam turns a gradient at float-rounding level (a
    # bias that barely matters) into a full-size step of either sign
    for x, y in zip(jax.tree_util.tree_leaves(pa), jax.tree_util.tree_leaves(pb), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-3, atol=3e-3)
    assert not (two_processes / "eval.json").exists()  # judged and evaluated by a one-process rerun


def test_distributed_options_need_the_flag(smoke_dataset, tmp_path):
    _, data, _ = smoke_dataset
    r = subprocess.run([sys.executable, "-m", "wm.train", "--data", str(data), "--out", str(tmp_path / "x"),
                        "--config", "smoke", "--process-id", "1"], cwd=ROOT, env=_env(), capture_output=True,
                       text=True)
    assert r.returncode == 2 and "--distributed" in r.stderr
