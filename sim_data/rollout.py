"""Batched closed-loop episodes of a policy in the environment, on either engine.

With the `mjx` engine a whole episode is one jitted `lax.scan` (policy, controls, physics, task);
with `cpu` the jitted policy and task halves run around the threaded C engine each control step.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from sim_data.env import HomeEnv, State


@struct.dataclass
class Trajectory:
    """Stacked per-step records of a batch of episodes: leaves are (B, T, ...).

    Attributes:
      qpos: (B, T, nq) after each step; qvel: (B, T, nv); action: (B, T, 20);
      success: (B, T) bool; mocap_pos: (B, T, nmocap, 3).
    """

    qpos: jax.Array
    qvel: jax.Array
    action: jax.Array
    success: jax.Array
    mocap_pos: jax.Array


def _record(state: State, action) -> Trajectory:
    return Trajectory(qpos=state.qpos, qvel=state.qvel, action=action, success=state.success, mocap_pos=state.mocap_pos)


def _to_batch_major(traj: Trajectory) -> Trajectory:
    return jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), traj)


def run_episodes(env: HomeEnv, policy, params, rng: jax.Array, record: bool = False, progress=None):
    """Runs env.batch_size episodes of env's task to the end.

    Args:
      env: the environment (its engine and task).
      policy: an object with `init_carry(params, obs, task_state, rng)` and
        `act(params, obs, carry, rng) -> (action, carry)`.
      params: the policy's parameters.
      rng: a PRNG key; it seeds the initial states (through `env.reset`) and the policy.
      record: also return the stacked Trajectory.
      progress: optional callable(n_steps) called after each control step (cpu engine).
    Returns:
      (final State, Trajectory or None).
    """
    k_reset, k_pol, k_act = jax.random.split(rng, 3)
    state = env.reset(k_reset)
    carry = policy.init_carry(params, state.obs, state.task, k_pol)
    if env.engine.name == "mjx":
        state, traj = _scan_episode(env, policy, env.episode_steps, record, params, state, carry, k_act)
        return state, (_to_batch_major(traj) if record else None)
    act = _jitted_act(policy)
    steps = []
    for t in range(env.episode_steps):
        action, carry = act(params, state.obs, carry, jax.random.fold_in(k_act, t))
        state = env.step(state, action)
        if record:
            steps.append(_record(state, action))
        if progress is not None:
            progress(1)
    traj = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs, axis=1), *steps) if record else None
    return state, traj


@functools.lru_cache(maxsize=64)
def _jitted_act(policy):
    return jax.jit(policy.act)


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 3))
def _scan_episode(env: HomeEnv, policy, num_steps: int, record: bool, params, state, carry, rng):
    def body(c, t):
        st, pc = c
        action, pc = policy.act(params, st.obs, pc, jax.random.fold_in(rng, t))
        st = env._mjx_step(st, action)
        return (st, pc), (_record(st, action) if record else None)

    (state, _), traj = jax.lax.scan(body, (state, carry), jnp.arange(num_steps))
    return state, traj
