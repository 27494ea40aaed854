"""A finished training run read back (its configuration, best parameters, normalisation, status),
from its run directory or from its portable bundle.

A bundle (`python -m wm.checkpoint RUN BUNDLE`) is a directory small enough to copy between machines:
`bundle.json` (the run's configuration, normalisation, training status, eval.json, the judge's
standardisation, the training data's initial-state seeds and learned policies, and a SHA-256 of every
other file), the best parameters in bfloat16 split into `params-K.msgpack` shards of at most 15 MiB,
and `judge.msgpack` (with a second judge, `judge2.msgpack` too). It is written under a temporary name
and renamed when whole. Every reader here (and `wm.judge.load_judge`) takes either kind of directory,
so `make eval ARGS="wm=BUNDLE"` evaluates a model trained on another machine.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from flax import serialization, traverse_util

from sim_data.dataset.cache import TrainingCache
from sim_data.policies.registry import used_fingerprints, used_policies, used_seeds
from sim_data.util import read_json, run_cli, write_json_atomic
from wm.config import TrainConfig, from_dict
from wm.imagine import Norm
from wm.model import init_params

BUNDLE = "bundle.json"
SHARD_BYTES = 15 * 2**20
BUNDLE_BYTES = 64 * 2**20  # what a GPU machine returns in all (its files of <= 16 MiB each)
BUNDLE_FORMAT = 1
# the episode judges' file stems (wm.judge.save_judge: <stem>.json and <stem>.msgpack) and read-outs' names
JUDGE, SECOND_JUDGE = "judge", "judge2"
RUN_FILES = ("config.json", "norm.json", "train_status.json", "eval.json",  # copied into a bundle
             *(f"{name}.json" for name in (JUDGE, SECOND_JUDGE)))
JUDGE_BLOBS = tuple(f"{name}.msgpack" for name in (JUDGE, SECOND_JUDGE))  # the judges' parameters, where fit


def is_bundle(out: Path) -> bool:
    """Whether out is a bundle directory (it holds bundle.json) rather than a training run's."""
    return (Path(out) / BUNDLE).exists()


def bundle_meta(out: Path) -> dict:
    """The bundle.json of a bundle directory."""
    return read_json(Path(out) / BUNDLE)


def run_file(out: Path, name: str) -> dict | None:
    """A run's small JSON file (config.json, norm.json, train_status.json, eval.json, judge.json) from a
    run directory, or its copy inside a bundle; None where there is none."""
    out = Path(out)
    if is_bundle(out):
        return bundle_meta(out)["files"].get(name)
    path = out / name
    return read_json(path) if path.exists() else None


def load_run_config(out: Path) -> tuple[TrainConfig, Path]:
    """(TrainConfig, the training data's directory) of a run or bundle."""
    d = run_file(out, "config.json")
    if d is None:
        raise FileNotFoundError(f"{out} holds no world model (config.json or {BUNDLE}): run make train first")
    return from_dict(d["train"]), Path(d["data"])


def training_status(out: Path) -> dict:
    """{"step", "steps", "cut_short"} of a training run (train_status.json); cut_short is None for a
    run that never finished a command."""
    return run_file(out, "train_status.json") or {"step": None, "steps": None, "cut_short": None}


def training_seeds(out: Path) -> set:
    """The initial-state seeds of a run's training data (its manifest, or the copy in its bundle), which
    an evaluation holds out."""
    if is_bundle(out):
        return set(bundle_meta(out).get("data_seeds", ()))
    return used_seeds(load_run_config(out)[1])


def training_policies(out: Path) -> set:
    """The learned policies whose rollouts were in a run's training data (its manifest, or the copy in
    its bundle): an evaluation reports the policies the world model never saw act apart."""
    if is_bundle(out):
        return set(bundle_meta(out).get("data_policies", ()))
    return used_policies(load_run_config(out)[1])


def training_fingerprints(out: Path) -> set:
    """The fingerprints of the same policies (sim_data.policies.registry.fingerprint), where the
    training data's manifests record them."""
    if is_bundle(out):
        return set(bundle_meta(out).get("data_fingerprints", ()))
    return used_fingerprints(load_run_config(out)[1])


def trained_tasks(out: Path) -> tuple:
    """The tasks a run's world model learned to judge: its episode judge's, else those its training
    named (train_tasks), else those of its training data's cache; () where none of these is at hand."""
    judge = run_file(out, "judge.json")
    if judge is not None:
        return tuple(judge["tasks"])
    cfg, data = load_run_config(out)
    if cfg.train_tasks:
        return tuple(cfg.train_tasks)
    if not (Path(data) / "cache" / "index.json").exists():
        return ()
    return tuple(TrainingCache(data).tasks)


