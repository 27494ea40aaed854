"""A policy in the loop of an imagination that moves the robot over a still scene, compiled once.

Where a task's outcome follows from the robot's own motion (step_back: how far the base backed away),
an imagination needs three things right: where the actions take the robot, what its camera then sees,
and that the policy reading those frames acts as it would in the simulator. This one takes each from a
model fit on recorded episodes, and nothing from the simulator after the first state:

- the base's and the actuated joints' motion under the actions (`wm.egomotion`: first-order linear
  models of the driving commands and of the joints' targets);
- the camera's pose at the predicted robot state, by MuJoCo's kinematics (MJX, so under jit);
- the frame there: the first frame carried to that pose through its depth
  (`sim_data.sim.render.reproject`: parallax exact, the robot's own pixels kept in place) and what
  the first frame never showed drawn by a trained generator (`wm.fill`);
- the policy's proprioception: the first state's (`proprio="held"`), or the predicted joints, their
  velocities and the base's velocity, the fingers' closure held (`proprio="predicted"`).

`imagine_robot` runs whole episodes as one `lax.scan` (policy, models and frame size static; the
policy's parameters, the first views and the keys are data), so a batch of states and any policy of
the same structure reuse one program. `load_motion` reads what `experiments.fill` trained.
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
from flax import struct

from sim_data.sim import robot as R
from sim_data.sim import scene as S
from sim_data.sim.engines import make_engine
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import (
    HEAD_CAMERA,
    cached_renderers,
    episode_rgb,
    reproject,
    rides_with_camera,
    riding_pixels,
)
from sim_data.sim.tasks import CONTROL_DT, TaskState, update_task
from wm.egomotion import load_egomotion, step_base, step_joints, wrap_angle
from wm.fill import FILL_JSON, FillConfig, filled, load_fill

PROPRIO_MODES = ("held", "predicted")
PREDICTS = ("step_back",)  # the tasks whose success follows from the base's motion alone


@struct.dataclass
class FirstView:
    """The batch's first state as the imagination starts from it: rgb (B, S, S, 3) uint8, depth (B, S, S)
    float32 metres along the camera axis, rides (B, S, S) bool (the robot's own pixels), pos (B, 3) and
    mat (B, 3, 3) the camera's world pose, qpos (B, nq), mocap (B, nmocap, 3), proprio (B, 37), task
    the TaskState (B, ...) its task's rule advances."""
    rgb: jax.Array
    depth: jax.Array
    rides: jax.Array
    pos: jax.Array
    mat: jax.Array
    qpos: jax.Array
    mocap: jax.Array
    proprio: jax.Array
    task: TaskState


@struct.dataclass
class Motion:
    """The fitted models: base (3, 6) and joints (16, 3) (wm.egomotion), the fill's parameters; its
    net, config and frame size static (None where no fill was trained)."""
    base: jax.Array
    joints: jax.Array
    fill_params: dict
    fill_net: object = struct.field(pytree_node=False)
    fill_cfg: FillConfig = struct.field(pytree_node=False)
    size: int = struct.field(pytree_node=False)


def load_motion(out: Path) -> Motion:
    """The models experiments.fill wrote to out (egomotion.json with joints; fill.json and fill.msgpack
    where it trained a fill: without one, fill_params, fill_net, fill_cfg and size are None, and the
    motion serves wm.grasp, not imagine_robot)."""
    base, joints = load_egomotion(out, joints=True)
    net, params, cfg, size = load_fill(out) if (Path(out) / FILL_JSON).exists() else (None,) * 4
    return Motion(jnp.asarray(base, jnp.float32), jnp.asarray(joints, jnp.float32), params, net, cfg, size)


class RobotCamera:
    """A camera's world pose at robot states no simulation reached, by MJX's kinematics (the `mjx`
    engine's start of an episode, traceable); hashable by identity, so a static argument of jit. One
    per camera (`robot_camera`)."""

    def __init__(self, camera: str = HEAD_CAMERA):
        self.name = camera
        self.model = S.load_model()
        self.cam = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if self.cam < 0:
            raise ValueError(f"unknown camera {camera!r}")
        self.scene = S.scene_index(self.model)
        self.idx = self.scene.robot
        self.fovy = float(self.model.cam_fovy[self.cam])
        self._engine = make_engine("mjx", self.model, 1)  # its init maps over any batch

    def data(self, qpos, mocap):
        """MJX data with every body, geom, site and camera placed at qpos (B, nq), mocap (B, nmocap, 3)."""
        return self._engine.init(qpos, mocap)

    def pose(self, qpos, mocap) -> tuple[jax.Array, jax.Array]:
        """(B, 3) positions and (B, 3, 3) world-from-camera rotations at qpos (B, nq), mocap (B, nmocap, 3)."""
        d = self.data(qpos, mocap)
        return d.cam_xpos[:, self.cam], d.cam_xmat[:, self.cam]


@functools.lru_cache(maxsize=4)
def robot_camera(camera: str = HEAD_CAMERA) -> RobotCamera:
    return RobotCamera(camera)


def robot_start(qpos, idx: R.RobotIndex) -> tuple:
    """The motion models' state at qpos (B, nq): (base (B, 3) x, y, yaw; its last step (B, 3); the actuated
    joints (B, 16); their last step (B, 16)), the steps zero. Traceable."""
    base, joints = qpos[:, jnp.asarray(idx.base_qpos)], qpos[:, jnp.asarray(idx.posed_qpos)]
    return base, jnp.zeros_like(base), joints, jnp.zeros_like(joints)


def step_robot(base_coef, joint_coef, robot: tuple, action) -> tuple:
    """robot_start's state one control step on under action (B, 20) as applied, by the base model
    base_coef (3, 6) and the joints' joint_coef (16, 3) (wm.egomotion). Traceable."""
    base, moved, joints, turned = robot
    base, moved = step_base(base_coef, base, moved, action)
    joints, turned = step_joints(joint_coef, joints, turned, action)
    return base, moved, joints, turned


def posed(qpos, base, joints, idx: R.RobotIndex) -> jax.Array:
    """qpos (B, nq) with the base (B, 3: x, y, yaw) and the actuated joints (B, 16) set; the rest (the
    objects, the fingers) as given. Traceable."""
    return qpos.at[:, jnp.asarray(idx.base_qpos)].set(base).at[:, jnp.asarray(idx.posed_qpos)].set(joints)


def predicted_proprio(joints, joint_step, base_step, closure) -> jax.Array:
    """(B, 37) proprioception of a predicted robot (sim_data.sim.robot.proprioception's layout): joints
    (B, 16), their change over the step (B, 16), the base's displacement in its own frame (B, 3:
    forward, left, turn) over the step, and the fingers' closure (B, 2), held from the first state."""
    return jnp.concatenate([joints, joint_step / CONTROL_DT, base_step / CONTROL_DT, closure], -1)


@functools.partial(jax.jit, static_argnames=("policy", "camera", "steps", "proprio", "keep_frames"))
def imagine_robot(policy, policy_params, motion: Motion, view: FirstView, policy_keys, camera: RobotCamera,
                  steps: int, proprio: str = "held", keep_frames: bool = False) -> dict:
    """`steps` control steps of `policy` (a sim_data policy: init_carry, act) acting on the imagined
    frames from view, its carry started by init_carry(params, {"image", "proprio"} of the first state,
    None, k_init) and step t acting with fold_in(k_act, t), policy_keys = (k_init, k_act), as the
    evaluator seeds a policy in the simulator and in a world model.

    The task's own rule (sim_data.sim.tasks.update_task) runs on the predicted states, the objects held
    where they started: for step_back, the band of distance backed at the end, failed where the base
    came within its radius of an obstacle on the way.

    Returns {"action": (B, T, 20) the actions as applied, "base": (B, T + 1, 3) the predicted base
    poses (x, y, yaw; the first the start's), "qpos": (B, nq) the last predicted state, "success":
    (B,) bool the rule's verdict on the last, and with keep_frames "frames": (B, T, S, S, 3) uint8 the
    frames read after each step}."""
    if proprio not in PROPRIO_MODES:
        raise ValueError(f"proprio must be one of {', '.join(PROPRIO_MODES)}; got {proprio!r}")
    idx = camera.idx
    base_v, posed_v = jnp.asarray(idx.base_qvel), jnp.asarray(idx.posed_qvel)
    qvel0 = jnp.zeros((view.qpos.shape[0], camera.model.nv), jnp.float32)
    k_init, k_act = policy_keys
    closure = view.proprio[:, R.PROPRIO_BASE_VEL.stop:]
    obs = {"image": view.rgb, "proprio": view.proprio}
    carry0 = policy.init_carry(policy_params, obs, None, k_init)
    robot0 = robot_start(view.qpos, idx)

    def body(c, t):
        obs, pc, ts, _, robot = c
        action, pc = policy.act(policy_params, obs, pc, jax.random.fold_in(k_act, t))
        action = R.applied_action(action, idx)
        before = robot[0]
        robot = base, moved, joints, turned = step_robot(motion.base, motion.joints, robot, action)
        qpos = posed(view.qpos, base, joints, idx)
        step = jnp.concatenate([base[:, :2] - before[:, :2], wrap_angle(base[:, 2:] - before[:, 2:])], -1)
        qvel = (qvel0.at[:, base_v].set(step / CONTROL_DT)
                .at[:, posed_v].set(turned / CONTROL_DT))
        ts, success = update_task(ts, qpos, qvel, view.mocap, camera.scene)
        pos, mat = camera.pose(qpos, view.mocap)
        frame, covered = reproject(view.rgb, view.depth, view.rides, view.pos, view.mat, pos, mat, camera.fovy)
        frame = filled(motion.fill_net, motion.fill_params, motion.fill_cfg, frame, covered, pos, mat, camera.fovy)
        seen = view.proprio if proprio == "held" else predicted_proprio(joints, turned, moved, closure)
        out = (action, base, frame if keep_frames else None)
        return ({"image": frame, "proprio": seen}, pc, ts, success, robot), out

    init = (obs, carry0, view.task, jnp.zeros(view.qpos.shape[0], bool), robot0)
    (_, _, _, success, (base, _, joints, _)), (actions, bases, frames) = jax.lax.scan(body, init, jnp.arange(steps))
    qpos = posed(view.qpos, base, joints, idx)
    out = {"action": jnp.swapaxes(actions, 0, 1),
           "base": jnp.concatenate([robot0[0][:, None], jnp.swapaxes(bases, 0, 1)], 1), "qpos": qpos,
           "success": success}
    if keep_frames:
        out["frames"] = jnp.swapaxes(frames, 0, 1)
    return out


def start_view(env: HomeEnv, state, size: int, camera: RobotCamera) -> FirstView:
    """The FirstView of an environment's states (a batch just reset, say): the camera's frame and depth
    at size x size pixels by the project's renderer, the pixels of the robot's own body, the camera's
    pose, the states' qpos, mocap positions and proprioception."""
    (renderer,) = cached_renderers(size, (camera.name,))
    poses = env.poses(state)
    drawn = renderer.render(poses, episode_rgb(renderer.geometry, state.task.colors))
    rides = riding_pixels(rides_with_camera(env.model, camera.name), drawn["geom_id"])
    pos, mat = camera.pose(state.qpos, state.mocap_pos)
    return FirstView(jnp.asarray(drawn["rgb"], jnp.uint8), jnp.asarray(drawn["depth"], jnp.float32),
                     jnp.asarray(rides), pos, mat, jnp.asarray(state.qpos, jnp.float32),
                     jnp.asarray(state.mocap_pos, jnp.float32), jnp.asarray(state.obs["proprio"], jnp.float32),
                     state.task)

