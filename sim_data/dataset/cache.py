"""The training cache: a dataset's episodes as memory-mapped arrays, built from its MCAP files alone,
and a loader of shuffled fixed-length windows.

    python -m sim_data.dataset.cache build OUT            # build, or finish a killed build
    python -m sim_data.dataset.cache rebuild OUT          # from scratch, from OUT/episodes/*.mcap alone
    python -m sim_data.dataset.cache rebuild OUT --skip-corrupt   # leave out unreadable files, listed in index.json
    python -m sim_data.dataset.cache info OUT

Layout of `OUT/cache/`: shards `shard-00000/` .. of up to `shard_episodes` episodes (files in name
order), each holding `<camera>.npy` (N, H, W, 3) uint8, `proprio.npy` (N, 37) float32,
`action.npy` (N, 20) float32 (row t is the action taken after frame t; zeros after an episode's
last frame), `success.npy` (N,) bool, `progress.npy` (N,) float32 (task progress in [0, 1]) and
`scene.npy` (N, 24) float32 (the scene's state, `sim_data.sim.scene.scene_state`, from the recorded
qpos and mocap positions), `grip_px.npy` (N, 2, 2) float32 (where the left and right grip sites appear
in the head camera's frame, image coordinates in [0, 1], NaN behind it: `sim_data.sim.render.grip_pixels`
of the same) and `episodes.json`; N counts frames (T+1 per episode).
`index.json`, written last, lists shards, episodes (with shard, start, length) and skipped
files. Shards are written under a temporary name and renamed when whole, so a killed build
resumes; the same MCAP files give the same bytes. A dataset that links another's episodes
(`generate --reuse`) copies their rows from the other's built cache (`build_cache(reuse=...)`), the
same bytes without decoding them again.
"""

from __future__ import annotations

import argparse
import collections
import concurrent.futures as cf
import contextlib
import functools
import hashlib
import json
import multiprocessing
import os
import shutil
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sim_data.dataset.episodes import CorruptEpisode, read_episode, read_episode_meta
from sim_data.sim.render import grip_pixels
from sim_data.sim.scene import load_model, scene_index, scene_state
from sim_data.util import run_cli, write_json_atomic

FORMAT = 4
EPISODE_KEYS = ("episode_id", "task", "policy", "policy_kind", "skill", "seed", "success", "split", "heldout")
ARRAYS = ("proprio", "action", "success", "progress", "scene", "grip_px")


def cache_dir(out: Path) -> Path:
    """The directory of the training cache of the dataset in out: out/cache."""
    return Path(out) / "cache"


def episode_files(out: Path) -> list[Path]:
    """The dataset's finished episode files, in name order."""
    files = sorted((Path(out) / "episodes").glob("*.mcap"))
    if not files:
        raise FileNotFoundError(f"{out}/episodes holds no .mcap files: generate a dataset first (make data)")
    return files


@functools.cache
def _home_scene_index():
    """The home scene's addresses, looked up once per decoding process."""
    return scene_index(load_model())


def _decode(path: Path, cameras) -> dict:
    """One episode's cache rows, or {"error": why} for a file that does not read back whole."""
    try:
        ep = read_episode(path, cameras=cameras)
    except CorruptEpisode as e:
        return {"error": str(e)}
    try:
        scene = scene_state(ep["qpos"], ep["mocap_pos"], _home_scene_index())
    except ValueError as e:
        return {"error": f"{path}: {e}"}
    grip = grip_pixels(load_model(), ep["qpos"], ep["mocap_pos"])
    n = ep["proprio"].shape[0]
    missing = [c for c in cameras if c not in ep["frames"]]
    if missing:
        return {"error": f"{path}: no camera {missing} (the dataset's other files have it)"}
    action = np.zeros((n, ep["action"].shape[1]), np.float32)
    action[: n - 1] = ep["action"]
    return {"record": _record(ep["meta"], f"episodes/{path.name}", n), "frames": ep["frames"], "proprio": ep["proprio"], "action": action, "success": ep["success"],
            "progress": ep["progress"], "scene": scene, "grip_px": grip}


SOURCES = "sources.json"  # a shard's episode files as they were when it was built (_file_stamps)


def _file_stamps(files) -> dict:
    """{file name: [size, modification time in ns]}: a file written again under its name (an episode
    simulated again, a corrupt one replaced) changes its stamp, so the shard that holds it is rebuilt."""
    return {f.name: [(st := f.stat()).st_size, st.st_mtime_ns] for f in files}


