"""World-model speed: training throughput and model FLOPs utilisation, and imagination frames/s
with a policy in the loop; writes JSON.

    python -m wm.bench --out runs/bench/wm.json [--config full] [--imagine-batch 1024] [key=value ...]
    python -m wm.bench --train-only --profile 5 --out runs/bench/wm_profile.json   # + GPU time by kernel
    python -m wm.bench --imagine-only --out runs/bench/imagine_cache.json model.imagine=cache

MFU = (FLOPs of one train step from XLA's cost analysis of the lowered, not yet optimised, step) x
(steps/s) / (the bf16 matrix-multiply rate measured on the same device: 8192^3 products, best of 10).
The compiled step's cost analysis is not used: on GPUs it leaves out the matrix products and
convolutions XLA hands to cuBLAS and cuDNN (jax-ml/jax#22249), which made an earlier figure about 16x low.
Inputs are random frames and actions of the configured shapes, so no dataset is needed.
Imagination: `wm.imagine.closed_loop` with a small convolutional policy (image and proprio in,
action out) over `--horizon` steps; a frame is one imagined step of one episode, decoded.
`--profile N` traces N train steps with `jax.profiler` and sums the GPU's kernels by name
(`kernel_profile`): where a step's time goes, matrix kernels against the fused elementwise ones.
On a host of several GPUs the report also holds `scaling` (see `scaling`; `--scaling 1,2,4` alone
measures only that).
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from sim_data.policies.registry import applied_policy
from sim_data.util import device_name, run_cli, write_json_atomic
from wm.config import make_config
from wm.imagine import Norm, closed_loop, init_state, step
from wm.model import init_params
from wm.probes import stand_in_probes
from wm.train import (
    initial_state,
    jitted_train_step,
    make_mesh,
    perceptual_weights,
    put_batch,
    state_shardings,
)


def matmul_rate(n: int = 8192, reps: int = 10, chain: int = 8) -> float:
    """Measured bf16 FLOP/s of n x n x n matrix products, `chain` of them in one jitted call (so that
    the call's dispatch and the host's wait are spread over them), best of reps."""
    if jax.devices()[0].platform == "cpu":
        n, chain = 1024, 2
    k = jax.random.split(jax.random.PRNGKey(0))
    a = jax.random.normal(k[0], (n, n), jnp.bfloat16)
    w = (jax.random.normal(k[1], (n, n), jnp.float32) / np.sqrt(n)).astype(jnp.bfloat16)  # keeps the scale
    f = jax.jit(lambda x: jax.lax.fori_loop(0, chain, lambda i, y: y @ w, x))
    f(a).block_until_ready()
    best = np.inf
    for _ in range(reps):
        t = time.perf_counter()
        f(a).block_until_ready()
        best = min(best, time.perf_counter() - t)
    return 2 * n**3 * chain / best


def step_inputs(cfg):
    """(state, batch, norm) of one train step: fresh parameters, random frames and actions (with the
    read loss, every window of task 0 at its episode's start)."""
    m = cfg.model
    params = init_params(m, jax.random.PRNGKey(0), window=cfg.window)
    state = initial_state(cfg, params)
    rng = np.random.default_rng(0)
    b, t = cfg.batch, cfg.window
    batch = {"frames": jnp.asarray(rng.integers(0, 255, (b, t, m.size, m.size, 3), dtype=np.uint8)),
             "proprio": jnp.asarray(rng.normal(size=(b, t, m.proprio_dim)), jnp.float32),
             "action": jnp.asarray(rng.normal(size=(b, t, m.action_dim)), jnp.float32),
             "success": jnp.zeros((b, t), bool), "progress": jnp.zeros((b, t)), "outcome": jnp.zeros((b,), bool)}
    if m.scene:
        batch["scene"] = jnp.asarray(rng.normal(size=(b, t, m.scene_dim)), jnp.float32)
    if m.anchor or cfg.w_read > 0:
        batch["start"] = jnp.zeros((b,), jnp.int32)
    if m.anchor:
        batch["anchor"] = batch["frames"][:, 0]
    if cfg.w_read > 0:
        batch["task"] = jnp.zeros((b,), jnp.int32)
    if cfg.grip_focus > 0:
        batch["grip_px"] = jnp.asarray(rng.uniform(size=(b, t, 2, 2)), jnp.float32)
    return state, batch, unit_norm(m)


def unit_norm(m) -> Norm:
    """Statistics that leave a ModelConfig m's proprioception, actions and scene state as they are."""
    return Norm(jnp.zeros(m.proprio_dim), jnp.ones(m.proprio_dim), jnp.zeros(m.action_dim), jnp.ones(m.action_dim),
                jnp.zeros(m.scene_dim), jnp.ones(m.scene_dim))


def blank_context(m, batch: int) -> tuple:
    """2 blank context steps of `batch` episodes for ModelConfig m: frames (B, 2, S, S, 3) uint8,
    proprioception (B, 2, P) and the action between them (B, 1, A), zeros."""
    return (jnp.zeros((batch, 2, m.size, m.size, 3), jnp.uint8), jnp.zeros((batch, 2, m.proprio_dim)),
            jnp.zeros((batch, 1, m.action_dim)))


def frozen_inputs(cfg):
    """(lpips_weights, probes) of a train step of cfg: the LPIPS network's weights where cfg.w_lpips > 0,
    stand-in probes (wm.probes.stand_in_probes) where cfg.w_read > 0, each else None."""
    return perceptual_weights(cfg), stand_in_probes(cfg.read_probes, cfg.model.size, cfg.model.dtype) if cfg.w_read > 0 else None


def step_flops(preset: str, overrides=()) -> float:
    """FLOPs of one train step by XLA's cost analysis of the lowered, not yet optimised, step.

    `Lowered.cost_analysis` is not implemented on plugin backends such as the GPU's (it returns None),
    so off the CPU the count runs in a child process restricted to the CPU; the HLO is the same.
    """
    if jax.default_backend() != "cpu":
        child = subprocess.run([sys.executable, "-m", "wm.bench", "--flops-only", "--config", preset, *overrides],
                               env={**os.environ, "JAX_PLATFORMS": "cpu"}, capture_output=True, text=True)
        if child.returncode:
            raise RuntimeError(f"counting FLOPs on the CPU failed:\n{child.stderr[-2000:]}")
        return float(child.stdout.split()[-1])
    cfg = make_config(preset, overrides)
    args = (*jax.eval_shape(lambda: step_inputs(cfg)), *frozen_inputs(cfg))
    cost = jitted_train_step.lower(cfg, *args).cost_analysis()
    if isinstance(cost, list | tuple):
        cost = cost[0]
    if not cost or "flops" not in cost:
        raise RuntimeError(f"XLA gave no cost analysis on {jax.default_backend()} (jax {jax.__version__})")
    return float(cost["flops"])


_HLO_SHAPE = r"[a-z0-9]+\[([0-9,]*)\]"


def _dims(text: str) -> tuple:
    return tuple(int(x) for x in text.split(",") if x)


def matmul_flops_by_shape(hlo: str) -> dict:
    """FLOPs of the convolutions and dot products in an HLO module's text (`Lowered.as_text(dialect=
    "hlo")`), summed over the instructions of one op, element type, operand shapes and window:
    {(op, dtype, lhs shape, rhs shape, window or contracting dims, out shape): FLOPs}. A dot counts
    2 x output elements x contracted size; a convolution 2 x output elements x the kernel operand's
    elements / its output features (the weight gradient's "kernel" being an activation) / the input
    dilation's factors (an input gradient skips the zeros it dilates its input with); the products
    with a convolution's zero padding are counted."""
    shapes = {m.group(1): _dims(m.group(2)) for m in re.finditer(r"^\s*([\w.\-]+) = " + _HLO_SHAPE, hlo, re.M)}
    out = {}
    for line in hlo.splitlines():
        m = re.search(r"= ([a-z0-9]+)\[([0-9,]*)\]\{[^}]*\} (convolution|dot)\(([\w.\-]+), ([\w.\-]+)\)", line)
        if m is None:
            continue
        dtype, result, op, lhs, rhs = m.group(1), _dims(m.group(2)), m.group(3), shapes[m.group(4)], shapes[m.group(5)]
        if op == "dot":
            contracting = _dims(re.search(r"lhs_contracting_dims=\{([0-9,]*)\}", line).group(1))
            flops, how = dot_flops(lhs, result, contracting), f"contracting {contracting}"
        else:
            kernel_labels = re.search(r"dim_labels=\w+_(\w+)->", line).group(1)
            how = re.search(r"window=\{([^}]*)\}", line).group(1)
            dilation = re.search(r"lhs_dilate=([0-9x]+)", how)
            flops = conv_flops(rhs, result, kernel_labels.index("o"),
                               [int(d) for d in dilation.group(1).split("x")] if dilation else [1])
        key = (op, dtype, lhs, rhs, how, result)
        out[key] = out.get(key, 0.0) + flops
    return out


def dot_flops(lhs, result, contracting) -> float:
    """2 x output elements x the contracted size: a dot product's FLOPs (lhs, result: shapes;
    contracting: the lhs dimensions summed over, none for an outer product)."""
    return 2.0 * float(np.prod(result)) * float(np.prod([lhs[i] for i in contracting]))


def conv_flops(kernel, result, out_feature_dim: int, lhs_dilation) -> float:
    """A convolution's FLOPs: 2 x output elements x the kernel operand's elements / its output features
    (the weight gradient's "kernel" being an activation) / the input dilation's factors (a transposed
    convolution or an input gradient skips the zeros it dilates its input with); the products with its
    zero padding are counted."""
    return 2.0 * float(np.prod(result)) * float(np.prod(kernel)) / kernel[out_feature_dim] / float(np.prod(lhs_dilation))


_TENSOR = r"tensor<([^>]*)>"
_NOT_SCOPES = {"while", "body", "cond", "closed_call", "checkpoint", "remat", "pjit", "scan", "vmap"}


def _tensor_dims(t: str) -> list:
    return [int(x) for x in t.split("x")[:-1]]


def flops_by_module(text: str, depth: int = 2) -> dict:
    """FLOPs of the convolutions and dot products (dot_flops, conv_flops) in a lowered program's StableHLO
    with its locations (`Lowered.as_text(debug_info=True)`), summed by the Flax module scope whose code
    made each (its first `depth` scopes, "(outside any module)" where there is none): {scope: FLOPs}.
    A function the program calls (a jitted helper, a loop's body outlined) counts once a call site, its
    products placed under the call's scope where their own name none; a loop's body counts once, as in
    XLA's cost analysis, and both branches of a conditional count."""
    locs = dict(re.findall(r"^(#loc\d+) = loc\((.*)\)$", text, re.M))

    def name(loc: str, hops: int = 0) -> str:
        body = locs.get(loc, "")
        quoted = re.match(r'"([^"]*)"', body)
        inner = re.findall(r"#loc\d+", body)
        if quoted and not quoted.group(1).endswith(":"):  # "prim:" wraps an op's own location on some versions
            return quoted.group(1)
        return name(inner[0], hops + 1) if inner and hops < 32 else ""

    def scope_of(line: str) -> list:
        loc = re.search(r"loc\((#loc\d+)\)\s*$", line)
        parts = name(loc.group(1)).split("/")[:-1] if loc else []  # the last part names the primitive
        return [q for q in parts if "(" not in q and "," not in q and not q.endswith("_fun") and q not in _NOT_SCOPES]

    own: dict = {}  # function -> {scope tuple: FLOPs}
    calls: dict = {}  # function -> [(callee, scope tuple of the call)]
    func = None
    for line in text.splitlines():
        head = re.match(r"\s*func\.func (?:public |private )?@([\w.\-]+)", line)
        if head:
            func = head.group(1)
            own.setdefault(func, {})
            calls.setdefault(func, [])
            continue
        callee = re.search(r"(?:func\.)?call @([\w.\-]+)\(", line)
        if callee:
            calls[func].append((callee.group(1), tuple(scope_of(line))))
            continue
        if "stablehlo.dot_general" in line:
            m = re.search(r"contracting_dims = \[([0-9, ]*)\] x .*?: \(" + _TENSOR + ", " + _TENSOR + r"\) -> "
                          + _TENSOR, line)
            lhs, result = _tensor_dims(m.group(2)), _tensor_dims(m.group(4))
            flops = dot_flops(lhs, result, [int(i) for i in m.group(1).split(",") if i.strip()])
        elif "stablehlo.convolution" in line:
            m = re.search(r"\]x\[([^\]]*)\]->.*?: \(" + _TENSOR + ", " + _TENSOR + r"\) -> " + _TENSOR, line)
            dilation = re.search(r"lhs_dilate = \[([0-9, ]*)\]", line)
            labels = [x.strip() for x in m.group(1).split(",")]
            flops = conv_flops(_tensor_dims(m.group(3)), _tensor_dims(m.group(4)), labels.index("o"),
                               [int(d) for d in dilation.group(1).split(",")] if dilation else [1])
        else:
            continue
        key = tuple(scope_of(line))
        own[func][key] = own[func].get(key, 0.0) + flops

    def total(fn: str, outer: tuple, seen: tuple) -> dict:
        out: dict = {}
        for key, f in own.get(fn, {}).items():
            k = key or outer
            out[k] = out.get(k, 0.0) + f
        for callee, at in calls.get(fn, []):
            if callee not in seen:
                for k, f in total(callee, at or outer, seen + (callee,)).items():
                    out[k] = out.get(k, 0.0) + f
        return out

    entry = "main" if "main" in own else next(iter(own), None)
    by = total(entry, (), (entry,)) if entry else {}
    merged: dict = {}
    for key, f in by.items():
        k = "/".join(key[:depth]) or "(outside any module)"
        merged[k] = merged.get(k, 0.0) + f
    return merged


def imagine_step_flops(cfg, batch: int = 16, depth: int = 2) -> dict:
    """FLOPs of one imagined step of one episode (`wm.imagine.step`: the dynamics, the decoder, the frame
    generator's Euler steps, the re-encoding; the acting policy's own are left out), by Flax module scope
    (flops_by_module), from cfg's model (a TrainConfig) lowered on this backend, not compiled."""
    m = cfg.model
    params = jax.eval_shape(lambda: init_params(m, jax.random.PRNGKey(0), window=cfg.window))
    norm = unit_norm(m)
    state = jax.eval_shape(lambda p: init_state(m, p, norm, *blank_context(m, batch)), params)
    action = jax.ShapeDtypeStruct((batch, m.action_dim), jnp.float32)
    text = jax.jit(step, static_argnums=0).lower(m, params, norm, state, action).as_text(debug_info=True)
    by = flops_by_module(text, depth)
    if by and set(by) == {"(outside any module)"}:
        raise RuntimeError("the lowered step's locations name no Flax module: this jax writes them otherwise, "
                           "and wm.bench.flops_by_module needs to learn how")
    return {k: v / batch for k, v in by.items()}


def step_flops_by_shape(preset: str, overrides=()) -> dict:
    """matmul_flops_by_shape of one train step of the preset, lowered (not compiled) on this backend."""
    cfg = make_config(preset, overrides)
    args = (*jax.eval_shape(lambda: step_inputs(cfg)), *frozen_inputs(cfg))
    return matmul_flops_by_shape(jitted_train_step.lower(cfg, *args).as_text(dialect="hlo"))


def train_rate(cfg, steps: int = 20, profile: int = 0, mesh=None) -> dict:
    """Time of one train step of cfg (mean of `steps` after 3 untimed ones) and, where profile > 0,
    the kernel_profile of `profile` more steps traced with jax.profiler (under "profile"). With a
    mesh, the step runs data parallel over it, parameters placed as cfg.param_sharding says."""
    state, batch, norm = step_inputs(cfg)
    weights, probes = frozen_inputs(cfg)
    if mesh is not None:
        state = jax.device_put(state, state_shardings(state, mesh, cfg.param_sharding == "fsdp"))
        batch = put_batch(batch, mesh)
        norm, weights, probes = jax.device_put((norm, weights, probes), NamedSharding(mesh, P()))
    t0 = time.perf_counter()
    compiled = jitted_train_step.lower(cfg, state, batch, norm, weights, probes).compile()
    compile_s = time.perf_counter() - t0
    for _ in range(3):
        state, parts = compiled(state, batch, norm, weights, probes)
    jax.block_until_ready(parts)
    t0 = time.perf_counter()
    for _ in range(steps):
        state, parts = compiled(state, batch, norm, weights, probes)
    jax.block_until_ready(parts)
    dt = (time.perf_counter() - t0) / steps
    out = {"batch": cfg.batch, "window": cfg.window,
           "params": int(sum(x.size for x in jax.tree_util.tree_leaves(state["params"]))),
           "step_s": dt, "frames_per_s": cfg.batch * cfg.window / dt, "compile_s": compile_s}
    if profile:
        with tempfile.TemporaryDirectory() as d:
            jax.profiler.start_trace(d, create_perfetto_trace=True)
            for _ in range(profile):
                state, parts = compiled(state, batch, norm, weights, probes)
            jax.block_until_ready(parts)
            jax.profiler.stop_trace()
            found = sorted(Path(d).rglob("perfetto_trace.json.gz"))
            if not found:
                raise RuntimeError(f"jax.profiler wrote no perfetto_trace.json.gz under {d}")
            with gzip.open(found[-1], "rt") as f:
                out["profile"] = kernel_profile(json.load(f), profile)
    return out


def scaling(preset: str, overrides=(), per_device_batch: int | None = None, counts=(1, 2, 4, 8),
            shardings=("replicated", "fsdp"), steps: int = 20, one_device: dict | None = None) -> list[dict]:
    """Training throughput on the first n devices for each n in counts (those this host has), at the
    same per-device batch (default: the preset's batch), for each parameter sharding. Each row: devices,
    param_sharding, batch (global), step_s, frames_per_s, frames_per_s_per_device, compile_s and
    efficiency (per-device throughput against one device's, or against the fewest devices measured
    where 1 is not among counts). One device is measured once, since there every sharding is the same
    program, or not at all where `one_device` gives its train_rate at that batch already."""
    per = per_device_batch or make_config(preset, overrides).batch
    if any(c < 1 for c in counts):
        raise ValueError(f"device counts are >= 1, got {sorted(counts)}")
    counts = sorted(c for c in set(counts) if c <= jax.device_count())
    if not counts:
        raise ValueError(f"none of the device counts fits this host's {jax.device_count()} devices")
    rows, one_rate = [], None  # one_rate: one device's frames/s, once measured
    for sharding in shardings:
        base = one_rate
        for n in counts:
            if n == 1 and one_rate is not None:
                continue  # on one device fsdp shards nothing: the same program as replicated
            if n == 1 and one_device is not None:
                r = one_device
            else:
                cfg = make_config(preset, [*overrides, f"batch={per * n}", f"param_sharding={sharding}"])
                r = train_rate(cfg, steps, mesh=make_mesh(jax.devices()[:n]))
            per_device = r["frames_per_s"] / n
            base = base or per_device
            if n == 1:
                one_rate = per_device
            rows.append({"devices": n, "param_sharding": sharding, "batch": per * n, "step_s": r["step_s"],
                         "frames_per_s": r["frames_per_s"], "frames_per_s_per_device": per_device,
                         "efficiency": per_device / base, "compile_s": r["compile_s"]})
    return rows


MATRIX_KERNEL = re.compile(r"gemm|xmma|cutlass|nvjet|wgmma", re.I)


def kernel_profile(trace: dict, steps: int, top: int = 25) -> dict:
    """Device time per step by kernel from a Chrome/perfetto trace (`jax.profiler`'s
    perfetto_trace.json): the complete events ("ph": "X", durations in microseconds) of every process
    named /device:..., summed by name. Matrix kernels (cuBLAS, cuDNN, CUTLASS: names with gemm, xmma,
    cutlass, nvjet) are one kind; every other kernel's kind is its name less a trailing number
    (XLA's fusions: loop_add_fusion_12 -> loop_add_fusion).

    Returns {"step_ms", "matrix_share", "by_kind": {kind: ms a step}, "top": [{"name", "ms", "calls"}]}
    (ms and calls per step); raises ValueError when the trace holds no device events (a CPU run)."""
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    devices = {e["pid"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"
               and str(e.get("args", {}).get("name", "")).startswith("/device:")}
    time_us, calls = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("ph") == "X" and e.get("pid") in devices:
            time_us[e["name"]] += float(e.get("dur", 0.0))
            calls[e["name"]] += 1
    if not time_us:
        raise ValueError("the trace holds no device kernels: profile on a GPU")
    by_kind = collections.Counter()
    for name, us in time_us.items():
        by_kind["matrix kernels" if MATRIX_KERNEL.search(name) else re.sub(r"[_.]?\d+$", "", name)] += us
    total = sum(time_us.values())

    def ms(us):
        return us / 1e3 / steps

    return {"step_ms": ms(total), "matrix_share": by_kind["matrix kernels"] / total,
            "by_kind": {k: ms(v) for k, v in by_kind.most_common()},
            "top": [{"name": n, "ms": ms(us), "calls": calls[n] / steps} for n, us in time_us.most_common(top)]}


class ConvPolicy(nn.Module):
    """A small image + proprio -> action network (the shape of the behaviour-cloning policies)."""

    @nn.compact
    def __call__(self, image, proprio):
        x = image.astype(jnp.float32) / 255.0
        for ch in (16, 32, 64):
            x = nn.relu(nn.Conv(ch, (3, 3), strides=(2, 2))(x))
        x = jnp.concatenate([x.mean(axis=(1, 2)), proprio], -1)
        return nn.Dense(20)(nn.relu(nn.Dense(128)(x)))


class BenchPolicy:
    """ConvPolicy under the project's policy protocol."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["image"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        return ConvPolicy().apply(params, obs["image"], obs["proprio"]), carry + 1


def imagine_rate(cfg, batch: int, horizon: int) -> dict:
    """Closed-loop imagination throughput of cfg's model (a TrainConfig; fresh parameters) with a small conv policy
    (BenchPolicy) acting: `batch` episodes of `horizon` steps from 2 blank context frames, best of 3 timed calls.
    Returns {"batch", "horizon", "frames_per_s", "first_call_s" (the compiling call's seconds)}."""
    m = cfg.model
    params = init_params(m, jax.random.PRNGKey(0), window=cfg.window)
    pol = applied_policy(BenchPolicy())  # as the evaluation runs a policy: its actions as the robot applies them
    pparams = ConvPolicy().init(jax.random.PRNGKey(1), jnp.zeros((1, m.size, m.size, 3), jnp.uint8), jnp.zeros((1, 37)))
    norm = unit_norm(m)
    frames, proprio, acts = blank_context(m, batch)
    t0 = time.perf_counter()
    jax.block_until_ready(closed_loop(m, pol, horizon, params, norm, pparams, frames, proprio, acts,
                                      jax.random.PRNGKey(0)))
    compile_s = time.perf_counter() - t0
    best = np.inf
    for r in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(closed_loop(m, pol, horizon, params, norm, pparams, frames, proprio, acts,
                                          jax.random.PRNGKey(r)))
        best = min(best, time.perf_counter() - t0)
    return {"batch": batch, "horizon": horizon, "frames_per_s": batch * horizon / best, "first_call_s": compile_s}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path)
    p.add_argument("--config", default=None, help="training preset (default: full on a GPU, demo on the CPU)")
    p.add_argument("--imagine-batch", type=int, default=None)
    p.add_argument("--horizon", type=int, default=32)
    p.add_argument("overrides", nargs="*")
    p.add_argument("--flops-only", action="store_true", help="print the FLOPs of one train step and stop")
    p.add_argument("--train-only", action="store_true", help="time training only, not imagination")
    p.add_argument("--imagine-only", action="store_true",
                   help="time imagination only (model.imagine=window|cache picks how it reads its past)")
    p.add_argument("--profile", type=int, default=0, metavar="N",
                   help="also trace N train steps and write the GPU's time by kernel (a GPU only)")
    p.add_argument("--flops-by-shape", type=int, default=0, metavar="N",
                   help="print the N convolution and dot shapes of one train step with the most FLOPs and stop")
    p.add_argument("--imagine-flops", action="store_true",
                   help="print (and with --out write) the FLOPs of one imagined frame by module, lowered, and stop")
    p.add_argument("--scaling", default=None, metavar="N,N,...",
                   help="only training throughput on the first N devices for each N (same per-device batch), "
                        "replicated and fsdp: per-device frames/s and efficiency against one device's")
    p.add_argument("--per-device-batch", type=int, default=None, help="with --scaling (default: the preset's batch)")
    p.add_argument("--steps", type=int, default=20, help="timed train steps per measurement")
    a = p.parse_intermixed_args(argv)  # key=value overrides before or after the options
    gpu = jax.devices()[0].platform != "cpu"
    preset = a.config or ("full" if gpu else "demo")
    if a.scaling:
        if a.out is None:
            p.error("--out is required")
        try:
            counts = [int(c) for c in a.scaling.split(",")]
        except ValueError:
            p.error(f"--scaling takes device counts such as 1,2,4,8, got {a.scaling!r}")
        try:
            rows = scaling(preset, a.overrides, a.per_device_batch, counts, steps=a.steps)
        except ValueError as e:
            p.error(str(e))
        report = {"device": device_name(), "device_count": jax.device_count(), "config": preset,
                  "overrides": list(a.overrides), "scaling": rows}
        a.out.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(a.out, report)
        print(json.dumps(report, indent=1))
        return 0
    if a.flops_only:
        print(step_flops(preset, a.overrides))
        return 0
    if a.imagine_flops:
        by = imagine_step_flops(make_config(preset, a.overrides))
        total = sum(by.values())
        report = {"device": device_name(), "config": preset, "overrides": list(a.overrides),
                  "imagine_step_flops": total, "by_module": dict(sorted(by.items(), key=lambda kv: -kv[1]))}
        for scope, f in report["by_module"].items():
            print(f"{f / 1e9:8.3f} GFLOP {f / total:6.1%}  {scope}")
        print(f"{total / 1e9:8.3f} GFLOP an imagined frame (convolutions and dot products)")
        if a.out is not None:
            write_json_atomic(a.out, report)
        return 0
    if a.flops_by_shape:
        by = step_flops_by_shape(preset, a.overrides)
        total = sum(by.values())
        print(f"{total / 1e12:.3f} TFLOP in convolutions and dot products; the largest shares:")
        for (op, dtype, lhs, rhs, how, result), f in sorted(by.items(), key=lambda kv: -kv[1])[:a.flops_by_shape]:
            print(f"{f / total:6.1%}  {op:11s} {dtype} {lhs} x {rhs} -> {result}  {how}")
        return 0
    if a.out is None:
        p.error("--out is required")
    cfg = make_config(preset, a.overrides)
    if a.imagine_only:
        report = {"device": device_name(), "config": preset, "overrides": list(a.overrides),
                  "imagine": imagine_rate(cfg, a.imagine_batch or (1024 if gpu else 16), a.horizon)}
        a.out.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(a.out, report)
        print(json.dumps(report, indent=1))
        return 0
    if a.profile and not gpu:
        p.error("--profile sums the GPU's kernels: run it on a GPU")
    rate = matmul_rate()
    train = train_rate(cfg, steps=a.steps, profile=a.profile)
    profile = train.pop("profile", None)
    train["flops_per_step"] = step_flops(preset, a.overrides)
    train["achieved_flops_per_s"] = train["flops_per_step"] / train["step_s"]
    train["mfu"] = train["achieved_flops_per_s"] / rate
    imag = None if a.train_only else imagine_rate(cfg, a.imagine_batch or (1024 if gpu else 16), a.horizon)
    # on a host of several GPUs `make bench` also measures how training scales over them (one compile
    # per device count and sharding; the one-device row is the step timed above)
    counts = [c for c in (1, 2, 4, 8, 16) if c <= jax.device_count()]
    grid = scaling(preset, a.overrides, counts=counts, steps=a.steps, one_device=train) \
        if gpu and len(counts) > 1 else None
    report = {"device": device_name(), "config": preset, "overrides": list(a.overrides),
              "bf16_matmul_flops_per_s": rate, "train": train, "imagine": imag, "profile": profile, "scaling": grid}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(a.out, report)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
