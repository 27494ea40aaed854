"""Household tasks: initial-state samplers, task state and success predicates, in JAX.

Every function here is pure `jax.numpy` over batched arrays, so the `cpu` and the `mjx` engines
share one task code path: tasks read only `qpos`/`qvel` (object poses come straight from their
free joints) and write only mocap positions (cue markers, dirt cells, stool, plant).

The task is data: each episode's `TaskState.task_id` (its index in TASK_NAMES) picks its station,
plant spot, stool, update rule, success rule and length, so one compiled program serves every task
(and batches that mix tasks).

Per-episode randomisation (uniform within these ranges; yaw in radians):

| what              | range                                                                   |
|-------------------|-------------------------------------------------------------------------|
| robot base        | station +- 2 cm in x, +- 3 cm in y, yaw +- 0.05                          |
| mug               | (0.64, 0.12) +- (3, 4) cm, yaw +- 0.3                                    |
| cloth             | (0.60, -0.62) +- 2 cm, yaw +- 0.2                                        |
| dirty patch       | centre (0.66, -0.40) +- 2 cm                                             |
| air fryer         | (0.82, -1.05) +- (2, 3) cm                                               |
| block             | (0.62, 0.50) +- 3 cm, yaw +- 0.3                                         |
| button order      | 2 distinct of the 3 buttons, uniformly                                   |
| stool (step_back) | 1.30..1.45 m behind the base, +- 0.25 m sideways                          |
| colours           | mug, cloth, block, fryer: each RGB channel uniform in [0.1, 0.9]         |
| plant             | held-out scenes only: on the counter (or arcade panel) beside the station |
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sim_data.sim import scene as S

TASK_NAMES = ("mug", "wipe", "airfryer", "arcade", "shelf", "step_back")
# the tasks whose success, once met, stays met (the mug's held lift, the wiped share): the others are
# judged on the episode's last step (a tray pushed back, a base driven on past the band, a late press)
LATCHED_TASKS = ("mug", "wipe")
CONTROL_DT = 0.05  # 20 Hz control
PHYSICS_SUBSTEPS = 10  # of the model's 5 ms timestep
NUM_DIRT = S.DIRT_GRID[0] * S.DIRT_GRID[1]

# Nominal positions (world x, y)
MUG_XY = (0.64, 0.12)
CLOTH_XY = (0.60, -0.62)
PATCH_XY = (0.66, -0.40)
FRYER_XY = (0.82, -1.05)
BLOCK_XY = (0.62, 0.50)
BUTTON_XY = ((0.64, 1.43), (0.64, 1.55), (0.64, 1.67))
SHELF_TARGET_XY = (0.77, 0.74)
SHOULDER_Y = 0.245  # right shoulder is this far to the robot's right of the base
BASE_X = 0.25
STEP_BACK_BAND = (0.5, 0.8)  # m behind the start at the episode's end
STOOL_BACK = (1.30, 1.45)  # m from the base's start to the stool's centre
# Success thresholds, shared by the success predicates and the progress that measures towards them
MUG_LIFT = 0.08  # m, the mug's bottom above the counter
MUG_HOLD = 0.5  # s held that high
WIPE_SHARE = 0.8  # of the dirt cells
TRAY_OUT = 0.10  # m of the air fryer's tray travel


@struct.dataclass
class TaskState:
    """Per-episode task state, batched along the leading axis B.

    Attributes:
      time: (B,) seconds since reset.
      hold: (B,) seconds the mug has been held high without interruption.
      achieved: (B,) bool, a latched event (mug held long enough, sequence completed).
      failed: (B,) bool, a latched failure (fryer body moved 2 cm, wrong button, a hit).
      progress: (B,) int, buttons of the sequence pressed so far.
      pressed: (B, 3) bool, buttons pressed at the last step (for edge detection).
      wiped: (B, 20) bool, dirt cells wiped (row-major over 4 x 5 cells).
      sequence: (B, 2) int, the buttons to press, in order.
      ref: (B, 6) fryer body xyz and base x, y, yaw at reset.
      patch: (B, 2) dirty-patch centre.
      colors: (B, 4, 3) RGB of mug, cloth, block, fryer.
      heldout: (B,) bool, the plant is in the scene.
      task_id: (B,) int32, the episode's task: its index in TASK_NAMES.
    """

    time: jax.Array
    hold: jax.Array
    achieved: jax.Array
    failed: jax.Array
    progress: jax.Array
    pressed: jax.Array
    wiped: jax.Array
    sequence: jax.Array
    ref: jax.Array
    patch: jax.Array
    colors: jax.Array
    heldout: jax.Array
    task_id: jax.Array


@dataclasses.dataclass(frozen=True)
class Task:
    """A task: where the robot starts, how long an episode lasts, and what success is."""

    name: str
    episode_seconds: float
    station_y: float  # nominal base y at reset
    plant_xy: tuple  # where the held-out plant stands: beside the station, in view
    update: Callable  # (TaskState, qpos, qvel, mocap_pos, idx) -> TaskState
    success: Callable  # (TaskState, qpos, qvel, mocap_pos, idx) -> (B,) bool

    @property
    def episode_steps(self) -> int:
        return int(round(self.episode_seconds / CONTROL_DT))

    @property
    def id(self) -> int:
        """The task's index in TASK_NAMES: its `TaskState.task_id`."""
        return TASK_NAMES.index(self.name)


