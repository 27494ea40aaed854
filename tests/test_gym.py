"""The Gymnasium environments: the API checker, the observation against the dataset's frames, a
policy's episode through gym.make against the same episode through HomeEnv, the vector env's
batched spaces, autoreset and truncation."""

import dataclasses
import warnings

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import sim_data  # registers the id
from examples.plugin_policy import BackAway
from examples.plugin_policy import make as make_back_away
from sim_data import ENV_ID
from sim_data.policies.bc import BCPolicy, PolicyNetConfig, init_params
from sim_data.sim import robot as R
from sim_data.sim import scene as S
from sim_data.sim.env import HomeEnv
from sim_data.sim.gym_env import IMAGE_SIZE, _where_rows
from sim_data.sim.render import RenderConfig, Renderer, episode_rgb
from sim_data.sim.rollout import record_episodes
from sim_data.sim.tasks import MAX_EPISODE_STEPS, get_task

# check_env's advice that is not a defect here: the action is in physical units (joint targets in
# rad, speed in m/s), the layout the dataset and every policy use, so it is not normalised to
# [-1, 1]; proprioception holds unbounded joint angles and velocities.
ADVISORY = ("we recommend using a symmetric and normalized space", "space minimum value is -infinity",
            "space maximum value is infinity")


@pytest.fixture(scope="module")
def env():
    e = gym.make(ENV_ID, task="step_back", render_mode="rgb_array", width=64, height=48)
    yield e
    e.close()


def _check_quietly(env):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=False)
    serious = [str(w.message) for w in caught if not any(a in str(w.message) for a in ADVISORY)]
    assert not serious, serious


@pytest.mark.slow
def test_check_env_passes_without_serious_warnings(env):
    _check_quietly(env)
    proprio_only = gym.make(ENV_ID, task="mug", obs="proprio")
    _check_quietly(proprio_only)
    assert proprio_only.observation_space.shape == (R.PROPRIO_DIM,)


def test_spaces_and_spec(env):
    space = env.observation_space
    assert isinstance(space, gym.spaces.Dict) and set(space) == {"image", "proprio"}
    assert space["image"].shape == (IMAGE_SIZE, IMAGE_SIZE, 3) and space["image"].dtype == np.uint8
    assert space["proprio"].shape == (R.PROPRIO_DIM,) and space["proprio"].dtype == np.float32
    assert env.action_space.shape == (R.ACTION_DIM,)
    # the TimeLimit that gym.make adds must never cut a task short: the longest task's horizon
    assert env.spec.max_episode_steps == MAX_EPISODE_STEPS == max(get_task(t).episode_steps for t in sim_data.TASK_NAMES)


def test_reset_is_seeded_and_task_is_an_option(env):
    a, _ = env.reset(seed=4)
    b, _ = env.reset(seed=4)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    _, info = env.reset(seed=4, options={"task": "mug"})
    assert info["task"] == "mug" and env.unwrapped.episode_steps == get_task("mug").episode_steps
    # the seed gives HomeEnv's initial state for the same key
    ref = HomeEnv("mug", 1, engine="cpu").reset(jax.random.PRNGKey(4))
    np.testing.assert_array_equal(np.asarray(env.unwrapped.state.qpos), np.asarray(ref.qpos))
    with pytest.raises(ValueError, match="unknown task"):
        env.reset(options={"task": "juggle"})
    with pytest.raises(ValueError, match="seed must be an int"):
        env.reset(seed=2**32)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="obs must be one of"):
        gym.make(ENV_ID, obs="pixels")
    with pytest.raises(ValueError, match="unknown engine"):
        gym.make(ENV_ID, engine="gpu")
    e = gym.make(ENV_ID, task="mug", obs="proprio")
    e.reset(seed=0)
    with pytest.raises(ValueError, match="action must have shape"):
        e.unwrapped.step(np.zeros(7, np.float32))


