"""Functional, batched environment in the style of MuJoCo Playground: `reset(rng) -> State`,
`step(state, action) -> State`.

One control step (20 Hz) is: actions -> actuator controls (shared JAX), `PHYSICS_SUBSTEPS`
physics substeps in the chosen engine, then task state, success and observations (shared JAX).
With the `mjx` engine the whole step is one jitted function; with `cpu` the two shared halves
are jitted and the C engine runs between them.

The task is data (`TaskState.task_id`): the jitted functions belong to an `EnvCore` (model, engine,
batch size, held-out flag), which every `HomeEnv` of those settings shares whatever its task, so
they compile once for all tasks.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sim_data.sim import robot as R
from sim_data.sim import scene as S
from sim_data.sim.engines import default_engine, make_engine
from sim_data.sim.render import Poses, poses_from_arrays
from sim_data.sim.tasks import (
    PHYSICS_SUBSTEPS,
    Task,
    TaskState,
    dirt_mocap_z,
    episode_done,
    get_task,
    sample_initial,
    task_progress,
    update_task,
)


@struct.dataclass
class State:
    """Batched environment state (leading axis B).

    Attributes:
      physics: the engine's own state (`mjx.Data` or `CpuPhysics`).
      qpos: (B, nq) float32 joint positions after the last step.
      qvel: (B, nv) float32 joint velocities.
      mocap_pos: (B, nmocap, 3) positions of the mocap props (cues, dirt cells, stool, plant).
      task: TaskState.
      obs: {"proprio": (B, 37), "qpos", "qvel", "time": (B,)}; the last three are privileged
        and read only by scripted policies.
      success: (B,) bool, the task's success flag at this step.
      progress: (B,) float32 in [0, 1], how far towards success (`sim_data.sim.tasks.task_progress`).
      done: (B,) bool, the episode's time is up (its task's episode_steps).
      step: (B,) int32 control steps taken.
    """

    physics: Any
    qpos: jax.Array
    qvel: jax.Array
    mocap_pos: jax.Array
    task: TaskState
    obs: dict
    success: jax.Array
    progress: jax.Array
    done: jax.Array
    step: jax.Array


def _observe(qpos, qvel, ts: TaskState, idx: S.SceneIndex) -> dict:
    return {"proprio": R.proprioception(qpos, qvel, idx.robot), "qpos": qpos, "qvel": qvel, "time": ts.time}


def shown_poses(engine_poses: dict, mocap_pos, dirt_geom, dirt_mocap) -> Poses:
    """The Poses a frame of a state shows: the engine's (`{"geom_xpos": (B, ngeom, 3), ...}`, the kinematics
    of the step's last substep) with the dirt cells' geoms dirt_geom (20,) at the heights of their mocap
    bodies dirt_mocap (20,) in the state's mocap_pos (B, nmocap, 3). The step sinks the cells it wiped after
    its physics placed the geoms, so without this a frame would show them one step late (traceable)."""
    xpos = jnp.asarray(engine_poses["geom_xpos"])
    xpos = xpos.at[:, dirt_geom, 2].set(jnp.asarray(mocap_pos, xpos.dtype)[:, dirt_mocap, 2])
    return poses_from_arrays(xpos, engine_poses["geom_xmat"], engine_poses["cam_xpos"], engine_poses["cam_xmat"])


class EnvCore:
    """What the jitted steps of an environment depend on: the model, the engine, B and the held-out
    flag, not the task (that is data in the state). Hashable by identity and shared through
    `env_core`, so that envs of different tasks reuse its compiled functions, and usable as a static
    argument of `jax.jit` (`sim_data.sim.rollout`).

    Args:
      batch_size: B. engine: "cpu" or "mjx". heldout: put the held-out plant into the scenes.
      nthread: threads of the `cpu` engine (default: all cores, at most B).
      tray_spring: (stiffness N/m, centre m) to make the air fryer's tray two-state
        (`sim_data.sim.scene.with_tray_spring`), or None for the plain slide.
    """

    def __init__(self, batch_size: int, engine: str, heldout: bool, nthread: int | None,
                 tray_spring: tuple | None = None):
        self.batch_size = batch_size
        self.heldout = heldout
        self.model = S.load_model(tray_spring=tray_spring)
        self.idx = S.scene_index(self.model)
        self.engine = make_engine(engine, self.model, batch_size, nthread)
        self._qpos0 = np.asarray(self.model.qpos0, np.float32)
        self._mocap0 = S.default_mocap_pos(self.model)
        self._sample = jax.jit(jax.vmap(self._sample_one))
        self._pre = jax.jit(self.pre_step)
        self._post = jax.jit(self.post_step)
        # an action as the robot applies it (robot.applied_action): what a rollout records
        self.applied = jax.jit(functools.partial(R.applied_action, idx=self.idx.robot))
        if self.engine.name == "mjx":
            self._step = jax.jit(self.mjx_step)
            self._init = jax.jit(self.engine.init)

    def _sample_one(self, key, task_id):
        return sample_initial(task_id, key, self.idx, self._qpos0, self._mocap0, self.heldout)

    # ---- shared halves of a control step -------------------------------------------------------
    def pre_step(self, state: State, action):
        """Actuator controls (B, nu) and mocap positions of a step under action (B, 20)."""
        yaw = state.qpos[:, self.idx.robot.base_qpos[2]]
        ctrl = R.action_to_ctrl(action, yaw, self.idx.robot)
        return ctrl, state.mocap_pos

    def post_step(self, state: State, action, qpos, qvel):
        """The State after the physics reached qpos (B, nq), qvel (B, nv): task, success, observations."""
        qpos, qvel = qpos.astype(jnp.float32), qvel.astype(jnp.float32)
        ts, success = update_task(state.task, qpos, qvel, state.mocap_pos, self.idx)
        mocap = state.mocap_pos.at[:, self.idx.dirt_mocap, 2].set(dirt_mocap_z(ts))
        step = state.step + 1
        return state.replace(
            qpos=qpos, qvel=qvel, mocap_pos=mocap, task=ts, obs=_observe(qpos, qvel, ts, self.idx),
            success=success, progress=task_progress(ts, qpos, qvel, mocap, self.idx, success),
            done=episode_done(ts, step), step=step)

    def mjx_step(self, state: State, action):
        """One control step with the `mjx` engine (traceable)."""
        ctrl, mocap = self.pre_step(state, action)
        physics, qpos, qvel = self.engine.advance(state.physics, ctrl, mocap, PHYSICS_SUBSTEPS)
        return self.post_step(state.replace(physics=physics), action, qpos, qvel)

    # ---- batched API ---------------------------------------------------------------------------
    def reset(self, keys, task_ids) -> State:
        """B initial states from keys (B, 2) of episodes of tasks task_ids (B,) int32."""
        qpos, mocap, ts = self._sample(keys, task_ids)
        if self.engine.name == "mjx":
            physics = self._init(qpos, mocap)
        else:
            physics = self.engine.init(np.asarray(qpos), np.asarray(mocap))
        b = self.batch_size
        qvel = jnp.zeros((b, self.model.nv), jnp.float32)
        return State(
            physics=physics, qpos=qpos, qvel=qvel, mocap_pos=mocap, task=ts, obs=_observe(qpos, qvel, ts, self.idx),
            success=jnp.zeros((b,), bool), progress=jnp.zeros((b,), jnp.float32), done=jnp.zeros((b,), bool),
            step=jnp.zeros((b,), jnp.int32))

    def poses(self, state: State) -> Poses:
        """`sim_data.sim.render.Poses` of the batch (traceable with the `mjx` engine)."""
        return shown_poses(self.engine.poses(state.physics), state.mocap_pos, self.idx.dirt_geom, self.idx.dirt_mocap)

    def step(self, state: State, action) -> State:
        """Advances every simulation by one control step under action (B, 20) float32."""
        if self.engine.name == "mjx":
            return self._step(state, action)
        bare = state.replace(physics=None)  # float64 C state rows stay out of (float32) jit
        ctrl, mocap = self._pre(bare, action)
        physics, qpos, qvel = self.engine.advance(state.physics, np.asarray(ctrl), np.asarray(mocap), PHYSICS_SUBSTEPS)
        return self._post(bare, action, qpos.astype(np.float32), qvel.astype(np.float32)).replace(physics=physics)


@functools.lru_cache(maxsize=32)
def env_core(batch_size: int, engine: str, heldout: bool, nthread: int | None = None,
             tray_spring: tuple | None = None) -> EnvCore:
    """The EnvCore of these settings, one per process: every task's env shares it and its compiles."""
    return EnvCore(batch_size, engine, heldout, nthread, tray_spring)


