"""The home scene: the MJCF, the named addresses the tasks use, and the scene's fixed geometry.

Layout (world frame, metres; the robot faces +x at the counter):

- kitchen counter: x in [0.5, 1.1], y in [-1.5, 1.0], top at z = 0.9
- air fryer near y = -1.05 (body free on the counter, tray on a 0..0.16 m slide toward the robot)
- cloth near y = -0.62, dirty patch of 4 x 5 cells (4 cm each) centred near (0.64, -0.40)
- mug near (0.64, 0.12); block near (0.62, 0.50); wall shelf board above the counter,
  x in [0.70, 1.00], y in [0.55, 0.95], top at z = 1.10
- arcade cabinet at y in [1.3, 1.8] with three spring buttons (red, green, blue) at x = 0.64,
  y = 1.43, 1.55, 1.67; two cue markers (a yellow sphere for the first, a white cube for the
  second button) show the order to press
- a stool (mocap) that stands behind the robot in `step_back`; a plant (mocap) that appears
  only in held-out scenes
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from pathlib import Path

import mujoco
import numpy as np

from sim_data.sim.robot import RobotIndex, robot_index

MODEL_PATH = Path(__file__).parent / "assets" / "home.xml"

COUNTER_TOP = 0.9
COUNTER_BOX = (0.5, 1.1, -1.5, 1.0)  # x0, x1, y0, y1
ARCADE_BOX = (0.55, 1.05, 1.3, 1.8)
SHELF_BOARD = (0.70, 1.0, 0.55, 0.95, 1.10)  # x0, x1, y0, y1, top z
STOOL_HALF = 0.2
BASE_RADIUS = 0.22  # footprint of the robot's base for the "hit anything" check
MUG_HALF_HEIGHT = 0.05
CLOTH_HALF = (0.05, 0.04, 0.015)
BLOCK_HALF = (0.025, 0.025, 0.045)
DIRT_GRID = (4, 5)  # cells along x, along y
DIRT_CELL = 0.04
BUTTON_PRESSED = -0.007  # button slide (m) below which a button counts as pressed
HIDDEN_Z = -3.0  # mocap props parked under the floor are out of the scene

# Right-arm and left-arm joint angles of the ready pose (ACTION order within an arm).
READY_NECK_PITCH = 0.85  # head tilted down: the counter and hands fill the head camera
READY_ARM = np.array([0.2, 0.0, 0.0, -2.1, 0.0, 1.4, 0.0], dtype=np.float32)


# Geoms whose colour is drawn per episode (TaskState.colors rows: mug, cloth, block, fryer).
COLORED_GEOMS = (("mug", "mug_body", "mug_handle"), ("cloth",), ("block",), ("fryer", "fryer_top"))


def paint(model: mujoco.MjModel, colors) -> None:
    """Writes one episode's colours (4, 3) into a model's geom_rgba (use a copy for rendering)."""
    for names, rgb in zip(COLORED_GEOMS, np.asarray(colors)):
        for n in names:
            model.geom_rgba[model.geom(n).id, :3] = rgb


@dataclasses.dataclass(frozen=True)
class SceneIndex:
    """Addresses of everything tasks and policies read, for one compiled model."""

    robot: RobotIndex
    mug_qpos: int  # free joint: xyz, quat (w, x, y, z)
    cloth_qpos: int
    fryer_qpos: int
    block_qpos: int
    block_qvel: int
    tray_qpos: int
    button_qpos: np.ndarray  # (3,)
    cue_mocap: np.ndarray  # (2,)
    stool_mocap: int
    plant_mocap: int
    dirt_mocap: np.ndarray  # (20,) row-major over DIRT_GRID
    dirt_geom: np.ndarray  # (20,) the cells' geoms, in dirt_mocap's order, each at its body's origin
    grip_site: np.ndarray  # (2,) left, right
    hand_body: np.ndarray  # (2,)
    nq: int
    nv: int
    nmocap: int


def default_mocap_pos(model: mujoco.MjModel) -> np.ndarray:
    """(nmocap, 3) float32 positions of the mocap bodies as authored, in mocap-id order."""
    bodies = np.flatnonzero(model.body_mocapid >= 0)
    return np.asarray(model.body_pos[bodies[np.argsort(model.body_mocapid[bodies])]], np.float32)


def load_model(path: str = str(MODEL_PATH), tray_spring: tuple | None = None) -> mujoco.MjModel:
    """The compiled home scene (cached: one model per path and tray_spring, however they are passed;
    treat it as read-only); with tray_spring (stiffness, centre), the air fryer's tray made two-state
    (with_tray_spring)."""
    return _compiled(str(path), tuple(float(v) for v in tray_spring) if tray_spring else None)


@functools.lru_cache(maxsize=None)
def _compiled(path: str, tray_spring: tuple | None) -> mujoco.MjModel:
    model = mujoco.MjModel.from_xml_path(path)
    return with_tray_spring(model, *tray_spring) if tray_spring else model


def with_tray_spring(model: mujoco.MjModel, stiffness: float, centre: float) -> mujoco.MjModel:
    """A copy of model with the air fryer's tray pushed away from `centre` (m along its slide) by
    `stiffness` (N/m): a negative joint stiffness about centre, an over-centre spring, so that a tray
    let go short of centre falls shut and one pulled past it snaps open against its stop. Its outcome is
    then one of two states centimetres apart, where a plain slide ends wherever the pull left it,
    millimetres either side of a success line that no frame resolves (docs/results.md)."""
    model = copy.copy(model)
    joint = model.joint("fryer_tray")
    low, high = (float(v) for v in model.jnt_range[joint.id])
    if not stiffness > 0:
        raise ValueError(f"tray_spring: the stiffness must be > 0 N/m, got {stiffness}")
    if not low < centre < high:
        raise ValueError(f"tray_spring: the centre must lie inside the tray's travel ({low:g}, {high:g}) m, got {centre}")
    model.jnt_stiffness[joint.id] = -stiffness
    model.qpos_spring[joint.qposadr[0]] = centre
    return model


def dirt_geoms(model: mujoco.MjModel) -> np.ndarray:
    """(20,) int32 geom ids of the dirt cells, row-major over DIRT_GRID. Each must sit at its mocap body's
    origin: the renderer places it at the body's position (sim_data.sim.env.shown_poses)."""
    ids = np.array([model.geom(f"dirt_{i}").id for i in range(DIRT_GRID[0] * DIRT_GRID[1])], dtype=np.int32)
    if np.any(model.geom_pos[ids] != 0):
        raise ValueError("the dirt cells' geoms must sit at their bodies' origins (no pos in home.xml)")
    return ids


