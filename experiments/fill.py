"""Trains the generator of what a reprojected frame leaves empty (`wm.fill`) on a dataset's episodes.

Each recorded episode is replayed in MuJoCo's C engine from its seed with its recorded actions (the
dataset's own replay), the head camera drawn at every `--every`-th step with its depth and pose; the
first frame, reprojected to each later pose through its depth, is paired with the frame drawn there.
The training split's episodes train the net; the validation split's measure it against the
reprojection's own guess for those pixels (its neighbours' colours), by the mean absolute error and
the PSNR over the pixels no point landed on.

    python -m experiments.fill --data runs/data/demo --tasks step_back --out runs/fill/demo

`--data` takes several datasets, comma-separated (a zoo's rollouts beside the data it was trained on).

Writes OUT/fill.json and OUT/fill.msgpack (wm.fill.load_fill reads them; `experiments.loop_oracle
--modes reproject_fill_learned --fill OUT` puts the net in a policy's loop), OUT/pairs-<split>.npz, the
replayed pairs, which a rerun reuses, and OUT/egomotion.json, the robot's motion from the actions (the
base's from the driving commands, the joints' from their targets: wm.egomotion) fit on the same
training episodes and checked open loop on the validation ones; a finished fill or model is not made
again. A task of wm.grasp.GRASPED among `--tasks` (mug, airfryer, wipe) is not replayed for the fill: its
episodes fit its grasp rule instead (in OUT/grasp.json: wm.grasp.fit_grasp_rule on the training split,
its accuracy on the validation split beside the majority outcome's), with the motion models already
in OUT; a task whose rule OUT holds is not fit again. Both fits read at most `--episodes` episodes a task
and split, spread over the dataset's policies.

    python -m experiments.fill --data runs/data/demo_demo_rollouts --tasks mug --out runs/fill/demo
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from experiments.loop_oracle import Camera
from sim_data.dataset.episodes import read_episode
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import reproject
from sim_data.sim.robot import robot_index
from sim_data.sim.scene import load_model
from sim_data.sim.tasks import TASK_NAMES
from sim_data.util import run_cli
from wm.egomotion import (
    EGOMOTION_JSON,
    fit_egomotion,
    fit_joints,
    load_egomotion,
    roll_base,
    roll_joints,
    save_egomotion,
)
from wm.fill import FILL_JSON, FillConfig, filled, hole_l1, save_fill, train_fill
from wm.geometric import robot_camera
from wm.grasp import (
    GRASPED,
    GraspRule,
    closure_variants,
    fit_grasp_rule,
    load_grasp,
    refine_closure,
    robot_path,
    rule_grid,
    save_grasp,
    verdicts_of_rules,
)

PAIR_KEYS = ("reprojected", "covered", "true", "cam_pos", "cam_mat")
REPLAY_BATCH = 32


def manifest_rows(data: Path, tasks, split: str) -> list[dict]:
    """The manifest records of data's episodes of `tasks` in `split`, in the manifest's order, each with
    its episode file's path under "path"."""
    manifest = Path(data) / "manifest.jsonl"
    if not manifest.exists():
        raise FileNotFoundError(f"{data} is not a dataset (no manifest.jsonl); make one with "
                                f"python -m sim_data.dataset.generate")
    rows = [json.loads(line) for line in manifest.read_text().splitlines() if line]
    return [{**r, "path": str(Path(data) / r["file"])} for r in rows if r["task"] in tasks and r["split"] == split]


