"""A training run packed to travel between GPU leases and resume where it stopped.

A lent machine keeps nothing for the next lease, and a lease holds about 30 minutes of which the
data, the zoo and the rollouts take 7 to 8: a world model trained for longer goes in parts. The
first lease trains to a step (`pause_at`, wm.config.TrainConfig) and packs the run; the next one
regenerates the data, restores the run and trains on to `steps` (or to a later pause):

    python -m wm.train --config full ... steps=13000 pause_at=8000        # saves and stops at 8000
    python -m wm.carry pack runs/wm/full_grip runs/carry/full_grip         # carry.json + run.tgz.partNN
    # copy the parts off the machine and carry them in, four a call (a call moves 64 MiB each way), then:
    python -m wm.carry restore DIR[,DIR...] runs/wm/full_grip              # the same wm.train resumes

The pack holds what resuming needs, bit for bit: the latest checkpoint (parameters, optimiser
state, the loader's position, the best validation loss), the kept parameters (best/; left out where
they are the latest step's own, which the resumed run keeps again from its state), config.json,
norm.json, metrics.jsonl and train_status.json, as one tar.gz cut into files of <= 15 MiB, and
carry.json, which names the parts, their SHA-256 and the fingerprint of the data the run trained
on: a resumed run refuses data that differs (check_data), since its steps would then not be those
of an uninterrupted run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import tarfile
import time
from pathlib import Path

import jax

from sim_data.util import device_name, folder_list, read_json, run_cli, unpacked_tar, write_json_atomic, write_parts
from wm.checkpoint import file_sha256, training_status

CARRY = "carry.json"  # the pack's description, beside its parts, and kept in the restored run
PART = "run.tgz.part"
PART_BYTES = 15 * 2**20  # a lent GPU brings back files of <= 16 MiB
CALL_BYTES = 60 * 2**20  # a lease call moves 64 MiB each way, the repository's tree beside a carried folder
PACKED = ("config.json", "norm.json", "metrics.jsonl", "train_status.json", "checkpoints", "best")
FINGERPRINTED = ("proprio.npy", "action.npy", "success.npy")  # per cache shard, beside its index.json


def data_fingerprint(data: Path) -> str:
    """SHA-256 of a dataset's training cache as a run reads it: index.json (its episodes, splits,
    outcomes and lengths) and every shard's proprioception, actions and success flags, which any
    difference in the simulation moves (the frames, gigabytes, are left out)."""
    cache = Path(data) / "cache"
    if not (cache / "index.json").exists():
        raise FileNotFoundError(f"{data} holds no training cache (cache/index.json): generate the data first")
    h = hashlib.sha256((cache / "index.json").read_bytes())
    for shard in json.loads((cache / "index.json").read_text())["shards"]:
        for name in FINGERPRINTED:
            f = cache / shard["name"] / name
            if f.exists():
                h.update(f"{shard['name']}/{name}".encode())
                h.update(f.read_bytes())
    return h.hexdigest()


def pack_run(run: Path, dest: Path, part_bytes: int = PART_BYTES) -> dict:
    """Packs the stopped training run `run` (one with train_status.json: paused, cut short or
    finished) into dest: PACKED as one tar.gz cut into dest/PARTNN of <= part_bytes, and dest/CARRY
    ({"step", "steps", "parts", "sizes" (each part's bytes), "bytes", "sha256", "data", "data_sha256",
    "device" and "devices", the kind and count of the devices it was packed on, "best_from_latest": the
    step whose kept parameters were left out as the latest checkpoint's own, or None}), written last. Returns
    carry.json's contents. Raises FileNotFoundError where run has no status or checkpoint (it never
    finished a command: rerun its training first)."""
    run, dest = Path(run), Path(dest)
    status = training_status(run)
    if status["step"] is None or not (run / "checkpoints").is_dir():
        raise FileNotFoundError(f"{run} holds no stopped training run (train_status.json and checkpoints/): train it "
                                "with a pause_at, or until it stops, before packing it")
    # kept parameters of the latest step itself are left out (a quarter of the pack): the resumed run keeps
    # them again from the restored state (wm.train's Run.restore, best_from_latest)
    latest, best = _steps(run / "checkpoints"), _steps(run / "best")
    from_latest = best[0] if len(best) == 1 and best == latest[-1:] else None
    data = Path(read_json(run / "config.json")["data"])
    fingerprint = data_fingerprint(data)  # before any part is written: data that is gone stops it here
    dest.mkdir(parents=True, exist_ok=True)
    (dest / CARRY).unlink(missing_ok=True)
    whole = dest / (PART + ".tmp")
    try:
        # float32 weights and optimiser moments barely compress: the fastest level keeps the pack quick
        with tarfile.open(whole, "w:gz", compresslevel=1) as tar:
            for name in PACKED:
                if (run / name).exists() and not (name == "best" and from_latest is not None):
                    tar.add(run / name, arcname=name)
        parts = write_parts(whole, dest, PART, part_bytes)
        meta = {"step": status["step"], "steps": status["steps"], "parts": len(parts),
                "sizes": [f.stat().st_size for f in parts], "bytes": whole.stat().st_size,
                "sha256": file_sha256(whole), "data": str(data), "data_sha256": fingerprint,
                "device": device_name(), "devices": jax.device_count(), "best_from_latest": from_latest}
    finally:
        whole.unlink(missing_ok=True)
    write_json_atomic(dest / CARRY, meta)
    return meta


def restore_run(src, run: Path, wait_s: float = 0.0) -> dict:
    """Restores the run that pack_run packed, its parts and carry.json in src (a folder, or several:
    a lease carries them in several calls, each its own folder), into `run`, carry.json kept there for
    check_data; waits up to wait_s seconds for the parts carry.json names to arrive (a chain that
    restores before its train stage while later calls carry them in). Returns carry.json's contents.
    Raises FileNotFoundError where no folder holds carry.json or a part is still missing, ValueError
    where the parts do not make the packed archive or `run` holds another training run (restore into
    an empty path); a run restored from the same pack already is left as it is."""
    folders = folder_list(src)
    where = ", ".join(map(str, folders))
    if wait_s and not _arrived(folders):
        print(f"waiting up to {wait_s:.0f} s for the packed run's {CARRY} and parts in {where}", file=sys.stderr,
              flush=True)
        deadline = time.monotonic() + wait_s
        while not _arrived(folders) and time.monotonic() < deadline:
            time.sleep(2.0)
    meta = _read_carry(folders)
    if meta is None:
        raise FileNotFoundError(f"{where} holds no readable {CARRY}: pack the run with python -m wm.carry pack RUN "
                                "DEST and carry its folder in whole")
    files = _part_files(folders, meta)
    if missing := [n for n, f in files.items() if f is None]:
        raise FileNotFoundError(f"{where} lacks {', '.join(missing)} of the packed run's {meta['parts']} parts, or "
                                "holds them cut short: carry them in too")
    run = Path(run)
    if (run / CARRY).exists() and read_json(run / CARRY).get("sha256") == meta["sha256"]:
        return meta  # restored already (a rerun of the same command)
    if (run / "train_status.json").exists() or (run / "checkpoints").exists():
        raise ValueError(f"{run} holds another training run: restore into an empty path, or remove it")
    joined = b"".join(f.read_bytes() for f in files.values())
    if hashlib.sha256(joined).hexdigest() != meta["sha256"]:
        raise ValueError(f"{where}: the parts do not make the packed run (SHA-256 differs from {CARRY}'s): is a part "
                         "damaged or from another packing?")
    with unpacked_tar(joined, PACKED, run.parent, where, "the packed run does not unpack") as (unpacked, _):
        run.mkdir(parents=True, exist_ok=True)
        for name in PACKED:
            if (unpacked / name).exists():
                shutil.move(str(unpacked / name), str(run / name))
    write_json_atomic(run / CARRY, meta)
    return meta


CARRY_KEYS = ("step", "steps", "parts", "sizes", "sha256", "data_sha256")


def _steps(checkpoints: Path) -> list[int]:
    """The steps an orbax checkpoint directory holds (its numbered folders), in order."""
    return sorted(int(d.name) for d in checkpoints.iterdir() if d.is_dir() and d.name.isdigit()) \
        if checkpoints.is_dir() else []


def best_from_latest(run: Path) -> int | None:
    """The step of a run restored from a pack whose kept parameters (best/) the pack left out as the latest
    checkpoint's own, to be kept again from the restored state; None for any other run."""
    carried = Path(run) / CARRY
    return read_json(carried).get("best_from_latest") if carried.exists() else None


def _read_carry(folders) -> dict | None:
    """carry.json from the first of folders holding a whole one; None while none does (not carried in
    yet, still being written, or not pack_run's)."""
    for d in folders:
        try:
            meta = read_json(d / CARRY)
        except (FileNotFoundError, ValueError):
            continue
        if all(k in meta for k in CARRY_KEYS) and len(meta["sizes"]) == meta["parts"]:
            return meta
    return None


def _part_files(folders, meta: dict) -> dict:
    """{each part's name (PARTNN, write_parts'): its file in folders at its packed size, or None (absent, or
    still being copied in)}."""
    return {f"{PART}{k:02d}": next((d / f"{PART}{k:02d}" for d in folders if (d / f"{PART}{k:02d}").is_file()
                                    and (d / f"{PART}{k:02d}").stat().st_size == size), None)
            for k, size in enumerate(meta["sizes"])}


def _arrived(folders) -> bool:
    """Whether folders hold a whole carry.json and every part it names at its packed size."""
    meta = _read_carry(folders)
    return meta is not None and all(f is not None for f in _part_files(folders, meta).values())


def check_data(run: Path, data: Path) -> None:
    """Where `run` was restored from a pack (it holds carry.json), refuses to resume it on data whose
    fingerprint differs from the packed run's (ValueError): another machine kind's simulation, or
    other settings, would make its remaining steps differ from an uninterrupted run's."""
    carried = Path(run) / CARRY
    if not carried.exists():
        return
    meta = read_json(carried)
    if (meta.get("device"), meta.get("devices")) != (device_name(), jax.device_count()):
        print(f"warning: {run} was packed on {meta.get('devices')} x {meta.get('device')} and resumes on "
              f"{jax.device_count()} x {device_name()}: its remaining steps may differ from an uninterrupted run's "
              "in the last bits", file=sys.stderr)
    if data_fingerprint(data) != meta["data_sha256"]:
        raise ValueError(f"{data} is not the data {run} trained on before it was packed (their fingerprints differ: "
                         "generate it with the same commit, settings and machine kind), so its remaining steps would "
                         "not be an uninterrupted run's; train a fresh run on this data instead")


def call_groups(dest: Path, meta: dict, call_bytes: int = CALL_BYTES) -> list[list[Path]]:
    """The files of the pack in dest (pack_run's, meta its carry.json) in groups of at most call_bytes,
    carry.json in the first: what one lease call copies off the machine, or carries in as one folder."""
    groups, size = [[Path(dest) / CARRY]], (Path(dest) / CARRY).stat().st_size
    for k, part_size in enumerate(meta["sizes"]):
        if size + part_size > call_bytes:
            groups.append([])
            size = 0
        groups[-1].append(Path(dest) / f"{PART}{k:02d}")
        size += part_size
    return groups


def adopt_data_path(run: Path, data: Path) -> None:
    """Where `run` was restored from a pack and check_data passed, records data's path in its
    config.json: the same data, by its fingerprint, where the repository lies elsewhere on this machine."""
    run = Path(run)
    if not (run / CARRY).exists() or not (run / "config.json").exists():
        return
    config = read_json(run / "config.json")
    if config.get("data") != str(Path(data).absolute()):
        write_json_atomic(run / "config.json", {**config, "data": str(Path(data).absolute())})


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    pk = sub.add_parser("pack", help="pack a stopped training run into DEST (carry.json and parts of <= 15 MiB)")
    pk.add_argument("run", type=Path)
    pk.add_argument("dest", type=Path)
    rs = sub.add_parser("restore", help="restore a packed run from its folders into RUN (an empty path)")
    rs.add_argument("src", help="the folder(s) holding carry.json and the parts, comma-separated")
    rs.add_argument("run", type=Path)
    rs.add_argument("--wait", type=float, default=0.0, metavar="SECONDS",
                    help="wait up to SECONDS for carry.json and the parts to arrive")
    a = p.parse_args(argv)
    if a.command == "pack":
        meta = pack_run(a.run, a.dest)
        print(f"{a.run}: step {meta['step']} of {meta['steps']} packed into {a.dest} ({CARRY} and {meta['parts']} "
              f"parts, {meta['bytes'] / 2**20:.1f} MiB); off a lent machine, a call each (into a folder of its own "
              f"to carry in the next lease, the first with {CARRY}):")
        for k, group in enumerate(call_groups(a.dest, meta)):
            print(f"  {k + 1}: cp {' '.join(map(str, group))} $OUT")
    else:
        meta = restore_run(a.src, a.run, a.wait)
        print(f"{a.run}: restored at step {meta['step']} of {meta['steps']}; its training command resumes it")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
