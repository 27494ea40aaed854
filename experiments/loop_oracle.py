"""What a policy does when the frames it reads stand in for an imagination's: its closed loop in the
simulator, from the evaluator's held-out initial states, with the head camera's frame replaced.

A world model ranks a policy by letting it act on imagined frames; a policy that acts on its camera
then behaves as the frames let it. This study separates what the frames must get right from what a
world model gets wrong, with the simulator's own state and camera:

- `true`: the simulator's frames, the reference loop;
- `still`: the first frame held, what an imagination that draws no motion shows;
- `reproject`: the first frame carried to the camera's true pose through its depth
  (`sim_data.sim.render.reproject`): the camera's motion and its parallax exact, what the first frame
  hid filled from its neighbours, the world frozen (an arm or an object moved is not redrawn);
- `reproject_fill_true`: the same with the pixels no point landed on taken from the simulator's frame:
  what a generator that draws exactly what the first frame hid would add to the reprojection;
- `reproject_fill_learned`: the same with those pixels drawn by a generator trained on a dataset's
  episodes (`wm.fill`, trained by `experiments.fill`; `--fill DIR`), which knows the camera's pose but
  not the simulator's frame;
- `egomotion_fill_learned`: the same at the camera's pose with the base where a model of its motion
  under the driving commands puts it (`wm.egomotion`, fit beside the fill), run open loop from the
  first state on the actions the policy took, the joints as the simulator has them: the frames of an
  imagination whose camera moves as the actions say;
- `imagined`: the same with nothing of the simulator after the first state: the actuated joints where
  a model of their motion under their targets puts them (`wm.egomotion` too), the objects held where
  they were, the policy's proprioception the first state's, and the success predicted by the task's
  own rule on the predicted states (step_back only: the band of distance backed, failed where the base
  met an obstacle on the way); the simulator runs beside it only to say what the same actions truly do.
  A world model for step_back made of the first frame's depth, the motion models and the fill, run as
  one compiled loop (`wm.geometric.imagine_robot`, which the evaluator's geometric read-out runs);
- `imagined_body`: the same, stepped here, with the robot's own body drawn at its predicted joints (the
  renderer's drawing of the robot's geoms alone, as its model gives their shapes) where the first
  frame's drawing of it was, what that drawing hid left to the fill; its success the band alone;
- `flow_chain`: each frame shown warped from the last one shown by the true frames' motion, block
  matched on 8x8 cells (`wm.model.block_flow`, `wm.model.warp`): the world model's own warp, given
  the true motion of every step;
- `flow_anchor`: the first frame warped by the motion from it to the true frame now, block matched on
  the same cells: the same warp anchored on the first frame, so that motion accumulates over the
  episode rather than being resampled away step by step.

Written to OUT/loop_oracle.json, per task, policy and mode: the success rate with its Wilson interval,
the base's displacement back along its starting heading at the end (mean, least, most), the forward
command summed over the episode (as applied), the RMS gap of the actions from the `true` loop's at
each step (mean over the episode), and the PSNR of the frames read against the simulator's frame of
the same state (steps 1-8 and the episode's second half); and OUT/frames/<task>/<policy>_<mode>.png,
the first episode's true frames above those read, at five steps from the first to the last; with the
`imagined` modes, their predicted success beside the true loop's, per policy and per task (Pearson r
and mean absolute error over the policies, `imagined_against_true`). The same
command resumes: a (task, policy, mode) already in the file is kept. The `cpu` engine (MuJoCo's C
engine), on any machine.

The held-out states are the evaluator's (`heldout_seeds`, past the zoo's data seeds; the evaluator also
skips its world models' training seeds, which collide with a held-out seed rarely), and the policy
draws its random numbers as in the evaluator's first slice of states: where a task's states fit one
slice (`state_batch`), the `true` loop's outcomes are the evaluation's own.

    python -m experiments.loop_oracle --policies runs/policies/demo --tasks step_back --out runs/oracle/demo
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image
from tqdm import tqdm

from experiments.evaluate import chunk_policy
from sim_data.policies.registry import heldout_seeds, resolve, used_seeds
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import (
    HEAD_CAMERA,
    cached_renderers,
    camera_poses,
    episode_rgb,
    poses_of,
    reproject,
    rides_with_camera,
    riding_pixels,
)
from sim_data.sim.robot import FORWARD_SPEED
from sim_data.sim.rollout import jitted_act, jitted_init
from sim_data.sim.tasks import STEP_BACK_BAND, TASK_NAMES, backward_distance
from sim_data.util import run_cli, wilson_interval, write_json_atomic
from wm.egomotion import load_egomotion, step_base, step_joints
from wm.fill import filled, load_fill
from wm.geometric import PREDICTS, Motion, imagine_robot, robot_camera, start_view
from wm.metrics import psnr as frame_psnr
from wm.model import block_flow, warp

MODES = ("true", "still", "reproject", "reproject_fill_true", "reproject_fill_learned", "egomotion_fill_learned",
         "imagined", "imagined_body", "flow_chain", "flow_anchor")
LEARNED, EGOMOTION, IMAGINED, BODY = "reproject_fill_learned", "egomotion_fill_learned", "imagined", "imagined_body"
NEEDS_FILL = (LEARNED, EGOMOTION, IMAGINED, BODY)  # the modes that draw with a trained fill (--fill)
PREDICTED = (IMAGINED, BODY)  # the modes that predict the robot's motion and the success
FLOW_RADIUS = 4
ANCHOR_RADIUS = 8  # the match from the first frame searches twice a step's radius: its motion accumulates
RESULTS = "loop_oracle.json"
PSNR_EQUAL = 100.0  # dB where the frame read is the true one (its PSNR is infinite)
STRIP_FRAMES = 5  # steps of the first episode filmed, evenly spread from the first to the last


class Camera:
    """The head camera of a batch of episodes: each state's frame, depth, the pixels of the robot's own
    body and the camera's pose."""

    def __init__(self, env: HomeEnv, colors, size: int):
        (self.renderer,) = cached_renderers(size, (HEAD_CAMERA,))
        geo = self.renderer.geometry
        self.cam = geo.cam_names.index(HEAD_CAMERA)
        self.fovy = float(geo.fovy[self.cam])
        self.rides = rides_with_camera(env.model, HEAD_CAMERA)
        self.env = env
        self.rgb = episode_rgb(geo, colors)

    def draw(self, state) -> dict:
        return self.draw_poses(self.env.poses(state))

    def draw_poses(self, poses) -> dict:
        """The same drawing at any Poses (B, ...): where a predicted robot would be, for instance."""
        out = {k: np.asarray(v) for k, v in self.renderer.render(poses, self.rgb).items()}
        out["rides"] = riding_pixels(self.rides, out["geom_id"])
        out["pos"], out["mat"] = np.asarray(poses.cam_xpos[:, self.cam]), np.asarray(poses.cam_xmat[:, self.cam])
        return out


