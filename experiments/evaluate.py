"""Policy evaluation in the world model against the simulator.

    python -m experiments.evaluate --config demo --out runs/eval/demo [key=value ...]
    make eval CONFIG=demo OUT=runs/eval/demo

For every task and every policy that runs on it (zoo checkpoints, plug-ins), from N held-out
initial states per task (seeds checked against every seed of the world model's and the zoo's
datasets):
- true success: closed-loop episodes in the simulator, the policy seeing the rendered head camera;
- predicted success: closed-loop episodes in the world model from the same initial frame and
  proprioception, for the task's episode length; an episode's predicted probability is read from
  the imagined episode by `readout` (thresholded at `threshold` for its outcome): "judge", the
  episode judge's (`wm.judge`, trained with the world model on imaginations of its training
  episodes) where it knows the task; "progress", the progress head's value at the last step
  (clipped to [0, 1]; every task's progress is 1 exactly where it succeeded); "success", the
  highest per-step success probability. Every read-out's statistics are reported beside the
  chosen one's ("readouts" and "readout_<name>"): which reads imagination best depends on the model.
  A judge fit to closed-loop imaginations of learned policies (the chain's rollouts) ranked the
  demo zoo and the `full` zoo far better than the heads; a judge fit to scripted episodes alone
  ranked the `full` zoo far worse than the progress head (docs/results.md). The default, "auto",
  picks by that (auto_readout).
- with several world models (`wm=RUN,RUN,...`: an ensemble, say of training seeds), each imagines
  every episode and the predicted probability is their mean; every model's own ranking statistics
  are kept beside the ensemble's ("members"). One model's training seed moves its ranking more than
  most design choices do; the mean of a few cancels much of that luck.

Policies run in batches of up to `batch` episodes whatever their architectures: each architecture's
checkpoints with their parameters stacked, the architectures side by side (a MixedPolicy), so one
compiled rollout serves a whole zoo. Each task is saved when done (`OUT/tasks/<task>.npz`) and a
rerun resumes. On several GPUs or CPU cores (`--part K/N`, one process each, sim_data.parts) every
task's batches are spread over the parts, the largest first onto the least loaded, whatever the number of tasks;
each part saves its share (`OUT/tasks/<task>.partKofN.npz`) and the run without a part merges them,
with the outcomes and probabilities of one unsplit run. `OUT/results.json` holds the per-policy
rates and intervals and the statistics (experiments.stats): the headline within each task (their
mean over tasks, with bootstrap intervals over policies and initial states), per task, and pooled
over tasks (secondary: tasks of different difficulty correlate for free), beside the imitation-loss
proxy; `OUT/videos.npz` real and imagined episodes and the controllability panel
for the report.

    python -m experiments.evaluate --config full --warm wm=runs/wm/full [key=value ...]

compiles the evaluation's programs ahead, beside the world model's training (`warm`): what the
evaluation then compiles it loads from JAX's persistent compilation cache instead. With
`truth_cache=DIR truth_frames=1` it also simulates every episode of the evaluation into DIR, and
the evaluation given the same settings reads them instead of simulating: the simulator's share of
the evaluation runs beside the training too.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import math
import os
import re
import shutil
import sys
import time
from collections import Counter
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from experiments import stats as S
from experiments.ensemble import member_metrics
from sim_data.config import as_json, differing_fields, preset_config, preset_help
from sim_data.dataset.cache import TrainingCache
from sim_data.parts import add_part_argument, config_and_part, exclusive, in_turn
from sim_data.policies.bc import MixedPolicy
from sim_data.policies.registry import (
    applied_policy,
    describe,
    fingerprint,
    group_by_policy,
    heldout_seeds,
    policy_chunks,
    reset_keys_of,
    resolve,
    stacked_sources,
    used_seeds,
)
from sim_data.policies.scripted import simulate_actions
from sim_data.sim import robot as R
from sim_data.sim.engines import ENGINES, PHYSICS_REVISION, default_engine
from sim_data.sim.env import cached_env
from sim_data.sim.render import HEAD_CAMERA, cached_renderers
from sim_data.sim.rollout import WARM_STEPS, record_policies
from sim_data.sim.tasks import TASK_NAMES, TASKS
from sim_data.util import (
    device_name,
    hash_arrays,
    make_output_dir,
    package_versions,
    read_json,
    run_cli,
    wait_for_files,
    write_json_atomic,
)
from wm.checkpoint import (
    bundle_holds,
    bundle_meta,
    is_bundle,
    load_run_config,
    load_started,
    load_trained,
    trained_tasks,
    training_fingerprints,
    training_policies,
    training_seeds,
    training_status,
)
from wm.config import with_imagine
from wm.egomotion import EGOMOTION_JSON
from wm.geometric import PREDICTS, Motion, imagine_robot, load_motion, robot_camera, start_view
from wm.grasp import grasp_success, load_grasp
from wm.imagine import (
    PROGRESS_FEATURE,
    SUCCESS_FEATURE,
    closed_loop,
    episode_success,
    observed_features,
    open_loop,
)
from wm.judge import JUDGE, SECOND_JUDGE, check_features, load_judge
from wm.metrics import psnr
from wm.model import IMAGINE_MODES
from wm.quality import no_nan, program_panel
from wm.train import warm_after_training

# Per-step arrays (P, N, T) saved with each task: imagined success and progress, the simulator's progress
TRACES = ("trace_success", "trace_progress", "true_progress")
# "judge2": the second episode judge (wm.config.TrainConfig.judge2_inputs), NaN for a model without one
MODEL_READOUTS = ("progress", "judge", "success", "judge2")
# "geometric": the task's rule on states predicted from the actions (cfg.geometric): the robot's own motion
# imagined over the still scene where success follows from it (wm.geometric.PREDICTS), the held object moved
# by its task's fitted grasp (wm.grasp.GRASPED) along the actions the policy took in the world model's imagination;
# the ranked read-out elsewhere; NaN without one
GEOMETRIC = "geometric"
READOUTS = MODEL_READOUTS + (GEOMETRIC,)
AUTO = "auto"  # the judge where every model's judge saw its own closed-loop imaginations of learned policies
READOUT_KEYS = tuple(f"readout_{r}" for r in READOUTS)
# the second judge's read-out of the simulated episodes themselves, beside prob_observed (cfg.readout's):
# whether what it misses is imagination's or its own
OBSERVED_SECOND = f"prob_observed_{SECOND_JUDGE}"
# Steps at which imagined frames are compared with the simulator's (and the task's last step)
FIDELITY_HORIZONS = (1, 8, 16, 32, 64)
# Per-episode arrays of the imagination's fidelity to the simulated episode: frame PSNR and copy-first
# PSNR at each horizon (P, N, H), the RMS gap of the policy's actions at each step (P, N, T) and in each
# action dimension over the episode (P, N, 20), and the mean signed difference in each dimension (P, N, 20)
FIDELITY = ("frame_psnr", "copy_first_psnr", "action_gap", "action_gap_dims", "action_bias_dims")
# the width at which a task file written before one of them reads it (unknown: NaN), where a newer part's is fixed
FIDELITY_MISSING_WIDTH = {"action_bias_dims": R.ACTION_DIM}
# a task's per-policy arrays, (P, N, ...) (the ensemble members' prob_members, (K, P, N), apart)
POLICY_ARRAYS = (("true", "prob", "prob_observed", OBSERVED_SECOND, "prob_replayed", "sim_imagined", "sim_finite")
                 + READOUT_KEYS + TRACES + FIDELITY)
READOUT_LABELS = {"progress": "progress head at the last step", "judge": "episode judge",
                  "success": "highest per-step success probability", "judge2": "second episode judge",
                  GEOMETRIC: "the task's rule on states predicted from the actions (wm.geometric, wm.grasp)"}


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Attributes:
      policies: policy specs (`sim_data.policies.registry`: zoo registries, plug-ins).
      wm: the world model's training run directory (make train OUT), or several, comma-separated:
        an ensemble whose mean probability is the prediction (their frames must be of one size).
      tasks: tasks to evaluate (empty: every task of the learned policies; with plug-ins alone, every task
        the world models learned to judge).
      episodes: held-out initial states per task (each policy runs from all of them).
      seed: names the held-out initial states. engine: "cpu", "mjx" or "" (mjx on a GPU).
      batch: episodes simulated or imagined together (policies x initial states).
      state_batch: initial states a batch runs (0: all of them). With it every batch holds up to
        batch // state_batch policies from state_batch of the states, and a task's states run as
        episodes // state_batch slices of one shape: one compiled program serves every number of
        states, and a task of few batches spreads over the parts (GPUs) slice by slice. Must divide
        episodes.
      readout: how an imagined episode's success probability is read: "progress", "judge" or
        "success" (above; "judge" falls back to "success" for a task the judge does not know), or
        "auto": "judge" where every model was trained (and its judge fit) with rollouts of learned
        policies, "progress" otherwise (auto_readout).
      threshold: a predicted probability at or above it is a predicted success.
      video_policies: policies per task whose episodes are kept for the report (lowest, middle and
        highest true rate first); video_episodes: kept episodes per such policy.
      gaps: true gaps of the decision analysis; decision_episodes: episodes per policy on its curve.
      max_minutes: stop before a task that would end past this wall time (judged by the longest
        task so far; 0: no limit), so a stage fits its time slot; a rerun evaluates the rest. It
        does not change results and is not part of the configuration a rerun must match.
      truth_cache: a directory where the simulator's side of each batch (outcomes, first frames and
        proprioception) is kept and reused by later evaluations of the same policies from the same
        states, whatever the world model (a sweep ranks one zoo with many models); "" keeps none.
        Rankings running at once share its batches out (each simulates those no other is simulating).
        Without truth_frames used only with video_policies=0, as it keeps no real videos. A warm-up
        (warm) of an evaluation with a truth_cache simulates every batch into it, beside the world
        model's training, so that the evaluation itself only imagines.
      truth_frames: with truth_cache, also keep each batch's simulated frames, proprioception and
        actions, so that an evaluation reading the cache reads the simulated episodes through the
        world model, compares imagined frames with them and films them, as one that simulated
        (its figures and videos those of an evaluation without a cache). Costs S*S*3 bytes a frame:
        about 30 GB for the `full` zoo at 100 states (truth_space checks the disk first); an entry
        kept without frames is simulated again.
      keep_features: also keep every imagined episode's step features (wm.imagine.step_features, the
        first model's) in OUT/features/<task>.npy, (P, N, T, F) float16 in the order of the task's
        policies and states, so other read-outs of the same imaginations (judges: experiments.judge_study)
        can be fit and compared without imagining again; and those of the simulated episodes themselves
        (truth_features) in OUT/features/<task>.observed.npy, where the simulator ran in this run. Not
        with --part.
      replay: also imagine each simulated episode open loop under its own actions, from its first
        frame, and read it as the imagined ones (prob_replayed, "replayed" in the within-task
        statistics): the gap between it and the read-out of the true episodes is the dynamics'
        error under the policy's real actions; between the imagined and the replayed, what the
        policy acting on imagined frames changes. And the converse: the actions the policy took in
        the first model's imagination played open loop in the simulator from the same initial state
        (sim_imagined, "sim_imagined" in the within-task statistics, "loop_actions" for the model
        against it): whether the loop's actions truly succeed where the model says they do (its
        dynamics and judge on its own loop) and how far acting on imagined frames alone moves the
        outcomes. Costs one more imagination and one more simulation of every episode.
      imagine: how the world models imagine (wm.model.ModelConfig.imagine: "window" or "cache") in
        place of the setting each was trained with; "" keeps theirs.
      geometric: a directory of the robot's motion and fill models (python -m experiments.fill --out
        DIR): the tasks whose success follows from the robot's own motion (wm.geometric.PREDICTS) are
        also imagined by wm.geometric.imagine_robot, from the same states with the same policy keys,
        read by the task's rule on the predicted states ("readout_geometric"); where DIR holds a grasp
        rule (experiments.fill with tasks of wm.grasp.GRASPED), those tasks' outcomes are read by
        their rule on the states the actions of the policy's imagined episodes lead to (wm.grasp:
        the robot's motion models, the object moved with the grip that holds it); elsewhere the ranked
        read-out. "" imagines them by the world models alone.
      geometric_ranks: rank those tasks' policies by the geometric read-out (prob) rather than cfg.readout.
    """

    policies: tuple = ()
    wm: str = ""
    tasks: tuple = ()
    episodes: int = 200
    seed: int = 0
    engine: str = ""
    batch: int = 2048
    state_batch: int = 0
    readout: str = AUTO
    threshold: float = 0.5
    video_policies: int = 4
    video_episodes: int = 2
    gaps: tuple = (0.1, 0.2)
    decision_episodes: tuple = (5, 10, 20, 50, 100, 200, 500)
    max_minutes: float = 0.0
    truth_cache: str = ""
    truth_frames: bool = False
    keep_features: bool = False
    replay: bool = False
    imagine: str = ""
    geometric: str = ""
    geometric_ranks: bool = False

    def validate(self) -> None:
        """Raises ValueError where a setting is missing or out of range: no policies or world model, too few
        episodes, a state_batch that does not divide them, an unknown engine, read-out, task or imagine mode,
        a threshold outside (0, 1), truth_cache with videos but without truth_frames, truth_frames without
        truth_cache, or a world model named twice (a run beside its own bundle too)."""
        if not self.policies:
            raise ValueError("name at least one policy spec (policies=runs/policies/demo,...)")
        if not self.wm:
            raise ValueError("name the world model's run directory (wm=runs/wm/demo)")
        if self.episodes < 2 or self.batch < 1:
            raise ValueError(f"episodes must be >= 2 and batch >= 1, got {self.episodes}, {self.batch}")
        if self.state_batch < 0 or (self.state_batch and self.episodes % self.state_batch):
            raise ValueError(f"state_batch must divide episodes ({self.episodes}), got {self.state_batch}")
        if self.engine not in ("",) + ENGINES:
            raise ValueError(f"engine must be one of {ENGINES} or empty, got {self.engine!r}")
        if self.readout not in MODEL_READOUTS + (AUTO,):
            raise ValueError(f"readout must be one of {MODEL_READOUTS + (AUTO,)}, got {self.readout!r} (the geometric "
                             f"read-out ranks with geometric=DIR geometric_ranks=1)")
        if self.geometric_ranks and not self.geometric:
            raise ValueError("geometric_ranks ranks by the geometric read-out: name its models (geometric=DIR, "
                             "trained by python -m experiments.fill --out DIR)")
        if not 0 < self.threshold < 1:
            raise ValueError(f"threshold must be in (0, 1), got {self.threshold}")
        if self.video_policies < 0 or self.video_episodes < 0:
            raise ValueError(f"video_policies and video_episodes count what the report films, >= 0; got "
                             f"{self.video_policies}, {self.video_episodes}")
        if not self.gaps or any(not 0 < g <= 1 for g in self.gaps):
            raise ValueError(f"gaps are the decision analysis's true gaps between two policies, each in (0, 1]; got "
                             f"{self.gaps!r} (gaps=0.1,0.2)")
        if not self.decision_episodes or any(n < 1 for n in self.decision_episodes):
            raise ValueError(f"decision_episodes are episode counts a policy, each >= 1; got {self.decision_episodes!r}")
        if self.max_minutes < 0:
            raise ValueError(f"max_minutes is a safety stop in minutes, >= 0 (0: none); got {self.max_minutes}")
        if self.truth_cache and self.video_policies and not self.truth_frames:
            raise ValueError("truth_cache keeps no real videos without their frames: use it with video_policies=0, "
                             "or keep the frames (truth_frames=1)")
        if self.truth_frames and not self.truth_cache:
            raise ValueError("truth_frames keeps the simulated frames in the truth cache: name it (truth_cache=DIR)")
        unknown = [t for t in self.tasks if t not in TASK_NAMES]
        if unknown:
            raise ValueError(f"unknown tasks {unknown}; choose among {', '.join(TASK_NAMES)}")
        if twice := sorted({t for t in self.tasks if self.tasks.count(t) > 1}):
            # evaluated once, but every row and pooled statistic would count each of its policies twice
            raise ValueError(f"tasks names {', '.join(twice)} twice: {','.join(self.tasks)}")
        if self.imagine not in ("",) + IMAGINE_MODES:
            raise ValueError(f"imagine must be one of {', '.join(IMAGINE_MODES)} or empty, got {self.imagine!r}")
        same = [os.path.realpath(w) for w in self.wm_runs]  # one directory however spelled (a/, ./a, a link)
        if len(set(same)) != len(same):
            raise ValueError(f"wm names a run twice: {self.wm}")
        # a bundle of a run, named beside that run as it still stands, is the same model twice (in bfloat16)
        own = [w for w in self.wm_runs if is_bundle(w) and os.path.realpath(src := bundle_meta(w)["source"]) in same
               and bundle_holds(Path(src), Path(w))]
        if own:
            raise ValueError(f"wm names {', '.join(own)}, the bundle of a run it also names: the same world model "
                             f"twice; name one of them ({self.wm})")

    @property
    def wm_runs(self) -> tuple:
        """The world models' run directories (one, or an ensemble's)."""
        return tuple(w.strip() for w in self.wm.split(",") if w.strip())


