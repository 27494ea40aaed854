"""Policies as probes of what predicted frames hold: the read loss (TrainConfig.w_read).

A policy ranked in the world model acts on imagined frames; where it reads them otherwise than the
true frames, it takes other actions and the imagined episode leaves the one the simulator would run.
The read loss trains the frames a policy's way: the behaviour-cloning checkpoints whose rollouts the
dataset holds (each only on windows of its own task) read every 4th predicted frame of each training
pass and its true frame, beside the true proprioception and time, and the squared difference of the
two action chunks, in the checkpoint's standardised action units, is the loss. The checkpoints are
fixed: only the world model learns.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sim_data.policies.bc import BCPolicy, PolicyNet, PolicyNetConfig, normalise_proprio, stack_params, stand_in_params


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
    return {**params, "net": jax.tree_util.tree_map(lambda x: np.asarray(jnp.asarray(x, dtype)), params["net"])}


def _chunk(net, params, frames, proprio, t, dtype):
    """A probe's standardised action chunk (N, chunk, 20) float32 from frames (N, S, S, 3) in [0, 1],
    its convolutions in dtype."""
    out = PolicyNet(net, dtype).apply({"params": params["net"]}, frames * 255.0,
                                      normalise_proprio(params, proprio).astype(dtype), t)
    return out.astype(jnp.float32)


def readings(probes: Probes, frames, proprio, t) -> tuple:
    """Every probe's standardised action chunks for frames (N, S, S, 3) in [0, 1] (proprio (N, 37),
    t (N,) int32): per group, (P_g, N, chunk, 20), their gradient stopped."""
    # one checkpoint after another: vmapped, their convolutions become grouped ones, several times slower
    return tuple(jax.lax.stop_gradient(jax.lax.map(lambda p, net=net: _chunk(net, p, frames, proprio, t, probes.dtype), params))
                 for net, params in zip(probes.nets, probes.params, strict=True))


def read_loss_from(probes: Probes, pred, true_readings: tuple, proprio, t, task):
    """read_loss with the probes' readings of the true frames given (readings'), so that several
    passes of predictions of the same frames share them."""
    total, rows = jnp.zeros(()), jnp.zeros(())
    for net, params, tasks, want in zip(probes.nets, probes.params, probes.tasks, true_readings, strict=True):
        def one(args, net=net):
            p, k, w = args
            err = jnp.mean((_chunk(net, p, pred, proprio, t, probes.dtype) - w) ** 2, axis=(1, 2))
            mine = (task == k).astype(jnp.float32)
            return jnp.sum(mine * err), jnp.sum(mine)
        s, n = jax.lax.map(one, (params, jnp.asarray(tasks), want))
        total, rows = total + jnp.sum(s), rows + jnp.sum(n)
    return total / jnp.maximum(rows, 1.0)


def read_loss(probes: Probes, pred, target, proprio, t, task):
    """The mean over probes and their own task's rows of the squared difference between the action
    chunk each probe reads from the predicted frames and the one it reads from the true frames
    (pred, target (N, S, S, 3) in [0, 1], the true frames' gradient stopped), given the true frames'
    proprio (N, 37) in its own units, steps t (N,) int32 since the episode began and task (N,) int32.
    0 where no row is of a probe's task."""
    return read_loss_from(probes, pred, readings(probes, target, proprio, t), proprio, t, task)


def stand_in_probes(n: int, size: int, dtype: str = "float32") -> Probes:
    """n probes of the zoo's default convolutional network (PolicyNetConfig's) for frames of `size`,
    freshly initialised, all of task 0, computing in dtype: a step's shapes and cost without a
    dataset (wm.bench)."""
    net = PolicyNetConfig(size=size)
    one = jax.tree_util.tree_map(np.asarray, stand_in_params(net, False))
    return Probes(params=(_weights_in(stack_params([one] * n), dtype),), tasks=(np.zeros(n, np.int32),),
                  nets=(net,), dtype=dtype)