def test_image_is_the_renderers_head_frame(env):
    obs, _ = env.reset(seed=2, options={"task": "step_back"})
    state = env.unwrapped.state
    head = Renderer(S.load_model(), RenderConfig(camera="head_cam"))
    frame = head.render(HomeEnv("step_back", 1, engine="cpu").poses(state), episode_rgb(head.geometry, state.task.colors))
    np.testing.assert_array_equal(obs["image"], np.asarray(frame["rgb"][0]))
    np.testing.assert_array_equal(obs["proprio"], np.asarray(state.obs["proprio"][0]))


@dataclasses.dataclass(frozen=True)
class PixelBackAway:
    """examples/plugin_policy's BackAway, its neck yaw steered by the frame's mean brightness, so that
    its actions depend on every pixel it is shown."""

    def init_carry(self, params, obs, task_state, rng):
        return BackAway().init_carry(params, obs, task_state, rng)

    def act(self, params, obs, carry, rng):
        action, carry = BackAway().act(params, obs, carry, rng)
        look = 0.4 * (obs["image"].astype(jnp.float32).mean(axis=(1, 2, 3)) / 255.0 - 0.5)
        return action.at[:, R.NECK.start].add(look), carry


@dataclasses.dataclass(frozen=True)
class FirstFrameBackAway:
    """BackAway whose neck yaw holds the first frame's mean brightness: its carry starts from the frame
    it sees at reset, as a policy that remembers its first view would (init_carry reads obs["image"])."""

    def init_carry(self, params, obs, task_state, rng):
        first = obs["image"].astype(jnp.float32).mean(axis=(1, 2, 3)) / 255.0
        return BackAway().init_carry(params, obs, task_state, rng), first

    def act(self, params, obs, carry, rng):
        action, steps = BackAway().act(params, obs, carry[0], rng)
        return action.at[:, R.NECK.start].add(0.4 * (carry[1] - 0.5)), (steps, carry[1])


def _bc_policy():
    """A behaviour-cloning network of the zoo's conv lineage with random weights throughout (the zoo
    initialises its head to zero, which would ignore the frame)."""
    cfg = PolicyNetConfig(encoder="conv", width=8, hidden=32)
    norm = {"proprio_mean": np.zeros(R.PROPRIO_DIM), "proprio_std": np.ones(R.PROPRIO_DIM),
            "action_mean": np.zeros(R.ACTION_DIM), "action_std": np.full(R.ACTION_DIM, 0.3)}
    params = init_params(cfg, jax.random.PRNGKey(5), norm, use_proprio=True)
    head = params["net"]["head"]
    head["kernel"] = 0.05 * jax.random.normal(jax.random.PRNGKey(6), head["kernel"].shape)
    return BCPolicy(cfg), params


@pytest.mark.parametrize("which", ["pixel_back_away", "first_frame", "bc"])
def test_policy_through_gym_make_is_the_homeenv_episode(which):
    """The same seed and policy noise through gym.make and through HomeEnv (record_episodes, as the
    dataset records): byte-equal frames at every step, equal actions and the same success; both give
    init_carry the reset's camera frame."""
    policy, params = {"pixel_back_away": (PixelBackAway(), make_back_away()[1]),
                      "first_frame": (FirstFrameBackAway(), make_back_away()[1])}.get(which) or _bc_policy()
    seed, rng = 11, jax.random.PRNGKey(3)
    head = Renderer(S.load_model(), RenderConfig(camera="head_cam"))
    _, rec = record_episodes(HomeEnv("step_back", 1, engine="cpu"), policy, params, rng, (head,),
                             reset_keys=jax.random.split(jax.random.PRNGKey(seed), 1))

    env = gym.make(ENV_ID, task="step_back")
    obs, _ = env.reset(seed=seed)
    _, k_pol, k_act = jax.random.split(rng, 3)
    batched = lambda o: {k: jnp.asarray(v)[None] for k, v in o.items()}
    carry = jax.jit(policy.init_carry)(params, batched(obs), env.unwrapped.state.task, k_pol)  # as HomeEnv runs it
    act = jax.jit(policy.act)
    frames, actions, truncated, t = [obs["image"]], [], False, 0
    while not truncated:
        action, carry = act(params, batched(obs), carry, jax.random.fold_in(k_act, t))
        obs, reward, terminated, truncated, info = env.step(np.asarray(action[0]))
        frames.append(obs["image"])
        actions.append(np.asarray(action[0]))
        t += 1
    assert t == get_task("step_back").episode_steps and not terminated
    np.testing.assert_array_equal(np.stack(frames), np.asarray(rec.frames["head_cam"][0]))
    # the record holds the actions as the robot applied them (a BC policy's may pass their ranges)
    applied = np.asarray(R.applied_action(jnp.asarray(np.stack(actions)), R.robot_index(S.load_model())))
    np.testing.assert_array_equal(applied, np.asarray(rec.action[0]))
    assert info["success"] == bool(rec.success[0, -1]) and reward == float(info["success"])
    if which == "pixel_back_away":
        assert info["success"]  # backs 0.6 m away: inside step_back's band