# the overrides that rank every task by the world model's own read-out where a preset names geometric models:
# what a study of world-model designs compares (experiments.sweep, experiments.design)
WORLD_MODEL_ALONE = ("geometric=", "geometric_ranks=0")

PRESETS = {
    # enough episodes that the true rates resolve a ranking: 16 a policy (95% interval about +-0.2) on the
    # demo's CPU, 100 (+-0.1) on a GPU. The demo runs one policy a batch: XLA's CPU numerics move with a
    # batch's composition, enough to flip a marginal grasp or an imagined loop, so a policy's figures
    # would change with the policies evaluated beside it (and on 2 cores it is faster than batches of 256).
    # The world model: `make demo`'s (experiments.pipeline's demo preset trains one), its step_back and mug
    # ranked as `make demo` ranks them, by the geometric models its train stage fits (runs/fill/demo)
    "demo": EvalConfig(policies=("runs/policies/demo",), wm="runs/wm/demo", episodes=16, batch=16,
                       geometric="runs/fill/demo", geometric_ranks=True),
    # 52 policies x 50 states a batch: the 100 states run as two slices of one compiled program (50 as one)
    "full": EvalConfig(policies=("runs/policies/full",), wm="runs/wm/full", episodes=100, batch=2600, state_batch=50,
                       max_minutes=8.0),
}


def make_config(preset: str, overrides=()) -> EvalConfig:
    """The named preset of PRESETS with dotted `key=value` overrides applied, validated."""
    return preset_config(PRESETS, preset, overrides)


# ---- one task ------------------------------------------------------------------------------------

def task_chunks(cfg: EvalConfig, sources, n: int) -> list:
    """The batches a task's sources run in: [(policies, padded)], at most cfg.batch // n policies (n
    initial states each) a batch whatever their architectures (chunk_policy), those of one
    architecture next to each other, the last batch padded by repeating its last policy."""
    return list(policy_chunks([s for g in group_by_policy(sources) for s in g], n, cfg.batch))


def state_slices(cfg: EvalConfig, n: int) -> list[tuple[int, int]]:
    """[(start, stop)] of the n initial states each batch of a task runs: all at once, or
    cfg.state_batch at a time."""
    width = cfg.state_batch or n
    return [(s, min(s + width, n)) for s in range(0, n, width)]


def task_batches(cfg: EvalConfig, sources, n: int) -> list[tuple[int, int, list, list]]:
    """Every batch of a task of n initial states: (chunk index k, slice index j, policies, padded), the
    chunks (task_chunks) of as many policies as a slice's states leave room for, each run on every
    slice (state_slices), chunk by chunk."""
    slices = state_slices(cfg, n)
    width = slices[0][1] - slices[0][0]
    return [(k, j, part, padded) for k, (part, padded) in enumerate(task_chunks(cfg, sources, width))
            for j in range(len(slices))]


def chunk_policy(padded, n: int) -> tuple:
    """(policy, params) running a batch's sources side by side, n episodes each: a StackedPolicy of each
    architecture's checkpoints, in a MixedPolicy where the batch holds several architectures (one
    compiled rollout, in the simulator and in the world model, for all of them); each source salted by
    its name, so that a stochastic policy draws the same numbers whatever shares its batch."""
    groups = group_by_policy(padded)
    stacks = [stacked_sources(g) for g in groups]
    if len(stacks) == 1:
        return stacks[0]
    return (MixedPolicy(tuple(p for p, _ in stacks), tuple(len(g) * n for g in groups)),
            tuple(q for _, q in stacks))


def slice_key(cfg: EvalConfig, j: int) -> jax.Array:
    """The random key of slice j of a task's states, whatever the batch: each policy draws by its own
    salt (chunk_policy)."""
    return jax.random.fold_in(jax.random.PRNGKey(cfg.seed), j)


def balance_chunks(sizes: dict, n_parts: int) -> dict:
    """{key: part} spreading the chunks `sizes` ({key: episodes}) over n_parts processes, largest
    first onto the least loaded (ties to the lower part): a task's chunks may go to several parts."""
    load = [0] * n_parts
    out = {}
    for key in sorted(sizes, key=lambda k: -sizes[k]):  # stable: equal sizes keep their order
        k = load.index(min(load))
        out[key] = k
        load[k] += sizes[key]
    return out


