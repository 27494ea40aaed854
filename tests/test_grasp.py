"""The held object predicted from the actions (wm.grasp): the grip site's kinematics against MuJoCo's C
engine, the rule's verdicts on hand-made paths and on the C engine's scripted episodes (the mug, the air
fryer's tray), and its fit."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import scripted

from experiments import evaluate as E
from sim_data.sim import scene as S
from sim_data.sim.env import HomeEnv
from sim_data.sim.robot import RIGHT_HAND
from sim_data.sim.rollout import run_episodes
from sim_data.sim.tasks import CONTROL_DT, MUG_HOLD, MUG_LIFT, dirt_cell_xy, mug_height
from wm import egomotion as EM
from wm import grasp as GR
from wm.fill import FillConfig, init_fill
from wm.geometric import Motion, load_motion, robot_camera

RULE = GR.GraspRule.of([0.5, 0.04, -0.02, 0.02, 0.4, 1.0])


def _mug_start(n=3, seed=0):
    env = HomeEnv("mug", n, engine="cpu")
    return env, env.reset(jax.random.split(jax.random.PRNGKey(seed), n))


def test_the_grip_site_is_where_mujocos_c_kinematics_puts_it():
    """robot_path's grip site at its predicted states equals MuJoCo's C kinematics there to 1e-5, and
    its states are the motion models' (the base and joints rolled by wm.egomotion)."""
    env, state = _mug_start(2)
    camera = robot_camera()
    rng = np.random.default_rng(0)
    actions = rng.uniform(env.idx.robot.action_low, env.idx.robot.action_high, (2, 6, 20)).astype(np.float32)
    base = np.zeros((3, 6))
    base[0, 3], base[2, 4] = 0.05, 0.05
    joints = np.tile([0.5, 0.0, 0.0], (EM.JOINTS, 1))
    path = GR.robot_path(jnp.asarray(base, jnp.float32), jnp.asarray(joints, jnp.float32), state.qpos,
                         state.mocap_pos, actions, camera)
    qpos, grip = np.asarray(path["qpos"]), np.asarray(path["grip"])
    assert qpos.shape == (2, 6, env.model.nq) and grip.shape == (2, 6, 3)
    rolled = EM.roll_joints(joints, np.asarray(state.qpos)[:, env.idx.robot.posed_qpos], actions)
    np.testing.assert_allclose(qpos[..., env.idx.robot.posed_qpos], rolled[:, 1:], atol=1e-5)
    model, data = camera.model, mujoco.MjData(camera.model)
    site = GR.grip_site(camera)
    for b in range(2):
        for t in range(6):
            data.qpos[:] = qpos[b, t]
            data.mocap_pos[:] = np.asarray(state.mocap_pos)[b]
            mujoco.mj_kinematics(model, data)
            np.testing.assert_allclose(grip[b, t], data.site_xpos[site], atol=1e-5)


def _hand_made(state, steps, lift_by, close_at, open_at, beside, swept):
    """A path of `steps` states whose grip site sits on each mug (offset `beside` m in x), closes at
    close_at, rises by lift_by m over ten steps from there and opens at open_at; where `swept`, it
    arrives over the mug only at close_at, from 5 cm away in y."""
    camera = robot_camera()
    _, obj, _ = GR.object_joint("mug", camera)
    qpos = np.repeat(np.asarray(state.qpos)[:, None], steps, 1)
    grip = np.repeat(qpos[:, :, obj:obj + 3].copy(), 1, 0)
    grip[:, :, 0] += np.asarray(beside)[:, None]
    t = np.arange(steps)
    grip[:, :, 2] += np.asarray(lift_by)[:, None] * np.clip((t - close_at) / 10, 0, 1)[None]
    grip[:, :close_at, 1] += 0.05 * np.asarray(swept, float)[:, None]
    closure = np.where((t >= close_at) & (t < np.asarray(open_at)[:, None]), 1.0, 0.0)
    actions = np.zeros((len(qpos), steps, 20), np.float32)
    actions[..., RIGHT_HAND] = closure
    return {"qpos": jnp.asarray(qpos, jnp.float32), "grip": jnp.asarray(grip, jnp.float32)}, actions