def _shard_current(shard: Path, group) -> bool:
    """Whether a built shard holds the episode files of group as they are now."""
    if not (shard / "episodes.json").exists() or not (shard / SOURCES).exists():
        return False
    return json.loads((shard / SOURCES).read_text()) == _file_stamps(group)


def _write_shard(root: Path, name: str, decoded: list, cameras, stamps: dict) -> dict:
    """Writes one shard (in name.tmp, renamed when whole) with its files' stamps; returns its summary."""
    tmp, final = root / f"{name}.tmp", root / name
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    (tmp / SOURCES).write_text(json.dumps(stamps))
    good = [d for d in decoded if "error" not in d]
    records, start = [], 0
    for d in good:
        records.append({**d["record"], "shard": name, "start": start})
        start += d["record"]["length"]
    for cam in cameras:
        np.save(tmp / f"{cam}.npy", np.concatenate([d["frames"][cam] for d in good]) if good
                         else np.zeros((0, 0, 0, 3), np.uint8))
    for k in ARRAYS:
        np.save(tmp / f"{k}.npy", np.concatenate([d[k] for d in good]) if good else np.zeros((0,)))
    skipped = [{"file": str(d.get("file", "")), "error": d["error"]} for d in decoded if "error" in d]
    summary = {"name": name, "frames": start, "episodes": records, "skipped": skipped}
    (tmp / "episodes.json").write_text(json.dumps(summary, indent=1))
    shutil.rmtree(final, ignore_errors=True)  # a shard built from the files as they were
    os.replace(tmp, final)
    return summary


def build_cache(out: Path, skip_corrupt: bool = False, workers: int | None = None, shard_episodes: int = 64,
                cameras=None, progress: bool = True, reuse: Path | None = None) -> dict:
    """Builds (or finishes) OUT/cache from OUT/episodes/*.mcap; returns the index written to index.json.

    Args:
      out: the dataset directory.
      skip_corrupt: leave out files that do not read back whole and list them in the index
        (`skipped`) and on stderr; without it such a file stops the build with an error naming it.
      workers: decoding processes (default: the CPU count, at most 16).
      shard_episodes: episodes per shard.
      cameras: cameras to cache (default: those of the first episode).
      reuse: a dataset whose built cache holds some of these episodes, from the same files (hard
        links: `generate --reuse`): their rows are copied from it instead of decoded again, the
        shards byte for byte those a decoding gives (reused_rows).
    """
    files = episode_files(out)
    root = cache_dir(out)
    root.mkdir(exist_ok=True)
    if cameras is None:
        cameras = _cameras_of(files, skip_corrupt)
    cameras = list(cameras)
    plan = {"format": FORMAT, "files": [p.name for p in files], "shard_episodes": shard_episodes, "cameras": cameras}
    plan_path = root / "plan.json"
    if plan_path.exists() and json.loads(plan_path.read_text()) != plan:
        for p in root.iterdir():  # the episode set changed: the old shards describe another dataset
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    write_json_atomic(plan_path, plan)  # a rerun compares against it to resume
    (root / "index.json").unlink(missing_ok=True)
    groups = [files[i:i + shard_episodes] for i in range(0, len(files), shard_episodes)]
    names = [f"shard-{i:05d}" for i in range(len(groups))]
    todo = [(n, g) for n, g in zip(names, groups) if not _shard_current(root / n, g)]
    stamps = {n: _file_stamps(g) for n, g in todo}  # before decoding: a file written meanwhile is built again
    bar = tqdm(total=sum(len(g) for _, g in todo), unit="ep", desc="cache", disable=not progress or not todo)
    workers = workers or min(16, os.cpu_count() or 1)
    copied = reused_rows(reuse, files, cameras) if reuse is not None else {}
    decoding = any(f.name not in copied for _, g in todo for f in g)
    pool = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) if decoding else None

    def start(group):  # a decoding for each file, or the reused cache's rows
        return [copied[f.name] if f.name in copied else pool.submit(_decode, f, cameras) for f in group]

    with pool or contextlib.nullcontext():
        submitted = [start(g) for _, g in todo[:2]]
        for k, (name, group) in enumerate(todo):
            if k + 2 < len(todo):  # keep the next shards decoding while this one is written
                submitted.append(start(todo[k + 2][1]))
            decoded = []
            for f, fut in zip(group, submitted[k]):
                d = fut.result() if isinstance(fut, cf.Future) else _copy_rows(*fut, cameras)
                if "error" in d:
                    if not skip_corrupt:
                        pool.shutdown(cancel_futures=True)
                        raise CorruptEpisode(d["error"] + " (python -m sim_data.dataset.cache rebuild OUT --skip-corrupt "
                                             "leaves such files out and lists them)")
                    d["file"] = f"episodes/{f.name}"
                decoded.append(d)
                bar.update(1)
            submitted[k] = None
            _write_shard(root, name, decoded, cameras, stamps[name])
    bar.close()
    index = _write_index(root, names, cameras)
    for s in index["skipped"]:
        print(f"skipped {s['file']}: {s['error']}", file=sys.stderr)
    return index