def evaluate_task(cfg: EvalConfig, task: str, sources, models, seeds, engine: str, progress: bool,
                  chunks=None, motion=None, grasp=None) -> dict:
    """True and predicted outcomes of every source on task from the held-out seeds, predicted by
    each of K world models (`models`: load_models' list); with `chunks` (keys
    (k, j) of task_batches), of those batches only (a part of the task, for merge_task_parts).

    Returns {"names": [P], "true": (P, N) bool, "prob": (P, N) float (cfg.readout's; the models'
    mean), "readout_<name>": (P, N) float for each of READOUTS (the mean), "prob_observed": (P, N)
    float (cfg.readout applied to the simulated episodes themselves, _read_truth; the mean; NaN
    where the outcomes came from cfg.truth_cache without frames), OBSERVED_SECOND: (P, N) float (the
    second judge's, the same way; NaN without one), "prob_replayed": (P, N) float
    (cfg.readout of each simulated episode's actions imagined open loop, _read_replay, with
    cfg.replay; the mean; NaN otherwise), "sim_finite": (P, N) bool
    (the simulated episode's proprioception and actions all finite; True where read from a truth
    cache without frames), "prob_members": (K, P, N), "trace_success" and "trace_progress": (P, N, T) float16
    (the per-step success probability and predicted progress of each imagined episode; the models'
    mean), "true_progress": (P, N, T) float16 (the simulator's progress; NaN where a truth cache's
    entry lacks it), "videos": {key: (T+1, S, S, 3)} (the first model's imagination), "video_index": [...],
    "sim_s", "wm_s", "steps"}; with motion (wm.geometric.load_motion's, cfg.geometric; grasp:
    wm.grasp.load_grasp's {task: rule}) "readout_geometric" (geometric_readout; with cfg.geometric_ranks
    "prob" too). With `chunks`, a row per policy and slice of states instead: "names"
    repeat, "slices" [P'] gives each row's slice, and N is a slice's states (merge_task_parts joins them).
    """
    slices = state_slices(cfg, len(seeds))
    reset_keys = reset_keys_of(seeds)
    renderer = cached_renderers(models[0][0].model.size, (HEAD_CAMERA,))
    kept, starts = {}, {}
    clock = {"sim_s": 0.0, "wm_s": 0.0, "steps": None, "wm_parts": dict.fromkeys(WM_PARTS, 0.0)}
    todo = [b for b in task_batches(cfg, sources, len(seeds)) if chunks is None or b[:2] in chunks]
    bar = tqdm(total=sum(len(part) * (slices[j][1] - slices[j][0]) for _, j, part, _ in todo), desc=f"{task}",
               unit="ep", disable=not progress)

    def run_batch(batch, wait: bool) -> list | None:
        """One batch's rows [(name, slice, {key: the policy's array over the slice's states})]; None
        where another process is simulating its truth (wait=False)."""
        _, j, part, padded = batch
        s0, s1 = slices[j]
        n = s1 - s0
        policy, params = chunk_policy(padded, n)
        rng = slice_key(cfg, j)
        t0 = time.perf_counter()
        truth = simulate_batch(cfg, task, batch, (policy, params), slices, seeds, reset_keys, engine, renderer, wait)
        if truth is None:
            return None
        clock["steps"] = truth["steps"]
        clock["sim_s"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        got, each = _predict_batch(cfg, task, models, policy, params, truth, rng, clock["wm_parts"])
        if motion is not None:
            with _timed(clock["wm_parts"], "geometric_s"):
                if task in geometric_tasks(motion, grasp) and j not in starts:  # a slice's first views serve its batches
                    starts[j] = geometric_start(task, reset_keys[s0:s1], models[0][0].model.size)
                got |= geometric_readout(cfg, task, motion, policy, params, starts.get(j), len(padded), rng, got,
                                         grasp, [e["action"] for e in each])
        got = {key: v.reshape((len(padded), n) + v.shape[1:])[: len(part)] for key, v in got.items()}
        got["true"] = truth["outcome"][: len(part)]
        with _timed(clock["wm_parts"], "sim_imagined_s"):
            got["sim_imagined"] = (simulate_actions(task, each[0]["action"], reset_keys[s0:s1], engine)[: len(part)]
                                   .astype(np.float64) if cfg.replay else np.full((len(part), n), np.nan))
        clock["wm_s"] += time.perf_counter() - t0
        if j == 0:  # the report's videos come from the first slice's states
            for i, src in enumerate(part):
                kept[src.name] = _keep_examples(cfg, src.name, i, n, got["true"][i], got["prob"][i],
                                                truth.get("frames"), each[0]["frames"])
        bar.update(len(part) * n)
        return [(src.name, j, {key: v[i] for key, v in got.items()}) for i, src in enumerate(part)]

    # rankings sharing cfg.truth_cache (other GPUs' models) each take the batches no other is simulating
    rows = [row for batch_rows in in_turn(todo, run_batch) for row in batch_rows]
    bar.close()
    sim_s, wm_s, steps, wm_parts = clock["sim_s"], clock["wm_s"], clock["steps"], clock["wm_parts"]
    if chunks is None:
        res = join_slices(rows, len(models), len(seeds))
        first = list(range(len(res["names"])))
    else:
        res = _stack_rows(rows, len(models), slices[0][1] - slices[0][0])
        first = [r for r, j in enumerate(res["slices"]) if j == 0]
    videos, index = _select_videos(cfg, task, [res["names"][r] for r in first], res["true"][first], kept)
    return {**res, "videos": videos, "video_index": index, "sim_s": sim_s, "wm_s": wm_s, "wm_parts": wm_parts,
            "steps": steps}


# the parts of an evaluation batch's world-model time (results.json's timing "imagine_parts"): the
# policies' closed loops with every read-out of them, their frames and actions against the simulator's,
# the simulated episodes read through each model (truth_features), and with replay=1 their actions
# imagined open loop and the loop's actions simulated; the rest of imagine_s is the host's bookkeeping
WM_PARTS = ("closed_loop_s", "fidelity_s", "observed_s", "replay_s", "sim_imagined_s", "geometric_s")


@contextlib.contextmanager
def _timed(clock: dict, key: str):
    """Adds the with-block's wall time to clock[key]."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        clock[key] += time.perf_counter() - t0


def _predict_batch(cfg: EvalConfig, task: str, models, policy, params, truth: dict, rng,
                   clock: dict | None = None) -> tuple[dict, list]:
    """Every world model's predictions for one simulated batch of B episodes: ({"prob": (B,) the
    models' mean of cfg.readout, "prob_members": (B, K) per model, "readout_<name>", "prob_observed",
    OBSERVED_SECOND, "prob_replayed" (B,), "sim_finite" (B,), the traces (B, T), the fidelity arrays, and with
    cfg.keep_features "features" and "features_observed" (B, T, F) float16}, each model's _imagine).
    clock: {WM_PARTS name: seconds} to which each part's wall time is added (each part ends in host
    arrays, so its device work is inside its time)."""
    clock = clock if clock is not None else dict.fromkeys(WM_PARTS, 0.0)
    steps, frames0, proprio0 = truth["steps"], truth["frames0"], truth["proprio0"]
    b = len(frames0)
    with _timed(clock, "closed_loop_s"):
        # the policy draws from the keys it drew from in the simulator (record_policies' split of rng)
        policy_keys = tuple(jax.random.split(rng, 3)[1:])
        each = [_imagine(m, task, policy, params, frames0, proprio0, steps, jax.random.fold_in(rng, 1), policy_keys)
                for m in models]
    p_each = np.stack([e[cfg.readout] for e in each], axis=1)  # (B, K)
    with _timed(clock, "fidelity_s"):
        fidelity = imagination_fidelity(truth, each[0]["frames"], each[0]["action"], steps)
    got = {"prob": p_each.mean(1), "prob_members": p_each,
           **{k: np.mean([e[k] for e in each], axis=0).astype(np.float16) for k in ("trace_success", "trace_progress")},
           "true_progress": truth.get("progress", np.full((b, steps), np.nan)).astype(np.float16), **fidelity,
           **{f"readout_{r}": np.mean([e[r] for e in each], axis=0) for r in MODEL_READOUTS},
           f"readout_{GEOMETRIC}": np.full(b, np.nan)}
    with _timed(clock, "observed_s"):
        seen = [truth_features(m, truth) for m in models]
        on_truth = [_read_truth(m, task, x, b) for m, x in zip(models, seen)]
    got["prob_observed"] = np.mean([r[cfg.readout] for r in on_truth], axis=0)
    got[OBSERVED_SECOND] = np.mean([r[SECOND_JUDGE] for r in on_truth], axis=0)
    with _timed(clock, "replay_s"):
        got["prob_replayed"] = (np.mean([_read_replay(m, task, truth, cfg.readout) for m in models], axis=0)
                                if cfg.replay else np.full(b, np.nan))
    got["sim_finite"] = simulated_finite(truth)
    if cfg.keep_features:
        got["features"] = np.asarray(each[0]["features"], np.float16)
        if seen[0] is not None:
            got["features_observed"] = np.asarray(seen[0], np.float16)
    return got, each


def geometric_start(task: str, reset_keys, size: int) -> tuple:
    """(wm.geometric.FirstView, the number of control steps) of the N states of reset_keys (N, 2) on
    task, drawn at size x size pixels in the simulation's scene (_simulate's env)."""
    env = cached_env(task, len(reset_keys), "cpu", False)
    return start_view(env, env.reset(jnp.asarray(reset_keys)), size, robot_camera()), env.episode_steps


def geometric_tasks(motion: Motion | None, grasp: dict | None) -> tuple:
    """The tasks the geometric read-out predicts: wm.geometric.PREDICTS where motion holds a fill, and
    those grasp holds a rule of (wm.grasp.load_grasp's {task: GraspRule})."""
    if motion is None:
        return ()
    return (PREDICTS if motion.fill_net is not None else ()) + tuple(grasp or ())


def geometric_readout(cfg: EvalConfig, task: str, motion: Motion, policy, params, start: tuple, copies: int, rng,
                      got: dict, grasp: dict | None = None, loops_actions=()) -> dict:
    """The geometric read-out of a batch of `copies` policies (chunk_policy's, policy-major) from the
    N states of start (geometric_start's): for a task of wm.geometric.PREDICTS, the policies acting in
    wm.geometric.imagine_robot's imagination from each state's first drawing, with the keys they drew
    from in the simulator and the predicted robot's proprioception, their success the task's rule on the
    predicted states (1 or 0 an episode); for a task grasp holds a rule of (wm.grasp.load_grasp's), its
    verdict (wm.grasp.grasp_success) on each world model's loop of the batch (loops_actions: [(B, T, 20)]
    the actions its policies took there), the mean over the models; elsewhere got["prob"] (the ranked
    read-out). Returns {"readout_geometric": (B,) float64} and, with cfg.geometric_ranks on such a task,
    "prob" and "prob_members" ((B,), (B, K)) replaced by it."""
    if task not in geometric_tasks(motion, grasp):
        return {f"readout_{GEOMETRIC}": got["prob"]}
    first, steps = start
    view = jax.tree.map(lambda x: jnp.tile(x, (copies,) + (1,) * (jnp.ndim(x) - 1)), first)
    if task in PREDICTS:
        policy_keys = tuple(jax.random.split(rng, 3)[1:])  # _predict_batch's: the simulator's draws
        # the policy reads the predicted body (a policy that sums its sensed speed stops where the model says)
        moved = imagine_robot(policy, params, motion, view, policy_keys, robot_camera(), steps, "predicted")
        p = np.asarray(moved["success"], np.float64)
    else:
        p = np.mean([np.asarray(grasp_success(grasp[task], motion.base, motion.joints, view.qpos, view.mocap, view.task,
                                              actions, robot_camera(), task)["success"], np.float64)
                     for actions in loops_actions], axis=0)
    out = {f"readout_{GEOMETRIC}": p}
    if cfg.geometric_ranks:
        out |= {"prob": p, "prob_members": np.repeat(p[:, None], got["prob_members"].shape[1], axis=1)}
    return out


def _empty_rows(k: int, n: int) -> dict:
    """evaluate_task's arrays for no policy (a part given none of a task's batches)."""
    empty = np.zeros((0, n))
    return {"names": [], "slices": [], "true": empty.astype(bool), "prob": empty, "prob_observed": empty,
            OBSERVED_SECOND: empty, "prob_replayed": empty, "sim_imagined": empty, "sim_finite": np.ones((0, n), bool),
            **{key: np.zeros((0, n, 0), np.float16) for key in TRACES + FIDELITY},
            **{key: empty for key in READOUT_KEYS}, "prob_members": np.zeros((k, 0, n))}


def _stack_rows(rows: list, k: int, n: int) -> dict:
    """evaluate_task's arrays from rows [(name, slice, {key: array})] in their order (no joining):
    "names" and "slices" per row; prob_members (K, rows, N)."""
    if not rows:
        return _empty_rows(k, n)
    out = {key: np.stack([r[2][key] for r in rows]) for key in _common_keys([r[2] for r in rows])}
    out["prob_members"] = out["prob_members"].transpose(2, 0, 1)
    return {"names": [r[0] for r in rows], "slices": [r[1] for r in rows], **out}


def _common_keys(arrays: list) -> list:
    """The keys every dict of arrays has, in the first one's order (a batch read from the truth cache
    has no features of the simulated episodes)."""
    return [key for key in arrays[0] if all(key in a for a in arrays)]


def join_slices(rows: list, k: int, n: int) -> dict:
    """One row per policy (in the order of first appearance) from rows [(name, slice, {key: array
    with the slice's states first, prob_members (slice states, K)})]: each policy's slices joined in
    slice order into its n states; evaluate_task's arrays. Raises where a policy's slices do not
    make up its n states."""
    if not rows:
        return {key: v for key, v in _empty_rows(k, n).items() if key != "slices"}
    by_name: dict = {}
    for name, j, arrays in rows:
        by_name.setdefault(name, {})[j] = arrays
    joined = []
    for name, parts in by_name.items():
        ordered = [parts[j] for j in sorted(parts)]
        got = {key: np.concatenate([a[key] for a in ordered]) for key in _common_keys(ordered)}
        if len(got["true"]) != n:
            raise ValueError(f"{name}: its batches hold {len(got['true'])} of the task's {n} states: rerun the parts "
                             "(--part K/N) of this evaluation")
        joined.append((name, 0, got))
    out = _stack_rows(joined, k, n)
    del out["slices"]
    return out


def merge_task_parts(cfg: EvalConfig, parts: list, order: list) -> dict:
    """One task's results from its parts' (evaluate_task with chunks: a row per policy and slice of
    states), policies in `order` (the names as evaluate_task without chunks lists them), each policy's
    slices joined; the videos of the policies cfg.video_policies picks among those the parts filmed
    (the least and most successful are always among them). A part given none of the task's batches
    (more parts than batches) holds no rows and is passed over."""
    parts = [p for p in parts if p["names"]] or parts[:1]
    rows = [(name, j, {**{key: p[key][r] for key in POLICY_ARRAYS}, "prob_members": p["prob_members"][:, r].T})
            for p in parts for r, (name, j) in enumerate(zip(p["names"], p.get("slices") or [0] * len(p["names"])))]
    n = len(parts[0]["seeds"])
    if sorted({name for name, _, _ in rows}) != sorted(order):
        raise ValueError(f"the parts hold {len({name for name, _, _ in rows})} policies, not the task's {len(order)}: "
                         "rerun the parts (--part K/N) of this evaluation")
    joined = join_slices(rows, parts[0]["prob_members"].shape[0], n)
    at = [joined["names"].index(x) for x in order]
    merged = {key: v.take(at, axis=1 if key == "prob_members" else 0) for key, v in joined.items() if key != "names"}
    true = merged["true"]
    filmed = {v["policy"] for p in parts for v in p["video_index"]}
    shown = [i for i, x in enumerate(order) if x in filmed]
    chosen = {order[shown[i]] for i in filmed_policies(true[shown].mean(1), cfg.video_policies)}
    index = [v for p in parts for v in p["video_index"] if v["policy"] in chosen]
    keys = {i["key"] for i in index}
    videos = {k: v for p in parts for k, v in p["videos"].items() if k.rsplit("/", 1)[0] in keys}
    return {**merged, "names": list(order), "videos": videos, "video_index": index,
            "sim_s": sum(p["sim_s"] for p in parts), "wm_s": sum(p["wm_s"] for p in parts),
            # parts saved before the split have none: the sum only where every part was timed
            "wm_parts": ({k: sum(p["wm_parts"][k] for p in parts) for k in WM_PARTS}
                         if all(set(WM_PARTS) <= set(p.get("wm_parts", {})) for p in parts) else {}),
            "steps": next((p["steps"] for p in parts if p["steps"] is not None), None), "seeds": parts[0]["seeds"]}


def _imagine(model, task, policy, params, frames0, proprio0, steps, rng, policy_keys=None) -> dict:
    """One world model's closed-loop episodes of a batch (policy_keys: closed_loop's): {read-out name:
    (B,) float64 the episode's success probability by that read-out (read_episodes), "trace_success"
    and "trace_progress": (B, T) float32 the per-step heads' outputs, "frames": (B, T, S, S, 3) uint8
    imagined, "action": (B, T, 20) float32 the policy's actions}."""
    wm_cfg, wm_params, norm, judge, judge2 = model
    got = closed_loop(wm_cfg.model, applied_policy(policy), steps, wm_params, norm, params, frames0, proprio0,
                      np.zeros((len(frames0), 0, R.ACTION_DIM), np.float32), rng, policy_keys=policy_keys)
    return {**read_episodes(judge, task, got["features"], judge2), "trace_success": np.asarray(got["success"], np.float32),
            "trace_progress": np.asarray(got["progress"], np.float32), "frames": got["frames"],
            "action": np.asarray(got["action"], np.float32), "features": got["features"]}


def fidelity_horizons(steps: int) -> tuple:
    """The horizons (1-based steps) at which an episode of `steps` steps is compared: FIDELITY_HORIZONS
    up to its length, and its last step."""
    return tuple(sorted({h for h in FIDELITY_HORIZONS if h <= steps} | {steps}))


def fidelity_summary(res: dict) -> dict:
    """One task's imagination_fidelity arrays as means over its finite episodes, at each horizon:
    {"horizons", "frame_psnr", "copy_first_psnr", "gain_over_copy_first_db", "action_gap"} (the last:
    the action gap at the horizon's step); None values where no episode had frames."""
    hs = fidelity_horizons(res["steps"]) if res["steps"] else ()

    def mean(x):  # (P, N, H) -> (H,) over every episode
        return _mean_curve(np.reshape(x, (-1, len(hs)))) if hs else []

    frames, first = mean(res["frame_psnr"]), mean(res["copy_first_psnr"])
    gap = mean(np.take(res["action_gap"], [h - 1 for h in hs], axis=-1))
    return {"horizons": list(hs), "frame_psnr": frames, "copy_first_psnr": first,
            "gain_over_copy_first_db": [None if a is None or b is None else round(a - b, 3)
                                        for a, b in zip(frames, first, strict=True)],
            "action_gap": gap}


def imagination_fidelity(truth: dict, imagined, actions, steps: int) -> dict:
    """How closely closed-loop imagination follows the simulated episode of the same policy from the
    same start. truth: simulate_truth's ("frames" (B, T+1, S, S, 3), "action" (B, T, 20)); imagined
    (B, T, S, S, 3) uint8, frame t after action t; actions (B, T, 20) the policy's in imagination.
    Returns {"frame_psnr", "copy_first_psnr": (B, H) float32 dB at fidelity_horizons(steps) (the
    imagined frame against the true one; the first true frame against it: what a model that never
    moves scores; identical frames count 100 dB), "action_gap": (B, T) float32 the root-mean-square
    difference of the policy's action on imagined and on true observations, "action_gap_dims": (B, 20)
    float32 the same per action dimension over the episode's steps (a gap in one dimension, such as
    the base's speed, that the mean over 20 dilutes), "action_bias_dims": (B, 20) float32 the mean signed
    difference (imagined minus true) per dimension over the steps (a hand that closes firmer in
    imagination: a grasp is a threshold on its closure)}; NaN where the truth came from the cache
    without frames."""
    hs = fidelity_horizons(steps)
    b = len(actions)
    if "frames" not in truth:
        return {"frame_psnr": np.full((b, len(hs)), np.nan, np.float32),
                "copy_first_psnr": np.full((b, len(hs)), np.nan, np.float32),
                "action_gap": np.full((b, steps), np.nan, np.float32),
                "action_gap_dims": np.full((b, R.ACTION_DIM), np.nan, np.float32),
                "action_bias_dims": np.full((b, R.ACTION_DIM), np.nan, np.float32)}
    real = truth["frames"]
    at = [h - 1 for h in hs]
    true_h = np.asarray(real[:, hs])
    pred = np.minimum(psnr(np.asarray(imagined[:, at]), true_h), 100.0)
    first = np.minimum(psnr(np.asarray(real[:, :1]), true_h), 100.0)
    diff = np.asarray(actions, np.float64) - np.asarray(truth["action"], np.float64)
    return {"frame_psnr": pred.astype(np.float32), "copy_first_psnr": first.astype(np.float32),
            "action_gap": np.sqrt((diff ** 2).mean(-1)).astype(np.float32),
            "action_gap_dims": np.sqrt((diff ** 2).mean(1)).astype(np.float32),
            "action_bias_dims": diff.mean(1).astype(np.float32)}


def read_episodes(judge, task: str, features, judge2=None) -> dict:
    """Every read-out of episodes' success from their step features ((B, T, F), wm.imagine.step_features
    or observed_features): {"progress": (B,) the progress head's last value clipped to [0, 1],
    "success": (B,) the highest per-step success probability, "judge": (B,) the episode judge's
    (the "success" read-out where no judge knows the task), "judge2": (B,) the second judge's
    (NaN without one, or where it does not know the task)}, float64."""
    x = np.asarray(features)
    out = {"progress": np.clip(x[:, -1, PROGRESS_FEATURE], 0.0, 1.0).astype(np.float64),
           "success": np.asarray(episode_success(x[..., SUCCESS_FEATURE], task), np.float64)}
    out["judge"] = judge.probability(x, task).astype(np.float64) if judge is not None and judge.knows(task) \
        else out["success"]
    out["judge2"] = judge2.probability(x, task).astype(np.float64) if judge2 is not None and judge2.knows(task) \
        else np.full(len(x), np.nan)
    return out


def truth_features(model, truth: dict):
    """One world model's step features of the simulated episodes themselves, as if imagination were
    exact (wm.imagine.observed_features): (B, T, F), or None where the truth's frames are not at hand
    (read back from the truth cache)."""
    if "frames" not in truth:
        return None
    wm_cfg, wm_params, norm, _, _ = model
    return observed_features(wm_cfg.model, wm_params, norm, truth["frames"], truth["proprio"], truth["action"])


def _read_truth(model, task, x, b: int) -> dict:
    """One world model's read-outs (read_episodes) of the b simulated episodes' features x
    (truth_features): {name: (B,) float64}. Above the world model's own figure, imagination loses what
    decides the outcome; where low, the heads (or the judge) cannot read the outcome even from true
    frames; NaN where x is None."""
    if x is None:
        return {r: np.full(b, np.nan) for r in READOUTS}
    return read_episodes(model[3], task, x, model[4])


def _read_replay(model, task, truth: dict, readout: str) -> np.ndarray:
    """One world model's read-out of the simulated episodes' own actions (B, T, 20) imagined open loop
    from their first frame and proprioception (wm.imagine.open_loop): (B,) float64; NaN where the
    truth's actions are not at hand (read back from the truth cache)."""
    b = len(truth["frames0"])
    if "frames" not in truth:
        return np.full(b, np.nan)
    wm_cfg, wm_params, norm, judge, judge2 = model
    got = open_loop(wm_cfg.model, wm_params, norm, truth["frames0"], truth["proprio0"],
                    np.zeros((b, 0, R.ACTION_DIM), np.float32), truth["action"])
    return read_episodes(judge, task, got["features"], judge2)[readout]


def simulated_finite(truth: dict) -> np.ndarray:
    """(B,) bool: each simulated episode's proprioception and actions are all finite (an engine whose
    state diverged leaves NaN or inf, and its outcome means little); True where the truth came back
    from the truth cache without them."""
    if "proprio" not in truth:
        return np.ones(len(truth["frames0"]), bool)
    ok = lambda x: np.isfinite(np.asarray(x)).reshape(len(x), -1).all(axis=1)
    return ok(truth["proprio"]) & ok(truth["action"])


def simulate_batch(cfg: EvalConfig, task: str, batch, chunk: tuple, slices, seeds, reset_keys, engine: str,
                   renderer, wait: bool = True, read: bool = True) -> dict | None:
    """simulate_truth of one of task_batches' batches (k, j, policies, padded), chunk its padded
    policies' (policy, params) (chunk_policy), from the states of slice j with the slice's random key."""
    _, j, _, padded = batch
    s0, s1 = slices[j]
    policy, params = chunk
    return simulate_truth(cfg, task, policy, params, seeds[s0:s1], reset_keys[s0:s1], slice_key(cfg, j), engine,
                          renderer, wait, code="".join(s.code for s in padded), read=read)


def simulate_all(cfg: EvalConfig, tasks, sources, used: set, engine: str, renderer, progress: bool = True) -> None:
    """Every batch of cfg's evaluation of tasks simulated into cfg.truth_cache, as the evaluation
    would simulate it (simulate_batch; the same held-out states, slices and random keys), those no
    other process is simulating first; batches the cache holds are left as they are."""
    for task in tasks:
        seeds = heldout_seeds(task, cfg.episodes, cfg.seed, used)
        slices, reset_keys = state_slices(cfg, len(seeds)), reset_keys_of(seeds)
        todo = task_batches(cfg, [s for s in sources if s.runs_on(task)], len(seeds))
        bar = tqdm(total=sum(len(part) * (slices[j][1] - slices[j][0]) for _, j, part, _ in todo),
                   desc=f"simulate {task}", unit="ep", disable=not progress)

        def attempt(batch, wait: bool) -> bool | None:
            _, j, part, padded = batch
            chunk = chunk_policy(padded, slices[j][1] - slices[j][0])
            if simulate_batch(cfg, task, batch, chunk, slices, seeds, reset_keys, engine, renderer, wait,
                              read=False) is None:
                return None
            bar.update(len(part) * (slices[j][1] - slices[j][0]))
            return True

        in_turn(todo, attempt)
        bar.close()


def truth_space(cfg: EvalConfig, tasks, sources, size: int) -> None:
    """Raises ValueError where the disk of cfg.truth_cache has too little room for the frames that
    cfg.truth_frames keeps there: (T+1) frames of size x size x 3 bytes for each of a task's episodes
    (every batch's policies, padding included, from every state), less what the cache holds already."""
    if not cfg.truth_frames:
        return
    root = Path(cfg.truth_cache)
    root.mkdir(parents=True, exist_ok=True)
    slices = state_slices(cfg, cfg.episodes)
    episodes = {t: sum(len(padded) * (slices[j][1] - slices[j][0])
                       for _, j, _, padded in task_batches(cfg, [s for s in sources if s.runs_on(t)], cfg.episodes))
                for t in tasks}
    need = sum(n * (TASKS[t].episode_steps + 1) * size * size * 3 for t, n in episodes.items())
    need -= sum(f.stat().st_size for f in root.glob("*.npz") if ".tmp" not in f.name)  # not a dead writer's half file
    free = shutil.disk_usage(root).free
    if need > 0.95 * free:
        raise ValueError(f"truth_frames: the simulated frames need about {need / 1e9:.1f} GB more in {root}, which has "
                         f"{free / 1e9:.1f} GB free: free some space, evaluate fewer states (episodes=...), or keep "
                         "the outcomes alone (truth_frames=0 with video_policies=0)")


TRUTH_ARRAYS = ("frames", "proprio", "action")  # the simulated episodes a truth cache keeps with truth_frames


def simulate_truth(cfg: EvalConfig, task: str, policy, params, seeds, reset_keys, rng, engine: str,
                   renderer, wait: bool = True, code: str = "", read: bool = True) -> dict | None:
    """Closed-loop simulator episodes of P stacked policies from n initial states, or the same read
    back from cfg.truth_cache (a process that finds another simulating the same batch waits for it,
    under a lock file beside the cache entry, and reads its outcomes; with wait=False it returns None
    at once instead). Returns {"outcome": (P, n) bool, "frames0": (P*n, 1, S, S, 3) uint8,
    "proprio0": (P*n, 1, 37), "steps": int, and "frames": (P*n, T+1, S, S, 3), "proprio": (P*n,
    T+1, 37) and "action": (P*n, T, 20) where simulated or kept (cfg.truth_frames)}. code: the
    plug-ins' code_digest, part of the cache's key. read=False: {} where the cache holds the batch
    (a warm-up filling the cache has no use for it)."""
    if not cfg.truth_cache:
        return _simulate(task, policy, params, seeds, reset_keys, rng, engine, renderer)
    path = Path(cfg.truth_cache) / f"{task}-{_truth_key(task, policy, params, seeds, rng, engine, renderer, code)}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    # Rankings on other GPUs wait for the one simulating this batch: the simulator on a GPU is not
    # bit-reproducible, and models compared must be compared against the same outcomes.
    with exclusive(path.with_suffix(".lock"), wait) as held:
        if not held:
            return None
        if path.exists():
            with np.load(path) as z:
                if not cfg.truth_frames or "frames" in z.files:
                    if not read:
                        return {}
                    keep = ("outcome", "frames0", "proprio0", "progress") + (TRUTH_ARRAYS if cfg.truth_frames else ())
                    return {k: z[k] for k in keep if k in z.files} | {"steps": int(z["steps"])}
        truth = _simulate(task, policy, params, seeds, reset_keys, rng, engine, renderer)
        _keep_truth(cfg, path, truth)
    return truth


TRUTH_RESERVE = 2 << 30  # bytes an entry of the truth cache leaves free on its disk (the training's checkpoints beside)


def _keep_truth(cfg: EvalConfig, path: Path, truth: dict) -> None:
    """Writes truth (simulate_truth's, the lock of path held) to the cache entry path through a temporary
    file: first removes what a writer killed before its rename left there (SIGKILL: a warm-up stopped
    beside the training), and keeps nothing, with a warning, where the disk would keep less than
    TRUTH_RESERVE free or the write fails: the evaluation goes on with the simulated episodes in hand."""
    for stale in path.parent.glob(f"{path.stem}.tmp*.npz"):
        stale.unlink(missing_ok=True)
    arrays = {k: np.asarray(v) for k, v in truth.items() if cfg.truth_frames or k not in TRUTH_ARRAYS}
    size = sum(a.nbytes for a in arrays.values())
    if shutil.disk_usage(path.parent).free < size + TRUTH_RESERVE:
        print(f"warning: {path.parent} has no room for {size / 1e9:.1f} GB more: {path.name} not kept in the "
              "truth cache", file=sys.stderr)
        return
    tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}.npz")
    try:
        np.savez(tmp, **arrays)
        tmp.replace(path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        print(f"warning: {path.name} not kept in the truth cache ({e})", file=sys.stderr)


def _simulate(task, policy, params, seeds, reset_keys, rng, engine, renderer, steps: int | None = None) -> dict:
    env = cached_env(task, policy.count(params) * len(seeds), engine, False)
    outcome, rec = record_policies(env, policy, params, reset_keys, rng, renderer, steps)
    return {"outcome": outcome, "frames0": np.asarray(rec.frames[HEAD_CAMERA][:, :1]),
            "proprio0": np.asarray(rec.proprio[:, :1]), "steps": steps or env.episode_steps,
            "frames": rec.frames[HEAD_CAMERA], "proprio": rec.proprio, "action": rec.action,
            "progress": np.asarray(rec.progress[:, 1:], np.float32)}


def _truth_key(task, policy, params, seeds, rng, engine, renderer, code: str = "") -> str:
    """A digest of everything a batch of simulated episodes depends on: the task, the policies (their
    class, configuration, parameters and plug-ins' code), the initial states, the random key, the
    engine and its physics revision, the camera."""
    h = hashlib.sha256(json.dumps([task, describe(policy), [int(s) for s in seeds], np.asarray(rng).tolist(), engine,
                                   PHYSICS_REVISION, [repr(r.cfg) for r in renderer], code], default=str).encode())
    hash_arrays(h, params)
    return h.hexdigest()[:20]


def _keep_examples(cfg, name, j, n, outcome, p, real, imagined) -> list:
    """Up to video_episodes episodes of one policy (a success and a failure first), real and imagined."""
    if real is None or not cfg.video_policies:
        return []
    order = [int(np.argmax(outcome)), int(np.argmin(outcome))] + list(range(n))
    picked = list(dict.fromkeys(order))[: cfg.video_episodes]
    out = []
    for e in picked:
        row = j * n + e
        real_ep = np.asarray(real[row])
        gen = np.concatenate([real_ep[:1], np.asarray(imagined[row])])
        out.append({"episode": e, "true_success": bool(outcome[e]), "pred_prob": float(p[e]), "real": real_ep,
                    "imagined": gen})
    return out


def filmed_policies(rates, limit: int) -> list[int]:
    """Which policies (indices into rates) the report films: the least, the median and the most
    successful first, then the others by rate, at most `limit`."""
    order = [int(i) for i in np.argsort(rates, kind="stable")]
    if not order:
        return []
    picks = [order[0], order[len(order) // 2], order[-1]] + order
    return list(dict.fromkeys(picks))[:limit]


def _select_videos(cfg, task, names, true, kept):
    chosen = filmed_policies(true.mean(1), cfg.video_policies)
    videos, index = {}, []
    for i in chosen:
        for ex in kept[names[i]]:
            key = f"{task}/{names[i]}/{ex['episode']}"
            videos[key + "/real"], videos[key + "/imagined"] = ex["real"], ex["imagined"]
            index.append({"task": task, "policy": names[i], "episode": ex["episode"], "key": key,
                          "true_success": ex["true_success"], "pred_prob": ex["pred_prob"]})
    return videos, index


# ---- results ---------------------------------------------------------------------------------------

def _interval_of_mean(x) -> list:
    """A 95% t-interval of a policy's mean predicted probability over its episodes, within [0, 1]
    ([0, 1] for one episode; NaN where a prediction is not finite)."""
    x = np.asarray(x, np.float64)
    if not np.isfinite(x).all():
        return [math.nan, math.nan]
    return S.mean_interval(x, (0.0, 1.0))[1] or [0.0, 1.0]


def failed_peak_progress(true_progress, outcomes) -> float | None:
    """How near a policy's failed episodes came to success: the highest progress the simulator measured
    in each failed episode ((N, T) true_progress against (N,) bool outcomes; 1 is the success line,
    sim_data.sim.tasks.task_progress), averaged over them and rounded to 3 decimals; None where no
    episode failed or none of those has a progress (a truth cache kept without it). Near 1, the
    policy's true rate turns on a few millimetres of its task's measure; at 1, its failures reached
    success and left it (a drive past step_back's band)."""
    failed = np.asarray(true_progress, np.float64)[~np.asarray(outcomes, bool)]
    peaks = [float(np.nanmax(e)) for e in failed if np.isfinite(e).any()]
    return round(float(np.mean(peaks)), 3) if peaks else None


def _mean_curve(x) -> list:
    """(N, T) per-episode values -> their mean at each step (NaN episodes left out; null where all are),
    rounded to 3 decimals for results.json."""
    x = np.asarray(x, np.float64)
    ok = np.isfinite(x)
    n = ok.sum(0)
    m = np.where(ok, x, 0.0).sum(0) / np.maximum(n, 1)
    return [round(float(v), 3) if k else None for v, k in zip(m, n, strict=True)]


def _mean_or_none(x) -> float | None:
    """The mean of x, or None where any of it is NaN (not measured)."""
    return None if np.isnan(x).any() else float(np.mean(x))


def _finite(x) -> bool:
    """Whether x is a finite number (None and NaN are not)."""
    return isinstance(x, (int, float)) and math.isfinite(x)


def _finite_mean(x) -> float | None:
    """The mean of x's finite values, rounded to 4 decimals; None where none is finite."""
    x = np.asarray(x, np.float64)
    ok = np.isfinite(x)
    return round(float(x[ok].mean()), 4) if ok.any() else None


def largest_action_gap(dims) -> dict | None:
    """The action dimension whose RMS gap between the policy's actions on imagined and on true frames is
    largest over a policy's episodes: {"dim": its name (sim_data.sim.robot.ACTION_NAMES), "rms"}, from
    dims (N, 20) (imagination_fidelity's action_gap_dims); None where no episode has them."""
    dims = np.asarray(dims, np.float64)
    ok = np.isfinite(dims).all(axis=-1)
    if dims.size == 0 or not ok.any():
        return None
    rms = np.sqrt((dims[ok] ** 2).mean(0))
    k = int(rms.argmax())
    return {"dim": R.ACTION_NAMES[k], "rms": round(float(rms[k]), 4)}


def closure_gap(dims, bias) -> dict:
    """The right hand's closure in imagination against on true frames over a policy's episodes, from dims and
    bias (N, 20) (imagination_fidelity's action_gap_dims and action_bias_dims; bias (N, 0) from results
    written without it): {"closure_gap": the RMS gap, "closure_bias": the mean signed difference (> 0: the
    hand closes firmer in imagination)}, each None where no episode has it."""
    dims, bias = np.asarray(dims, np.float64), np.asarray(bias, np.float64)
    gap = dims[:, R.RIGHT_HAND] if dims.shape[-1] == R.ACTION_DIM else np.full(len(dims), np.nan)
    sign = bias[:, R.RIGHT_HAND] if bias.shape[-1] == R.ACTION_DIM else np.full(len(bias), np.nan)
    ok, signed = np.isfinite(gap), np.isfinite(sign)
    return {"closure_gap": round(float(np.sqrt((gap[ok] ** 2).mean())), 4) if ok.any() else None,
            "closure_bias": round(float(sign[signed].mean()), 4) if signed.any() else None}


def policy_rows(cfg: EvalConfig, task: str, res: dict, sources_by_name: dict) -> list[dict]:
    """One report row per policy of task from its results (evaluate_task's dict; sources_by_name: the sources by
    name, for their records and kinds): the true rate and predicted rate with their intervals, the thresholded
    prediction, alignment, each read-out's rate (those of READOUTS that read the task: no second judge's
    where the world models have none), the rates read on the simulated and replayed episodes, mean
    progress curves, the action gap, and the per-episode outcomes and probabilities (the rates read on the
    simulated episodes: cfg.readout's and the second judge's, None where not read); with an ensemble, each
    member's predicted rate ("pred_rates")."""
    rows = []
    members = res["prob_members"].transpose(1, 0, 2)  # (P, K, N)
    named = readouts_of({task: res}, [task])
    readouts = np.stack([res[f"readout_{r}"] for r in named], axis=1).reshape(len(res["names"]), len(named), -1)
    for name, t, p, r, pk, ok, tp, ip, gap, dims, bias, obs, obs2, rep, played in zip(
            res["names"], res["true"], res["prob"], readouts, members, res["sim_finite"], res["true_progress"],
            res["trace_progress"], res["action_gap"], res["action_gap_dims"], res["action_bias_dims"],
            res["prob_observed"], res[OBSERVED_SECOND], res["prob_replayed"], res["sim_imagined"], strict=True):
        rec = sources_by_name[name].record
        k, n = int(t.sum()), len(t)
        read = bool(np.isfinite(p).all())  # a non-finite prediction reads no outcome
        rows.append({"name": name, "task": task, "lineage": rec.get("lineage", "plugin"), "step": rec.get("step"),
                     "kind": sources_by_name[name].kind, "n": n, "true_rate": k / n,
                     "true_ci": list(S.wilson_interval(k, n)), "pred_rate": float(p.mean()),
                     "pred_ci": _interval_of_mean(p),
                     "pred_rate_thresholded": float((p >= cfg.threshold).mean()) if read else math.nan,
                     "pred_thresholded_ci": (list(S.wilson_interval(int((p >= cfg.threshold).sum()), n)) if read
                                             else [math.nan, math.nan]),
                     # a checkpoint whose imitation training diverged (NaN) has no loss to rank by
                     "val_loss": rec.get("val_loss") if _finite(rec.get("val_loss")) else None,
                     "alignment": S.alignment(p >= cfg.threshold, t) if read else math.nan,
                     "pred_rate_readouts": dict(zip(named, r.mean(1).tolist(), strict=True)),
                     # the read-out of the simulated episodes, and of their actions replayed (replay=1)
                     "pred_rate_on_truth": _mean_or_none(obs), "pred_rate_replayed": _mean_or_none(rep),
                     f"pred_rate_on_truth_{SECOND_JUDGE}": _mean_or_none(obs2),
                     # the simulator's success on the actions the policy took in imagination (replay=1)
                     "true_rate_imagined_actions": _mean_or_none(played),
                     "nonfinite_episodes": int((~ok).sum()), "nonfinite_predictions": int((~np.isfinite(p)).sum()),
                     # mean progress over the episodes at each step, the simulator's and the imagined
                     "progress_true": _mean_curve(tp), "progress_imagined": _mean_curve(ip),
                     "failed_peak_progress": failed_peak_progress(tp, t),
                     # RMS gap of the policy's actions on imagined and on true frames, over its episodes' steps
                     "action_gap": _finite_mean(gap), "action_gap_largest": largest_action_gap(dims),
                     **closure_gap(dims, bias),
                     # per held-out state, in the order of the seeds: for ensembles (experiments.ensemble)
                     "true_episodes": t.astype(int).tolist(), "pred_episodes": np.round(p, 5).tolist()})
        if len(pk) > 1:
            rows[-1]["pred_rates"] = pk.mean(1).tolist()  # each ensemble member's
    return rows


def readouts_of(results: dict, tasks) -> list[str]:
    """The READOUTS that read every task of tasks (results: {task: evaluate_task's dict}): all, the
    second judge and the geometric read-out only where theirs is not NaN throughout any task (a model
    without a second judge, or one that never learned the task, reads nothing there; the geometric
    read-out reads only with cfg.geometric)."""
    return [r for r in READOUTS
            if r not in (SECOND_JUDGE, GEOMETRIC) or all(np.isfinite(results[t][f"readout_{r}"]).any() for t in tasks)]


def read_readouts(rows: list[dict]) -> list[str]:
    """The READOUTS that every policy of rows (policy_rows) has a rate of: all but a second judge the
    world models do not have."""
    return [r for r in READOUTS if all(r in row["pred_rate_readouts"] for row in rows)]


def ranking_block(rows: list[dict], true_eps, prob_eps, threshold: float, member_eps=None) -> dict:
    """The world model's statistics and the imitation-loss baseline's over one set of policies (rows,
    and their episodes' (P, N) outcomes and probabilities in the same order); with an ensemble's
    member_eps (K, P, N), each member's own statistics ("members"). A policy whose predicted rate is
    not finite (its imagination diverged) is left out of every statistic and named in "left_out"
    (where fewer than two are left, none is: the statistics are then NaN)."""
    read = [i for i, r in enumerate(rows) if np.isfinite(r["pred_rate"])]
    left_out = [r["name"] for r in rows if not np.isfinite(r["pred_rate"])]
    if left_out and len(read) >= 2:
        rows, true_eps, prob_eps = [rows[i] for i in read], np.asarray(true_eps)[read], np.asarray(prob_eps)[read]
        member_eps = None if member_eps is None else np.asarray(member_eps)[:, read]
    true = [r["true_rate"] for r in rows]
    out = S.ranking_metrics([r["pred_rate"] for r in rows], true)
    ranked = tuple(out)
    out["pearson_ci_bootstrap"] = list(S.bootstrap_pearson(prob_eps, true_eps, draws=1000))
    out["alignment"] = S.alignment(prob_eps >= threshold, true_eps)
    thr = S.ranking_metrics([r["pred_rate_thresholded"] for r in rows], true)
    out["thresholded"] = {k: thr[k] for k in ("pearson", "spearman", "mmrv", "pairwise_acc_gap10")}
    out["readouts"] = {}
    for name in read_readouts(rows):
        m = S.ranking_metrics([r["pred_rate_readouts"][name] for r in rows], true)
        out["readouts"][name] = {k: m[k] for k in ("pearson", "spearman", "mmrv", "pairwise_acc_gap10")}
    if left_out and len(read) < 2:  # fewer than two predictions read: nothing is ranked (the above compared NaN)
        out |= {k: [math.nan] * 2 if isinstance(out[k], list) else math.nan
                for k in (*ranked, "pearson_ci_bootstrap", "alignment")}
        out["thresholded"] = dict.fromkeys(out["thresholded"], math.nan)
        out["readouts"] = {name: dict.fromkeys(m, math.nan) for name, m in out["readouts"].items()}
    if member_eps is not None and len(member_eps) > 1:
        out |= member_metrics(np.array([r["pred_rates"] for r in rows]).T, true, member_eps, true_eps, threshold)
    with_loss = [r for r in rows if r["val_loss"] is not None]
    if len(with_loss) >= 2:  # lower imitation loss predicts higher success
        out["baseline"] = S.ranking_metrics([-r["val_loss"] for r in with_loss], [r["true_rate"] for r in with_loss])
    if left_out:
        out["left_out"] = left_out
    return out


def within_task_block(results: dict, tasks, rows: list[dict], cfg: EvalConfig, keep) -> dict:
    """The within-task headline (experiments.stats.within_task) of the world model (cfg.readout, with
    cfg.geometric_ranks the geometric read-out where it predicts) beside the imitation-loss proxy
    (minus each checkpoint's validation loss; policies without one, such as plug-ins, are left out of
    the proxy's statistics), the world model's other read-outs ("readout_<name>"), and, where every episode has it, the read-out applied to the simulated
    episodes themselves ("on_truth", _read_truth: what it reads where imagination is exact; the second
    judge's "on_truth_judge2" beside it, unless it is the one ranked by) and to
    their own actions replayed open loop ("replayed", cfg.replay), and the simulator's outcomes of
    the actions taken in imagination ("sim_imagined", cfg.replay), over the policies whose name `keep`
    accepts."""
    true, wm, proxy, observed, observed2, replayed, played, picked_of = {}, {}, {}, {}, {}, {}, {}, {}
    # a second judge only where it reads every task: its mean over tasks then means what the others' does
    # ranked by the geometric read-out where it predicts, the ranked one is that read-out and cfg.readout another
    ranked = GEOMETRIC if cfg.geometric_ranks else cfg.readout
    others = {f"readout_{r}": {} for r in readouts_of(results, tasks) if r != ranked}
    for t in tasks:
        names = results[t]["names"]
        loss = {r["name"]: r["val_loss"] for r in rows if r["task"] == t}
        picked = picked_of[t] = [j for j, name in enumerate(names) if keep(name)]
        true[t], wm[t] = results[t]["true"][picked], results[t]["prob"][picked]
        proxy[t] = np.array([math.nan if loss[names[j]] is None else -loss[names[j]] for j in picked])
        observed[t] = results[t]["prob_observed"][picked]
        observed2[t] = results[t][OBSERVED_SECOND][picked]
        replayed[t] = results[t]["prob_replayed"][picked]
        played[t] = results[t]["sim_imagined"][picked]
        for key, got in others.items():
            got[t] = results[t][key][picked]
    predictors = {"world_model": wm, "proxy": proxy, **others}
    second = [] if cfg.readout == SECOND_JUDGE else [(f"on_truth_{SECOND_JUDGE}", observed2)]
    for name, got in (("on_truth", observed), *second, ("replayed", replayed), ("sim_imagined", played)):
        if all(np.isfinite(o).all() for o in got.values()):
            predictors[name] = got
    out = S.within_task(true, predictors, cfg.threshold)
    # a policy whose imagination diverged is left out of the world model's statistics (stats.draw_statistics)
    left_out = {t: [results[t]["names"][j] for j, ok in zip(picked_of[t], S.scored_policies(wm[t])) if not ok]
                for t in tasks}
    if any(left_out.values()):
        out["left_out"] = {t: names for t, names in left_out.items() if names}
    return out


def loop_actions_block(results: dict, tasks, cfg: EvalConfig) -> dict | None:
    """The world model's within-task statistics (experiments.stats.within_task) against the simulator's
    outcomes of the very actions the policies took in its imagination (cfg.replay's sim_imagined)
    instead of the true outcomes: how well it reads its own loop, apart from what acting on imagined
    frames changes; None without them."""
    played = {t: results[t]["sim_imagined"] for t in tasks}
    if not all(np.isfinite(v).all() for v in played.values()):
        return None
    wm = {t: results[t]["prob"] for t in tasks}
    return S.within_task({t: v > 0.5 for t, v in played.items()}, {"world_model": wm}, cfg.threshold)["world_model"]


def decision_analysis(cfg: EvalConfig, tasks: dict, alignment: float, most: int = 30) -> dict:
    """The binomial model's curve per gap, beside resampling the world model's actual outcomes of the
    policy pairs (same task) whose true gap is within 0.05 of it: up to `most` pairs, spread evenly
    over every task's (`pair_tasks` counts them by task)."""
    eps = list(cfg.decision_episodes)
    out = {"alignment": alignment, "episodes": eps, "model": {}, "resampled": {}, "pairs": {}, "pair_tasks": {}}
    for g in cfg.gaps:
        # no alignment where no prediction was read (every imagination diverged): no binomial curve
        out["model"][str(g)] = (S.p_pick_better(min(max(alignment, 0.0), 1.0), g, eps).tolist()
                                if np.isfinite(alignment) else None)
        pairs = []
        for task, res in tasks.items():
            rates = res["true"].mean(1)
            read = np.isfinite(res["prob"]).all(1)  # a policy whose imagination diverged reads no outcome
            # the window's edges in, whatever the rates' float rounding
            pairs += [(task, a, b) for a in range(len(rates)) for b in range(len(rates))
                      if read[a] and read[b] and abs(rates[a] - rates[b] - g) <= 0.05 + 1e-9]
        spread = np.unique(np.linspace(0, len(pairs) - 1, min(most, len(pairs))).round().astype(int))
        chosen = [pairs[i] for i in spread]
        curves = [S.resampled_pick_better(tasks[t]["prob"][a] >= cfg.threshold, tasks[t]["prob"][b] >= cfg.threshold,
                                          eps, draws=500, seed=k) for k, (t, a, b) in enumerate(chosen)]
        out["pairs"][str(g)] = len(curves)
        out["pair_tasks"][str(g)] = dict(Counter(t for t, _, _ in chosen))
        out["resampled"][str(g)] = np.mean(curves, axis=0).tolist() if curves else None
    return out


# ---- compiling ahead -----------------------------------------------------------------------------

EXIT_CUT_SHORT = 3  # the exit status of a run max_minutes stopped before its last task: rerun the same command
WARM_START_WAIT_S = 900.0  # how long `--warm` waits for its world models' training to start


def warm(cfg: EvalConfig, progress: bool = True, wait_s: float = 0.0, after_training: bool = False) -> None:
    """Runs the evaluation's compiled programs once each, so that JAX's persistent compilation cache
    holds them for the evaluation of cfg, which then loads them instead of compiling: on every task,
    each batch of policies of the first slice of states (the evaluation's policies, states and batch
    shapes) for its first WARM_STEPS steps, in the simulator and in each world model (closed loop,
    the read-out of the simulated episodes, and the replay with cfg.replay), and the
    controllability panel. The world models need only have started training (wm.checkpoint.
    load_started: their shapes and normalisation, parameters of zeros), so the warm-up runs beside
    their training; wait_s: how long to wait for each run's config.json and norm.json. Not warmed:
    the episode judge's reading (the judge is fit after training), with cfg.replay the simulation of
    the imagined actions (whole episodes), and on the `mjx` engine the joining of an episode's
    segments (`_recording_of`, a program per episode length; about a second to compile).
    after_training: first the programs that the first world model's training runs once it has
    trained (wm.train.warm_after_training: its judge's fit, eval.json), which it needs sooner. With
    cfg.truth_cache, last, every batch's whole episodes simulated into it (simulate_all; with
    cfg.truth_frames their frames too), so that the evaluation only imagines. Writes nothing but
    the caches."""
    cfg.validate()
    wait_for_files([Path(run) / f for run in cfg.wm_runs for f in ("config.json", "norm.json")], wait_s,
                   f"{', '.join(map(str, cfg.wm_runs))} to start training")
    # which read-out ranks changes no compiled program ("auto" needs the judges, fit after training)
    cfg = dataclasses.replace(cfg, readout=MODEL_READOUTS[0]) if cfg.readout == AUTO else cfg
    sources = resolve(cfg.policies)
    tasks = evaluation_tasks(cfg, sources)
    models = []
    for run in cfg.wm_runs:
        wm_cfg, params, norm = load_started(Path(run))
        models.append((with_imagine(wm_cfg, cfg.imagine), params, norm, None, None))
    t0 = time.perf_counter()
    if after_training:
        train_cfg, train_data = load_run_config(Path(cfg.wm_runs[0]))
        warm_after_training(train_cfg, train_data, models[0][2])
        print(f"the programs after the world model's training ran once in {time.perf_counter() - t0:.0f} s",
              file=sys.stderr)
        jax.clear_caches()  # the evaluation's stage lowers its programs from cleared caches (experiments.pipeline)
    used = seeds_in_use(cfg, sources)
    engine = cfg.engine or default_engine()
    renderer = cached_renderers(models[0][0].model.size, (HEAD_CAMERA,))
    t0 = time.perf_counter()
    for task in tasks:
        seeds = heldout_seeds(task, cfg.episodes, cfg.seed, used)
        s0, s1 = state_slices(cfg, len(seeds))[0]
        reset_keys, rng = reset_keys_of(seeds[s0:s1]), slice_key(cfg, 0)
        first = [b for b in task_batches(cfg, [s for s in sources if s.runs_on(task)], len(seeds)) if b[1] == 0]
        for _, _, _, padded in tqdm(first, desc=f"warm {task}", unit="batch", disable=not progress):
            policy, params = chunk_policy(padded, s1 - s0)
            truth = _simulate(task, policy, params, seeds[s0:s1], reset_keys, rng, engine, renderer, WARM_STEPS)
            _predict_batch(cfg, task, models, policy, params, truth, rng)
    wm_cfg, wm_params, norm, _, _ = models[0]
    wm_data = load_run_config(Path(cfg.wm_runs[0]))[1]
    if (Path(wm_data) / "cache" / "index.json").exists():
        program_panel(wm_cfg, wm_params, norm, TrainingCache(wm_data), horizon=48)
    print(f"the evaluation's programs ran once in {time.perf_counter() - t0:.0f} s ({', '.join(tasks)})",
          file=sys.stderr)
    if cfg.truth_cache:
        t0 = time.perf_counter()
        truth_space(cfg, tasks, sources, wm_cfg.model.size)
        simulate_all(cfg, tasks, sources, used, engine, renderer, progress)
        print(f"the evaluation's episodes simulated into {cfg.truth_cache} in {time.perf_counter() - t0:.0f} s",
              file=sys.stderr)


# ---- the run -----------------------------------------------------------------------------------------

def run(cfg: EvalConfig, out: Path, progress: bool = True, part: tuple[int, int] | None = None,
        partial: bool = False, preset: str = "") -> dict | None:
    """Evaluates (or completes the evaluation of) cfg into out; returns the results. Where
    cfg.max_minutes stops it before the last task, results.json holds the tasks finished, lists the
    others in "missing_tasks" and says so in "cut_short" (rerun the same call to finish). part: (K, N)
    evaluates the K-th of N shares of every task's batches (balance_chunks) and returns None
    (sim_data.parts: one process per GPU; a run without a part merges the shares and gathers
    results.json). partial:
    evaluate nothing more and gather the tasks finished so far (a run cut short); results.json
    lists the others in "missing_tasks". preset: the name of cfg's preset, recorded so that the
    report shows that preset's targets."""
    cfg.validate()
    out = Path(out)
    sources = resolve(cfg.policies)  # the policies and models are checked before OUT records the configuration
    if cfg.geometric and not (Path(cfg.geometric) / EGOMOTION_JSON).exists():
        raise ValueError(f"geometric={cfg.geometric} holds no geometric models (the robot's motion, the fill, the grasp "
                         "rules) ranking the tasks whose success they predict: `make demo` fits the demo's in its train "
                         f"stage (python -m experiments.fill --out {cfg.geometric} ...); or pass geometric= geometric_ranks=0 "
                         "to rank every task by the world model's read-out alone")
    tasks = evaluation_tasks(cfg, sources)
    models = load_models(cfg.wm_runs, cfg.imagine)
    motion = load_motion(Path(cfg.geometric)) if cfg.geometric else None
    grasp = load_grasp(Path(cfg.geometric)) if cfg.geometric else {}
    if motion is not None and motion.size is not None and motion.size != models[0][0].model.size:
        raise ValueError(f"the geometric models in {cfg.geometric} draw {motion.size}-px frames; the world models "
                         f"imagine {models[0][0].model.size}-px ones: train the fill at that size (--size)")
    if cfg.readout == SECOND_JUDGE and (lacking := [r for r, m in zip(cfg.wm_runs, models) if m[4] is None]):
        raise ValueError(f"readout=judge2 ranks by a second episode judge, which {', '.join(lacking)} lacks: train "
                         "with judge2_inputs=... (wm.config.TrainConfig) or choose another read-out")
    if cfg.readout == SECOND_JUDGE and (unknown := sorted({t for m in models for t in tasks if not m[4].knows(t)})):
        raise ValueError(f"readout=judge2: the second episode judge never learned tasks {unknown}, which it would "
                         f"read as nothing; evaluate tasks={','.join(t for t in tasks if t not in unknown)} or choose "
                         "another read-out")
    make_output_dir(out / "tasks")
    prints = _check_config(cfg, out, sources, models)
    try:
        truth_space(cfg, tasks, sources, models[0][0].model.size)
    except ValueError as e:
        # what the cache does not hold is simulated here all the same (the figures do not depend on the
        # cache): an evaluation, unlike the warm-up that fills the cache, goes on, keeping what fits
        print(f"warning: {e}; the evaluation simulates what the cache lacks and keeps only what fits", file=sys.stderr)
    cfg = dataclasses.replace(cfg, readout=auto_readout(cfg.readout, cfg.wm_runs, models))
    wm_data = str(load_run_config(Path(cfg.wm_runs[0]))[1])  # the first model's data: the tasks it saw
    wm_cache = TrainingCache(wm_data) if (Path(wm_data) / "cache" / "index.json").exists() else None
    if unseen := unlearned_tasks(cfg.wm_runs, tasks, wm_cache):
        print(f"warning: the world model never saw tasks {unseen} in training", file=sys.stderr)
    used = seeds_in_use(cfg, sources)
    engine = cfg.engine or default_engine()
    results = evaluate_tasks(cfg, out, tasks, sources, models, used, engine, progress, part, partial, motion, grasp)
    if results is None:
        return None
    if not results:
        raise ValueError(f"{out}: no task is finished yet ({', '.join(tasks)}); run without --partial")
    ruled = geometric_tasks(motion, grasp) if cfg.geometric_ranks else ()
    report = gather(cfg, out, tasks, results, sources, prints, models, wm_data, wm_cache, engine, preset, ruled)
    stopped = not partial and len(results) < len(tasks)
    report["cut_short"] = {"max_minutes": cfg.max_minutes, "tasks_left": report["missing_tasks"]} if stopped else None
    write_json_atomic(out / "results.json", no_nan(report))
    return report


def learned_tasks(runs, wm_cache=None) -> list[str] | None:
    """The tasks every world model of `runs` learned (wm.checkpoint.trained_tasks: its judge's, its
    training's, a bundle's included, whether or not its training data is on this machine); where a
    model names none, those of its first model's training cache (wm_cache); None where neither says."""
    learned = [set(trained_tasks(Path(r))) for r in runs]
    if learned and all(learned):
        return sorted(set.intersection(*learned))
    return list(wm_cache.tasks) if wm_cache is not None else None


def unlearned_tasks(runs, tasks, wm_cache=None) -> list[str]:
    """The tasks of `tasks` some world model of `runs` never learned (learned_tasks; none where nothing
    says what they learned)."""
    known = learned_tasks(runs, wm_cache)
    return [] if known is None else [t for t in tasks if t not in known]


def seeds_in_use(cfg: EvalConfig, sources) -> set:
    """The initial-state seeds the evaluation must not draw: those of the zoo's datasets and of every
    world model's training data (a bundle's copy of its seeds where the data is elsewhere)."""
    zoo_data = {s.record.get("data") for s in sources} - {None}
    return used_seeds(*zoo_data).union(*(training_seeds(Path(r)) for r in cfg.wm_runs))


def evaluation_tasks(cfg: EvalConfig, sources) -> list[str]:
    """The tasks to evaluate: cfg.tasks where named, else those of the zoo's policies, else (plug-ins
    alone, which run on any task) every task that each of cfg's world models learned to judge."""
    tasks = list(cfg.tasks) or sorted({s.task for s in sources if s.task})
    if tasks:
        # a task no policy runs on (a zoo's checkpoints of other tasks, no plug-in) has nothing to evaluate:
        # said here, before anything runs, rather than failing deep inside its batches
        if empty := [t for t in tasks if not any(s.runs_on(t) for s in sources)]:
            trained = sorted({s.task for s in sources if s.task})
            raise ValueError(f"no policy runs on task {', '.join(empty)}: the registry's checkpoints run on the "
                             f"task they were trained for ({', '.join(trained)}) and plug-ins on any; leave "
                             f"{'it' if len(empty) == 1 else 'them'} out of tasks=... or add a plug-in")
        return tasks
    known = [set(trained_tasks(Path(r))) for r in cfg.wm_runs]
    tasks = sorted(set.intersection(*known)) if known else []
    if not tasks:
        raise ValueError("no task to evaluate: the policies are all plug-ins and the world model names none "
                         "it learned; name tasks=...")
    print(f"plug-ins alone: evaluated on the world model's tasks {', '.join(tasks)} (tasks=... to choose)",
          file=sys.stderr)
    return tasks


def evaluate_tasks(cfg: EvalConfig, out: Path, tasks, sources, models, used: set, engine: str, progress: bool,
                   part: tuple[int, int] | None, partial: bool, motion=None, grasp=None) -> dict | None:
    """{task: results (evaluate_task)} of every task evaluated, read back from out/tasks where a
    run before evaluated it (or its parts did, merged here), without those cfg.max_minutes stopped it
    before (see run); None for a part. motion: the geometric models (cfg.geometric) or None; grasp: their
    grasp rules ({task: rule})."""
    results = {}
    by_task = {t: [s for s in sources if s.runs_on(t)] for t in tasks}
    if part is not None and cfg.keep_features:
        raise ValueError("keep_features keeps one run's imaginations: evaluate without --part")
    if part is not None:  # every task's batches spread over the parts, the largest first
        sizes = {(t, k, j): len(padded) * (cfg.state_batch or cfg.episodes) for t in tasks
                 for k, j, _, padded in task_batches(cfg, by_task[t], cfg.episodes)}
        mine = {key for key, k in balance_chunks(sizes, part[1]).items() if k == part[0]}
    t_start, longest = time.perf_counter(), 0.0
    for task in tasks:
        path = out / "tasks" / (f"{task}.npz" if part is None else f"{task}.part{part[0]}of{part[1]}.npz")
        if not path.exists() and part is None and (merged := _merged_parts(cfg, out, task, by_task[task])):
            _save_task(path, merged)
        if part is not None and (out / "tasks" / f"{task}.npz").exists():
            continue  # gathered already
        if path.exists():
            results[task] = load_task(path)
            continue
        if partial:
            continue
        elapsed = time.perf_counter() - t_start
        if cfg.max_minutes and longest and elapsed + longest > 60 * cfg.max_minutes:
            left = [t for t in tasks if not (out / "tasks" / f"{t}.npz").exists()]
            print(f"stopping after {elapsed:.0f} s (max_minutes={cfg.max_minutes:g}): results.json holds the tasks "
                  f"finished; rerun the same command to evaluate {', '.join(left)}", file=sys.stderr)
            break
        t_task = time.perf_counter()
        seeds = heldout_seeds(task, cfg.episodes, cfg.seed, used)
        chunks = None if part is None else {(k, j) for t, k, j in mine if t == task}
        res = evaluate_task(cfg, task, by_task[task], models, seeds, engine, progress, chunks, motion, grasp)
        longest = max(longest, time.perf_counter() - t_task)
        res["seeds"] = seeds
        if "features" in res:
            save_features(out, task, res.pop("features"))
        if "features_observed" in res:
            save_features(out, task, res.pop("features_observed"), observed=True)
        _save_task(path, res)
        results[task] = load_task(path)
    return None if part is not None else results


def gather(cfg: EvalConfig, out: Path, tasks, results: dict, sources, prints: dict, models, wm_data: str, wm_cache,
           engine: str, preset: str, ruled: tuple = ()) -> dict:
    """results.json's contents from the finished tasks' results (the others listed as missing), and
    out/videos.npz. prints: each source's fingerprint (_check_config's); ruled: the tasks ranked by the
    geometric read-out (geometric_tasks' with cfg.geometric_ranks)."""
    # the tasks every model learned (its judge's, else its training's: wm.checkpoint.trained_tasks)
    known = learned_tasks(cfg.wm_runs, wm_cache)
    train_tasks = list(tasks) if known is None else known
    missing = [t for t in tasks if t not in results]
    tasks = [t for t in tasks if t in results]
    by_name = {s.name: s for s in sources}
    rows = [r for task in tasks for r in policy_rows(cfg, task, results[task], by_name)]
    bad = {t: int((~results[t]["sim_finite"]).sum()) for t in tasks if not results[t]["sim_finite"].all()}
    if bad:
        print(f"warning: simulated episodes whose state went non-finite (their true outcome is doubtful; the judge "
              f"on truth is left out): {bad}", file=sys.stderr)
    if unread := S.nonfinite_policies(rows):
        print(f"warning: {unread}", file=sys.stderr)
    seen = seen_policies(cfg.wm_runs, sources, prints)
    for r in rows:
        r["in_wm_data"] = r["name"] in seen
    trained_on_policies = any(training_policies(Path(r)) or training_fingerprints(Path(r)) for r in cfg.wm_runs)
    metrics = all_metrics(cfg, results, tasks, rows, seen, trained_on_policies)
    training = [training_status(Path(r)) for r in cfg.wm_runs]
    wm_cfg, wm_params, norm, judge, _ = models[0]
    panel = program_panel(wm_cfg, wm_params, norm, wm_cache, horizon=48) if wm_cache is not None else {}
    _write_videos(out, results, tasks, panel)
    return {
        "config": json.loads(json.dumps(dataclasses.asdict(cfg))), "preset": preset, "engine": engine,
        "device": device_name(),
        "versions": package_versions(("jax", "flax", "optax", "orbax-checkpoint", "mujoco", "mujoco-mjx", "numpy")),
        "world_model": {"run": cfg.wm, "runs": list(cfg.wm_runs), "data": wm_data,
                        "train_tasks": train_tasks,
                        "training": training, "cut_short": any(t["cut_short"] is not False for t in training),
                        "readout": cfg.readout, "imagine": wm_cfg.model.imagine,
                        # what each judge reads, so that comparisons across runs can tell judges apart
                        "judge_inputs": list(wm_cfg.judge_inputs), "judge2_inputs": list(wm_cfg.judge2_inputs),
                        "rule": {t: READOUT_LABELS[GEOMETRIC] if t in ruled
                                 else READOUT_LABELS["success"] if cfg.readout == "judge" and not
                                 (judge is not None and judge.knows(t)) else READOUT_LABELS[cfg.readout]
                                 for t in tasks},
                        # the tasks ranked by the geometric read-out instead (cfg.geometric_ranks)
                        "geometric_ranks": [t for t in tasks if t in ruled]},
        "tasks": tasks, "missing_tasks": missing, "policies": rows, "metrics": metrics,
        "checkpoint_selection": S.checkpoint_selection(rows),
        # the chosen read-out's, then each read-out's ("by_readout")
        "families": S.family_statistics(rows) | {"by_readout": {
            r: S.family_statistics([dict(x, rate=x["pred_rate_readouts"][r]) for x in rows], "rate", ceiling=False)
            for r in read_readouts(rows)}},
        # which policies carry each task's MMRV (the ranked read-out's rates)
        "rank_violations": S.rank_violations([r for r in rows if np.isfinite(r["pred_rate"])]),
        "decision": decision_analysis(cfg, results, metrics["pooled"]["alignment"]),
        "videos": [v for t in tasks for v in results[t]["video_index"]],
        "controllability": sorted(panel),
        "imagination": {t: fidelity_summary(results[t]) for t in tasks},
        "timing": {t: {"simulate_s": results[t]["sim_s"], "imagine_s": results[t]["wm_s"],
                       "imagine_parts": results[t].get("wm_parts", {}),
                       "episodes": int(results[t]["true"].size), "steps": results[t]["steps"],
                       "nonfinite_sim_episodes": int((~results[t]["sim_finite"]).sum())} for t in tasks},
    }


def seen_policies(wm_runs, sources, prints: dict | None = None) -> set:
    """The names of the policies of `sources` whose own rollouts some world model of wm_runs saw in
    training. Where its data records what each policy computes (registry.fingerprint), by that alone:
    a policy evaluated under another name than its rollouts' is seen, and one that took a trained
    policy's name but computes otherwise (a plug-in revised since its rollouts) is not; where its
    data records no fingerprint (an older dataset), by name. prints: {name: fingerprint} of the
    sources where already computed."""
    prints = prints or {s.name: fingerprint(s) for s in sources}
    seen = set()
    for run in map(Path, wm_runs):
        computed = training_fingerprints(run)
        names = set() if computed else training_policies(run)
        seen |= {s.name for s in sources if prints[s.name] in computed or s.name in names}
    return seen


def all_metrics(cfg: EvalConfig, results: dict, tasks, rows: list[dict], seen: set,
                trained_on_policies: bool) -> dict:
    """results.json's "metrics": the within-task headline, pooled and per task, what each interval
    resamples ("intervals", experiments.stats.INTERVALS) (and with cfg.replay
    loop_actions_block's "loop_actions"); the same for the policies not in `seen` (those whose rollouts
    the world model never saw) where there are three or more of them and it was trained on any policy's, and
    within task for those of them that are not counterfactual families ("unseen_networks_within_task",
    unseen_networks) over the tasks that hold three or more."""
    true_eps, prob_eps, member_eps = _episodes_of(results, tasks, lambda name: True)
    metrics = {"within_task": within_task_block(results, tasks, rows, cfg, lambda name: True),
               "mmrv_floor": S.mmrv_floor({t: results[t]["true"] for t in tasks}),
               "pooled": ranking_block(rows, true_eps, prob_eps, cfg.threshold, member_eps), "per_task": {},
               "intervals": S.INTERVALS}
    if (loop := loop_actions_block(results, tasks, cfg)) is not None:
        metrics["loop_actions"] = loop
    for t in tasks:
        metrics["per_task"][t] = ranking_block([r for r in rows if r["task"] == t], results[t]["true"],
                                               results[t]["prob"], cfg.threshold, results[t]["prob_members"])
    unseen = [r for r in rows if r["name"] not in seen]
    if trained_on_policies and len(unseen) >= 3:  # trained on scripts alone, every row is unseen: the block above
        true_eps, prob_eps, member_eps = _episodes_of(results, tasks, lambda name: name not in seen)
        metrics["unseen"] = ranking_block(unseen, true_eps, prob_eps, cfg.threshold, member_eps)
        # over the tasks that hold an unseen policy (a task with none has nothing to resample)
        some = [t for t in tasks if any(r["task"] == t and r["name"] not in seen for r in rows)]
        metrics["unseen_within_task"] = within_task_block(results, some, rows, cfg,
                                                          lambda name: name not in seen)
        networks = S.unseen_networks(rows, seen)
        held = [t for t in tasks if sum(r["task"] == t and r["name"] in networks for r in rows) >= 3]
        if held:
            metrics["unseen_networks_within_task"] = within_task_block(results, held, rows, cfg,
                                                                       lambda name: name in networks)
    return metrics


def _write_videos(out: Path, results: dict, tasks, panel: dict) -> None:
    """OUT/videos.npz: the kept real and imagined episodes of every task and the controllability panel."""
    videos = {k: v for t in tasks for k, v in results[t]["videos"].items()}
    videos.update({f"controllability/{p}/{kind}": v[kind] for p, v in panel.items() for kind in ("real", "imagined")})
    tmp = out / "videos.tmp.npz"
    np.savez_compressed(tmp, **videos)
    tmp.replace(out / "videos.npz")


def _episodes_of(results: dict, tasks, keep) -> tuple:
    """(true (P', N), prob (P', N), the members' prob (K, P', N)), stacked over tasks, of the policies
    whose name `keep` accepts."""
    picked = [(t, j) for t in tasks for j, name in enumerate(results[t]["names"]) if keep(name)]
    return (np.stack([results[t]["true"][j] for t, j in picked]), np.stack([results[t]["prob"][j] for t, j in picked]),
            np.stack([results[t]["prob_members"][:, j] for t, j in picked], axis=1))


def auto_readout(readout: str, runs, models) -> str:
    """The read-out `readout` names; for "auto", "judge" where every model has a judge and learned
    policies' rollouts in its training data (wm.checkpoint.training_policies), else "progress".
    Measured: a judge fit to imaginations of scripted episodes alone ranked the `full` zoo within
    tasks at 0.27 and 0.10 (two seeds) where the progress head ranked at 0.70 and 0.40; fit also to
    the closed-loop imaginations of three lineages it ranked at 0.84 (docs/results.md)."""
    if readout != AUTO:
        return readout
    with_rollouts = all(m[3] is not None and training_policies(Path(r)) for r, m in zip(runs, models, strict=True))
    return "judge" if with_rollouts else "progress"


def load_models(runs, imagine: str = "") -> list:
    """[(TrainConfig, params, Norm, judge or None, second judge or None)] of world-model run
    directories, checked to draw frames of one size (the simulator renders the first frame once for
    all of them); imagine: their imagination setting (wm.model.ModelConfig.imagine) in place of their
    own, unless empty."""
    models = []
    for run in runs:
        wm_cfg, params, norm = load_trained(Path(run))
        wm_cfg = with_imagine(wm_cfg, imagine)
        judges = [load_judge(Path(run), name) for name in (JUDGE, SECOND_JUDGE)]
        for judge in judges:
            if judge is not None:
                check_features(wm_cfg.model, judge)
        models.append((wm_cfg, params, norm, *judges))
    sizes = {m[0].model.size for m in models}
    if len(sizes) > 1:
        raise ValueError(f"the world models {list(runs)} draw frames of sizes {sorted(sizes)}: an ensemble needs one")
    return models


def _merged_parts(cfg: EvalConfig, out: Path, task: str, sources) -> dict | None:
    """The task's results merged from a complete set of its parts' files (`--part K/N` runs), or None."""
    for n in sorted({int(m.group(1)) for f in (out / "tasks").glob(f"{task}.part*of*.npz")
                     if (m := re.fullmatch(rf"{re.escape(task)}\.part\d+of(\d+)\.npz", f.name))}):
        files = [out / "tasks" / f"{task}.part{k}of{n}.npz" for k in range(n)]
        if all(f.exists() for f in files):
            order = list(dict.fromkeys(s.name for _, _, part, _ in task_batches(cfg, sources, cfg.episodes)
                                       for s in part))
            return merge_task_parts(cfg, [load_task(f) for f in files], order)
    return None


def _features_path(out: Path, task: str, observed: bool) -> Path:
    return Path(out) / "features" / (f"{task}.observed.npy" if observed else f"{task}.npy")


def save_features(out: Path, task: str, features, observed: bool = False) -> None:
    """Writes one task's imagined step features (P, N, T, F) float16 to out/features/<task>.npy, or
    with `observed` those of its simulated episodes (truth_features) to <task>.observed.npy, atomically."""
    path = _features_path(out, task, observed)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}.npy")
    np.save(tmp, np.asarray(features, np.float16))
    os.replace(tmp, path)


def load_features(out: Path, task: str, observed: bool = False) -> np.ndarray:
    """The step features an evaluation kept for task (keep_features=1): (P, N, T, F) float16, of the
    imagined episodes, or with `observed` of the simulated ones (kept where the simulator ran here)."""
    path = _features_path(out, task, observed)
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing: evaluate with keep_features=1 (and without --part"
                                + (", without truth_cache)" if observed else ")"))
    return np.load(path)


def _save_task(path: Path, res: dict) -> None:
    meta = {"names": res["names"], "video_index": res["video_index"], "sim_s": res["sim_s"], "wm_s": res["wm_s"],
            "wm_parts": res.get("wm_parts", {}),
            "steps": res["steps"], "seeds": res["seeds"], **({"slices": res["slices"]} if "slices" in res else {})}
    arrays = {**{k: res[k] for k in POLICY_ARRAYS + ("prob_members",)},
              "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)}
    arrays.update({f"video:{k}": v for k, v in res["videos"].items()})
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)


def load_task(path: Path) -> dict:
    """One finished task's results as evaluate_task returns them (without step features), from out/tasks."""
    with np.load(path) as z:
        meta = json.loads(z["meta"].tobytes().decode())
        videos = {k[len("video:"):]: z[k] for k in z.files if k.startswith("video:")}
        members = z["prob_members"] if "prob_members" in z.files else z["prob"][None]  # before ensembles
        observed, observed2, replayed, played = (
            z[k] if k in z.files else np.full(z["prob"].shape, np.nan)
            for k in ("prob_observed", OBSERVED_SECOND, "prob_replayed", "sim_imagined"))
        finite = z["sim_finite"] if "sim_finite" in z.files else np.ones(z["prob"].shape, bool)
        traces = {k: z[k] if k in z.files else np.zeros(z["prob"].shape + (0,), np.float16) for k in TRACES}
        fidelity = {k: z[k] if k in z.files else
                    np.full(z["prob"].shape + (FIDELITY_MISSING_WIDTH.get(k, 0),), np.nan, np.float32) for k in FIDELITY}
        readouts = {k: z[k] if k in z.files else np.full(z["prob"].shape, np.nan) for k in READOUT_KEYS}
        return {**meta, "true": z["true"].astype(bool), "prob": z["prob"], **readouts,
                **fidelity,
                "prob_observed": observed, OBSERVED_SECOND: observed2, "prob_replayed": replayed, "sim_imagined": played,
                "sim_finite": finite,
                "prob_members": members, **traces, "videos": videos}


FINGERPRINTS = "policy_fingerprints"  # config.json's record of what each policy computed with
WM_FINGERPRINTS = "wm_fingerprints"  # config.json's digests of the world models its results came from


def wm_fingerprint(model) -> str:
    """A digest of what a world model (load_models' (config, params, Norm, judge, second judge))
    computes: a run trained again, or another bundle copied to the same path, changes it."""
    wm_cfg, params, norm, *judges = model
    h = hashlib.sha256(json.dumps(as_json(wm_cfg), sort_keys=True).encode())
    hash_arrays(h, (params, [getattr(norm, f.name) for f in dataclasses.fields(norm)]))
    for k, judge in enumerate(judges):
        if judge is not None:
            h.update(b"judge2" if k else b"")  # the first judge's digest as a model without a second one had
            hash_arrays(h, (judge.params, judge.mean, judge.std, judge.columns))
    return h.hexdigest()[:16]


def _compared(fields: dict) -> dict:
    """An evaluation's config (as_json) as a rerun into its OUT must match it: without what does not
    change its results, the time budget and the truth cache where it keeps the simulated frames (the
    figures are then those of an evaluation without one); a cache without them leaves the frame
    figures out (NaN), which a rerun must match."""
    without_frames = bool(fields.get("truth_cache")) and not fields.get("truth_frames")
    kept = {k: v for k, v in fields.items() if k not in ("max_minutes", "truth_cache", "truth_frames")}
    return kept | {"truth_cache_without_frames": without_frames}


def _check_config(cfg: EvalConfig, out: Path, sources, models=None) -> dict:
    """Records cfg, every policy's fingerprint (its parameters and, for a plug-in, its code) and every
    world model's (wm_fingerprint; with `models`) in out/config.json, or checks a rerun against them:
    results an OUT holds are read back, so they must come from this configuration and these policies
    and world models as they are now. An OUT that holds no results yet (a run that failed before its
    first task was saved) is taken over by the new configuration. Returns {name: fingerprint}."""
    mine = as_json(cfg)
    mine.pop("max_minutes")  # a time budget does not change what is computed
    prints = {s.name: fingerprint(s) for s in sources}
    wm_prints = None if models is None else [wm_fingerprint(m) for m in models]
    path = out / "config.json"
    if path.exists() and (any((out / "tasks").glob("*.npz")) or (out / "results.json").exists()):
        saved = read_json(path)
        theirs = saved.pop(FINGERPRINTS, {})
        their_wm = saved.pop(WM_FINGERPRINTS, None)  # None: an OUT that records none, resumed as it is
        differs = differing_fields(_compared(saved), _compared(mine), _compared(as_json(EvalConfig())))
        if differs:
            raise ValueError(f"{out} holds an evaluation of another configuration (differs: {', '.join(differs)}); "
                             "use another OUT")
        changed = sorted(name for name, digest in theirs.items() if prints.get(name, digest) != digest)
        if changed:
            raise ValueError(f"{out} holds results of {changed} as their code or parameters were then, not as "
                             "they are now; use another OUT")
        if their_wm is not None and wm_prints is not None and their_wm != wm_prints:
            raise ValueError(f"{out} holds results of the world model {cfg.wm} as it was then: what is there now "
                             "differs (trained again, or another bundle copied there); use another OUT")
    else:
        write_json_atomic(path, mine | {FINGERPRINTS: prints}
                          | ({} if wm_prints is None else {WM_FINGERPRINTS: wm_prints}))
    return prints


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=preset_help(PRESETS))
    p.add_argument("--config", default="demo", help=f"preset: {', '.join(PRESETS)}")
    p.add_argument("--out", type=Path, help="the evaluation's directory (required unless --warm)")
    p.add_argument("--warm", action="store_true",
                   help="compile the evaluation's programs into JAX's persistent compilation cache and write nothing "
                        "else (warm), waiting up to 15 minutes for the world models' training to start: beside "
                        "their training, so that the evaluation loads its programs instead of compiling them")
    p.add_argument("--warm-after-training", action="store_true",
                   help="with --warm: first the programs the first world model's training runs once it has "
                        "trained (its episode judge's fit, eval.json)")
    add_part_argument(p, "evaluate this part's share of every task's batches", "gather results.json")
    p.add_argument("--partial", action="store_true",
                   help="evaluate nothing more: results.json over the tasks finished so far (a run cut short)")
    p.add_argument("overrides", nargs="*", help="key=value overrides (e.g. episodes=50 policies=DIR,mod:attr)")
    a = p.parse_intermixed_args(argv)  # key=value overrides before or after the options
    cfg, part = config_and_part(p, a, make_config)
    t0 = time.perf_counter()
    if a.partial and part is not None:
        p.error("--partial gathers; it takes no --part")
    if a.warm_after_training and not a.warm:
        p.error("--warm-after-training goes with --warm")
    if a.warm:
        if part is not None or a.partial:
            p.error("--warm compiles for one process's whole evaluation: leave out --part and --partial")
        warm(cfg, wait_s=WARM_START_WAIT_S, after_training=a.warm_after_training)
        return 0
    if a.out is None:
        p.error("--out is required (unless --warm)")
    res = run(cfg, a.out, part=part, partial=a.partial, preset=a.config)
    if res is None:
        return 0  # a part: the run without --part gathers
    w = res["metrics"]["within_task"]
    print(json.dumps(no_nan({"within_task_mean": {who: {k: [w[who]["mean"][k], w[who]["mean_ci"][k]]
                                                        for k in S.WITHIN_TASK}
                                                  for who in ("world_model", "proxy")}}), indent=1))
    # where parts simulated and imagined in other processes (the pipeline's eval stage), this one only gathered
    print(f"{S.policy_count(res['policies'])}; {time.perf_counter() - t0:.0f} s in this process; "
          f"results {a.out / 'results.json'}")
    if res["cut_short"]:
        print(f"cut short by max_minutes={cfg.max_minutes:g} before tasks {', '.join(res['cut_short']['tasks_left'])}: "
              f"exit status {EXIT_CUT_SHORT}; rerun the same command to finish", file=sys.stderr)
        return EXIT_CUT_SHORT
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
