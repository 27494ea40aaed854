"""The LeRobot export of the smoke dataset read back: every parquet file with pyarrow, the metadata,
the video with PyAV against the MCAP episodes, and with LeRobot's own dataset class where the
`lerobot` extra is installed."""

import json
import shutil

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from sim_data.dataset import lerobot as L
from sim_data.dataset.episodes import (
    CorruptEpisode,
    read_episode,
    read_episode_meta,
    write_episode_mcap,
)
from sim_data.sim.robot import ACTION_NAMES, PROPRIO_NAMES
from sim_data.sim.tasks import TASK_TEXT

# JPEG (quality 90) in the MCAP files, then H.264 at crf 18 with 4:2:0 chroma: mean absolute
# difference per pixel and channel, out of 255
VIDEO_TOLERANCE = 4.0


@pytest.fixture(scope="module")
def export(smoke_dataset, tmp_path_factory):
    """(data dir, export dir, info, manifest rows in export order, their episodes read from MCAP)."""
    _, data, _ = smoke_dataset
    out = tmp_path_factory.mktemp("lerobot") / "smoke"
    info = L.export(data, out)
    rows = L.read_manifest(data)
    episodes = [read_episode(data / r["file"], cameras=("head_cam",), sim_state=False) for r in rows]
    return data, out, info, rows, episodes


def _episodes_table(out):
    return pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()


def test_frames_parquet_holds_every_step_of_every_episode(export):
    _, out, info, rows, episodes = export
    table = pq.read_table(out / "data/chunk-000/file-000.parquet")
    lengths = [len(e["action"]) for e in episodes]
    assert table.num_rows == sum(lengths) == info["total_frames"]
    assert table.schema.field("action").type == pa.list_(pa.float32(), 20)
    assert table.schema.field("observation.state").type == pa.list_(pa.float32(), 37)
    for name, dtype in (("next.success", pa.bool_()), ("next.done", pa.bool_()), ("timestamp", pa.float32()),
                        ("frame_index", pa.int64()), ("episode_index", pa.int64()), ("index", pa.int64()),
                        ("task_index", pa.int64())):
        assert table.schema.field(name).type == dtype, name
    assert set(table.column_names) == {k for k, f in info["features"].items() if f["dtype"] != "video"}
    col = {k: table.column(k).to_numpy() for k in ("episode_index", "frame_index", "index", "task_index",
                                                   "timestamp", "next.success", "next.done")}
    action = np.stack(table.column("action").to_numpy(zero_copy_only=False))
    state = np.stack(table.column("observation.state").to_numpy(zero_copy_only=False))
    np.testing.assert_array_equal(col["index"], np.arange(table.num_rows))
    tasks = pq.read_table(out / "meta/tasks.parquet").to_pylist()
    start = 0
    for i, (row, ep, n) in enumerate(zip(rows, episodes, lengths, strict=True)):
        s = slice(start, start + n)
        assert (col["episode_index"][s] == i).all() and (col["episode_index"] == i).sum() == n
        np.testing.assert_array_equal(col["frame_index"][s], np.arange(n))
        np.testing.assert_allclose(col["timestamp"][s], np.arange(n) * 0.05, atol=1e-6)
        np.testing.assert_array_equal(action[s], ep["action"])
        np.testing.assert_array_equal(state[s], ep["proprio"][:n])
        np.testing.assert_array_equal(col["next.success"][s], ep["success"][1:])
        assert col["next.done"][s].tolist() == [False] * (n - 1) + [True]
        assert {tasks[t]["task"] for t in col["task_index"][s]} == {TASK_TEXT[row["task"]]}
        start += n


