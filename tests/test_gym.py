"""The Gymnasium environment."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import sim_data  # noqa: F401  (registers the id)
from sim_data import ENV_ID


@pytest.fixture(scope="module")
def env():
    e = gym.make(ENV_ID, task="step_back", render_mode="rgb_array", width=64, height=48)
    yield e
    e.close()


def test_check_env_passes(env):
    check_env(env.unwrapped, skip_render_check=False)


def test_reset_is_seeded_and_task_is_an_option(env):
    a, _ = env.reset(seed=4)
    b, _ = env.reset(seed=4)
    np.testing.assert_array_equal(a, b)
    _, info = env.reset(seed=4, options={"task": "mug"})
    assert info["task"] == "mug"
    with pytest.raises(ValueError, match="unknown task"):
        env.reset(options={"task": "juggle"})


def test_step_back_program_succeeds_and_renders(env):
    obs, _ = env.reset(seed=1, options={"task": "step_back"})
    action = np.zeros(20, np.float32)
    action[:14] = np.concatenate([sim_data.sim.scene.READY_ARM] * 2)
    action[15] = sim_data.sim.scene.READY_NECK_PITCH
    action[18] = -0.3
    success, truncated = False, False
    for t in range(200):
        if t == 40:
            action[18] = 0.0  # 2 s at 0.3 m/s: 0.6 m back
        obs, reward, terminated, truncated, info = env.step(action)
        success = info["success"]
        if truncated:
            break
    assert truncated and success and reward == 1.0
    frame = env.render()
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8 and frame.std() > 5
