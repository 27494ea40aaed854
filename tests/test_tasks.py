"""Samplers and success predicates on hand-built states; the task as data in one compiled program."""

import contextlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import scripted
from jax._src.dispatch import BACKEND_COMPILE_EVENT

from sim_data.policies.scripted import ScriptedPolicy
from sim_data.sim import scene as S
from sim_data.sim import tasks as T
from sim_data.sim.env import HomeEnv
from sim_data.sim.rollout import run_episodes


def initial(task, seed=0, batch=1, heldout=False):
    env = HomeEnv(task, batch, engine="cpu", heldout=heldout)
    return env, env.reset(jax.random.PRNGKey(seed))


def update(env, st, qpos, qvel=None):
    qvel = jnp.zeros_like(st.qvel) if qvel is None else qvel
    return T.update_task(st.task, jnp.asarray(qpos), qvel, st.mocap_pos, env.idx)


def test_sampler_is_deterministic_and_in_range():
    env, a = initial("mug", seed=3, batch=8)
    _, b = initial("mug", seed=3, batch=8)
    np.testing.assert_array_equal(np.asarray(a.qpos), np.asarray(b.qpos))
    mug = np.asarray(a.qpos[:, env.idx.mug_qpos : env.idx.mug_qpos + 3])
    assert np.all(np.abs(mug[:, 0] - T.MUG_XY[0]) <= 0.03 + 1e-6) and np.all(np.abs(mug[:, 1] - T.MUG_XY[1]) <= 0.04 + 1e-6)
    np.testing.assert_allclose(mug[:, 2], S.COUNTER_TOP + S.MUG_HALF_HEIGHT, atol=1e-6)
    assert len({tuple(np.round(m, 5)) for m in mug}) == 8  # episodes differ
    cols = np.asarray(a.task.colors)
    assert cols.shape == (8, 4, 3) and cols.min() >= 0.1 and cols.max() <= 0.9
    seq = np.asarray(a.task.sequence)
    assert np.all(seq[:, 0] != seq[:, 1]) and seq.min() >= 0 and seq.max() <= 2


def test_plant_only_in_heldout_scenes():
    env, st = initial("mug")
    _, held = initial("mug", heldout=True)
    assert float(st.mocap_pos[0, env.idx.plant_mocap, 2]) < 0
    assert float(held.mocap_pos[0, env.idx.plant_mocap, 2]) == pytest.approx(S.COUNTER_TOP)


def test_mug_needs_half_a_second_above_8cm():
    env, st = initial("mug")
    q = np.asarray(st.qpos).copy()
    q[0, env.idx.mug_qpos + 2] = S.COUNTER_TOP + S.MUG_HALF_HEIGHT + 0.079
    ts, ok = update(env, st, q)
    assert float(ts.hold[0]) == 0.0 and not bool(ok[0])
    q[0, env.idx.mug_qpos + 2] += 0.002
    for i in range(10):  # 10 control steps of 50 ms = 0.5 s
        ts, ok = update(env, st.replace(task=ts) if i else st, q)
        assert bool(ok[0]) == (i == 9)
    q[0, env.idx.mug_qpos + 2] = 0.95  # put down: success stays (latched)
    ts, ok = update(env, st.replace(task=ts), q)
    assert bool(ok[0]) and float(ts.hold[0]) == 0.0


def test_wipe_counts_cells_under_the_cloth_on_the_counter():
    env, st = initial("wipe")
    q = np.asarray(st.qpos).copy()
    cells = np.asarray(T.dirt_cell_xy(st.task.patch))[0]
    a = env.idx.cloth_qpos
    q[0, a + 3 : a + 7] = [1, 0, 0, 0]
    # centred on a cell: the cloth (10 x 8 cm) covers that cell and its neighbours within 5 / 4 cm
    q[0, a : a + 2] = cells[0]
    ts, _ = update(env, st, q)
    covered = np.abs(cells - cells[0]) <= [0.05 + 1e-6, 0.04 + 1e-6]
    np.testing.assert_array_equal(np.asarray(ts.wiped[0]), covered.all(-1))
    # lifted 1 cm: nothing is wiped
    q[0, a + 2] += 0.01
    q[0, a : a + 2] = cells[-1]
    ts2, _ = update(env, st.replace(task=ts), q)
    np.testing.assert_array_equal(np.asarray(ts2.wiped), np.asarray(ts.wiped))
    # sweep every cell: success at >= 80 %
    q[0, a + 2] -= 0.01
    for c in cells[: int(0.8 * len(cells))]:
        q[0, a : a + 2] = c
        ts, ok = update(env, st.replace(task=ts), q)
    assert float(T.wiped_fraction(ts)[0]) >= 0.8 and bool(ok[0])
    # wiped cells sink out of sight
    z = np.asarray(T.dirt_mocap_z(ts))[0]
    assert np.all(z[np.asarray(ts.wiped[0])] < S.COUNTER_TOP)


