"""Videos to share: an evaluation's real and imagined episodes side by side as MP4 files, one per
policy, and the controllability panel, from the evaluation directory (experiments.evaluate).

    python -m experiments.videos RUN [--scale 4]        # writes RUN/videos/
    make videos RUN=runs/eval/demo

RUN/videos/ holds

- `<task>/<policy>.mp4`: the policy's filmed episodes one after another, each frame the simulator's
  (left) beside the world model's imagination (right) of the same start and actions, with a caption
  below (episode, true outcome, predicted success probability);
- `controllability.mp4`: one start, each action program a row (named in its caption), real left and
  imagined right;
- `index.json`: per file its policy or programs and, per episode, the frame range, the true outcome
  and the predicted success probability (what the report labels its links with).

Frames are the 64 px head camera enlarged `scale` times (nearest pixel), at the 20 Hz control rate,
H.264 (sim_data.video). `make report` links the files when they are present.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import cv2
import numpy as np

from experiments.report import read_index
from sim_data.dataset.episodes import CONTROL_DT
from sim_data.util import run_cli, write_json_atomic
from sim_data.video import write_mp4

FPS = round(1 / CONTROL_DT)
SCALE = 4
GAP = 2  # white pixels between the real and the imagined frame, before scaling
CAPTION = 7  # height of the caption band under the frames, before scaling


def side_by_side(real: np.ndarray, imagined: np.ndarray, scale: int = SCALE) -> np.ndarray:
    """(T, H, W, 3) uint8 real and imagined frames -> (T', H*scale, (2W + GAP)*scale, 3) uint8, the real
    frame left, a white gap, the imagined frame right; T' = the shorter of the two."""
    n = min(len(real), len(imagined))
    gap = np.full((n, real.shape[1], GAP, 3), 255, np.uint8)
    both = np.concatenate([real[:n], gap, imagined[:n]], axis=2)
    return both.repeat(scale, axis=1).repeat(scale, axis=2)


def captioned(frames: np.ndarray, text: str, scale: int = SCALE) -> np.ndarray:
    """frames (T, H, W, 3) uint8 with a white band of CAPTION * scale rows below, text written in it:
    (T, H + CAPTION * scale, W, 3) uint8; the frames themselves are left as they are."""
    band = np.full((CAPTION * scale, frames.shape[2], 3), 255, np.uint8)
    cv2.putText(band, text, (scale, round(CAPTION * scale * 0.72)), cv2.FONT_HERSHEY_SIMPLEX, 0.1 * scale,
                (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([frames, np.broadcast_to(band, (len(frames), *band.shape))], axis=1)


def panel_grid(panel: dict, scale: int = SCALE) -> np.ndarray:
    """The controllability panel {program: {"real": (T, H, W, 3), "imagined": (T, H, W, 3)}} -> one
    (T', rows, cols, 3) uint8 video: a row per program (sorted by name), real left and imagined right,
    its name in a caption below, rows parted by white gaps; T' = the shortest sequence."""
    rows = [captioned(side_by_side(panel[p]["real"], panel[p]["imagined"], scale), f"{p}: real | imagined", scale)
            for p in sorted(panel)]
    n = min(len(r) for r in rows)
    gap = np.full((n, GAP * scale, rows[0].shape[2], 3), 255, np.uint8)
    parts = [x for r in rows for x in (r[:n], gap)][:-1]
    return np.concatenate(parts, axis=1)


def _safe(name: str) -> str:
    """A file name for a policy name (which may hold '/', ':', '#', '~')."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "policy"


def load_run(run: Path) -> tuple[dict, dict]:
    """(results.json, videos.npz's arrays) of an evaluation directory; FileNotFoundError naming a
    missing file."""
    run = Path(run)
    for name in ("results.json", "videos.npz"):
        if not (run / name).exists():
            raise FileNotFoundError(f"{run / name} is missing: {run} is not an evaluation directory (make eval)")
    res = json.loads((run / "results.json").read_text())
    with np.load(run / "videos.npz") as z:
        return res, {k: z[k] for k in z.files}


def policy_videos(res: dict, videos: dict, out: Path, scale: int = SCALE) -> list[dict]:
    """One MP4 per (task, policy) of results.json's filmed episodes; returns their index entries
    {"file", "task", "policy", "episodes": [{"episode", "frames": [from, to), "true_success", "pred_prob"}]}."""
    by_policy: dict = {}
    for v in res["videos"]:
        if v["key"] + "/real" in videos:
            by_policy.setdefault((v["task"], v["policy"]), []).append(v)
    entries, used = [], set()
    for (task, policy), eps in by_policy.items():
        # zoo policy names begin with their task, which the directory already says
        name = _safe(policy.removeprefix(f"{task}/"))
        while f"{task}/{name}" in used:  # two names that differ only in replaced characters
            name += "_"
        used.add(f"{task}/{name}")
        clips, rows, start = [], [], 0
        for v in eps:
            clip = captioned(side_by_side(videos[v["key"] + "/real"], videos[v["key"] + "/imagined"], scale),
                             f"ep {v['episode']}: truly {'success' if v['true_success'] else 'failure'}, "
                             f"predicted {v['pred_prob']:.2f}", scale)
            clips.append(clip)
            rows.append({"episode": v["episode"], "frames": [start, start + len(clip)],
                         "true_success": v["true_success"], "pred_prob": v["pred_prob"]})
            start += len(clip)
        path = out / task / f"{name}.mp4"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_mp4(path, np.concatenate(clips), FPS)
        entries.append({"file": str(path.relative_to(out)), "task": task, "policy": policy, "episodes": rows})
    return entries


def controllability_video(videos: dict, out: Path, scale: int = SCALE) -> dict | None:
    """controllability.mp4 from videos.npz's `controllability/<program>/{real,imagined}` arrays;
    its index entry {"file", "programs" (top to bottom)}, or None where the run has no panel."""
    programs = sorted({k.split("/")[1] for k in videos if k.startswith("controllability/")})
    if not programs:
        return None
    panel = {p: {kind: videos[f"controllability/{p}/{kind}"] for kind in ("real", "imagined")} for p in programs}
    write_mp4(out / "controllability.mp4", panel_grid(panel, scale), FPS)
    return {"file": "controllability.mp4", "programs": programs}


def write_videos(run: Path, scale: int = SCALE) -> Path:
    """Writes RUN/videos/ (the policies' MP4 files, controllability.mp4, index.json); returns its path."""
    if scale < 1:
        raise ValueError(f"scale must be a positive integer, got {scale}")
    res, videos = load_run(run)
    out = Path(run) / "videos"
    out.mkdir(exist_ok=True)
    index = {"fps": FPS, "scale": scale, "layout": "real left, imagined right",
             "policies": policy_videos(res, videos, out, scale),
             "controllability": controllability_video(videos, out, scale)}
    write_json_atomic(out / "index.json", index)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="an evaluation directory (make eval OUT)")
    p.add_argument("--scale", type=int, default=SCALE, help=f"enlarge the frames this many times (default {SCALE})")
    a = p.parse_args(argv)
    out = write_videos(a.run, a.scale)
    index = read_index(a.run)
    n = len(index["policies"]) + (index["controllability"] is not None)
    print(f"{out}: {n} MP4 files (index.json lists them)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
