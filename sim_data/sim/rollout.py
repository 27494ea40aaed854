"""Batched closed-loop episodes of a policy in the environment, on either engine.

With the `mjx` engine an episode runs as segments of SEGMENT control steps, each one call of a
jitted `lax.scan` (policy, controls, physics, task); with `cpu` the jitted policy and task halves
run around the threaded C engine each control step. The compiled programs take the env's task-free
`EnvCore` and the policy as static arguments and the task as data, so one compilation per engine,
batch size, policy and renderers serves every task and episode length.
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sim_data.sim.engines import CpuEngine
from sim_data.sim.env import EnvCore, HomeEnv, State, shown_poses
from sim_data.sim.render import Poses, Renderer, episode_rgb
from sim_data.sim.tasks import EPISODE_STEPS

SEGMENT = 20  # control steps per compiled scan: every task's episode_steps is a multiple
WARM_STEPS = 2 * SEGMENT  # what a warm-up runs: a first segment and a later one, every per-segment program
assert not (EPISODE_STEPS % SEGMENT).any(), "an episode must be whole segments"


@struct.dataclass
class Trajectory:
    """Stacked per-step records of a batch of episodes: leaves are (B, T, ...).

    Attributes:
      qpos: (B, T, nq) after each step; qvel: (B, T, nv); action: (B, T, 20);
      success: (B, T) bool; progress: (B, T) float32; mocap_pos: (B, T, nmocap, 3).
    """

    qpos: jax.Array
    qvel: jax.Array
    action: jax.Array
    success: jax.Array
    progress: jax.Array
    mocap_pos: jax.Array


def _record(state: State, action) -> Trajectory:
    return Trajectory(qpos=state.qpos, qvel=state.qvel, action=action, success=state.success,
                      progress=state.progress, mocap_pos=state.mocap_pos)


def _to_batch_major(traj: Trajectory) -> Trajectory:
    return jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), traj)


def _concat_time(segments):
    """Time-major pytrees (SEGMENT, ...) of consecutive segments -> one (T, ...) pytree."""
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=0), *segments)


@jax.jit
def _trajectory_of(segments) -> Trajectory:
    """The segments' records as one batch-major Trajectory: one program, where eager concatenations
    and transposes would each compile for every leaf's shape."""
    return _to_batch_major(_concat_time(segments))


def _segment_starts(env: HomeEnv, steps: int | None = None) -> range:
    return range(0, env.episode_steps if steps is None else steps, SEGMENT)


def _check_steps(env: HomeEnv, steps: int | None) -> None:
    """Refuses a step limit that is not whole segments of the env's episode (None: the whole episode)."""
    if steps is not None and not (0 < steps <= env.episode_steps and steps % SEGMENT == 0):
        raise ValueError(f"steps={steps}: give a multiple of {SEGMENT} up to the episode's {env.episode_steps}")


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
    carry = jitted_init(policy)(params, state.obs, state.task, k_pol)
    if env.engine.name == "mjx":
        segments = []
        for start in _segment_starts(env):
            state, carry, traj = _scan_segment(env.core, policy, record, params, state, carry, k_act, jnp.int32(start))
            segments.append(traj)
        return state, (_trajectory_of(segments) if record else None)
    act = jitted_act(policy)
    steps = []
    for t in range(env.episode_steps):
        action, carry = act(params, state.obs, carry, jax.random.fold_in(k_act, t))
        action = env.core.applied(action)
        state = env.step(state, action)
        if record:
            steps.append(_record(state, action))
        if progress is not None:
            progress(1)
    # stacked on the host, where the cpu engine's arrays are: jnp.stack would compile for every length
    traj = jax.tree_util.tree_map(lambda *xs: jax.device_put(np.stack(xs, axis=1)), *steps) if record else None
    return state, traj


@functools.lru_cache(maxsize=64)
def jitted_act(policy):
    """policy.act jitted once per policy object (equal policies share it), so that every episode batch of
    the same shapes runs one compiled program."""
    return jax.jit(policy.act)


