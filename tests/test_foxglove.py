"""Episode files as Foxglove reads them: schemas, named fields, time, checksums, the 3D view, the layout."""

import json
import shutil
from pathlib import Path

import mujoco
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import DataEnd
from mcap.stream_reader import StreamReader

from sim_data.dataset import foxglove as F
from sim_data.dataset.episodes import CONTROL_DT, EPOCH_NS, CorruptEpisode, read_episode
from sim_data.sim.robot import ACTION_NAMES, PROPRIO_NAMES
from sim_data.sim.scene import load_model, scene_index

LAYOUT = Path(__file__).resolve().parent.parent / "examples" / "foxglove_layout.json"
TOL = 10 ** -F.DECIMALS  # poses are written rounded to this


def _types(name):
    return {"object": dict, "array": list, "string": str, "boolean": bool, "integer": int, "number": (int, float)}[name]


def conforms(obj, schema, where="") -> None:
    """Asserts obj matches the jsonschema subset the files use (type, properties, required, items);
    the `jsonschema` package is not a dependency of the repo."""
    if "type" in schema:
        kind = schema["type"]
        assert isinstance(obj, _types(kind)) and (kind in ("boolean",) or not isinstance(obj, bool)), \
            f"{where}: {obj!r} is not {kind}"
    if isinstance(obj, dict):
        missing = set(schema.get("required", ())) - set(obj)
        assert not missing, f"{where}: missing {sorted(missing)}"
        for k, sub in schema.get("properties", {}).items():
            if k in obj:
                conforms(obj[k], sub, f"{where}.{k}")
    if isinstance(obj, list) and "items" in schema:
        for i, item in enumerate(obj):
            conforms(item, schema["items"], f"{where}[{i}]")


