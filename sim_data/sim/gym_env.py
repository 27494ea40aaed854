"""Gymnasium environments over the project's own simulation: one episode at a time (`HomeGymEnv`,
`gym.make`) or N side by side on one batched engine (`HomeVectorEnv`, `gym.make_vec`).

    import gymnasium as gym, sim_data
    env = gym.make(sim_data.ENV_ID, task="mug")
    obs, info = env.reset(seed=0, options={"task": "wipe"})   # the task can change at reset
    envs = gym.make_vec(sim_data.ENV_ID, num_envs=64, vectorization_mode="vector_entry_point", engine="cpu")

Observation (`obs=`): "dict" (default), the observation the project's policies act on,
{"image": (64, 64, 3) uint8 head-camera frame, "proprio": (37,) float32}; the frame is drawn by the
project's JAX renderer (`sim_data.sim.render`) exactly as `sim_data.sim.rollout.record_episodes`
draws it for the dataset and the policies, so a zoo policy or plug-in (`sim_data.policies.registry`)
acts through Gymnasium on the same pixels. "proprio": the 37 proprioception floats alone.

Action: the 20 floats of `sim_data.sim.robot`, in physical units (joint targets in rad bounded by the
actuators' control ranges, closures 0..1, speed +-0.5 m/s, yaw rate +-1 rad/s), the units the
dataset and the policies use. Reward: 1.0 at steps where the task's success flag holds, else 0.
`terminated` is never set, since success does not end an episode (mug counts a hold of 0.5 s);
`truncated` when the task's episode time is up; `info["success"]` carries the flag.

Episode length: tasks differ (`sim_data.sim.tasks.EPISODE_STEPS`: step_back 100 control steps, mug
120, wipe 200, ...). The id is registered with `max_episode_steps` = the longest task's
(`MAX_EPISODE_STEPS`), and each environment truncates at its own task's `episode_steps`: Gymnasium's
TimeLimit, fixed when the id is made, would otherwise cut short every task longer than the one it
was set for, including a task chosen at reset. `env.unwrapped.episode_steps` is the current task's.

Seeding: `reset(seed=s)` starts from the states `HomeEnv(task, B).reset(jax.random.PRNGKey(s))`
gives (B = 1 for `HomeGymEnv`, num_envs for `HomeVectorEnv`), so an episode through Gymnasium is
the same episode as through `HomeEnv`; resets without a seed (and the vector env's autoresets) draw
their keys from the env's `np_random`.

`render()` (render_mode "rgb_array") draws `camera` (default the external camera) at width x height
with the same JAX renderer; no OpenGL is needed.
"""

from __future__ import annotations

import functools
from typing import ClassVar

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from sim_data.sim import robot as R
from sim_data.sim.env import HomeEnv, State
from sim_data.sim.render import HEAD_CAMERA, RenderConfig, Renderer, episode_rgb
from sim_data.sim.tasks import MAX_EPISODE_STEPS, TASK_NAMES, get_task

ENV_ID = "WMLab/HomeHumanoid-v0"
OBS_MODES = ("dict", "proprio")
IMAGE_SIZE = 64  # the dataset's and the policies' head-camera frames
RENDER_TILE = 16
SEED_LIMIT = 2**32  # jax.random.PRNGKey keeps a seed's low 32 bits only: larger seeds would collide


def seed_key(seed) -> jax.Array:
    """The PRNG key of a Gymnasium seed (an int in [0, 2**32))."""
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < SEED_LIMIT:
        raise ValueError(f"seed must be an int in [0, 2**32), got {seed!r}")
    return jax.random.PRNGKey(int(seed))


def _drawn_key(rng: np.random.Generator) -> jax.Array:
    return jax.random.PRNGKey(int(rng.integers(0, SEED_LIMIT)))


