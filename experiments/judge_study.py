"""Which episode judge reads a world model's imaginations best, measured on a kept evaluation.

    python -m experiments.judge_study --eval runs/eval/full_r3 --out runs/judge_study/full_r3
    python -m experiments.judge_study --eval runs/eval/full_r3 --out ... --wm RUN --data DATA --variants a,b

The evaluation (experiments.evaluate with keep_features=1) keeps the step features of every
imagined episode of its zoo. Each judge variant here is fit as wm.train fits its judge (wm.judge.fit
on the world model's imaginations of its training episodes: open loop under their logged actions,
closed loop for the rollouts of learned policies) but on other episodes or inputs, then reads the
kept imaginations; its within-task statistics come from experiments.stats.within_task (one bootstrap
over policies and initial states shared by every variant), beside the evaluation's own read-outs
(the judge saved with the model, the progress head, the per-step rule), for every policy and for the
policies whose rollouts the world model never saw.

A variant with `replay_labels` labels each closed-loop imagination of a learned policy's rollout by
the simulator's outcome of the actions the policy took in that imagination, played open loop from
the episode's initial state (wm.judge.replayed_labels, as wm.train's judge_labels=replayed),
instead of the outcome of the rollout in the simulator: the judge then learns what the imagined
actions achieve, and a loop that drifts from its true actions (a drive that overshoots in
imagination) is read by its own actions.

Beside them two bounds, neither a valid evaluation. The observed bound: a judge fit to the training
episodes' true frames (what imagination would show were it exact) reading the evaluation's simulated
episodes (kept by keep_features=1): how far the head camera and the proprioception decide each task's
outcome, whatever the world model imagines; where the judges of imaginations reach it, better
dynamics cannot help them. The cross-fit bound: a judge cross-fit on the evaluation's own imaginations
and outcomes (each task's policies split into folds; a fold is read by a judge fit on the others).
It measures how much of the within-task ranking the imagined episodes carry, whatever the judge
learns from: where it is high and the trained judges are low, the judge's training data limits;
where it is low too, the world model's imaginations do.

Writes OUT/judge_study.json and prints a table; the imagined training episodes
(OUT/imagined_{train,val}.npz) and each variant's probabilities (OUT/variants/<name>.npz) are kept,
so a rerun resumes, and `--score-only` scores what OUT/variants holds from the evaluation's files
alone.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

import numpy as np

from experiments import stats as S
from experiments.evaluate import MODEL_READOUTS, load_features, load_task
from sim_data.dataset.cache import TrainingCache, window_episodes
from sim_data.sim.engines import default_engine
from sim_data.util import run_cli, write_json_atomic
from wm.checkpoint import load_run_config, load_trained
from wm.config import JUDGE_LR, make_config, with_imagine
from wm.imagine import FEATURE_GROUPS, feature_columns
from wm.judge import (
    VAL_EPISODES,
    closed_loop_rows,
    dataset_policies,
    fit,
    imagine_episodes,
    join_episodes,
    load_judge,
    observe_episodes,
    replay_batch,
    replayed_labels,
    spread,
)

ENSEMBLE = 6  # the judges of the seed-spread and ensemble variants


@dataclasses.dataclass(frozen=True)
class Variant:
    """A judge fit to `episodes` of the world model's imagined training episodes (0: all; "rollouts":
    only the learned policies' closed-loop ones), reading the step-feature groups `inputs`; with
    `observed`, to the same episodes read from their true frames too (wm.judge.observe_episodes, as
    wm.train's judge_observed), and with `imagined` False to those true readings alone: a judge of
    real episodes, as a success classifier trained on robot data would be, reading imaginations.
    seed: added to the world model's seed for the judge's initialisation and batches; members: that
    many judges, of seeds seed, seed + 1, ..., read as the mean of their probabilities; lr: the
    judge's learning rate; select: each member kept at its own best validation step ("best") or at its
    last ("last"); raw_mean: the features' own mean pooled too (wm.judge.fit); replay_labels: the
    closed-loop imaginations labelled by their own actions' outcome in the simulator (replayed)."""

    episodes: int = 0
    inputs: tuple = FEATURE_GROUPS
    rollouts_only: bool = False
    observed: bool = False
    imagined: bool = True
    closed_loop: bool = True  # False: the learned policies' rollouts imagined open loop under their logged actions
    seed: int = 0
    members: int = 1
    lr: float = JUDGE_LR
    select: str = "best"
    raw_mean: bool = False
    replay_labels: bool = False


def preset_judge(preset: str) -> Variant:
    """The Variant that fits the episode judge of wm.config's `preset` (its inputs, learning rate,
    members and kept step)."""
    cfg = make_config(preset)
    return Variant(inputs=cfg.judge_inputs, lr=cfg.judge_lr, members=cfg.judge_members, select=cfg.judge_select,
                   raw_mean=cfg.judge_raw_mean, observed=cfg.judge_observed,
                   replay_labels=cfg.judge_labels == "replayed")


VARIANTS = {
    "refit_1024": Variant(episodes=1024),  # TrainConfig's default judge_episodes, fit again
    "all": Variant(),
    "all_no_action": Variant(inputs=tuple(g for g in FEATURE_GROUPS if g != "action")),
    # without the outcome head, which learns each window's final success from what it shows so far
    # (the task, the scene, the phase), the judge must read what the imagined steps did
    "all_no_outcome": Variant(inputs=tuple(g for g in FEATURE_GROUPS if g != "outcome")),
    "all_proprio_progress": Variant(inputs=("proprio", "progress")),
    "rollouts_only": Variant(rollouts_only=True),
    "all_observed": Variant(observed=True),
    "observed_only": Variant(observed=True, imagined=False),
    # every episode imagined under its logged actions and labelled with their outcome in the simulator,
    # where a closed-loop imagination carries the outcome of the actions its policy took on true frames
    "all_open_loop": Variant(closed_loop=False),
    # the judge's own seed: `all` fit again from other initialisations on the same imaginations
    **{f"all_seed{k}": Variant(seed=k) for k in range(1, ENSEMBLE)},
    # the mean of ENSEMBLE such judges; the same at a quarter of the learning rate, where a judge
    # that overfits its few hundred episodes within the first validations stops less abruptly
    f"all_x{ENSEMBLE}": Variant(members=ENSEMBLE),
    "all_lr5e-4": Variant(lr=5e-4),
    f"all_lr5e-4_x{ENSEMBLE}": Variant(lr=5e-4, members=ENSEMBLE),
    # the same judges kept at their last step: a validation of a few dozen episodes (the demo's) keeps
    # members that have barely left their initialisation
    f"all_lr5e-4_x{ENSEMBLE}_last": Variant(lr=5e-4, members=ENSEMBLE, select="last"),
    # the presets' judges as wm.config names them (both read the proprioception and actions; `demo`'s
    # kept at the last step), and the same pooling the features' own mean too (a distance at any speed)
    **{f"{name}_recipe{tag}": dataclasses.replace(preset_judge(name), raw_mean=raw)
       for name in ("full", "demo") for tag, raw in (("", False), ("_raw_mean", True))},
    # `full`'s second judge: every group but the scene head's, as six at a quarter of the learning rate
    "full_judge2": dataclasses.replace(preset_judge("full"), inputs=make_config("full").judge2_inputs),
    # the presets' judges without the actions: a judge that reads the commands can learn what a
    # degraded command looks like (a weak grip, noise) rather than whether the imagined body got there;
    # "_proprio" reads the imagined body alone, "_seen" every imagined group but the actions and the
    # scene head's
    **{f"{name}_recipe_{tag}": dataclasses.replace(preset_judge(name), inputs=inputs)
       for name in ("full", "demo")
       for tag, inputs in (("proprio", ("proprio",)),
                           ("seen", tuple(g for g in FEATURE_GROUPS if g not in ("action", "scene"))))},
    # the presets' judges learning what the closed loop's imagined actions truly achieve
    **{f"{name}_recipe_replay": dataclasses.replace(preset_judge(name), replay_labels=True)
       for name in ("full", "demo")},
}
BOUND = "crossfit_bound"
# A judge fit to the training episodes' true frames alone, reading the evaluation's simulated episodes
# (their kept observed features): how far the observations decide each task's outcome, whatever the
# world model imagines. An upper bound on any judge of imaginations that learns from these episodes.
OBSERVED_BOUND = "observed_bound"
SAVED = "saved_judge"  # the judge fit with the world model, if any, on the kept (float16) features
FOLDS = 4
# The order variants are fit in by default: what matters most first, so a run cut short keeps it.
DEFAULT_ORDER = (SAVED, "refit_1024", BOUND, OBSERVED_BOUND, "all", "all_observed", "observed_only",
                 "all_no_action", "all_no_outcome", "all_proprio_progress", "rollouts_only")
SPECIAL = (BOUND, SAVED, OBSERVED_BOUND)


def imagined(path: Path, make) -> dict:
    """imagine_episodes' dict, read from path or made by make() and saved there (float16 features)."""
    if path.exists():
        z = np.load(path, allow_pickle=False)
        return {"features": z["features"].astype(np.float32), "mask": z["mask"], "task": list(z["task"]),
                "label": z["label"], "rollout": z["rollout"]}
    d = make()
    tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}.npz")
    np.savez(tmp, **{**d, "features": d["features"].astype(np.float16), "task": np.array(d["task"])})
    os.replace(tmp, path)
    return d