def test_step_back_program_succeeds_and_renders(env):
    env.reset(seed=1, options={"task": "step_back"})
    action = np.zeros(20, np.float32)
    action[:14] = np.concatenate([S.READY_ARM] * 2)
    action[15] = S.READY_NECK_PITCH
    action[18] = -0.3
    success, truncated = False, False
    for t in range(200):
        if t == 40:
            action[18] = 0.0  # 2 s at 0.3 m/s: 0.6 m back
        _, reward, _, truncated, info = env.step(action)
        success = info["success"]
        if truncated:
            break
    assert truncated and success and reward == 1.0
    frame = env.render()
    assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8 and frame.std() > 5


def test_truncation_at_each_tasks_own_horizon():
    env = gym.make(ENV_ID, task="step_back", obs="proprio")
    for task in ("step_back", "wipe"):  # 100 and 200 control steps; TimeLimit's 200 cuts neither short
        env.reset(seed=0, options={"task": task})
        steps, truncated = 0, False
        while not truncated:
            _, _, terminated, truncated, _ = env.step(np.zeros(R.ACTION_DIM, np.float32))
            steps += 1
            assert not terminated
        assert steps == get_task(task).episode_steps, task


def _make_vec(n, **kw):
    return gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", **kw)


@pytest.mark.slow
def test_vector_env_spaces_and_seeding():
    single = gym.make(ENV_ID, task="mug")
    envs = _make_vec(2, task="mug")  # the batch of the other vector envs here: their compiled programs
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert envs.single_observation_space == single.observation_space
    assert envs.single_action_space == single.action_space
    assert envs.observation_space["image"].shape == (2, IMAGE_SIZE, IMAGE_SIZE, 3)
    assert envs.observation_space["proprio"].shape == (2, R.PROPRIO_DIM)
    assert envs.action_space.shape == (2, R.ACTION_DIM)
    obs, info = envs.reset(seed=7)
    assert obs in envs.observation_space and info["success"].shape == (2,)
    ref = HomeEnv("mug", 2, engine="cpu").reset(jax.random.PRNGKey(7))
    np.testing.assert_array_equal(np.asarray(envs.unwrapped.state.qpos), np.asarray(ref.qpos))
    # a seed per simulation: simulation i starts as the single env does from seed i
    obs, _ = envs.reset(seed=[5, 6])
    for i, s in enumerate((5, 6)):
        one, _ = single.reset(seed=s)
        np.testing.assert_array_equal(obs["image"][i], one["image"])
        np.testing.assert_array_equal(obs["proprio"][i], one["proprio"])
    obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
    assert obs in envs.observation_space and reward.shape == terminated.shape == truncated.shape == (2,)
    frames = _make_vec(2, task="mug", render_mode="rgb_array", width=64, height=48)
    frames.reset(seed=0)
    assert [f.shape for f in frames.render()] == [(48, 64, 3)] * 2


