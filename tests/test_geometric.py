"""The robot's motion imagined over the still scene with a policy in the loop (wm.geometric), and the
evaluator's geometric read-out built on it."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import evaluate as E
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import camera_poses
from sim_data.sim.robot import FORWARD_SPEED, PROPRIO_BASE_VEL, YAW_RATE
from sim_data.sim.tasks import CONTROL_DT, STEP_BACK_BAND, backward_distance, base_clearance
from wm import egomotion as EM
from wm import geometric as G
from wm.checkpoint import load_run_config
from wm.fill import FillConfig, init_fill, save_fill

SIZE = 32
# a base that moves 0.05 s of each command a step (no lag), joints that close half their gap a step
BASE = np.zeros((3, 6))
BASE[0, 3], BASE[2, 4] = 0.05, 0.05
JOINTS = np.tile([0.5, 0.0, 0.0], (EM.JOINTS, 1))


@dataclasses.dataclass(frozen=True)
class ReadsItsView:
    """Backs away faster the brighter its frame, turns a little, and sets every joint target to
    params["target"]; with `body`, its forward command also follows the base's forward speed it reads."""
    body: bool = False

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        b = obs["image"].shape[0]
        bright = obs["image"].astype(jnp.float32).mean(axis=(1, 2, 3)) / 255.0
        forward = -0.1 - 0.3 * bright + (0.2 * obs["proprio"][:, PROPRIO_BASE_VEL.start] if self.body else 0.0)
        action = jnp.full((b, 20), params["target"], jnp.float32)
        return action.at[:, FORWARD_SPEED].set(forward).at[:, YAW_RATE].set(0.2), carry + 1


def _motion():
    cfg = FillConfig(width=4, levels=1)
    net, params = init_fill(cfg, SIZE)
    return G.Motion(jnp.asarray(BASE, jnp.float32), jnp.asarray(JOINTS, jnp.float32), params, net, cfg, SIZE)


def _start(n=2, seed=0):
    env = HomeEnv("step_back", n, engine="cpu")
    return env, env.reset(jax.random.split(jax.random.PRNGKey(seed), n))


def test_the_camera_is_placed_where_mujocos_c_kinematics_puts_it():
    """At states no simulation reached (the base moved and turned, the neck and arms at other angles),
    the traced pose of the head camera is the C engine's (render.camera_poses) to 1e-5."""
    env, state = _start()
    qpos = np.array(state.qpos)
    qpos[:, env.idx.robot.base_qpos] += [0.4, -0.3, 0.7]
    qpos[:, env.idx.robot.posed_qpos] += np.linspace(-0.3, 0.3, EM.JOINTS)
    camera = G.robot_camera()
    pos, mat = camera.pose(qpos, state.mocap_pos)
    want_pos, want_mat = camera_poses(env.model, qpos, np.asarray(state.mocap_pos))
    np.testing.assert_allclose(pos, want_pos, atol=1e-5)
    np.testing.assert_allclose(mat, want_mat, atol=1e-5)


def test_the_policy_reads_the_imagined_frames_and_the_robot_moves_as_its_models_say():
    """Each action is the policy's reply to the frame imagined after the step before (the first to
    the first state's frame); the base and joints follow wm.egomotion's models of those actions step
    for step; the frames change as the camera moves; and the task's rule on the predicted base is the
    predicted success."""
    env, state = _start()
    camera = G.robot_camera()
    view = G.start_view(env, state, SIZE, camera)
    policy, steps = ReadsItsView(), 50
    keys = tuple(jax.random.split(jax.random.PRNGKey(1)))
    got = G.imagine_robot(policy, {"target": 0.3}, _motion(), view, keys, camera, steps, keep_frames=True)
    action, base, frames = np.asarray(got["action"]), np.asarray(got["base"]), np.asarray(got["frames"])
    assert action.shape == (2, steps, 20) and base.shape == (2, steps + 1, 3) and frames.shape == (2, steps, SIZE, SIZE, 3)
    seen = np.concatenate([np.asarray(view.rgb)[:, None], frames[:, :-1]], 1).astype(np.float64)
    np.testing.assert_allclose(action[..., FORWARD_SPEED], -0.1 - 0.3 * seen.mean(axis=(2, 3, 4)) / 255.0, atol=1e-5)
    np.testing.assert_allclose(base, EM.roll_base(BASE, np.asarray(view.qpos)[:, env.idx.robot.base_qpos], action),
                               atol=1e-5)
    joints = EM.roll_joints(JOINTS, np.asarray(view.qpos)[:, env.idx.robot.posed_qpos], action)[:, -1]
    np.testing.assert_allclose(np.asarray(got["qpos"])[:, env.idx.robot.posed_qpos], joints, atol=1e-5)
    assert np.abs(frames[:, -1].astype(float) - np.asarray(view.rgb)).mean() > 1.0  # the view moved
    back = np.asarray(backward_distance(state.task, got["qpos"], env.idx))
    assert (back > 0).all()  # it backed away
    path = np.repeat(np.asarray(view.qpos)[:, None], steps + 1, 1)
    path[..., env.idx.robot.base_qpos] = base
    clear = np.asarray(base_clearance(path, np.asarray(state.mocap_pos)[:, None, env.idx.stool_mocap], env.idx))
    band = (back >= STEP_BACK_BAND[0]) & (back <= STEP_BACK_BAND[1])
    np.testing.assert_array_equal(np.asarray(got["success"]), band & (clear[:, 1:] >= 0).all(1))
    assert np.asarray(got["success"]).any(), (back, clear.min(1))  # the rule has a success to tell apart