def test_airfryer_fails_when_the_body_moves_2cm():
    env, st = initial("airfryer")
    q = np.asarray(st.qpos).copy()
    q[0, env.idx.tray_qpos] = 0.101
    ts, ok = update(env, st, q)
    assert bool(ok[0])
    q[0, env.idx.fryer_qpos] += 0.021
    ts, ok = update(env, st.replace(task=ts), q)
    assert not bool(ok[0])
    q[0, env.idx.fryer_qpos] -= 0.021  # moved back: still a failure
    ts, ok = update(env, st.replace(task=ts), q)
    assert not bool(ok[0]) and bool(ts.failed[0])


def press(env, st, q, button, ts=None):
    q = q.copy()
    q[0, env.idx.button_qpos] = 0.0
    if button is not None:
        q[0, env.idx.button_qpos[button]] = -0.01
    return update(env, st.replace(task=ts) if ts is not None else st, q)


def test_arcade_needs_the_cued_order():
    env, st = initial("arcade", seed=1)
    q = np.asarray(st.qpos)
    first, second = (int(x) for x in np.asarray(st.task.sequence[0]))
    ts, ok = press(env, st, q, first)
    ts, ok = press(env, st, q, first, ts)  # holding it down is one press
    ts, ok = press(env, st, q, None, ts)
    assert int(ts.progress[0]) == 1 and not bool(ok[0])
    ts, ok = press(env, st, q, second, ts)
    assert bool(ok[0])
    ts, ok = press(env, st, q, second)  # wrong first button
    assert bool(ts.failed[0]) and not bool(ok[0])


def test_shelf_needs_the_block_resting_on_the_board():
    env, st = initial("shelf")
    q = np.asarray(st.qpos).copy()
    a = env.idx.block_qpos
    x0, x1, y0, y1, top = S.SHELF_BOARD
    q[0, a : a + 3] = [(x0 + x1) / 2, (y0 + y1) / 2, top + S.BLOCK_HALF[2]]
    _, ok = update(env, st, q)
    assert bool(ok[0])
    moving = np.zeros(st.qvel.shape, np.float32)
    moving[0, env.idx.block_qvel + 2] = -0.2
    _, ok = update(env, st, q, jnp.asarray(moving))
    assert not bool(ok[0])
    q[0, a] = x1 + 0.01
    _, ok = update(env, st, q)
    assert not bool(ok[0])


def test_step_back_distance_and_hits():
    env, st = initial("step_back")
    q = np.asarray(st.qpos).copy()
    b = env.idx.robot.base_qpos
    x0, y0, yaw0 = (float(v) for v in np.asarray(st.task.ref[0, 3:]))
    q[0, b[0]] = x0 - 0.51 * np.cos(yaw0)
    q[0, b[1]] = y0 - 0.51 * np.sin(yaw0)
    ts, ok = update(env, st, q)
    assert bool(ok[0])
    for beyond in (0.49, 0.81):  # outside the band of stopping distances, short or long
        q[0, b[0]], q[0, b[1]] = x0 - beyond * np.cos(yaw0), y0 - beyond * np.sin(yaw0)
        _, ok = update(env, st, q)
        assert not bool(ok[0]), beyond
    stool = np.asarray(st.mocap_pos[0, env.idx.stool_mocap, :2])
    q[0, b[0]], q[0, b[1]] = stool[0] + S.STOOL_HALF + S.BASE_RADIUS - 0.01, stool[1]
    ts, ok = update(env, st.replace(task=ts), q)
    assert bool(ts.failed[0]) and not bool(ok[0])