def _yaw_quat(yaw):
    return jnp.stack([jnp.cos(yaw / 2), jnp.zeros_like(yaw), jnp.zeros_like(yaw), jnp.sin(yaw / 2)], -1)


def quat_yaw(q):
    """Yaw (B,) of quaternions (B, 4) in MuJoCo's (w, x, y, z) order."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def dirt_cell_xy(patch):
    """(..., 20, 2) centres of the dirt cells of patches centred at (..., 2)."""
    nx, ny = S.DIRT_GRID
    ix, iy = np.meshgrid(np.arange(nx) - (nx - 1) / 2, np.arange(ny) - (ny - 1) / 2, indexing="ij")
    offs = np.stack([ix.ravel(), iy.ravel()], -1) * S.DIRT_CELL
    return patch[..., None, :] + offs


def sample_initial(task_id, key: jax.Array, idx: S.SceneIndex, qpos0: jax.Array, mocap0: jax.Array, heldout: bool):
    """Samples one episode's initial state.

    Args:
      task_id: () int, the task's index in TASK_NAMES (traceable).
      key: a PRNG key.
      idx: scene addresses.
      qpos0: (nq,) the model's qpos0; mocap0: (nmocap, 3) default mocap positions.
      heldout: put the plant into the scene.
    Returns:
      qpos (nq,), mocap_pos (nmocap, 3), TaskState (unbatched leaves).
    """
    k = jax.random.split(key, 12)
    u = lambda kk, lo, hi, shape=(): jax.random.uniform(kk, shape, minval=lo, maxval=hi)
    r = idx.robot
    qpos = jnp.asarray(qpos0, jnp.float32)
    task_id = jnp.asarray(task_id, jnp.int32)
    station = jnp.stack([jnp.float32(BASE_X), jnp.asarray(STATION_Y)[task_id], jnp.float32(0.0)])
    base = station + u(k[0], -1, 1, (3,)) * jnp.array([0.02, 0.03, 0.05])
    qpos = qpos.at[r.base_qpos].set(base)
    ready = np.concatenate([S.READY_ARM, S.READY_ARM])
    qpos = qpos.at[r.arm_qpos].set(ready)
    qpos = qpos.at[r.posed_qpos[15]].set(S.READY_NECK_PITCH)
    qpos = qpos.at[r.finger_qpos].set(0.03)

    def place(q, adr, xy, z, yaw):
        q = q.at[adr : adr + 3].set(jnp.array([xy[0], xy[1], z]))
        return q.at[adr + 3 : adr + 7].set(_yaw_quat(yaw))

    mug_xy = jnp.array(MUG_XY) + u(k[1], -1, 1, (2,)) * jnp.array([0.03, 0.04])
    qpos = place(qpos, idx.mug_qpos, mug_xy, S.COUNTER_TOP + S.MUG_HALF_HEIGHT, u(k[2], -0.3, 0.3))
    cloth_xy = jnp.array(CLOTH_XY) + u(k[3], -0.02, 0.02, (2,))
    qpos = place(qpos, idx.cloth_qpos, cloth_xy, S.COUNTER_TOP + S.CLOTH_HALF[2], u(jax.random.fold_in(k[3], 1), -0.2, 0.2))
    fryer_xy = jnp.array(FRYER_XY) + u(k[4], -1, 1, (2,)) * jnp.array([0.02, 0.03])
    qpos = place(qpos, idx.fryer_qpos, fryer_xy, S.COUNTER_TOP + 0.15, jnp.zeros(()))
    block_xy = jnp.array(BLOCK_XY) + u(k[5], -0.03, 0.03, (2,))
    qpos = place(qpos, idx.block_qpos, block_xy, S.COUNTER_TOP + S.BLOCK_HALF[2], u(k[6], -0.3, 0.3))

    first = jax.random.randint(k[7], (), 0, 3)
    second = (first + jax.random.randint(k[8], (), 1, 3)) % 3
    sequence = jnp.stack([first, second])
    patch = jnp.array(PATCH_XY) + u(k[9], -0.02, 0.02, (2,))

    mocap = jnp.asarray(mocap0, jnp.float32)
    buttons = jnp.array(BUTTON_XY)
    for i in range(2):
        cue = jnp.concatenate([buttons[sequence[i]] + jnp.array([0.075, 0.0]), jnp.array([S.COUNTER_TOP + 0.02])])
        mocap = mocap.at[idx.cue_mocap[i]].set(cue)
    cells = dirt_cell_xy(patch)
    mocap = mocap.at[idx.dirt_mocap].set(jnp.concatenate([cells, jnp.full((NUM_DIRT, 1), S.COUNTER_TOP + 0.0005)], -1))
    back, side = u(k[10], STOOL_BACK[0], STOOL_BACK[1]), u(k[11], -0.25, 0.25)
    c, s = jnp.cos(base[2]), jnp.sin(base[2])
    behind = jnp.stack([base[0] - back * c - side * s, base[1] - back * s + side * c, jnp.float32(0.0)])
    stool = jnp.where(task_id == TASK_NAMES.index("step_back"), behind, jnp.array([-1.5, 2.6, S.HIDDEN_Z]))
    mocap = mocap.at[idx.stool_mocap].set(stool)
    plant_z = S.COUNTER_TOP if heldout else S.HIDDEN_Z
    mocap = mocap.at[idx.plant_mocap].set(jnp.append(jnp.asarray(PLANT_XY)[task_id], jnp.float32(plant_z)))

    colors = u(jax.random.fold_in(key, 99), 0.1, 0.9, (4, 3))
    ts = TaskState(
        time=jnp.zeros(()), hold=jnp.zeros(()), achieved=jnp.zeros((), bool), failed=jnp.zeros((), bool),
        progress=jnp.zeros((), jnp.int32), pressed=jnp.zeros((3,), bool), wiped=jnp.zeros((NUM_DIRT,), bool),
        sequence=sequence, ref=jnp.concatenate([jnp.concatenate([fryer_xy, jnp.array([S.COUNTER_TOP + 0.15])]), base]),
        patch=patch, colors=colors, heldout=jnp.asarray(heldout), task_id=task_id,
    )
    return qpos, mocap, ts


def dirt_mocap_z(ts: TaskState):
    """(B, 20) heights of the dirt cells: wiped cells sink 1 cm into the counter, out of sight."""
    return jnp.where(ts.wiped, S.COUNTER_TOP - 0.01, S.COUNTER_TOP + 0.0005)


def _tick(ts):
    return ts.replace(time=ts.time + CONTROL_DT)


# ---- mug: lift at least 8 cm above the counter and hold for 0.5 s -----------------------------
def mug_height(qpos, idx):
    """(B,) m of the mug's bottom above the counter top."""
    return qpos[..., idx.mug_qpos + 2] - S.MUG_HALF_HEIGHT - S.COUNTER_TOP