@functools.lru_cache(maxsize=64)
def jitted_init(policy):
    """policy.init_carry jitted once per policy object, as jitted_act."""
    return jax.jit(policy.init_carry)  # eager, its many small ops would each compile


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _scan_segment(core: EnvCore, policy, record: bool, params, state, carry, rng, start):
    """SEGMENT control steps from step `start` (an int32 array: data, not static) with the `mjx`
    engine; the policy's noise at step t is fold_in(rng, t). Returns (state, carry, Trajectory of
    (SEGMENT, B, ...) leaves or None)."""
    def body(c, t):
        st, pc = c
        action, pc = policy.act(params, st.obs, pc, jax.random.fold_in(rng, t))
        action = core.applied(action)
        st = core.mjx_step(st, action)
        return (st, pc), (_record(st, action) if record else None)

    (state, carry), traj = jax.lax.scan(body, (state, carry), start + jnp.arange(SEGMENT, dtype=jnp.int32))
    return state, carry, traj


@struct.dataclass
class Recording:
    """Whole episodes as a dataset stores them: T+1 observations around T actions (leaves (B, ...)).

    Attributes:
      frames: {camera name: (B, T+1, H, W, 3) uint8}, frame t seen before action t.
      proprio: (B, T+1, 37); qpos: (B, T+1, nq); qvel: (B, T+1, nv); mocap_pos: (B, T+1, nmocap, 3).
      success: (B, T+1) bool (False at t = 0); progress: (B, T+1) float32 (0 at t = 0); action: (B, T, 20).
    """

    frames: dict
    proprio: jax.Array
    qpos: jax.Array
    qvel: jax.Array
    mocap_pos: jax.Array
    success: jax.Array
    progress: jax.Array
    action: jax.Array


def _observation(poses: Poses, state: State, renderers, rgb):
    frames = {r.cfg.camera: r.render_batch(poses, rgb)["rgb"] for r in renderers}
    rec = {"proprio": state.obs["proprio"], "qpos": state.qpos, "qvel": state.qvel, "mocap_pos": state.mocap_pos,
           "success": state.success, "progress": state.progress}
    obs = dict(state.obs)
    if frames:
        obs["image"] = frames[renderers[0].cfg.camera]
    return obs, frames, rec


def _stack_recording(first, rest, actions, xp=jnp) -> Recording:
    """first: (frames, rec) of the reset state; rest: the same stacked over T steps (time-major).
    xp: the array module of the stacking: numpy for the cpu engine's host arrays (jax.numpy would
    compile for every episode length), jax.numpy for the device's."""
    def cat(a, b):
        return xp.concatenate([a[:, None], xp.swapaxes(b, 0, 1)], axis=1)

    frames = {k: cat(first[0][k], rest[0][k]) for k in first[0]}
    rec = {k: cat(first[1][k], rest[1][k]) for k in first[1]}
    return Recording(frames=frames, action=xp.swapaxes(actions, 0, 1), **rec)


@jax.jit
def _recording_of(first, segments) -> Recording:
    """The `mjx` engine's Recording from the reset state's (frames, record) and the segments'
    ((frames, record), actions): one program rather than an eager op per leaf's shape."""
    rest, actions = _concat_time(segments)
    return _stack_recording(first, rest, actions)


