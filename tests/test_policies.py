"""Scripted policies: IK converges, skill degrades, programs are well formed."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import scripted

from sim_data.policies.scripted import (
    PROGRAMS,
    Kinematics,
    ScriptedPolicy,
    ScriptOrProgramPolicy,
    action_program,
    ik_step,
    play_params,
    play_program,
)
from sim_data.sim import robot as R
from sim_data.sim import scene as S
from sim_data.sim.env import HomeEnv
from sim_data.sim.rollout import jitted_init, run_episodes
from sim_data.sim.tasks import CONTROL_DT, MAX_EPISODE_STEPS


@pytest.fixture(scope="module")
def kin(model):
    return Kinematics(model)


@pytest.fixture(scope="module")
def right_grip(kin):
    """kin.grip of the right hand, compiled once: run op by op it takes half a minute of dispatch."""
    return jax.jit(lambda qpos: kin.grip(qpos, 1))


def test_kinematics_matches_mujoco(model, kin, right_grip):
    import mujoco

    d = mujoco.MjData(model)
    d.qpos[:] = model.qpos0
    q = np.asarray(kin.idx.robot.arm_qpos)
    d.qpos[q] = np.concatenate([S.READY_ARM, S.READY_ARM])
    mujoco.mj_forward(model, d)
    p, rot, jac = right_grip(jnp.asarray(d.qpos, jnp.float32))
    np.testing.assert_allclose(np.asarray(p), d.site("right_grip").xpos, atol=1e-5)
    np.testing.assert_allclose(np.asarray(rot), d.site("right_grip").xmat.reshape(3, 3), atol=1e-5)
    jacp = np.zeros((3, model.nv))
    jacr = np.zeros((3, model.nv))
    mujoco.mj_jacSite(model, d, jacp, jacr, model.site("right_grip").id)
    dofs = kin.idx.robot.arm_qvel[7:]
    np.testing.assert_allclose(np.asarray(jac), np.concatenate([jacp[:, dofs], jacr[:, dofs]]), atol=1e-5)


def test_ik_reaches_a_hand_down_target(model, kin, right_grip):
    qpos = jnp.asarray(model.qpos0, jnp.float32).at[kin.idx.robot.arm_qpos].set(np.concatenate([S.READY_ARM, S.READY_ARM]))
    target, yaw = jnp.array([0.40, -0.25, 1.0]), 0.3  # a grasp pose in front of the right shoulder
    step = jax.jit(lambda q: ik_step(kin, qpos, q, target, yaw))
    q = qpos[kin.idx.robot.arm_qpos[7:]]
    for _ in range(60):
        q = step(q)
    p, rot, _ = right_grip(qpos.at[kin.idx.robot.arm_qpos[7:]].set(q))
    assert float(jnp.linalg.norm(p - target)) < 2e-3
    assert float(rot[2, 2]) > 0.999  # hand z up => fingers point down
    assert abs(float(jnp.arctan2(rot[1, 0], rot[0, 0])) - yaw) < 1e-2


def test_skill_changes_the_plan_deterministically(model):
    env = HomeEnv("mug", 2, engine="cpu")  # the batch of the other scripted tests here: one compiled plan
    pol = ScriptedPolicy.create("mug", model)
    st = env.reset(jax.random.PRNGKey(0))
    params = {"skill": jnp.array([1.0, 0.2])}
    init = jitted_init(pol)  # run_episodes' compiled plan, not a program of its own
    c1 = init(params, st.obs, st.task, jax.random.PRNGKey(1))
    c2 = init(params, st.obs, st.task, jax.random.PRNGKey(1))
    np.testing.assert_array_equal(np.asarray(c1.pos), np.asarray(c2.pos))
    mug = np.asarray(st.qpos[:, env.idx.mug_qpos : env.idx.mug_qpos + 2])
    grasp = np.asarray(c1.pos[:, -4, :2])  # the mug's keyframe 2 of 6 (the script's last six): at the grasp
    np.testing.assert_allclose(grasp[0], mug[0], atol=1e-6)  # skill 1: exact perception
    assert np.abs(grasp[1] - mug[1]).max() > 1e-4  # skill 0.2: perception noise


@pytest.mark.slow
def test_scripted_arcade_succeeds_at_full_skill_and_actions_are_valid(model):
    env = HomeEnv("arcade", 2, engine="cpu")
    pol = ScriptedPolicy.create("arcade", model)
    st, traj = run_episodes(env, pol, {"skill": jnp.ones(2)}, jax.random.PRNGKey(3), record=True)
    assert np.asarray(st.success).all()
    a = np.asarray(traj.action)
    assert a.shape == (2, env.episode_steps, R.ACTION_DIM)
    assert np.all(a >= env.idx.robot.action_low - 1e-6) and np.all(a <= env.idx.robot.action_high + 1e-6)


@pytest.mark.parametrize("name", PROGRAMS)
def test_action_programs(name, idx):
    a = action_program(name, 60)
    assert a.shape == (60, R.ACTION_DIM) and a.dtype == np.float32
    assert np.all(a >= idx.robot.action_low - 1e-6) and np.all(a <= idx.robot.action_high + 1e-6)
    assert np.abs(np.diff(a, axis=0)).max() > 0 or name == "step_backwards"


def test_action_programs_differ_and_move_the_robot():
    env = HomeEnv("mug", 1, engine="cpu")
    finals = {}
    for name in PROGRAMS:
        st = env.reset(jax.random.PRNGKey(0))
        for a in action_program(name, 40):
            st = env.step(st, a[None])
        finals[name] = np.asarray(st.qpos[0])
    base = env.idx.robot.base_qpos
    assert finals["step_backwards"][base[0]] < finals["reach_mug"][base[0]] - 0.3
    names = list(finals)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            assert np.abs(finals[names[i]] - finals[names[j]]).max() > 0.05


def test_play_is_seeded_smooth_bounded_and_varied(idx):
    low, high = idx.robot.action_low, idx.robot.action_high
    table = play_params(range(40), 100, low, high)["table"]
    assert table.shape == (40, 100, R.ACTION_DIM)
    np.testing.assert_array_equal(play_program(7, 100), play_program(7, 100))
    assert np.all(table >= low - 1e-6) and np.all(table <= high + 1e-6)
    ready = np.concatenate([S.READY_ARM, S.READY_ARM, [0.0, S.READY_NECK_PITCH]])
    np.testing.assert_allclose(table[:, 0, :16], np.broadcast_to(ready, (40, 16)), atol=0.31)  # + an oscillation
    np.testing.assert_array_equal(table[:, 0, R.DRIVE], 0.0)  # starts standing still
    eased = np.stack([play_program(s, 100, "eased") for s in range(20)])
    stepped = np.stack([play_program(s, 100, "stepped") for s in range(20)])
    assert np.abs(np.diff(eased, axis=1)).max() < 0.8  # eased knots: no jumps between control steps
    assert np.abs(np.diff(stepped[:, :, R.DRIVE], axis=1)).max() > 0.1  # stepped ones jump
    moved = np.abs(table - table[:, :1]).max(axis=1)  # (40, 20): how far each action moves in its episode
    for part in (R.LEFT_ARM, R.RIGHT_ARM, R.NECK, R.HAND_CLOSURE, R.DRIVE):
        assert (moved[:, part].max(axis=1) > 0.1).mean() > 0.3  # every part of the action vector is exercised
        assert (moved[:, part].max(axis=1) < 1e-6).mean() > 0.0 or part == R.HAND_CLOSURE  # and sometimes rests
    assert (table[:, :, R.FORWARD_SPEED] < -0.1).any() and (table[:, :, R.FORWARD_SPEED] > 0.1).any()


def test_play_nods_only_where_asked_and_leaves_the_rest_of_the_episode_as_it_was():
    """nod: a 0.5-2 Hz sine of 0.05-0.2 rad on the neck's pitch (and sometimes its yaw) over the play
    episode's own neck, every other action as at nod 0; nod 0 is the play of old, draw for draw."""
    steps, t = 200, np.arange(200) * CONTROL_DT
    yawed = 0
    for seed in range(30):
        plain, nodding = play_program(seed, steps), play_program(seed, steps, nod=1.0)
        np.testing.assert_array_equal(play_program(seed, steps, nod=0.0), plain)
        others = [c for c in range(R.ACTION_DIM) if c not in range(R.NECK.start, R.NECK.stop)]
        np.testing.assert_array_equal(nodding[:, others], plain[:, others])
        added = nodding[:, R.NECK] - plain[:, R.NECK]  # (steps, 2): yaw, pitch
        pitch, yaw = added[:, 1], added[:, 0]
        np.testing.assert_allclose(added[0], 0.0, atol=1e-7)  # the neck starts at the episode's own start
        yawed += bool(np.abs(yaw).max() > 0)
        for wave in (pitch,) + ((yaw,) if np.abs(yaw).max() > 0 else ()):
            # one sine: its least-squares fit at the best frequency of a fine grid leaves nothing behind
            crossings = np.count_nonzero(np.diff(np.sign(wave)) != 0)
            hz = crossings / (2 * t[-1])
            assert 0.4 <= hz <= 2.1 and 0.05 - 1e-6 <= np.abs(wave).max() <= 0.2 + 1e-6
            best = min(np.linalg.lstsq(np.stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)], 1), wave,
                                       rcond=None)[1].sum() for f in np.linspace(0.5, 2.0, 1501))
            assert best < 1e-3 * (wave**2).sum()  # a 0.001 Hz grid leaves a trace; two sines leave a fifth
    assert 5 <= yawed <= 25  # the yaw about half the time
    half = [np.abs(play_program(s, steps, nod=0.5) - play_program(s, steps)).max() > 0 for s in range(60)]
    assert 15 <= sum(half) <= 45