def take(d: dict, rows) -> dict:
    """The episodes `rows` of an imagine_episodes dict."""
    rows = np.asarray(rows, np.int64)
    return {"features": d["features"][rows], "mask": d["mask"][rows], "task": [d["task"][i] for i in rows],
            "label": d["label"][rows]}


def evaluation_episodes(features: dict, true: dict, rows: dict) -> dict:
    """The kept imaginations of the policies `rows` ({task: (p,) int}) as one imagine_episodes dict,
    padded to the longest task. features {task: (P, N, T, F)}, true {task: (P, N) bool}."""
    t_max = max(f.shape[2] for f in features.values())
    x, m, task, y = [], [], [], []
    for t, r in rows.items():
        f = features[t][r].astype(np.float32)
        f = f.reshape((-1,) + f.shape[2:])
        x.append(np.pad(f, ((0, 0), (0, t_max - f.shape[1]), (0, 0))))
        m.append(np.arange(t_max)[None].repeat(len(f), 0) < f.shape[1])
        task += [t] * len(f)
        y.append(true[t][r].reshape(-1))
    return {"features": np.concatenate(x), "mask": np.concatenate(m), "task": task, "label": np.concatenate(y)}


def read_tasks(judge, features: dict) -> dict:
    """{task: (P, N) the judge's probabilities} of the kept imaginations {task: (P, N, T, F)}."""
    out = {}
    for t, f in features.items():
        p, n = f.shape[:2]
        x = f.reshape((p * n,) + f.shape[2:]).astype(np.float32)
        out[t] = np.concatenate([judge.probability(x[k:k + 4096], t) for k in range(0, len(x), 4096)]).reshape(p, n)
    return out