def progress(env, st, q, ts=None):
    """The task progress after one update from st (or st with task state ts) to qpos q."""
    st = st.replace(task=ts) if ts is not None else st
    ts, ok = update(env, st, q)
    return ts, float(T.task_progress(ts, jnp.asarray(q), st.qvel, st.mocap_pos, env.idx, ok)[0])


def test_progress_measures_each_task_towards_its_success_and_is_one_at_success():
    env, st = initial("mug")
    q = np.asarray(st.qpos).copy()
    q[0, env.idx.mug_qpos + 2] = S.COUNTER_TOP + S.MUG_HALF_HEIGHT + 0.04  # half the lift, no hold yet
    assert progress(env, st, q)[1] == pytest.approx(0.25, abs=1e-5)
    q[0, env.idx.mug_qpos + 2] += 0.05
    ts, p = progress(env, st, q)  # lifted, held one step of 0.05 s
    assert p == pytest.approx(0.5 + 0.5 * 0.05 / 0.5, abs=1e-5)
    for _ in range(9):
        ts, p = progress(env, st, q, ts)
    assert p == 1.0

    env, st = initial("wipe")
    q = np.asarray(st.qpos).copy()
    a = env.idx.cloth_qpos
    q[0, a + 3 : a + 7] = [1, 0, 0, 0]
    ts = None
    for c in np.asarray(T.dirt_cell_xy(st.task.patch))[0][:8]:
        q[0, a : a + 2] = c
        ts, p = progress(env, st, q, ts)
    assert p == pytest.approx(min(1.0, np.asarray(ts.wiped[0]).sum() / 20 / 0.8), abs=1e-6) and 0 < p < 1

    env, st = initial("airfryer")
    q = np.asarray(st.qpos).copy()
    q[0, env.idx.tray_qpos] = 0.05
    ts, p = progress(env, st, q)
    assert p == pytest.approx(0.5, abs=1e-5)
    q[0, env.idx.fryer_qpos] += 0.021  # the body moved: a failure, no progress
    assert progress(env, st, q, ts)[1] == 0.0

    env, st = initial("step_back")
    q = np.asarray(st.qpos).copy()
    b = env.idx.robot.base_qpos
    x0, y0, yaw0 = (float(v) for v in np.asarray(st.task.ref[0, 3:]))
    for back, want in ((0.2, 0.4), (0.6, 1.0), (0.85, 0.0)):  # on the way, inside the band, past it
        q[0, b[0]], q[0, b[1]] = x0 - back * np.cos(yaw0), y0 - back * np.sin(yaw0)
        assert progress(env, st, q)[1] == pytest.approx(want, abs=1e-4), back


def test_unknown_task_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown task 'dance'.*mug"):
        HomeEnv("dance", 1, engine="cpu")


@contextlib.contextmanager
def counted_compiles():
    """Yields a list that collects the duration of every XLA compilation made inside the block."""
    got = []

    def listener(event, duration, **_):
        if event == BACKEND_COMPILE_EVENT:
            got.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield got
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def test_every_task_gets_its_own_station_plant_and_stool_from_its_id():
    for name in T.TASK_NAMES:
        env, st = initial(name, heldout=True)
        assert int(st.task.task_id[0]) == T.TASKS[name].id == T.TASK_NAMES.index(name)
        assert abs(float(st.qpos[0, env.idx.robot.base_qpos[1]]) - T.TASKS[name].station_y) <= 0.03 + 1e-6
        np.testing.assert_allclose(np.asarray(st.mocap_pos[0, env.idx.plant_mocap, :2]), T.TASKS[name].plant_xy)
        stool = np.asarray(st.mocap_pos[0, env.idx.stool_mocap])
        assert (stool[2] == 0.0) == (name == "step_back"), name  # on the floor behind the robot, else hidden


