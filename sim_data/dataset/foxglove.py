"""Foxglove 3D messages of an episode: the scene's geometry once, the moving bodies' poses per step.

The messages follow Foxglove's own schemas (`foxglove.SceneUpdate`, `foxglove.FrameTransforms`),
JSON-encoded with the jsonschema subset written here. JSON rather than protobuf: once the chunks
are zstd-compressed protobuf saves nothing measurable (docs/design.md, the dataset format), and the
GPU image that writes datasets has no internet and carries its wheels, while JSON needs nothing
beyond orjson.

Frames: `world` (MuJoCo's world frame, z up, the name of MuJoCo's world body), one frame per
*frame body* (a body with a joint or a mocap body; bodies welded to their parent, like the
robot's legs, share their ancestor's frame), each in its moving parent's frame or in `world`,
and `<camera>` for each camera, the optical frame (z forward, x right, y down) Foxglove expects,
parented to the camera's body. A frame body whose world pose changes during the episode gets a
transform each step; the geoms of the others are drawn in `world` at their pose at t = 0.

Poses are rounded to 1e-4 (0.1 mm, 1e-4 in a quaternion component): finer than anything a
viewer shows, and short decimals keep the files small.
"""

from __future__ import annotations

import mujoco
import numpy as np

DECIMALS = 4
FRAME_WORLD = "world"

_NUM = {"type": "number"}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
         "required": ["sec", "nsec"]}


def _xyz(*keys: str) -> dict:
    return {"type": "object", "properties": {k: _NUM for k in keys}, "required": list(keys)}


_POSE = {"type": "object", "properties": {"position": _xyz("x", "y", "z"), "orientation": _xyz("x", "y", "z", "w")},
         "required": ["position", "orientation"]}
_COLOR = _xyz("r", "g", "b", "a")
_PRIMITIVE = {"type": "object", "properties": {"pose": _POSE, "size": _xyz("x", "y", "z"), "color": _COLOR},
              "required": ["pose", "size", "color"]}
_CYLINDER = {"type": "object",
             "properties": {**_PRIMITIVE["properties"], "bottom_scale": _NUM, "top_scale": _NUM},
             "required": ["pose", "size", "bottom_scale", "top_scale", "color"]}
_PRIMITIVE_LISTS = ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models")

FRAME_TRANSFORMS_SCHEMA = {
    "title": "foxglove.FrameTransforms", "type": "object", "required": ["transforms"],
    "properties": {"transforms": {"type": "array", "items": {
        "type": "object",
        "properties": {"timestamp": _TIME, "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
                       "translation": _xyz("x", "y", "z"), "rotation": _xyz("x", "y", "z", "w")},
        "required": ["timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"]}}},
}
SCENE_UPDATE_SCHEMA = {
    "title": "foxglove.SceneUpdate", "type": "object", "required": ["deletions", "entities"],
    "properties": {
        "deletions": {"type": "array", "items": {"type": "object"}},
        "entities": {"type": "array", "items": {
            "type": "object",
            "properties": {
                "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"}, "lifetime": _TIME,
                "frame_locked": {"type": "boolean"},
                "metadata": {"type": "array", "items": {"type": "object"}},
                **{k: {"type": "array", "items": {"type": "object"}} for k in _PRIMITIVE_LISTS},
                "cubes": {"type": "array", "items": _PRIMITIVE},
                "spheres": {"type": "array", "items": _PRIMITIVE},
                "cylinders": {"type": "array", "items": _CYLINDER},
            },
            "required": ["timestamp", "frame_id", "id", "lifetime", "frame_locked", "metadata", *_PRIMITIVE_LISTS]}},
    },
}

# MuJoCo camera frames look along -z with y up; Foxglove's optical frames look along +z with y down:
# a half turn about x, as a (w, x, y, z) quaternion.
_CAM_TO_OPTICAL = np.array([0.0, 1.0, 0.0, 0.0])


def frame_bodies(model: mujoco.MjModel) -> np.ndarray:
    """(nbody,) int: the body whose frame each body's geoms are drawn in (itself when it has a
    joint, is a mocap body or is the world; else its nearest such ancestor)."""
    own = (model.body_jntnum > 0) | (model.body_mocapid >= 0)
    own[0] = True
    out = np.arange(model.nbody)
    for b in range(model.nbody):  # parents come before children in MuJoCo's body order
        out[b] = b if own[b] else out[model.body_parentid[b]]
    return out