def reused_rows(reuse: Path, files: list[Path], cameras) -> dict:
    """{file name: (TrainingCache of reuse, episode index)} for each of `files` that is the same file
    (a hard link) as an episode of reuse's built cache, where that cache holds `cameras`; {} where reuse
    has no built cache of this format."""
    try:
        cache = TrainingCache(reuse)
    except (FileNotFoundError, ValueError):
        return {}
    if not set(cameras) <= set(cache.cameras):
        return {}
    held = {Path(e["file"]).name: i for i, e in enumerate(cache.episodes)}
    out = {}
    for f in files:
        i = held.get(f.name)
        other = Path(reuse) / "episodes" / f.name
        if i is not None and other.exists() and os.path.samefile(f, other):
            out[f.name] = (cache, i)
    return out


def _record(fields: dict, file: str, length: int) -> dict:
    """An episode's index record: its EPISODE_KEYS from fields (the file's metadata, or a cache's
    record), its file (relative to the dataset) and its length in frames."""
    return {**{k: fields.get(k) for k in EPISODE_KEYS}, "file": file, "length": length}


def _copy_rows(cache: TrainingCache, i: int, cameras) -> dict:
    """Episode i of a built cache as _decode gives it from its file."""
    e, ep = cache.episodes[i], cache.episode(i, cameras)
    return {"record": _record(e, e["file"], e["length"]), "frames": ep["frames"], **{k: ep[k] for k in ARRAYS}}


def _cameras_of(files, skip_corrupt) -> list:
    for f in files:
        try:
            return list(read_episode_meta(f)["cameras"])
        except CorruptEpisode:
            if not skip_corrupt:
                raise
    raise CorruptEpisode("no episode file of the dataset is readable")


def _write_index(root: Path, names, cameras) -> dict:
    shards = [json.loads((root / n / "episodes.json").read_text()) for n in names]
    size = None
    for s in shards:
        if s["frames"]:
            size = int(np.load(root / s["name"] / f"{cameras[0]}.npy", mmap_mode="r").shape[1])
            break
    index = {
        "format": FORMAT, "cameras": cameras, "size": size,
        "frames": sum(s["frames"] for s in shards),
        "shards": [{"name": s["name"], "frames": s["frames"], "episodes": len(s["episodes"])} for s in shards],
        "episodes": [e for s in shards for e in s["episodes"]],
        "skipped": [x for s in shards for x in s["skipped"]],
    }
    tmp = root / "index.json.tmp"
    tmp.write_text(json.dumps(index, indent=1))
    os.replace(tmp, root / "index.json")
    return index


def rebuild_cache(out: Path, **kwargs) -> dict:
    """Deletes OUT/cache and builds it again from the MCAP files alone."""
    shutil.rmtree(cache_dir(out), ignore_errors=True)
    return build_cache(out, **kwargs)


# ---- reading --------------------------------------------------------------------------------------

