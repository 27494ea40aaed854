"""`make videos` on a small evaluation directory (results.json and videos.npz as experiments.evaluate
writes them), read back with OpenCV; the report's links to the files."""

import json

import cv2
import numpy as np
import pytest

from experiments import videos as V
from experiments.report import read_index, video_links

H = W = 64
SCALE = 2


def _clip(n: int, seed: int) -> np.ndarray:
    """(n, H, W, 3) uint8: a square moving over a colour gradient (smooth, as rendered frames are)."""
    rng = np.random.default_rng(seed)
    base = np.zeros((H, W, 3), np.uint8)
    base[..., 0] = np.linspace(30, 220, W, dtype=np.uint8)[None]
    base[..., 1] = np.linspace(200, 40, H, dtype=np.uint8)[:, None]
    base[..., 2] = rng.integers(60, 200)
    frames = np.repeat(base[None], n, axis=0)
    for t in range(n):
        y, x = 8 + t % 40, 4 + (2 * t) % 44
        frames[t, y:y + 16, x:x + 16] = rng.integers(0, 255, 3)
    return frames


@pytest.fixture
def run(tmp_path):
    """An evaluation directory: two policies (one named like a zoo checkpoint), one with two episodes,
    one imagination a frame shorter than its real episode, and a controllability panel of two programs."""
    eps = [("mug", "mug/conv_proprio/5", 0, 30, 30), ("mug", "mug/conv_proprio/5", 3, 25, 25),
           ("mug", "examples.plugin_policy:make", 1, 20, 19)]
    arrays, index = {}, []
    for i, (task, policy, ep, n_real, n_imag) in enumerate(eps):
        key = f"{task}/{policy}/{ep}"
        # the imagination mirrored: the two sides differ everywhere but in the middle column
        arrays[key + "/real"], arrays[key + "/imagined"] = _clip(n_real, i), _clip(n_imag, 10 + i)[:, :, ::-1]
        index.append({"task": task, "policy": policy, "episode": ep, "key": key, "true_success": i == 0,
                      "pred_prob": 0.25 * i})
    for j, program in enumerate(("reach_mug", "air_guitar")):
        arrays[f"controllability/{program}/real"] = _clip(12, 20 + j)
        arrays[f"controllability/{program}/imagined"] = _clip(12, 30 + j)[:, :, ::-1]
    (tmp_path / "results.json").write_text(json.dumps({"videos": index, "controllability": ["air_guitar", "reach_mug"]}))
    np.savez_compressed(tmp_path / "videos.npz", **arrays)
    return tmp_path, arrays, index


def _read(path) -> np.ndarray:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    cap.release()
    return np.stack(frames)


def _shrink(frames: np.ndarray) -> np.ndarray:
    """(T, h*SCALE, w*SCALE, 3) -> (T, h, w, 3) float: each SCALE x SCALE block's mean."""
    t, h, w, _ = frames.shape
    return frames.reshape(t, h // SCALE, SCALE, w // SCALE, SCALE, 3).mean(axis=(2, 4))


def test_each_policy_gets_one_file_of_its_episodes_real_left_imagined_right(run):
    run, arrays, _ = run
    out = V.write_videos(run, scale=SCALE)
    index = read_index(run)
    assert index["fps"] == 20 and [e["policy"] for e in index["policies"]] == ["mug/conv_proprio/5",
                                                                               "examples.plugin_policy:make"]
    for entry in index["policies"]:
        video = _read(out / entry["file"])
        assert video.shape[1:] == ((H + V.CAPTION) * SCALE, (2 * W + V.GAP) * SCALE, 3)
        assert len(video) == entry["episodes"][-1]["frames"][1]
        for ep in entry["episodes"]:
            a, b = ep["frames"]
            key = f"mug/{entry['policy']}/{ep['episode']}"
            real, imagined = arrays[key + "/real"], arrays[key + "/imagined"]
            assert b - a == min(len(real), len(imagined))
            left = _shrink(video[a:b, : H * SCALE, : W * SCALE])
            right = _shrink(video[a:b, : H * SCALE, (W + V.GAP) * SCALE:])
            assert np.abs(left - real[: b - a]).mean() < 3.0
            assert np.abs(right - imagined[: b - a]).mean() < 3.0
            assert np.abs(left - imagined[: b - a]).mean() > 30.0  # the two sides are told apart


def test_the_controllability_panel_has_a_row_per_program(run):
    run, arrays, _ = run
    out = V.write_videos(run, scale=SCALE)
    entry = read_index(run)["controllability"]
    assert entry["programs"] == ["air_guitar", "reach_mug"]
    video = _read(out / entry["file"])
    row = (H + V.CAPTION + V.GAP) * SCALE
    assert video.shape == (12, 2 * row - V.GAP * SCALE, (2 * W + V.GAP) * SCALE, 3)
    for i, program in enumerate(entry["programs"]):
        real = _shrink(video[:, i * row: i * row + H * SCALE, : W * SCALE])
        assert np.abs(real - arrays[f"controllability/{program}/real"]).mean() < 3.0


def test_the_report_links_the_files_and_a_run_without_videos_has_none(run):
    run, _, _ = run
    assert video_links(read_index(run)) == []
    V.write_videos(run, scale=SCALE)
    links = video_links(read_index(run))
    assert [label for label, _ in links] == ["mug/conv_proprio/5", "examples.plugin_policy:make",
                                             "controllability panel"]
    assert all((run / href).is_file() for _, href in links)


def test_a_directory_without_an_evaluation_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="results.json is missing"):
        V.write_videos(tmp_path)
