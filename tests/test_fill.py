"""The generator of what a reprojected frame leaves empty (wm.fill) and its training on a dataset's
episodes (experiments.fill)."""

import json
import shutil

import jax
import numpy as np
import pytest

from examples.plugin_policy import ready_pose
from experiments import fill as F
from experiments import loop_oracle as L
from sim_data.dataset.episodes import read_episode
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import floor_hits
from sim_data.sim.robot import FORWARD_SPEED, YAW_RATE
from wm import egomotion as E
from wm import fill as W
from wm import grasp as GR

SIZE, FOVY, CELL = 16, 60.0, 0.75
LIGHT, DARK, WALL = np.array([200, 170, 120]), np.array([90, 70, 50]), np.array([150, 150, 160])


def _camera(x, y, yaw, pitch, height=1.0):
    """(pos (3,), world-from-camera (3, 3)) of a camera at (x, y, height) looking along yaw, pitched down."""
    f = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), -np.sin(pitch)])
    r = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    return np.array([x, y, height]), np.stack([r, np.cross(-f, r), -f], axis=1)


def _checker_pairs(n, seed):
    """n frames of a checker floor (cells of CELL m) under a grey wall, seen from random poses, the lower
    rows (a random number of them) left empty as a reprojection leaves what its frame never showed."""
    rng = np.random.default_rng(seed)
    cams = [_camera(*rng.uniform(-2, 2, 2), rng.uniform(-np.pi, np.pi), rng.uniform(0.5, 1.0)) for _ in range(n)]
    pos, mat = np.stack([c[0] for c in cams]), np.stack([c[1] for c in cams])
    xy, ray = floor_hits(pos, mat, FOVY, SIZE, SIZE)
    parity = (np.floor(xy[..., 0] / CELL) + np.floor(xy[..., 1] / CELL)) % 2 > 0
    true = np.where(parity[..., None], LIGHT, DARK)
    true = np.where((ray[..., 2] < -1e-6)[..., None], true, WALL).astype(np.uint8)
    rows = np.arange(SIZE)[None, :, None]
    covered = np.broadcast_to(rows < rng.integers(4, 12, n)[:, None, None], (n, SIZE, SIZE)).copy()
    shown = np.where(covered[..., None], true, true.reshape(n, -1, 3).mean(1)[:, None, None]).astype(np.uint8)
    return {"reprojected": shown, "covered": covered, "true": true, "cam_pos": pos, "cam_mat": mat}


def test_the_fill_learns_the_floor_from_where_its_rays_land(tmp_path):
    """Trained on frames of a checker floor, the net draws unseen frames' empty rows well under half
    the error of their best single colour, keeps every pixel a point landed on, and draws the same
    after a save and load."""
    cfg = W.FillConfig(width=8, levels=2, steps=400, batch=16, lr=3e-3)
    net, params, fit = W.train_fill(_checker_pairs(512, 0), FOVY, cfg, progress=False)
    test = _checker_pairs(64, 1)
    drawn = W.filled(net, params, cfg, test["reprojected"], test["covered"], test["cam_pos"], test["cam_mat"], FOVY)
    hole = ~test["covered"]
    err = np.abs(drawn.astype(float) - test["true"]).mean(-1)[hole].mean()
    best_colour = np.median(test["true"][hole], axis=0)
    flat = np.abs(best_colour - test["true"][hole]).mean()
    assert err < 0.5 * flat, (err, flat)
    np.testing.assert_array_equal(drawn[test["covered"]], test["reprojected"][test["covered"]])
    assert fit["loss"] < fit["losses"][0]

    W.save_fill(tmp_path, params, cfg, SIZE, {"train_loss": fit["loss"]})
    net2, params2, cfg2, size2 = W.load_fill(tmp_path)
    assert (cfg2, size2) == (cfg, SIZE)
    again = W.filled(net2, params2, cfg2, test["reprojected"], test["covered"], test["cam_pos"], test["cam_mat"], FOVY)
    np.testing.assert_array_equal(again, drawn)


def test_the_hole_scores_count_only_the_empty_pixels():
    true = np.zeros((1, 2, 2, 3), np.uint8)
    pred = true.copy()
    pred[0, 0, 0] = 30  # an empty pixel off by 30 in every channel
    pred[0, 1, 1] = 200  # a covered one, not counted
    covered = np.array([[[False, True], [True, True]]])
    s = F.hole_scores(pred, true, covered)
    assert s["hole_mae"] == pytest.approx(30.0) and s["hole_share"] == 0.25
    assert s["hole_psnr_db"] == pytest.approx(10 * np.log10(255.0 ** 2 / 900.0))


