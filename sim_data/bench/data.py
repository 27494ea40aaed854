"""Dataset throughput end to end: simulation, rendering, JPEG/JSON/zstd encoding and finished MCAP
files, then the training cache and its window loader; writes JSON.

    python -m sim_data.bench.data --out runs/bench/data.json            # 2-core defaults (cpu engine)
    python -m sim_data.bench.data --out F --tasks mug,wipe --episodes 4096 --batch 2048 --workers 14

A warm-up run of one chunk per task compiles everything first (compilation is a one-off per
task and batch size, reported separately); the measured run then generates `episodes` episodes
per task with another seed into a fresh directory. Frames count every camera (two per step).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from sim_data.dataset.cache import TrainingCache, WindowLoader
from sim_data.dataset.generate import generate, make_config
from sim_data.util import device_name, run_cli, write_json_atomic


def loader_rate(out: Path, window: int, batch: int, batches: int) -> dict:
    """Frames/s of the window loader over the dataset's cache (one camera, the training set)."""
    loader = WindowLoader(TrainingCache(out), window, batch, split=None, seed=0)
    next(loader)
    t = time.perf_counter()
    for _ in range(batches):
        next(loader)
    dt = time.perf_counter() - t
    loader.close()
    return {"window": window, "batch": batch, "batches_per_s": batches / dt, "frames_per_s": batches * batch * window / dt}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--tasks", default="mug,wipe")
    p.add_argument("--episodes", type=int, default=16, help="measured episodes per task")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--engine", default="")
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--dir", type=Path, default=None, help="where the datasets go (default: a temporary directory)")
    a = p.parse_args(argv)
    base = ["skills=1.0", f"tasks={a.tasks}", f"batch={a.batch}", f"workers={a.workers}", f"size={a.size}",
            f"engine={a.engine}"]
    root = Path(tempfile.mkdtemp(dir=a.dir))
    try:
        t = time.perf_counter()
        warm = generate(make_config("default", base + [f"episodes={a.batch}", "seed=1000", "cache=false"]),
                        root / "warm", progress=False)
        warm_s = time.perf_counter() - t
        cfg = make_config("default", base + [f"episodes={a.episodes}", "seed=1001"])
        stats = generate(cfg, root / "run", progress=True)
        tp = stats["throughput"]
        loader = loader_rate(root / "run", window=16, batch=64, batches=50)
        size_bytes = sum(f.stat().st_size for f in (root / "run" / "episodes").glob("*.mcap"))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    report = {
        "device": device_name(), "engine": tp["engine"], "config": dataclasses.asdict(cfg),
        "warmup_s (compilation + one chunk per task)": warm_s, "warmup_frames": warm["throughput"]["frames_generated"],
        "frames_per_s_into_files": tp["frames_per_s"], "episodes_per_s": tp["episodes_per_s"],
        "frames": tp["frames_generated"], "wall_s": tp["wall_s"], "simulate_s": tp["simulate_s"],
        "wait_for_writers_s": tp["wait_for_writers_s"], "workers": tp["workers"],
        "mcap_bytes_per_frame": size_bytes / tp["frames_generated"],
        "cache_build_s": tp.get("cache_s"), "cache_frames_per_s": tp["cache_frames"] * len(cfg.cameras) / tp["cache_s"],
        "loader": loader,
    }
    write_json_atomic(a.out, report)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