def load_trained(out: Path):
    """(TrainConfig, best parameters (float32), Norm) of a finished training run in out, or of its bundle."""
    out = Path(out)
    if is_bundle(out):
        return _load_bundle(out)
    if not (out / "config.json").exists() or not (out / "best").exists():
        raise FileNotFoundError(f"{out} holds no trained world model (config.json and best/, or {BUNDLE}): "
                                "run make train first")
    cfg, _ = load_run_config(out)
    norm = Norm.from_dict(read_json(out / "norm.json"))
    mgr = ocp.CheckpointManager(out.absolute() / "best", options=ocp.CheckpointManagerOptions(create=False))
    step = mgr.latest_step()
    if step is None:
        raise FileNotFoundError(f"{out}/best holds no checkpoint")
    shapes = _shapes(cfg)
    return cfg, restore_params(mgr, step, shapes, _first_device(shapes)), norm


def load_started(out: Path):
    """(TrainConfig, parameters of zeros, Norm) of a training run that has started (its config.json and
    norm.json written, its training perhaps under way): the parameters are of the trained ones' shapes,
    types and placement (load_trained), so that programs compiled with them are those an evaluation of
    the finished run compiles (experiments.evaluate's warm-up)."""
    out = Path(out)
    if not (out / "config.json").exists() or not (out / "norm.json").exists():
        raise FileNotFoundError(f"{out} holds no started training run (config.json and norm.json)")
    cfg, _ = load_run_config(out)
    norm = Norm.from_dict(read_json(out / "norm.json"))
    shapes = _shapes(cfg)
    # zeros made on the host: an eager jnp.zeros would compile a program for every parameter's shape
    return cfg, jax.device_put(jax.tree_util.tree_map(lambda x: np.zeros(x.shape, x.dtype), shapes),
                               _first_device(shapes)), norm


def _first_device(shapes):
    """Shardings placing every parameter on this process's first device, whatever the topology the run
    was trained on (several processes, fsdp): without a target sharding orbax would ask for the saved one."""
    one = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.tree_util.tree_map(lambda _: one, shapes)


def restore_params(manager: ocp.CheckpointManager, step: int, shapes, shardings):
    """The parameters of a `best/` checkpoint at step: shapes (arrays or ShapeDtypeStructs) and
    shardings, pytrees like the parameters, say what to build and where to place it, whatever
    topology saved it (several processes, fsdp); without a target sharding orbax asks for the saved one."""
    abstract = jax.tree_util.tree_map(lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s), shapes, shardings)
    got = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore({"params": abstract}),
                                                         loader=ocp.args.JsonRestore()))
    return got["state"]["params"]


def _shapes(cfg: TrainConfig):
    return jax.eval_shape(lambda: init_params(cfg.model, jax.random.PRNGKey(0), window=cfg.window))


# ---- bundles ---------------------------------------------------------------------------------------------

