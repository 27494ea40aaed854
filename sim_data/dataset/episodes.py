"""One episode, one MCAP file: the writer, and readers that check what they read.

| topic | schema (jsonschema, JSON messages) | content per control step (20 Hz) |
|---|---|---|
| `/head_cam/image`, `/ext_cam/image` | `foxglove.CompressedImage` | JPEG frame (t = 0..T) |
| `/robot_state` | `wmlab.RobotState` | proprioception: one field per `PROPRIO_NAMES` entry (t = 0..T) |
| `/action` | `wmlab.Action` | the action taken at step t: one field per `ACTION_NAMES` entry (t = 0..T-1) |
| `/task_state` | `wmlab.TaskState` | step, time, success flag, progress in [0, 1] (t = 0..T) |
| `/sim_state` | `wmlab.SimState` | qpos, qvel, mocap_pos: the full simulator state (t = 0..T) |
| `/tf` | `foxglove.FrameTransforms` | world poses of the bodies that move, camera frames (t = 0..T) |
| `/scene` | `foxglove.SceneUpdate` | every visible geom as a primitive, once (t = 0) |

and a metadata record `episode` (task, policy, skill, seed, success, split, configuration,
package versions). Observation t is seen before action t; the last one follows the last action.
Named fields (`/robot_state.pos_left_elbow`, `/action.forward_speed`) are what Foxglove's Plot
panel addresses; `/tf` and `/scene` are its 3D panel's input (`sim_data.dataset.foxglove`).

Time: every episode starts at EPOCH_NS, 2026-01-01T00:00:00Z, and step t is logged at
EPOCH_NS + t * CONTROL_DT. A fixed epoch rather than the wall clock of the run, because the same
configuration and seed must give the same bytes; one epoch for all episodes, so that two files
opened side by side line up step by step.

Files are chunked (1 MiB), zstd-compressed, indexed and checksummed (each chunk's CRC and the
data section's CRC, both checked by `read_episode`); they open in Foxglove without plugins.
"""

from __future__ import annotations

import base64
import json
import os
from pathlib import Path

import cv2
import numpy as np
import orjson
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import CompressionType, Writer

from sim_data.dataset import foxglove
from sim_data.sim.robot import ACTION_NAMES, PROPRIO_NAMES
from sim_data.sim.scene import load_model
from sim_data.sim.tasks import CONTROL_DT

