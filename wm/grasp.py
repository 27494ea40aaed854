"""Objects the hand takes (the mug, the air fryer's tray, the cloth), predicted from the actions, and
the task's verdict.

A world model that ranks grasping policies must know whether the hand closed on the object and where the
hand took it. This model takes both from the actions and the first state alone:

- the base and the actuated joints move under the actions by `wm.egomotion`'s fitted models, and MuJoCo's
  kinematics (MJX, so under jit) place the right hand's grip site at every predicted state;
- each time the right hand's commanded closure rises to `GraspRule.closure` (an open hand closing, or
  one closed from the first step), the grip takes the object when the site lies within `reach_xy` of
  the place it is held by (the mug's and the cloth's centres, the tray's handle) horizontally, between
  `z_low` and `z_high` above it, and moved at most `speed` over that step; while the closure stays at
  `release` or more (a hand that eases its grip part-way through a pull still holds) the object moves
  with the grip site: the mug and the cloth freely (let go, dropped to the height they started at), the
  tray along its slide by the grip's travel on the slide's axis, within the slide's range (left where
  the hand lets go);
- the task's own rule (`sim_data.sim.tasks.update_task`: for the mug, its bottom 8 cm above the counter
  for half a second; for the air fryer, the tray 10 cm out at the end; for wipe, 80% of the dirt's cells
  under the cloth while it lies on the counter) runs on the predicted states.

Each task's six numbers are fit on its recorded episodes (`fit_grasp_rule`: the most accurate on the
training split's outcomes, over a grid) and checked on the validation split; `experiments.fill` fits and
saves them (`GRASP_JSON`) beside the motion models. `grasp_success` reads any batch of action sequences:
the actions a policy took in a world model's imagination, or those of simulated episodes.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from sim_data.sim import robot as R
from sim_data.sim.tasks import CONTROL_DT, TaskState, update_task
from sim_data.util import read_json, write_json_atomic
from wm.geometric import RobotCamera, posed, robot_start, step_robot

GRASP_JSON = "grasp.json"


@dataclasses.dataclass(frozen=True)
class Held:
    """How a task's object moves in the hand: joint, the joint that carries it (a free joint: the
    body follows the grip; a slide: its travel follows the grip's along the slide's axis); handle, the
    geom the grip takes it by (None: the body's own centre)."""
    joint: str
    handle: str | None = None


GRASPED = {"mug": Held("mug"), "airfryer": Held("fryer_tray", "handle"), "wipe": Held("cloth")}
GRIP_SITE = "right_grip"
# the grid fit_grasp_rule searches, one axis a field of GraspRule
GRID = {"closure": (0.3, 0.5, 0.7, 0.9),
        "reach_xy": (0.015, 0.02, 0.025, 0.03, 0.035, 0.04, 0.05, 0.06, 0.08),
        "z_low": (-0.04, -0.03, -0.02, -0.01, 0.0),
        "z_high": (0.01, 0.02, 0.03, 0.04, 0.05),
        "speed": (0.1, 0.2, 0.4, 0.8, 1e3),  # 1e3 m/s: no limit
        "release": (0.3, 0.5, 1.0)}  # above the closure: let go as soon as the closure falls below it
# the closures refine_closure tries with the grid's rule's other numbers: a grasp holds above a sharp threshold
# on the closure command (0.40-0.45 for the scripts' mug, 0.2-0.3 for the tray), finer than GRID's steps
CLOSURE_STEPS = tuple(round(0.1 + 0.05 * k, 2) for k in range(18))
RULES_AT_ONCE = 500  # verdicts_of_rules' batch of rules


@struct.dataclass
class GraspRule:
    """When the grip holds the object: closure, the right hand's commanded closure that closes it;
    reach_xy (m), the grip site's largest horizontal distance from the place it is held by at that step
    (object_at's "handle"); z_low and z_high (m), the lowest and highest the site may be above that
    place; speed (m/s), the fastest the site may move over the step it closes in (a hand that sweeps
    past does not hold); release, the closure below which a held object is let go (at most closure: a
    hand that eases its grip part-way through a pull still holds). Scalars (or arrays of one shape, to
    score several rules at once)."""
    closure: jax.Array
    reach_xy: jax.Array
    z_low: jax.Array
    z_high: jax.Array
    speed: jax.Array
    release: jax.Array

    @classmethod
    def of(cls, values) -> GraspRule:
        """The rule of values in GRID's order of fields (or a {field: value} dict)."""
        if isinstance(values, dict):
            values = [values[k] for k in GRID]
        return cls(*(jnp.asarray(v, jnp.float32) for v in values))

    def as_dict(self) -> dict:
        return {k: float(getattr(self, k)) for k in GRID}


def _named(camera: RobotCamera, kind, name: str) -> int:
    i = mujoco.mj_name2id(camera.model, kind, name)
    if i < 0:
        raise ValueError(f"the scene has no {kind.name[6:].lower()} {name!r}")
    return i


def grip_site(camera: RobotCamera) -> int:
    return _named(camera, mujoco.mjtObj.mjOBJ_SITE, GRIP_SITE)


def held_of(task: str) -> Held:
    if task not in GRASPED:
        raise ValueError(f"no object to grasp in task {task!r}; the grasp model reads {', '.join(GRASPED)}")
    return GRASPED[task]


def object_joint(task: str, camera: RobotCamera) -> tuple[int, int, bool]:
    """Task's held object's joint: (its id, its qpos address, whether it slides)."""
    j = _named(camera, mujoco.mjtObj.mjOBJ_JOINT, held_of(task).joint)
    return j, int(camera.model.jnt_qposadr[j]), camera.model.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE


def object_at(task: str, camera: RobotCamera, qpos, mocap) -> dict:
    """Where the grip must take task's object at states qpos (B, nq), mocap (B, nmocap, 3): {"handle":
    (B, 3) the point, "coords": (B, k) the joint's coordinates that move (a free joint's position, k=3;
    a slide's travel, k=1), "carry": (B, 3, k) the coordinates' change per metre of grip motion, "low",
    "high": (k,) their range}. Traceable."""
    held = held_of(task)
    j, adr, slides = object_joint(task, camera)
    d = camera.data(qpos, mocap)
    if slides:
        lo, hi = camera.model.jnt_range[j]
        coords, carry = qpos[:, adr:adr + 1], d.xaxis[:, j, :, None]
    else:
        lo, hi = -np.inf, np.inf
        coords, carry = qpos[:, adr:adr + 3], jnp.broadcast_to(jnp.eye(3), (qpos.shape[0], 3, 3))
    handle = (d.geom_xpos[:, _named(camera, mujoco.mjtObj.mjOBJ_GEOM, held.handle)] if held.handle
              else qpos[:, adr:adr + 3])
    k = coords.shape[1]
    return {"handle": handle, "coords": coords, "carry": carry, "low": jnp.full(k, lo, jnp.float32),
            "high": jnp.full(k, hi, jnp.float32)}


@functools.partial(jax.jit, static_argnames=("camera",))
def robot_path(base_coef, joint_coef, qpos0, mocap0, actions, camera: RobotCamera) -> dict:
    """The robot's states predicted from qpos0 (B, nq), mocap0 (B, nmocap, 3) under actions (B, T, 20)
    as applied, by base_coef (3, 6) and joint_coef (16, 3) (wm.egomotion): {"qpos": (B, T, nq) after
    each step (the objects where they started), "grip": (B, T, 3) the right hand's grip site there}."""
    site = grip_site(camera)

    def body(robot, action):
        robot = base, _, joints, _ = step_robot(base_coef, joint_coef, robot, action)
        qpos = posed(qpos0, base, joints, camera.idx)
        return robot, (qpos, camera.data(qpos, mocap0).site_xpos[:, site])

    _, (qpos, grip) = jax.lax.scan(body, robot_start(qpos0, camera.idx),
                                   jnp.swapaxes(jnp.asarray(actions, jnp.float32), 0, 1))
    return {"qpos": jnp.swapaxes(qpos, 0, 1), "grip": jnp.swapaxes(grip, 0, 1)}


def held_verdict(rule: GraspRule, path: dict, actions, mocap0, task0: TaskState, camera: RobotCamera,
                 task: str) -> dict:
    """The task's verdict on robot_path's states with the object moved by rule: {"success": (B,) bool
    after the last step, "held": (B,) bool the grip took the object, "moved": (B,) float32 the farthest
    (m) the object's coordinates got from their start, "at": (B, k) those coordinates after the last
    step (object_at's)}. Traceable; the object starts where path's states hold it."""
    _, adr, _ = object_joint(task, camera)
    qpos, grip = jnp.swapaxes(path["qpos"], 0, 1), jnp.swapaxes(path["grip"], 0, 1)
    closure = jnp.swapaxes(jnp.asarray(actions, jnp.float32)[..., R.RIGHT_HAND], 0, 1)
    obj = object_at(task, camera, qpos[0], mocap0)
    start, k = obj["coords"], obj["coords"].shape[1]
    free = k == 3  # a free body let go falls to the height it started at (where it lay); a slide stays where left
    qvel = jnp.zeros(qpos.shape[1:2] + (camera.model.nv,), jnp.float32)

    def body(c, x):
        was, held, grip_at, coords_at, coords, before, ts, _, far = c
        q, g, u = x
        closed = u >= rule.closure
        closing = closed & ~was
        rel = g - obj["handle"]
        near = ((jnp.hypot(rel[:, 0], rel[:, 1]) <= rule.reach_xy)
                & (rel[:, 2] >= rule.z_low) & (rel[:, 2] <= rule.z_high)
                & (jnp.linalg.norm(g - before, axis=-1) <= rule.speed * CONTROL_DT))
        grip_at = jnp.where(closing[:, None], g, grip_at)
        coords_at = jnp.where(closing[:, None], coords, coords_at)
        held = (held | (closing & near)) & (u >= jnp.minimum(rule.release, rule.closure))
        carried = jnp.clip(coords_at + jnp.einsum("bi,bik->bk", g - grip_at, obj["carry"]), obj["low"], obj["high"])
        coords = jnp.where(held[:, None], carried, coords.at[:, 2].set(start[:, 2]) if free else coords)
        ts, success = update_task(ts, q.at[:, adr:adr + k].set(coords), qvel, mocap0, camera.scene)
        far = jnp.maximum(far, jnp.linalg.norm(coords - start, axis=-1))
        return (closed, held, grip_at, coords_at, coords, g, ts, success, far), held

    no = jnp.zeros(start.shape[0], bool)
    init = (no, no, jnp.zeros_like(grip[0]), start, start, grip[0], task0, no, jnp.zeros(start.shape[0]))
    (*_, at, _, _, success, far), held = jax.lax.scan(body, init, (qpos, grip, closure))
    return {"success": success, "held": held.any(0), "moved": far, "at": at}


@functools.partial(jax.jit, static_argnames=("camera", "task"))
def grasp_success(rule: GraspRule, base_coef, joint_coef, qpos0, mocap0, task0: TaskState, actions,
                  camera: RobotCamera, task: str) -> dict:
    """held_verdict on robot_path's states: the task's verdict from qpos0 (B, nq), mocap0 (B, nmocap, 3)
    and task0 (the TaskState at reset) under actions (B, T, 20) as applied."""
    path = robot_path(base_coef, joint_coef, qpos0, mocap0, actions, camera)
    return held_verdict(rule, path, actions, mocap0, task0, camera, task)


@functools.partial(jax.jit, static_argnames=("camera", "task"))
def _verdicts(rules: GraspRule, path: dict, actions, mocap0, task0: TaskState, camera: RobotCamera, task: str):
    return jax.vmap(lambda r: held_verdict(r, path, actions, mocap0, task0, camera, task)["success"])(rules)


def verdicts_of_rules(rules: GraspRule, path: dict, actions, mocap0, task0: TaskState, camera: RobotCamera,
                      task: str) -> np.ndarray:
    """(G, B) bool: held_verdict's success under each of the G rules of rules ((G,) arrays), at most
    RULES_AT_ONCE at a time (the last batch padded with the last rule: one compiled program)."""
    g = len(rules.closure)
    at_once = min(g, RULES_AT_ONCE)
    out = []
    for i in range(0, g, at_once):
        idx = np.minimum(np.arange(i, i + at_once), g - 1)
        out.append(np.asarray(_verdicts(jax.tree.map(lambda x: x[idx], rules), path, actions, mocap0, task0, camera,
                                        task))[: g - i])
    return np.concatenate(out)


def rule_grid() -> GraspRule:
    """Every rule of fit_grasp_rule's grid (GRID), as a GraspRule of (G,) arrays, the last field fastest."""
    return GraspRule.of(np.array(list(itertools.product(*GRID.values()))).T)


def fit_grasp_rule(verdicts: np.ndarray, outcomes: np.ndarray) -> tuple[GraspRule, float]:
    """The rule of rule_grid() whose verdicts (G, E) bool (verdicts_of_rules' over the training
    episodes) agree most often with their recorded outcomes (E,) bool, and that share. Among equally
    accurate rules, the one nearest the middle of them (each number's median over them, in steps of its
    grid), so that a rule the data cannot pin down keeps a margin on every side; then the first in the
    grid's order."""
    steps = np.array(list(itertools.product(*(range(len(v)) for v in GRID.values()))))
    best, acc = _most_accurate(verdicts, outcomes, steps)
    return jax.tree.map(lambda x: x[best], rule_grid()), acc


def _most_accurate(verdicts, outcomes, steps) -> tuple[int, float]:
    """(index, share) of the candidate whose verdicts (G, E) bool agree most often with outcomes (E,) bool;
    among equally accurate ones, the nearest the middle of them by their grid steps (G, K)."""
    acc = (np.asarray(verdicts) == np.asarray(outcomes, bool)[None]).mean(1)
    tied = np.flatnonzero(acc == acc.max())
    at = steps[tied]
    best = int(tied[np.argmin(np.abs(at - np.median(at, 0)).sum(1))])
    return best, float(acc[best])


def closure_variants(rule: GraspRule) -> GraspRule:
    """rule (one rule's scalars) with its closure at each of CLOSURE_STEPS: a GraspRule of (F,) arrays."""
    n = len(CLOSURE_STEPS)
    return GraspRule.of({**{k: np.full(n, v) for k, v in rule.as_dict().items()}, "closure": np.array(CLOSURE_STEPS)})


def refine_closure(rule: GraspRule, verdicts: np.ndarray, outcomes: np.ndarray) -> tuple:
    """fit_grasp_rule's rule with its closure placed on CLOSURE_STEPS: verdicts (F, E) bool are
    closure_variants(rule)'s over the training episodes, outcomes (E,) bool their recorded ones; among the
    closures that agree with the most, the middle one, as fit_grasp_rule keeps a margin on every side of
    what the data allows (the grid's closure is among them, so the accuracy never falls). Returns (rule,
    its accuracy)."""
    best, acc = _most_accurate(verdicts, outcomes, np.arange(len(CLOSURE_STEPS))[:, None])
    return jax.tree.map(lambda x: x[best], closure_variants(rule)), acc


def save_grasp(out: Path, task: str, rule: GraspRule, metrics: dict) -> None:
    """Writes task's rule and its fit's metrics into out/grasp.json, beside the other tasks' there."""
    path = Path(out) / GRASP_JSON
    held = read_json(path) if path.exists() else {"rules": {}, "metrics": {}}
    held["rules"][task], held["metrics"][task] = rule.as_dict(), metrics
    write_json_atomic(path, held)


def load_grasp(out: Path) -> dict:
    """The rules save_grasp wrote in out ({task: GraspRule}), or {} where out holds none."""
    path = Path(out) / GRASP_JSON
    if not path.exists():
        return {}
    rules = read_json(path).get("rules")
    if not isinstance(rules, dict) or any(set(r) != set(GRID) or t not in GRASPED for t, r in rules.items()):
        raise ValueError(f"{path} does not hold a rule of {list(GRID)} for each of its tasks (of {list(GRASPED)}): "
                         f"remove it and run python -m experiments.fill --out {Path(out)} --tasks TASKS again")
    return {t: GraspRule.of(r) for t, r in rules.items()}