def scene_index(model: mujoco.MjModel) -> SceneIndex:
    """Looks up every named address the tasks and policies use."""

    def qadr(name):
        return int(model.joint(name).qposadr[0])

    def mocap(name):
        return int(model.body_mocapid[model.body(name).id])

    return SceneIndex(
        robot=robot_index(model),
        mug_qpos=qadr("mug"),
        cloth_qpos=qadr("cloth"),
        fryer_qpos=qadr("fryer"),
        block_qpos=qadr("block"),
        block_qvel=int(model.joint("block").dofadr[0]),
        tray_qpos=qadr("fryer_tray"),
        button_qpos=np.array([qadr(f"button_{i}") for i in range(3)], dtype=np.int32),
        cue_mocap=np.array([mocap("cue_0"), mocap("cue_1")], dtype=np.int32),
        stool_mocap=mocap("stool"),
        plant_mocap=mocap("plant"),
        dirt_mocap=np.array([mocap(f"dirt_{i}") for i in range(DIRT_GRID[0] * DIRT_GRID[1])], dtype=np.int32),
        dirt_geom=dirt_geoms(model),
        grip_site=np.array([model.site("left_grip").id, model.site("right_grip").id], dtype=np.int32),
        hand_body=np.array([model.body("left_hand").id, model.body("right_hand").id], dtype=np.int32),
        nq=model.nq,
        nv=model.nv,
        nmocap=model.nmocap,
    )


# The scene's state as the robot would describe it: what the world model is taught to track beside the
# frames (wm's `model.scene`). Positions in metres, of each object's frame in the robot base's frame
# (x forward, y left, z up from the floor), so that they follow what the head camera sees move.
SCENE_STATE_NAMES = (
    "base_x", "base_y", "base_cos_yaw", "base_sin_yaw",
    "mug_x", "mug_y", "mug_z", "mug_up",
    "cloth_x", "cloth_y", "cloth_z", "fryer_x", "fryer_y", "fryer_z", "block_x", "block_y", "block_z",
    "stool_x", "stool_y", "stool_z",
    "tray_travel", "button_0", "button_1", "button_2",
)


def _in_base_frame(p, base_xy, cos_yaw, sin_yaw):
    """World points p (..., 3) -> the robot base's frame (..., 3)."""
    dx, dy = p[..., 0] - base_xy[..., 0], p[..., 1] - base_xy[..., 1]
    return np.stack([cos_yaw * dx + sin_yaw * dy, -sin_yaw * dx + cos_yaw * dy, p[..., 2]], axis=-1)


def scene_state(qpos: np.ndarray, mocap_pos: np.ndarray, idx: SceneIndex) -> np.ndarray:
    """The scene's state (..., 24) float32 in SCENE_STATE_NAMES order from qpos (..., nq) and mocap_pos
    (..., nmocap, 3): the base's world position and heading, the mug's, cloth's, fryer's and block's
    positions and the stool's in the base's frame, the mug's uprightness (the z component of its up
    axis: 1 standing, 0 on its side), the fryer tray's and the buttons' slides."""
    qpos, mocap_pos = np.asarray(qpos, np.float64), np.asarray(mocap_pos, np.float64)
    if qpos.shape[-1] != idx.nq or mocap_pos.shape[-2:] != (idx.nmocap, 3):
        raise ValueError(f"qpos (..., {idx.nq}) and mocap_pos (..., {idx.nmocap}, 3) of this scene expected, got "
                         f"{qpos.shape} and {mocap_pos.shape}: recorded with another scene?")
    base = qpos[..., idx.robot.base_qpos]
    c, s = np.cos(base[..., 2]), np.sin(base[..., 2])
    rel = lambda p: _in_base_frame(p, base[..., :2], c, s)  # noqa: E731
    mug = qpos[..., idx.mug_qpos:idx.mug_qpos + 7]
    qx, qy = mug[..., 4], mug[..., 5]
    mug_up = 1.0 - 2.0 * (qx * qx + qy * qy)  # R[2, 2] of the unit quaternion (w, x, y, z)
    parts = [base[..., :2], c[..., None], s[..., None], rel(mug[..., :3]), mug_up[..., None]]
    parts += [rel(qpos[..., a:a + 3]) for a in (idx.cloth_qpos, idx.fryer_qpos, idx.block_qpos)]
    parts += [rel(mocap_pos[..., idx.stool_mocap, :]), qpos[..., [idx.tray_qpos]], qpos[..., idx.button_qpos]]
    return np.concatenate(parts, axis=-1).astype(np.float32)
