"""A learned generator of what a reprojected frame leaves empty.

A camera that moves over a still scene sees, in its new view, points that its first frame showed
(`sim_data.sim.render.reproject` carries them over exactly, through their depth) and points the
first frame never showed: the floor between the robot and the counter once it backs away, the sides of
what it turns past. `FillNet` draws the second kind: a small U-Net that reads the reprojected frame,
which of its pixels a point landed on, and each pixel's ray in the world with where that ray meets the
floor (`sim_data.sim.render.floor_hits`, in Fourier features, since the floor's texture is a function
of its position). It is trained on pairs from recorded episodes, the first frame reprojected to a later
camera pose against the frame drawn there, with an L1 loss on the pixels no point landed on; its
output replaces only those pixels (`filled`).

Config and parameters are saved together (`save_fill`, `load_fill`): fill.json and fill.msgpack.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization
from tqdm import tqdm

from sim_data.sim.render import floor_hits
from sim_data.util import read_json, write_json_atomic

FILL_JSON, FILL_PARAMS = "fill.json", "fill.msgpack"


@dataclasses.dataclass(frozen=True)
class FillConfig:
    """The generator's shape and its training budget (in steps: the same command gives the same net)."""
    width: int = 16  # channels at full resolution, doubled at each level down
    levels: int = 3
    freqs: tuple = (0.25, 0.4, 0.66, 1.0, 1.6, 2.5, 4.0)  # cycles per metre of the floor features
    steps: int = 2000  # with batch 16: 11-14 minutes on 2 CPU cores at 64 px
    batch: int = 16
    lr: float = 2e-3
    seed: int = 0

    def __post_init__(self):
        if self.width < 4 or self.levels < 1 or self.steps < 1 or self.batch < 1 or self.lr <= 0:
            raise ValueError(f"FillConfig needs width >= 4, levels >= 1, steps >= 1, batch >= 1 and lr > 0; "
                             f"got {self}")

    @property
    def in_channels(self) -> int:
        return 3 + 1 + 3 + 1 + 2 + 4 * len(self.freqs)


class FillNet(nn.Module):
    """(B, S, S, C) per-pixel features (fill_features) -> (B, S, S, 3) colours in [0, 1]; S a multiple
    of 2 ** levels."""
    width: int
    levels: int

    @nn.compact
    def __call__(self, x):
        h = nn.gelu(nn.Conv(self.width, (3, 3))(x))
        skips = []
        for i in range(self.levels):
            h = nn.gelu(nn.Conv(self.width * 2 ** i, (3, 3))(h))
            skips.append(h)
            h = nn.gelu(nn.Conv(self.width * 2 ** (i + 1), (3, 3), strides=2)(h))
        h = nn.gelu(nn.Conv(self.width * 2 ** self.levels, (3, 3))(h))
        for i in reversed(range(self.levels)):
            skip = skips[i]
            h = jax.image.resize(h, (h.shape[0], *skip.shape[1:3], h.shape[-1]), "nearest")
            h = nn.gelu(nn.Conv(self.width * 2 ** i, (3, 3))(jnp.concatenate([h, skip], -1)))
        return nn.sigmoid(nn.Conv(3, (1, 1))(h))


def fill_features(reprojected, covered, cam_pos, cam_mat, fovy, freqs) -> jax.Array:
    """(B, S, S, C) float32 inputs of FillNet: the reprojected frame ((B, S, S, 3) uint8) in [0, 1],
    `covered` ((B, S, S) bool: a point landed there), each pixel's unit ray in the world (3), whether it
    meets the floor (1), where (x, y in metres, 2) and those in sines and cosines at `freqs` cycles per
    metre; cam_pos (B, 3), cam_mat (B, 3, 3) world-from-camera. Traceable."""
    b, s = covered.shape[:2]
    xy, ray = floor_hits(cam_pos, cam_mat, fovy, s, s)
    down = (ray[..., 2] < -1e-6)[..., None]
    phase = 2 * jnp.pi * xy[..., None, :] * jnp.asarray(freqs, jnp.float32)[:, None]  # (B, S, S, F, 2)
    waves = jnp.concatenate([jnp.sin(phase), jnp.cos(phase)], -1).reshape(b, s, s, -1) * down
    return jnp.concatenate([jnp.asarray(reprojected, jnp.float32) / 255.0,
                            jnp.asarray(covered, jnp.float32)[..., None], ray, down, xy, waves], -1)


def init_fill(cfg: FillConfig, size: int):
    """FillNet and its parameters for size x size frames."""
    if size % 2 ** cfg.levels:
        raise ValueError(f"frames of {size} px do not halve {cfg.levels} times; use fewer levels")
    net = FillNet(cfg.width, cfg.levels)
    params = net.init(jax.random.PRNGKey(cfg.seed), jnp.zeros((1, size, size, cfg.in_channels)))["params"]
    return net, params