def _unit(x):
    return jnp.asarray(x, jnp.float32) / 255.0


@functools.partial(jax.jit, static_argnums=3)
def _warped(src, frm, to, radius: int):
    """src warped by the block-matched motion from frm to `to` (all (B, S, S, 3) in [0, 1]), as uint8."""
    flow, _ = block_flow(frm, to, radius)
    return jnp.clip(warp(src, flow) * 255.0 + 0.5, 0, 255).astype(jnp.uint8)


def shown_frame(mode: str, first: dict, now: dict, prev_true, prev_shown, fovy: float, fill=None) -> np.ndarray:
    """(B, S, S, 3) uint8: the frame the policy reads in `mode`, given the first state's drawing, the
    current one's (for the modes that place the camera by wm.egomotion, the drawing at the imagined
    pose), the last step's true frame and the last frame shown; fill: wm.fill.load_fill's (net,
    params, cfg, size), for the modes that draw with it (NEEDS_FILL)."""
    if mode == "true":
        return now["rgb"]
    if mode == "still":
        return first["rgb"]
    if mode in ("reproject", "reproject_fill_true", *NEEDS_FILL):
        frame, covered = reproject(first["rgb"], first["depth"], first["rides"], first["pos"], first["mat"],
                                   now["pos"], now["mat"], fovy, keep_rides=mode != BODY)
        if mode in NEEDS_FILL:
            net, params, cfg, _ = fill
            frame = filled(net, params, cfg, frame, covered, now["pos"], now["mat"], fovy)
            return np.where(now["rides"][..., None], now["rgb"], frame) if mode == BODY else frame
        return frame if mode == "reproject" else np.where(covered[..., None], frame, now["rgb"])
    if mode in ("flow_chain", "flow_anchor"):
        src, frm, radius = ((prev_shown, prev_true, FLOW_RADIUS) if mode == "flow_chain"
                            else (first["rgb"], first["rgb"], ANCHOR_RADIUS))
        return np.asarray(_warped(_unit(src), _unit(frm), _unit(now["rgb"]), radius))
    raise ValueError(f"unknown mode {mode!r}; choose among {', '.join(MODES)}")