def crossfit_bound(features: dict, true: dict, tasks: tuple, steps: int, seed: int, folds: int = FOLDS) -> dict:
    """{task: (P, N)} probabilities of a judge cross-fit on the evaluation itself: each task's policies
    dealt into `folds` folds at random; fold k is read by a judge fit on the folds other than k and
    k+1, kept at its best loss on fold k+1."""
    rng = np.random.default_rng(seed)
    fold_of = {t: rng.permutation(len(true[t])) % folds for t in tasks}
    every = evaluation_episodes(features, true, {t: np.arange(len(true[t])) for t in tasks})
    episode_fold = np.concatenate([np.repeat(fold_of[t], true[t].shape[1]) for t in tasks])  # every's rows
    out = {t: np.zeros(true[t].shape) for t in tasks}
    for k in range(folds):
        v = (k + 1) % folds
        train = take(every, np.flatnonzero((episode_fold != k) & (episode_fold != v)))
        val = take(every, np.flatnonzero(episode_fold == v))
        judge, _ = fit(train, val, tasks, steps, seed + k, progress=False)
        for t in tasks:
            held = np.flatnonzero(fold_of[t] == k)
            out[t][held] = read_tasks(judge, {t: features[t][held]})[t]
    return out


def fit_variant(v: Variant, train: dict, val: dict, tasks: tuple, wm_cfg, steps: int, observed: dict | None = None) -> tuple:
    """(EpisodeJudge, fit metrics) of variant v on the imagined training episodes (and, for an
    `observed` variant, the same episodes' `observed` dict, observe_episodes' in train's order)."""
    rows = np.arange(len(train["label"]))
    if v.rollouts_only:
        rows = rows[train["rollout"]]
    if v.episodes and v.episodes < len(rows):
        rows = np.asarray(spread(list(rows), v.episodes))
    learn = take(train, rows)
    if v.observed:
        learn = join_episodes(learn, take(observed, rows)) if v.imagined else take(observed, rows)
    return fit(learn, val, tasks, steps, wm_cfg.seed + v.seed, progress=True,
               columns=feature_columns(wm_cfg.model, v.inputs), lr=v.lr, members=v.members, select=v.select,
               raw_mean=v.raw_mean)


