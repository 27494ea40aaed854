"""The robot's own motion predicted from the actions alone: how far and which way the camera's carrier
moves at each step under the driving commands, and where the position-controlled joints (the neck
that carries the camera among them) go under their targets, for an imagination that redraws the
scene from the camera's predicted pose.

The base's displacement over a control step, in its own frame at the step's start (forward, left,
turn), follows a first-order model of the commands: d_t = A [d_{t-1}, v_t, w_t, 1], with v_t, w_t
the forward-speed and yaw-rate commands as applied (`sim_data.sim.robot.FORWARD_SPEED`, `YAW_RATE`)
and A (3, 6) fit by least squares on recorded episodes (`fit_egomotion`). `roll_base` runs it from a
start pose, each step fed its own last prediction, never the simulator's. Each actuated joint j
(the action's first 16 entries are their targets, in `sim_data.sim.robot.ACTION_NAMES`' order, the
order of `RobotIndex.posed_qpos`) moves as dq_t = a_j (u_t - q_t) + b_j dq_{t-1} + c_j
(`fit_joints`, `step_joints`, `roll_joints`).
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sim_data.sim.robot import FORWARD_SPEED, YAW_RATE
from sim_data.util import read_json, write_json_atomic

EGOMOTION_JSON = "egomotion.json"


def wrap_angle(angle):
    """Angles (any shape, NumPy or traced) wrapped into [-pi, pi)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def displacements(base: np.ndarray) -> np.ndarray:
    """(..., T, 3) per-step displacements (forward m, left m, turn rad) of base poses (..., T + 1, 3)
    (world x, y, yaw), each in the base's frame at the step's start."""
    base = np.asarray(base, np.float64)
    dxy = base[..., 1:, :2] - base[..., :-1, :2]
    yaw = base[..., :-1, 2]
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * dxy[..., 0] + s * dxy[..., 1], -s * dxy[..., 0] + c * dxy[..., 1],
                     wrap_angle(base[..., 1:, 2] - yaw)], -1)


def _regressors(prev, action, xp=np):
    """(..., 6) the base model's inputs [d_{t-1}, v_t, w_t, 1] from prev (..., 3) and action (..., 20), in
    prev's dtype; xp: NumPy for the fit, jax.numpy for the traced step."""
    action = xp.asarray(action, prev.dtype)
    return xp.concatenate([prev, action[..., FORWARD_SPEED:FORWARD_SPEED + 1], action[..., YAW_RATE:YAW_RATE + 1],
                           xp.ones(prev.shape[:-1] + (1,), prev.dtype)], -1)


def fit_egomotion(bases, actions) -> np.ndarray:
    """A (3, 6) of the first-order model, fit by least squares on episodes: bases [(T_i + 1, 3)] world
    base poses, actions [(T_i, 20)] the actions applied (episodes of any lengths)."""
    xs, ys = [], []
    for base, action in zip(bases, actions):
        d = displacements(base)
        if len(d) != len(action):
            raise ValueError(f"an episode has {len(base)} base poses and {len(action)} actions; it needs one "
                             f"pose more than actions")
        prev = np.concatenate([np.zeros((1, 3)), d[:-1]])
        xs.append(_regressors(prev, action))
        ys.append(d)
    if not xs:
        raise ValueError("no episodes to fit the base's motion on")
    coef, *_ = np.linalg.lstsq(np.concatenate(xs), np.concatenate(ys), rcond=None)
    return coef.T


def step_base(coef, base, prev, action) -> tuple:
    """One control step of the model: base (B, 3) world pose, prev (B, 3) the last predicted displacement,
    action (B, 20) -> (the next base pose, its displacement), float32. Traceable."""
    d = _regressors(jnp.asarray(prev, jnp.float32), action, jnp) @ jnp.asarray(coef, jnp.float32).T
    base = jnp.asarray(base, jnp.float32)
    c, s = jnp.cos(base[:, 2]), jnp.sin(base[:, 2])
    moved = jnp.stack([base[:, 0] + c * d[:, 0] - s * d[:, 1], base[:, 1] + s * d[:, 0] + c * d[:, 1],
                       wrap_angle(base[:, 2] + d[:, 2])], -1)
    return moved, d