def imagined_loop(task: str, source, reset_keys: np.ndarray, rng: jax.Array, motion: Motion,
                  proprio: str = "held") -> dict:
    """run_loop's `imagined` mode: the policy acts in wm.geometric.imagine_robot's imagination from the
    first state, compiled once; the simulator then plays the actions it took there, for what they truly
    do and for the frames the imagination should have drawn. Returns run_loop's dict."""
    env = HomeEnv(task, len(reset_keys), engine="cpu")
    state = start = env.reset(jnp.asarray(reset_keys))
    camera = Camera(env, state.task.colors, motion.size)
    robot = robot_camera()
    view = start_view(env, start, motion.size, robot)
    policy, params = chunk_policy([source], len(reset_keys))
    _, k_pol, k_act = jax.random.split(rng, 3)
    got = imagine_robot(policy, params, motion, view, (k_pol, k_act), robot, env.episode_steps, proprio,
                        keep_frames=True)
    actions, frames = np.asarray(got["action"]), np.asarray(got["frames"])
    psnr, strip = [], []
    filmed = set(np.linspace(0, env.episode_steps - 1, STRIP_FRAMES).round().astype(int).tolist())
    for t in range(env.episode_steps):
        state = env.step(state, jnp.asarray(actions[:, t]))
        now = camera.draw(state)
        psnr.append(np.minimum(frame_psnr(frames[:, t], now["rgb"]), PSNR_EQUAL))
        if t in filmed:
            strip.append(np.concatenate([now["rgb"][0], frames[0, t]], axis=0))
    back = np.asarray(backward_distance(start.task, got["qpos"], env.idx))
    return {"predicted_back": back, "predicted_success": np.asarray(got["success"], bool),
            "success": np.asarray(state.success, bool),
            "back": np.asarray(backward_distance(state.task, state.qpos, env.idx)),
            "forward": actions[..., FORWARD_SPEED].sum(axis=1), "actions": actions,
            "psnr": np.stack(psnr, axis=1), "strip": np.concatenate(strip, axis=1)}