def read_variant(v: Variant, train: dict, val: dict, tasks: tuple, wm_cfg, steps: int, features: dict,
                 observed: dict | None = None) -> tuple[dict, dict]:
    """({task: (P, N)} probabilities, fit metrics) of variant v's judge (fit_variant; with several
    members, the mean of theirs) reading the kept imaginations features ({task: (P, N, T, F)})."""
    judge, metrics = fit_variant(v, train, val, tasks, wm_cfg, steps, observed)
    return read_tasks(judge, features), metrics


def observed_bound(train: dict, val: dict, features: dict, tasks: tuple, steps: int, seed: int) -> tuple:
    """({task: (P, N)} probabilities, fit metrics) of a judge fit to the training episodes' true frames
    (train, val: observe_episodes' dicts) reading the evaluation's simulated episodes' kept features
    ({task: (P, N, T, F)}, load_features(..., observed=True))."""
    judge, metrics = fit(train, val, tasks, steps, seed, progress=True)
    return read_tasks(judge, features), metrics


def loaded_policies(data: Path) -> dict:
    """wm.judge.dataset_policies(data), refusing a dataset whose policies cannot be loaded from here:
    their rollouts would be imagined open loop, where wm.train's judge learnt from their closed-loop
    imaginations, so the study's judges would learn from other imaginations than the saved one."""
    pols = dataset_policies(data)
    specs = json.loads((Path(data) / "config.json").read_text()).get("policies") or []
    if specs and not pols:
        raise FileNotFoundError(f"the policies whose rollouts {data} holds ({', '.join(specs)}) cannot be loaded "
                                "from here: run the study from the directory their paths are relative to")
    return pols


def finished_tasks(eval_dir: Path) -> tuple:
    """The tasks an evaluation finished (out/tasks/<task>.npz), sorted."""
    tasks = tuple(sorted(p.stem for p in (Path(eval_dir) / "tasks").glob("*.npz") if "." not in p.stem))
    if not tasks:
        raise FileNotFoundError(f"{eval_dir}/tasks holds no finished task: run the evaluation first")
    return tasks


