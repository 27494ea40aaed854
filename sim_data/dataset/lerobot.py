"""LeRobot export: a dataset's episodes (scripted, play, programs and policy rollouts alike) in
LeRobot's dataset layout v3.0, which `lerobot.datasets.lerobot_dataset.LeRobotDataset(repo_id,
root=OUT)` opens.

    python -m sim_data.dataset.lerobot DATA OUT [--overwrite]
    make export-lerobot DATA=runs/data/demo OUT=runs/lerobot/demo

OUT holds

| path | content |
|---|---|
| `meta/info.json` | `codebase_version` v3.0, fps (the 20 Hz control rate), the features (dtype, shape, names), totals, splits, path templates |
| `meta/stats.json` | per feature min, max, mean, std, count, q01..q99 (images per channel, in [0, 1]) |
| `meta/tasks.parquet` | one instruction per task (`sim_data.sim.tasks.TASK_TEXT`) and its `task_index` |
| `meta/episodes/chunk-000/file-000.parquet` | per episode its length, task, frame range, data and video file and time range, stats, and the source dataset's episode id, policy, policy kind, skill, seed, success and split |
| `data/chunk-CCC/file-FFF.parquet` | one row per frame: `action` (20), `observation.state` (37), `next.success`, `next.done`, `timestamp`, `frame_index`, `episode_index`, `index`, `task_index` |
| `videos/observation.images.head_cam/chunk-CCC/file-FFF.mp4` | the head camera, H.264 (yuv420p, a key frame every 2 frames), episodes one after another |

A frame is one control step: observation t and the action taken at t, with `next.success` the
success flag after that action. An MCAP episode of T actions gives T frames; its last observation
(after the last action) has no action and is left out. Episodes are ordered by split (train, val,
test, programs), so that each split is one range of episode indices in `info.json`'s `splits`.
Everything is written into `OUT.tmp` and renamed to OUT when whole.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

from sim_data.dataset.episodes import read_episode, read_episode_meta
from sim_data.sim.render import HEAD_CAMERA
from sim_data.sim.robot import ACTION_NAMES, PROPRIO_NAMES
from sim_data.sim.tasks import CONTROL_DT, TASK_TEXT
from sim_data.util import run_cli
from sim_data.video import CODEC, PIX_FMT, Mp4Writer

CODEBASE_VERSION = "v3.0"
FPS = round(1 / CONTROL_DT)
VIDEO_KEY = f"observation.images.{HEAD_CAMERA}"
SPLIT_ORDER = ("train", "val", "test", "programs")
# LeRobot's defaults (lerobot.datasets.utils): files per chunk directory, and the size at which a
# data or video file is closed and the next one begun
CHUNKS_SIZE = 1000
DATA_FILE_MB = 100
VIDEO_FILE_MB = 200
VIDEO_GOP = 2  # LeRobot's encoder default: any frame decodes after at most one other
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}"
DATA_PATH = "data/" + CHUNK_FILE + ".parquet"
VIDEO_PATH = "videos/{video_key}/" + CHUNK_FILE + ".mp4"
EPISODES_PATH = "meta/episodes/" + CHUNK_FILE + ".parquet"
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
# the source dataset's manifest columns kept in the episodes table
EPISODE_COLUMNS = ("episode_id", "policy", "policy_kind", "skill", "seed", "success", "split", "heldout")


def features(height: int, width: int) -> dict:
    """info.json's features: per column its dtype, shape and names (LeRobot's schema)."""
    scalar = {"shape": [1], "names": None}
    return {
        "action": {"dtype": "float32", "shape": [len(ACTION_NAMES)], "names": list(ACTION_NAMES)},
        "observation.state": {"dtype": "float32", "shape": [len(PROPRIO_NAMES)], "names": list(PROPRIO_NAMES)},
        VIDEO_KEY: {"dtype": "video", "shape": [height, width, 3], "names": ["height", "width", "channels"],
                    "info": {"video.height": height, "video.width": width, "video.codec": "h264",
                             "video.pix_fmt": PIX_FMT, "video.is_depth_map": False, "video.fps": FPS,
                             "video.channels": 3, "video.g": VIDEO_GOP, "has_audio": False}},
        "next.success": {"dtype": "bool", **scalar},
        "next.done": {"dtype": "bool", **scalar},
        "timestamp": {"dtype": "float32", **scalar},
        "frame_index": {"dtype": "int64", **scalar},
        "episode_index": {"dtype": "int64", **scalar},
        "index": {"dtype": "int64", **scalar},
        "task_index": {"dtype": "int64", **scalar},
    }


# ---- inputs -------------------------------------------------------------------------------------------

def read_manifest(data: Path) -> list[dict]:
    """The rows of DATA/manifest.jsonl, ordered by split (SPLIT_ORDER, others after) and then as listed.

    Raises FileNotFoundError or ValueError naming what is missing: the directory, its manifest, an
    episode file, or any episode at all.
    """
    data = Path(data)
    if not data.is_dir():
        raise FileNotFoundError(f"the dataset {data} does not exist (make data OUT={data})")
    path = data / "manifest.jsonl"
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing: {data} is not a dataset written by sim_data.dataset.generate")
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if not rows:
        raise ValueError(f"{path} lists no episodes: nothing to export")
    missing = [r["file"] for r in rows if not (data / r["file"]).exists()]
    if missing:
        raise FileNotFoundError(f"{data}: {len(missing)} episode files of the manifest are missing, e.g. {missing[0]}")
    unknown = sorted({r["task"] for r in rows} - set(TASK_TEXT))
    if unknown:
        raise ValueError(f"{path}: tasks {unknown} have no instruction in sim_data.sim.tasks.TASK_TEXT")
    rank = {s: i for i, s in enumerate(SPLIT_ORDER)}
    return sorted(rows, key=lambda r: rank.get(r["split"], len(rank)))


def check_cameras(data: Path, rows: list[dict]) -> None:
    """Raises ValueError naming the first episode recorded without the head camera."""
    for r in rows:
        if HEAD_CAMERA not in read_episode_meta(Path(data) / r["file"]).get("cameras", []):
            raise ValueError(f"{Path(data) / r['file']}: recorded without the {HEAD_CAMERA} camera, which the export needs")


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"the output {out} is a file; name a directory")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ValueError(f"the output {out} is not empty; name a new directory or pass --overwrite")


# ---- statistics ------------------------------------------------------------------------------------------

def column_stats(x: np.ndarray) -> dict:
    """LeRobot's per-feature statistics of x (N, D) over its N frames: each (D,) float64, count (1,)."""
    x = np.asarray(x, np.float64).reshape(len(x), -1)
    out = {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0), "count": np.array([len(x)])}
    out.update({f"q{round(q * 100):02d}": np.quantile(x, q, axis=0) for q in QUANTILES})
    return out


