"""The two engines against MuJoCo's C engine and against each other.

Parity, as stated in the README: replaying the actions of a scripted episode, the `mjx` engine
stays within 2e-3 (m or rad) of the `cpu` engine on every qpos entry over a whole `mug`
episode (120 control steps, 1200 physics steps), and the success flags agree.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import scripted
from mujoco import mjx

from sim_data.policies.scripted import ScriptedPolicy
from sim_data.sim import robot as R
from sim_data.sim import scene as S
from sim_data.sim.engines import (
    POSE_FIELDS,
    CpuEngine,
    MjxEngine,
    standalone_free_bodies,
)
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import RenderConfig, Renderer
from sim_data.sim.rollout import (
    SEGMENT,
    _scan_recorded,
    _scan_segment,
    compile_recorded_ahead,
    record_episodes,
    run_episodes,
)
from sim_data.sim.tasks import PHYSICS_SUBSTEPS, TASK_NAMES

PARITY_TOL = 2e-3


@pytest.fixture(scope="module")
def mug_episode():
    env = HomeEnv("mug", 2, engine="cpu")
    pol, params = scripted(env.model, [1.0, 1.0])  # the scripts through the dataset fixture's compiled rollout
    rng = jax.random.PRNGKey(5)
    state, traj = run_episodes(env, pol, params, rng, record=True)
    return env, rng, state, traj


def test_cpu_engine_is_mujoco_c_engine(model, mug_episode):
    """Batched, threaded stepping equals a plain mj_step loop bit for bit."""
    env, rng, _, traj = mug_episode
    k_reset = jax.random.split(rng, 3)[0]
    st = env.reset(k_reset)
    d = mujoco.MjData(model)
    d.qpos[:] = np.asarray(st.physics.rows[1, 1 : 1 + model.nq])
    d.mocap_pos[:] = np.asarray(st.mocap_pos[1], np.float64)
    mujoco.mj_forward(model, d)
    for t in range(5):
        action = np.asarray(traj.action[:, t])
        ctrl = np.asarray(R.action_to_ctrl(jnp.asarray(action), st.qpos[:, env.idx.robot.base_qpos[2]], env.idx.robot))
        d.ctrl[:] = ctrl[1]
        for _ in range(PHYSICS_SUBSTEPS):
            mujoco.mj_step(model, d)
        st = env.step(st, action)
        np.testing.assert_array_equal(np.asarray(st.physics.rows[1, 1 : 1 + model.nq]), d.qpos)


# slow: compiling the MJX step on the CPU takes minutes whatever the episode's length; the C engine's
# test above stays in `make test`
@pytest.mark.slow
def test_mjx_replays_cpu_episode_within_tolerance(mug_episode):
    env, rng, state, traj = mug_episode
    mj = HomeEnv("mug", 2, engine="mjx")
    s = mj.reset(jax.random.split(rng, 3)[0])
    np.testing.assert_allclose(np.asarray(s.qpos), np.asarray(env.reset(jax.random.split(rng, 3)[0]).qpos), atol=1e-6)
    worst, flags = 0.0, []
    for t in range(env.episode_steps):
        s = mj.step(s, traj.action[:, t])
        worst = max(worst, float(np.abs(np.asarray(s.qpos) - np.asarray(traj.qpos[:, t])).max()))
        flags.append(np.asarray(s.success))
    assert worst < PARITY_TOL, f"engines diverged by {worst}"
    np.testing.assert_array_equal(np.stack(flags, 1), np.asarray(traj.success))
    assert np.asarray(state.success).all()  # and the scripted episodes did succeed


@pytest.mark.slow
def test_mjx_init_places_what_forward_places_and_steps_the_same(mug_episode):
    """The engine's init runs only the position stages; poses, and the step after, equal mjx.forward's."""
    _, rng, _, _ = mug_episode
    mj = HomeEnv("mug", 2, engine="mjx")
    eng = mj.engine
    state = mj.reset(jax.random.split(rng, 3)[0])

    def forward(q, mp):  # what the engine's init ran before: the whole forward pass from the sampled state
        return mjx.forward(eng.mx, mjx.make_data(eng.mx, impl="jax").replace(qpos=q, mocap_pos=mp))

    full = jax.jit(jax.vmap(forward))(state.qpos, state.mocap_pos)
    for k in ("qpos", *POSE_FIELDS):
        np.testing.assert_allclose(np.asarray(getattr(state.physics, k)), np.asarray(getattr(full, k)), atol=1e-6)
    action = jnp.zeros((2, R.ACTION_DIM), jnp.float32)
    a, b = mj.step(state, action), mj.step(state.replace(physics=full), action)
    np.testing.assert_array_equal(np.asarray(a.qpos), np.asarray(b.qpos))
    np.testing.assert_array_equal(np.asarray(a.qvel), np.asarray(b.qvel))


@pytest.mark.slow
@pytest.mark.parametrize("task", TASK_NAMES)
def test_closed_loop_success_flags_agree(task):
    b = 2  # XLA:CPU can wedge on the MJX episode scans at larger batches (README, known issues)
    cpu, mj = HomeEnv(task, b, engine="cpu"), HomeEnv(task, b, engine="mjx")
    pol = ScriptedPolicy.create(task, cpu.model)
    params = {"skill": jnp.array([0.2, 1.0])}
    rng = jax.random.PRNGKey(11)
    a, _ = run_episodes(cpu, pol, params, rng)
    m, _ = run_episodes(mj, pol, params, rng)
    np.testing.assert_array_equal(np.asarray(a.success), np.asarray(m.success))


@pytest.mark.slow
def test_mjx_rollout_compiles_once_for_every_task():
    """The compiled segment of SEGMENT control steps that ran one task's episodes runs another's."""
    pol = ScriptedPolicy.create()
    params, rng = {"skill": jnp.ones(1)}, jax.random.PRNGKey(2)
    compiled = []
    for task in ("step_back", "mug"):
        env = HomeEnv(task, 1, engine="mjx")
        state, traj = run_episodes(env, pol, params, rng, record=True)
        compiled.append(_scan_segment._cache_size())
        assert traj.success.shape == (1, env.episode_steps) and env.episode_steps % SEGMENT == 0
        assert np.asarray(state.done).all() and np.asarray(state.success).all(), task
    assert compiled[1] == compiled[0]


@pytest.mark.slow
def test_a_recorded_rollout_compiled_ahead_compiles_once_and_records_the_same_episodes():
    """compile_recorded_ahead alone puts the program in jit's cache (its run from zeros), so the
    episodes' own calls compile nothing more, and they are the episodes recorded without it."""
    env = HomeEnv("mug", 2, engine="mjx")
    pol, params = ScriptedPolicy.create(), {"skill": jnp.ones(2)}
    head = (Renderer(env.model, RenderConfig(camera="head_cam", width=32, height=32)),)
    rng = jax.random.PRNGKey(4)
    k_reset, k_pol, k_act = jax.random.split(rng, 3)  # as record_episodes splits it
    before = _scan_recorded._cache_size()
    compile_recorded_ahead(env, pol, params, head, k_reset, k_pol, k_act).result()
    assert _scan_recorded._cache_size() == before + 1
    _, ahead = record_episodes(env, pol, params, rng, head, steps=SEGMENT, compile_ahead=True)
    _, plain = record_episodes(env, pol, params, rng, head, steps=SEGMENT)
    assert _scan_recorded._cache_size() == before + 1
    for a, b in zip(jax.tree.leaves(ahead), jax.tree.leaves(plain)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


class _Commands:
    """The same command at every step: (20,) params["action"] for every episode of the batch."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        return jnp.broadcast_to(params["action"], (carry.shape[0], R.ACTION_DIM)), carry + 1


def test_a_rollout_records_the_action_the_robot_applied_not_the_one_asked_for(model):
    """A command past its range (driving back at 0.9 m/s, closures of 1.5) or NaN is recorded as the robot
    applies it, a NaN as 0 and the rest clipped, so that a world model trained on the record or given a
    policy's actions in imagination reads what the robot did; the simulation is that of the applied command."""
    idx = R.robot_index(model)
    asked = np.zeros(R.ACTION_DIM, np.float32)
    asked[R.FORWARD_SPEED], asked[R.YAW_RATE] = -0.9, 2.5
    asked[R.HAND_CLOSURE] = 1.5
    asked[R.NECK.start] = np.nan
    applied = np.asarray(R.applied_action(jnp.asarray(asked), idx))
    assert applied[R.FORWARD_SPEED] == -R.MAX_FORWARD_SPEED and applied[R.YAW_RATE] == R.MAX_YAW_RATE
    np.testing.assert_array_equal(applied[R.HAND_CLOSURE], 1.0)
    assert applied[R.NECK.start] == 0.0 and np.isfinite(applied).all()
    env = HomeEnv("step_back", 1, engine="cpu")
    rng = jax.random.PRNGKey(3)
    runs = {}
    for name, action in (("asked", asked), ("applied", applied)):
        runs[name] = run_episodes(env, _Commands(), {"action": jnp.asarray(action)}, rng, record=True)
    for name in runs:
        np.testing.assert_array_equal(np.asarray(runs[name][1].action), np.broadcast_to(applied, (1, env.episode_steps,
                                                                                                   R.ACTION_DIM)))
    np.testing.assert_array_equal(np.asarray(runs["asked"][0].qpos), np.asarray(runs["applied"][0].qpos))
    _, rec = record_episodes(env, _Commands(), {"action": jnp.asarray(asked)}, rng, steps=SEGMENT)
    np.testing.assert_array_equal(np.asarray(rec.action), np.broadcast_to(applied, (1, SEGMENT, R.ACTION_DIM)))


def test_reset_takes_a_typed_key_as_the_raw_key_it_holds():
    """jax.random.key(3) and jax.random.PRNGKey(3), one key or one per episode, draw the same initial
    states; keys for another batch size are refused, saying what reset takes."""
    env = HomeEnv("mug", 2, engine="cpu")
    want = np.asarray(env.reset(jax.random.PRNGKey(3)).qpos)
    for keys in (jax.random.key(3), jax.random.split(jax.random.key(3), 2), jax.random.split(jax.random.PRNGKey(3), 2)):
        np.testing.assert_array_equal(np.asarray(env.reset(keys).qpos), want)
    with pytest.raises(ValueError, match=r"one PRNG key or 2 of them .* got an array of shape \(3, 2\)"):
        env.reset(jax.random.split(jax.random.PRNGKey(0), 3))
    with pytest.raises(ValueError, match=r"one PRNG key or 2 of them .* got typed keys of shape \(3,\)"):
        env.reset(jax.random.split(jax.random.key(0), 3))
    other = env.reset(jax.random.key(3, impl="rbg"))  # another implementation's keys draw their own states
    assert np.isfinite(np.asarray(other.qpos)).all()


def test_unknown_engine_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown engine 'gpu'"):
        HomeEnv("mug", 1, engine="gpu")


def _tumbling_cloth_model(scene: mujoco.MjModel) -> mujoco.MjModel:
    """The scene's cloth alone, falling freely: its box, mass and the scene's timestep and integrator,
    without contacts (a cloth knocked off the counter has nothing to land on)."""
    cloth = scene.body("cloth")
    integrator = mujoco.mjtIntegrator(scene.opt.integrator).name.removeprefix("mjINT_").lower()
    half = " ".join(str(x) for x in S.CLOTH_HALF)
    return mujoco.MjModel.from_xml_string(f"""
<mujoco><option timestep="{scene.opt.timestep}" integrator="{integrator}"/>
<worldbody><body name="cloth" pos="0 0 1"><freejoint/>
<geom type="box" size="{half}" mass="{cloth.mass[0]}" contype="0" conaffinity="0"/></body></worldbody></mujoco>""")


def _set_qvel(engine, physics, qvel):
    """The physics state of either engine with its joint velocities (B, nv) replaced."""
    if engine.name == "mjx":
        return physics.replace(qvel=jnp.asarray(qvel, jnp.float32))
    nq, nv = engine.model.nq, engine.model.nv
    rows = physics.rows.copy()
    rows[:, 1 + nq:1 + nq + nv] = qvel  # mjSTATE_INTEGRATION rows: time, qpos, qvel, ...
    return physics.replace(rows=rows)


@pytest.mark.slow
def test_mjx_tumbling_free_body_stays_finite_and_tracks_the_c_engine(model):
    """A flat, light body tumbling about its intermediate axis (the cloth flung off the counter by
    noisy actions) keeps its angular momentum bounded on MJX as on the C engine, whose implicitfast
    integrates standalone free bodies' gyroscopic term implicitly; integrated explicitly, the tumble
    gains energy at every flip and its state went non-finite within 5 s."""
    mini = _tumbling_cloth_model(model)
    assert standalone_free_bodies(mini) == ((1, 0),)
    b, steps = 2, 100
    omega = np.array([[1.0, 50.0, 1.0], [-4.0, 80.0, 3.0]])  # rad/s, body frame, about the intermediate axis
    qvel = np.concatenate([np.tile([0.5, -0.3, 1.0], (b, 1)), omega], axis=1)
    qpos = np.tile(mini.qpos0, (b, 1))
    ctrl, mocap = np.zeros((b, 0)), np.zeros((b, 0, 3))
    cpu, mj = CpuEngine(mini, b), MjxEngine(mini, b)
    ref = _set_qvel(cpu, cpu.init(qpos, mocap), qvel)
    state = _set_qvel(mj, mj.init(qpos, mocap), qvel)
    advance = jax.jit(mj.advance, static_argnums=3)
    worst_q, worst_v = 0.0, 0.0
    for _ in range(steps):
        ref, q_ref, v_ref = cpu.advance(ref, ctrl, mocap, PHYSICS_SUBSTEPS)
        state, q, v = advance(state, jnp.asarray(ctrl, jnp.float32), jnp.asarray(mocap, jnp.float32), PHYSICS_SUBSTEPS)
        q, v = np.asarray(q), np.asarray(v)
        assert np.isfinite(q).all() and np.isfinite(v).all()
        worst_q = max(worst_q, float(np.abs(q - q_ref).max()))
        worst_v = max(worst_v, float(np.abs(v - v_ref).max()))
    assert worst_q < 0.01 and worst_v < 0.2, (worst_q, worst_v)
    assert np.linalg.norm(v[:, 3:], axis=1).max() <= np.linalg.norm(omega, axis=1).max()


def test_the_two_state_tray_pushes_away_from_its_centre_in_both_engines():
    # an over-centre spring of 300 N/m about 7 cm: 300 x (0.12 - 0.07) = 15 N outward at 12 cm, 300 x
    # (0.03 - 0.07) = -12 N inward at 3 cm; the plain slide has none
    plain, sprung = S.load_model(), S.load_model(tray_spring=(300.0, 0.07))
    tray = sprung.joint("fryer_tray")
    assert plain.jnt_stiffness[tray.id] == 0.0 and sprung is not plain
    assert S.load_model(tray_spring=None) is plain and S.load_model(tray_spring=[300, 0.07]) is sprung  # one each
    passive = jax.jit(lambda m, d: mjx.forward(m, d).qfrc_passive)
    on_mjx = mjx.put_model(sprung)
    for q, force in ((0.12, 15.0), (0.03, -12.0)):
        data = mujoco.MjData(sprung)
        data.qpos[tray.qposadr[0]] = q
        mujoco.mj_forward(sprung, data)
        assert data.qfrc_spring[tray.dofadr[0]] == pytest.approx(force, rel=1e-6)
        assert float(passive(on_mjx, mjx.put_data(sprung, data))[tray.dofadr[0]]) == pytest.approx(
            data.qfrc_passive[tray.dofadr[0]], rel=1e-4, abs=1e-4)
    with pytest.raises(ValueError, match="stiffness must be > 0"):
        S.load_model(tray_spring=(-1.0, 0.07))
    with pytest.raises(ValueError, match="inside the tray's travel"):
        S.load_model(tray_spring=(300.0, 0.2))