def body_poses(model: mujoco.MjModel, qpos: np.ndarray, mocap_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World poses of every body at every step by forward kinematics.

    qpos: (T+1, nq); mocap_pos: (T+1, nmocap, 3).
    Returns (pos (T+1, nbody, 3), quat (T+1, nbody, 4) as (w, x, y, z)), float64.
    """
    data = mujoco.MjData(model)
    n = qpos.shape[0]
    pos, quat = np.empty((n, model.nbody, 3)), np.empty((n, model.nbody, 4))
    for t in range(n):
        data.qpos[:] = qpos[t]
        data.mocap_pos[:] = mocap_pos[t]
        mujoco.mj_kinematics(model, data)
        pos[t], quat[t] = data.xpos, data.xquat
    return pos, quat


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(4,) x (4,) -> (4,) Hamilton product of (w, x, y, z) quaternions."""
    out = np.empty(4)
    mujoco.mju_mulQuat(out, np.asarray(a, np.float64), np.asarray(b, np.float64))
    return out


def _relative(p_parent, q_parent, p_child, q_child) -> tuple[np.ndarray, np.ndarray]:
    """The child's pose in the parent's frame: ((3,), (4,) w, x, y, z)."""
    inv = np.empty(4)
    mujoco.mju_negQuat(inv, np.asarray(q_parent, np.float64))
    p = np.empty(3)
    mujoco.mju_rotVecQuat(p, np.asarray(p_child, np.float64) - p_parent, inv)
    return p, _quat_mul(inv, q_child)


def _r(x) -> float:
    return round(float(x), DECIMALS)


def _vec(p) -> dict:
    return {"x": _r(p[0]), "y": _r(p[1]), "z": _r(p[2])}


def _rot(q) -> dict:
    """(w, x, y, z) -> Foxglove's {x, y, z, w}."""
    return {"x": _r(q[1]), "y": _r(q[2]), "z": _r(q[3]), "w": _r(q[0])}


def moving_frames(model: mujoco.MjModel, pos: np.ndarray, quat: np.ndarray) -> list[int]:
    """Frame bodies (ids, ascending) whose world pose changes during the episode (pos, quat from
    `body_poses`); the world never moves."""
    frames = np.unique(frame_bodies(model))
    moved = (np.abs(pos - pos[:1]).max(axis=(0, 2)) > 10 ** -DECIMALS) | \
            (np.abs(quat - quat[:1]).max(axis=(0, 2)) > 10 ** -DECIMALS)
    return [int(b) for b in frames if b != 0 and moved[b]]


def frame_parents(model: mujoco.MjModel, moving: list[int]) -> dict:
    """{moving frame body: its parent in the transform tree}: the frame body of its MuJoCo parent
    when that moves too, else 0 (the world)."""
    owner = frame_bodies(model)
    return {b: int(owner[model.body_parentid[b]]) if int(owner[model.body_parentid[b]]) in moving else 0
            for b in moving}


def transform_tree(model: mujoco.MjModel, moving: list[int], cameras) -> tuple[dict, dict]:
    """The episode's transform tree, worked out once for all its steps: ({moving frame body: its
    parent}, `frame_parents`; {camera name: the frame its optical frame hangs from}, its frame body
    where that moves, else 0, the world)."""
    owner = frame_bodies(model)
    cam_parent = {}
    for cam in cameras:
        body = int(owner[model.camera(cam).bodyid[0]])
        cam_parent[cam] = body if body in moving else 0
    return frame_parents(model, moving), cam_parent


def frame_transforms(model: mujoco.MjModel, tree: tuple[dict, dict], pos: np.ndarray, quat: np.ndarray, t: int,
                     stamp: dict) -> dict:
    """One `foxglove.FrameTransforms` message for step t: each moving frame body in its parent's
    frame (`frame_parents`: a tree like the robot's, where a joint's transform changes only in its
    own degrees of freedom, which keeps the numbers few and the files small), and each camera as an
    optical frame in its frame body's frame (in `world` when that body does not move).

    tree: `transform_tree`'s; pos, quat: (T+1, nbody, 3), (T+1, nbody, 4) world poses from
    `body_poses`; stamp: {"sec", "nsec"}.
    """
    parents, cam_parent = tree
    tf = []
    for b, parent in parents.items():
        p, q = _relative(pos[t, parent], quat[t, parent], pos[t, b], quat[t, b])
        tf.append({"timestamp": stamp, "parent_frame_id": model.body(parent).name, "child_frame_id": model.body(b).name,
                   "translation": _vec(p), "rotation": _rot(q)})
    for cam, body in cam_parent.items():
        cam_pos, cam_quat = _camera_world(model, model.camera(cam), pos[t], quat[t])
        p, q = _relative(pos[t, body], quat[t, body], cam_pos, _quat_mul(cam_quat, _CAM_TO_OPTICAL))
        tf.append({"timestamp": stamp, "parent_frame_id": model.body(body).name,
                   "child_frame_id": cam, "translation": _vec(p), "rotation": _rot(q)})
    return {"transforms": tf}


def _camera_world(model: mujoco.MjModel, cam, pos: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A camera's world pose ((3,), (4,) w, x, y, z) from its body's pose; pos, quat: (nbody, ...)."""
    b = int(cam.bodyid[0])
    p = np.empty(3)
    mujoco.mju_rotVecQuat(p, np.asarray(cam.pos, np.float64), quat[b])
    return pos[b] + p, _quat_mul(quat[b], cam.quat)


def _geom_primitives(model: mujoco.MjModel, g: int, p: np.ndarray, q: np.ndarray) -> dict:
    """The primitive lists drawing geom g at pose (p (3,), q (4,) w, x, y, z) in its entity's frame."""
    size, rgba = model.geom_size[g], model.geom_rgba[g]
    color = {"r": _r(rgba[0]), "g": _r(rgba[1]), "b": _r(rgba[2]), "a": _r(rgba[3])}
    pose = {"position": _vec(p), "orientation": _rot(q)}
    kind = mujoco.mjtGeom(int(model.geom_type[g]))
    out = {k: [] for k in _PRIMITIVE_LISTS}
    if kind == mujoco.mjtGeom.mjGEOM_PLANE:  # drawn as a 1 mm slab; an infinite plane's half size 0 as 5 m
        hx, hy = (s if s > 0 else 5.0 for s in size[:2])
        out["cubes"].append({"pose": pose, "size": _vec((2 * hx, 2 * hy, 0.001)), "color": color})
    elif kind == mujoco.mjtGeom.mjGEOM_BOX:
        out["cubes"].append({"pose": pose, "size": _vec(2 * size), "color": color})
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        out["spheres"].append({"pose": pose, "size": _vec([2 * size[0]] * 3), "color": color})
    elif kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        out["spheres"].append({"pose": pose, "size": _vec(2 * size), "color": color})
    elif kind in (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_CAPSULE):
        r, h = size[0], size[1]
        out["cylinders"].append({"pose": pose, "size": _vec((2 * r, 2 * r, 2 * h)), "bottom_scale": 1.0,
                                 "top_scale": 1.0, "color": color})
        if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:  # Foxglove has no capsule: a cylinder and two end spheres
            for sign in (-1.0, 1.0):
                end = np.empty(3)
                mujoco.mju_rotVecQuat(end, np.array([0.0, 0.0, sign * h]), q)
                out["spheres"].append({"pose": {"position": _vec(p + end), "orientation": _rot(q)},
                                       "size": _vec([2 * r] * 3), "color": color})
    else:
        raise ValueError(f"geom {model.geom(g).name or g} has type {kind.name}, which the Foxglove scene does not draw; "
                         "add it to sim_data.dataset.foxglove._geom_primitives")
    return out


def drawn_geoms(model: mujoco.MjModel) -> list[int]:
    """Geom ids the scene draws: the visible ones (alpha > 0), in id order."""
    return [g for g in range(model.ngeom) if model.geom_rgba[g, 3] > 0]


def scene_update(model: mujoco.MjModel, moving: list[int], qpos0: np.ndarray, mocap0: np.ndarray,
                 stamp: dict) -> dict:
    """The `foxglove.SceneUpdate` of an episode's first state: one entity per drawn geom, id the
    geom's name (or `geom_<id>`), in its frame body's frame when that moves (frame-locked, so it
    follows `/tf`), else in `world` at its pose at t = 0. Colours are the model's as authored.

    qpos0: (nq,); mocap0: (nmocap, 3); stamp: {"sec", "nsec"}.
    """
    data = mujoco.MjData(model)
    data.qpos[:], data.mocap_pos[:] = qpos0, mocap0
    mujoco.mj_kinematics(model, data)
    owner = frame_bodies(model)
    entities = []
    for g in drawn_geoms(model):
        gq = np.empty(4)
        mujoco.mju_mat2Quat(gq, data.geom_xmat[g])
        body = int(owner[model.geom_bodyid[g]])
        if body in moving:
            p, q = _relative(data.xpos[body], data.xquat[body], data.geom_xpos[g], gq)
            frame = model.body(body).name
        else:
            p, q, frame = data.geom_xpos[g].copy(), gq, FRAME_WORLD
        entities.append({"timestamp": stamp, "frame_id": frame, "id": model.geom(g).name or f"geom_{g}",
                         "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": frame != FRAME_WORLD, "metadata": [],
                         **_geom_primitives(model, g, p, q)})
    return {"deletions": [], "entities": entities}