def study(eval_dir: Path, out: Path, wm_run: Path | None = None, data: Path | None = None, variants=None,
          steps: int | None = None, draws: int = 1000) -> dict:
    """Fits the variants named in `variants` (VARIANTS' names, BOUND, SAVED; default DEFAULT_ORDER) in
    that order, reads the kept imaginations of eval_dir with each (out/variants/<name>.npz), then
    scores them (score)."""
    wm_run = Path(wm_run or json.loads((eval_dir / "config.json").read_text())["wm"].split(",")[0])
    names = list(variants or DEFAULT_ORDER)
    unknown = [n for n in names if n not in VARIANTS and n not in SPECIAL]
    if unknown:
        raise ValueError(f"unknown variants {unknown}; choose among {', '.join([*VARIANTS, *SPECIAL])}")
    wm_cfg, params, norm = load_trained(wm_run)
    # the evaluation's imagination setting, so that the judges learn from imaginations like those they read
    wm_cfg = with_imagine(wm_cfg, json.loads((eval_dir / "config.json").read_text()).get("imagine", ""))
    data = Path(data or load_run_config(wm_run)[1])
    if not (data / "cache" / "index.json").exists():
        raise FileNotFoundError(f"{data} holds no training cache: name the world model's data with --data")
    tasks = finished_tasks(eval_dir)
    true = {t: load_task(eval_dir / "tasks" / f"{t}.npz")["true"] for t in tasks}
    features = {t: load_features(eval_dir, t) for t in tasks}
    steps = steps or wm_cfg.judge_steps
    (out / "variants").mkdir(parents=True, exist_ok=True)

    seen = {t: load_features(eval_dir, t, observed=True) for t in tasks} if OBSERVED_BOUND in names else {}
    fitted = [VARIANTS[n] for n in names if n in VARIANTS] + ([Variant(observed=True)] if seen else [])
    train = val = train_open = val_open = train_replay = val_replay = None
    observed = observed_val = None
    ids, val_ids = [], []
    if fitted:
        cache = TrainingCache(data)
        ids = [int(i) for i in window_episodes(cache, wm_cfg.window, "train", wm_cfg.train_tasks or None,
                                              wm_cfg.train_fraction) if cache.episodes[i]["task"] in tasks]
        if all(v.episodes and not v.rollouts_only for v in fitted):  # only what the largest subset needs
            ids = spread(ids, max(v.episodes for v in fitted))
        val_ids = spread(cache.select("val", list(tasks)), VAL_EPISODES)  # as wm.judge.fit_judge
        pols = loaded_policies(data)

        def make(split_ids, seed, policies=pols):
            def go():
                d = imagine_episodes(wm_cfg.model, params, norm, cache, split_ids, wm_cfg.camera, True, policies, seed)
                return {**d, "rollout": closed_loop_rows(cache, split_ids, pols)}
            return go

        train = imagined(out / f"imagined_train_{len(ids)}.npz", make(ids, wm_cfg.seed))
        val = imagined(out / "imagined_val.npz", make(val_ids, wm_cfg.seed + 1))
        if any(v.replay_labels for v in fitted):
            engine = default_engine()
            batch = replay_batch(cache, [(ids, train["rollout"]), (val_ids, val["rollout"])])
            train_replay = {**train, "label": replayed_labels(wm_cfg.model, norm, cache, ids, train, train["rollout"],
                                                              engine, batch)}
            val_replay = {**val, "label": replayed_labels(wm_cfg.model, norm, cache, val_ids, val, val["rollout"],
                                                          engine, batch)}
            print(f"replayed labels: {int((train_replay['label'] != train['label']).sum())} of "
                  f"{int(train['rollout'].sum())} closed-loop training imaginations relabelled", file=sys.stderr)
        if not all(v.closed_loop for v in fitted):
            train_open = imagined(out / f"imagined_train_open_{len(ids)}.npz", make(ids, wm_cfg.seed, {}))
            val_open = imagined(out / "imagined_val_open.npz", make(val_ids, wm_cfg.seed + 1, {}))
        if any(v.observed for v in fitted):
            def observe(split_ids):
                return lambda: {**observe_episodes(wm_cfg.model, params, norm, cache, split_ids, wm_cfg.camera),
                                "rollout": closed_loop_rows(cache, split_ids, pols)}
            observed = imagined(out / f"observed_train_{len(ids)}.npz", observe(ids))
            observed_val = imagined(out / "observed_val.npz", observe(val_ids))
    saved = load_judge(wm_run) if SAVED in names else None
    for name in names:
        path = out / "variants" / f"{name}.npz"
        if path.exists() and fit_matches(path, name):
            continue
        if name == SAVED and saved is None:
            print(f"judge variant {name} skipped: {wm_run} saved no judge", file=sys.stderr)
            continue
        print(f"judge variant {name}", file=sys.stderr)
        try:
            if name == SAVED:
                probs, fit_metrics = read_tasks(saved, features), {}
            elif name == BOUND:
                probs, fit_metrics = crossfit_bound(features, true, tasks, steps, wm_cfg.seed), {"folds": FOLDS}
            elif name == OBSERVED_BOUND:
                probs, fit_metrics = observed_bound(observed, observed_val, seen, tasks, steps, wm_cfg.seed)
            else:
                v = VARIANTS[name]
                learn, check = ((train_replay, val_replay) if v.replay_labels else (train, val)) if v.closed_loop \
                    else (train_open, val_open)
                probs, fit_metrics = read_variant(v, learn, check, tasks, wm_cfg, steps, features, observed)
        except ValueError as e:  # one outcome only among what a variant would learn from
            print(f"warning: judge variant {name} skipped: {e}", file=sys.stderr)
            continue
        tmp = path.with_name(f"{name}.tmp{os.getpid()}.npz")
        np.savez(tmp, __fit__=json.dumps(fit_metrics), __variant__=json.dumps(variant_definition(name)), **probs)
        os.replace(tmp, path)
    setup = {"wm": str(wm_run), "data": str(data), "judge_steps": steps, "train_episodes": len(ids),
             "rollout_episodes": int(train["rollout"].sum()) if train else 0, "val_episodes": len(val_ids),
             "variants": {n: dataclasses.asdict(v) for n, v in VARIANTS.items() if n in names}}
    return score(eval_dir, out, draws, setup)


def variant_definition(name: str) -> dict | None:
    """What variant `name` fits (its Variant as a dict), saved beside its readings; None for the
    saved judge and the bounds, whose definitions are the run's and the study's own."""
    return dataclasses.asdict(VARIANTS[name]) if name in VARIANTS else None