EPOCH_NS = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z: the log time of every episode's first step
IMAGE_SCHEMA = {
    "title": "foxglove.CompressedImage", "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}
NUM_ARRAY = {"type": "array", "items": {"type": "number"}}


def _object(title: str, fields: dict) -> dict:
    return {"title": title, "type": "object", "properties": fields, "required": list(fields)}


SCHEMAS = {
    "/robot_state": _object("wmlab.RobotState", {n: {"type": "number"} for n in PROPRIO_NAMES}),
    "/action": _object("wmlab.Action", {n: {"type": "number"} for n in ACTION_NAMES}),
    "/task_state": _object("wmlab.TaskState", {"step": {"type": "integer"}, "time": {"type": "number"},
                                               "success": {"type": "boolean"}, "progress": {"type": "number"}}),
    "/sim_state": _object("wmlab.SimState", {"qpos": NUM_ARRAY, "qvel": NUM_ARRAY, "mocap_pos": NUM_ARRAY}),
}
# written for viewers, not read back: derived from /sim_state
VIEW_SCHEMAS = {"/tf": foxglove.FRAME_TRANSFORMS_SCHEMA, "/scene": foxglove.SCENE_UPDATE_SCHEMA}


NUMPY = orjson.OPT_SERIALIZE_NUMPY


class CorruptEpisode(ValueError):
    """An episode file that cannot be read back whole."""


def encode_jpeg(frame: np.ndarray, quality: int) -> bytes:
    """frame: (H, W, 3) uint8 RGB -> JPEG bytes."""
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return jpg.tobytes()


def write_episode_mcap(path: Path, episode: dict, meta: dict, jpeg_quality: int) -> None:
    """Writes one episode to path atomically (a temporary name, renamed when whole).

    episode: frames {camera: (T+1, H, W, 3) uint8}, proprio (T+1, 37), qpos (T+1, nq),
      qvel (T+1, nv), mocap_pos (T+1, nmocap, 3), success (T+1,) bool, progress (T+1,) float in
      [0, 1] (`sim_data.sim.tasks.task_progress`), action (T, 20).
    meta: the `episode` metadata record (values that are not strings are stored as JSON).
    """
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    n_obs = episode["proprio"].shape[0]
    # float32 arrays, written by orjson as the shortest decimal that reads back to the same float32
    proprio, qpos, qvel, action = (np.ascontiguousarray(episode[k], np.float32)
                                   for k in ("proprio", "qpos", "qvel", "action"))
    progress = np.asarray(episode["progress"], np.float32)
    mocap = np.ascontiguousarray(episode["mocap_pos"], np.float32).reshape(n_obs, -1, 3)
    # the 3D view from the stored (float32) state, so that a reader recomputing it from /sim_state agrees
    model = load_model()
    pos, quat = foxglove.body_poses(model, qpos.astype(np.float64), mocap.astype(np.float64))
    moving = foxglove.moving_frames(model, pos, quat)
    tree = foxglove.transform_tree(model, moving, list(episode["frames"]))
    with open(tmp, "wb") as f:
        w = Writer(f, chunk_size=1 << 20, compression=CompressionType.ZSTD, enable_crcs=True, enable_data_crcs=True)
        w.start(profile="", library="wmlab")
        image_schema = w.register_schema("foxglove.CompressedImage", "jsonschema", json.dumps(IMAGE_SCHEMA).encode())
        channels = {cam: w.register_channel(f"/{cam}/image", "json", image_schema) for cam in episode["frames"]}
        for topic, schema in {**SCHEMAS, **VIEW_SCHEMAS}.items():
            sid = w.register_schema(schema["title"], "jsonschema", json.dumps(schema).encode())
            channels[topic] = w.register_channel(topic, "json", sid)
        for t in range(n_obs):
            ns = EPOCH_NS + round(t * CONTROL_DT * 1e9)
            stamp = {"sec": ns // 10**9, "nsec": ns % 10**9}

            def put(key, obj, ns=ns):
                w.add_message(channels[key], log_time=ns, publish_time=ns, data=orjson.dumps(obj, option=NUMPY))

            if t == 0:
                put("/scene", foxglove.scene_update(model, moving, qpos[0], mocap[0], stamp))
            for cam, frames in episode["frames"].items():
                put(cam, {"timestamp": stamp, "frame_id": cam, "format": "jpeg",
                          "data": base64.b64encode(encode_jpeg(frames[t], jpeg_quality)).decode()})
            put("/robot_state", dict(zip(PROPRIO_NAMES, proprio[t])))
            put("/task_state", {"step": t, "time": t * CONTROL_DT, "success": bool(episode["success"][t]),
                                "progress": progress[t]})
            put("/sim_state", {"qpos": qpos[t], "qvel": qvel[t], "mocap_pos": mocap[t].reshape(-1)})
            put("/tf", foxglove.frame_transforms(model, tree, pos, quat, t, stamp))
            if t < n_obs - 1:
                put("/action", dict(zip(ACTION_NAMES, action[t])))
        w.add_metadata("episode", {k: v if isinstance(v, str) else json.dumps(v) for k, v in meta.items()})
        w.finish()
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _maybe_json(v: str):
    try:
        return json.loads(v)
    except ValueError:
        return v


def read_episode_meta(path: Path) -> dict:
    """The `episode` metadata record of an MCAP file (values JSON-decoded where they were).

    Raises CorruptEpisode naming the file when it is not a whole MCAP file written by sim_data.
    """
    try:
        with open(path, "rb") as f:
            for rec in make_reader(f).iter_metadata():
                if rec.name == "episode":
                    return {k: _maybe_json(v) for k, v in rec.metadata.items()}
    except Exception as e:  # the mcap reader raises several types on damaged files
        raise CorruptEpisode(f"{path}: not a readable MCAP file ({type(e).__name__}: {e})") from e
    raise CorruptEpisode(f"{path}: no 'episode' metadata record (truncated or not written by sim_data.dataset.generate)")


def decode_jpeg(data: bytes) -> np.ndarray:
    """JPEG bytes -> (H, W, 3) uint8 RGB; None when the bytes do not decode."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return None if img is None else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _named(messages: list, legacy_key: str, names) -> np.ndarray:
    """(N, len(names)) float32 from N JSON messages with one field per name, in `names` order; a
    file written before named fields holds the row under `legacy_key` instead."""
    rows = []
    for m in messages:
        obj = orjson.loads(m)
        rows.append(obj[legacy_key] if legacy_key in obj else [obj[n] for n in names])
    return np.array(rows, np.float32)


def read_episode(path: Path, cameras=None, sim_state: bool = True) -> dict:
    """Reads a whole episode back and checks it.

    Args:
      path: an episode's MCAP file.
      cameras: camera names to decode (default: all the file has; () for none).
      sim_state: also read qpos, qvel and mocap_pos.
    Returns:
      {"meta": the metadata record, "frames": {camera: (T+1, H, W, 3) uint8}, "proprio": (T+1, 37) f32,
       "action": (T, 20) f32, "success": (T+1,) bool, "progress": (T+1,) f32 (the success flag
       where a file predates the progress field), and with sim_state "qpos" (T+1, nq) f32,
       "qvel" (T+1, nv) f32, "mocap_pos" (T+1, nmocap, 3) f32}.
    Raises:
      CorruptEpisode naming the file and what is wrong: unreadable or truncated MCAP, a failed
      checksum or decompression, a message or frame missing, an image that does not decode.
    """
    meta = read_episode_meta(path)
    wanted = list(meta.get("cameras", [])) if cameras is None else list(cameras)
    n_obs = int(meta["num_steps"]) + 1
    topics = {f"/{c}/image": c for c in wanted}
    skip = {"/sim_state"} if not sim_state else set()
    cols: dict = {t: [] for t in list(topics) + [t for t in SCHEMAS if t not in skip]}
    try:
        with open(path, "rb") as f:  # a sequential read checks each chunk's CRC and the data section's
            for _, channel, message in NonSeekingReader(f, validate_crcs=True).iter_messages(topics=list(cols)):
                cols[channel.topic].append(message.data)
    except Exception as e:
        raise CorruptEpisode(f"{path}: messages unreadable ({type(e).__name__}: {e})") from e
    for topic, msgs in cols.items():
        want = n_obs - 1 if topic == "/action" else n_obs
        if len(msgs) != want:
            raise CorruptEpisode(f"{path}: {topic} has {len(msgs)} messages, the metadata says {want}")
    try:
        out = {"meta": meta, "frames": {}}
        for topic, cam in topics.items():
            frames = []
            for t, data in enumerate(cols[topic]):
                img = decode_jpeg(base64.b64decode(orjson.loads(data)["data"]))
                if img is None:
                    raise CorruptEpisode(f"{path}: {topic} frame {t} is not a decodable JPEG")
                frames.append(img)
            out["frames"][cam] = np.stack(frames)
        out["proprio"] = _named(cols["/robot_state"], "proprio", PROPRIO_NAMES)
        out["action"] = _named(cols["/action"], "action", ACTION_NAMES).reshape(n_obs - 1, len(ACTION_NAMES))
        task_state = [orjson.loads(m) for m in cols["/task_state"]]
        out["success"] = np.array([m["success"] for m in task_state], bool)
        out["progress"] = np.array([m.get("progress", m["success"]) for m in task_state], np.float32)
        if sim_state:
            sims = [orjson.loads(m) for m in cols["/sim_state"]]
            out["qpos"] = np.array([s["qpos"] for s in sims], np.float32)
            out["qvel"] = np.array([s["qvel"] for s in sims], np.float32)
            out["mocap_pos"] = np.array([s["mocap_pos"] for s in sims], np.float32).reshape(n_obs, -1, 3)
    except CorruptEpisode:
        raise
    except (ValueError, KeyError, TypeError, orjson.JSONDecodeError) as e:
        raise CorruptEpisode(f"{path}: a message does not parse ({type(e).__name__}: {e})") from e
    if bool(out["success"][-1]) != bool(meta["success"]):
        raise CorruptEpisode(f"{path}: the last success flag disagrees with the metadata's success")
    return out