def test_metadata_describes_the_export(export):
    data, out, info, rows, episodes = export
    assert info == json.loads((out / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 20
    assert info["total_episodes"] == len(rows) == len((data / "manifest.jsonl").read_text().splitlines())
    assert info["total_tasks"] == len({r["task"] for r in rows})
    f = info["features"]
    assert f["action"]["names"] == list(ACTION_NAMES) and f["observation.state"]["names"] == list(PROPRIO_NAMES)
    assert f["observation.images.head_cam"]["dtype"] == "video"
    assert f["observation.images.head_cam"]["shape"] == list(episodes[0]["frames"]["head_cam"].shape[1:])
    assert (out / info["data_path"].format(chunk_index=0, file_index=0)).exists()
    assert (out / info["video_path"].format(video_key="observation.images.head_cam", chunk_index=0, file_index=0)).exists()
    # each split one range of episode indices, as the rows are ordered
    for split, span in info["splits"].items():
        a, b = map(int, span.split(":"))
        assert {r["split"] for r in rows[a:b]} == {split}
    assert sum(int(s.split(":")[1]) - int(s.split(":")[0]) for s in info["splits"].values()) == len(rows)

    eps = _episodes_table(out)
    assert [e["episode_index"] for e in eps] == list(range(len(rows)))
    total = 0
    for e, row, ep in zip(eps, rows, episodes, strict=True):
        n = len(ep["action"])
        assert e["length"] == n and (e["dataset_from_index"], e["dataset_to_index"]) == (total, total + n)
        assert e["tasks"] == [TASK_TEXT[row["task"]]]
        assert e["videos/observation.images.head_cam/from_timestamp"] == pytest.approx(total / 20)
        assert e["videos/observation.images.head_cam/to_timestamp"] == pytest.approx((total + n) / 20)
        assert (e["episode_id"], e["policy"], e["success"], e["split"]) == (
            row["episode_id"], row["policy"], row["success"], row["split"])
        np.testing.assert_allclose(e["stats/action/mean"], ep["action"].mean(0), rtol=1e-5, atol=1e-6)
        total += n

    stats = json.loads((out / "meta/stats.json").read_text())
    actions = np.concatenate([ep["action"] for ep in episodes]).astype(np.float64)
    np.testing.assert_allclose(stats["action"]["mean"], actions.mean(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(stats["action"]["std"], actions.std(0), rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(stats["action"]["min"], actions.min(0))
    assert stats["action"]["count"] == [len(actions)]
    frames = np.concatenate([ep["frames"]["head_cam"][: len(ep["action"])] for ep in episodes]) / 255.0
    image = np.array(stats["observation.images.head_cam"]["mean"])
    assert image.shape == (3, 1, 1)
    np.testing.assert_allclose(image.ravel(), frames.reshape(-1, 3).mean(0), atol=1e-6)


def test_video_frames_match_the_mcap_frames(export):
    _, out, info, _, episodes = export
    path = out / info["video_path"].format(video_key="observation.images.head_cam", chunk_index=0, file_index=0)
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec.name == "h264" and stream.pix_fmt == "yuv420p"
        decoded = [(float(f.time), f.to_ndarray(format="rgb24")) for f in container.decode(stream)]
    times = np.array([t for t, _ in decoded])
    video = np.stack([f for _, f in decoded])
    assert len(video) == info["total_frames"]
    for e, ep in zip(_episodes_table(out), episodes, strict=True):
        # LeRobot finds frame k of an episode at from_timestamp + k / fps
        first = round(e["videos/observation.images.head_cam/from_timestamp"] * 20)
        n = e["length"]
        np.testing.assert_allclose(times[first:first + n], e["videos/observation.images.head_cam/from_timestamp"]
                                   + np.arange(n) / 20, atol=1e-4)
        real = ep["frames"]["head_cam"][:n].astype(np.float64)
        assert np.abs(video[first:first + n] - real).mean() < VIDEO_TOLERANCE


def test_inputs_and_outputs_are_checked_before_writing(export, tmp_path):
    data, out, *_ = export
    with pytest.raises(FileNotFoundError, match="does not exist"):
        L.export(tmp_path / "nosuch", tmp_path / "a")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "manifest.jsonl").write_text("")
    with pytest.raises(ValueError, match="lists no episodes"):
        L.export(tmp_path / "empty", tmp_path / "a")
    (tmp_path / "file").write_text("x")
    with pytest.raises(NotADirectoryError, match="is a file"):
        L.export(data, tmp_path / "file")
    with pytest.raises(ValueError, match="not empty"):
        L.export(data, out)
    # an episode recorded with the external camera only
    row = json.loads((data / "manifest.jsonl").read_text().splitlines()[0])
    ep = read_episode(data / row["file"], cameras=("ext_cam",))
    meta = dict(read_episode_meta(data / row["file"]), cameras=["ext_cam"])
    (tmp_path / "ext" / "episodes").mkdir(parents=True)
    write_episode_mcap(tmp_path / "ext" / row["file"], ep, meta, jpeg_quality=90)
    (tmp_path / "ext" / "manifest.jsonl").write_text(json.dumps(row) + "\n")
    with pytest.raises(ValueError, match="without the head_cam camera"):
        L.export(tmp_path / "ext", tmp_path / "a")
    assert not (tmp_path / "a").exists() and not (tmp_path / "a.tmp").exists()


def test_a_failed_export_leaves_nothing_and_overwrite_replaces(export, tmp_path):
    data, _, info, rows, _ = export
    broken = tmp_path / "data"
    shutil.copytree(data, broken, ignore=shutil.ignore_patterns("cache"))
    last = broken / rows[-1]["file"]
    last.write_bytes(last.read_bytes()[: last.stat().st_size // 2])
    with pytest.raises(CorruptEpisode):
        L.export(broken, tmp_path / "out")
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.tmp").exists()
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "stale").write_text("x")
    assert L.export(data, tmp_path / "out", overwrite=True) == info
    assert not (tmp_path / "out" / "stale").exists() and (tmp_path / "out" / "meta" / "info.json").exists()
    for onto in (data, data.parent):  # an OUT that is the dataset or holds it would replace it
        with pytest.raises(ValueError, match="would replace the dataset"):
            L.export(data, onto, overwrite=True)
    assert (data / "manifest.jsonl").exists()


def test_lerobot_reads_the_export(export):
    lerobot_dataset = pytest.importorskip("lerobot.datasets.lerobot_dataset", reason="the lerobot extra")
    _, out, info, rows, episodes = export
    ds = lerobot_dataset.LeRobotDataset("wmlab/smoke", root=out, video_backend="pyav")
    assert len(ds) == info["total_frames"] and ds.num_episodes == len(rows) and ds.fps == 20
    starts = np.cumsum([0] + [len(e["action"]) for e in episodes])
    for i in (0, len(rows) - 1):
        for k in (0, len(episodes[i]["action"]) - 1):
            item = ds[int(starts[i] + k)]
            assert int(item["episode_index"]) == i and int(item["frame_index"]) == k
            assert item["task"] == TASK_TEXT[rows[i]["task"]]
            np.testing.assert_array_equal(item["action"].numpy(), episodes[i]["action"][k])
            np.testing.assert_array_equal(item["observation.state"].numpy(), episodes[i]["proprio"][k])
            image = item["observation.images.head_cam"].numpy().transpose(1, 2, 0) * 255  # (3, H, W) in [0, 1]
            assert np.abs(image - episodes[i]["frames"]["head_cam"][k]).mean() < VIDEO_TOLERANCE