def test_a_nod_stays_inside_the_neck_s_range_as_a_whole_sine(idx):
    """Where a drawn nod would cross the neck's limit its amplitude shrinks to fit, so the clip to the
    action bounds never flattens its crests; the wave stays one sine, the rest of the episode as before."""
    low, high = idx.robot.action_low, idx.robot.action_high
    steps, capped = 100, 0
    for seed in range(200):
        plain, free = play_program(seed, steps), play_program(seed, steps, nod=1.0)
        fitted = play_program(seed, steps, nod=1.0, bounds=(low, high))
        table = play_params([seed], steps, low, high, nod=1.0)["table"][0]
        np.testing.assert_array_equal(table[:, R.NECK], fitted[:, R.NECK])  # nothing left for the clip there
        neck = fitted[:, R.NECK]
        assert np.all(neck >= low[R.NECK] - 1e-6) and np.all(neck <= high[R.NECK] + 1e-6)
        over = np.any(free[:, R.NECK] > high[R.NECK] + 1e-6) or np.any(free[:, R.NECK] < low[R.NECK] - 1e-6)
        capped += bool(over)
        for j in range(2):
            wave, drawn = fitted[:, R.NECK][:, j] - plain[:, R.NECK][:, j], free[:, R.NECK][:, j] - plain[:, R.NECK][:, j]
            if np.abs(drawn).max() > 0:  # the same sine, scaled by the room the knots leave
                scale = np.abs(wave).max() / np.abs(drawn).max()
                np.testing.assert_allclose(wave, scale * drawn, atol=1e-6)
                assert scale == 1.0 or not np.all(neck[:, j] < high[R.NECK][j] - 1e-4) or not np.all(
                    neck[:, j] > low[R.NECK][j] + 1e-4)  # shrunk only as far as a crest meets the limit
    assert capped >= 5  # drawn nods that would have crossed the pitch's 1.2 rad do occur