def record_episodes(env: HomeEnv, policy, params, rng: jax.Array, renderers: tuple[Renderer, ...] = (),
                    progress=None, reset_keys=None, steps: int | None = None,
                    compile_ahead: bool = False) -> tuple[State, Recording]:
    """Runs env.batch_size episodes to the end, rendering every camera of `renderers` at every step.

    The policy sees `obs["image"]`, the first renderer's frame, besides the state's observations.
    Same seeding as `run_episodes`: one rng gives the same initial states and policy noise;
    reset_keys (B, 2), if given, seed each episode's initial state instead. steps: only the first
    `steps` control steps (whole segments; the same compiled programs as a whole episode's, which is
    how a run's programs are compiled ahead of it). compile_ahead (the `mjx` engine): the recorded
    rollout compiles in a background thread (compile_recorded_ahead) while this thread compiles
    and runs the reset, the first observation and the policy's carry; for programs that no warm-up
    process has put in the persistent cache (a warmed program's text must follow one tracing order).
    Returns (final State, Recording).
    """
    _check_steps(env, steps)
    renderers = tuple(renderers)
    k_reset, k_pol, k_act = jax.random.split(rng, 3)
    keys = k_reset if reset_keys is None else reset_keys
    ahead = (compile_recorded_ahead(env, policy, params, renderers, keys, k_pol, k_act)
             if compile_ahead and env.engine.name == "mjx" else None)
    state = env.reset(keys)
    rgb = episode_rgb(renderers[0].geometry, state.task.colors) if renderers else None
    if env.engine.name == "mjx":
        obs, frames, rec = _observe_mjx(env.core, renderers, state, rgb)
        # the policy's carry starts from what it sees at reset, the camera's frame included
        carry = jitted_init(policy)(params, obs, state.task, k_pol)
        if ahead is not None:
            _wait_ahead(ahead)  # a call before it ends would compile the same program a second time
        segments = []
        for start in _segment_starts(env, steps):
            state, carry, obs, seg = _scan_recorded(env.core, policy, renderers, params, state, carry, obs, k_act,
                                                    jnp.int32(start), rgb)
            segments.append(seg)
        return state, _recording_of((frames, rec), segments)
    jitted = _jitted_cpu_observe(renderers)

    def observe(st, colors):
        # float64 rows stay out of jit
        return jitted(st.replace(physics=st.physics.replace(rows=None)), colors, env.core.idx.dirt_geom,
                      env.core.idx.dirt_mocap)

    act = jitted_act(policy)
    obs, frames, rec = observe(state, rgb)
    carry = jitted_init(policy)(params, obs, state.task, k_pol)
    first, recorded, actions = (frames, rec), [], []
    for t in range(env.episode_steps if steps is None else steps):
        action, carry = act(params, obs, carry, jax.random.fold_in(k_act, t))
        action = env.core.applied(action)
        state = env.step(state, action)
        obs, frames, rec = observe(state, rgb)
        recorded.append((frames, rec))
        actions.append(action)
        if progress is not None:
            progress(1)
    first, recorded, actions = jax.device_get((first, recorded, actions))
    rest = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *recorded)
    return state, jax.device_put(_stack_recording(first, rest, np.stack(actions), xp=np))


@functools.lru_cache(maxsize=64)
def _jitted_cpu_observe(renderers):
    """Shared by every task and batch size of the cpu engine (the renderer compiles once per shape);
    dirt_geom and dirt_mocap: the scene index's (shown_poses)."""
    def observe(st, rgb, dirt_geom, dirt_mocap):
        return _observation(shown_poses(CpuEngine.poses(st.physics), st.mocap_pos, dirt_geom, dirt_mocap), st,
                            renderers, rgb)

    return jax.jit(observe)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _observe_mjx(core: EnvCore, renderers, state, rgb):
    """(observation, frames, record) of a state of the `mjx` engine."""
    return _observation(core.poses(state), state, renderers, rgb)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _scan_recorded(core: EnvCore, policy, renderers, params, state, carry, obs, rng, start, rgb):
    """SEGMENT recorded control steps from step `start` (int32 data) with the `mjx` engine, obs the
    policy's observation of `state`. Returns (state, carry, obs, ((frames, record), actions)), the
    last with (SEGMENT, B, ...) leaves."""
    def body(c, t):
        st, pc, ob = c
        action, pc = policy.act(params, ob, pc, jax.random.fold_in(rng, t))
        action = core.applied(action)
        st = core.mjx_step(st, action)
        ob, fr, rc = _observation(core.poses(st), st, renderers, rgb)
        return (st, pc, ob), ((fr, rc), action)

    (state, carry, obs), seg = jax.lax.scan(body, (state, carry, obs), start + jnp.arange(SEGMENT, dtype=jnp.int32))
    return state, carry, obs, seg


_AHEAD_POOL = cf.ThreadPoolExecutor(1, thread_name_prefix="compile-ahead")
# (core, policy, renderers, the types of params and the action key) -> the Future of its first compile;
# read and written by the calling thread only
_AHEAD: dict = {}