class TrainingCache:
    """Read access to a built cache (arrays memory-mapped, opened on first use).

    Attributes:
      episodes: the index's episode records (task, policy, skill, seed, success, split, shard,
        start, length, ...). tasks: sorted task names (the task ids of the loader's batches).
    """

    def __init__(self, out: Path):
        path = cache_dir(out) / "index.json"
        if not path.exists():
            raise FileNotFoundError(f"{path} is missing: build the cache with python -m sim_data.dataset.cache build {out}")
        self.root = cache_dir(out)
        self.index = json.loads(path.read_text())
        if self.index.get("format") != FORMAT:
            raise ValueError(f"{path} has format {self.index.get('format')}, this code reads {FORMAT}: rebuild it")
        self.episodes = self.index["episodes"]
        self.cameras = self.index["cameras"]
        self.tasks = sorted({e["task"] for e in self.episodes})
        self._maps: dict = {}
        self._finite: dict = {}

    def array(self, shard: str, name: str) -> np.ndarray:
        """The memory-mapped array `name` (a camera or proprio/action/success) of a shard."""
        key = (shard, name)
        if key not in self._maps:
            self._maps[key] = np.load(self.root / shard / f"{name}.npy", mmap_mode="r")
        return self._maps[key]

    def select(self, split: str | None = None, tasks=None, finite_only: bool = True) -> list[int]:
        """Indices of the episodes of a split (train / val / test / programs; None: all) and tasks
        (None: all); with finite_only, episodes whose proprio or actions hold NaN or inf (a physics
        blow-up) are left out."""
        return [i for i, e in enumerate(self.episodes)
                if (split is None or e["split"] == split) and (tasks is None or e["task"] in tasks)
                and (not finite_only or self.finite(i))]

    def subset(self, ids: list[int], fraction: float) -> list[int]:
        """The episodes of ids whose id hashes below `fraction`: a fixed share, nested across
        fractions (those of 1/8 are among those of 1/4), the same on every machine."""
        if fraction >= 1:
            return list(ids)
        return [i for i in ids if _unit_hash(self.episodes[i]["episode_id"]) < fraction]

    def finite(self, i: int) -> bool:
        """Whether episode i's proprio and actions are all finite."""
        if i not in self._finite:
            e = self.episodes[i]
            sl = slice(e["start"], e["start"] + e["length"])
            self._finite[i] = bool(np.isfinite(self.array(e["shard"], "proprio")[sl]).all()
                                   and np.isfinite(self.array(e["shard"], "action")[sl]).all())
        return self._finite[i]

    def non_finite(self) -> list[str]:
        """Ids of the episodes holding NaN or inf."""
        return [e["episode_id"] for i, e in enumerate(self.episodes) if not self.finite(i)]

    def episode(self, i: int, cameras=None) -> dict:
        """Episode i whole: {"frames": {camera: (T+1, H, W, 3) uint8}, "proprio": (T+1, 37),
        "action": (T+1, 20) (last row zeros), "success": (T+1,) bool, "progress": (T+1,) float32,
        "scene": (T+1, 24) float32, "grip_px": (T+1, 2, 2) float32, "record": its index record}."""
        e = self.episodes[i]
        sl = slice(e["start"], e["start"] + e["length"])
        cams = self.cameras if cameras is None else cameras
        out = {k: np.asarray(self.array(e["shard"], k)[sl]) for k in ARRAYS}
        out["frames"] = {c: np.asarray(self.array(e["shard"], c)[sl]) for c in cams}
        out["record"] = e
        return out


def _unit_hash(key: str) -> float:
    return int.from_bytes(hashlib.sha256(f"subset/{key}".encode()).digest()[:4], "little") / 2**32


def window_episodes(cache: TrainingCache, window: int, split: str | None = "train", tasks=None,
                    fraction: float = 1.0) -> np.ndarray:
    """(E,) int64 the episodes a WindowLoader of these arguments draws windows from: the split's
    (tasks', fraction's: TrainingCache.select, .subset) episodes at least `window` steps long."""
    return np.array([i for i in cache.subset(cache.select(split, tasks), fraction)
                     if cache.episodes[i]["length"] >= window], np.int64)


def epoch_episodes(cache: TrainingCache, window: int, split: str | None = "train", tasks=None,
                   fraction: float = 1.0, repeat=None) -> np.ndarray:
    """(E',) int64 the episodes of an epoch of a WindowLoader of these arguments: window_episodes',
    each listed `repeat(record)` times (default once)."""
    return repeated(cache, window_episodes(cache, window, split, tasks, fraction), repeat)


def repeated(cache: TrainingCache, episodes: np.ndarray, repeat=None) -> np.ndarray:
    """episodes (E,) with each listed `repeat(record)` times (default once)."""
    return episodes if repeat is None else np.repeat(
        episodes, [_repeat_count(repeat, cache.episodes[i]) for i in episodes])


def _repeat_count(repeat, record: dict) -> int:
    n = repeat(record)
    if int(n) != n or n < 0:
        raise ValueError(f"repeat gave {n!r} for episode {record.get('episode_id')}: a count >= 0 is needed")
    return int(n)