def run_loop(task: str, source, mode: str, reset_keys: np.ndarray, rng: jax.Array, size: int = 64,
             fill=None, egomotion=None) -> dict:
    """One closed loop of `source` (a registry PolicySource) on `task` from reset_keys (B, 2), reading the
    frames of `mode` (size x size pixels; fill: load_fill's tuple, for the learned fills; egomotion:
    load_egomotion's (base, joints) models, for egomotion_fill_learned and the imagined modes), the
    policy run and seeded as the evaluator runs it in the simulator (its chunk of one, salted by its
    name; rng split as `record_episodes` splits it). Returns per-episode arrays: success (B,), back
    (B,) m, forward (B,) the applied forward command summed, (the imagined modes only)
    predicted_success (B,) and predicted_back (B,) m from the imagined base,
    actions (B, T, 20), psnr (B, T) of the frames read; and "strip", the first episode's true and read
    frames at STRIP_FRAMES steps (save_strip)."""
    if mode == IMAGINED:
        net, params, cfg, fill_size = fill
        return imagined_loop(task, source, reset_keys, rng, Motion(*map(jnp.asarray, egomotion), params, net, cfg,
                                                                   fill_size))
    env = HomeEnv(task, len(reset_keys), engine="cpu")
    state = start = env.reset(jnp.asarray(reset_keys))
    camera = Camera(env, state.task.colors, size)
    first = camera.draw(state)
    policy, params = chunk_policy([source], len(reset_keys))
    _, k_pol, k_act = jax.random.split(rng, 3)
    obs = {**state.obs, "image": jnp.asarray(first["rgb"])}
    carry = jitted_init(policy)(params, obs, state.task, k_pol)
    act = jitted_act(policy)
    prev_true = prev_shown = first["rgb"]
    base_qpos, posed_qpos = env.idx.robot.base_qpos, env.idx.robot.posed_qpos
    base, moved = np.asarray(state.qpos)[:, base_qpos].astype(np.float64), np.zeros((len(reset_keys), 3))
    joints = np.asarray(state.qpos)[:, posed_qpos].astype(np.float64)
    turned = np.zeros_like(joints)
    actions, psnr, strip = [], [], []
    filmed = set(np.linspace(0, env.episode_steps - 1, STRIP_FRAMES).round().astype(int).tolist())
    for t in range(env.episode_steps):
        action, carry = act(params, obs, carry, jax.random.fold_in(k_act, t))
        action = env.core.applied(action)
        actions.append(np.asarray(action))
        state = env.step(state, action)
        now = camera.draw(state)
        seen = now
        if mode in (EGOMOTION, BODY):
            base_model, joint_model = egomotion
            base, moved = step_base(base_model, base, moved, np.asarray(action))
            held = mode == BODY
            robot = np.array(start.qpos if held else state.qpos)  # the state the camera is placed by
            robot[:, base_qpos] = base
            if held:
                joints, turned = step_joints(joint_model, joints, turned, np.asarray(action))
                robot[:, posed_qpos] = joints
            mocap = start.mocap_pos if held else state.mocap_pos
            seen = (camera.draw_poses(poses_of(env.model, robot, mocap)) if mode == BODY
                    else {**now, **dict(zip(("pos", "mat"), camera_poses(env.model, robot, mocap)))})
        shown = shown_frame(mode, first, seen, prev_true, prev_shown, camera.fovy, fill)
        psnr.append(np.minimum(frame_psnr(shown, now["rgb"]), PSNR_EQUAL))
        if t in filmed:
            strip.append(np.concatenate([now["rgb"][0], shown[0]], axis=0))
        prev_true, prev_shown = now["rgb"], shown
        obs = {**state.obs, "image": jnp.asarray(shown)}
        if mode == BODY:
            obs["proprio"] = start.obs["proprio"]
    actions = np.stack(actions, axis=1)
    predicted = {}
    if mode == BODY:
        back = np.asarray(backward_distance(start.task, robot, env.idx))
        predicted = {"predicted_back": back, "predicted_success": (back >= STEP_BACK_BAND[0]) & (back <= STEP_BACK_BAND[1])}
    return {**predicted, "success": np.asarray(state.success, bool),
            "back": np.asarray(backward_distance(state.task, state.qpos, env.idx)),
            "forward": actions[..., FORWARD_SPEED].sum(axis=1), "actions": actions,
            "psnr": np.stack(psnr, axis=1), "strip": np.concatenate(strip, axis=1)}


