"""Gymnasium environment over the `cpu` engine: one simulation of one task.

    import gymnasium as gym, sim_data
    env = gym.make("WMLab/HomeHumanoid-v0", task="mug", render_mode="rgb_array")
    obs, info = env.reset(seed=0, options={"task": "wipe"})   # the task can change at reset

Observation: the 37-float proprioception vector (`sim_data.sim.robot`). Action: the 20-float action
vector, bounded by the joint ranges, closures [0, 1], speed +-0.5 m/s, yaw rate +-1 rad/s.
Reward: 1.0 at steps where the task's success flag holds, else 0. `truncated` when the task's
episode time is up; `info["success"]` carries the flag. `render()` draws the external camera with
MuJoCo's OpenGL renderer (`camera="head_cam"` for the egocentric view).
"""

from __future__ import annotations

import copy

import gymnasium as gym
import jax
import mujoco
import numpy as np

from sim_data.sim import robot as R
from sim_data.sim.env import HomeEnv
from sim_data.sim.scene import paint
from sim_data.sim.tasks import TASK_NAMES, get_task

ENV_ID = "WMLab/HomeHumanoid-v0"


class HomeGymEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, task: str = "mug", render_mode: str | None = None, heldout: bool = False,
                 width: int = 320, height: int = 240, camera: str = "ext_cam"):
        get_task(task)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self._heldout, self._size, self._camera = heldout, (height, width), camera
        self._envs: dict[str, HomeEnv] = {}
        self._task = task
        env = self._env()
        idx = env.idx.robot
        self.action_space = gym.spaces.Box(idx.action_low, idx.action_high, dtype=np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (R.PROPRIO_DIM,), dtype=np.float32)
        self._state = None
        self._renderer = None
        self._data = None

    def _env(self) -> HomeEnv:
        if self._task not in self._envs:
            self._envs[self._task] = HomeEnv(self._task, 1, engine="cpu", heldout=self._heldout, nthread=1)
        return self._envs[self._task]

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if options and "task" in options:
            if options["task"] not in TASK_NAMES:
                raise ValueError(f"unknown task {options['task']!r}; choose one of {', '.join(TASK_NAMES)}")
            self._task = options["task"]
        key = jax.random.PRNGKey(int(self.np_random.integers(0, 2**31 - 1)))
        self._state = self._env().reset(key)
        return self._obs(), {"task": self._task, "success": False}

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, np.float32).reshape(1, R.ACTION_DIM)
        self._state = self._env().step(self._state, action)
        success = bool(self._state.success[0])
        truncated = bool(self._state.done[0])
        return self._obs(), float(success), False, truncated, {"task": self._task, "success": success}

    def _obs(self):
        return np.asarray(self._state.obs["proprio"][0], np.float32)

    def render(self):
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        env = self._env()
        if self._renderer is None:
            self._model = copy.deepcopy(env.model)  # painted per episode; the shared model stays as loaded
            self._renderer = mujoco.Renderer(self._model, *self._size)
            self._data = mujoco.MjData(self._model)
        paint(self._model, self._state.task.colors[0])
        self._data.qpos[:] = np.asarray(self._state.qpos[0], np.float64)
        self._data.mocap_pos[:] = np.asarray(self._state.mocap_pos[0], np.float64)
        mujoco.mj_forward(self._model, self._data)
        self._renderer.update_scene(self._data, self._camera)
        return self._renderer.render().copy()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def register() -> None:
    """Registers ENV_ID with Gymnasium (idempotent)."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="sim_data.sim.gym_env:HomeGymEnv", max_episode_steps=None)