def fit_matches(path: Path, name: str) -> bool:
    """Whether the readings saved at path were fit as variant `name` is now defined (a variant whose
    definition changed, or readings saved without one, are fit again, with a message)."""
    with np.load(path) as z:
        saved = json.loads(str(z["__variant__"])) if "__variant__" in z.files else "unrecorded"
    want = json.loads(json.dumps(variant_definition(name)))  # tuples as JSON's lists, as saved
    if saved == want:
        return True
    print(f"judge variant {name}: its saved readings were fit as {saved}, not as {want}: fitting it again",
          file=sys.stderr)
    return False


def score(eval_dir: Path, out: Path, draws: int = 1000, setup: dict | None = None) -> dict:
    """Within-task statistics (experiments.stats.within_task) of the evaluation's own read-outs and of
    every variant saved in out/variants, for every policy and for those the world model never saw act
    (results.json's in_wm_data); written to out/judge_study.json with `setup` and printed as a table."""
    tasks = finished_tasks(eval_dir)
    res = {t: load_task(eval_dir / "tasks" / f"{t}.npz") for t in tasks}
    true = {t: res[t]["true"] for t in tasks}
    predictors = {f"eval_{r}": {t: res[t][f"readout_{r}"] for t in tasks} for r in MODEL_READOUTS
                  if any(np.isfinite(res[t][f"readout_{r}"]).any() for t in tasks)}  # a second judge where fit
    fits = {}
    for path in sorted((out / "variants").glob("*.npz"), key=lambda p: p.stat().st_mtime_ns):
        if ".tmp" in path.name:
            continue
        with np.load(path, allow_pickle=False) as z:
            predictors[path.stem] = {t: z[t] for t in tasks}
            fits[path.stem] = json.loads(str(z["__fit__"]))
    seen = {r["name"] for r in json.loads((eval_dir / "results.json").read_text())["policies"] if r["in_wm_data"]}
    unseen = {t: np.array([n not in seen for n in res[t]["names"]]) for t in tasks}
    unseen_stats = None
    if all(u.sum() >= 3 for u in unseen.values()):
        unseen_stats = S.within_task({t: true[t][unseen[t]] for t in tasks},
                                     {n: {t: p[t][unseen[t]] for t in tasks} for n, p in predictors.items()},
                                     draws=draws)
    report = {"eval": str(eval_dir), "tasks": list(tasks), **(setup or {}), "fit": fits,
              "policies": {t: len(true[t]) for t in tasks}, "episodes": {t: true[t].shape[1] for t in tasks},
              "unseen_policies": {t: int(u.sum()) for t, u in unseen.items()},
              "within_task": S.within_task(true, predictors, draws=draws), "unseen_within_task": unseen_stats}
    write_json_atomic(out / "judge_study.json", report)
    print(table(report))
    return report


def table(report: dict) -> str:
    """A markdown table of every predictor's mean within-task Pearson (interval), per task, and on the unseen policies."""
    w, u = report["within_task"], report["unseen_within_task"]
    tasks = w["tasks"]
    names = [k for k in w if isinstance(w[k], dict) and "mean" in w[k]]
    lines = [f"| read-out | within-task Pearson | {' | '.join(tasks)} | MMRV | unseen Pearson |",
             "|---" * (len(tasks) + 4) + "|"]
    for n in names:
        m, ci = w[n]["mean"]["pearson"], w[n]["mean_ci"]["pearson"]
        per = " | ".join(f"{w[n]['per_task'][t]['pearson']:.2f}" for t in tasks)
        un = f"{u[n]['mean']['pearson']:.2f}" if u else "-"
        lines.append(f"| {n} | {m:.2f} [{ci[0]:.2f}, {ci[1]:.2f}] | {per} | {w[n]['mean']['mmrv']:.2f} | {un} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--eval", type=Path, required=True, help="an evaluation run with keep_features=1")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--wm", type=Path, default=None, help="the world model (default: the evaluation's first)")
    ap.add_argument("--data", type=Path, default=None, help="its training data (default: the run's)")
    ap.add_argument("--variants", default="", help=f"comma-separated, fit in the order given (default {','.join(DEFAULT_ORDER)})")
    ap.add_argument("--steps", type=int, default=None, help="judge optimiser steps (default the run's judge_steps)")
    ap.add_argument("--draws", type=int, default=1000, help="bootstrap draws")
    ap.add_argument("--score-only", action="store_true",
                    help="score the variants already in OUT/variants (no world model or data needed)")
    a = ap.parse_args(argv)
    if a.score_only:
        score(a.eval, a.out, a.draws)
    else:
        study(a.eval, a.out, a.wm, a.data, [v for v in a.variants.split(",") if v] or None, a.steps, a.draws)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