def test_the_held_mug_follows_the_grip_and_the_tasks_own_rule_decides():
    """On hand-made paths: a grip that closes on the mug and rises 15 cm lifts it (the task's rule:
    8 cm held for half a second) and succeeds; the same grip opened before half a second above 8 cm
    drops it and fails; one that closes 6 cm beside the mug never holds it, nor one that sweeps onto it
    at 1 m/s as it closes."""
    env, state = _mug_start(4)
    steps, close_at = 60, 10
    above = close_at + int(np.ceil(10 * MUG_LIFT / 0.15))  # the first step 8 cm up
    short = above + int(MUG_HOLD / CONTROL_DT) - 3
    path, actions = _hand_made(state, steps, [0.15] * 4, close_at, [steps, short, steps, steps], [0.0, 0.0, 0.06, 0.0],
                               [False, False, False, True])
    got = GR.held_verdict(RULE, path, actions, state.mocap_pos, state.task, robot_camera(), "mug")
    assert np.asarray(got["held"]).tolist() == [True, True, False, False]
    assert np.asarray(got["success"]).tolist() == [True, False, False, False]
    np.testing.assert_allclose(np.asarray(got["moved"]), [0.15, 0.15, 0.0, 0.0], atol=1e-5)
    slow = GR.GraspRule.of({**RULE.as_dict(), "speed": 1e3})  # with no limit on its speed, the sweep holds it
    assert np.asarray(GR.held_verdict(slow, path, actions, state.mocap_pos, state.task, robot_camera(), "mug")["success"]
                      ).tolist() == [True, False, False, True]
    # the rule's mug starts where the task measures its height: on the counter
    np.testing.assert_allclose(np.asarray(mug_height(state.qpos, S.scene_index(env.model))), 0.0, atol=2e-3)


def _rule_at(*at) -> int:
    """The grid index of the rule at these positions along each field's values (wm.grasp.GRID's order)."""
    return int(np.ravel_multi_index(at, tuple(len(v) for v in GR.GRID.values())))


def test_fit_grasp_rule_takes_the_most_accurate_rule_and_the_middle_of_equals():
    grid = GR.rule_grid()
    outcomes = np.array([True, False, True, False])
    verdicts = np.zeros((len(grid.closure), 4), bool)
    verdicts[_rule_at(0, 0, 0, 0, 0, 0)] = [True, False, True, True]  # 3 of 4
    rule, acc = GR.fit_grasp_rule(verdicts, outcomes)
    assert acc == 0.75 and rule.as_dict() == jax.tree.map(lambda x: x[_rule_at(0, 0, 0, 0, 0, 0)], grid).as_dict()
    # three reaches in a row equally right: the middle one
    for reach in (1, 2, 3):
        verdicts[_rule_at(1, reach, 1, 2, 3, 1)] = outcomes
    rule, acc = GR.fit_grasp_rule(verdicts, outcomes)
    assert acc == 1.0 and rule.as_dict() == jax.tree.map(lambda x: x[_rule_at(1, 2, 1, 2, 3, 1)], grid).as_dict()
    assert rule.as_dict()["reach_xy"] == pytest.approx(GR.GRID["reach_xy"][2])


def test_refine_closure_places_the_threshold_between_the_grid_steps_where_the_outcomes_turn():
    rule = GR.GraspRule.of({"closure": 0.5, "reach_xy": 0.04, "z_low": -0.03, "z_high": 0.03, "speed": 0.4,
                            "release": 0.5})
    variants = GR.closure_variants(rule)
    assert np.allclose(variants.closure, GR.CLOSURE_STEPS) and np.allclose(variants.reach_xy, 0.04)
    assert set(GR.GRID["closure"]) <= set(GR.CLOSURE_STEPS)  # the grid's rule is among its variants
    # episodes whose hands close to these commands hold exactly when the command is 0.43 or more
    closes = np.array([0.2, 0.3, 0.41, 0.46, 0.48, 0.6, 1.0])
    held = closes >= 0.43
    verdicts = np.array([closes >= c for c in GR.CLOSURE_STEPS])
    assert np.mean((closes >= 0.5) == held) < 1.0  # the grid's closure misreads one
    refined, acc = GR.refine_closure(rule, verdicts, held)
    assert acc == 1.0 and refined.as_dict() == {**rule.as_dict(), "closure": pytest.approx(0.45)}
    # outcomes that every closure from 0.35 to 0.55 reads alike: the middle of them
    closes = np.array([0.2, 0.3, 0.6, 1.0])
    verdicts = np.array([closes >= c for c in GR.CLOSURE_STEPS])
    refined, acc = GR.refine_closure(rule, verdicts, closes >= 0.43)
    assert acc == 1.0 and refined.as_dict()["closure"] == pytest.approx(0.45)  # 0.35 to 0.6 tie: the middle


