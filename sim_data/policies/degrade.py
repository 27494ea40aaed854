"""Policies degraded by known amounts: counterfactual families built from one checkpoint.

A degraded policy runs a base policy of the protocol (`sim_data.policies.registry`) and changes its actions by
four knobs, all data (so every level of every family of one base network runs in one compiled
rollout, their parameters stacked):

- noise: the std of Gaussian noise added to the arm and neck joint targets (radians);
- delay: control steps of latency: the action sent is the one computed `delay` steps before (the
  first one held until then), at most MAX_DELAY;
- grip: a factor on the hand closures (1: unchanged; 0.3: a weak grip);
- drive: a factor on the driving command, forward speed and yaw rate (shortened or lengthened
  motions).

The true success of such a family moves with the knob, which is what a world model that reads the
actions must reproduce. A knob is a scalar (every row of the batch alike) or one value per row (B,):
a perturbed copy of a checkpoint (perturbation) degrades each of its episodes by its own knob and level.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from sim_data.sim import robot as R

MAX_DELAY = 8
KNOBS = ("noise", "delay", "grip", "drive")
NEUTRAL = {"noise": 0.0, "delay": 0, "grip": 1.0, "drive": 1.0}
# the levels of a perturbed copy's episodes (perturbation): past the evaluation families' on both sides
PERTURB_RANGES = {"noise": (0.05, 0.4), "delay": (1, MAX_DELAY), "grip": (0.1, 0.9), "drive": (0.4, 1.6)}
GOLDEN = 0.6180339887498949


def degrade_params(base_params, **knobs) -> dict:
    """The parameters of a DegradedPolicy: the base's and every knob (NEUTRAL where not given), each a
    scalar or one value per row of the batch (B,)."""
    unknown = set(knobs) - set(KNOBS)
    if unknown:
        raise ValueError(f"unknown degradation {sorted(unknown)}; the knobs are {', '.join(KNOBS)}")
    k = {name: np.asarray(v) for name, v in {**NEUTRAL, **knobs}.items()}
    bad = [name for name, v in k.items() if v.dtype.kind not in "iuf" or not np.all(np.isfinite(v))]
    if bad:
        raise ValueError(f"{', '.join(bad)} must be finite numbers, got {', '.join(str(knobs[b]) for b in bad)}")
    if np.any(k["delay"] < 0) or np.any(k["delay"] > MAX_DELAY) or np.any(k["delay"] != np.round(k["delay"])):
        raise ValueError(f"delay must be whole control steps in 0..{MAX_DELAY}, got {knobs['delay']}")
    if np.any(k["noise"] < 0) or np.any(k["grip"] < 0):
        raise ValueError(f"noise and grip must be >= 0, got {k['noise']} and {k['grip']}")
    return {"base": base_params, "noise": jnp.asarray(k["noise"], jnp.float32),
            "delay": jnp.asarray(k["delay"], jnp.int32), "grip": jnp.asarray(k["grip"], jnp.float32),
            "drive": jnp.asarray(k["drive"], jnp.float32)}


def perturbation(i: int) -> dict:
    """The knobs of episode i of a perturbed copy: knob KNOBS[i % 4] at a level spread over its
    PERTURB_RANGES by a golden-ratio sequence in i // 4 (any first 4n episodes cover every range), the
    others NEUTRAL. Each episode changes one thing, so the world model sees what each does."""
    knob = KNOBS[i % len(KNOBS)]
    lo, hi = PERTURB_RANGES[knob]
    level = lo + (hi - lo) * ((i // len(KNOBS) * GOLDEN) % 1.0)
    return {**NEUTRAL, knob: int(round(level)) if knob == "delay" else float(level)}


def perturbed_params(base_params, episodes) -> dict:
    """degrade_params with one row per episode index in `episodes` (B,), each at its perturbation."""
    rows = [perturbation(i) for i in episodes]
    return degrade_params(base_params, **{k: np.array([r[k] for r in rows]) for k in KNOBS})


@dataclasses.dataclass(frozen=True)
class DegradedPolicy:
    """A base policy whose actions are degraded by the knobs in its parameters (degrade_params). The
    carry: {"base": the base's carry, "past": (B, MAX_DELAY + 1, 20) the last actions computed,
    newest first, "t": (B,) int32 steps taken}."""

    base: object

    @property
    def cfg(self):
        """The base network's configuration (its image size is the renderer's)."""
        return self.base.cfg

    @property
    def stacks_in_turn(self) -> bool:
        return bool(getattr(self.base, "stacks_in_turn", False))

    def init_carry(self, params, obs, task_state, rng):
        b = obs["proprio"].shape[0]
        return {"base": self.base.init_carry(params["base"], obs, task_state, rng),
                "past": jnp.zeros((b, MAX_DELAY + 1, R.ACTION_DIM), jnp.float32), "t": jnp.zeros((b,), jnp.int32)}

    def act(self, params, obs, carry, rng):
        """The base's action (B, 20) float32 degraded: noise added to the arm and neck targets, hand closures
        scaled by grip, driving by drive, then the action computed `delay` steps before sent; and the carry."""
        base_key, noise_key = jax.random.split(rng)
        action, base_carry = self.base.act(params["base"], obs, carry["base"], base_key)
        action = action.astype(jnp.float32)
        b = action.shape[0]
        per_row = lambda knob: jnp.broadcast_to(knob, (b,))[:, None]
        joints = jax.random.normal(noise_key, action[:, :R.NECK.stop].shape) * per_row(params["noise"])
        action = action.at[:, :R.NECK.stop].add(joints)
        action = action.at[:, R.HAND_CLOSURE].multiply(per_row(params["grip"]))
        action = action.at[:, R.DRIVE].multiply(per_row(params["drive"]))
        past = jnp.concatenate([action[:, None], carry["past"][:, :-1]], axis=1)
        lag = jnp.minimum(per_row(params["delay"])[:, 0], carry["t"])  # before `delay` steps, the first is held
        sent = jnp.take_along_axis(past, lag[:, None, None], axis=1)[:, 0]
        return sent, {"base": base_carry, "past": past, "t": carry["t"] + 1}
