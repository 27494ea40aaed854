"""Simulated ground truth: a NEO-like humanoid in a home scene, tasks, two physics engines
(`cpu`: MuJoCo's C engine; `mjx`: MJX), scripted policies and their success tables."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # headless OpenGL for MuJoCo's renderer

from sim_data.util import set_xla_flags  # noqa: E402

# before JAX's backend starts: every command, test and script of the project imports this package, so
# XLA runs with one setting however it is started (python -m, pytest, make)
set_xla_flags()

from sim_data.policies.scripted import PROGRAMS, ScriptedPolicy, action_program  # noqa: E402
from sim_data.sim import robot  # noqa: E402
from sim_data.sim.env import HomeEnv, State  # noqa: E402
from sim_data.sim.gym_env import ENV_ID, register  # noqa: E402
from sim_data.sim.rollout import Trajectory, run_episodes  # noqa: E402
from sim_data.sim.scene import load_model, scene_index  # noqa: E402
from sim_data.sim.tasks import TASK_NAMES, TASKS, get_task  # noqa: E402

register()

__all__ = [
    "ENV_ID", "HomeEnv", "PROGRAMS", "ScriptedPolicy", "State", "TASKS", "TASK_NAMES", "Trajectory",
    "action_program", "get_task", "load_model", "robot", "run_episodes", "scene_index",
]
