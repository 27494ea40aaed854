"""Policies as probes of what predicted frames hold: the read loss (TrainConfig.w_read).

A policy ranked in the world model acts on imagined frames; where it reads them otherwise than the
true frames, it takes other actions and the imagined episode leaves the one the simulator would run.
The read loss trains the frames a policy's way: the behaviour-cloning checkpoints whose rollouts the
dataset read every 4th predicted frame of each training pass and its true frame, beside the true
proprioception and time, and the squared difference of the two action chunks, in the checkpoint's
standardised action units, is the loss. Each frame is read by one checkpoint of its own task, the
task's checkpoints taking its frames in turn: the loss is, in expectation over the batch's order, the
mean over a task's checkpoints, at one network pass a frame instead of one per checkpoint. The
checkpoints are fixed: only the world model learns.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sim_data.policies.bc import BCPolicy, PolicyNet, PolicyNetConfig, normalise_proprio, stack_params, stand_in_params
from sim_data.sim.robot import ACTION_DIM, HAND_CLOSURE


@struct.dataclass
class Probes:
    """Probe checkpoints grouped by network: nets[g] (a PolicyNetConfig, static), params[g] stacked
    parameter trees (every leaf with a leading P_g axis; the networks' weights in `dtype`), tasks[g]
    (P_g,) int32 (the index of each checkpoint's task in the training cache's tasks); dtype (static):
    what their convolutions compute in, the world model's (ModelConfig.dtype)."""

    params: tuple
    tasks: tuple
    nets: tuple = struct.field(pytree_node=False)
    dtype: str = struct.field(pytree_node=False, default="float32")

    @property
    def count(self) -> int:
        return sum(int(t.shape[0]) for t in self.tasks)

    @property
    def turns(self) -> tuple:
        """Per group (P_g,) int32: each checkpoint's place among its task's checkpoints, over every group."""
        return self._split(_place_among_equals(jnp.concatenate([jnp.asarray(k) for k in self.tasks])))

    @property
    def shares(self) -> tuple:
        """Per group (P_g,) int32: how many checkpoints, over every group, share each one's task."""
        every = jnp.concatenate([jnp.asarray(k) for k in self.tasks])
        return self._split(jnp.sum(every[:, None] == every[None, :], axis=1, dtype=jnp.int32))

    def _split(self, x) -> tuple:
        """x (count,), over the groups one after another, as one array a group."""
        return tuple(jnp.split(x, np.cumsum([int(t.shape[0]) for t in self.tasks])[:-1]))


def _place_among_equals(x):
    """(N,) int32: how many earlier entries of x (N,) equal each one."""
    return jnp.sum(jnp.tril(x[:, None] == x[None, :], -1), axis=1, dtype=jnp.int32)


def probe_sources(policies: dict, tasks: list[str], frame_size: int, n: int) -> list:
    """At most n PolicySources of `policies` ({name: PolicySource}, wm.judge.dataset_policies) to probe
    with: registry checkpoints of a behaviour-cloning network (not a family's degraded member, a
    perturbed copy or a plug-in) trained for one of `tasks`, spread evenly over them in name order.
    Raises ValueError where a network reads frames of another size than the world model's."""
    fit = sorted((s for s in policies.values()
                  if s.kind == "learned" and type(s.policy) is BCPolicy and s.task in tasks), key=lambda s: s.name)
    for s in fit:
        if s.policy.cfg.size != frame_size:
            raise ValueError(f"{s.name} reads {s.policy.cfg.size}x{s.policy.cfg.size} frames, the world model "
                             f"predicts {frame_size}x{frame_size}: it cannot probe them")
    if len(fit) <= n:
        return fit
    return [fit[int(k)] for k in np.unique(np.round(np.linspace(0, len(fit) - 1, n)).astype(int))]


def make_probes(sources: list, tasks: list[str], dtype: str = "float32") -> Probes | None:
    """Probes of sources (probe_sources'), one group per network configuration, their networks'
    weights cast to dtype (the world model's compute dtype: in float32 a GPU runs the probes'
    convolutions several times slower than in bfloat16); None for none."""
    groups: dict = {}
    for s in sources:
        groups.setdefault(s.policy.cfg, []).append(s)
    if not groups:
        return None
    nets = tuple(groups)
    return Probes(params=tuple(_weights_in(stack_params([jax.tree_util.tree_map(np.asarray, s.params)
                                                         for s in groups[c]]), dtype) for c in nets),
                  tasks=tuple(np.array([tasks.index(s.task) for s in groups[c]], np.int32) for c in nets),
                  nets=nets, dtype=dtype)


def _weights_in(params: dict, dtype: str) -> dict:
    """params with the network's weights (params["net"]) cast to dtype; the normalisation as it is."""
    return {**params, "net": jax.tree_util.tree_map(lambda x: np.asarray(x).astype(jnp.dtype(dtype)), params["net"])}


def _chunk(net, params, frames, proprio, t, dtype):
    """A probe's standardised action chunk (N, chunk, 20) float32 from frames (N, S, S, 3) in [0, 1],
    its convolutions in dtype."""
    out = PolicyNet(net, dtype).apply({"params": params["net"]}, frames * 255.0,
                                      normalise_proprio(params, proprio).astype(dtype), t)
    return out.astype(jnp.float32)


def row_capacity(rows: int, probes: int) -> int:
    """How many of `rows` frames one of `probes` checkpoints reads at most: twice its even share, so
    that a batch weighted towards one task loses few of that task's frames."""
    return min(rows, -(-2 * rows // probes))


def probe_rows(probes: Probes, task) -> tuple:
    """The frames each probe reads, given each frame's task (N,) int32: a task's frames go to its
    checkpoints in turn (the frame's place among its task's frames, modulo the task's checkpoint
    count), at most row_capacity of them a checkpoint, in order. Per group, (rows (P_g, C) int32
    indices into the N frames, valid (P_g, C) bool: False past a checkpoint's frames)."""
    n = task.shape[0]
    place = _place_among_equals(jnp.asarray(task))  # earlier frames of the same task
    cap = row_capacity(n, probes.count)
    out = []
    for tasks, turns, shares in zip(probes.tasks, probes.turns, probes.shares, strict=True):
        mine = (task[None, :] == jnp.asarray(tasks)[:, None]) & (place[None, :] % shares[:, None] == turns[:, None])
        # each of a probe's frames to the slot of its place among them, by comparison rather than a sort
        slot = mine[:, :, None] & ((jnp.cumsum(mine, axis=1) - 1)[:, :, None] == jnp.arange(cap))  # (P_g, N, C)
        rows = jnp.sum(slot * jnp.arange(n, dtype=jnp.int32)[:, None], axis=1, dtype=jnp.int32)
        out.append((rows, jnp.any(slot, axis=1)))
    return tuple(out)


def readings(probes: Probes, frames, proprio, t, rows: tuple) -> tuple:
    """Each probe's standardised action chunks for its frames (probe_rows') of frames (N, S, S, 3) in
    [0, 1] (proprio (N, 37), t (N,) int32): per group, (P_g, C, chunk, 20), their gradient stopped."""
    frames, proprio, t = jnp.asarray(frames), jnp.asarray(proprio), jnp.asarray(t)

    def one(args, net):
        p, r = args
        return _chunk(net, p, frames[r], proprio[r], t[r], probes.dtype)
    # one checkpoint after another: vmapped, their convolutions become grouped ones, several times slower
    return tuple(jax.lax.stop_gradient(jax.lax.map(functools.partial(one, net=net), (params, r)))
                 for net, params, (r, _) in zip(probes.nets, probes.params, rows, strict=True))


def read_loss_from(probes: Probes, pred, true_readings: tuple, proprio, t, rows: tuple, dims=None):
    """read_loss with the frames' assignment (probe_rows') and the probes' readings of the true frames
    (readings') given, so that several passes of predictions of the same frames share them; dims as
    read_loss's."""
    pred, proprio, t = jnp.asarray(pred), jnp.asarray(proprio), jnp.asarray(t)
    weights = None if dims is None else jnp.asarray(dims, jnp.float32) / np.sum(dims, dtype=np.float32)
    total, count = jnp.zeros(()), jnp.zeros(())
    for net, params, (r, valid), want in zip(probes.nets, probes.params, rows, true_readings, strict=True):
        def one(args, net=net):
            p, r, v, w = args
            # the frames picked by a one-hot product, not indexing: the gradient of an index is a
            # scatter, which deterministic GPU ops sort
            pick = ((r[:, None] == jnp.arange(pred.shape[0])) & v[:, None]).astype(pred.dtype)
            frames = jnp.einsum("cn,n...->c...", pick, pred, precision=jax.lax.Precision.HIGHEST)
            sq = (_chunk(net, p, frames, proprio[r], t[r], probes.dtype) - w) ** 2
            err = jnp.mean(sq, axis=(1, 2)) if weights is None else jnp.sum(jnp.mean(sq, axis=1) * weights, -1)
            v = v.astype(jnp.float32)
            return jnp.sum(v * err), jnp.sum(v)
        s, n = jax.lax.map(one, (params, r, valid, want))
        total, count = total + jnp.sum(s), count + jnp.sum(n)
    return total / jnp.maximum(count, 1.0)


def read_loss(probes: Probes, pred, target, proprio, t, task, dims=None):
    """The mean over frames of the squared difference between the action chunk that the frame's probe
    (one checkpoint of its task, probe_rows') reads from the predicted frame and the one it reads from
    the true frame (pred, target (N, S, S, 3) in [0, 1], the true frames' gradient stopped), given the
    true frames' proprio (N, 37) in its own units, steps t (N,) int32 since the episode began and task
    (N,) int32. Frames of a task without probes count for nothing; 0 where every frame is of one.
    dims (20,): each action dimension's weight in a frame's mean (read_dims; None: all alike)."""
    rows = probe_rows(probes, task)
    return read_loss_from(probes, pred, readings(probes, target, proprio, t, rows), proprio, t, rows, dims)


def read_dims(closure: float):
    """(20,) float32 weights of the action dimensions in the read loss: the hands' closure commands at
    `closure`, every other dimension at 1; None at closure 1 (the plain mean). A policy's closure decides
    whether it grasps, and it is what an image-only network loses first on imagined frames."""
    if closure == 1.0:
        return None
    w = np.ones(ACTION_DIM, np.float32)
    w[HAND_CLOSURE] = closure
    return w


def stand_in_probes(n: int, size: int, dtype: str = "float32") -> Probes:
    """n probes of the zoo's default convolutional network (PolicyNetConfig's) for frames of `size`,
    freshly initialised, all of task 0, computing in dtype: a step's shapes and cost without a
    dataset (wm.bench)."""
    net = PolicyNetConfig(size=size)
    one = jax.tree_util.tree_map(np.asarray, stand_in_params(net, False))
    return Probes(params=(_weights_in(stack_params([one] * n), dtype),), tasks=(np.zeros(n, np.int32),),
                  nets=(net,), dtype=dtype)