def mug_lifted(qpos, idx):
    """(B,) bool: the mug's bottom is at least 8 cm above the counter top."""
    return qpos[..., idx.mug_qpos + 2] - S.MUG_HALF_HEIGHT >= S.COUNTER_TOP + MUG_LIFT


def _mug_update(ts, qpos, qvel, mocap, idx):
    hold = jnp.where(mug_lifted(qpos, idx), ts.hold + CONTROL_DT, 0.0)
    return _tick(ts.replace(hold=hold, achieved=ts.achieved | (hold >= MUG_HOLD - 1e-6)))


def _latched(ts, qpos, qvel, mocap, idx):
    return ts.achieved & ~ts.failed


# ---- wipe: wipe at least 80% of the dirty patch ------------------------------------------------
def cloth_cover(qpos, patch, idx):
    """(B, 20) bool: dirt cells under the cloth while the cloth lies on the counter."""
    c = qpos[..., idx.cloth_qpos : idx.cloth_qpos + 3]
    yaw = quat_yaw(qpos[..., idx.cloth_qpos + 3 : idx.cloth_qpos + 7])
    d = dirt_cell_xy(patch) - c[..., None, :2]
    cs, sn = jnp.cos(yaw)[..., None], jnp.sin(yaw)[..., None]
    u = d[..., 0] * cs + d[..., 1] * sn
    v = -d[..., 0] * sn + d[..., 1] * cs
    on_counter = (c[..., 2] - S.CLOTH_HALF[2] < S.COUNTER_TOP + 0.008)[..., None]
    return on_counter & (jnp.abs(u) <= S.CLOTH_HALF[0]) & (jnp.abs(v) <= S.CLOTH_HALF[1])


