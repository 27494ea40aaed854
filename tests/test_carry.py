"""A training run paused, packed, restored on another path and resumed (wm.carry): the same model as
the uninterrupted run, and the packs and data it refuses."""

import io
import json
import shutil
import tarfile
import threading

import jax
import numpy as np
import pytest

from sim_data.util import device_name
from wm import carry as C
from wm.checkpoint import load_trained
from wm.config import make_config
from wm.train import main as train_main

TIMING = ("steps_per_s", "frames_per_s", "input_wait")  # what a logged step measures of the machine


def _logged(run):
    return [{k: v for k, v in json.loads(line).items() if k not in TIMING}
            for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_a_paused_run_packed_and_restored_elsewhere_resumes_to_the_uninterrupted_model(smoke_dataset,
                                                                                      smoke_world_model, tmp_path):
    _, data, _ = smoke_dataset
    args = ["--config", "smoke", "--data", str(data)]
    first = tmp_path / "lease1" / "run"
    assert train_main([*args, "--out", str(first), "pause_at=10"]) == 0
    assert json.loads((first / "train_status.json").read_text()) == {"step": 10, "steps": 30, "cut_short": True,
                                                                      "paused": True}
    assert not (first / "eval.json").exists()
    assert train_main([*args, "--out", str(first), "pause_at=10"]) == 0  # rerun as it is, it stays paused
    assert [m["step"] for m in _logged(first)] == [5, 10]
    # packed in parts of 256 KiB, carried in by two calls: the parts split between two folders
    meta = C.pack_run(first, tmp_path / "pack", part_bytes=256 * 2**10)
    parts = sorted((tmp_path / "pack").glob(C.PART + "*"))
    assert meta["step"] == 10 and meta["parts"] == len(parts) > 2 and meta["data_sha256"] == C.data_fingerprint(data)
    # the kept parameters are step 10's own: left out of the pack, kept again by the resumed run
    assert C._steps(first / "best") == C._steps(first / "checkpoints") == [10] and meta["best_from_latest"] == 10
    assert all(p.stat().st_size <= 256 * 2**10 for p in parts)
    one, two = tmp_path / "call1", tmp_path / "call2"
    one.mkdir()
    two.mkdir()
    for k, p in enumerate(parts):
        shutil.copy(p, (one if k % 2 else two) / p.name)
    with pytest.raises(FileNotFoundError, match="holds no readable carry.json"):
        C.restore_run([one, two], tmp_path / "lease2" / "run")
    (two / C.CARRY).write_text((tmp_path / "pack" / C.CARRY).read_text()[:40])  # still being copied in
    with pytest.raises(FileNotFoundError, match="holds no readable carry.json"):
        C.restore_run([one, two], tmp_path / "lease2" / "run")
    shutil.copy(tmp_path / "pack" / C.CARRY, two / C.CARRY)
    whole = (one / parts[1].name).read_bytes()
    (one / parts[1].name).write_bytes(whole[:1000])  # a part half copied in is not taken yet
    with pytest.raises(FileNotFoundError, match=f"lacks {parts[1].name}"):
        C.restore_run([one, two], tmp_path / "lease2" / "run")
    # a restore that waits takes the part once its copy is whole
    finish = threading.Timer(1.0, lambda: (one / parts[1].name).write_bytes(whole))
    finish.start()
    second = tmp_path / "lease2" / "run"
    assert C.restore_run([one, two], second, wait_s=30) == meta
    finish.join()
    assert C.restore_run([one, two], second) == meta  # restored already: left as it is
    assert not (second / "best").exists()
    with pytest.raises(ValueError, match="holds another training run"):
        C.restore_run([one, two], first)
    # the next lease resumes it to its steps, its data regenerated at another path (the repository lies
    # elsewhere): every logged loss and the kept parameters are the uninterrupted run's, bit for bit
    moved = tmp_path / "lease2" / "data"
    shutil.copytree(data, moved)
    assert train_main(["--config", "smoke", "--data", str(moved), "--out", str(second)]) == 0
    assert json.loads((second / "config.json").read_text())["data"] == str(moved.absolute())
    assert json.loads((second / "train_status.json").read_text())["cut_short"] is False
    assert _logged(second) == _logged(smoke_world_model)
    for a, b in zip(jax.tree_util.tree_leaves(load_trained(second)[1]),
                    jax.tree_util.tree_leaves(load_trained(smoke_world_model)[1]), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # a pack restored beside data that differs is refused before any step
    other = tmp_path / "lease3" / "run"
    C.restore_run([one, two], other)
    carried = json.loads((other / C.CARRY).read_text())
    (other / C.CARRY).write_text(json.dumps({**carried, "data_sha256": "0" * 64}))
    with pytest.raises(ValueError, match="not the data"):
        train_main([*args, "--out", str(other)])
    assert [m["step"] for m in _logged(other)] == [5, 10]


def test_kept_parameters_of_an_earlier_step_travel_in_the_pack(smoke_world_model, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(smoke_world_model, run)
    (run / "best" / "5").mkdir()  # as a run whose validation kept another step than its latest
    meta = C.pack_run(run, tmp_path / "pack")
    joined = b"".join(f.read_bytes() for f in sorted((tmp_path / "pack").glob(C.PART + "*")))
    with tarfile.open(fileobj=io.BytesIO(joined), mode="r:gz") as tar:
        names = tar.getnames()
    assert meta["best_from_latest"] is None and "best/5" in names and "checkpoints" in names


def test_damaged_or_foreign_packs_are_refused(smoke_world_model, tmp_path):
    with pytest.raises(FileNotFoundError, match="no stopped training run"):
        C.pack_run(tmp_path / "nothing", tmp_path / "pack")
    meta = C.pack_run(smoke_world_model, tmp_path / "pack", part_bytes=512 * 2**10)
    assert meta["sizes"] == [f.stat().st_size for f in sorted((tmp_path / "pack").glob(C.PART + "*"))]
    assert (meta["device"], meta["devices"]) == (device_name(), jax.device_count())
    # what each lease call copies off: carry.json with the first parts, then as many as a call moves
    small = C.pack_run(smoke_world_model, tmp_path / "small", part_bytes=64 * 2**10)
    groups = C.call_groups(tmp_path / "small", small, call_bytes=2 * 64 * 2**10 + 4096)
    assert small["parts"] > 4 and groups[0][0].name == C.CARRY
    assert [len(g) for g in groups[:-1]] == [3] + [2] * (len(groups) - 2) and len(groups[-1]) in (1, 2)
    assert [f.name for g in groups for f in g][1:] == [f"{C.PART}{k:02d}" for k in range(small["parts"])]
    part = tmp_path / "pack" / f"{C.PART}00"
    damaged = bytearray(part.read_bytes())
    damaged[-1] ^= 0xFF  # whole in size, one byte changed
    part.write_bytes(bytes(damaged))
    with pytest.raises(ValueError, match="SHA-256 differs"):
        C.restore_run(tmp_path / "pack", tmp_path / "run")
    assert not (tmp_path / "run").exists()
    carried = json.loads((tmp_path / "pack" / C.CARRY).read_text())
    (tmp_path / "pack" / C.CARRY).write_text(json.dumps({k: v for k, v in carried.items() if k != "sizes"}))
    with pytest.raises(FileNotFoundError, match="holds no readable carry.json"):  # not pack_run's
        C.restore_run(tmp_path / "pack", tmp_path / "run")


@pytest.mark.parametrize("pause_at", [-1, 30, 31])
def test_a_pause_at_or_past_the_budget_is_refused(pause_at):
    with pytest.raises(ValueError, match="pause_at is a step before steps=30"):
        make_config("smoke", [f"pause_at={pause_at}"])