class WindowLoader:
    """Shuffled fixed-length windows of a cache's episodes, gathered ahead by background threads.

    Every start position of every selected episode is one window; an epoch visits them all in
    an order drawn from (seed, epoch), in batches of `batch` (the last partial batch is dropped).
    `repeat(record)`, given, says how many times an episode's windows count in an epoch (its index
    record, TrainingCache.episodes; default once each): `episodes` lists an episode that often,
    `distinct` once.
    `first_windows` adds each episode's first window (its start 0) that many more times an epoch (times
    its `repeat`: each listing of an episode brings its own), since imagination starts from an episode's
    first frame, a position one window in (length - window + 1) covers.
    `state()` after a batch and `restore(state)` in a new loader continue the same sequence.
    `part=(i, n)` yields the i-th of n equal row blocks of each batch (B = batch / n rows): n
    processes that each take their part train on the same global batches as one process would.

    Batches: {"frames": {camera: (B, T, H, W, 3) uint8}, "proprio": (B, T, 37) float32,
    "action": (B, T, 20) float32 (action t follows frame t), "success": (B, T) bool, "progress": (B, T) float32,
    "scene": (B, T, 24) float32 (sim_data.sim.scene.scene_state), "grip_px": (B, T, 2, 2) float32 (grip_pixels),
    "outcome": (B,) bool (the episode's success), "task": (B,) int32 (index into cache.tasks),
    "start": (B,) int32 (the window's first step), "episode": (B,) int32}; with first_frames, also
    "first_frames": {camera: (B, H, W, 3) uint8} (each window's episode's first frame).
    """

    def __init__(self, cache: TrainingCache, window: int, batch: int, split: str | None = "train", seed: int = 0,
                 cameras=None, tasks=None, fraction: float = 1.0, prefetch: int = 8, threads: int = 4,
                 part: tuple[int, int] = (0, 1), first_frames: bool = False, repeat=None, first_windows: int = 0):
        if window < 1 or batch < 1:
            raise ValueError(f"window and batch must be >= 1, got {window}, {batch}")
        if first_windows < 0:
            raise ValueError(f"first_windows counts extra first windows an episode (>= 0), got {first_windows}")
        index, count = part
        if not (count >= 1 and 0 <= index < count and batch % count == 0):
            raise ValueError(f"part {part} must be (i, n) with 0 <= i < n and n dividing the batch {batch}")
        self.cache, self.window, self.batch, self.seed = cache, window, batch, seed
        self.first_frames = first_frames
        self.part = (int(index), int(count))
        self.cameras = list(cameras or cache.cameras[:1])
        bad = [c for c in self.cameras if c not in cache.cameras]
        if bad:
            raise ValueError(f"cameras {bad} are not in the cache (it has {cache.cameras})")
        self.distinct = window_episodes(cache, window, split, tasks, fraction)
        self.episodes = repeated(cache, self.distinct, repeat)
        counts = np.array([cache.episodes[i]["length"] - window + 1 for i in self.episodes], np.int64)
        if counts.sum() < batch:
            raise ValueError(f"split {split!r} has {int(counts.sum())} windows of length {window}, fewer than a batch "
                             f"of {batch}")
        self._ends = np.cumsum(counts)
        self._firsts = self._ends - counts  # the first window id of each episode
        self._every = int(self._ends[-1])  # the ids past these are first windows again, episode by episode
        self.windows = self._every + first_windows * len(self.episodes)
        self.batches_per_epoch = self.windows // batch
        self._task_id = {t: i for i, t in enumerate(cache.tasks)}
        self._position = (0, 0)
        self._prefetch, self._threads = prefetch, threads
        self._pool, self._inflight = None, collections.deque()
        self._orders: dict = {}

    # ---- iteration state ----
    def state(self) -> dict:
        """Where the loader is: pass to `restore` to continue after the batches already taken."""
        return {"epoch": self._position[0], "batch": self._position[1], "seed": self.seed,
                "window": self.window, "batch_size": self.batch, "windows": self.windows}

    def restore(self, state: dict) -> None:
        """Continues from a `state()` of a loader of the same seed, window, batch size and windows (ValueError
        otherwise): the next batch is the one after those taken there; batches gathered ahead are dropped."""
        mine = {"seed": self.seed, "window": self.window, "batch_size": self.batch, "windows": self.windows}
        theirs = {k: state.get(k) for k in mine}
        if theirs != mine:
            raise ValueError(f"loader state is for another loader ({theirs}), this one is {mine}")
        self._halt()
        self._position = (int(state["epoch"]), int(state["batch"]))

    # ---- batches ----
    def _order(self, epoch: int) -> np.ndarray:
        order = self._orders.get(epoch)
        if order is None:  # computed once per epoch: a permutation of millions of windows takes ~20 ms
            order = np.random.default_rng([self.seed, epoch]).permutation(self.windows)
            self._orders = {epoch: order, **{e: o for e, o in self._orders.items() if e == epoch - 1}}
        return order

    def batch_at(self, epoch: int, k: int) -> dict:
        """This loader's part of batch k of an epoch (what iteration yields there)."""
        local = self.batch // self.part[1]
        first = k * self.batch + self.part[0] * local
        return self.gather(self._order(epoch)[first:first + local])

    def gather(self, window_ids: np.ndarray) -> dict:
        """The windows with these ids (0 .. windows-1) as one batch."""
        extra = window_ids >= self._every
        pos = np.where(extra, (window_ids - self._every) % len(self.episodes),
                       np.searchsorted(self._ends, np.minimum(window_ids, self._every - 1), side="right"))
        starts = np.where(extra, 0, window_ids - self._firsts[pos])
        eps = self.episodes[pos]
        recs = [self.cache.episodes[i] for i in eps]
        out = {"frames": {}, "outcome": np.array([r["success"] for r in recs], bool),
               "task": np.array([self._task_id[r["task"]] for r in recs], np.int32),
               "start": starts.astype(np.int32), "episode": eps.astype(np.int32)}
        shards = np.array([r["shard"] for r in recs])
        firsts = np.array([r["start"] for r in recs], np.int64)  # each episode's first row in its shard
        rows = (firsts + starts)[:, None] + np.arange(self.window)
        for name in self.cameras + list(ARRAYS):
            arr = self._rows(name, shards, rows)
            if name in self.cameras:
                out["frames"][name] = arr
            else:
                out[name] = arr
        if self.first_frames:  # each window's episode's first frame, for a model that keeps it in view
            out["first_frames"] = {name: self._rows(name, shards, firsts) for name in self.cameras}
        return out

    def _rows(self, name: str, shards: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Array `name` at rows (B, ...) int of the shards (B,): (B, ..., *the array's row shape)."""
        first = self.cache.array(shards[0], name)
        arr = np.empty(rows.shape + first.shape[1:], first.dtype)
        for shard in np.unique(shards):
            sel = np.nonzero(shards == shard)[0]
            arr[sel] = self.cache.array(shard, name)[rows[sel]]
        return arr

    def _advance(self, epoch: int, k: int) -> tuple[int, int]:
        k += 1
        return (epoch + 1, 0) if k == self.batches_per_epoch else (epoch, k)

    def _halt(self):
        if self._pool is not None:
            for fut in self._inflight:
                fut.cancel()
            self._pool.shutdown(wait=False)
        self._pool, self._inflight = None, collections.deque()

    def __iter__(self):
        return self

    def __next__(self) -> dict:
        if self._pool is None:  # the next `prefetch` batches are gathered by `threads` threads, in order
            self._pool = cf.ThreadPoolExecutor(self._threads, thread_name_prefix="window-loader")
            self._ahead = self._position
            for _ in range(self._prefetch):
                self._inflight.append(self._pool.submit(self.batch_at, *self._ahead))
                self._ahead = self._advance(*self._ahead)
        fut = self._inflight.popleft()
        self._inflight.append(self._pool.submit(self.batch_at, *self._ahead))
        self._ahead = self._advance(*self._ahead)
        try:
            item = fut.result()
        except Exception:
            self._halt()
            raise
        self._position = self._advance(*self._position)
        return item

    def close(self) -> None:
        self._halt()


# ---- command line ---------------------------------------------------------------------------------

def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("command", choices=("build", "rebuild", "info"))
    p.add_argument("out", type=Path, help="the dataset directory (holding episodes/)")
    p.add_argument("--skip-corrupt", action="store_true", help="leave out unreadable files and list them")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--shard-episodes", type=int, default=64)
    a = p.parse_args(argv)
    if a.command == "info":
        idx = TrainingCache(a.out).index
        print(json.dumps({k: idx[k] for k in ("cameras", "size", "frames", "shards", "skipped")}, indent=1))
        return 0
    build = rebuild_cache if a.command == "rebuild" else build_cache
    try:
        idx = build(a.out, skip_corrupt=a.skip_corrupt, workers=a.workers, shard_episodes=a.shard_episodes)
    except (CorruptEpisode, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"{cache_dir(a.out)}: {len(idx['episodes'])} episodes, {idx['frames']} frames in {len(idx['shards'])} "
          f"shards; {len(idx['skipped'])} skipped")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
