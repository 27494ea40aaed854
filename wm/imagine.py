"""Imagination: the world model as an environment. A pure, jittable `step(state, action) -> state`
over a sliding buffer of the last K latent frames (and, with `model.imagine="cache"`, the attention
keys and values each of them had when it was read), an open-loop rollout from a given action
sequence, and a closed-loop rollout in which a policy of the project's protocol
(`act(params, obs, carry, rng) -> (action, carry)`, obs {"image", "proprio"}) sees decoded frames
and predicted proprioception.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sim_data.sim.tasks import LATCHED_TASKS
from sim_data.util import pad_with_last
from wm.model import INPUT_CLIP, ModelConfig, WorldModel


@struct.dataclass
class Norm:
    """Input standardisation: proprio and action mean and std (37,), (20,); the scene state's (24,)
    (sim_data.sim.scene.scene_state), standardising the target of a model with `model.scene`, where
    the statistics have it (None in those written before it was recorded)."""

    proprio_mean: jax.Array
    proprio_std: jax.Array
    action_mean: jax.Array
    action_std: jax.Array
    scene_mean: jax.Array | None = None
    scene_std: jax.Array | None = None

    def proprio(self, p):
        return jnp.clip((p - self.proprio_mean) / self.proprio_std, -INPUT_CLIP, INPUT_CLIP)

    def unproprio(self, p):
        return p * self.proprio_std + self.proprio_mean

    def action(self, a):
        """Standardised actions, clipped: a policy may command what no training episode did."""
        return jnp.clip((a - self.action_mean) / self.action_std, -INPUT_CLIP, INPUT_CLIP)

    def scene(self, s):
        """The standardised scene state (..., 24), clipped like the inputs: an object that moves where no
        training episode moved it (a block knocked off the counter) must not outweigh every other loss."""
        if self.scene_mean is None:
            raise ValueError("these statistics have no scene state (norm.json predates it): a model with "
                             "model.scene trains on a dataset cache that records it (rebuild the cache)")
        return jnp.clip((s - self.scene_mean) / self.scene_std, -INPUT_CLIP, INPUT_CLIP)

    def to_dict(self) -> dict:
        keys = ("proprio_mean", "proprio_std", "action_mean", "action_std", "scene_mean", "scene_std")
        return {k: np.asarray(getattr(self, k)).tolist() for k in keys if getattr(self, k) is not None}

    @classmethod
    def from_dict(cls, d: dict) -> Norm:
        return cls(**{k: jnp.asarray(v, jnp.float32) for k, v in d.items()})


@struct.dataclass
class ImagineState:
    """The last K frames the dynamics sees (leaves (B, K, ...)); slot K-1 is the current frame.

    Attributes:
      z: (B, K, 8, 8, C) latents; proprio: (B, K, 37) normalised; action: (B, K, 20) normalised
      (slot K-1 is filled by the next step); valid: (B, K) bool; frame: (B, S, S, 3) float32 in
      [0, 1], the current frame (decoded, or the last context frame); success: (B,) probability that
      the current frame is a success; outcome: (B,) predicted probability of the episode's success;
      progress: (B,) predicted task progress in [0, 1] (sim_data.sim.tasks.task_progress);
      scene: with cfg.scene, (B, scene_dim) the scene state predicted for the current frame, standardised
      (Norm.scene; zeros for a context frame); (B, 0) otherwise.
      k, v: with cfg.imagine "cache", the attention keys and values of slots 0..K-2 at every layer
      (B, depth, K-1, N, heads, D/heads), in the compute dtype; (B, 0) otherwise.
      anchor: with cfg.anchor, the latents (B, 8, 8, C) of the episode's first frame, which every
      prediction also sees; (B, 0) otherwise.
      clock: (B,) int32, the index in its episode of the current frame (slot K-1; the first frame's is 0).
      draw: (B,) uint32, a hash of the context's first frame (frame_hash): with clock, what the frame
      generator's noise is drawn from (refine_noise).
    """

    z: jax.Array
    proprio: jax.Array
    action: jax.Array
    valid: jax.Array
    frame: jax.Array
    success: jax.Array
    outcome: jax.Array
    progress: jax.Array
    scene: jax.Array
    k: jax.Array
    v: jax.Array
    anchor: jax.Array
    clock: jax.Array
    draw: jax.Array


def anchor_latents(cfg: ModelConfig, params, frames, anchor=None) -> jax.Array:
    """The anchor of imagined episodes (ImagineState.anchor): with cfg.anchor the latents (B, 8, 8, C)
    of anchor (B, S, S, 3) uint8, the episodes' first frames, or where it is None of the context's first
    frames (frames (B, C, S, S, 3): right for a context that starts the episode); (B, 0) without."""
    b = frames.shape[0]
    if not cfg.anchor:
        return jnp.zeros((b, 0))
    first = frames[:, 0] if anchor is None else anchor
    return WorldModel(cfg).apply({"params": params}, first, method=WorldModel.encode)


def buffer_time(clock, k: int) -> jax.Array:
    """(B,) the episode index of a buffer's slot K-1 -> (B, K) int32 those of its K slots (negative
    for the empty slots before an episode's first frame)."""
    return (clock[:, None] - (k - 1) + jnp.arange(k)).astype(jnp.int32)


def init_state(cfg: ModelConfig, params, norm: Norm, frames, proprio, actions, anchor=None, start=None) -> ImagineState:
    """A buffer from C <= K context observations.

    frames: (B, C, S, S, 3) uint8; proprio: (B, C, 37); actions: (B, C-1, 20), those between them;
    anchor: (B, S, S, 3) uint8, the episodes' first frames, for a model with an anchor whose context
    starts later in the episode (default: the context's first frames); start: (B,) int, the index in
    its episode of the context's first frame (default 0: the context starts the episode).
    """
    model = WorldModel(cfg)
    b, c = frames.shape[:2]
    k = cfg.context
    if c > k:
        raise ValueError(f"{c} context frames exceed the model's context of {k}")
    z = model.apply({"params": params}, frames, method=WorldModel.encode)
    pad = k - c

    def place(x):
        return jnp.concatenate([jnp.zeros((b, pad) + x.shape[2:], x.dtype), x], axis=1)

    acts = jnp.concatenate([norm.action(actions), jnp.zeros((b, 1, cfg.action_dim))], axis=1)
    valid = jnp.concatenate([jnp.zeros((b, pad), bool), jnp.ones((b, c), bool)], axis=1)
    z, p, a = place(z), place(norm.proprio(proprio)), place(acts)
    first = anchor_latents(cfg, params, frames, anchor)
    clock = jnp.broadcast_to(jnp.asarray(0 if start is None else start, jnp.int32), (b,)) + c - 1
    k = v = jnp.zeros((b, 0))
    if cfg.imagine == "cache":  # slot K-1's keys wait for its action: the first step computes them
        out = model.apply({"params": params}, z, p, a, valid, with_kv=True, anchor=first,
                          time=buffer_time(clock, cfg.context), method=WorldModel.predict)
        k, v = out["k"][:, :, :-1], out["v"][:, :, :-1]
    return ImagineState(z=z, proprio=p, action=a, valid=valid,
                        frame=frames[:, -1].astype(jnp.float32) / 255.0, success=jnp.zeros((b,)),
                        outcome=jnp.zeros((b,)), progress=jnp.zeros((b,)), scene=jnp.zeros((b, cfg.scene_width)),
                        k=k, v=v, anchor=first, clock=clock, draw=frame_hash(frames[:, 0]))


def empty_cache(cfg: ModelConfig, b: int) -> tuple:
    """The keys and values of K-1 empty slots, (B, depth, K-1, N, heads, D/heads) each, for
    cfg.imagine "cache"; (B, 0) otherwise."""
    if cfg.imagine != "cache":
        return jnp.zeros((b, 0)), jnp.zeros((b, 0))
    shape = (b, cfg.depth, cfg.context - 1, cfg.tokens_per_frame, cfg.heads, cfg.dim // cfg.heads)
    return jnp.zeros(shape, cfg.compute_dtype), jnp.zeros(shape, cfg.compute_dtype)


def predict_next(cfg: ModelConfig, params, z, proprio, action, valid, cache: tuple, anchor, clock,
                 noise=None) -> tuple[dict, tuple]:
    """The dynamics' prediction for the frame after a buffer's last slot: z (B, K, 8, 8, C), proprio
    (B, K, 37), action (B, K, 20) normalised, valid (B, K) bool; cache: (k, v) of slots 0..K-2 (cfg.imagine
    "cache") or unused; anchor: ImagineState.anchor (anchor_latents); clock: (B,) int, the episode index
    of slot K-1 (ImagineState.clock); noise: with cfg.stochastic = S, (B, S) standard normal draws for
    the prediction's code (None: the prior's mean). Returns (predict's outputs at slot K-1, leaves (B,
    ...), the cache of slots 1..K-1: what the buffer's next step reads once it has pushed a frame)."""
    model = WorldModel(cfg)
    if cfg.imagine != "cache":
        draws = None if noise is None else jnp.broadcast_to(noise[:, None], z.shape[:2] + noise.shape[1:])
        out = model.apply({"params": params}, z, proprio, action, valid, anchor=anchor,
                          time=buffer_time(clock, z.shape[1]), noise=draws, method=WorldModel.predict)
        return {key: x[:, -1] for key, x in out.items()}, cache
    past = {"k": cache[0], "v": cache[1], "valid": valid[:, :-1]}
    out = model.apply({"params": params}, z[:, -1:], proprio[:, -1:], action[:, -1:], past=past,
                      anchor=anchor, time=clock[:, None], noise=None if noise is None else noise[:, None],
                      method=WorldModel.predict)
    cache = tuple(jnp.concatenate([c[:, :, 1:], out.pop(key)], axis=2) for c, key in zip(cache, ("k", "v")))
    return {key: x[:, -1] for key, x in out.items()}, cache


REFINE_SEED = 7  # the frame generator's noise: one draw per episode and step, whatever the batch


def frame_hash(frames) -> jax.Array:
    """(B, S, S, 3) uint8 -> (B,) uint32, a multiplicative hash of each frame's pixels (integer
    arithmetic: the same on every backend)."""
    flat = frames.reshape(frames.shape[0], -1).astype(jnp.uint32)
    weights = jnp.arange(flat.shape[1], dtype=jnp.uint32) * jnp.uint32(2654435761) + jnp.uint32(1)
    return jnp.sum(flat * weights, axis=1, dtype=jnp.uint32)


def refine_noise(draw, clock, shape: tuple) -> jax.Array:
    """Standard normal noise (B, *shape) for the frame generator (ModelConfig.refine), drawn from each
    episode's draw (ImagineState.draw: its context's first frame) and the step its frame is imagined
    for (clock (B,) int): an episode's draws do not depend on which batch or chunk it is imagined in,
    every policy from the same state sees the same noise, and each state its own."""
    base = jax.random.PRNGKey(REFINE_SEED)
    return jax.vmap(lambda d, c: jax.random.normal(jax.random.fold_in(jax.random.fold_in(base, d), c), shape))(
        draw, clock)


def step(cfg: ModelConfig, params, norm: Norm, state: ImagineState, action, noise=None) -> ImagineState:
    """Advances every imagined episode by one control step under action (B, 20); noise: a stochastic
    model's draws (B, S) for its code (predict_next; None: the prior's mean)."""
    model = WorldModel(cfg)
    acts = state.action.at[:, -1].set(norm.action(action))
    out, (k, v) = predict_next(cfg, params, state.z, state.proprio, acts, state.valid, (state.k, state.v),
                               state.anchor, state.clock, noise)

    def push(buf, new):
        return jnp.concatenate([buf[:, 1:], new[:, None]], axis=1)

    z_next = out["z"]
    frame, keep = model.apply({"params": params}, z_next, state.frame, out["flow"], with_keep=True,
                              method=WorldModel.decode)
    if cfg.refine:
        frame = model.apply({"params": params}, frame, z_next, refine_noise(state.draw, state.clock, frame.shape[1:]),
                            method=WorldModel.sample_frame)
        if keep is not None:  # the generator's draw does not move what the gate keeps
            frame = jnp.where(keep[..., None] > cfg.keep_threshold, state.frame, frame)
    # kept on the uint8 grid: a change under half a level vanishes instead of accumulating over a long
    # rollout, so what the model leaves still stays exactly still (and the policy sees this frame)
    frame = to_uint8(frame)
    if cfg.reencode:
        z_next = model.apply({"params": params}, frame, method=WorldModel.encode)
    frame = frame.astype(jnp.float32) / 255.0
    return ImagineState(
        z=push(state.z, z_next), proprio=push(state.proprio, out["proprio"]),
        action=push(acts, jnp.zeros_like(acts[:, -1])), valid=push(state.valid, jnp.ones_like(state.valid[:, -1])),
        frame=frame, success=jax.nn.sigmoid(out["success"]), outcome=jax.nn.sigmoid(out["outcome"]),
        progress=jax.nn.sigmoid(out["progress"]), scene=out["scene"] if cfg.scene else state.scene, k=k, v=v,
        anchor=state.anchor, clock=state.clock + 1, draw=state.draw)


def episode_success(success, task: str):
    """(B, T) per-step success probabilities of imagined episodes of task -> (B,) the episode's
    predicted success: for a latched task (LATCHED_TASKS: once met, it stays) the highest over time,
    since a model that sees only its last K frames may forget it was met (the lifted mug put down);
    for the others the last step's, as the simulator judges them (a base driven on past the band was
    inside it on the way)."""
    s = jnp.asarray(success)
    return jnp.max(s, axis=1) if task in LATCHED_TASKS else s[:, -1]


def step_features(norm: Norm, state: ImagineState, action) -> jax.Array:
    """What the episode judge (wm.judge) reads of one imagined step, (B, F) with F = feature_dim(cfg):
    the predicted proprioception (standardised), the action taken (standardised), the new latent grid
    pooled to 2x2 cells, with cfg.scene the predicted scene state (standardised), the per-step success
    and outcome probabilities and the predicted progress."""
    return _join_features(state.proprio[:, -1], norm.action(action), state.z[:, -1], state.scene,
                          (state.success, state.outcome, state.progress))


def _join_features(proprio, action, z, scene, heads) -> jax.Array:
    """(B, F) step features, blocks in FEATURE_GROUPS order: proprio (B, 37) and action (B, 20)
    standardised, the latent grid z (B, s, s, C) pooled, the scene state (B, cfg.scene_width), heads
    (success, outcome, progress) each (B,)."""
    return jnp.concatenate([proprio, action, pool_latents(z), scene] + [h[:, None] for h in heads], axis=-1)


def pool_latents(z) -> jax.Array:
    """(B, s, s, C) latent grids -> (B, 4C): their means over 2x2 cells."""
    b, s, _, c = z.shape
    return z.reshape(b, 2, s // 2, 2, s // 2, c).mean(axis=(2, 4)).reshape(b, 4 * c)


SUCCESS_FEATURE, OUTCOME_FEATURE, PROGRESS_FEATURE = -3, -2, -1  # where step_features keeps the heads' outputs


def _feature_sizes(cfg: ModelConfig) -> tuple:
    """The widths of step_features' blocks, in FEATURE_GROUPS order."""
    return (cfg.proprio_dim, cfg.action_dim, 4 * cfg.latent, cfg.scene_width, 1, 1, 1)


def feature_dim(cfg: ModelConfig) -> int:
    """F, the width of step_features' rows for a model of cfg."""
    return sum(_feature_sizes(cfg))


# step_features' blocks, in order ("scene" is empty for a model without the scene head)
FEATURE_GROUPS = ("proprio", "action", "latent", "scene", "success", "outcome", "progress")


def feature_columns(cfg: ModelConfig, groups) -> np.ndarray:
    """The columns of step_features holding the named FEATURE_GROUPS, in feature order: (K,) int."""
    unknown = set(groups) - set(FEATURE_GROUPS)
    if unknown or not groups:
        raise ValueError(f"feature groups are among {', '.join(FEATURE_GROUPS)}; got {list(groups)}")
    starts = np.cumsum((0,) + _feature_sizes(cfg))
    cols = np.concatenate([np.arange(starts[k], starts[k + 1]) for k, g in enumerate(FEATURE_GROUPS) if g in groups])
    if not len(cols):
        raise ValueError(f"feature groups {list(groups)} hold no columns for this model (\"scene\" needs model.scene)")
    return cols


def current_observation(norm: Norm, state: ImagineState) -> dict:
    """What a policy sees: {"image": (B, S, S, 3) uint8 current frame, "proprio": (B, 37)}."""
    return {"image": to_uint8(state.frame), "proprio": norm.unproprio(state.proprio[:, -1])}


def to_uint8(x):
    """Frames in [0, 1], any shape, as uint8 images: scaled by 255, rounded and clipped."""
    return jnp.clip(jnp.round(x * 255.0), 0, 255).astype(jnp.uint8)


SEGMENT = 20  # imagined steps per compiled call: one program serves every horizon
DYNAMICS_STREAM = 1 << 20  # closed_loop's stochastic codes draw from fold_in(rng, this), apart from the policy's keys


OPEN_LOOP_OUTPUTS = ("frames", "proprio", "success", "outcome", "progress", "features")


def open_loop(cfg: ModelConfig, params, norm: Norm, frames, proprio, context_actions, actions, anchor=None,
              start=None, keys=OPEN_LOOP_OUTPUTS) -> dict:
    """Imagines H steps from C context observations under logged actions.

    frames (B, C, S, S, 3) uint8, proprio (B, C, 37), context_actions (B, C-1, 20), actions (B, H, 20)
    (action h follows imagined frame h-1, the first follows the last context frame); anchor, start: the
    episodes' first frames (B, S, S, 3) uint8 and the contexts' indices (B,) in their episodes where the
    context starts later (init_state). A stochastic model (cfg.stochastic) takes its prior's mean code
    at every step: the open-loop figures score its central future, closed_loop samples.
    Returns {"frames": (B, H, S, S, 3) uint8, "proprio": (B, H, 37), "success": (B, H),
    "outcome": (B, H), "progress": (B, H), "features": (B, H, F) (step_features)} for frames C .. C+H-1
    after the context, numpy arrays: those named in `keys` (the others, the frames above all, are not
    copied off the device). The steps run in compiled segments of SEGMENT steps (the last one padded
    with zero actions whose steps are dropped), so that every horizon shares one program.
    """
    h = actions.shape[1]
    if h < 1:
        raise ValueError("open_loop imagines at least one step: actions must be (B, H >= 1, 20)")
    unknown = [k for k in keys if k not in OPEN_LOOP_OUTPUTS]
    if unknown or not keys:
        raise ValueError(f"open_loop returns some of {', '.join(OPEN_LOOP_OUTPUTS)}; got keys {tuple(keys)}")
    state = _open_loop_start(cfg, params, norm, frames, proprio, context_actions, anchor, start)
    # padded and cut on the host: eager slices of a device array would compile a program per shape
    acts = np.asarray(actions, np.float32)
    acts = np.pad(acts, ((0, 0), (0, -h % SEGMENT), (0, 0)))
    parts = []
    for t0 in range(0, h, SEGMENT):
        state, got = _open_loop_segment(cfg, params, norm, state, acts[:, t0:t0 + SEGMENT])
        parts.append(got)
    return {k: np.concatenate([np.asarray(p[k]) for p in parts], axis=1)[:, :h] for k in keys}


_open_loop_start = jax.jit(init_state, static_argnums=(0,))


@functools.partial(jax.jit, static_argnums=(0,))
def _open_loop_segment(cfg: ModelConfig, params, norm: Norm, state: ImagineState, actions):
    """SEGMENT steps of open_loop from state under actions (B, SEGMENT, 20): (state, outputs)."""
    def body(st, a):
        st = step(cfg, params, norm, st, a)
        return st, (to_uint8(st.frame), norm.unproprio(st.proprio[:, -1]), st.success, st.outcome, st.progress,
                    step_features(norm, st, a))

    state, (f, p, s, o, g, x) = jax.lax.scan(body, state, jnp.swapaxes(actions, 0, 1))
    sw = functools.partial(jnp.swapaxes, axis1=0, axis2=1)
    return state, {"frames": sw(f), "proprio": sw(p), "success": s.T, "outcome": o.T, "progress": g.T,
                   "features": sw(x)}


def closed_loop(cfg: ModelConfig, policy, horizon: int, params, norm: Norm, policy_params, frames, proprio,
                context_actions, rng, anchor=None, start=None, policy_keys=None) -> dict:
    """A policy acting inside the world model for `horizon` steps from C context observations (anchor,
    start: the episodes' first frames (B, S, S, 3) uint8 and the contexts' indices (B,) in their
    episodes where the context starts later: init_state).

    The policy's carry starts from `policy.init_carry(policy_params, obs, None, k_init)` on the last
    context observation and its step t acts with `fold_in(k_act, t)`, (k_init, k_act) split from rng or
    given as policy_keys: an evaluation gives the keys its simulated episodes' policy drew from
    (sim_data.sim.rollout's), so that a stochastic policy draws alike in the simulator and in
    imagination. A stochastic model (cfg.stochastic) draws each step's code from its prior with keys
    of its own, derived from rng, each episode's from its first frame and step (ImagineState.draw,
    clock), so that it does not depend on the episode's row or batch. The steps run in compiled segments of SEGMENT steps, so
    that horizons of every task share one program (the last segment's surplus steps are dropped).
    Returns {"frames":
    (B, horizon, S, S, 3) uint8, "proprio": (B, horizon, 37), "success": (B, horizon), "outcome":
    (B, horizon), "progress": (B, horizon), "action": (B, horizon, 20), "features": (B, horizon, F)}.
    """
    carry, keys = _closed_loop_start(cfg, policy, params, norm, policy_params, frames, proprio, context_actions, rng,
                                     anchor, start, policy_keys)
    parts = []
    for t0 in range(0, horizon, SEGMENT):
        carry, got = _closed_loop_segment(cfg, policy, params, norm, policy_params, carry, keys, t0)
        parts.append(got)
    return {k: jnp.concatenate([p[k] for p in parts], axis=1)[:, :horizon] for k in parts[0]}


@functools.partial(jax.jit, static_argnums=(0, 1))
def _closed_loop_start(cfg: ModelConfig, policy, params, norm: Norm, policy_params, frames, proprio, context_actions,
                       rng, anchor, start, policy_keys=None):
    state = init_state(cfg, params, norm, frames, proprio, context_actions, anchor, start)
    k_init, k_act = jax.random.split(rng) if policy_keys is None else policy_keys
    k_code = jax.random.fold_in(rng, DYNAMICS_STREAM)
    obs = {"image": frames[:, -1], "proprio": proprio[:, -1]}
    return (state, obs, policy.init_carry(policy_params, obs, None, k_init)), (k_act, k_code)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _closed_loop_segment(cfg: ModelConfig, policy, params, norm: Norm, policy_params, carry, keys, t0):
    k_act, k_code = keys

    def body(c, t):
        st, ob, pc = c
        action, pc = policy.act(policy_params, ob, pc, jax.random.fold_in(k_act, t))
        noise = None
        if cfg.stochastic:  # each episode's own draws (its first frame's hash and step), whatever its batch row
            noise = jax.vmap(lambda d, c: jax.random.normal(jax.random.fold_in(jax.random.fold_in(k_code, d), c),
                                                            (cfg.stochastic,)))(st.draw, st.clock)
        st = step(cfg, params, norm, st, action, noise)
        ob = current_observation(norm, st)
        return (st, ob, pc), (ob["image"], ob["proprio"], st.success, st.outcome, st.progress, action,
                              step_features(norm, st, action))

    carry, (f, p, s, o, g, a, x) = jax.lax.scan(body, carry, t0 + jnp.arange(SEGMENT))
    sw = functools.partial(jnp.swapaxes, axis1=0, axis2=1)
    return carry, {"frames": sw(f), "proprio": sw(p), "success": s.T, "outcome": o.T, "progress": g.T,
                   "action": sw(a), "features": sw(x)}


def observed_features(cfg: ModelConfig, params, norm: Norm, frames, proprio, actions) -> jax.Array:
    """The episode judge's features of a true episode: what step_features would read had the world
    model imagined every frame exactly. frames (B, T+1, S, S, 3) uint8, proprio (B, T+1, 37), actions
    (B, T, 20) -> (B, T, F): for step t, the true proprioception and encoded frame t+1, action t, and
    the success, outcome and progress heads' outputs given the true context up to frame t and action t.
    The judge's reading of these is what it would read were imagination exact. Runs in
    compiled segments of SEGMENT steps (the last one padded), so every episode length shares one program."""
    b, t = actions.shape[:2]
    k = cfg.context
    latent = jax.eval_shape(lambda f: WorldModel(cfg).apply({"params": params}, f, method=WorldModel.encode),
                            jax.ShapeDtypeStruct((b,) + frames.shape[2:], frames.dtype))
    buf = (jnp.zeros((b, k) + latent.shape[1:], latent.dtype), jnp.zeros((b, k, proprio.shape[-1])),
           jnp.zeros((b, k, actions.shape[-1])), jnp.zeros((b, k), bool), empty_cache(cfg, b),
           _first_latents(cfg, params, frames[:, :1]), jnp.full((b,), -1, jnp.int32))
    parts = []
    for t0 in range(0, t, SEGMENT):
        n = min(SEGMENT, t - t0)
        pad = ((0, 0), (0, SEGMENT - n)) + ((0, 0),) * (frames.ndim - 2)
        f = jnp.pad(frames[:, t0:t0 + n + 1], pad, mode="edge")  # on the device the episodes are on
        p = jnp.pad(proprio[:, t0:t0 + n + 1], pad[:3], mode="edge")
        a = jnp.pad(actions[:, t0:t0 + n], pad[:3])
        buf, x = _observed_segment(cfg, params, norm, buf, f, p, a)
        parts.append(x[:, :n])
    return jnp.concatenate(parts, axis=1)


_first_latents = jax.jit(anchor_latents, static_argnums=(0,))


@functools.partial(jax.jit, static_argnums=(0,))
def _observed_segment(cfg: ModelConfig, params, norm: Norm, buf, frames, proprio, actions):
    """SEGMENT steps of observed_features: frames (B, SEGMENT+1, ...), proprio (B, SEGMENT+1, 37),
    actions (B, SEGMENT, 20); buf: the context buffers (latents, proprio, actions, valid, the keys
    and values of cfg.imagine "cache", the episodes' anchor, the episode index of the last frame
    pushed) carried over."""
    model = WorldModel(cfg)
    b = frames.shape[0]
    z = jax.lax.map(lambda f: model.apply({"params": params}, f, method=WorldModel.encode),
                    jnp.swapaxes(frames, 0, 1))  # (SEGMENT+1, B, 8, 8, C), a frame at a time
    p, a = jnp.swapaxes(norm.proprio(proprio), 0, 1), jnp.swapaxes(norm.action(actions), 0, 1)

    def push(buf, new):
        return jnp.concatenate([buf[:, 1:], new[:, None]], axis=1)

    def body(buf, t):
        zb, pb, ab, vb = (push(x, y) for x, y in zip(buf[:4], (z[t], p[t], a[t], jnp.ones((b,), bool))))
        clock = buf[6] + 1
        out, cache = predict_next(cfg, params, zb, pb, ab, vb, buf[4], buf[5], clock)
        scene = out["scene"] if cfg.scene else jnp.zeros((b, 0))
        x = _join_features(p[t + 1], a[t], z[t + 1], scene,
                           [jax.nn.sigmoid(out[k]) for k in ("success", "outcome", "progress")])
        return (zb, pb, ab, vb, cache, buf[5], clock), x

    buf, x = jax.lax.scan(body, buf, jnp.arange(SEGMENT))
    return buf, jnp.swapaxes(x, 0, 1)


# on an H200 chunks of 512 imagined the judge's 5,011 training episodes no faster than chunks of 64
# (110 s each) and compiled a program for every power of two the episodes' groups came to (docs/benchmarks.md)
CHUNK = 64


def chunk_size(n: int) -> int:
    """The batch size that n samples are imagined in: CHUNK, or for fewer samples the next power of two
    (so that few batch sizes compile)."""
    return CHUNK if n > CHUNK else 1 << (n - 1).bit_length()


def padded_chunks(items: list):
    """(start, part, n) over items in chunks of chunk_size(len(items)): each part padded with its last
    item to the chunk's size (one batch size, one compilation), its first n items real."""
    size = chunk_size(len(items))
    for start in range(0, len(items), size):
        part = items[start:start + size]
        yield start, pad_with_last(part, size), len(part)


def context_sample(ep: dict, camera: str, start: int, context: int, horizon: int) -> dict:
    """From an episode (sim_data.dataset.cache's episode dict): `context` observations from `start`, the
    `horizon` logged actions that follow, the episode's first frame (the anchor) and `start`, as
    open_loop_chunked takes them."""
    c0, c1 = start, start + context
    return {"frames": ep["frames"][camera][c0:c1], "proprio": ep["proprio"][c0:c1],
            "context_actions": ep["action"][c0:c1 - 1], "actions": ep["action"][c1 - 1:c1 - 1 + horizon],
            "anchor": ep["frames"][camera][0], "start": np.int32(start)}


def open_loop_chunked(cfg: ModelConfig, params, norm: Norm, samples: list[dict], horizon: int,
                      keys=OPEN_LOOP_OUTPUTS) -> dict:
    """open_loop over samples {"frames" (C, S, S, 3), "proprio" (C, 37), "context_actions" (C-1, 20),
    "actions" (horizon, 20), optionally "anchor" (S, S, 3) the episode's first frame and "start" () the
    context's index in it} in chunks of chunk_size (the last one padded, so one compilation serves
    all); its outputs named in `keys`, numpy arrays with a leading axis of len(samples)."""
    outs = []
    for _, part, n in padded_chunks(samples):
        stack = {k: np.stack([s[k] for s in part]) for k in part[0]}
        got = open_loop(cfg, params, norm, stack["frames"], stack["proprio"], stack["context_actions"],
                        stack["actions"][:, :horizon], stack.get("anchor"), stack.get("start"), keys)
        outs.append({k: np.asarray(v)[:n] for k, v in got.items()})
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}