def test_vector_env_truncates_at_the_horizon_and_autoresets_next_step():
    envs = _make_vec(2, task="step_back", obs="proprio")
    hold = np.tile(sim_data.action_program("step_backwards", 1)[0], (2, 1))
    envs.reset(seed=3)
    first = np.asarray(envs.unwrapped.state.qpos)
    horizon = get_task("step_back").episode_steps
    for t in range(horizon):
        obs, reward, terminated, truncated, info = envs.step(hold)
        assert not terminated.any() and truncated.all() == (t == horizon - 1)
    # next step: both simulations start their next episode; the action is ignored
    obs, reward, terminated, truncated, info = envs.step(hold)
    assert not truncated.any() and not reward.any() and not info["success"].any()
    np.testing.assert_array_equal(np.asarray(envs.unwrapped.state.step), [0, 0])
    restarted = np.asarray(envs.unwrapped.state.qpos)
    assert not np.array_equal(restarted, first)  # new initial states, drawn from the env's np_random
    np.testing.assert_array_equal(obs, np.asarray(envs.unwrapped.state.obs["proprio"]))
    # a cap below the task's horizon, as make_vec's max_episode_steps gives
    capped = _make_vec(2, task="step_back", obs="proprio", max_episode_steps=5)
    capped.reset(seed=0)
    ends = [capped.step(hold)[3].all() for _ in range(6)]
    assert ends == [False] * 4 + [True, False]


def test_row_merge_keeps_each_rows_whole_simulation():
    """Autoreset swaps rows of the batch's state: a merged state must step each row exactly as the
    state it came from steps it (the cpu engine's float64 rows included)."""
    env = HomeEnv("mug", 2, engine="cpu")
    act = np.tile(sim_data.action_program("reach_mug", 1)[0], (2, 1))
    a = env.step(env.reset(jax.random.PRNGKey(0)), act)
    b = env.reset(jax.random.PRNGKey(1))
    mask = np.array([False, True])
    merged = env.step(_where_rows(mask, b, a), act)
    a1, b1 = env.step(a, act), env.step(b, act)
    np.testing.assert_array_equal(np.asarray(merged.qpos[0]), np.asarray(a1.qpos[0]))
    np.testing.assert_array_equal(np.asarray(merged.qpos[1]), np.asarray(b1.qpos[1]))
    np.testing.assert_array_equal(np.asarray(merged.step), [2, 1])


@pytest.mark.slow
def test_vector_env_on_mjx_matches_cpu():
    """The mjx engine behind the same vector env: the same initial states, observations within the
    engines' parity, and autoreset swapping rows of mjx.Data."""
    hold = np.tile(sim_data.action_program("step_backwards", 1)[0], (2, 1))
    out = {}
    for engine in ("cpu", "mjx"):
        envs = _make_vec(2, task="step_back", engine=engine, max_episode_steps=3)
        steps = [envs.reset(seed=3)[0]] + [envs.step(hold)[0] for _ in range(4)]
        out[engine] = steps, np.asarray(envs.unwrapped.state.step)
    (cpu, cpu_step), (mjx, mjx_step) = out["cpu"], out["mjx"]
    np.testing.assert_array_equal(mjx_step, [0, 0])  # truncated at the 3rd step, restarted at the 4th
    np.testing.assert_array_equal(cpu_step, mjx_step)
    for a, b in zip(cpu, mjx):
        np.testing.assert_allclose(a["proprio"], b["proprio"], atol=1e-3)
        assert np.mean(a["image"] != b["image"]) < 0.01
    np.testing.assert_array_equal(cpu[0]["image"], mjx[0]["image"])
    np.testing.assert_array_equal(cpu[4]["image"], mjx[4]["image"])  # autoreset: new initial states, same on both