def _where_rows(mask: np.ndarray, new, old):
    """The pytree whose row b (leading axis) is new's where mask (B,) holds, else old's; numpy
    leaves (the cpu engine's state) stay numpy."""
    def pick(a, b):
        xp = np if isinstance(a, np.ndarray) else jnp
        return xp.where(mask.reshape(mask.shape + (1,) * (np.ndim(a) - 1)), a, b)

    return jax.tree_util.tree_map(pick, new, old)


def _render_config(camera: str, height: int, width: int) -> RenderConfig:
    tile = RENDER_TILE if height % RENDER_TILE == 0 and width % RENDER_TILE == 0 else 0
    return RenderConfig(camera=camera, height=height, width=width, tile=tile)


@functools.lru_cache(maxsize=16)
def _frames_of(model, cfg: RenderConfig):
    """Jitted frames(poses, colors) -> (B, H, W, 3) uint8 of one camera of model, shared by
    every environment that draws it: a second `gym.make` (or vector env) reuses the traced and
    compiled renderer instead of tracing it again (jit keeps a program per batch size)."""
    renderer = Renderer(model, cfg)

    def frames(poses, colors):
        return renderer.render_batch(poses, episode_rgb(renderer.geometry, colors))["rgb"]

    return jax.jit(frames)


class _Batch:
    """B simulations of one task (a task chosen per episode) and their Gymnasium observations.

    Args:
      task: the first task's name. batch_size: B. obs: "dict" or "proprio". engine: "cpu" or "mjx".
      heldout: put the held-out plant into the scenes. nthread: threads of the `cpu` engine.
      camera, height, width: what `render()` draws.
    """

    def __init__(self, task: str, batch_size: int, obs: str, engine: str, heldout: bool, nthread: int | None,
                 camera: str, height: int, width: int):
        if obs not in OBS_MODES:
            raise ValueError(f"obs must be one of {', '.join(OBS_MODES)}, got {obs!r}")
        self.task = get_task(task).name
        self.batch_size, self.obs_mode = batch_size, obs
        self._settings = {"engine": engine, "heldout": heldout, "nthread": nthread}
        self._envs: dict[str, HomeEnv] = {}
        env = self.env()
        idx = env.idx.robot
        self.action_space = gym.spaces.Box(idx.action_low, idx.action_high, dtype=np.float32)
        proprio = gym.spaces.Box(-np.inf, np.inf, (R.PROPRIO_DIM,), dtype=np.float32)
        if obs == "dict":
            image = gym.spaces.Box(0, 255, (IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.uint8)
            self.observation_space = gym.spaces.Dict({"image": image, "proprio": proprio})
        else:
            self.observation_space = proprio
        head = RenderConfig(camera=HEAD_CAMERA, height=IMAGE_SIZE, width=IMAGE_SIZE)
        self._frames = {"head": _frames_of(env.model, head), "view": _frames_of(env.model, _render_config(camera, height, width))}

    def env(self) -> HomeEnv:
        """The HomeEnv of the current task (every task's shares one compiled core)."""
        if self.task not in self._envs:
            self._envs[self.task] = HomeEnv(self.task, self.batch_size, **self._settings)
        return self._envs[self.task]

    def set_task(self, name: str) -> None:
        if name not in TASK_NAMES:
            raise ValueError(f"unknown task {name!r}; choose one of {', '.join(TASK_NAMES)}")
        self.task = name

    def reset(self, keys) -> State:
        """B initial states of the current task from one key (split B ways) or keys (B, 2)."""
        return self.env().reset(keys)

    def step(self, state: State, actions) -> State:
        """One control step of every simulation under actions (B, 20)."""
        actions = np.asarray(actions, np.float32)
        if actions.shape != (self.batch_size, R.ACTION_DIM):
            raise ValueError(f"actions must have shape ({self.batch_size}, {R.ACTION_DIM}), got {actions.shape}")
        return self.env().step(state, actions)

    def head_frames(self, state: State) -> np.ndarray:
        """(B, 64, 64, 3) uint8: the head camera as the dataset and the policies see it."""
        return np.array(self._frames["head"](self.env().poses(state), state.task.colors))

    def view_frames(self, state: State) -> np.ndarray:
        """(B, height, width, 3) uint8: `render()`'s camera."""
        return np.array(self._frames["view"](self.env().poses(state), state.task.colors))

    def observe(self, state: State):
        """The batch's observation: {"image": (B, 64, 64, 3) uint8, "proprio": (B, 37) float32} or
        the proprioception (B, 37) alone; fresh arrays, never views of the state."""
        proprio = np.array(state.obs["proprio"], np.float32)
        if self.obs_mode == "proprio":
            return proprio
        return {"image": self.head_frames(state), "proprio": proprio}


class HomeGymEnv(gym.Env):
    """One simulation of one task (see the module doc): `gym.make(ENV_ID, task=..., ...)`.

    Args:
      task: the first episode's task (`reset(options={"task": ...})` changes it).
      render_mode: None or "rgb_array".
      obs: "dict" ({"image": (64, 64, 3) uint8, "proprio": (37,) float32}) or "proprio" ((37,) float32).
      engine: "cpu" (MuJoCo's C engine) or "mjx".
      heldout: put the held-out plant into the scenes.
      width, height, camera: what `render()` draws.
    """

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, task: str = "mug", render_mode: str | None = None, obs: str = "dict", engine: str = "cpu",
                 heldout: bool = False, width: int = 320, height: int = 240, camera: str = "ext_cam"):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self._sim = _Batch(task, 1, obs, engine, heldout, 1, camera, height, width)
        self.action_space = self._sim.action_space
        self.observation_space = self._sim.observation_space
        self._state: State | None = None

    @property
    def task(self) -> str:
        return self._sim.task

    @property
    def episode_steps(self) -> int:
        """Control steps of the current task's episode, where `truncated` is set."""
        return get_task(self._sim.task).episode_steps

    @property
    def state(self) -> State:
        """The simulation's `sim_data.State` (batch of 1): privileged, for scripted policies and checks."""
        if self._state is None:
            raise RuntimeError("call reset() first")
        return self._state

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if options and "task" in options:
            self._sim.set_task(options["task"])
        self._state = self._sim.reset(seed_key(seed) if seed is not None else _drawn_key(self.np_random))
        return self._obs(), {"task": self.task, "success": False}

    def step(self, action):
        """One control step under action (20,) float32: (observation, reward 1.0 where the task's success flag
        holds else 0.0, terminated False, truncated when the episode's time is up, {"task", "success"})."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, np.float32)
        if action.shape != (R.ACTION_DIM,):
            raise ValueError(f"action must have shape ({R.ACTION_DIM},), got {action.shape}")
        self._state = self._sim.step(self._state, action[None])
        success = bool(self._state.success[0])
        truncated = bool(self._state.done[0])
        return self._obs(), float(success), False, truncated, {"task": self.task, "success": success}

    def _obs(self):
        obs = self._sim.observe(self._state)
        return {k: v[0] for k, v in obs.items()} if isinstance(obs, dict) else obs[0]

    def render(self):
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return self._sim.view_frames(self._state)[0]


class HomeVectorEnv(VectorEnv):
    """num_envs simulations of one task on one batched engine (`HomeEnv` of batch num_envs):
    `gym.make_vec(ENV_ID, num_envs=N, vectorization_mode="vector_entry_point", ...)`.

    Spaces are the single env's batched (`batch_space`): observations {"image": (N, 64, 64, 3)
    uint8, "proprio": (N, 37) float32} (or (N, 37)), actions (N, 20). Autoreset is Gymnasium's
    next-step mode (`metadata["autoreset_mode"]`): the step after a simulation's episode ends
    starts its next episode (the action given for it is ignored, its reward is 0, terminated and
    truncated False) while the others step on. Infos: {"success": (N,) bool, "_success": (N,) True}.

    Args:
      num_envs: N.
      task: every simulation's task (`reset(options={"task": ...})` changes it for all).
      render_mode: None or "rgb_array" (`render()` gives a tuple of N frames).
      obs: "dict" or "proprio". engine: "cpu" (default; threaded over the batch) or "mjx".
      heldout: put the held-out plant into the scenes.
      max_episode_steps: truncate no later than this many steps (the registered value, the longest
        task's, by default: then each task's own episode_steps applies).
      width, height, camera: what `render()` draws. nthread: threads of the `cpu` engine.
    """

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 20, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int, task: str = "mug", render_mode: str | None = None, obs: str = "dict",
                 engine: str = "cpu", heldout: bool = False, max_episode_steps: int | None = None,
                 width: int = 320, height: int = 240, camera: str = "ext_cam", nthread: int | None = None):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if max_episode_steps is not None and max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1 or None, got {max_episode_steps}")
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.max_episode_steps = max_episode_steps
        self._sim = _Batch(task, num_envs, obs, engine, heldout, nthread, camera, height, width)
        self.single_observation_space = self._sim.observation_space
        self.single_action_space = self._sim.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._state: State | None = None
        self._autoreset = np.zeros(num_envs, bool)

    @property
    def task(self) -> str:
        return self._sim.task

    @property
    def episode_steps(self) -> int:
        """Control steps after which every simulation is truncated."""
        steps = get_task(self._sim.task).episode_steps
        return steps if self.max_episode_steps is None else min(steps, self.max_episode_steps)

    @property
    def state(self) -> State:
        """The batch's `sim_data.State`: privileged, for scripted policies and checks."""
        if self._state is None:
            raise RuntimeError("call reset() first")
        return self._state

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        """Starts every simulation's episode. seed: one int (the N states of
        `HomeEnv(task, N).reset(PRNGKey(seed))`), or N ints (simulation i starts as
        `HomeGymEnv.reset(seed=seed[i])` does), or None (keys drawn from np_random)."""
        if isinstance(seed, (list, tuple, np.ndarray)):
            if len(seed) != self.num_envs:
                raise ValueError(f"seed has {len(seed)} values for {self.num_envs} environments")
            super().reset()
            self.np_random = np.random.default_rng([int(s) for s in seed])  # autoresets follow every seed
            keys = jnp.stack([jax.random.split(seed_key(s), 1)[0] for s in seed])
        else:
            super().reset(seed=seed)
            keys = seed_key(seed) if seed is not None else _drawn_key(self.np_random)
        if options and "task" in options:
            self._sim.set_task(options["task"])
        self._state = self._sim.reset(keys)
        self._autoreset = np.zeros(self.num_envs, bool)
        return self._sim.observe(self._state), self._info()

    def step(self, actions):
        """One control step of every simulation under actions (N, 20): (observations, rewards (N,) float64,
        terminated (N,) bool, never set, truncated (N,) bool, infos); a simulation whose episode ended on the
        previous step restarts instead (next-step autoreset: its action ignored, reward 0, not truncated)."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        state = self._sim.step(self._state, actions)
        restart = self._autoreset
        if restart.any():
            state = _where_rows(restart, self._sim.reset(_drawn_key(self.np_random)), state)
        self._state = state
        success = np.array(state.success, bool) & ~restart
        truncated = (np.array(state.done, bool) | (np.array(state.step) >= self.episode_steps)) & ~restart
        terminated = np.zeros(self.num_envs, bool)
        self._autoreset = terminated | truncated
        return self._sim.observe(state), success.astype(np.float64), terminated, truncated, self._info()

    def _info(self) -> dict:
        success = np.array(self._state.success, bool)
        return {"success": success, "_success": np.ones(self.num_envs, bool)}

    def render(self):
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return tuple(self._sim.view_frames(self._state))


def register() -> None:
    """Registers ENV_ID with Gymnasium, single and vector entry points (idempotent)."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="sim_data.sim.gym_env:HomeGymEnv",
                     vector_entry_point="sim_data.sim.gym_env:HomeVectorEnv", max_episode_steps=MAX_EPISODE_STEPS)