def _scripted_episodes(task: str, batches) -> tuple:
    """Pairs of episodes of the scripted policy in MuJoCo's C engine, one pair a (skills, grips or None,
    seed) of batches: (first states [one a pair], actions (E, T, 20), the joints' recorded positions
    (E, T + 1, 16), the outcomes (E,) bool)."""
    firsts, actions, joints, outcomes = [], [], [], []
    for skill, grip, seed in batches:
        env = HomeEnv(task, 2, engine="cpu")
        pol, params = scripted(env.model, list(skill), grip=None if grip is None else list(grip))
        rng = jax.random.PRNGKey(seed)
        state, traj = run_episodes(env, pol, params, rng, record=True)
        first = env.reset(jax.random.split(rng, 3)[0])
        firsts.append(first)
        actions.append(np.asarray(traj.action))
        q = np.concatenate([np.asarray(first.qpos)[:, None], np.asarray(traj.qpos)], 1)
        joints.append(q[..., env.idx.robot.posed_qpos])
        outcomes.append(np.asarray(state.success))
    return firsts, np.concatenate(actions), np.concatenate(joints), np.concatenate(outcomes)


def _rule_reads(rule, task: str, firsts, actions, joints) -> np.ndarray:
    """(E,) bool: the rule's verdicts on _scripted_episodes' episodes, the joints model fit on them and a
    still base."""
    joint_coef = jnp.asarray(EM.fit_joints(list(joints), list(actions)), jnp.float32)
    still = jnp.zeros((3, 6), jnp.float32)
    return np.concatenate([np.asarray(GR.grasp_success(rule, still, joint_coef, f.qpos, f.mocap_pos, f.task,
                                                       actions[2 * k:2 * k + 2], robot_camera(), task)["success"])
                           for k, f in enumerate(firsts)])


@pytest.fixture(scope="module")
def scripted_mug_episodes():
    """Eight mug episodes of the scripted policy in MuJoCo's C engine, at skills 1.0 and 0.3 and full and
    weak grips (_scripted_episodes')."""
    return _scripted_episodes("mug", [((1.0, 0.3), (1.0, 1.0), 100), ((1.0, 1.0), (0.2, 1.0), 101),
                                      ((0.3, 1.0), (1.0, 0.1), 102), ((1.0, 0.3), (1.0, 1.0), 103)])


def test_the_rule_reads_the_outcomes_of_mujocos_scripted_episodes(scripted_mug_episodes):
    """The states predicted from each episode's first state and actions (a joints model fit on the
    episodes, a still base) with the rule held in hand give the C engine's outcomes in at least 7 of 8
    episodes, among which both outcomes occur."""
    firsts, actions, joints, outcomes = scripted_mug_episodes
    assert outcomes.any() and not outcomes.all()
    assert (_rule_reads(RULE, "mug", firsts, actions, joints) == outcomes).sum() >= 7


TRAY_RULE = GR.GraspRule.of([0.7, 0.08, -0.02, 0.02, 0.4, 1.0])  # as fit on 144 scripted air fryer episodes


def test_the_tray_slides_out_with_the_grip_within_its_range_and_stays_where_the_hand_lets_go():
    """On hand-made paths from air fryer starts: a grip that closes on the handle and draws back 12 cm
    along the slide pulls the tray out 12 cm (the task's rule: 10 cm) and succeeds, and the tray stays
    there when the hand opens and pushes back; one drawn back 5 cm fails; one drawn back 25 cm takes the
    tray to its 16 cm end stop; one that closes 10 cm above the handle never holds it."""
    env = HomeEnv("airfryer", 4, engine="cpu")
    state = env.reset(jax.random.split(jax.random.PRNGKey(1), 4))
    camera = robot_camera()
    at = GR.object_at("airfryer", camera, state.qpos, state.mocap_pos)
    handle, axis = np.asarray(at["handle"]), np.asarray(at["carry"])[..., 0]
    np.testing.assert_allclose(np.asarray(at["coords"]), 0.0, atol=1e-6)  # the tray starts in
    steps, close_at, open_at = 60, 10, 35
    pull = np.array([0.12, 0.05, 0.25, 0.12])
    t = np.arange(steps)
    out = np.clip((t - close_at) / 20, 0, 1)[None] * pull[:, None] - 0.1 * np.clip((t - open_at - 5) / 10, 0, 1)[None]
    grip = handle[:, None] + out[..., None] * axis[:, None]
    grip[3, :, 2] += 0.10
    actions = np.zeros((4, steps, 20), np.float32)
    actions[:, close_at:open_at, RIGHT_HAND] = 1.0
    path = {"qpos": jnp.repeat(state.qpos[:, None], steps, 1), "grip": jnp.asarray(grip, jnp.float32)}
    got = GR.held_verdict(TRAY_RULE, path, actions, state.mocap_pos, state.task, camera, "airfryer")
    assert np.asarray(got["held"]).tolist() == [True, True, True, False]
    np.testing.assert_allclose(np.asarray(got["moved"]), [0.12, 0.05, 0.16, 0.0], atol=1e-5)
    assert np.asarray(got["success"]).tolist() == [True, False, True, False]