def wiped_fraction(ts):
    """(B,) the share of the dirt patch's 20 cells wiped so far."""
    return jnp.mean(ts.wiped.astype(jnp.float32), axis=-1)


def _wipe_update(ts, qpos, qvel, mocap, idx):
    return _tick(ts.replace(wiped=ts.wiped | cloth_cover(qpos, ts.patch, idx)))


def _wipe_success(ts, qpos, qvel, mocap, idx):
    return wiped_fraction(ts) >= WIPE_SHARE - 1e-6


# ---- airfryer: tray out at least 10 cm while the body moves less than 2 cm ----------------------
def fryer_displacement(ts, qpos, idx):
    """(B,) distance (m) the air fryer's body has moved from where it stood at reset."""
    return jnp.linalg.norm(qpos[..., idx.fryer_qpos : idx.fryer_qpos + 3] - ts.ref[..., :3], axis=-1)


def _airfryer_update(ts, qpos, qvel, mocap, idx):
    return _tick(ts.replace(failed=ts.failed | (fryer_displacement(ts, qpos, idx) >= 0.02)))


def _airfryer_success(ts, qpos, qvel, mocap, idx):
    return (qpos[..., idx.tray_qpos] >= TRAY_OUT) & ~ts.failed


# ---- arcade: press the cued buttons in the cued order -------------------------------------------
def _arcade_update(ts, qpos, qvel, mocap, idx):
    pressed = qpos[..., idx.button_qpos] < S.BUTTON_PRESSED
    rising = pressed & ~ts.pressed
    step = jnp.clip(ts.progress, 0, 1)
    expected = jnp.take_along_axis(ts.sequence, step[..., None], axis=-1)[..., 0]
    is_expected = jax.nn.one_hot(expected, 3, dtype=bool) & (ts.progress < 2)[..., None]
    good = jnp.any(rising & is_expected, axis=-1)
    bad = jnp.any(rising & ~is_expected, axis=-1)
    progress = ts.progress + good.astype(jnp.int32)
    return _tick(ts.replace(pressed=pressed, progress=progress, failed=ts.failed | bad, achieved=progress >= 2))


# ---- shelf: the block rests within the shelf board's bounds ------------------------------------
def block_on_shelf(qpos, qvel, idx):
    """(B,) bool: the block lies on the shelf board, inside its edges, and is at rest."""
    p = qpos[..., idx.block_qpos : idx.block_qpos + 3]
    x0, x1, y0, y1, top = S.SHELF_BOARD
    inside = (p[..., 0] > x0) & (p[..., 0] < x1) & (p[..., 1] > y0) & (p[..., 1] < y1)
    bottom = p[..., 2] - S.BLOCK_HALF[2]
    resting = (bottom > top - 0.01) & (bottom < top + 0.02)
    still = jnp.linalg.norm(qvel[..., idx.block_qvel : idx.block_qvel + 3], axis=-1) < 0.05
    return inside & resting & still


def _shelf_success(ts, qpos, qvel, mocap, idx):
    return block_on_shelf(qpos, qvel, idx)


# ---- step_back: the base ends 0.5-0.8 m behind its start without hitting anything -------------
# The head camera looks ahead, so the stool behind the robot is never in view: success is a stop
# inside a band of distances that the receding counter shows, and the stool stands beyond the band
# (its nearest touch is STOOL_BACK[0] - STOOL_HALF - BASE_RADIUS = 0.88 m back), so every outcome is
# decidable from the camera and the commanded motion.