class HomeEnv:
    """B simulations of one task in the home scene, on the `cpu` or `mjx` engine.

    Args:
      task: a name from `sim_data.sim.tasks.TASK_NAMES`.
      batch_size: B.
      engine: "cpu", "mjx" or None for the default (mjx where a GPU is present).
      heldout: put the held-out plant into the scenes.
      nthread: threads of the `cpu` engine (default: all cores, at most B).
      tray_spring: (stiffness N/m, centre m): the air fryer's tray two-state (EnvCore), or None.

    Attributes:
      core: the shared, task-free EnvCore that runs the steps.
    """

    def __init__(self, task: str, batch_size: int, engine: str | None = None, heldout: bool = False,
                 nthread: int | None = None, tray_spring: tuple | None = None):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.task: Task = get_task(task)
        self.batch_size = batch_size
        self.heldout = heldout
        self.core = env_core(batch_size, engine or default_engine(), heldout, nthread,
                             tuple(tray_spring) if tray_spring else None)
        self.model, self.idx, self.engine = self.core.model, self.core.idx, self.core.engine
        if self.engine.name == "mjx" and batch_size > 2 and default_engine() == "cpu":
            warnings.warn("the mjx engine is meant for GPUs: on XLA:CPU its episode scans can stall at batch "
                          "sizes above 2 (see README, known issues); use engine='cpu' here", stacklevel=2)

    @property
    def episode_steps(self) -> int:
        return self.task.episode_steps

    def reset(self, rng: jax.Array) -> State:
        """Samples B initial states. rng: one PRNG key, or B keys (one per episode): raw, (2,) or (B, 2)
        uint32 (jax.random.PRNGKey), or typed, () or (B,) (jax.random.key: of the default implementation
        it draws as the raw key it holds)."""
        keys = jnp.asarray(rng)
        typed = jnp.issubdtype(keys.dtype, jax.dtypes.prng_key)
        if keys.shape == (() if typed else (2,)):
            keys = jax.random.split(keys, self.batch_size)
        if keys.shape[:1] != (self.batch_size,) or keys.ndim != (1 if typed else 2):
            raise ValueError(f"reset takes one PRNG key or {self.batch_size} of them ({self.batch_size} typed keys "
                             f"or ({self.batch_size}, 2) raw ones), got {'typed keys' if typed else 'an array'} "
                             f"of shape {keys.shape}")
        return self.core.reset(keys, jnp.full((self.batch_size,), self.task.id, jnp.int32))

    def poses(self, state: State) -> Poses:
        """`sim_data.sim.render.Poses` of the batch (traceable with the `mjx` engine)."""
        return self.core.poses(state)

    def step(self, state: State, action) -> State:
        """Advances every simulation by one control step (CONTROL_DT) under action (B, 20)."""
        action = jnp.asarray(action, jnp.float32)
        if action.shape != (self.batch_size, R.ACTION_DIM):
            raise ValueError(f"action must have shape ({self.batch_size}, {R.ACTION_DIM}), got {action.shape}")
        return self.core.step(state, action)


@functools.lru_cache(maxsize=32)
def cached_env(task, batch, engine, heldout) -> HomeEnv:
    """The env of a task; the envs of one (batch, engine, heldout) share one EnvCore and its compiles."""
    return HomeEnv(task, batch, engine=engine, heldout=heldout)