@pytest.fixture(scope="module")
def episode(smoke_dataset):
    """(path, {topic: [decoded messages]}, {topic: [log times]}, {topic: (schema name, encoding, schema)})."""
    _, out, _ = smoke_dataset
    row = next(json.loads(r) for r in (out / "manifest.jsonl").read_text().splitlines() if r)
    path = out / row["file"]
    msgs, times, schemas = {}, {}, {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            msgs.setdefault(channel.topic, []).append(json.loads(message.data))
            times.setdefault(channel.topic, []).append(message.log_time)
            schemas[channel.topic] = (schema.name, schema.encoding, json.loads(schema.data), channel.message_encoding)
    return path, msgs, times, schemas


def test_every_message_matches_its_channels_jsonschema(episode):
    _, msgs, _, schemas = episode
    assert {"/tf", "/scene", "/robot_state", "/action", "/task_state", "/sim_state", "/head_cam/image"} <= set(msgs)
    assert schemas["/tf"][0] == "foxglove.FrameTransforms" and schemas["/scene"][0] == "foxglove.SceneUpdate"
    for topic, (name, encoding, schema, message_encoding) in schemas.items():
        assert encoding == "jsonschema" and message_encoding == "json" and schema["title"] == name
        for t, m in enumerate(msgs[topic]):
            conforms(m, schema, f"{topic}[{t}]")
    assert len(msgs["/scene"]) == 1 and len(msgs["/tf"]) == len(msgs["/robot_state"])


def test_named_fields_round_trip_in_name_order(episode):
    path, msgs, _, _ = episode
    ep = read_episode(path, cameras=())
    assert list(msgs["/robot_state"][0]) == list(PROPRIO_NAMES) and list(msgs["/action"][0]) == list(ACTION_NAMES)
    np.testing.assert_array_equal(np.array([[m[n] for n in PROPRIO_NAMES] for m in msgs["/robot_state"]], np.float32),
                                  ep["proprio"])
    np.testing.assert_array_equal(np.array([[m[n] for n in ACTION_NAMES] for m in msgs["/action"]], np.float32),
                                  ep["action"])
    assert ep["proprio"].dtype == ep["action"].dtype == np.float32 and ep["action"].shape[1] == len(ACTION_NAMES)


def test_log_times_start_at_the_fixed_epoch_and_step_by_control_dt(episode):
    _, msgs, times, _ = episode
    steps = np.array([m["step"] for m in msgs["/task_state"]])
    expected = EPOCH_NS + np.round(steps * CONTROL_DT * 1e9).astype(np.int64)
    assert EPOCH_NS == 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z
    np.testing.assert_array_equal(np.array(times["/task_state"]), expected)
    np.testing.assert_array_equal(np.array(times["/tf"]), expected)
    assert times["/scene"] == [EPOCH_NS] and times["/action"] == list(expected[:-1])
    stamp = msgs["/head_cam/image"][3]["timestamp"]
    assert stamp["sec"] * 10**9 + stamp["nsec"] == expected[3]


def _world_pose(tf_msg, frame):
    """World pose ((3,), (4,) w, x, y, z) of `frame` composed along the message's transform tree."""
    by_child = {t["child_frame_id"]: t for t in tf_msg["transforms"]}
    pos, quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
    while frame != "world":
        t = by_child[frame]
        p = np.array([t["translation"][k] for k in "xyz"])
        q = np.array([t["rotation"][k] for k in "wxyz"])
        rotated = np.empty(3)
        mujoco.mju_rotVecQuat(rotated, pos, q)
        pos = p + rotated
        out = np.empty(4)
        mujoco.mju_mulQuat(out, q, quat)
        quat = out
        frame = t["parent_frame_id"]
    return pos, quat


def test_transforms_put_the_mug_and_the_hands_where_the_state_says(episode):
    path, msgs, _, _ = episode
    ep = read_episode(path, cameras=())
    model = load_model()
    adr = scene_index(model).mug_qpos
    data = mujoco.MjData(model)
    n = len(msgs["/tf"])
    for t in (0, n // 2, n - 1):
        # the mug's free joint is its world pose: position, then (w, x, y, z)
        p, q = _world_pose(msgs["/tf"][t], "mug")
        np.testing.assert_allclose(p, ep["qpos"][t, adr:adr + 3], atol=2 * TOL)
        ref = ep["qpos"][t, adr + 3:adr + 7]
        assert min(np.abs(q - ref).max(), np.abs(q + ref).max()) < 4 * TOL
        # a hand, five transforms down the robot's tree, against MuJoCo's forward kinematics
        data.qpos[:], data.mocap_pos[:] = ep["qpos"][t], ep["mocap_pos"][t]
        mujoco.mj_forward(model, data)
        for hand in ("left_hand", "right_hand"):
            p, _ = _world_pose(msgs["/tf"][t], hand)
            np.testing.assert_allclose(p, data.body(hand).xpos, atol=10 * TOL)
        # the head camera's optical axis (+z) is MuJoCo's camera -z
        _, q = _world_pose(msgs["/tf"][t], "head_cam")
        axis = np.empty(3)
        mujoco.mju_rotVecQuat(axis, np.array([0.0, 0.0, 1.0]), q)
        np.testing.assert_allclose(axis, -data.cam("head_cam").xmat.reshape(3, 3)[:, 2], atol=10 * TOL)


def test_scene_has_one_entity_per_visible_geom_posed_as_mujoco_places_it(episode):
    path, msgs, _, _ = episode
    model = load_model()
    ep = read_episode(path, cameras=())
    entities = msgs["/scene"][0]["entities"]
    visible = [g for g in range(model.ngeom) if model.geom_rgba[g, 3] > 0]
    assert len(entities) == len(visible) == len({e["id"] for e in entities})
    moving = {t["child_frame_id"] for t in msgs["/tf"][0]["transforms"]}
    data = mujoco.MjData(model)
    data.qpos[:], data.mocap_pos[:] = ep["qpos"][0], ep["mocap_pos"][0]
    mujoco.mj_forward(model, data)
    static = 0
    for g, e in zip(visible, entities):
        assert e["id"] == (model.geom(g).name or f"geom_{g}")
        assert e["frame_id"] == "world" or e["frame_id"] in moving
        assert e["frame_locked"] == (e["frame_id"] != "world")
        if e["frame_id"] == "world":  # drawn where MuJoCo puts it at t = 0
            static += 1
            prim = (e["cubes"] + e["cylinders"] + e["spheres"])[0]
            np.testing.assert_allclose([prim["pose"]["position"][k] for k in "xyz"], data.geom_xpos[g], atol=TOL)
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
                np.testing.assert_allclose([prim["size"][k] for k in "xyz"], 2 * model.geom_size[g], atol=TOL)
                assert [prim["color"][k] for k in "rgba"] == pytest.approx(model.geom_rgba[g], abs=TOL)
    world_geoms = [g for g in visible if model.geom_bodyid[g] == 0]
    assert static >= len(world_geoms) > 0


def _corrupt(src: Path, dst: Path, offset: int) -> None:
    shutil.copy(src, dst)
    raw = bytearray(dst.read_bytes())
    raw[offset] ^= 0xFF
    dst.write_bytes(bytes(raw))


def test_a_flipped_byte_in_the_data_is_caught_by_the_checksums(episode, tmp_path):
    path, _, _, _ = episode
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    with open(path, "rb") as f:
        data_end = [r for r in StreamReader(f).records if isinstance(r, DataEnd)]
    assert len(data_end) == 1 and data_end[0].data_section_crc != 0  # the data section's CRC is written
    assert all(c.compression == "zstd" for c in summary.chunk_indexes)
    chunk = summary.chunk_indexes[0]
    bad = tmp_path / path.name
    _corrupt(path, bad, chunk.chunk_start_offset + chunk.chunk_length // 2)
    with pytest.raises(CorruptEpisode, match=path.name):
        read_episode(bad, cameras=())
    # a byte of the chunk's header (its start time) only the data section's CRC covers
    _corrupt(path, bad, chunk.chunk_start_offset + 1 + 8 + 2)
    with pytest.raises(CorruptEpisode, match=path.name):
        read_episode(bad, cameras=())


def _fields(obj, prefix=""):
    """Every field path of a decoded message: `a`, `a.b`, ..."""
    for k, v in obj.items():
        yield prefix + k
        if isinstance(v, dict):
            yield from _fields(v, prefix + k + ".")


def test_layout_is_json_and_names_only_topics_and_fields_the_files_have(episode):
    _, msgs, _, _ = episode
    layout = json.loads(LAYOUT.read_text())
    panels = layout["configById"]
    assert {p.split("!")[0] for p in panels} == {"Image", "3D", "Plot"}

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)
    image = next(c for p, c in panels.items() if p.startswith("Image!"))
    assert image["imageMode"]["imageTopic"] in msgs
    scene = next(c for p, c in panels.items() if p.startswith("3D!"))
    assert set(scene["topics"]) <= set(msgs)
    assert scene["followTf"] in {t["child_frame_id"] for t in msgs["/tf"][0]["transforms"]}
    plotted = [s["value"] for p, c in panels.items() if p.startswith("Plot!") for s in c["paths"]]
    assert "/task_state.progress" in plotted and "/task_state.success" in plotted
    for value in plotted:
        topic, field = value.split(".", 1)
        assert topic in msgs and field in set(_fields(msgs[topic][0])), value
