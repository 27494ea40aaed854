"""A user's own policy, evaluated without editing the project: the README's plug-in example.

    python -m sim_data.dataset.generate --config smoke --out runs/data/mine tasks=step_back policies=examples.plugin_policy:make

It follows the policy protocol (`sim_data.policies.registry`): hashable, batched, jittable, params shared by
the batch. It backs away from the counter for `params["seconds"]` at `params["speed"]` m/s,
holding the arms, neck and hands in the ready pose, and counts control steps in its carry.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from sim_data.policies.scripted import action_program
from sim_data.sim import robot
from sim_data.sim.tasks import CONTROL_DT


@dataclasses.dataclass(frozen=True)
class BackAway:
    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        hold = jnp.broadcast_to(params["ready"], (carry.shape[0], robot.ACTION_DIM))
        moving = carry * CONTROL_DT < params["seconds"]
        action = hold.at[:, robot.FORWARD_SPEED].set(jnp.where(moving, self.speed(params, rng, carry.shape), 0.0))
        return action, carry + 1

    def speed(self, params, rng, shape):
        """The commanded base speed of each episode this step: the parameters' own."""
        return params["speed"]


def ready_pose():
    """(20,) the arms, neck and hands in the ready pose, the base still."""
    return jnp.asarray(action_program("step_backwards", 1)[0]).at[robot.FORWARD_SPEED].set(0.0)


def make(seconds: float = 2.0, speed: float = -0.3):
    """(policy, params): what `policies=examples.plugin_policy:make` loads."""
    return BackAway(), {"ready": ready_pose(), "seconds": jnp.float32(seconds), "speed": jnp.float32(speed)}


# The same policy at other lengths, speeds and directions: on step_back only a stop 0.5-0.8 m back succeeds, so
# these check a world model on drives it never saw (policies=far=examples.plugin_policy:far, ...).
def short():
    """0.24 m back: too short."""
    return make(seconds=0.8)


def far():
    """1.5 m back: too far."""
    return make(seconds=5.0)


def slow_far():
    """0.75 m back at half speed: inside the band."""
    return make(seconds=5.0, speed=-0.15)


def fast():
    """0.9 m back at 0.45 m/s: just past the band."""
    return make(seconds=2.0, speed=-0.45)


def idle():
    """Holds the ready pose and never moves: fails every task."""
    return make(seconds=0.0)


def forward():
    """0.6 m towards the counter: fails every task."""
    return make(seconds=2.0, speed=0.3)