def test_predicted_proprioception_carries_the_base_speed_of_the_step_before():
    """With proprio="predicted" the policy reads the base's forward speed over the last imagined step
    (the model's displacement over CONTROL_DT), the start's before the first; held, the start's always."""
    env, state = _start(seed=2)
    camera = G.robot_camera()
    view = G.start_view(env, state, SIZE, camera)
    keys = tuple(jax.random.split(jax.random.PRNGKey(3)))
    run = {m: G.imagine_robot(ReadsItsView(body=True), {"target": 0.0}, _motion(), view, keys, camera, 6, m,
                              keep_frames=True) for m in G.PROPRIO_MODES}
    got = run["predicted"]
    frames = np.concatenate([np.asarray(view.rgb)[:, None], np.asarray(got["frames"])[:, :-1]], 1)
    speed = np.concatenate([np.asarray(view.proprio)[:, None, PROPRIO_BASE_VEL.start],
                            EM.displacements(np.asarray(got["base"]))[:, :-1, 0] / CONTROL_DT], 1)
    want = -0.1 - 0.3 * frames.astype(np.float64).mean(axis=(2, 3, 4)) / 255.0 + 0.2 * speed
    np.testing.assert_allclose(np.asarray(got["action"])[..., FORWARD_SPEED], want, atol=1e-4)
    held = np.asarray(run["held"]["action"])[..., FORWARD_SPEED]
    assert not np.allclose(held, np.asarray(got["action"])[..., FORWARD_SPEED], atol=1e-3)
    with pytest.raises(ValueError, match="proprio"):
        G.imagine_robot(ReadsItsView(), {"target": 0.0}, _motion(), view, keys, camera, 2, "sensed")


def test_the_evaluator_refuses_a_geometric_ranking_without_its_models():
    with pytest.raises(ValueError, match="geometric=DIR"):
        E.EvalConfig(policies=("p",), wm="w", geometric_ranks=True).validate()
    with pytest.raises(ValueError, match="geometric_ranks"):
        E.EvalConfig(policies=("p",), wm="w", readout="geometric").validate()


@pytest.mark.slow  # a minute on 2 cores: the smoke world model imagines step_back beside the geometric loop
def test_the_evaluator_reads_step_back_by_the_robots_imagined_motion(smoke_world_model, tmp_path):
    """A plug-in that backs away 2 s at 0.3 m/s: under a base model that moves 0.05 s of the command a
    step it backs 0.6 m, inside the band, in every state, so the geometric read-out is 1 for every
    episode; with geometric_ranks it is the ranked prediction too, and the results say so."""
    size = load_run_config(smoke_world_model)[0].model.size
    motion_dir = tmp_path / "motion"
    cfg = FillConfig(width=4, levels=1)
    save_fill(motion_dir, init_fill(cfg, size)[1], cfg, size, {})
    EM.save_egomotion(motion_dir, BASE, {}, JOINTS)
    base = E.EvalConfig(policies=("examples.plugin_policy:make",), wm=str(smoke_world_model), tasks=("step_back",),
                        episodes=2, batch=2, video_policies=0, decision_episodes=(5,), geometric=str(motion_dir))
    res = E.run(base, tmp_path / "read", progress=False)
    (row,) = res["policies"]
    assert row["pred_rate_readouts"]["geometric"] == 1.0 and row["true_rate"] == 1.0
    assert E.load_task(tmp_path / "read" / "tasks" / "step_back.npz")["readout_geometric"].tolist() == [[1.0, 1.0]]
    assert "readout_geometric" in res["metrics"]["within_task"]
    ranked = E.run(dataclasses.replace(base, geometric_ranks=True), tmp_path / "ranked", progress=False)
    assert ranked["policies"][0]["pred_rate"] == 1.0
    assert ranked["world_model"]["geometric_ranks"] == ["step_back"]
    # ranked by it, the geometric read-out is the world model's column, and the read-out it replaced another
    w = ranked["metrics"]["within_task"]
    assert "readout_geometric" not in w and f"readout_{ranked['world_model']['readout']}" in w