def mug_rule(qpos, idx):
    """(B, T) success of the mug from its rule alone: lifted 8 cm for 10 control steps, latched."""
    lifted = np.asarray(T.mug_lifted(qpos, idx))
    run = np.zeros(lifted.shape, int)
    for t in range(lifted.shape[1]):
        run[:, t] = (run[:, t - 1] + 1 if t else 1) * lifted[:, t]
    return np.maximum.accumulate(run >= 10, axis=1)


def test_one_compiled_episode_serves_every_task_and_keeps_each_tasks_rules():
    """Envs of two tasks share one core; a scripted episode of the second task compiles nothing
    new, and each task's success flags follow its own rule."""
    envs = {name: HomeEnv(name, 2, engine="cpu") for name in ("step_back", "mug")}
    assert envs["mug"].core is envs["step_back"].core
    policies = {name: ScriptedPolicy.create(name, env.model) for name, env in envs.items()}
    assert policies["mug"] == policies["step_back"] and hash(policies["mug"]) == hash(policies["step_back"])
    # the scripts as the data generator runs them: the dataset fixture's compiled rollout
    policy, params = scripted(envs["mug"].model, [1.0, 1.0])
    assert policy.script == policies["mug"]
    rng = jax.random.PRNGKey(5)
    back, traj_back = run_episodes(envs["step_back"], policy, params, rng, record=True)
    with counted_compiles() as compiles:
        mug, traj_mug = run_episodes(envs["mug"], policy, params, rng, record=True)
    assert compiles == [], f"{len(compiles)} compilations for the second task"
    core = envs["mug"].core
    assert traj_mug.success.shape == (2, T.TASKS["mug"].episode_steps) and np.asarray(mug.done).all()
    assert traj_back.success.shape == (2, T.TASKS["step_back"].episode_steps) and np.asarray(back.done).all()
    np.testing.assert_array_equal(np.asarray(traj_mug.success), mug_rule(traj_mug.qpos, core.idx))
    d = np.asarray(T.backward_distance(back.task, traj_back.qpos[:, -1], core.idx))
    assert np.asarray(back.success).all() and np.all((d >= T.STEP_BACK_BAND[0]) & (d <= T.STEP_BACK_BAND[1]))
    assert np.asarray(mug.success).all()


def test_scene_state_is_mujocos_frames_in_the_robots_frame(model, idx, np_rng):
    """Every object's position in the base's frame, the mug's uprightness and the slides, against
    MuJoCo's own kinematics (mj_forward's body positions and orientations) at random poses."""
    data = mujoco.MjData(model)
    for _ in range(3):
        mujoco.mj_resetData(model, data)
        data.qpos[idx.robot.base_qpos] = np_rng.uniform(-1, 1, 3) * [0.5, 0.5, np.pi]
        quat = np_rng.normal(size=4)
        data.qpos[idx.mug_qpos + 3:idx.mug_qpos + 7] = quat / np.linalg.norm(quat)
        data.qpos[idx.tray_qpos], data.qpos[idx.button_qpos] = 0.07, [-0.002, -0.008, 0.0]
        data.mocap_pos[idx.stool_mocap] = [-0.6, 0.1, 0.0]
        mujoco.mj_forward(model, data)
        got = dict(zip(S.SCENE_STATE_NAMES, S.scene_state(data.qpos, data.mocap_pos, idx)))
        base = model.body("base").id
        rot, origin = data.xmat[base].reshape(3, 3), data.xpos[base]
        for name in ("mug", "cloth", "fryer", "block", "stool"):
            want = rot.T @ (data.xpos[model.body(name).id] - origin)
            np.testing.assert_allclose([got[f"{name}_{a}"] for a in "xy"], want[:2], atol=1e-5)
            np.testing.assert_allclose(got[f"{name}_z"], data.xpos[model.body(name).id][2], atol=1e-5)
        np.testing.assert_allclose(got["mug_up"], data.xmat[model.body("mug").id][8], atol=1e-5)
        np.testing.assert_allclose([got["base_cos_yaw"], got["base_sin_yaw"]], rot[:2, 0], atol=1e-6)
        assert (got["tray_travel"], got["button_1"]) == (np.float32(0.07), np.float32(-0.008))
    with pytest.raises(ValueError, match="another scene"):
        S.scene_state(data.qpos[:-1], data.mocap_pos, idx)