def _rect_distance(p, box):
    x0, x1, y0, y1 = box
    dx = jnp.maximum(jnp.maximum(x0 - p[..., 0], p[..., 0] - x1), 0.0)
    dy = jnp.maximum(jnp.maximum(y0 - p[..., 1], p[..., 1] - y1), 0.0)
    return jnp.sqrt(dx * dx + dy * dy)


def base_clearance(qpos, mocap_stool, idx):
    """(B,) distance (m) from the base footprint's edge to the nearest obstacle footprint."""
    p = qpos[..., idx.robot.base_qpos[:2]]
    h = S.STOOL_HALF
    sx, sy = mocap_stool[..., 0], mocap_stool[..., 1]
    d_stool = _rect_distance(p - jnp.stack([sx, sy], -1), (-h, h, -h, h))
    d = jnp.minimum(jnp.minimum(_rect_distance(p, S.COUNTER_BOX), _rect_distance(p, S.ARCADE_BOX)), d_stool)
    return d - S.BASE_RADIUS


def backward_distance(ts, qpos, idx):
    """(B,) distance (m) the base has moved backwards from its reset position, along its heading at reset
    (negative: forwards)."""
    p = qpos[..., idx.robot.base_qpos[:2]]
    x0, y0, yaw0 = ts.ref[..., 3], ts.ref[..., 4], ts.ref[..., 5]
    return -((p[..., 0] - x0) * jnp.cos(yaw0) + (p[..., 1] - y0) * jnp.sin(yaw0))


def _step_back_success(ts, qpos, qvel, mocap, idx):
    d = backward_distance(ts, qpos, idx)
    return (d >= STEP_BACK_BAND[0]) & (d <= STEP_BACK_BAND[1]) & ~ts.failed


def _step_back_update(ts, qpos, qvel, mocap, idx):
    hit = base_clearance(qpos, mocap[..., idx.stool_mocap, :], idx) < 0.0
    return _tick(ts.replace(failed=ts.failed | hit))


def _no_update(ts, qpos, qvel, mocap, idx):
    return _tick(ts)


TASKS: dict[str, Task] = {
    "mug": Task("mug", 6.0, MUG_XY[1] + SHOULDER_Y, (1.0, 0.45), _mug_update, _latched),
    "wipe": Task("wipe", 10.0, PATCH_XY[1] - 0.04 + SHOULDER_Y, (1.0, -0.05), _wipe_update, _wipe_success),
    "airfryer": Task("airfryer", 7.0, FRYER_XY[1] + SHOULDER_Y, (1.0, -0.6), _airfryer_update, _airfryer_success),
    "arcade": Task("arcade", 8.0, BUTTON_XY[1][1] + SHOULDER_Y, (0.72, 1.33), _arcade_update, _latched),
    "shelf": Task("shelf", 9.0, 0.62 + SHOULDER_Y, (1.0, 0.25), _no_update, _shelf_success),
    "step_back": Task("step_back", 5.0, 0.25, (1.0, 0.45), _step_back_update, _step_back_success),
}
assert tuple(TASKS) == TASK_NAMES  # a task's id is its index in both

# One instruction per task, as a dataset's language annotation (the LeRobot export's task text)
TASK_TEXT: dict[str, str] = {
    "mug": "Pick up the mug from the counter and hold it up.",
    "wipe": "Wipe the dirty patch on the counter with the cloth.",
    "airfryer": "Pull the air fryer's tray out without moving the fryer.",
    "arcade": "Press the arcade button marked by the yellow sphere, then the one marked by the white cube.",
    "shelf": "Put the block on the shelf.",
    "step_back": "Step back from the counter without hitting the stool behind you.",
}
assert tuple(TASK_TEXT) == TASK_NAMES

# per-task constants indexed by TaskState.task_id
STATION_Y = np.array([TASKS[n].station_y for n in TASK_NAMES], np.float32)
PLANT_XY = np.array([TASKS[n].plant_xy for n in TASK_NAMES], np.float32)
EPISODE_STEPS = np.array([TASKS[n].episode_steps for n in TASK_NAMES], np.int32)
MAX_EPISODE_STEPS = int(EPISODE_STEPS.max())