def compile_recorded_ahead(env: HomeEnv, policy, params, renderers: tuple, reset_keys, k_pol, k_act) -> cf.Future:
    """The Future of `_scan_recorded`'s compilation for env's batch, policy, renderers and the types
    of params and k_act, started in a background thread the first time they are seen (later calls
    return the same Future).

    reset_keys: (B, 2) uint32, or one key (what env.reset takes); k_pol, k_act: the keys that
    record_episodes gives the policy's carry and its actions. The thread finds the shapes of the reset
    state, its observation and the policy's carry by `jax.eval_shape` and runs one segment from zeros
    of those shapes, which compiles the program into jit's own cache as a real call would; the
    segment's output is discarded. XLA compiles with the interpreter lock released, so this compile
    runs beside those the caller goes on with. The thread sees JAX's global configuration only:
    callers inside a thread-local context (`jax.default_device`, `jax.enable_x64` as a context) would
    compile another program than theirs, so they leave compile_ahead off."""
    leaves, tree = jax.tree_util.tree_flatten(params)
    key = (env.core, policy, renderers, tree, tuple(jax.typeof(x) for x in leaves), jax.typeof(k_act))
    if key not in _AHEAD:
        _AHEAD[key] = _AHEAD_POOL.submit(_run_recorded_on_zeros, env, policy, params, renderers, reset_keys,
                                         k_pol, k_act)
    return _AHEAD[key]


def _wait_ahead(ahead: cf.Future) -> None:
    """Waits for a compile started by compile_recorded_ahead. Where it failed, warns and forgets it, so
    that the caller's own call compiles the program and a later call tries again."""
    error = ahead.exception()
    if error is None:
        return
    for key in [k for k, f in _AHEAD.items() if f is ahead]:
        del _AHEAD[key]
    warnings.warn(f"compiling the recorded rollout ahead failed ({error!r}); it compiles in turn instead",
                  RuntimeWarning, stacklevel=3)


def _run_recorded_on_zeros(env: HomeEnv, policy, params, renderers: tuple, reset_keys, k_pol, k_act) -> None:
    """One segment of `_scan_recorded` from zeros of the shapes a real call gives it (compile_recorded_ahead);
    nothing where the state, observation or carry hold typed PRNG keys or weakly typed values, whose
    zeros it does not make (a plain zero array in their place would compile another program)."""
    state = jax.eval_shape(env.reset, reset_keys)
    rgb = jax.eval_shape(lambda c: episode_rgb(renderers[0].geometry, c), state.task.colors) if renderers else None
    obs = jax.eval_shape(lambda st, c: _observe_mjx(env.core, renderers, st, c)[0], state, rgb)
    carry = jax.eval_shape(policy.init_carry, params, obs, state.task, k_pol)
    shapes = (state, carry, obs, rgb)
    leaves = jax.tree_util.tree_leaves(shapes)
    if any(s.weak_type or jax.dtypes.issubdtype(s.dtype, jax.dtypes.prng_key) for s in leaves):
        return
    # host zeros put on the device: an eager jnp.zeros would compile a program per shape
    state, carry, obs, rgb = jax.tree_util.tree_map(lambda s: jax.device_put(np.zeros(s.shape, s.dtype)), shapes)
    jax.block_until_ready(_scan_recorded(env.core, policy, renderers, params, state, carry, obs, k_act,
                                         jnp.int32(0), rgb))


def record_policies(env: HomeEnv, policy, params, reset_keys, rng: jax.Array, renderers=(),
                    steps: int | None = None) -> tuple:
    """P policies (a `sim_data.policies.bc.StackedPolicy` and its stacked parameters, leading axis P,
    or a MixedPolicy of such), each from the same n initial states (reset_keys (n, 2)), as one batch of
    P*n episodes (env.batch_size); steps: the first steps only (record_episodes). Returns ((P, n) bool
    final success, the Recording)."""
    p, rest = divmod(env.batch_size, len(reset_keys))
    if rest:
        raise ValueError(f"a batch of {env.batch_size} is not whole runs of {len(reset_keys)} initial states")
    _, rec = record_episodes(env, policy, params, rng, renderers, reset_keys=np.tile(np.asarray(reset_keys), (p, 1)),
                             steps=steps)
    return np.asarray(rec.success[:, -1]).reshape(p, len(reset_keys)), rec