def save_strip(path: Path, strip: np.ndarray) -> None:
    """Writes run_loop's strip ((2 S, STRIP_FRAMES S, 3) uint8: the simulator's frame above the frame read,
    at evenly spread steps of the first episode) as a PNG four times the size, atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    big = Image.fromarray(strip).resize((strip.shape[1] * 4, strip.shape[0] * 4), Image.NEAREST)
    tmp = path.with_suffix(".tmp.png")
    big.save(tmp)
    os.replace(tmp, path)


def summary(res: dict, reference: dict | None) -> dict:
    """The figures of one loop (run_loop's dict), its action gap against the `true` loop's (reference)."""
    n, k = len(res["success"]), int(res["success"].sum())
    half = res["psnr"].shape[1] // 2
    back = res["back"]
    out = {"episodes": n, "success": k / n, "success_ci": list(wilson_interval(k, n)),
           "back_m": {"mean": float(back.mean()), "min": float(back.min()), "max": float(back.max())},
           "forward_sum": float(res["forward"].mean()),
           "psnr_db_steps_1_8": float(res["psnr"][:, :8].mean()),
           "psnr_db_second_half": float(res["psnr"][:, half:].mean())}
    if reference is not None:
        gap = np.sqrt(((res["actions"] - reference["actions"]) ** 2).mean(axis=-1))
        out["action_gap"] = float(gap.mean())
    if "predicted_success" in res:
        k, pb = int(res["predicted_success"].sum()), res["predicted_back"]
        out["predicted_success"], out["predicted_success_ci"] = k / n, list(wilson_interval(k, n))
        out["predicted_back_m"] = {"mean": float(pb.mean()), "min": float(pb.min()), "max": float(pb.max())}
    return out


def imagined_against_true(results: dict) -> dict:
    """Per task and predicting mode (PREDICTED), its predicted success rates against the true loop's over
    the policies that have both: Pearson r (None where either side is constant), mean absolute error,
    policies."""
    out = {}
    for task, pols in results.get("tasks", {}).items():
        for mode in PREDICTED:
            pairs = [(v[mode]["predicted_success"], v["true"]["success"]) for v in pols.values()
                     if mode in v and "true" in v]
            if not pairs:
                continue
            pred, true = np.array(pairs).T
            r = float(np.corrcoef(pred, true)[0, 1]) if len(pairs) > 1 and pred.std() > 0 and true.std() > 0 else None
            out.setdefault(task, {})[mode] = {"pearson": r, "mean_abs_error": float(np.abs(pred - true).mean()),
                                              "policies": len(pairs)}
    return out


def study(policies: str, tasks: list[str], out: Path, modes: list[str], episodes: int, seed: int, size: int = 64,
          progress: bool = True, fill: Path | None = None) -> dict:
    """Runs every (task, policy, mode) not yet in OUT/loop_oracle.json and writes it after each; a pair
    with modes left runs its `true` loop first, the reference of their action gap. fill: the directory
    of a trained wm.fill and wm.egomotion (experiments.fill's OUT), needed by NEEDS_FILL's modes."""
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        raise ValueError(f"unknown modes {unknown}; choose among {', '.join(MODES)}")
    bad = [t for t in tasks if t not in TASK_NAMES]
    if bad:
        raise ValueError(f"unknown tasks {bad}; choose among {', '.join(TASK_NAMES)}")
    if episodes < 1 or size < 8 or size % 8:
        raise ValueError(f"--episodes must be >= 1 and --size a multiple of 8; got {episodes} and {size}")
    fill_net = egomotion = None
    if any(m in NEEDS_FILL for m in modes):
        if fill is None:
            raise ValueError(f"the modes {', '.join(NEEDS_FILL)} draw with a trained fill: name its directory "
                             f"with --fill (train one with python -m experiments.fill)")
        fill_net = load_fill(fill)
        egomotion = load_egomotion(fill, joints=True) if any(m in (EGOMOTION, *PREDICTED) for m in modes) else None
        if fill_net[3] != size:
            raise ValueError(f"the fill in {fill} draws {fill_net[3]}-px frames; the loops here read {size}-px "
                             f"ones (--size)")
    if any(m in PREDICTED for m in modes) and any(t not in PREDICTS for t in tasks):
        raise ValueError(f"the modes {', '.join(PREDICTED)} predict the robot's motion alone, from which only the "
                         f"success of {', '.join(PREDICTS)} follows; run them on those tasks")
    sources = resolve([s for s in policies.split(",") if s])
    path = out / RESULTS
    results = json.loads(path.read_text()) if path.exists() else {}
    settings = {"episodes": episodes, "seed": seed, "size": size}
    if results and results.get("settings", {}) != settings:
        raise ValueError(f"{path} was written with {results.get('settings')}; use another --out or the same "
                         f"--episodes, --seed and --size")
    results["settings"] = settings
    used = used_seeds(*({s.record.get("data") for s in sources} - {None}))
    jobs = [(t, s) for t in tasks for s in sources if s.runs_on(t)]
    if not jobs:
        raise ValueError(f"none of the policies runs on {', '.join(tasks)}")
    # the evaluator's key for its first slice of states (experiments.evaluate.slice_key)
    rng = jax.random.fold_in(jax.random.PRNGKey(seed), 0)
    bar = tqdm(total=len(jobs) * len(modes), desc="loops", disable=not progress)
    for task, source in jobs:
        keys = np.stack([np.asarray(jax.random.PRNGKey(s)) for s in heldout_seeds(task, episodes, seed, used)])
        done = results.setdefault("tasks", {}).setdefault(task, {}).setdefault(source.name, {})
        todo = [m for m in modes if m not in done]
        bar.update(len(modes) - len(todo))
        if not todo:
            continue
        reference = run_loop(task, source, "true", keys, rng, size)
        for mode in todo:
            res = reference if mode == "true" else run_loop(task, source, mode, keys, rng, size, fill_net, egomotion)
            if mode != "true":
                save_strip(out / "frames" / task / f"{source.slug}_{mode}.png", res["strip"])
            done[mode] = summary(res, None if mode == "true" else reference)
            if mode in NEEDS_FILL:
                done[mode]["fill"] = str(fill)
            if any(m in PREDICTED for m in modes):
                results["imagined_against_true"] = imagined_against_true(results)
            write_json_atomic(path, results)
            bar.update(1)
    bar.close()
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policies", required=True, help="policy specs as the evaluator takes them (a zoo registry, "
                    "registry#lineage, a plug-in module:function, comma-separated)")
    ap.add_argument("--tasks", required=True, help="comma-separated task names")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--modes", help=f"comma-separated among {', '.join(MODES)} (default: all, those with a "
                    "learned fill only with --fill)")
    ap.add_argument("--episodes", type=int, default=16, help="held-out initial states a policy (the evaluator's)")
    ap.add_argument("--seed", type=int, default=0, help="the evaluator's seed: its held-out states and draws")
    ap.add_argument("--size", type=int, default=64, help="the camera's frame size in pixels, the world model's")
    ap.add_argument("--fill", type=Path, help="a trained fill's directory (experiments.fill --out), for "
                    f"{' and '.join(NEEDS_FILL)}")
    a = ap.parse_args(argv)
    modes = ([m for m in a.modes.split(",") if m] if a.modes
             else [m for m in MODES if m not in NEEDS_FILL or a.fill is not None])
    res = study(a.policies, [t for t in a.tasks.split(",") if t], a.out, modes,
                a.episodes, a.seed, a.size, fill=a.fill)
    for task, pols in res["tasks"].items():
        for name, by_mode in pols.items():
            line = "  ".join(f"{m} {v['success']:.2f} ({v['back_m']['mean']:+.2f} m)" for m, v in by_mode.items())
            for mode in PREDICTED:
                if mode in by_mode:
                    line += f"  {mode} predicted {by_mode[mode]['predicted_success']:.2f}"
            print(f"{task:10s} {name:42s} {line}")
    for task, by_mode in res.get("imagined_against_true", {}).items():
        for mode, fit in by_mode.items():
            r = "undefined" if fit["pearson"] is None else f"{fit['pearson']:.3f}"
            print(f"{task}: {mode}'s predicted against true success over {fit['policies']} policies: Pearson {r}, "
                  f"mean |error| {fit['mean_abs_error']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
