"""The humanoid's action and proprioception vectors: the one place their layouts are defined.

Action (20 floats), modelled on the 1X world-model dataset's layout (joint targets, then the
neck, hand closures and the driving command):

| index  | name                         | unit  | range                 |
|--------|------------------------------|-------|-----------------------|
| 0-6    | left arm joint targets       | rad   | actuator ctrlrange    |
|        |  shoulder_pitch, shoulder_roll, shoulder_yaw, elbow, wrist_yaw, wrist_pitch, wrist_roll |
| 7-13   | right arm joint targets      | rad   | same order            |
| 14-15  | neck yaw, neck pitch         | rad   | actuator ctrlrange    |
| 16     | left hand closure            | 1     | 0 open .. 1 closed    |
| 17     | right hand closure           | 1     | 0 open .. 1 closed    |
| 18     | forward speed                | m/s   | [-0.5, 0.5]           |
| 19     | yaw rate                     | rad/s | [-1.0, 1.0]           |

The legs are not jointed: the base glides on the driving command (the legs are rigid geometry, a
choice made for MJX speed, see the README's benchmark notes).

Proprioception (37 floats):

| index  | name                                                        |
|--------|-------------------------------------------------------------|
| 0-15   | joint positions: left arm 7, right arm 7, neck 2            |
| 16-31  | joint velocities, same order                                |
| 32-34  | base velocity in the robot frame: forward, lateral (m/s), yaw rate (rad/s) |
| 35-36  | measured hand closures, left and right (0 open .. 1 closed) |
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

ARM_JOINTS = ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_yaw", "wrist_pitch", "wrist_roll")
SIDES = ("left", "right")
NECK_JOINTS = ("neck_yaw", "neck_pitch")
BASE_JOINTS = ("base_x", "base_y", "base_yaw")
FINGER_OPEN = 0.055  # finger slide (m) at closure 0; closure 1 drives the fingers together
MAX_FORWARD_SPEED = 0.5
MAX_YAW_RATE = 1.0

ACTION_NAMES: tuple[str, ...] = (
    tuple(f"left_{j}" for j in ARM_JOINTS)
    + tuple(f"right_{j}" for j in ARM_JOINTS)
    + NECK_JOINTS
    + ("left_hand_closure", "right_hand_closure", "forward_speed", "yaw_rate")
)
ACTION_DIM = len(ACTION_NAMES)
LEFT_ARM = slice(0, 7)
RIGHT_ARM = slice(7, 14)
ARMS = slice(0, 14)
NECK = slice(14, 16)
HAND_CLOSURE = slice(16, 18)
LEFT_HAND, RIGHT_HAND = 16, 17
DRIVE = slice(18, 20)
FORWARD_SPEED, YAW_RATE = 18, 19

POSED_JOINTS: tuple[str, ...] = ACTION_NAMES[:16]
PROPRIO_NAMES: tuple[str, ...] = (
    tuple(f"pos_{j}" for j in POSED_JOINTS)
    + tuple(f"vel_{j}" for j in POSED_JOINTS)
    + ("base_forward_vel", "base_lateral_vel", "base_yaw_rate", "left_hand_closure", "right_hand_closure")
)
PROPRIO_DIM = len(PROPRIO_NAMES)
PROPRIO_JOINT_POS = slice(0, 16)
PROPRIO_JOINT_VEL = slice(16, 32)
PROPRIO_BASE_VEL = slice(32, 35)
PROPRIO_HAND_CLOSURE = slice(35, 37)

# Actuator order in home.xml: arms (left, right), neck, fingers (left a, b, right a, b), base.
CTRL_ARMS = slice(0, 14)
CTRL_NECK = slice(14, 16)
CTRL_FINGERS = slice(16, 20)
CTRL_BASE = slice(20, 23)
CTRL_DIM = 23


@dataclasses.dataclass(frozen=True)
class RobotIndex:
    """qpos/qvel addresses of the robot's joints in one compiled model (numpy int arrays)."""

    base_qpos: np.ndarray  # (3,) x, y, yaw
    base_qvel: np.ndarray  # (3,)
    posed_qpos: np.ndarray  # (16,) POSED_JOINTS order
    posed_qvel: np.ndarray  # (16,)
    arm_qpos: np.ndarray  # (14,) left then right
    arm_qvel: np.ndarray  # (14,)
    finger_qpos: np.ndarray  # (4,) left a, left b, right a, right b
    action_low: np.ndarray  # (20,)
    action_high: np.ndarray  # (20,)