def image_stats(frames: np.ndarray) -> dict:
    """Per-channel statistics of frames (T, H, W, 3) uint8 scaled to [0, 1]: each (3, 1, 1), count (1,)
    the number of frames (LeRobot's layout for camera features)."""
    pixels = frames.reshape(-1, 3) / 255.0
    s = column_stats(pixels)
    return {k: (v if k == "count" else v.reshape(3, 1, 1)) for k, v in s.items()} | {"count": np.array([len(frames)])}


def aggregate_stats(per_episode: list[dict]) -> dict:
    """Dataset statistics from episodes' (LeRobot's aggregation): frame-weighted mean and pooled std,
    extreme min and max, and for the quantiles an envelope (min of the lower, max of the upper ones)."""
    out = {}
    for key in per_episode[0]:
        ss = [e[key] for e in per_episode]
        counts = np.array([s["count"][0] for s in ss], np.float64)
        w = counts.reshape(-1, *[1] * ss[0]["mean"].ndim) / counts.sum()
        means, stds = np.stack([s["mean"] for s in ss]), np.stack([s["std"] for s in ss])
        mean = (w * means).sum(0)
        agg = {"min": np.min([s["min"] for s in ss], 0), "max": np.max([s["max"] for s in ss], 0), "mean": mean,
               "std": np.sqrt((w * (stds**2 + (means - mean) ** 2)).sum(0)), "count": np.array([int(counts.sum())])}
        for q in QUANTILES:
            name = f"q{round(q * 100):02d}"
            agg[name] = (np.min if q <= 0.5 else np.max)([s[name] for s in ss], 0)
        out[key] = agg
    return out


def _jsonable(stats: dict) -> dict:
    return {k: {s: np.asarray(v).tolist() for s, v in d.items()} for k, d in stats.items()}


# ---- writers ---------------------------------------------------------------------------------------------