@pytest.mark.slow  # replays a smoke episode with the camera drawn (10-20 s on 2 cores)
def test_replayed_pairs_are_the_recorded_frames(smoke_dataset, tmp_path):
    """The frames paired with the reprojections are the dataset's own frames at those steps (up to its
    JPEG), the reprojection at the first pair nearly all covered, and a rerun reads the pairs back."""
    _, data, _ = smoke_dataset
    rows = F.manifest_rows(data, ["mug"], "train")
    assert rows
    pairs, fovy = F.replay_pairs(rows[:1], 64, 10, progress=False)
    ep = read_episode(data / rows[0]["file"], sim_state=False)
    recorded = ep["frames"]["head_cam"][10::10]
    assert pairs["true"].shape == recorded.shape and 0 < fovy < 180
    assert np.abs(pairs["true"].astype(float) - recorded).mean() < 4.0
    assert pairs["covered"][0].mean() > 0.8
    split = rows[0]["split"]
    F.cached_pairs(tmp_path, split, [data], ["mug"], 64, 10, progress=False)
    again, _ = F.cached_pairs(tmp_path, split, [data], ["mug"], 64, 10, progress=False)
    assert again["true"].shape[0] == len(F.manifest_rows(data, ["mug"], split)) * (len(ep["action"]) // 10)


def _drives(steps=100, seed=0):
    """The base's poses (B, T + 1, 3), the actuated joints' positions (B, T + 1, 16) and the actions
    (B, T, 20) of step_back episodes in MuJoCo's C engine, each a drive at a random speed and turn for a
    random time, then a stop."""
    env = HomeEnv("step_back", 4, engine="cpu")
    state = env.reset(jax.random.PRNGKey(seed))
    rng = np.random.default_rng(seed)
    actions = np.tile(np.asarray(ready_pose(), np.float32), (4, steps, 1))  # the arms held as the plug-in holds them
    moving = np.arange(steps)[None] < rng.integers(20, steps, (4, 1))  # a drive, then a stop
    actions[..., FORWARD_SPEED] = rng.uniform(-0.5, 0.5, (4, 1)) * moving
    actions[..., YAW_RATE] = rng.uniform(-0.3, 0.3, (4, 1)) * moving
    actions = np.asarray(env.core.applied(actions.reshape(-1, 20))).reshape(actions.shape)
    qpos = [np.asarray(state.qpos)]
    for t in range(steps):
        state = env.step(state, actions[:, t])
        qpos.append(np.asarray(state.qpos))
    qpos = np.stack(qpos, 1)
    return qpos[..., env.idx.robot.base_qpos], qpos[..., env.idx.robot.posed_qpos], actions


@pytest.mark.slow  # random drives and two closed loops of a plug-in with the camera drawn (30-60 s on 2 cores)
def test_the_imagined_loop_predicts_a_drive_from_its_actions_alone(tmp_path):
    """With the base's motion fit on random drives, the imagined loop of the back-away plug-in (blind to
    its camera) predicts where the simulator puts it to a centimetre, and so its success; the rates
    against the true loop's land in imagined_against_true; tasks whose success the base's motion does
    not decide are refused."""
    bases, qs, actions = _drives()
    E.save_egomotion(tmp_path / "fill", E.fit_egomotion(list(bases), list(actions)), {},
                     E.fit_joints(list(qs), list(actions)))
    cfg = W.FillConfig(width=4, levels=1)
    W.save_fill(tmp_path / "fill", W.init_fill(cfg, 64)[1], cfg, 64, {})
    res = L.study("blind=examples.plugin_policy:make", ["step_back"], tmp_path / "o", ["true", *L.PREDICTED], 3, 0,
                  progress=False, fill=tmp_path / "fill")
    blind = res["tasks"]["step_back"]["blind"]
    for mode in L.PREDICTED:
        assert blind[mode]["action_gap"] == 0.0
        assert abs(blind[mode]["predicted_back_m"]["mean"] - blind["true"]["back_m"]["mean"]) < 0.01
        assert blind[mode]["predicted_success"] == blind["true"]["success"]
        assert res["imagined_against_true"]["step_back"][mode] == {"pearson": None, "mean_abs_error": 0.0,
                                                                   "policies": 1}
    with pytest.raises(ValueError, match="step_back"):
        L.study("blind=examples.plugin_policy:make", ["mug"], tmp_path / "m", [L.IMAGINED], 2, 0, progress=False,
                fill=tmp_path / "fill")


def test_bad_inputs_are_refused(tmp_path):
    with pytest.raises(ValueError, match="FillConfig"):
        W.FillConfig(width=2)
    with pytest.raises(ValueError, match="halve"):
        W.init_fill(W.FillConfig(levels=3), 20)
    with pytest.raises(FileNotFoundError, match="experiments.fill"):
        W.load_fill(tmp_path)
    with pytest.raises(FileNotFoundError, match="manifest"):
        F.manifest_rows(tmp_path, ["mug"], "train")
    with pytest.raises(ValueError, match="unknown tasks"):
        F.main(["--data", str(tmp_path), "--tasks", "dance", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="--episodes >= 0"):
        F.main(["--data", str(tmp_path), "--tasks", "mug", "--out", str(tmp_path), "--episodes", "-1"])
    (tmp_path / "manifest.jsonl").write_text("")
    with pytest.raises(ValueError, match="no train or val episodes of step_back"):
        F.main(["--data", str(tmp_path), "--tasks", "step_back", "--out", str(tmp_path / "f")])
    for mode in L.NEEDS_FILL:
        with pytest.raises(ValueError, match="--fill"):
            L.study("blind=examples.plugin_policy:make", ["step_back"], tmp_path, [mode], 2, 0, progress=False)
    cfg = W.FillConfig(width=4, levels=1)
    W.save_fill(tmp_path / "fill", W.init_fill(cfg, 64)[1], cfg, 64, {})
    with pytest.raises(FileNotFoundError, match="egomotion.json"):
        L.study("blind=examples.plugin_policy:make", ["step_back"], tmp_path / "o", [L.EGOMOTION], 2, 0,
                progress=False, fill=tmp_path / "fill")
    with pytest.raises(ValueError, match="32-px"):
        L.study("blind=examples.plugin_policy:make", ["step_back"], tmp_path / "o", [L.LEARNED], 2, 0, size=32,
                progress=False, fill=tmp_path / "fill")


def test_the_fits_read_a_spread_of_each_tasks_episodes_in_the_datasets_order(tmp_path):
    """fit_rows keeps at most `limit` episodes a task, evenly spaced over them ordered by policy and
    episode (so each policy keeps its share), in the datasets' order; under the limit, or with 0, all."""
    def write(data, rows):
        data.mkdir()
        (data / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    # mug: 6 of policy "b" then 6 of "a", interleaved with step_back's 3; a val episode to leave out
    mug = [{"task": "mug", "policy": p, "episode_id": f"mug-{p}-{i}", "split": "train", "file": f"{p}{i}"}
           for p in ("b", "a") for i in range(6)]
    step_back = [{"task": "step_back", "policy": "a", "episode_id": f"sb-{i}", "split": "train", "file": f"s{i}"}
                 for i in range(3)]
    val = {"task": "mug", "policy": "a", "episode_id": "mug-v", "split": "val", "file": "v"}
    write(tmp_path / "one", mug[:6] + step_back + [val])
    write(tmp_path / "two", mug[6:])
    data = [tmp_path / "one", tmp_path / "two"]
    kept = F.fit_rows(data, ["mug", "step_back"], "train", 4)
    # mug ordered by policy: a0..a5, b0..b5; every third of the 12 -> a0, a3, b0, b3, in the datasets' order
    assert [r["episode_id"] for r in kept] == ["mug-b-0", "mug-b-3", "sb-0", "sb-1", "sb-2", "mug-a-0", "mug-a-3"]
    assert kept[0]["path"] == str(tmp_path / "one" / "b0")
    everything = [r["episode_id"] for r in F.fit_rows(data, ["mug", "step_back"], "train", 0)]
    assert everything == [r["episode_id"] for r in mug[:6] + step_back + mug[6:]]
    assert [r["episode_id"] for r in F.fit_rows(data, ["mug"], "train", 12)] == [r["episode_id"] for r in mug]
    assert [r["episode_id"] for r in F.fit_rows(data, ["mug"], "val", 1)] == ["mug-v"]


@pytest.mark.slow  # fits the motion models and the grasp grid's rules on the smoke episodes (about a minute on 2 cores)
def test_the_cli_fits_each_grasped_tasks_rule_once_and_names_a_task_without_episodes(smoke_dataset, tmp_path):
    """experiments.fill on a grasped task writes the motion models and that task's rule with its fit's
    figures into grasp.json; a rerun fits nothing again; a grasped task the data holds no episodes of
    is refused with the task named, and the rules already fit stay."""
    _, data, _ = smoke_dataset
    copy = tmp_path / "data"
    shutil.copytree(data, copy, symlinks=True)
    rows = [json.loads(line) for line in (copy / "manifest.jsonl").read_text().splitlines()]
    for r, split in zip(rows, ("train", "val")):  # one episode in each split
        r["split"] = split
    (copy / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = tmp_path / "geo"
    assert F.main(["--data", str(copy), "--tasks", "mug", "--out", str(out)]) == 0
    held = json.loads((out / GR.GRASP_JSON).read_text())
    assert set(held["rules"]) == {"mug"} and set(held["rules"]["mug"]) == set(GR.GRID)
    assert held["metrics"]["mug"]["train_episodes"] == 1 and held["metrics"]["mug"]["val_episodes"] == 1
    assert held["metrics"]["mug"]["train_accuracy"] == 1.0  # one episode: some rule of the grid reads it
    written = (out / GR.GRASP_JSON).stat().st_mtime_ns
    assert F.main(["--data", str(copy), "--tasks", "mug", "--out", str(out)]) == 0
    assert (out / GR.GRASP_JSON).stat().st_mtime_ns == written
    with pytest.raises(ValueError, match="no train or val episodes of airfryer"):
        F.main(["--data", str(copy), "--tasks", "mug,airfryer", "--out", str(out)])
    assert set(GR.load_grasp(out)) == {"mug"}