def test_scripts_and_programs_as_one_policy_act_each_row_as_its_own_kind(model):
    from sim_data.sim.rollout import run_episodes

    # the batch of the scripted tests above (their ScriptedPolicy compile serves), and the data generator's
    # ScriptOrProgramPolicy and table length (tables padded to MAX_EPISODE_STEPS rows): the dataset
    # fixture's compiled rollout
    env = HomeEnv("mug", 2, engine="cpu")
    table = np.stack([action_program("reach_mug", env.episode_steps), action_program("air_guitar", env.episode_steps)])
    both, params = scripted(model, [0.4, 1.0], table=table, program=[False, True])
    assert isinstance(both, ScriptOrProgramPolicy) and params["table"].shape[1] == MAX_EPISODE_STEPS
    rng = jax.random.PRNGKey(5)
    _, mixed = run_episodes(env, both, params, rng, record=True)
    _, alone = run_episodes(env, both.script, {"skill": jnp.array([0.4, 1.0])}, rng, record=True)
    # row 0 is the scripted policy's episode (the same noise from the same rng), row 1 plays its table
    np.testing.assert_array_equal(np.asarray(mixed.action[0]), np.asarray(alone.action[0]))
    np.testing.assert_array_equal(np.asarray(mixed.qpos[0]), np.asarray(alone.qpos[0]))
    np.testing.assert_array_equal(np.asarray(mixed.action[1]), table[1])
    # a batch of programs only (the branch that skips the script) plays the tables
    _, programs = run_episodes(env, both, scripted(model, [1.0, 1.0], table=table, program=[True, True])[1], rng,
                               record=True)
    np.testing.assert_array_equal(np.asarray(programs.action), table)


def test_a_weak_grip_scales_the_scripts_closures_and_the_mug_slips(model):
    from sim_data.sim.rollout import run_episodes

    env = HomeEnv("mug", 2, engine="cpu")  # the batch and policy of the test above: no new compile
    both, params = scripted(model, [1.0, 1.0])
    rng = jax.random.PRNGKey(5)
    firm, full = run_episodes(env, both, params, rng, record=True)
    slack, weak = run_episodes(env, both, scripted(model, [1.0, 1.0], grip=[1.0, 0.3])[1], rng, record=True)
    closure = np.asarray(full.action[:, :, R.RIGHT_HAND])
    assert closure.max() > 0.99  # the script closes the hand fully
    np.testing.assert_array_equal(np.asarray(weak.action[0]), np.asarray(full.action[0]))  # grip 1: as scripted
    np.testing.assert_allclose(np.asarray(weak.action[1, :, R.RIGHT_HAND]), 0.3 * closure[1], atol=1e-6)
    assert bool(np.asarray(firm.success)[1]) and not bool(np.asarray(slack.success)[1])


def test_unknown_program_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown program"):
        action_program("moonwalk", 10)
    with pytest.raises(ValueError, match="style"):
        play_program(0, 10, "wobbly")