def hole_l1(pred, target, covered) -> jax.Array:
    """Mean absolute colour error over the pixels no point landed on: pred, target (B, S, S, 3) in [0, 1],
    covered (B, S, S) bool."""
    hole = (~covered)[..., None].astype(pred.dtype)
    return (jnp.abs(pred - target) * hole).sum() / jnp.maximum(hole.sum() * 3, 1.0)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _train_step(net, tx, params, opt_state, x, target, covered):
    loss, grads = jax.value_and_grad(lambda p: hole_l1(net.apply({"params": p}, x), target, covered))(params)
    updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss


def train_fill(pairs: dict, fovy: float, cfg: FillConfig, progress: bool = True) -> tuple:
    """Fits FillNet on pairs {"reprojected": (N, S, S, 3) uint8, "covered": (N, S, S) bool, "true":
    (N, S, S, 3) uint8, "cam_pos": (N, 3), "cam_mat": (N, 3, 3)} for cfg.steps steps of cfg.batch pairs
    drawn with cfg.seed. Returns (net, params, {"loss": the mean hole L1 of the last tenth of the steps,
    "losses": every step's})."""
    n, size = len(pairs["covered"]), pairs["covered"].shape[1]
    if n < 1:
        raise ValueError("no pairs to train the fill on")
    net, params = init_fill(cfg, size)
    tx = optax.adamw(optax.cosine_decay_schedule(cfg.lr, cfg.steps, 0.05))
    opt_state = tx.init(params)
    rng = np.random.default_rng(cfg.seed)
    losses = []
    for _ in tqdm(range(cfg.steps), desc="fill", disable=not progress):
        i = rng.integers(0, n, cfg.batch)
        x = fill_features(pairs["reprojected"][i], pairs["covered"][i], pairs["cam_pos"][i], pairs["cam_mat"][i],
                          fovy, cfg.freqs)
        params, opt_state, loss = _train_step(net, tx, params, opt_state, x,
                                              jnp.asarray(pairs["true"][i], jnp.float32) / 255.0,
                                              jnp.asarray(pairs["covered"][i]))
        losses.append(loss)  # read back once at the end: a float() here would wait on every step
    losses = np.asarray(jax.device_get(losses), np.float64).tolist()
    tail = losses[-max(1, cfg.steps // 10):]
    return net, params, {"loss": float(np.mean(tail)), "losses": losses}


@functools.partial(jax.jit, static_argnums=(0, 2))
def filled(net, params, cfg: FillConfig, reprojected, covered, cam_pos, cam_mat, fovy) -> jax.Array:
    """(B, S, S, 3) uint8: the reprojected frames with the pixels no point landed on drawn by the net.
    Traceable (net and cfg static)."""
    x = fill_features(reprojected, covered, cam_pos, cam_mat, fovy, cfg.freqs)
    drawn = jnp.clip(net.apply({"params": params}, x) * 255.0 + 0.5, 0, 255).astype(jnp.uint8)
    return jnp.where(jnp.asarray(covered)[..., None], jnp.asarray(reprojected, jnp.uint8), drawn)


def save_fill(out: Path, params, cfg: FillConfig, size: int, metrics: dict) -> None:
    """Writes out/fill.msgpack (the parameters, atomically) and out/fill.json (config, frame size and the
    fit's metrics) for load_fill."""
    out.mkdir(parents=True, exist_ok=True)
    blob = out / FILL_PARAMS
    tmp = blob.with_name(blob.name + ".tmp")
    tmp.write_bytes(serialization.to_bytes(params))
    os.replace(tmp, blob)
    cfg_dict = dataclasses.asdict(cfg)
    write_json_atomic(out / FILL_JSON, {"config": {**cfg_dict, "freqs": list(cfg.freqs)}, "size": size,
                                        "metrics": metrics})


def load_fill(out: Path) -> tuple:
    """(net, params, cfg, size) of a fill saved by save_fill in out."""
    out = Path(out)
    if not (out / FILL_JSON).exists() or not (out / FILL_PARAMS).exists():
        raise FileNotFoundError(f"{out} holds no trained fill ({FILL_JSON} and {FILL_PARAMS}); train one with "
                                f"python -m experiments.fill --out {out}")
    meta = read_json(out / FILL_JSON)
    cfg = FillConfig(**{**meta["config"], "freqs": tuple(meta["config"]["freqs"])})
    net, template = init_fill(cfg, meta["size"])
    params = serialization.from_bytes(template, (out / FILL_PARAMS).read_bytes())
    return net, params, cfg, meta["size"]