class _FileIndex:
    """Where the next file goes: chunk-CCC/file-FFF, CHUNKS_SIZE files per chunk."""

    def __init__(self):
        self.chunk_index, self.file_index = 0, 0

    def advance(self) -> None:
        self.file_index += 1
        if self.file_index == CHUNKS_SIZE:
            self.chunk_index, self.file_index = self.chunk_index + 1, 0

    def path(self, root: Path, template: str, **kw) -> Path:
        p = root / template.format(chunk_index=self.chunk_index, file_index=self.file_index, **kw)
        p.parent.mkdir(parents=True, exist_ok=True)
        return p


class _DataFiles:
    """Frame tables into data/chunk-CCC/file-FFF.parquet, a new file past DATA_FILE_MB (uncompressed)."""

    def __init__(self, root: Path):
        self.root, self.at = root, _FileIndex()
        self._writer, self._bytes = None, 0

    def write(self, table: pa.Table) -> tuple[int, int]:
        """Appends one episode's table; returns its (chunk_index, file_index)."""
        if self._writer is not None and self._bytes + table.nbytes > DATA_FILE_MB * 2**20:
            self._writer.close()
            self._writer, self._bytes = None, 0
            self.at.advance()
        if self._writer is None:
            self._writer = pq.ParquetWriter(self.at.path(self.root, DATA_PATH), table.schema, compression="snappy")
        self._writer.write_table(table)
        self._bytes += table.nbytes
        return self.at.chunk_index, self.at.file_index

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()


class _VideoFiles:
    """One camera's episodes into videos/KEY/chunk-CCC/file-FFF.mp4, a new file past VIDEO_FILE_MB."""

    def __init__(self, root: Path, key: str):
        self.root, self.key, self.at = root, key, _FileIndex()
        self._writer = None

    def write(self, frames: np.ndarray) -> dict:
        """Appends one episode's frames (T, H, W, 3) uint8; returns its episodes-table columns."""
        if self._writer is not None and self._writer.bytes_written() > VIDEO_FILE_MB * 2**20:
            self._writer.close()
            self._writer = None
            self.at.advance()
        if self._writer is None:
            self._writer = Mp4Writer(self.at.path(self.root, VIDEO_PATH, video_key=self.key), FPS, gop=VIDEO_GOP)
        start, end = self._writer.append(frames)
        p = f"videos/{self.key}/"
        return {p + "chunk_index": self.at.chunk_index, p + "file_index": self.at.file_index,
                p + "from_timestamp": start, p + "to_timestamp": end}

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()

    def abort(self) -> None:
        if self._writer is not None:
            self._writer.abort()


def frame_table(episode: dict, episode_index: int, first_index: int, task_index: int) -> pa.Table:
    """One episode's data rows: T frames from an episode of read_episode (action (T, 20), proprio
    (T+1, 37), success (T+1,))."""
    action = np.asarray(episode["action"], np.float32)
    n = len(action)
    state = np.asarray(episode["proprio"][:n], np.float32)
    frame_index = np.arange(n, dtype=np.int64)

    def vectors(x):
        return pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), x.shape[1])

    return pa.table({
        "action": vectors(action), "observation.state": vectors(state),
        "next.success": pa.array(np.asarray(episode["success"][1:], bool)),
        "next.done": pa.array(frame_index == n - 1),
        "timestamp": pa.array((frame_index * CONTROL_DT).astype(np.float32)),
        "frame_index": pa.array(frame_index),
        "episode_index": pa.array(np.full(n, episode_index, np.int64)),
        "index": pa.array(first_index + frame_index),
        "task_index": pa.array(np.full(n, task_index, np.int64)),
    })


def episode_stats(table: pa.Table, frames: np.ndarray) -> dict:
    """Per-feature statistics of one episode's rows and camera frames (T, H, W, 3) uint8."""
    stats = {}
    for name in table.column_names:
        col = table.column(name).combine_chunks()
        x = (col.flatten().to_numpy().reshape(len(col), -1) if pa.types.is_fixed_size_list(col.type)
             else col.to_numpy(zero_copy_only=False).reshape(-1, 1))
        stats[name] = column_stats(x)
    stats[VIDEO_KEY] = image_stats(frames)
    return stats


