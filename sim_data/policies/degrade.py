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
actions must reproduce.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from sim_data.sim import robot as R

MAX_DELAY = 8
KNOBS = ("noise", "delay", "grip", "drive")
NEUTRAL = {"noise": 0.0, "delay": 0, "grip": 1.0, "drive": 1.0}


def degrade_params(base_params, **knobs) -> dict:
    """The parameters of a DegradedPolicy: the base's and every knob (NEUTRAL where not given)."""
    unknown = set(knobs) - set(KNOBS)
    if unknown:
        raise ValueError(f"unknown degradation {sorted(unknown)}; the knobs are {', '.join(KNOBS)}")
    k = {**NEUTRAL, **knobs}
    if not 0 <= int(k["delay"]) <= MAX_DELAY:
        raise ValueError(f"delay must be in 0..{MAX_DELAY} control steps, got {k['delay']}")
    if k["noise"] < 0 or k["grip"] < 0:
        raise ValueError(f"noise and grip must be >= 0, got {k['noise']} and {k['grip']}")
    return {"base": base_params, "noise": jnp.float32(k["noise"]), "delay": jnp.int32(k["delay"]),
            "grip": jnp.float32(k["grip"]), "drive": jnp.float32(k["drive"])}


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

    def init_carry(self, params, obs, task_state, rng):
        b = obs["proprio"].shape[0]
        return {"base": self.base.init_carry(params["base"], obs, task_state, rng),
                "past": jnp.zeros((b, MAX_DELAY + 1, R.ACTION_DIM), jnp.float32), "t": jnp.zeros((b,), jnp.int32)}

    def act(self, params, obs, carry, rng):
        base_key, noise_key = jax.random.split(rng)
        action, base_carry = self.base.act(params["base"], obs, carry["base"], base_key)
        action = action.astype(jnp.float32)
        joints = jax.random.normal(noise_key, action[:, :R.NECK.stop].shape) * params["noise"]
        action = action.at[:, :R.NECK.stop].add(joints)
        action = action.at[:, R.HAND_CLOSURE].multiply(params["grip"])
        action = action.at[:, R.DRIVE].multiply(params["drive"])
        past = jnp.concatenate([action[:, None], carry["past"][:, :-1]], axis=1)
        lag = jnp.minimum(params["delay"], carry["t"])  # before `delay` steps, the first action is held
        sent = jnp.take_along_axis(past, lag[:, None, None], axis=1)[:, 0]
        return sent, {"base": base_carry, "past": past, "t": carry["t"] + 1}