def roll_base(coef: np.ndarray, start: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """(B, T + 1, 3) base poses predicted from start (B, 3) under actions (B, T, 20), the first the start."""
    return _rolled(step_base, coef, start, actions)


def _rolled(step, coef, start, actions) -> np.ndarray:
    """_roll's (B, T + 1, D) float64 from NumPy inputs, float32 inside, the first change zero."""
    start = jnp.asarray(start, jnp.float32)
    return np.asarray(_roll(step, jnp.asarray(coef, jnp.float32), start, jnp.zeros_like(start),
                            jnp.asarray(actions, jnp.float32)), np.float64)


@functools.partial(jax.jit, static_argnames=("step",))
def _roll(step, coef, start, prev, actions):
    """(B, T + 1, D) the states `step` (step_base or step_joints) predicts from start (B, D), its last
    change prev (B, D), under actions (B, T, 20): one compiled scan, where a Python loop of eager steps
    would dispatch every operation of every step (minutes over a large dataset's validation episodes)."""
    def one(carry, action):
        state, change = step(coef, *carry, action)
        return (state, change), state
    _, states = jax.lax.scan(one, (start, prev), jnp.swapaxes(actions, 0, 1))
    return jnp.concatenate([start[:, None], jnp.swapaxes(states, 0, 1)], 1)


JOINTS = 16  # the actuated joints whose targets lead the action vector


def fit_joints(qs, actions) -> np.ndarray:
    """(16, 3) per joint (a, b, c) of dq_t = a (u_t - q_t) + b dq_{t-1} + c, by least squares on episodes:
    qs [(T_i + 1, 16)] the actuated joints' positions, actions [(T_i, 20)] as applied."""
    rows, ys = [], []
    for q, action in zip(qs, actions):
        q, u = np.asarray(q, np.float64), np.asarray(action, np.float64)[:, :JOINTS]
        if len(q) != len(u) + 1:
            raise ValueError(f"an episode has {len(q)} joint states and {len(u)} actions; it needs one state "
                             f"more than actions")
        dq = np.diff(q, axis=0)
        prev = np.concatenate([np.zeros((1, JOINTS)), dq[:-1]])
        rows.append(np.stack([u - q[:-1], prev, np.ones_like(prev)], -1))
        ys.append(dq)
    if not rows:
        raise ValueError("no episodes to fit the joints' motion on")
    x, y = np.concatenate(rows), np.concatenate(ys)
    return np.stack([np.linalg.lstsq(x[:, j], y[:, j], rcond=None)[0] for j in range(JOINTS)])


def step_joints(coef, q, prev, action) -> tuple:
    """One control step of the joints' model: q, prev (B, 16) positions and last predicted change, action
    (B, 20) -> (the next positions, their change), float32. Traceable."""
    a, b, c = jnp.asarray(coef, jnp.float32).T
    q = jnp.asarray(q, jnp.float32)
    dq = a * (jnp.asarray(action, jnp.float32)[:, :JOINTS] - q) + b * jnp.asarray(prev, jnp.float32) + c
    return q + dq, dq


def roll_joints(coef: np.ndarray, start: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """(B, T + 1, 16) joint positions predicted from start (B, 16) under actions (B, T, 20), the first the
    start."""
    return _rolled(step_joints, coef, start, actions)


def save_egomotion(out: Path, coef: np.ndarray, metrics: dict, joints: np.ndarray | None = None) -> None:
    """Writes out/egomotion.json: the base model's A, the joints' (a, b, c) where given, and the fit's
    metrics."""
    write_json_atomic(Path(out) / EGOMOTION_JSON, {"coef": np.asarray(coef).tolist(), "metrics": metrics,
                                                   "joints": None if joints is None else np.asarray(joints).tolist()})


def load_egomotion(out: Path, joints: bool = False):
    """A (3, 6) saved by save_egomotion in out; with joints, (A, the joints' (16, 3))."""
    path = Path(out) / EGOMOTION_JSON
    if not path.exists():
        raise FileNotFoundError(f"{out} holds no base-motion model ({EGOMOTION_JSON}); fit one with "
                                f"python -m experiments.fill --out {out}")
    meta = read_json(path)
    coef = np.asarray(meta["coef"], np.float64)
    if coef.shape != (3, 6):
        raise ValueError(f"{path}: the model's matrix is {coef.shape}, not (3, 6); fit it again")
    if not joints:
        return coef
    if meta.get("joints") is None:
        raise ValueError(f"{path} holds no model of the joints' motion; remove it and run python -m "
                         f"experiments.fill --out {Path(out)} again")
    return coef, np.asarray(meta["joints"], np.float64)