def write_bundle(run: Path, out: Path, dtype: str = "bfloat16") -> dict:
    """Writes the bundle of the finished training run `run` into `out` (replacing one there); returns
    its bundle.json. The parameters are cast to `dtype` ("bfloat16" or "float32")."""
    run, out = Path(run), Path(out)
    if is_bundle(run):
        raise ValueError(f"{run} is a bundle already")
    if out.exists() and not is_bundle(out):
        raise ValueError(f"{out} exists and is not a bundle: choose another directory")
    if dtype not in ("bfloat16", "float32"):
        raise ValueError(f"dtype must be bfloat16 or float32, got {dtype!r}")
    _, params, _ = load_trained(run)
    tmp = out.with_name(out.name + f".tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    flat = traverse_util.flatten_dict(jax.device_get(params), sep="/")
    shards, current, size = [], {}, 0
    for key in sorted(flat):
        a = np.asarray(jnp.asarray(flat[key], dtype))
        if current and size + a.nbytes > SHARD_BYTES:
            shards.append(current)
            current, size = {}, 0
        current[key], size = a, size + a.nbytes
    shards.append(current)
    hashes = {}
    for k, shard in enumerate(shards):
        name = f"params-{k}.msgpack"
        (tmp / name).write_bytes(serialization.msgpack_serialize({key: _to_bytes(a) for key, a in shard.items()}))
        hashes[name] = file_sha256(tmp / name)
    for blob in JUDGE_BLOBS:
        if (run / blob).exists():
            shutil.copyfile(run / blob, tmp / blob)
            hashes[blob] = file_sha256(tmp / blob)
    meta = {"format": BUNDLE_FORMAT, "source": str(run.absolute()), "dtype": dtype,
            "parameters": int(sum(a.size for a in flat.values())), "sha256": hashes, "files": _run_files(run),
            "data_seeds": sorted(training_seeds(run)), "data_policies": sorted(training_policies(run)),
            "data_fingerprints": sorted(training_fingerprints(run))}
    meta["meta_sha256"] = _meta_digest(meta)
    write_json_atomic(tmp / BUNDLE, meta)
    total = sum(f.stat().st_size for f in tmp.iterdir())
    if total > BUNDLE_BYTES:
        print(f"warning: the bundle holds {total / 2**20:.1f} MiB, more than the {BUNDLE_BYTES >> 20} MiB a GPU "
              "machine returns (bfloat16 parameters halve it)", file=sys.stderr)
    if out.exists():  # the old bundle aside until the new one is in place: a kill leaves one of the two
        old = out.with_name(out.name + f".old{os.getpid()}")
        os.replace(out, old)
        os.replace(tmp, out)
        shutil.rmtree(old)
    else:
        os.replace(tmp, out)
    return meta


def _meta_digest(meta: dict) -> str:
    """The SHA-256 of bundle.json's content but this digest (its configuration, normalisation and
    judges' statistics are read from it), as canonical JSON."""
    body = {k: v for k, v in meta.items() if k != "meta_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _run_files(run: Path) -> dict:
    """The small JSON files of a run directory that its bundle copies: {name: content}."""
    return {n: run_file(run, n) for n in RUN_FILES if (Path(run) / n).exists()}


def bundle_holds(run: Path, out: Path) -> bool:
    """Whether out is a bundle of the run directory `run` as it now stands: the same configuration,
    normalisation, training status, eval.json and judge (a run trained again, or its judge fit again,
    needs a new bundle)."""
    if not is_bundle(out):
        return False
    meta = bundle_meta(out)
    return meta["files"] == _run_files(run) and all(
        meta["sha256"].get(blob) == (file_sha256(Path(run) / blob) if (Path(run) / blob).exists() else None)
        for blob in JUDGE_BLOBS)


def _to_bytes(a: np.ndarray) -> dict:
    return {"dtype": str(a.dtype), "shape": list(a.shape), "data": a.tobytes()}


def _from_bytes(d: dict) -> np.ndarray:
    dtype = jnp.bfloat16 if d["dtype"] == "bfloat16" else np.dtype(d["dtype"])
    return np.frombuffer(d["data"], dtype).reshape(d["shape"]).astype(np.float32)


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, in hex."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def check_bundle(out: Path) -> dict:
    """bundle.json of the bundle in out, after checking each of its files against its SHA-256."""
    out = Path(out)
    meta = bundle_meta(out)
    if meta.get("format") != BUNDLE_FORMAT:
        raise ValueError(f"{out}: bundle format {meta.get('format')}, this code reads {BUNDLE_FORMAT}")
    if "meta_sha256" in meta and _meta_digest(meta) != meta["meta_sha256"]:
        raise ValueError(f"{out}/{BUNDLE} does not match its own SHA-256: the copy is damaged or was edited")
    for name, digest in meta["sha256"].items():
        if not (out / name).exists():
            raise FileNotFoundError(f"{out}/{name} is missing: copy the whole bundle directory")
        if file_sha256(out / name) != digest:
            raise ValueError(f"{out}/{name} does not match its SHA-256 in {BUNDLE}: the copy is damaged")
    return meta


def _load_bundle(out: Path):
    meta = check_bundle(out)
    cfg, _ = load_run_config(out)
    flat = {}
    for name in sorted(n for n in meta["sha256"] if n.startswith("params-")):
        flat.update({k: _from_bytes(v) for k, v in serialization.msgpack_restore((out / name).read_bytes()).items()})
    shapes = traverse_util.flatten_dict(_shapes(cfg), sep="/")
    if sorted(flat) != sorted(shapes) or any(flat[k].shape != shapes[k].shape for k in shapes):
        differ = sorted(k for k in shapes if k not in flat or flat[k].shape != shapes[k].shape)
        differ += sorted(k for k in flat if k not in shapes)
        raise ValueError(f"{out}: the bundle's parameters do not fit its configuration's model ({len(differ)} "
                         f"differ, first {differ[0]}): it was written by another version of wm.model; evaluate it "
                         f"with the commit that trained it, or train anew")
    params = traverse_util.unflatten_dict({k: jnp.asarray(v) for k, v in flat.items()}, sep="/")
    return cfg, params, Norm.from_dict(meta["files"]["norm.json"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="a finished training run (make train's OUT)")
    p.add_argument("out", type=Path, help="the bundle's directory")
    p.add_argument("--dtype", default="bfloat16", choices=("bfloat16", "float32"))
    a = p.parse_args(argv)
    meta = write_bundle(a.run, a.out, a.dtype)
    sizes = {f.name: f.stat().st_size for f in a.out.iterdir()}
    print(f"{a.out}: {meta['parameters']:,} parameters in {meta['dtype']}, {len(sizes)} files, "
          f"{sum(sizes.values()) / 2**20:.1f} MiB (largest {max(sizes.values()) / 2**20:.1f} MiB)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