def _tasks_table(tasks: list[str]) -> pa.Table:
    """meta/tasks.parquet: the task text as the pandas index `task`, as LeRobot's loader expects."""
    pandas_meta = {"index_columns": ["task"], "column_indexes": [], "columns": [
        {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
         "metadata": None},
        {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": None}],
        "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "2.2.0"}
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": pa.array(tasks, pa.string())})
    return table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})


def _episodes_table(records: list[dict]) -> pa.Table:
    columns = {k: [r[k] for r in records] for k in records[0]}
    return pa.table({k: pa.array([np.asarray(v).tolist() if isinstance(v, np.ndarray) else v for v in vs])
                     for k, vs in columns.items()})


def _splits(rows: list[dict]) -> dict:
    splits, start = {}, 0
    for i, r in enumerate(rows + [{"split": None}]):
        if i == len(rows) or r["split"] != rows[start]["split"]:
            splits[rows[start]["split"]] = f"{start}:{i}"
            start = i
    return splits


# ---- the export ----------------------------------------------------------------------------------------

def export(data: Path, out: Path, overwrite: bool = False, progress: bool = False) -> dict:
    """Writes the dataset in DATA as a LeRobot v3.0 dataset in OUT; returns its info.json.

    Raises FileNotFoundError, NotADirectoryError or ValueError for a missing or empty dataset,
    an episode without the head camera, or an OUT that is a file or a non-empty directory (unless
    overwrite).
    """
    data, out = Path(data), Path(out)
    rows = read_manifest(data)
    if out.resolve() == data.resolve() or out.resolve() in data.resolve().parents:
        raise ValueError(f"OUT {out} is the dataset {data} or holds it: an export there would replace the "
                         "dataset; choose another OUT")
    _check_out(out, overwrite)
    check_cameras(data, rows)
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        info = _write(data, tmp, rows, progress)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _replace_dir(tmp, out)
    return info


def _write(data: Path, tmp: Path, rows: list[dict], progress: bool) -> dict:
    """Every file of the export into tmp; returns info.json's contents."""
    tasks = list(dict.fromkeys(TASK_TEXT[r["task"]] for r in rows))
    data_files, videos = _DataFiles(tmp), _VideoFiles(tmp, VIDEO_KEY)
    records, per_episode, total, size = [], [], 0, None
    try:
        for i, row in enumerate(tqdm(rows, desc="export", unit="ep", disable=not progress)):
            ep = read_episode(data / row["file"], cameras=(HEAD_CAMERA,), sim_state=False)
            task = TASK_TEXT[row["task"]]
            table = frame_table(ep, i, total, tasks.index(task))
            n = table.num_rows
            frames = ep["frames"][HEAD_CAMERA][:n]
            size = size or frames.shape[1:3]
            chunk, file = data_files.write(table)
            stats = episode_stats(table, frames)
            per_episode.append(stats)
            records.append({"episode_index": i, "tasks": [task], "length": n,
                            "data/chunk_index": chunk, "data/file_index": file,
                            "dataset_from_index": total, "dataset_to_index": total + n, **videos.write(frames),
                            "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
                            **{f"stats/{k}/{s}": v for k, d in stats.items() for s, v in d.items()},
                            **{k: row.get(k) for k in EPISODE_COLUMNS}})
            total += n
        data_files.close()
        videos.close()
    except BaseException:
        data_files.close()
        videos.abort()
        raise
    pq.write_table(_episodes_table(records), _FileIndex().path(tmp, EPISODES_PATH))
    pq.write_table(_tasks_table(tasks), tmp / "meta" / "tasks.parquet")
    (tmp / "meta" / "stats.json").write_text(json.dumps(_jsonable(aggregate_stats(per_episode)), indent=1))
    info = {"codebase_version": CODEBASE_VERSION, "robot_type": "wmlab_humanoid", "fps": FPS,
            "total_episodes": len(records), "total_frames": total, "total_tasks": len(tasks),
            "chunks_size": CHUNKS_SIZE, "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB,
            "splits": _splits(rows), "data_path": DATA_PATH, "video_path": VIDEO_PATH, "features": features(*size)}
    (tmp / "meta" / "info.json").write_text(json.dumps(info, indent=2))
    return info


def _replace_dir(tmp: Path, out: Path) -> None:
    """Puts the finished tmp at out; a previous out (--overwrite) is removed only after."""
    old = out.with_name(out.name + ".old")
    if out.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(out, old)
    os.replace(tmp, out)
    shutil.rmtree(old, ignore_errors=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path, help="a dataset directory (make data OUT)")
    p.add_argument("out", type=Path, help="the LeRobot dataset directory to write (new or empty)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUT")
    a = p.parse_args(argv)
    info = export(a.data, a.out, a.overwrite, progress=True)
    print(f"{a.out}: LeRobot {info['codebase_version']}, {info['total_episodes']} episodes, "
          f"{info['total_frames']} frames at {info['fps']} fps, {info['total_tasks']} tasks, video {CODEC}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