def get_task(name: str) -> Task:
    """The task called `name`; raises ValueError listing the valid names otherwise."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; choose one of {', '.join(TASK_NAMES)}")
    return TASKS[name]


def select_task(task_id, options):
    """Each episode's own task's entry of `options`: one pytree per task (in TASK_NAMES order) whose
    leaves lead with task_id's shape ((B,) or () for one episode). Every option is computed, as a
    vmapped lax.switch would compute them, so a batch may mix tasks; it compiles no slower than
    the switch, and the rules are small next to a physics step."""
    def pick(*leaves):
        out = leaves[0]
        for k, leaf in enumerate(leaves[1:], start=1):
            out = jnp.where((task_id == k).reshape(task_id.shape + (1,) * (leaf.ndim - task_id.ndim)), leaf, out)
        return out

    return jax.tree_util.tree_map(pick, *options)


def update_task(ts: TaskState, qpos, qvel, mocap_pos, idx: S.SceneIndex):
    """Advances the task state by one control step and evaluates success, by each episode's task
    (ts.task_id).

    Args:
      ts: batched TaskState; qpos (B, nq), qvel (B, nv), mocap_pos (B, nmocap, 3) after the step;
        idx: scene addresses.
    Returns:
      (TaskState, success (B,) bool).
    """
    tasks = [TASKS[n] for n in TASK_NAMES]
    updated = [t.update(ts, qpos, qvel, mocap_pos, idx) for t in tasks]
    success = [t.success(u, qpos, qvel, mocap_pos, idx) for t, u in zip(tasks, updated)]
    return select_task(ts.task_id, updated), select_task(ts.task_id, success)


# ---- progress: a dense measure of each task's success, for the world model to learn -------------
# The success flag is 0 over most frames of failed and successful episodes alike; a learned model
# given only it can tell success from the task and the scene rather than from what the actions did.
# The progress is a quantity the actions move at every step and the camera shows (the mug's height,
# the dirt cells wiped, the tray's travel, the distance backed), scaled so that success is 1.

def _mug_progress(ts, qpos, qvel, mocap, idx):
    lift = mug_height(qpos, idx) / MUG_LIFT
    return 0.5 * jnp.clip(lift, 0.0, 1.0) + 0.5 * jnp.clip(ts.hold / MUG_HOLD, 0.0, 1.0)


def _wipe_progress(ts, qpos, qvel, mocap, idx):
    return jnp.clip(wiped_fraction(ts) / WIPE_SHARE, 0.0, 1.0)


def _airfryer_progress(ts, qpos, qvel, mocap, idx):
    return jnp.where(ts.failed, 0.0, jnp.clip(qpos[..., idx.tray_qpos] / TRAY_OUT, 0.0, 1.0))


def _arcade_progress(ts, qpos, qvel, mocap, idx):
    return jnp.where(ts.failed, 0.0, jnp.clip(ts.progress / 2.0, 0.0, 1.0))


def _shelf_progress(ts, qpos, qvel, mocap, idx):
    return block_on_shelf(qpos, qvel, idx).astype(jnp.float32)


def _step_back_progress(ts, qpos, qvel, mocap, idx):
    d = backward_distance(ts, qpos, idx)
    inside = (d <= STEP_BACK_BAND[1]) & ~ts.failed
    return jnp.where(inside, jnp.clip(d / STEP_BACK_BAND[0], 0.0, 1.0), 0.0)


PROGRESS = {"mug": _mug_progress, "wipe": _wipe_progress, "airfryer": _airfryer_progress,
            "arcade": _arcade_progress, "shelf": _shelf_progress, "step_back": _step_back_progress}
assert tuple(PROGRESS) == TASK_NAMES


def task_progress(ts: TaskState, qpos, qvel, mocap_pos, idx: S.SceneIndex, success):
    """(B,) float32 in [0, 1]: how far each episode has come towards its task's success, 1 wherever
    success (B,) holds. mug: half the lift to 8 cm plus half the hold to 0.5 s; wipe: the share of
    dirt cells wiped, over 80%; airfryer: the tray's travel over 10 cm (0 once the body moved);
    arcade: the cued buttons pressed, over 2 (0 after a wrong one); shelf: the success flag;
    step_back: the distance backed over 0.5 m (0 past the band's far end or after a hit).

    ts is the task state after the step (update_task's), qpos (B, nq), qvel (B, nv), mocap_pos
    (B, nmocap, 3)."""
    each = [PROGRESS[n](ts, qpos, qvel, mocap_pos, idx).astype(jnp.float32) for n in TASK_NAMES]
    return jnp.where(success, 1.0, select_task(ts.task_id, each))


def episode_done(ts: TaskState, step):
    """(B,) bool: step (B,) control steps have used up each episode's time."""
    return step >= jnp.asarray(EPISODE_STEPS)[ts.task_id]