CLOTH_RULE = GR.GraspRule.of([0.5, 0.03, -0.03, 0.02, 0.4, 0.5])  # as fit on 156 scripted wipe episodes


def test_the_cloth_wipes_the_cells_it_is_drawn_over_and_lies_where_the_hand_lets_go():
    """On hand-made paths from wipe starts: a grip that takes the cloth by its centre and draws it over
    every dirt cell at its own height wipes the patch (the task's rule: 80% of the cells under the
    cloth on the counter); the same grip let go on the patch's first cell leaves the cloth lying there
    (its cells alone wiped: the hand sweeps on without it); drawn 5 cm above the counter it wipes none."""
    env = HomeEnv("wipe", 3, engine="cpu")
    state = env.reset(jax.random.split(jax.random.PRNGKey(2), 3))
    camera = robot_camera()
    cloth = np.asarray(GR.object_at("wipe", camera, state.qpos, state.mocap_pos)["handle"])
    cells = np.asarray(dirt_cell_xy(state.task.patch))  # (3, 20, 2)
    close_at, per_cell = 5, 2
    steps = close_at + 10 + per_cell * cells.shape[1]
    grip = np.repeat(cloth[:, None], steps, 1)
    over = np.repeat(cells, per_cell, 1)  # each cell held under the cloth's centre for two steps
    grip[:, close_at + 10:, :2] = over
    grip[:, close_at + 1:close_at + 10, :2] = cloth[:, None, :2] + (over[:, :1] - cloth[:, None, :2]) * (
        np.arange(1, 10) / 10)[None, :, None]  # taken where it lies, then brought to the first cell
    grip[2, close_at + 1:, 2] += 0.05
    actions = np.zeros((3, steps, 20), np.float32)
    actions[:, close_at:, RIGHT_HAND] = 1.0
    actions[1, close_at + 10 + per_cell:, RIGHT_HAND] = 0.0
    path = {"qpos": jnp.repeat(state.qpos[:, None], steps, 1), "grip": jnp.asarray(grip, jnp.float32)}
    got = GR.held_verdict(CLOTH_RULE, path, actions, state.mocap_pos, state.task, camera, "wipe")
    assert np.asarray(got["held"]).all()
    assert np.asarray(got["success"]).tolist() == [True, False, False]
    at = np.asarray(got["at"])
    np.testing.assert_allclose(at[1, :2], cells[1, 0], atol=1e-5)  # let go on the first cell, it lies there
    np.testing.assert_allclose(at[:, 2], cloth[:, 2] + [0.0, 0.0, 0.05], atol=1e-5)  # on the counter; the third held up
    np.testing.assert_allclose(at[0, :2], cells[0, -1], atol=1e-5)  # held to the end: under the grip


@pytest.mark.parametrize("task, rule", [("airfryer", TRAY_RULE), ("wipe", CLOTH_RULE)])
def test_the_rule_reads_the_outcomes_of_mujocos_scripted_episodes_of_the_tray_and_the_cloth(task, rule):
    """As for the mug: the object's state predicted from each scripted episode's first state and
    actions (skills 1.0 and 0.4, a joints model fit on the episodes, a still base) gives the C engine's
    outcome in at least 7 of 8 episodes, among which both outcomes occur: the tray pulled out by its
    handle, the cloth drawn over the dirt."""
    firsts, actions, joints, outcomes = _scripted_episodes(task, [((1.0, 0.4), None, 200 + k) for k in range(4)])
    assert outcomes.any() and not outcomes.all()
    assert (_rule_reads(rule, task, firsts, actions, joints) == outcomes).sum() >= 7