def fit_rows(data: list[Path], tasks, split: str, limit: int) -> list[dict]:
    """The episodes of `tasks` in `split` of the datasets `data` that fit the motion models and the grasp
    rules: per task at most `limit` (0: all), evenly spaced over its episodes ordered by policy and
    episode, so every policy keeps its share and every run takes the same ones (in the datasets' order).
    A few hundred pin down their few coefficients; a `full` dataset's thousands would cost the eval
    stage minutes."""
    rows = [r for d in data for r in manifest_rows(d, tasks, split)]
    kept = set()
    for task in tasks:
        found = sorted((i for i, r in enumerate(rows) if r["task"] == task),
                       key=lambda i: (rows[i].get("policy", ""), rows[i]["episode_id"]))
        kept |= set(found if not limit or len(found) <= limit else
                    (found[k * len(found) // limit] for k in range(limit)))
    return [r for i, r in enumerate(rows) if i in kept]


def seeded_batches(rows: list[dict], pad: bool = False):
    """The episodes of `rows` (manifest_rows' records) in batches of at most REPLAY_BATCH, grouped by task,
    held-out scene and length, each reset again from its seeds: yields (task, steps, members (indices into
    rows), env (sim_data.sim.env.HomeEnv on the cpu engine), the state at reset, the recorded actions (B, T,
    20)). With pad every batch holds REPLAY_BATCH episodes, the last member repeated (one shape, one
    compilation); members lists the real ones."""
    groups: dict = {}
    for i, r in enumerate(rows):
        groups.setdefault((r["task"], bool(r.get("heldout", False)), int(r["num_steps"])), []).append(i)
    envs: dict = {}
    for (task, heldout, steps), members in groups.items():
        for start in range(0, len(members), REPLAY_BATCH):
            chunk = members[start:start + REPLAY_BATCH]
            batch = chunk + chunk[-1:] * (REPLAY_BATCH - len(chunk)) if pad else chunk
            key = (task, heldout, len(batch))
            if key not in envs:
                envs[key] = HomeEnv(task, len(batch), engine="cpu", heldout=heldout)
            env = envs[key]
            actions = np.stack([read_episode(Path(rows[i]["path"]), cameras=(), sim_state=False)["action"]
                                for i in batch])
            state = env.reset(jnp.stack([jax.random.PRNGKey(int(rows[i]["seed"])) for i in batch]))
            yield task, steps, chunk, env, state, actions


def replay_pairs(rows: list[dict], size: int, every: int, progress: bool = True) -> tuple[dict, float]:
    """Replays the episodes of `rows` (manifest_rows' records) and pairs, at every
    `every`-th step, the first frame reprojected to the camera's pose with the frame drawn there.
    Returns ({"reprojected": (N, S, S, 3) uint8, "covered": (N, S, S) bool, "true": (N, S, S, 3) uint8,
    "cam_pos": (N, 3), "cam_mat": (N, 3, 3)}, the camera's vertical field of view in degrees)."""
    out = {k: [] for k in PAIR_KEYS}
    fovy = None
    bar = tqdm(total=len(rows), desc="replay", disable=not progress)
    for _, steps, chunk, env, state, actions in seeded_batches(rows):
        camera = Camera(env, state.task.colors, size)
        fovy = camera.fovy
        first = camera.draw(state)
        for t in range(steps):
            state = env.step(state, actions[:, t])
            if (t + 1) % every:
                continue
            now = camera.draw(state)
            frame, covered = reproject(first["rgb"], first["depth"], first["rides"], first["pos"], first["mat"],
                                       now["pos"], now["mat"], fovy)
            for k, v in zip(PAIR_KEYS, (frame, covered, now["rgb"], now["pos"], now["mat"])):
                out[k].append(np.asarray(v))
        bar.update(len(chunk))
    bar.close()
    if fovy is None:
        raise ValueError("no episodes to replay")
    return {k: np.concatenate(v) for k, v in out.items()}, fovy


def cached_pairs(out: Path, split: str, data: list[Path], tasks, size: int, every: int,
                 progress: bool) -> tuple[dict, float]:
    """replay_pairs for the `split` episodes of the datasets in `data`, kept in OUT/pairs-<split>.npz for
    a rerun."""
    path = out / f"pairs-{split}.npz"
    settings = json.dumps({"data": [str(d) for d in data], "tasks": sorted(tasks), "size": size, "every": every})
    if path.exists():
        with np.load(path) as z:
            if str(z["settings"]) == settings:
                return {k: z[k] for k in PAIR_KEYS}, float(z["fovy"])
    rows = [r for d in data for r in manifest_rows(d, tasks, split)]
    if not rows:
        raise ValueError(f"{', '.join(map(str, data))} hold no {split} episodes of {', '.join(tasks)}")
    pairs, fovy = replay_pairs(rows, size, every, progress)
    out.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, settings=settings, fovy=fovy, **pairs)
    os.replace(tmp, path)
    return pairs, fovy


def hole_scores(pred: np.ndarray, true: np.ndarray, covered: np.ndarray) -> dict:
    """Mean absolute error (0-255) and PSNR (dB) over the pixels no point landed on, all frames pooled:
    pred, true (N, S, S, 3) uint8, covered (N, S, S) bool."""
    err = np.asarray(hole_l1(jnp.asarray(pred, jnp.float32), jnp.asarray(true, jnp.float32), jnp.asarray(covered)))
    hole = ~covered
    mse = ((pred.astype(np.float64) - true) ** 2)[hole].mean()
    return {"hole_mae": float(err), "hole_psnr_db": float(10 * np.log10(255.0 ** 2 / max(mse, 1e-12))),
            "hole_share": float(hole.mean())}


def validate(net, params, cfg: FillConfig, pairs: dict, fovy: float, batch: int = 256) -> dict:
    """The fill's hole scores on pairs beside those of the reprojection's neighbour fill."""
    drawn = np.concatenate([filled(net, params, cfg, *(pairs[k][i:i + batch] for k in
                                                       ("reprojected", "covered", "cam_pos", "cam_mat")), fovy)
                            for i in range(0, len(pairs["covered"]), batch)])
    return {"fill": hole_scores(drawn, pairs["true"], pairs["covered"]),
            "neighbours": hole_scores(pairs["reprojected"], pairs["true"], pairs["covered"]),
            "pairs": len(pairs["covered"])}


def recorded_motion(rows: list[dict]) -> tuple[list, list, list]:
    """The base's world poses ([(T + 1, 3)] x, y, yaw), the actuated joints' positions ([(T + 1, 16)])
    and the actions ([(T, 20)]) of the episodes of rows."""
    idx = robot_index(load_model())
    eps = [read_episode(Path(r["path"]), cameras=()) for r in rows]
    return ([e["qpos"][:, idx.base_qpos] for e in eps], [e["qpos"][:, idx.posed_qpos] for e in eps],
            [e["action"] for e in eps])


def fit_and_check_egomotion(train_rows: list[dict], val_rows: list[dict]) -> tuple[np.ndarray, np.ndarray, dict]:
    """wm.egomotion's base and joint models fit on train_rows' episodes, and how far from the recorded
    ones their open-loop predictions are on val_rows': the base at the end (metres, mean and largest,
    beside a base that never moves), the joints over the episode (radians, mean and largest, beside
    joints held at their start)."""
    bases, qs, actions = recorded_motion(train_rows)
    coef, joints = fit_egomotion(bases, actions), fit_joints(qs, actions)
    end_err, still_err, joint_err, held_err = [], [], [], []
    for base, q, action in zip(*recorded_motion(val_rows)):
        pred = roll_base(coef, base[None, 0], action[None])[0]
        end_err.append(float(np.linalg.norm(pred[-1, :2] - base[-1, :2])))
        still_err.append(float(np.linalg.norm(base[0, :2] - base[-1, :2])))
        joint_err.append(np.abs(roll_joints(joints, q[None, 0], action[None])[0] - q))
        held_err.append(np.abs(q - q[:1]))
    joint_err, held_err = np.concatenate(joint_err), np.concatenate(held_err)
    return coef, joints, {"val_end_error_m": {"mean": float(np.mean(end_err)), "max": float(np.max(end_err))},
                          "val_end_error_still_m": float(np.mean(still_err)),
                          "val_joint_error_rad": {"mean": float(joint_err.mean()), "max": float(joint_err.max())},
                          "val_joint_error_held_rad": float(held_err.mean()), "val_episodes": len(val_rows)}


def grasp_verdicts(rows: list[dict], base: np.ndarray, joints: np.ndarray, rules: GraspRule,
                   progress: bool = True) -> tuple:
    """Each of the G rules' verdicts (rules: a GraspRule of (G,) arrays) on the episodes of rows
    (manifest_rows' records of tasks in wm.grasp.GRASPED), their states predicted from the recorded
    actions and the episode's first state (reset again from its seed): ((G, E) bool, (E,) bool the
    recorded outcomes, in rows' order)."""
    camera = robot_camera()
    order, verdicts = [], []
    bar = tqdm(total=len(rows), desc="grasp", disable=not progress)
    for task, _, chunk, _, state, actions in seeded_batches(rows, pad=True):
        path = robot_path(base, joints, state.qpos, state.mocap_pos, actions, camera)
        got = verdicts_of_rules(rules, path, actions, state.mocap_pos, state.task, camera, task)
        verdicts.append(got[:, :len(chunk)])
        order += chunk
        bar.update(len(chunk))
    bar.close()
    back = np.argsort(order)
    return np.concatenate(verdicts, 1)[:, back], np.array([bool(r["success"]) for r in rows])


def fit_and_check_grasp(train_rows: list[dict], val_rows: list[dict], base: np.ndarray, joints: np.ndarray,
                        progress: bool = True) -> tuple[GraspRule, dict]:
    """wm.grasp's rule fit on train_rows' episodes (the grid's most accurate, its closure then refined:
    wm.grasp.refine_closure) and its accuracy on val_rows', beside that of always predicting the training
    split's more common outcome."""
    verdicts, outcomes = grasp_verdicts(train_rows, base, joints, rule_grid(), progress)
    rule, train_acc = fit_grasp_rule(verdicts, outcomes)
    variants, _ = grasp_verdicts(train_rows, base, joints, closure_variants(rule), progress)
    rule, train_acc = refine_closure(rule, variants, outcomes)
    val_verdicts, val_outcomes = grasp_verdicts(val_rows, base, joints, jax.tree.map(lambda x: x[None], rule),
                                                progress)
    majority = bool(outcomes.mean() >= 0.5)
    return rule, {"train_accuracy": train_acc, "val_accuracy": float(np.mean(val_verdicts[0] == val_outcomes)),
                  "val_accuracy_majority": float(np.mean(val_outcomes == majority)),
                  "train_episodes": len(train_rows), "val_episodes": len(val_rows),
                  "val_successes": int(val_outcomes.sum())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="dataset directories (sim_data.dataset.generate's OUT), "
                    "comma-separated")
    ap.add_argument("--tasks", required=True, help="comma-separated task names")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--size", type=int, default=64, help="frame size in pixels")
    ap.add_argument("--every", type=int, default=2, help="pair every k-th step of an episode")
    ap.add_argument("--steps", type=int, default=FillConfig.steps, help="training steps")
    ap.add_argument("--batch", type=int, default=FillConfig.batch)
    ap.add_argument("--width", type=int, default=FillConfig.width)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=384, help="at most this many episodes a task and split fit "
                    "the motion models and the grasp rules, spread over the dataset's policies (0: all)")
    a = ap.parse_args(argv)
    tasks = [t for t in a.tasks.split(",") if t]
    bad = [t for t in tasks if t not in TASK_NAMES]
    if bad or not tasks:
        raise ValueError(f"unknown tasks {bad}; choose among {', '.join(TASK_NAMES)}")
    if a.every < 1 or a.size < 8 or a.size % 8 or a.episodes < 0:
        raise ValueError(f"--every must be >= 1, --size a multiple of 8 and --episodes >= 0; got {a.every}, "
                         f"{a.size} and {a.episodes}")
    cfg = FillConfig(width=a.width, steps=a.steps, batch=a.batch, seed=a.seed)
    data = [Path(d) for d in a.data.split(",") if d]
    if not (a.out / EGOMOTION_JSON).exists():
        rows = {split: fit_rows(data, tasks, split, a.episodes) for split in ("train", "val")}
        empty = [split for split, found in rows.items() if not found]
        if empty:
            raise ValueError(f"{a.data} hold no {' or '.join(empty)} episodes of {', '.join(tasks)}")
        print(f"fitting the robot's motion on {len(rows['train'])} training episodes, checking it on "
              f"{len(rows['val'])}", flush=True)
        coef, joints, check = fit_and_check_egomotion(rows["train"], rows["val"])
        save_egomotion(a.out, coef, {**check, "data": a.data, "tasks": tasks}, joints)
        print(f"base motion: open loop over a validation episode ends {check['val_end_error_m']['mean']:.3f} m "
              f"from the recorded base (a still base: {check['val_end_error_still_m']:.3f} m); joints "
              f"{check['val_joint_error_rad']['mean']:.4f} rad from the recorded ones (held: "
              f"{check['val_joint_error_held_rad']:.4f})")
    grasped, drawn = [t for t in tasks if t in GRASPED], [t for t in tasks if t not in GRASPED]
    unfit = [t for t in grasped if t not in load_grasp(a.out)]
    base, joints = load_egomotion(a.out, joints=True) if unfit else (None, None)
    for task in unfit:
        rows = {split: fit_rows(data, [task], split, a.episodes) for split in ("train", "val")}
        if empty := [split for split, found in rows.items() if not found]:
            raise ValueError(f"{a.data} hold no {' or '.join(empty)} episodes of {task} to fit its grasp rule on")
        rule, check = fit_and_check_grasp(rows["train"], rows["val"], base, joints)
        save_grasp(a.out, task, rule, {**check, "data": a.data})
        print(f"grasp ({task}): {rule.as_dict()}; validation outcomes predicted {check['val_accuracy']:.3f} of "
              f"{check['val_episodes']} ({check['val_accuracy_majority']:.3f} by the majority outcome)")
    if not drawn:
        return 0
    if (a.out / FILL_JSON).exists():
        print(f"{a.out / FILL_JSON} exists: the fill is trained (remove it to train again)")
        return 0
    train, fovy = cached_pairs(a.out, "train", data, drawn, a.size, a.every, True)
    val, _ = cached_pairs(a.out, "val", data, drawn, a.size, a.every, True)
    print(f"{len(train['covered'])} training pairs ({(~train['covered']).mean():.1%} of their pixels empty), "
          f"{len(val['covered'])} validation pairs")
    net, params, fit = train_fill(train, fovy, cfg)
    scores = validate(net, params, cfg, val, fovy)
    save_fill(a.out, params, cfg, a.size, {"train_loss": fit["loss"], "val": scores, "data": a.data,
                                           "tasks": drawn, "every": a.every})
    print(json.dumps(scores, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
