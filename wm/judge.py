"""The episode judge: an imagined episode's success, read from everything the world model imagined
over the whole episode.

The dynamics' per-step success head reads only the last K imagined frames. On the simulator's own
frames it is good (teacher-forced), but over a long imagined episode the frames drift and blur, and
a task's success may depend on more than K frames show (stepping back half a metre is a sum of
velocities). The judge is a small network over the sequence of `wm.imagine.step_features` (predicted
proprioception, actions, pooled latents, a model with the scene head's predicted scene state, the
per-step success and outcome probabilities) and the task's name, pooled over time (mean, max, first,
last): the mean integrates what the proprioception says about the body's motion, the max keeps a
success reached and lost. It is trained on the world
model's own imaginations of the training episodes from their first frame (as the evaluator starts),
labelled with the simulator's outcome: open loop under their logged actions, and, for the rollouts
of learned policies in the data, closed loop with that policy acting on the imagined frames
(exactly what the evaluator imagines). So it learns what success looks like in imagination rather
than in the simulator's frames. The parameters best on the validation episodes' imaginations are
kept, or with TrainConfig.judge_select "last" those of the last step. With several members
(TrainConfig.judge_members) as many judges are fit from as many seeds and read as the mean of their
probabilities: fit to a few hundred episodes a judge is kept within its first validations, and one
judge's ranking then follows its seed.

Written to `OUT/judge.json` (configuration, feature standardisation, tasks, fit metrics) and
`OUT/judge.msgpack` (parameters, stacked over the members) by `wm.train` after training;
`load_judge(OUT)` reads them back.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import json
import os
import sys
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization
from tqdm import tqdm

from sim_data.policies.bc import stacked
from sim_data.policies.registry import applied_policy, policy_chunks, resolve, stack_key
from sim_data.policies.scripted import simulate_actions
from sim_data.sim.engines import default_engine
from sim_data.sim.robot import ACTION_DIM
from sim_data.util import even_pieces, pad_with_last, write_json_atomic
from wm.checkpoint import JUDGE, SECOND_JUDGE, run_file
from wm.config import JUDGE_LR, KEPT_STEPS
from wm.imagine import (
    SEGMENT,
    Norm,
    chunk_size,
    closed_loop,
    context_sample,
    feature_columns,
    feature_dim,
    observed_features,
    open_loop_chunked,
    padded_chunks,
)
from wm.metrics import accuracy, auroc
from wm.model import ModelConfig

WIDTH = 64
WEIGHT_DECAY = 0.05
BATCH = 256


class JudgeNet(nn.Module):
    """(B, T, F) standardised step features, (B, T) bool mask, (B,) int task -> (B,) success logits.
    Each step's features pass a per-step network, pooled over time (mean, max, first, last); with
    raw_mean the mean of the features themselves joins them: a sum over time of what a step says (the
    base's commanded speed, its measured velocity) is how far the body went, at any speed, where the
    mean of a nonlinear per-step network holds that only at the speeds it was fit to."""

    n_tasks: int
    width: int = WIDTH
    raw_mean: bool = False

    @nn.compact
    def __call__(self, x, mask, task):
        h = nn.gelu(nn.Dense(self.width)(x))
        h = nn.gelu(nn.Dense(self.width)(h))
        m = mask[..., None].astype(h.dtype)
        n = jnp.maximum(m.sum(axis=1), 1.0)
        mean = (h * m).sum(axis=1) / n
        top = jnp.where(m > 0, h, -1e9).max(axis=1)
        last = jnp.take_along_axis(h, (n[:, 0].astype(jnp.int32) - 1)[:, None, None], axis=1)[:, 0]
        pooled = [mean, top, h[:, 0], last] + ([(x * m).sum(axis=1) / n] if self.raw_mean else [])
        y = jnp.concatenate(pooled + [nn.Embed(self.n_tasks, self.width)(task)], axis=-1)
        return nn.Dense(1)(nn.gelu(nn.Dense(self.width)(y)))[..., 0]


@dataclasses.dataclass(frozen=True)
class EpisodeJudge:
    """A fitted judge: the parameters of its members stacked on a leading axis (M judges fit from M
    seeds, read as the mean of their probabilities; M = 1 for one), the step features it reads
    (`columns` (K,) int of the F that wm.imagine.step_features makes, `feature_dim` F), their
    standardisation (K,), the tasks it knows (in embedding order), whether it pools the features'
    own mean (JudgeNet.raw_mean)."""

    params: dict
    mean: np.ndarray
    std: np.ndarray
    tasks: tuple
    columns: np.ndarray
    feature_dim: int
    raw_mean: bool = False

    @property
    def members(self) -> int:
        return int(jax.tree_util.tree_leaves(self.params)[0].shape[0])

    def knows(self, task: str) -> bool:
        return task in self.tasks

    def probability(self, features, task: str, mask=None) -> np.ndarray:
        """features (B, T, F) of imagined episodes of `task` (mask (B, T) bool, default all steps)
        -> (B,) predicted probability of success (the mean of the members')."""
        if task not in self.tasks:
            raise ValueError(f"the judge was trained on tasks {list(self.tasks)}, not {task!r}")
        x = np.asarray(features, np.float32)
        if x.shape[-1] != self.feature_dim:
            raise ValueError(f"the judge reads step features of {self.feature_dim} columns, got {x.shape[-1]}")
        x = x[..., self.columns]
        mask = np.ones(x.shape[:2], bool) if mask is None else mask
        ids = np.full(x.shape[0], self.tasks.index(task), np.int32)
        return np.asarray(_probability(len(self.tasks), self.raw_mean, self.params, (x - self.mean) / self.std, mask,
                                       ids))


@functools.partial(jax.jit, static_argnums=(0, 1))
def _probability(n_tasks, raw_mean, params, x, mask, task):
    def member(p):
        return jax.nn.sigmoid(JudgeNet(n_tasks, raw_mean=raw_mean).apply({"params": p}, x, mask, task))
    if jax.tree_util.tree_leaves(params)[0].shape[0] == 1:  # one judge: its own program, not a batch of one
        return member(jax.tree_util.tree_map(lambda p: p[0], params))
    return jax.vmap(member)(params).mean(axis=0)


# ---- imagined episodes -----------------------------------------------------------------------------

def imagine_episodes(cfg: ModelConfig, params, norm: Norm, cache, ids: list[int], camera: str,
                     progress: bool = True, policies: dict | None = None, seed: int = 0) -> dict:
    """Imaginations of whole episodes from their first observation: open loop under their logged
    actions, or, for an episode of a policy in `policies` ({cache policy name: PolicySource}, see
    dataset_policies), closed loop with that policy acting on the imagined frames, as the evaluator
    runs it.

    Returns {"features": (N, T, F) float32 (padded to the longest), "mask": (N, T) bool, "task": [N] str,
    "label": (N,) bool the simulator's outcome}, in the order of ids.
    """
    pieces = []  # (cache ids, (len(ids), T, F) features) of each group
    bar = tqdm(total=len(ids), desc="judge: imagine", unit="ep", disable=not progress)
    for (n, key), group in _imagination_groups(cache, ids, policies).items():
        policy = None if key is None else key[0]
        if policy is None:
            samples = [context_sample(cache.episode(i, cameras=[camera]), camera, 0, 1, n - 1) for i, _ in group]
            x = open_loop_chunked(cfg, params, norm, samples, n - 1, ("features",))["features"]
        else:
            x = _closed_loop_features(cfg, params, norm, cache, group, camera, n - 1, policy, seed)
        pieces.append(([i for i, _ in group], x))
        bar.update(len(group))
    bar.close()
    return _episodes_in_order(cache, ids, pieces)


def _imagination_groups(cache, ids: list[int], policies: dict | None) -> dict:
    """{(episode length, the policy's stack_key or None for open loop): [(cache id, PolicySource or
    None)]}: the episodes of ids that imagine_episodes imagines together, in order of first appearance."""
    groups: dict = {}
    for i in ids:
        e = cache.episodes[i]
        src = (policies or {}).get(e["policy"])
        groups.setdefault((e["length"], None if src is None else stack_key(src)), []).append((i, src))
    return groups


def warm_imagination(cfg: ModelConfig, params, norm: Norm, cache, ids: list[int], camera: str,
                     policies: dict | None = None, seed: int = 0) -> None:
    """Runs the compiled programs of imagine_episodes(cfg, params, norm, cache, ids, camera, policies=
    policies) once each, so that JAX's persistent compilation cache holds them for it: each group's
    first chunk (the same batch, hence the same programs) for one segment of steps (every horizon
    shares the segments' programs). Returns nothing."""
    for (n, key), group in _imagination_groups(cache, ids, policies).items():
        horizon = min(n - 1, SEGMENT)
        if key is None:
            first = group[:chunk_size(len(group))]
            open_loop_chunked(cfg, params, norm, [context_sample(cache.episode(i, cameras=[camera]), camera, 0, 1,
                                                                 horizon) for i, _ in first], horizon, ("features",))
        else:
            chunk = chunk_size(len(group))
            slots, width = checkpoint_rows(group, chunk)
            _, part = next(iter(policy_chunks(slots, width, chunk)))
            _closed_loop_part(cfg, params, norm, cache, part, camera, horizon, key[0], jax.random.PRNGKey(seed))


def _episodes_in_order(cache, ids: list[int], pieces: list) -> dict:
    """imagine_episodes' dict from features computed by group, pieces [(cache ids, (n, T_g, F))]:
    each padded to the longest T_g and masked, the rows put back in the order of ids."""
    t_max = max(x.shape[1] for _, x in pieces)
    order = [i for group, _ in pieces for i in group]
    row_of = {i: k for k, i in enumerate(order)}
    back = np.array([row_of[i] for i in ids])
    feats = np.concatenate([np.pad(np.asarray(x, np.float32), ((0, 0), (0, t_max - x.shape[1]), (0, 0)))
                            for _, x in pieces])
    masks = np.concatenate([np.arange(t_max)[None].repeat(len(x), 0) < x.shape[1] for _, x in pieces])
    return {"features": feats[back], "mask": masks[back], "task": [cache.episodes[i]["task"] for i in ids],
            "label": np.array([cache.episodes[i]["success"] for i in ids], bool)}


def _closed_loop_features(cfg: ModelConfig, params, norm: Norm, cache, group, camera: str, horizon: int, policy,
                          seed: int):
    """(len(group), horizon, F) step features of closed-loop imaginations, each episode of group
    [(cache id, PolicySource)] with its own policy's parameters (one architecture). A checkpoint's
    episodes run side by side as one slot of a StackedPolicy (checkpoint_rows), so that a batch holds
    a few parameter sets, not one per episode (a policy that stacks in turn runs its sets one after
    another each step)."""
    chunk = chunk_size(len(group))
    slots, width = checkpoint_rows(group, chunk)
    feats = {}
    for k, (_, part) in enumerate(policy_chunks(slots, width, chunk)):
        rows, x = _closed_loop_part(cfg, params, norm, cache, part, camera, horizon, policy,
                                    jax.random.PRNGKey(seed + k))
        for row, i in enumerate(rows):
            feats.setdefault(i, x[row])  # a padding copy comes after its episode's own row
    return np.stack([feats[i] for i, _ in group])


def _closed_loop_part(cfg: ModelConfig, params, norm: Norm, cache, part, camera: str, horizon: int, policy, rng):
    """One batch of _closed_loop_features: part [(PolicySource, cache ids)] (a slot each) as (rows, the
    rows' (len(rows), horizon, F) step features), rows the cache ids slot after slot."""
    rows = [i for _, ids in part for i in ids]
    eps = {i: cache.episode(i, cameras=[camera]) for i in dict.fromkeys(rows)}  # a padding row reads none
    stacked_policy, policy_params = stacked(policy, [src.params for src, _ in part])
    got = closed_loop(cfg, applied_policy(stacked_policy), horizon, params, norm, policy_params,
                      np.stack([eps[i]["frames"][camera][:1] for i in rows]),
                      np.stack([eps[i]["proprio"][:1] for i in rows]),
                      np.zeros((len(rows), 0, cfg.action_dim), np.float32), rng)
    return rows, np.asarray(got["features"])


def checkpoint_rows(group, most: int) -> tuple[list, int]:
    """group [(cache id, PolicySource)] as ([(source, cache ids)], width): a slot per checkpoint in
    order of first appearance, one of more than `most` episodes cut into even slots of at most `most`,
    each slot padded to `width` ids (the most of any slot) by repeating its last. Checkpoints of very
    unequal counts pad the smaller ones far (the datasets' rollouts give each the same count)."""
    by_source: dict = {}
    for i, src in group:
        by_source.setdefault(src.name, (src, []))[1].append(i)
    slots = [(src, piece) for src, ids in by_source.values() for piece in even_pieces(ids, most)[0]]
    width = max(len(ids) for _, ids in slots)
    return [(src, pad_with_last(ids, width)) for src, ids in slots], width


def observe_episodes(cfg: ModelConfig, params, norm: Norm, cache, ids: list[int], camera: str,
                     progress: bool = True) -> dict:
    """The true episodes themselves as the judge would read them were imagination exact
    (wm.imagine.observed_features: each true frame encoded, the heads given the true context), as
    imagine_episodes' dict in the order of ids: {"features": (N, T, F) float32 (padded to the
    longest), "mask": (N, T) bool, "task": [N] str, "label": (N,) bool}."""
    groups: dict = {}
    for i in ids:
        groups.setdefault(cache.episodes[i]["length"], []).append(i)
    pieces = []
    bar = tqdm(total=len(ids), desc="judge: observe", unit="ep", disable=not progress)
    for group in groups.values():
        for _, part, k in padded_chunks(group):
            eps = [cache.episode(i, cameras=[camera]) for i in part]
            x = observed_features(cfg, params, norm, np.stack([ep["frames"][camera] for ep in eps]),
                                  np.stack([ep["proprio"] for ep in eps]), np.stack([ep["action"][:-1] for ep in eps]))
            pieces.append((part[:k], np.asarray(x)[:k]))
            bar.update(k)
    bar.close()
    return _episodes_in_order(cache, ids, pieces)


def join_episodes(a: dict, b: dict) -> dict:
    """Two imagine_episodes dicts as one, a's episodes first, padded to the longer; keys both hold."""
    t = max(a["features"].shape[1], b["features"].shape[1])

    def pad(x):
        return np.pad(x, ((0, 0), (0, t - x.shape[1])) + ((0, 0),) * (x.ndim - 2))

    out = {"features": np.concatenate([pad(a["features"]), pad(b["features"])]),
           "mask": np.concatenate([pad(a["mask"]), pad(b["mask"])]), "task": list(a["task"]) + list(b["task"])}
    return out | {k: np.concatenate([a[k], b[k]]) for k in a.keys() & b.keys() - out.keys()}


def dataset_policies(data: Path) -> dict:
    """{cache policy name: PolicySource} of the learned policies and plug-ins whose rollouts the dataset
    in `data` holds (its configuration's policy specs); {} when none, or when they cannot be loaded
    (their episodes are then imagined open loop)."""
    specs = json.loads((Path(data) / "config.json").read_text()).get("policies") or []
    if not specs:
        return {}
    try:
        return {f"{s.kind}:{s.name}": s for s in resolve(specs)}
    except (FileNotFoundError, ValueError, ImportError, RuntimeError) as e:  # RuntimeError: a plug-in that
        # fails without the simulator's task state (the world model gives none), or whose factory raises
        print(f"warning: the policies of {data} cannot be loaded ({e}); the judge imagines their episodes open loop",
              file=sys.stderr)
        return {}


# ---- fitting ---------------------------------------------------------------------------------------

def _standardisation(x, mask):
    v = x[mask]
    return v.mean(0), np.maximum(v.std(0), 1e-3)


def fit(train: dict, val: dict | None, tasks: tuple, steps: int, seed: int = 0,
        progress: bool = True, columns=None, lr: float = JUDGE_LR, members: int = 1,
        select: str = "best", raw_mean: bool = False) -> tuple[EpisodeJudge, dict]:
    """Fits a judge to imagined episodes (imagine_episodes' dicts), reading the step features'
    `columns` (default all; wm.imagine.feature_columns), with AdamW at learning rate lr: `members`
    judges from seeds seed, seed + 1, ... (the initialisation and the batches), each kept at its best
    step on val's loss (select "best" with val given) or at its last step (select "last", or no val),
    read as the mean of their probabilities; raw_mean: JudgeNet's. A judge of a few hundred episodes
    overfits them within its first validations, so one judge's ranking follows its seed; the mean of
    several does less.
    Returns the judge and its fit metrics (the ensemble's accuracy and AUROC on train and val; each
    member's kept step)."""
    if len(set(train["label"].tolist())) < 2:
        raise ValueError("the judge needs successes and failures among its training episodes")
    if members < 1:
        raise ValueError(f"a judge has at least one member, got members={members}")
    if select not in KEPT_STEPS:
        raise ValueError(f"a judge keeps its best or its last step, got select={select!r}")
    dim = train["features"].shape[-1]
    columns = np.arange(dim) if columns is None else np.asarray(columns)
    mean, std = _standardisation(train["features"][..., columns], train["mask"])

    def arrays(d):
        return ((d["features"][..., columns] - mean) / std, d["mask"],
                np.array([tasks.index(t) for t in d["task"]], np.int32), d["label"].astype(np.float32))

    # on the device once: a step gathers its batch there (_rows), not on the host and across to the device
    tr = jax.device_put(arrays(train))
    va = jax.device_put(arrays(val)) if val is not None and len(val["label"]) else None
    fits = [_fit_one(tr, va if select == "best" else None, (len(tasks), raw_mean), steps, seed + k, progress, lr)
            for k in range(members)]
    judge = EpisodeJudge(params=jax.tree_util.tree_map(lambda *p: np.stack(p), *[p for p, _ in fits]), mean=mean,
                         std=std, tasks=tuple(tasks), columns=columns, feature_dim=dim, raw_mean=raw_mean)
    metrics = {"episodes_train": len(train["label"]), "steps": steps, "members": members, "lr": lr, "select": select,
               "raw_mean": raw_mean,
               "kept_step": [k for _, k in fits] if members > 1 else fits[0][1]}
    for tag, d in (("train", train), ("val", val)):
        if d is None or not len(d["label"]):
            continue
        p = judge_episodes(judge, d)
        metrics.update({f"{tag}_episodes": len(p), f"{tag}_accuracy": accuracy(p, d["label"]),
                        f"{tag}_auroc": auroc(p, d["label"])})
    return judge, metrics


def _fit_one(tr: tuple, va: tuple | None, net: tuple, steps: int, seed: int, progress: bool,
             lr: float) -> tuple[dict, int]:
    """One member of fit's judge on its standardised (features, mask, task ids, labels) of the training
    and validation episodes, device arrays: (its kept parameters, its kept step). net: JudgeNet's
    (n_tasks, raw_mean)."""
    params = _judge_net(net).init(jax.random.PRNGKey(seed), *tr[:3])["params"]
    state, rng = _optimizer(lr).init(params), np.random.default_rng(seed)
    best, best_loss, best_step = params, np.inf, steps
    n = len(tr[3])
    for k in tqdm(range(1, steps + 1), desc="judge: fit", unit="step", disable=not progress):
        batch = _rows(tr, rng.choice(n, BATCH, replace=True)) if n > BATCH else tr
        params, state, _ = _update(net, lr, params, state, *batch)
        if va is not None and (k % 25 == 0 or k == steps):
            v = float(_loss(net, params, *va))
            if v < best_loss:
                best, best_loss, best_step = params, v, k
    return jax.tree_util.tree_map(np.asarray, jax.device_get(best if va is not None else params)), best_step


def _optimizer(lr: float = JUDGE_LR):
    return optax.adamw(lr, weight_decay=WEIGHT_DECAY)


# module-level programs (the network's task count and pooling, and the learning rate static): every fit
# of the same shapes, in this process or another through the persistent compilation cache, runs the same two
def _judge_net(net: tuple) -> JudgeNet:
    """The JudgeNet of (n_tasks, raw_mean), the static key of the fit's programs."""
    return JudgeNet(net[0], raw_mean=net[1])


def _judge_loss(net: tuple, p, x, m, t, y):
    return optax.sigmoid_binary_cross_entropy(_judge_net(net).apply({"params": p}, x, m, t), y).mean()


_loss = jax.jit(_judge_loss, static_argnums=(0,))


@jax.jit
def _rows(arrays: tuple, idx):
    """The rows idx (B,) of each of arrays (leading axis N): a batch gathered where the arrays are."""
    return tuple(jnp.take(a, idx, axis=0) for a in arrays)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _update(net: tuple, lr: float, p, o, x, m, t, y):
    loss, g = jax.value_and_grad(_judge_loss, argnums=1)(net, p, x, m, t, y)
    u, o = _optimizer(lr).update(g, o, p)
    return optax.apply_updates(p, u), o, loss


def judge_episodes(judge: EpisodeJudge, d: dict) -> np.ndarray:
    """(N,) the judge's probabilities for imagine_episodes' dict d (episodes of several tasks)."""
    p = np.zeros(len(d["label"]))
    tasks = np.array(d["task"])
    for t in sorted(set(d["task"])):
        rows = np.flatnonzero(tasks == t)
        p[rows] = judge.probability(d["features"][rows], t, d["mask"][rows])
    return p


REPLAY_BATCH = 1024  # the most imagined action sequences the simulator replays at once (replayed_labels)


def closed_loop_rows(cache, ids: list[int], policies: dict) -> np.ndarray:
    """(len(ids),) bool: which cache episodes imagine_episodes imagines closed loop, those of a policy
    in `policies` (dataset_policies)."""
    return np.array([cache.episodes[i]["policy"] in policies for i in ids], bool)


def replay_batch(cache, splits) -> int:
    """The batch replayed_labels replays every split in: the most closed-loop rows any task has in any
    of splits [(cache ids, closed (N,) bool)], at most REPLAY_BATCH. One batch size, so that the
    simulator's rollout compiles once for every task and split."""
    counts = [collections.Counter(cache.episodes[i]["task"] for k, i in enumerate(ids) if closed[k])
              for ids, closed in splits]
    return max(1, min(REPLAY_BATCH, max((n for c in counts for n in c.values()), default=1)))


def replayed_labels(model_cfg, norm: Norm, cache, ids: list[int], d: dict, closed, engine: str,
                    batch: int = REPLAY_BATCH) -> np.ndarray:
    """(N,) bool: the labels of d (imagine_episodes' dict of the cache episodes ids) with each row
    where `closed` ((N,) bool: imagined closed loop) replaced by the simulator's outcome of the actions
    its policy took in imagination (the step features' action columns, unstandardised by norm),
    played open loop from the episode's initial state (PRNGKey of its seed) on `engine`, `batch` rows
    at a time (the last batch of a task padded with its last row): what the imagined actions truly
    achieve, where the rollout's own label is what the policy achieved acting on true frames."""
    label = np.array(d["label"], bool)
    cols = feature_columns(model_cfg, ("action",))
    mean, std = np.asarray(norm.action_mean), np.asarray(norm.action_std)
    for task in sorted({cache.episodes[i]["task"] for i in ids}):
        rows = [k for k, i in enumerate(ids) if closed[k] and cache.episodes[i]["task"] == task]
        if not rows:
            continue
        steps = int(np.asarray(d["mask"][rows[0]]).sum())
        for piece in (rows[k:k + batch] for k in range(0, len(rows), batch)):
            padded = pad_with_last(piece, batch)
            actions = np.asarray(d["features"][padded, :steps])[..., cols] * std + mean
            keys = np.stack([np.asarray(jax.random.PRNGKey(int(cache.episodes[ids[k]]["seed"]))) for k in padded])
            label[piece] = simulate_actions(task, actions, keys, engine)[0][: len(piece)]
    return label


def warm_replay(cache, splits, engine: str) -> None:
    """Runs the simulator's programs of replayed_labels over splits [(cache ids, closed (N,) bool)] once
    each (per task with closed-loop rows: whole episodes of zero actions, replay_batch's batch), so that
    JAX's persistent compilation cache holds them for the fit's own replay."""
    batch, first = replay_batch(cache, splits), {}
    for ids, closed in splits:
        for k in np.flatnonzero(closed):
            first.setdefault(cache.episodes[ids[k]]["task"], cache.episodes[ids[k]])
    for task, ep in sorted(first.items()):
        keys = np.stack([np.asarray(jax.random.PRNGKey(int(ep["seed"])))] * batch)
        simulate_actions(task, np.zeros((batch, int(ep["length"]) - 1, ACTION_DIM), np.float32), keys, engine)


# enough to pick the judge's step; more only costs imagination when the judge learns from every episode
VAL_EPISODES = 256


def fit_judge(cfg, params, norm: Norm, cache, train_ids: list[int], out: Path, progress: bool = True) -> dict:
    """Imagines cfg.judge_episodes training episodes (and a quarter as many validation episodes, at most
    VAL_EPISODES), fits the judge and saves it in out; returns its metrics. cfg is the world model's
    TrainConfig; with cfg.judge_observed the judge learns from the training episodes' true frames
    too (observe_episodes), and is still kept at its best on the validation episodes' imaginations;
    with cfg.judge_labels "replayed" the closed-loop imaginations of the rollouts are labelled by what
    their imagined actions achieve in the simulator (replayed_labels). With cfg.judge2_inputs a second
    judge is fit on the same episodes and labels, reading those features (saved as judge2.*; its
    metrics under "judge2" in the returned dict)."""
    tasks, train_ids, val_ids = judge_split(cfg, cache, train_ids)
    labels = {bool(cache.episodes[i]["success"]) for i in train_ids}
    if len(labels) < 2:
        what = "successes" if labels == {True} else "failures"
        print(f"warning: the judge's {len(train_ids)} training episodes are all {what}; no judge (the per-step "
              "rule decides)", file=sys.stderr)
        return {"skipped": "one outcome only among the training episodes"}
    # the policies' own rollouts are imagined closed loop, as the evaluator imagines every policy
    pols = dataset_policies(cache.root.parent)
    train = imagine_episodes(cfg.model, params, norm, cache, train_ids, cfg.camera, progress, pols, cfg.seed)
    if cfg.judge_observed:  # the same episodes read from their true frames too
        train = join_episodes(train, observe_episodes(cfg.model, params, norm, cache, train_ids, cfg.camera, progress))
    val = imagine_episodes(cfg.model, params, norm, cache, val_ids, cfg.camera, progress, pols, cfg.seed + 1) \
        if val_ids else None
    relabelled = {}
    if cfg.judge_labels == "replayed":
        splits = {name: (d, ids, closed_loop_rows(cache, ids, pols))
                  for name, d, ids in (("train", train, train_ids), ("val", val, val_ids)) if d is not None}
        batch, engine = replay_batch(cache, [(ids, closed) for _, ids, closed in splits.values()]), default_engine()
        for name, (d, ids, closed) in splits.items():
            # replayed_labels reads the rows of ids alone: the true readings joined after them keep their labels
            label = replayed_labels(cfg.model, norm, cache, ids, d, closed, engine, batch)
            relabelled[name] = {"closed_loop": int(closed.sum()), "changed": int((label != d["label"]).sum())}
            d["label"] = label
        print(f"judge: labels replayed; {relabelled}", file=sys.stderr)
    labelled = {"labels": cfg.judge_labels, **({"relabelled": relabelled} if relabelled else {})}
    out_metrics = {}
    for name, inputs in judge_inputs(cfg).items():
        steps = (cfg.judge2_steps or cfg.judge_steps) if name == SECOND_JUDGE else cfg.judge_steps
        judge, metrics = fit(train, val, tasks, steps, cfg.seed, progress,
                             feature_columns(cfg.model, inputs), cfg.judge_lr, cfg.judge_members,
                             cfg.judge_select, cfg.judge_raw_mean)
        out_metrics[name] = {**metrics, "inputs": list(inputs), **labelled}
        save_judge(judge, out_metrics[name], Path(out), name)
    second = {SECOND_JUDGE: out_metrics[SECOND_JUDGE]} if SECOND_JUDGE in out_metrics else {}
    return out_metrics[JUDGE] | second


def judge_inputs(cfg) -> dict:
    """{file stem: feature groups} of the judges fit_judge fits for TrainConfig cfg: the judge, and the
    second judge where cfg.judge2_inputs names one."""
    return {JUDGE: cfg.judge_inputs, **({SECOND_JUDGE: cfg.judge2_inputs} if cfg.judge2_inputs else {})}


def judges_fit(cfg, out: Path) -> bool:
    """Whether every judge fit_judge fits for cfg is saved in the run directory out."""
    return all((Path(out) / f"{name}.json").exists() for name in judge_inputs(cfg))


def judge_split(cfg, cache, train_ids: list[int]) -> tuple[tuple, list[int], list[int]]:
    """(tasks, training episodes, validation episodes) of fit_judge from the world model's training
    episodes: cfg.judge_episodes of them spread evenly, and a quarter as many of the validation
    split's of the same tasks (at most VAL_EPISODES)."""
    tasks = tuple(sorted({cache.episodes[i]["task"] for i in train_ids}))
    val_ids = spread([i for i in cache.select("val") if cache.episodes[i]["task"] in tasks],
                     max(1, min(cfg.judge_episodes // 4, VAL_EPISODES)))
    return tasks, spread(train_ids, cfg.judge_episodes), val_ids


def warm_judge(cfg, params, norm: Norm, cache, train_ids: list[int]) -> EpisodeJudge | None:
    """Runs the compiled programs of fit_judge(cfg, params, norm, cache, train_ids, ...) once each (its
    imaginations' by warm_imagination, with judge_labels "replayed" its simulator's by warm_replay,
    each judge's fit (the second's too, with cfg.judge2_inputs) for two steps on episodes of placeholder
    features of the imaginations' shapes), so that JAX's persistent compilation cache holds them for
    the run's own fit_judge. Not warmed: with
    cfg.judge_observed, the reading of the true episodes. Returns the placeholder judge (for warming
    what reads a judge), None where fit_judge would fit none."""
    tasks, train_ids, val_ids = judge_split(cfg, cache, train_ids)
    if len({bool(cache.episodes[i]["success"]) for i in train_ids}) < 2:
        return None
    pols = dataset_policies(cache.root.parent)
    warm_imagination(cfg.model, params, norm, cache, train_ids, cfg.camera, pols, cfg.seed)
    if val_ids:
        warm_imagination(cfg.model, params, norm, cache, val_ids, cfg.camera, pols, cfg.seed + 1)
    if cfg.judge_labels == "replayed":
        warm_replay(cache, [(ids, closed_loop_rows(cache, ids, pols)) for ids in (train_ids, val_ids) if ids],
                    default_engine())
    dim = feature_dim(cfg.model)
    train = _placeholder_episodes(cache, train_ids, dim)
    val = _placeholder_episodes(cache, val_ids, dim) if val_ids else None
    judges = [fit(train, val, tasks, 2, cfg.seed, False, feature_columns(cfg.model, inputs), cfg.judge_lr,
                  cfg.judge_members, cfg.judge_select, cfg.judge_raw_mean)[0] for inputs in judge_inputs(cfg).values()]
    return judges[0]


def _placeholder_episodes(cache, ids: list[int], dim: int) -> dict:
    """imagine_episodes' dict of ids with its shapes, masks, tasks and labels, its features zeros."""
    steps = np.array([cache.episodes[i]["length"] - 1 for i in ids])
    t = int(steps.max())
    return {"features": np.zeros((len(ids), t, dim), np.float32), "mask": np.arange(t)[None] < steps[:, None],
            "task": [cache.episodes[i]["task"] for i in ids],
            "label": np.array([cache.episodes[i]["success"] for i in ids], bool)}


def spread(ids: list[int], n: int) -> list[int]:
    """At most n of ids, evenly spaced over the whole list: the k-th is ids[k * len(ids) // n], so that
    the last ids (the cache orders episodes by task and policy: the last tasks) are drawn as often as
    the first (a stride of len(ids) // n cut at n would leave out the tail, up to half the list)."""
    if len(ids) <= n:
        return list(ids)
    return [ids[k * len(ids) // n] for k in range(n)]


# ---- files -----------------------------------------------------------------------------------------

def save_judge(judge: EpisodeJudge, metrics: dict, out: Path, name: str = JUDGE) -> None:
    """Writes the judge into out for load_judge: its parameters as out/<name>.msgpack (atomically), and its
    tasks, normalisation, width, members, input columns, feature width and the fit's metrics as
    out/<name>.json (name: JUDGE, or SECOND_JUDGE for TrainConfig.judge2_inputs' judge)."""
    blob = out / f"{name}.msgpack"
    tmp = blob.with_name(blob.name + ".tmp")
    tmp.write_bytes(serialization.to_bytes(judge.params))
    os.replace(tmp, blob)
    write_json_atomic(out / f"{name}.json", {"tasks": list(judge.tasks), "mean": judge.mean.tolist(),
                                           "std": judge.std.tolist(), "width": WIDTH, "members": judge.members,
                                           "columns": judge.columns.tolist(), "feature_dim": judge.feature_dim,
                                           "raw_mean": judge.raw_mean, "metrics": metrics})


def load_judge(out: Path, name: str = JUDGE) -> EpisodeJudge | None:
    """The judge saved with a training run in out (or its bundle, wm.checkpoint), or None when it has none;
    name: SECOND_JUDGE for the second judge (TrainConfig.judge2_inputs)."""
    out = Path(out)
    meta = run_file(out, f"{name}.json")
    if meta is None or not (out / f"{name}.msgpack").exists():
        return None
    mean = np.asarray(meta["mean"], np.float32)
    raw_mean = bool(meta.get("raw_mean", False))  # judge.json without the key: the features' mean not pooled
    net = JudgeNet(len(meta["tasks"]), meta["width"], raw_mean)
    shapes = jax.eval_shape(lambda: net.init(jax.random.PRNGKey(0), jnp.zeros((1, 2, len(mean))),
                                             jnp.ones((1, 2), bool), jnp.zeros((1,), jnp.int32))["params"])
    members = meta.get("members")  # a judge saved without the key holds one member's parameters, unstacked
    lead = () if members is None else (int(members),)
    params = serialization.from_bytes(jax.tree_util.tree_map(lambda s: np.zeros(lead + s.shape, s.dtype), shapes),
                                      (out / f"{name}.msgpack").read_bytes())
    if members is None:
        params = jax.tree_util.tree_map(lambda p: p[None], params)
    columns = np.asarray(meta.get("columns", range(len(mean))), np.int64)  # a judge saved before input selection reads all
    return EpisodeJudge(params=params, mean=mean, std=np.asarray(meta["std"], np.float32), tasks=tuple(meta["tasks"]),
                        columns=columns, feature_dim=int(meta.get("feature_dim", len(mean))), raw_mean=raw_mean)


def check_features(cfg: ModelConfig, judge: EpisodeJudge) -> None:
    """Raises ValueError unless the judge reads step features as wide as the world model of cfg makes them."""
    if judge.feature_dim != feature_dim(cfg):
        raise ValueError(f"the judge reads step features of {judge.feature_dim} columns, the world model makes "
                         f"{feature_dim(cfg)}")