def test_a_task_without_an_object_to_grasp_is_refused():
    with pytest.raises(ValueError, match="no object to grasp"):
        GR.object_joint("step_back", robot_camera())


def test_the_evaluator_reads_the_mug_from_the_loops_actions_and_ranks_by_it():
    """experiments.evaluate's geometric read-out of a mug batch is wm.grasp's verdict on the actions the
    policies took in each world model's loop, the mean over the models; with geometric_ranks it is
    the ranked probability too. Without a grasp rule the mug keeps the ranked read-out."""
    keys = E.reset_keys_of(np.array([3, 4]))
    start = E.geometric_start("mug", keys, 16)
    net, params = init_fill(FillConfig(width=4, levels=1), 16)
    joints = np.tile([0.5, 0.0, 0.0], (EM.JOINTS, 1))
    motion = Motion(jnp.zeros((3, 6)), jnp.asarray(joints, jnp.float32), params, net, FillConfig(width=4, levels=1), 16)
    assert set(E.geometric_tasks(motion, {"mug": RULE})) == {"step_back", "mug"}
    assert E.geometric_tasks(motion, {}) == ("step_back",) and E.geometric_tasks(None, {"mug": RULE}) == ()
    first = start[0]
    _, obj, _ = GR.object_joint("mug", robot_camera())
    reach = np.zeros((2, start[1], 20), np.float32)  # the hand closed from the first step, away from the mug
    reach[..., RIGHT_HAND] = 1.0
    got = {"prob": np.array([0.3, 0.6]), "prob_members": np.array([[0.3], [0.6]])}
    cfg = E.make_config("demo", ["geometric_ranks=1", "geometric=x"])
    mine = E.geometric_readout(cfg, "mug", motion, None, None, start, 1, jax.random.PRNGKey(0), got, {"mug": RULE},
                               [reach, reach])
    direct = GR.grasp_success(RULE, motion.base, motion.joints, first.qpos, first.mocap, first.task, reach,
                              robot_camera(), "mug")
    np.testing.assert_array_equal(mine["readout_geometric"], np.asarray(direct["success"], np.float64))
    np.testing.assert_array_equal(mine["prob"], mine["readout_geometric"])
    assert mine["prob_members"].shape == (2, 1)
    assert np.asarray(first.qpos)[:, obj + 2].min() > S.COUNTER_TOP  # the mug stands on the counter
    kept = E.geometric_readout(cfg, "mug", motion, None, None, start, 1, jax.random.PRNGKey(0), got, {}, [reach])
    np.testing.assert_array_equal(kept["readout_geometric"], got["prob"])


def test_motion_models_without_a_fill_serve_the_grasp_alone(tmp_path):
    """A directory where experiments.fill fit the motion models and the grasp rule but no fill (a preset
    whose geometric tasks are grasped ones only) loads with the fill's parts None: the evaluator reads
    the grasped tasks by it and step_back by its world models."""
    joints = np.tile([0.5, 0.0, 0.0], (EM.JOINTS, 1))
    EM.save_egomotion(tmp_path, np.zeros((3, 6)), {}, joints)
    GR.save_grasp(tmp_path, "mug", RULE, {"val_accuracy": 0.9})
    other = GR.GraspRule.of({**RULE.as_dict(), "reach_xy": 0.05})
    GR.save_grasp(tmp_path, "airfryer", other, {})
    motion = load_motion(tmp_path)
    assert motion.fill_net is None and motion.size is None
    np.testing.assert_allclose(np.asarray(motion.joints), joints)
    rules = GR.load_grasp(tmp_path)
    assert rules["mug"].as_dict() == pytest.approx(RULE.as_dict())
    assert rules["airfryer"].as_dict() == pytest.approx(other.as_dict())
    assert E.geometric_tasks(motion, rules) == ("mug", "airfryer")
    assert GR.load_grasp(tmp_path / "none") == {}


def test_a_grasp_file_of_another_form_is_refused(tmp_path):
    (tmp_path / GR.GRASP_JSON).write_text('{"rule": {"closure": 0.5}, "metrics": {}}')
    with pytest.raises(ValueError, match="remove it and run python -m experiments.fill"):
        GR.load_grasp(tmp_path)
