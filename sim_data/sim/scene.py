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
    grip_site: np.ndarray  # (2,) left, right
    hand_body: np.ndarray  # (2,)
    nq: int
    nv: int
    nmocap: int


def default_mocap_pos(model: mujoco.MjModel) -> np.ndarray:
    """(nmocap, 3) float32 positions of the mocap bodies as authored, in mocap-id order."""
    bodies = np.flatnonzero(model.body_mocapid >= 0)
    return np.asarray(model.body_pos[bodies[np.argsort(model.body_mocapid[bodies])]], np.float32)


@functools.lru_cache(maxsize=None)
def load_model(path: str = str(MODEL_PATH)) -> mujoco.MjModel:
    """The compiled home scene (cached: treat it as read-only)."""
    return mujoco.MjModel.from_xml_path(path)


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
        grip_site=np.array([model.site("left_grip").id, model.site("right_grip").id], dtype=np.int32),
        hand_body=np.array([model.body("left_hand").id, model.body("right_hand").id], dtype=np.int32),
        nq=model.nq,
        nv=model.nv,
        nmocap=model.nmocap,
    )
