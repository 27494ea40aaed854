"""A finished training run read back: its configuration, best parameters, normalisation and status."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import orbax.checkpoint as ocp

from wm.config import TrainConfig, from_dict
from wm.imagine import Norm
from wm.model import init_params


def load_run_config(out: Path) -> tuple[TrainConfig, Path]:
    d = json.loads((Path(out) / "config.json").read_text())
    return from_dict(d["train"]), Path(d["data"])


def training_status(out: Path) -> dict:
    """{"step", "steps", "cut_short"} of a training run (train_status.json); cut_short is None for a
    run that never finished a command."""
    path = Path(out) / "train_status.json"
    if not path.exists():
        return {"step": None, "steps": None, "cut_short": None}
    return json.loads(path.read_text())


def load_trained(out: Path):
    """(TrainConfig, best parameters, Norm) of a finished training run in out."""
    out = Path(out)
    if not (out / "config.json").exists() or not (out / "best").exists():
        raise FileNotFoundError(f"{out} holds no trained world model (config.json and best/): run make train first")
    cfg, _ = load_run_config(out)
    norm = Norm.from_dict(json.loads((out / "norm.json").read_text()))
    shapes = jax.eval_shape(lambda: init_params(cfg.model, jax.random.PRNGKey(0), window=cfg.window))
    mgr = ocp.CheckpointManager(out.absolute() / "best", options=ocp.CheckpointManagerOptions(create=False))
    step = mgr.latest_step()
    if step is None:
        raise FileNotFoundError(f"{out}/best holds no checkpoint")
    abstract = {"params": jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), shapes)}
    got = mgr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                                                     loader=ocp.args.JsonRestore()))
    return cfg, got["state"]["params"], norm