def robot_index(model) -> RobotIndex:
    """Looks up the robot's joint addresses and the action bounds in an `mujoco.MjModel`."""

    def adr(names, field):
        return np.array([getattr(model.joint(n), field)[0] for n in names], dtype=np.int32)

    fingers = [f"{s}_finger_{f}" for s in SIDES for f in "ab"]
    # joint targets are bounded by their position actuators' ctrlrange (the joints carry no limits)
    low = np.array([model.actuator(n).ctrlrange[0] for n in ACTION_NAMES[:16]] + [0, 0, -MAX_FORWARD_SPEED, -MAX_YAW_RATE])
    high = np.array([model.actuator(n).ctrlrange[1] for n in ACTION_NAMES[:16]] + [1, 1, MAX_FORWARD_SPEED, MAX_YAW_RATE])
    return RobotIndex(
        base_qpos=adr(BASE_JOINTS, "qposadr"),
        base_qvel=adr(BASE_JOINTS, "dofadr"),
        posed_qpos=adr(POSED_JOINTS, "qposadr"),
        posed_qvel=adr(POSED_JOINTS, "dofadr"),
        arm_qpos=adr(ACTION_NAMES[:14], "qposadr"),
        arm_qvel=adr(ACTION_NAMES[:14], "dofadr"),
        finger_qpos=adr(fingers, "qposadr"),
        action_low=low.astype(np.float32),
        action_high=high.astype(np.float32),
    )


def clip_action(action: jnp.ndarray, low, high) -> jnp.ndarray:
    """action (..., 20) with a NaN as 0, then clipped to [low, high] (each (20,))."""
    a = jnp.where(jnp.isnan(action), 0.0, action)
    return jnp.clip(a, jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32))


def applied_action(action: jnp.ndarray, idx: RobotIndex) -> jnp.ndarray:
    """The action (..., 20) as the robot applies it: a NaN as 0, then clipped to [action_low,
    action_high] (the position actuators' control ranges, closures in [0, 1], speeds within
    +-MAX_FORWARD_SPEED and +-MAX_YAW_RATE). Datasets record it and the world model is given it, so
    that a command past a range (a lengthened drive, noise on a joint) reads as what the robot did."""
    return clip_action(action, idx.action_low, idx.action_high)


def action_to_ctrl(action: jnp.ndarray, base_yaw: jnp.ndarray, idx: RobotIndex) -> jnp.ndarray:
    """Maps actions to the 23 actuator controls of home.xml.

    Args:
      action: (B, 20) actions (taken here as applied_action: a NaN as 0, clipped to their ranges).
      base_yaw: (B,) current base heading, to turn the robot-frame driving command into
        world-frame base velocities.
      idx: the model's RobotIndex.
    Returns:
      (B, 23) float controls.
    """
    a = applied_action(action, idx)
    closure = a[..., HAND_CLOSURE]
    finger = (1.0 - closure) * FINGER_OPEN
    fingers = jnp.stack([finger[..., 0], finger[..., 0], finger[..., 1], finger[..., 1]], axis=-1)
    v, w = a[..., FORWARD_SPEED], a[..., YAW_RATE]
    base = jnp.stack([v * jnp.cos(base_yaw), v * jnp.sin(base_yaw), w], axis=-1)
    return jnp.concatenate([a[..., ARMS], a[..., NECK], fingers, base], axis=-1)


def proprioception(qpos: jnp.ndarray, qvel: jnp.ndarray, idx: RobotIndex) -> jnp.ndarray:
    """The proprioception vector (B, 37) from qpos (B, nq) and qvel (B, nv); layout in the module doc."""
    yaw = qpos[..., idx.base_qpos[2]]
    vx, vy, wz = (qvel[..., i] for i in idx.base_qvel)
    fwd = vx * jnp.cos(yaw) + vy * jnp.sin(yaw)
    lat = -vx * jnp.sin(yaw) + vy * jnp.cos(yaw)
    f = qpos[..., idx.finger_qpos]
    closure = 1.0 - jnp.stack([f[..., 0] + f[..., 1], f[..., 2] + f[..., 3]], axis=-1) / (2 * FINGER_OPEN)
    return jnp.concatenate(
        [qpos[..., idx.posed_qpos], qvel[..., idx.posed_qvel], jnp.stack([fwd, lat, wz], axis=-1), closure], axis=-1
    )