@dataclasses.dataclass(frozen=True)
class Flail:
    """Jitters every joint and the base around the ready pose at random, each step afresh: a policy
    that acts without purpose, and fails every task (its draws from the evaluator's key)."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        hold = jnp.broadcast_to(params["ready"], (carry.shape[0], robot.ACTION_DIM))
        return hold + params["scale"] * jax.random.normal(rng, hold.shape), carry + 1


def flail(scale: float = 0.5):
    """Random actions of standard deviation `scale` around the ready pose (clipped to their ranges)."""
    return Flail(), {"ready": ready_pose(), "scale": jnp.float32(scale)}


@dataclasses.dataclass(frozen=True)
class JitterBack(BackAway):
    """BackAway whose speed is drawn afresh each step around its mean (a standard deviation of half the
    mean, from the evaluator's key): the same distance on average, another each episode."""

    def speed(self, params, rng, shape):
        return params["speed"] * (1.0 + 0.5 * jax.random.normal(rng, shape))


def jitter_back():
    """About 0.66 m back at a jittering speed: inside step_back's band on average."""
    return JitterBack(), {"ready": ready_pose(), "seconds": jnp.float32(2.2), "speed": jnp.float32(-0.3)}


def jitter_far():
    """About 1.35 m back at a jittering speed: past the band."""
    return JitterBack(), {"ready": ready_pose(), "seconds": jnp.float32(4.5), "speed": jnp.float32(-0.3)}


@dataclasses.dataclass(frozen=True)
class LookBack:
    """Reads its camera: backs away at 0.3 m/s while the bottom quarter of its frame is brighter than
    `threshold` (the mean of its pixels in [0, 1]; the counter's white top fills it at the start), then
    stops for good (a latch in the carry). In a world model it acts on the imagined frames, so what it
    does there depends on how the model draws the receding counter."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), bool)

    def act(self, params, obs, carry, rng):
        size = obs["image"].shape[1]
        bright = obs["image"][:, size - size // 4:].astype(jnp.float32).mean(axis=(1, 2, 3)) / 255.0
        stopped = carry | (bright < params["threshold"])
        hold = jnp.broadcast_to(params["ready"], (carry.shape[0], robot.ACTION_DIM))
        return hold.at[:, robot.FORWARD_SPEED].set(jnp.where(stopped, 0.0, -0.3)), stopped


def look_back(threshold: float = 0.55):
    """Backs away until the bottom quarter of its view darkens below `threshold`."""
    return LookBack(), {"ready": ready_pose(), "threshold": jnp.float32(threshold)}


@dataclasses.dataclass(frozen=True)
class SpeedTable:
    """Backs away at `params["speeds"][step]` m/s (one entry a control step; the last held after the table
    ends), the arms, neck and hands in the ready pose: a drive at speeds that vary within the episode."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        hold = jnp.broadcast_to(params["ready"], (carry.shape[0], robot.ACTION_DIM))
        speed = params["speeds"][jnp.minimum(carry, params["speeds"].shape[0] - 1)]
        return hold.at[:, robot.FORWARD_SPEED].set(-speed), carry + 1


def speed_table(speed_at, seconds: float = 6.0):
    """(policy, params) backing away at speed_at(t) m/s (t: (N,) seconds from the start, numpy) for `seconds`."""
    t = np.arange(round(seconds / CONTROL_DT)) * CONTROL_DT
    return SpeedTable(), {"ready": ready_pose(), "speeds": jnp.asarray(speed_at(t), jnp.float32)}


# Back-aways whose speed varies, unlike any drive in the data (the distance in the first 5 s, step_back's episode):
def stop_go():
    """0.4 m/s for 0.4 s, then still for 0.3 s, four times: 0.64 m, inside step_back's band."""
    return speed_table(lambda t: np.where((t % 0.7 < 0.4) & (t < 2.8), 0.4, 0.0))


def ramp_back():
    """Speeding up from 0 to 0.5 m/s over 3 s, then stopping: 0.74 m, inside the band."""
    return speed_table(lambda t: np.where(t < 3.0, 0.5 * t / 3.0, 0.0))


def ramp_far():
    """Speeding up from 0 to 0.5 m/s over 4.5 s, then stopping: 1.11 m, too far."""
    return speed_table(lambda t: np.where(t < 4.5, 0.5 * t / 4.5, 0.0))


def surge():
    """0.5 m/s for 0.6 s, then 0.1 m/s for 3 s: 0.60 m, inside the band."""
    return speed_table(lambda t: np.where(t < 0.6, 0.5, np.where(t < 3.6, 0.1, 0.0)))


def pulse_short():
    """Two pulses of 0.3 s at 0.5 m/s a second apart: 0.30 m, too short."""
    return speed_table(lambda t: np.where((t < 0.3) | ((t >= 1.0) & (t < 1.3)), 0.5, 0.0))


def decel_far():
    """0.5 m/s slowing to a stop over 5 s: 1.26 m, too far."""
    return speed_table(lambda t: np.where(t < 5.0, 0.5 * (1.0 - t / 5.0), 0.0))


@dataclasses.dataclass(frozen=True)
class Odometer:
    """Backs away at 0.3 m/s until the distance its proprioception's forward speed sums to (the base's
    speed, `robot.PROPRIO_BASE_VEL`'s first entry, over each control step) reaches `params["metres"]`, then
    stops; the arms, neck and hands in the ready pose. A policy that reads its body, not its camera: in
    a world model it stops where the imagined body says it has gone."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.float32)

    def act(self, params, obs, carry, rng):
        driven = carry - obs["proprio"][:, robot.PROPRIO_BASE_VEL.start] * CONTROL_DT  # backwards: a negative speed
        hold = jnp.broadcast_to(params["ready"], (carry.shape[0], robot.ACTION_DIM))
        return hold.at[:, robot.FORWARD_SPEED].set(jnp.where(driven < params["metres"], -0.3, 0.0)), driven


def odometer(metres: float = 0.65):
    """Backs away until its body says it has gone `metres` (0.65 m: inside step_back's band)."""
    return Odometer(), {"ready": ready_pose(), "metres": jnp.float32(metres)}


def odometer_far():
    """The same to 1.1 m: too far."""
    return odometer(1.1)
