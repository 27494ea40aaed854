"""The action and proprioception layouts against the compiled model."""

import jax.numpy as jnp
import numpy as np

from sim_data.sim import robot as R


def test_action_layout_names_real_joints(model):
    assert R.ACTION_DIM == 20 and len(set(R.ACTION_NAMES)) == 20
    for name in R.ACTION_NAMES[:16]:
        assert model.joint(name).type == 3  # hinge
        assert model.actuator(name).ctrllimited  # the actuator bounds the target
    assert R.ACTION_NAMES[R.RIGHT_HAND] == "right_hand_closure"
    assert R.ACTION_NAMES[R.FORWARD_SPEED] == "forward_speed" and R.ACTION_NAMES[R.YAW_RATE] == "yaw_rate"


def test_ctrl_slices_match_actuator_order(model):
    names = [model.actuator(i).name for i in range(model.nu)]
    assert model.nu == R.CTRL_DIM
    assert names[R.CTRL_ARMS] == list(R.ACTION_NAMES[:14])
    assert names[R.CTRL_NECK] == ["neck_yaw", "neck_pitch"]
    assert names[R.CTRL_FINGERS] == ["left_finger_a", "left_finger_b", "right_finger_a", "right_finger_b"]
    assert names[R.CTRL_BASE] == ["base_x", "base_y", "base_yaw"]
    for i in range(model.nu):  # every actuator drives the joint of its own name
        assert model.joint(model.actuator_trnid[i, 0]).name == names[i]


def test_action_to_ctrl_maps_drive_to_world_frame(idx):
    a = np.zeros((1, 20), np.float32)
    a[0, R.ARMS] = 0.04  # inside every arm target's range (the elbow's top is 0.05)
    a[0, R.RIGHT_HAND] = 1.0
    a[0, R.LEFT_HAND] = 0.0
    a[0, R.FORWARD_SPEED] = 0.4
    a[0, R.YAW_RATE] = -0.3
    yaw = np.array([np.pi / 2], np.float32)
    ctrl = np.asarray(R.action_to_ctrl(jnp.asarray(a), jnp.asarray(yaw), idx.robot))
    np.testing.assert_allclose(ctrl[0, R.CTRL_ARMS], 0.04, atol=1e-7)
    np.testing.assert_allclose(ctrl[0, R.CTRL_FINGERS], [R.FINGER_OPEN, R.FINGER_OPEN, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(ctrl[0, R.CTRL_BASE], [0.0, 0.4, -0.3], atol=1e-6)  # facing +y: forward is +y


def test_action_to_ctrl_clips_to_ranges(idx):
    a = np.full((1, 20), 100.0, np.float32)
    ctrl = np.asarray(R.action_to_ctrl(jnp.asarray(a), jnp.zeros(1), idx.robot))
    np.testing.assert_allclose(ctrl[0, R.CTRL_ARMS], idx.robot.action_high[:14], atol=1e-6)
    np.testing.assert_allclose(ctrl[0, R.CTRL_BASE], [R.MAX_FORWARD_SPEED, 0.0, R.MAX_YAW_RATE], atol=1e-6)


def test_proprioception_layout(model, idx):
    qpos = np.array(model.qpos0, np.float32)[None]
    qvel = np.zeros((1, model.nv), np.float32)
    qpos[0, idx.robot.base_qpos[2]] = np.pi / 2  # facing +y
    qvel[0, idx.robot.base_qvel[1]] = 0.3  # moving +y: forward
    qvel[0, idx.robot.base_qvel[2]] = 0.2
    qpos[0, idx.robot.finger_qpos[:2]] = R.FINGER_OPEN  # left hand open
    qpos[0, idx.robot.posed_qpos[7]] = 0.25  # right shoulder pitch
    p = np.asarray(R.proprioception(jnp.asarray(qpos), jnp.asarray(qvel), idx.robot))[0]
    assert p.shape == (R.PROPRIO_DIM,) == (37,)
    np.testing.assert_allclose(p[R.PROPRIO_BASE_VEL], [0.3, 0.0, 0.2], atol=1e-6)
    np.testing.assert_allclose(p[R.PROPRIO_HAND_CLOSURE], [0.0, 1.0], atol=1e-6)
    assert R.PROPRIO_NAMES[7] == "pos_right_shoulder_pitch" and p[7] == np.float32(0.25)
