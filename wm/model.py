"""The world model: a frame tokenizer (convolutional autoencoder to a latent grid) and an
action-conditioned dynamics transformer over latents with heads for proprioception and success.

Shapes: frames (B, T, S, S, 3) uint8 with S = 64 or 128; latents (B, T, 8, 8, C) in [-1, 1];
actions (B, T, 20) where action t follows frame t; proprio (B, T, 37).

The dynamics model sees, for every frame t, the tokens of frames t-K+1 .. t (K = `context`, a
sliding window, block-causal in time, with a learned per-head bias for each frame distance) and
predicts frame t+1's latents, proprioception, success flag (logit) and the episode's outcome
(logit). A small MLP first predicts the next proprioception from the current one and the action
(the robot's own dynamics, blind to the scene); each frame's action, proprioception and that
prediction condition its tokens through adaptive layer norm (shift, scale and gate per block,
zero-initialised as in DiT), and the tokens add a visual correction to the next proprioception. Parameters are float32; compute
runs in `ModelConfig.dtype` (bfloat16 by default).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from sim_data.sim.robot import (
    PROPRIO_BASE_VEL,
    PROPRIO_DIM,
    PROPRIO_HAND_CLOSURE,
    PROPRIO_JOINT_POS,
    PROPRIO_JOINT_VEL,
)
from sim_data.util import jit_initialiser

LATENT_SIDE = 8
INPUT_CLIP = 10.0  # standardised proprio and actions are clipped to +-INPUT_CLIP, predicted proprio too
IMAGINE_MODES = ("window", "cache")
# the proprioception groups ModelConfig.blind may name (sim_data.sim.robot's layout)
BLIND_GROUPS = {"joints": PROPRIO_JOINT_POS, "joint_vel": PROPRIO_JOINT_VEL, "base": PROPRIO_BASE_VEL,
                "hands": PROPRIO_HAND_CLOSURE}
COPY_BIAS = 4.0  # the compose mask's initial logit: an untrained decoder passes the previous frame through (98%)
# the frame generator's noise, in pixel units ([0, 1]): above the spread of what it adds to the decoded frame
# (a few hundredths at one step, about a tenth at eight), so that its first step starts from noise alone
REFINE_SIGMA = 0.2


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Attributes:
      size: frame side (64 or 128); tokenizer: "conv" (a convolutional autoencoder, channels its
        widths, one stride-2 stage each: log2(size / 8) stages) or "patch" (an MLP over each 8x8
        cell's pixels with 3x3 mixing at the latent grid, channels[-1] its width: cheap, for CPUs);
      latent: latent channels; patch: latent cells per token side.
      dim, depth, heads, mlp: the transformer; context: K, frames each prediction sees.
      proprio_dim, action_dim: input sizes; dtype: compute dtype ("bfloat16" or "float32").
      compose: the decoder composes its output with the previous frame through a predicted mask
        (False: the latents alone make the frame).
      warp: the dynamics also predicts a flow field (8x8, upsampled) that warps the previous frame
        before the decoder composes with it, as the spatial-transformer predictors of Finn et al.
        2016: the view turning and the arms moving become displacements of pixels already seen.
      upsample: how the conv decoder doubles its resolution: "resize" (nearest neighbour, then a 3x3
        convolution at the doubled resolution) or "shuffle" (a 3x3 convolution to 4x the channels at
        the lower resolution, then depth-to-space: Shi et al. 2016's sub-pixel convolution; the same
        products over a quarter of the positions with 4x wider outputs).
      keep: the decoder also predicts, per pixel, whether it keeps the previous frame's value exactly
        (unwarped): a still robot in a still scene renders identical frames, which a warp of even a
        fraction of a pixel, or a composition mask short of 1, would blur (needs compose).
      keep_threshold: the gate keeps a pixel where its logit exceeds this (0: probability 0.5); the
        gate learns from its cross-entropy whatever the threshold, so a trained model may be evaluated
        at another (`python -m wm.quality ... model.keep_threshold=2`).
      reencode: imagination feeds each decoded frame back through the encoder (its 8-bit image, as
        a real frame would be) instead of the predicted latents, so that the dynamics always reads
        latents of images (what teacher-forced training shows it) however far it imagines;
        an imagination setting (wm.imagine.step), without effect on training.
      imagine: how imagination gives the dynamics its past (an imagination setting, without effect
        on training): "window" runs the transformer over the last K frames at every step, so the
        oldest frames of the buffer see only the frames still in it (what a training window's first
        K frames see); "cache" keeps each frame's attention keys and values from the step it was
        read, so every frame keeps what it saw then (sliding-window attention over the whole
        episode, as in a training window's later frames) and a step runs one frame's tokens through
        the transformer instead of K frames'. The two rank the `full` zoo alike on one model
        (docs/world-model.md); "cache" imagines 1.6 times as fast on an H200.
      anchor: every frame's prediction also attends to the episode's first frame (its tokens' keys
        and values at every layer, from their own projection of the frame's input tokens, with a
        learned attention bias per head and per span of frames since the first, ANCHOR_SPANS): the
        scene as it was before the robot touched it, sharp however far the context has slid from
        the start (training windows start anywhere in an episode, so without it a window's frames
        never see the episode's first), and weighed by how long ago it was.
      scan_layers: the transformer's layers as one block scanned over depth (parameters stacked on a
        leading depth axis, "layers") instead of depth blocks written out (Block_0, ...): the compiled
        programs hold one layer (the `full` train step at depth 8 lowers and compiles in 16.0 s against
        19.1 s on a 2-core CPU; on a GPU neither its compile nor its step time is measured yet, so no
        preset scans); the two layouts' parameters differ in their initial draw, not in what they compute.
      stochastic: the size of a per-frame stochastic latent (0: none, a deterministic dynamics). Each
        prediction draws a code w from a learned prior given what the transformer read (in training, from
        a posterior that also sees the true next latents, as SVG-LP, Denton and Fergus 2018), and a
        residual layer conditioned on w acts on every token before the output heads: where the context
        leaves the next frame open (the mug held or slipping), imagined episodes sample the outcomes
        instead of regressing to one average future.
      scene: a head also predicts the next frame's scene state (scene_dim values: the objects' positions
        in the robot's frame, the mug's uprightness, the tray's and buttons' travel;
        sim_data.sim.scene.scene_state), a target the simulator records and no camera frame states
        outright: the tokens must carry where the objects are, which decides a grasp. The episode judge
        reads the prediction of every imagined step where its inputs name it (judge_inputs "scene").
      refine: the steps of a generative frame model (0: none): a small convolutional network (FrameRefiner,
        refine_channels its widths at S/2 and S/4) that draws what the decoded frame lacks, the residual
        between the true frame and the decoder's, by flow matching (a straight path from Gaussian noise of
        std REFINE_SIGMA to the residual, the network predicting the clean residual at each point, as
        Li and He 2025's x-prediction), given the decoded frame and the predicted latents. The decoder's
        regression gives the mean of the futures the latents leave open, a blur; the generator samples one
        of them, sharp. Imagination runs `refine` Euler steps per frame from noise drawn by episode and
        step (wm.imagine.refine_noise); the keep gate still copies the pixels it keeps. Training teaches it
        on the decoded frames of every pass with their gradient stopped, and its parameters are clipped
        and updated apart (wm.train.make_optimizer): the rest of the model learns as without it.
      blind: the groups of the next proprioception (BLIND_GROUPS: "joints", "joint_vel", "base", "hands",
        named in that order) predicted from the named groups' present and the action alone (BlindBody),
        without the frame tokens' correction: the base glides on its driving command and the joints
        follow their targets whatever the camera shows and the unnamed groups do, so what the body
        does next cannot be read from what the task's frames usually show, nor from the drift of an
        imagined part it does not depend on. The named groups read each other: a joint's velocity
        follows the gap between its target and its position, so name "joint_vel" with "joints".
      blind_alone: groups of blind each predicted by a BlindBody of its own, from its own present and
        the action (blind=joints,joint_vel,base with blind_alone=base drives the base from the base
        alone, whatever the imagined arms do, while the arms' groups read each other).
    """

    size: int = 64
    tokenizer: str = "conv"
    channels: tuple = (64, 128, 256)
    latent: int = 16
    patch: int = 2
    dim: int = 384
    depth: int = 8
    heads: int = 6
    mlp: int = 4
    context: int = 8
    proprio_dim: int = 37
    action_dim: int = 20
    dtype: str = "bfloat16"
    compose: bool = True
    warp: bool = True
    upsample: str = "resize"
    keep: bool = False
    keep_threshold: float = 0.0
    reencode: bool = False
    imagine: str = "cache"
    anchor: bool = False
    scan_layers: bool = False
    stochastic: int = 0
    scene: bool = False
    scene_dim: int = 24
    refine: int = 0
    refine_channels: tuple = (64, 128)
    blind: tuple = ()
    blind_alone: tuple = ()

    def validate(self) -> None:
        """Raises ValueError where the architecture is inconsistent: an unknown tokenizer, upsampler or imagine
        mode, a size other than 64 or 128 or conv channels not one per encoder stage, a patch or head count that
        does not divide, warp or keep without compose, negative stochastic or refine, bad refine_channels."""
        stages = int(round(math.log2(self.size / LATENT_SIDE)))
        if self.tokenizer not in ("conv", "patch"):
            raise ValueError(f"tokenizer must be conv or patch, got {self.tokenizer!r}")
        if self.size not in (64, 128) or (self.tokenizer == "conv" and len(self.channels) != stages):
            raise ValueError(f"size {self.size} needs {stages} encoder stages (channels), got {self.channels}")
        if LATENT_SIDE % self.patch or self.dim % self.heads:
            raise ValueError("patch must divide 8 and heads must divide dim")
        if self.upsample not in ("resize", "shuffle"):
            raise ValueError(f"upsample must be resize or shuffle, got {self.upsample!r}")
        if self.warp and not self.compose:
            raise ValueError("warp needs compose: the warped previous frame is what the decoder composes with")
        if self.keep and not self.compose:
            raise ValueError("keep needs compose: it gates the composed frame against the previous one")
        if self.imagine not in IMAGINE_MODES:
            raise ValueError(f"imagine must be one of {', '.join(IMAGINE_MODES)}, got {self.imagine!r}")
        if self.stochastic < 0:
            raise ValueError(f"stochastic is a latent's size (0: none), got {self.stochastic}")
        if self.refine < 0:
            raise ValueError(f"refine is the frame generator's steps (0: none), got {self.refine}")
        if len(self.refine_channels) != 2 or any(c < 8 or c % 8 for c in self.refine_channels):
            raise ValueError(f"refine_channels are two widths, multiples of 8 (group norm); got {self.refine_channels}")
        if list(self.blind) != [g for g in BLIND_GROUPS if g in self.blind]:
            raise ValueError(f"blind names proprioception groups, each once, in the order {', '.join(BLIND_GROUPS)} "
                             f"(one model, one name); got {list(self.blind)}")
        if list(self.blind_alone) != [g for g in self.blind if g in self.blind_alone]:
            raise ValueError(f"blind_alone names groups of blind ({', '.join(self.blind) or 'none'}), each once, in "
                             f"blind's order; got {list(self.blind_alone)}")
        if self.blind and self.proprio_dim != PROPRIO_DIM:
            raise ValueError(f"blind groups are columns of the robot's proprioception ({PROPRIO_DIM} values, "
                             f"sim_data.sim.robot); this model's proprio_dim is {self.proprio_dim}")

    @property
    def scene_width(self) -> int:
        """Columns of the predicted scene state (the head's output, imagination's, the judge's): scene_dim or 0."""
        return self.scene_dim if self.scene else 0

    @property
    def blind_paths(self) -> tuple:
        """((name, groups), ...): one BlindBody each, the groups of blind not in blind_alone together
        ("blind"), then each of blind_alone by itself ("blind_<group>")."""
        shared = tuple(g for g in self.blind if g not in self.blind_alone)
        return ((("blind", shared),) if shared else ()) + tuple((f"blind_{g}", (g,)) for g in self.blind_alone)

    def group_mask(self, groups) -> np.ndarray:
        """(proprio_dim,) bool, a constant of the program: the proprioception columns of the named groups."""
        mask = np.zeros(self.proprio_dim, bool)
        for group in groups:
            mask[BLIND_GROUPS[group]] = True
        return mask

    @property
    def blind_mask(self) -> np.ndarray:
        """(proprio_dim,) bool: the proprioception columns of every blind path's groups."""
        return self.group_mask(self.blind)

    @property
    def tokens_per_frame(self) -> int:
        return (LATENT_SIDE // self.patch) ** 2

    @property
    def compute_dtype(self):
        return jnp.dtype(self.dtype)


class ResBlock(nn.Module):
    ch: int
    dtype: jnp.dtype

    @nn.compact
    def __call__(self, x):
        h = nn.Conv(self.ch, (3, 3), dtype=self.dtype)(nn.silu(nn.GroupNorm(8, dtype=self.dtype)(x)))
        h = nn.Conv(self.ch, (3, 3), dtype=self.dtype)(nn.silu(nn.GroupNorm(8, dtype=self.dtype)(h)))
        return x + h


def space_to_depth(x, p):
    """(N, H, W, C) -> (N, H/p, W/p, p*p*C)."""
    n, h, w, c = x.shape
    return x.reshape(n, h // p, p, w // p, p, c).transpose(0, 1, 3, 2, 4, 5).reshape(n, h // p, w // p, p * p * c)


def depth_to_space(x, p):
    """(N, H, W, p*p*C) -> (N, H*p, W*p, C)."""
    n, h, w, _ = x.shape
    return x.reshape(n, h, w, p, p, -1).transpose(0, 1, 3, 2, 4, 5).reshape(n, h * p, w * p, -1)


def warp(img, flow):
    """Backward warp: (N, S, S, C) images and (N, 8, 8, 2) flows in latent cells (dy, dx; one cell is
    S/8 pixels) -> (N, S, S, C), pixel (y, x) read bilinearly at (y + dy, x + dx), clamped at the border."""
    n, s, _, c = img.shape
    f = jax.image.resize(flow.astype(jnp.float32), (n, s, s, 2), "linear") * (s / LATENT_SIDE)
    yy, xx = jnp.meshgrid(jnp.arange(s, dtype=jnp.float32), jnp.arange(s, dtype=jnp.float32), indexing="ij")
    y, x = jnp.clip(yy + f[..., 0], 0, s - 1), jnp.clip(xx + f[..., 1], 0, s - 1)
    y0, x0 = jnp.floor(y), jnp.floor(x)
    wy, wx = (y - y0)[..., None], (x - x0)[..., None]
    y0, x0 = y0.astype(jnp.int32), x0.astype(jnp.int32)
    y1, x1 = jnp.minimum(y0 + 1, s - 1), jnp.minimum(x0 + 1, s - 1)
    flat = img.reshape(n, s * s, c)

    def at(yi, xi):
        return jnp.take_along_axis(flat, (yi * s + xi).reshape(n, s * s, 1), axis=1).reshape(n, s, s, c)

    return ((1 - wy) * ((1 - wx) * at(y0, x0) + wx * at(y0, x1)) + wy * ((1 - wx) * at(y1, x0) + wx * at(y1, x1)))


def block_flow(prev, nxt, radius: int):
    """The flow that warp() needs to draw nxt from prev, estimated by block matching: for each of the
    8x8 cells of nxt, the whole-pixel shift (dy, dx), |dy|, |dx| <= radius, whose block of prev (read as
    warp reads it, clamped at the border) is nearest in summed absolute difference; ties go to the
    smaller shift. prev, nxt (N, S, S, C) float -> (flow (N, 8, 8, 2) in latent cells, as warp takes it;
    confidence (N, 8, 8) in [0, 1]: how far the best match's error lies below the mean over shifts, as a
    share of that mean, so 0 where the cell has no texture to match and near 1 where one shift stands out)."""
    n, s, _, c = prev.shape
    cell = s // LATENT_SIDE
    shifts = sorted(((dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)),
                    key=lambda d: (abs(d[0]) + abs(d[1]), d))
    padded = jnp.pad(prev, ((0, 0), (radius, radius), (radius, radius), (0, 0)), mode="edge")

    def cell_error(d):
        moved = jax.lax.dynamic_slice(padded, (0, radius + d[0], radius + d[1], 0), (n, s, s, c))
        return jnp.abs(moved - nxt).reshape(n, LATENT_SIDE, cell, LATENT_SIDE, cell, c).sum((2, 4, 5))

    errors = jnp.stack([cell_error(d) for d in shifts], axis=-1)  # (N, 8, 8, shifts)
    best = jnp.argmin(errors, axis=-1)
    flow = jnp.asarray(shifts, jnp.float32)[best] / cell
    low, mean = errors.min(-1), errors.mean(-1)
    confidence = jnp.clip((mean - low) / (mean + 1e-6), 0.0, 1.0)
    return flow, confidence


class Encoder(nn.Module):
    """(N, S, S, 3) uint8 -> (N, 8, 8, C) latents in [-1, 1]."""

    cfg: ModelConfig

    @nn.compact
    def __call__(self, frames):
        dt = self.cfg.compute_dtype
        x = frames.astype(dt) / 127.5 - 1.0
        if self.cfg.tokenizer == "patch":  # each 8x8 cell's pixels through an MLP, mixed with its neighbours
            x = space_to_depth(x, self.cfg.size // LATENT_SIDE)
            h = self.cfg.channels[-1]
            x = nn.gelu(nn.Dense(h, dtype=dt)(x))
            x = x + nn.gelu(nn.Conv(h, (3, 3), dtype=dt)(x))
            return jnp.tanh(nn.Dense(self.cfg.latent, dtype=jnp.float32)(x).astype(jnp.float32))
        x = nn.Conv(self.cfg.channels[0], (3, 3), dtype=dt)(x)
        for ch in self.cfg.channels:
            x = nn.Conv(ch, (4, 4), strides=(2, 2), dtype=dt)(x)
            x = ResBlock(ch, dt)(x)
        x = nn.silu(nn.GroupNorm(8, dtype=dt)(x))
        return jnp.tanh(nn.Conv(self.cfg.latent, (1, 1), dtype=jnp.float32)(x).astype(jnp.float32))


class Decoder(nn.Module):
    """(N, 8, 8, C) latents, the previous frame (N, S, S, 3) in [0, 1] and optionally a flow (N, 8, 8, 2)
    that warps it first -> (N, S, S, 3) float32 in [0, 1].

    The output composes a generated frame with the previous one through a predicted per-pixel mask
    (`mask * prev + (1 - mask) * generated`, as in Finn et al. 2016's CDNA), so what does not move is
    carried over exactly and the latents spend their capacity on what changes. The mask starts near
    1 (COPY_BIAS), so an untrained model is the copy-last-frame baseline and training departs from it.
    With cfg.keep a fifth output is the keep gate's logit: where it exceeds cfg.keep_threshold (0:
    probability 0.5) the pixel is the previous frame's own (unwarped) value, exactly; a hard choice,
    learnt from its cross-entropy against the pixels that truly stay the same (`wm.train`), not
    through the frame.
    """

    cfg: ModelConfig

    @nn.compact
    def __call__(self, z, prev, flow=None, with_keep=False):
        """with_keep: also return the keep gate's logits (N, S, S) (None without cfg.keep)."""
        cfg, dt = self.cfg, self.cfg.compute_dtype
        p = cfg.size // LATENT_SIDE
        still = prev.astype(jnp.float32)
        if flow is not None and cfg.warp:
            prev = warp(still, flow)
        prev_cells = space_to_depth(prev.astype(dt) * 2.0 - 1.0, p)  # (N, 8, 8, 3 p^2)

        def from_prev(width):
            """The previous frame's cells, embedded; nothing when the latents alone make the frame."""
            return nn.Dense(width, dtype=dt)(prev_cells) if cfg.compose else 0.0

        outs = 5 if cfg.keep else 4  # generated RGB, compose mask[, keep gate]
        if cfg.tokenizer == "patch":
            h = cfg.channels[-1]
            x = nn.gelu(nn.Conv(h, (3, 3), dtype=dt)(z.astype(dt)) + from_prev(h))
            x = x + nn.gelu(nn.Dense(h, dtype=dt)(x))
            out = depth_to_space(nn.Dense(outs * p * p, dtype=jnp.float32)(x).astype(jnp.float32), p)
        else:
            chans = cfg.channels[::-1]
            x = nn.Conv(chans[0], (3, 3), dtype=dt)(z.astype(dt)) + from_prev(chans[0])
            for ch in chans:
                x = ResBlock(x.shape[-1], dt)(x)
                if cfg.upsample == "shuffle":
                    x = depth_to_space(nn.Conv(4 * ch, (3, 3), dtype=dt)(x), 2)
                else:
                    n, h, w, c = x.shape
                    x = jax.image.resize(x, (n, 2 * h, 2 * w, c), "nearest")
                    x = nn.Conv(ch, (3, 3), dtype=dt)(x)
            x = nn.silu(nn.GroupNorm(8, dtype=dt)(x))
            # in the compute dtype like every other convolution: in float32 (TF32 kernels) its weight
            # gradient alone took 9 of the 118 ms of a `full` train step on an H200
            out = nn.Conv(outs, (3, 3), dtype=dt)(x).astype(jnp.float32)
        if not cfg.compose:
            frame = nn.sigmoid(out[..., :3])
            return (frame, None) if with_keep else frame
        mask = nn.sigmoid(out[..., 3:4] + COPY_BIAS)
        frame = mask * prev.astype(jnp.float32) + (1.0 - mask) * nn.sigmoid(out[..., :3])
        keep = None
        if cfg.keep:
            keep = out[..., 4]
            frame = jnp.where(keep[..., None] > cfg.keep_threshold, still, frame)
        return (frame, keep) if with_keep else frame


class FilmBlock(nn.Module):
    """A residual block whose normalised activations are scaled and shifted by an embedding (the noise
    level's), zero-initialised so that it starts unconditioned."""

    ch: int
    dtype: jnp.dtype

    @nn.compact
    def __call__(self, x, emb):
        scale, shift = jnp.split(nn.Dense(2 * self.ch, dtype=jnp.float32, kernel_init=nn.initializers.zeros)(emb), 2, -1)
        h = nn.GroupNorm(8, dtype=self.dtype)(x) * (1 + scale[:, None, None]) + shift[:, None, None]
        h = nn.Conv(self.ch, (3, 3), dtype=self.dtype)(nn.silu(h.astype(self.dtype)))
        h = nn.Conv(self.ch, (3, 3), dtype=self.dtype)(nn.silu(nn.GroupNorm(8, dtype=self.dtype)(h)))
        return x + h


def noise_level_embedding(t, width: int = 32):
    """(N,) flow times in [0, 1] -> (N, width) sinusoidal features."""
    freqs = jnp.exp(jnp.linspace(0.0, math.log(1000.0), width // 2))
    angle = t.astype(jnp.float32)[:, None] * freqs
    return jnp.concatenate([jnp.sin(angle), jnp.cos(angle)], axis=-1)


class FrameRefiner(nn.Module):
    """The frame generator's denoiser (ModelConfig.refine): the noisy residual (N, S, S, 3) in units of
    REFINE_SIGMA, the flow times (N,) in [0, 1], the decoded frame (N, S, S, 3) in [0, 1] and the
    predicted latents (N, 8, 8, C) -> its estimate of the clean residual (N, S, S, 3), in pixel units.

    A two-level U-Net at S/2 and S/4 (the pixels folded 2x2 into channels, as the sub-pixel decoder),
    the latents added at S/4 and the noise level by FiLM; the output convolution starts at zero, so that
    an untrained generator returns the decoded frame unchanged."""

    cfg: ModelConfig

    @nn.compact
    def __call__(self, x, t, base, z):
        cfg, dt = self.cfg, self.cfg.compute_dtype
        c1, c2 = cfg.refine_channels
        emb = noise_level_embedding(t)
        emb = nn.silu(nn.Dense(c2, dtype=jnp.float32)(nn.silu(nn.Dense(c2, dtype=jnp.float32)(emb))))
        h = space_to_depth(jnp.concatenate([x, base * 2.0 - 1.0], axis=-1).astype(dt), 2)
        skip = FilmBlock(c1, dt)(nn.Conv(c1, (3, 3), dtype=dt)(h), emb)
        h = nn.Conv(c2, (4, 4), strides=(2, 2), dtype=dt)(skip)
        n, side = h.shape[0], h.shape[1]
        h = h + nn.Conv(c2, (1, 1), dtype=dt)(jax.image.resize(z.astype(dt), (n, side, side, z.shape[-1]), "nearest"))
        h = FilmBlock(c2, dt)(FilmBlock(c2, dt)(h, emb), emb)
        h = depth_to_space(nn.Conv(4 * c1, (3, 3), dtype=dt)(h), 2) + skip
        h = nn.silu(nn.GroupNorm(8, dtype=dt)(FilmBlock(c1, dt)(h, emb)))
        out = nn.Conv(12, (3, 3), dtype=dt, kernel_init=nn.initializers.zeros)(h)
        return depth_to_space(out.astype(jnp.float32), 2)


def patchify(z, p):
    """(B, T, 8, 8, C) -> (B, T, (8/p)^2, p*p*C)."""
    b, t, h, w, c = z.shape
    z = z.reshape(b, t, h // p, p, w // p, p, c).transpose(0, 1, 2, 4, 3, 5, 6)
    return z.reshape(b, t, (h // p) * (w // p), p * p * c)


def unpatchify(x, p, c):
    """(B, T, N, p*p*C) -> (B, T, 8, 8, C)."""
    b, t, n, _ = x.shape
    g = int(round(math.sqrt(n)))
    x = x.reshape(b, t, g, g, p, p, c).transpose(0, 1, 2, 4, 3, 5, 6)
    return x.reshape(b, t, g * p, g * p, c)


def _frame_window(t, context):
    """Query frame minus key frame (T, T) int, and whether the key is one of the `context` frames up to
    the query (T, T) bool."""
    dist = jnp.arange(t)[:, None] - jnp.arange(t)[None, :]
    return dist, (dist >= 0) & (dist < context)


def relative_time_bias(table, t):
    """(heads, K) learned bias by frame distance -> (heads, T, T): entry [h, i, j] is table[h, i - j]
    where key frame j is one of the K frames up to query frame i, else 0 (attention_mask masks those)."""
    dist, allowed = _frame_window(t, table.shape[1])
    return jnp.where(allowed[None], table[:, jnp.clip(dist, 0, table.shape[1] - 1)], 0.0)


def attention_mask(t, n, context, valid=None):
    """The constant additive mask (B or 1, 1, T*N, T*N) of causal attention over the last `context`
    frames of N tokens each, 0 where allowed and -1e9 elsewhere; valid: optional (B, T) bool, False for
    key frames that are empty slots."""
    allowed = jnp.repeat(jnp.repeat(_frame_window(t, context)[1], n, axis=0), n, axis=1)[None, None]
    if valid is not None:
        allowed = allowed & jnp.repeat(valid, n, axis=1)[:, None, None, :]
    return jnp.where(allowed, 0.0, -1e9).astype(jnp.float32)


ANCHOR_SPAN_STARTS = (0, 1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192)
ANCHOR_SPANS = len(ANCHOR_SPAN_STARTS)  # the anchor's bias has one value per span of frames since it


def anchor_span(time):
    """Frame indices in the episode (...) int -> (...) int32, the span of their distance from the
    first frame among ANCHOR_SPAN_STARTS (0: the first frame itself; 15: 192 frames and more): exact
    near the start, where the anchor still looks like the current view, coarser further out."""
    starts = jnp.asarray(ANCHOR_SPAN_STARTS, jnp.int32)
    return (jnp.searchsorted(starts, jnp.maximum(jnp.asarray(time, jnp.int32), 0), side="right") - 1).astype(jnp.int32)


def attention_logits(q, k, time_bias, n):
    """q: (B, Tq*N, heads, d), k: (B, Tk*N, heads, d); time_bias: (heads, Tq, Tk), or (B, heads, Tq, Tk)
    for a bias that differs between samples -> (B, heads, Tq*N, Tk*N) float32 logits q.k / sqrt(d) +
    time_bias[(b,) h, frame of q, frame of k].

    The bias rides in the product itself, as T extra dimensions of each head's queries (row i of the
    head's bias) and keys (one-hot of the key's frame): its gradient then comes out of the query
    gradient's product instead of a reduction of the whole (B, heads, T*N, T*N) logit gradient over
    the batch, which took about 5% of the full preset's train step on an H200 (5.8 ms of a 112.7 ms
    step in the profile of docs/benchmarks.md).
    """
    b, tn, h, d = q.shape
    tb = time_bias if time_bias.ndim == 4 else time_bias[None]
    t = tb.shape[3]
    q_bias = jnp.repeat(tb.transpose(0, 2, 1, 3), n, axis=1).astype(q.dtype)  # (B or 1, Tq*N, heads, Tk)
    k_onehot = jnp.repeat(jnp.eye(t, dtype=k.dtype), n, axis=0)  # (Tk*N, Tk)
    q = jnp.concatenate([q / math.sqrt(d), jnp.broadcast_to(q_bias, (b, tn, h, t))], -1)
    k = jnp.concatenate([k, jnp.broadcast_to(k_onehot[:, None], (b, k.shape[1], h, t))], -1)
    return jnp.einsum("bqhd,bkhd->bhqk", q, k).astype(jnp.float32)


class Block(nn.Module):
    cfg: ModelConfig

    @nn.compact
    def __call__(self, x, cond, time_bias, mask, past=None, anchor=None):
        """x: (B, T, N, D); cond: (B, T, D); time_bias: (heads, T, P+T), or with an anchor (B, heads, T,
        A+P+T), learned bias by query and key frame (relative_time_bias, after the anchor's column);
        mask: (B or 1, 1, T*N, (A+P+T)*N)
        additive constant, 0 or -1e9; past: None (P = 0), or the keys and values (B, P*N, heads,
        D/heads) of P earlier frames, which the T frames' queries see before their own; anchor: None
        (A = 0), or the anchor frame's input tokens (B, N, D) (A = 1), whose keys and values this
        layer projects and every query sees first.
        Returns (x (B, T, N, D), (keys, values) (B, T*N, heads, D/heads) of the T frames)."""
        cfg, dt = self.cfg, self.cfg.compute_dtype
        b, t, n, d = x.shape
        mod = nn.Dense(6 * d, dtype=dt, kernel_init=nn.initializers.zeros)(nn.silu(cond))[:, :, None]
        sh1, sc1, g1, sh2, sc2, g2 = jnp.split(mod, 6, axis=-1)
        h = nn.LayerNorm(use_scale=False, use_bias=False, dtype=dt)(x) * (1 + sc1) + sh1
        h = h.reshape(b, t * n, d)
        qkv = nn.Dense(3 * d, dtype=dt)(h).reshape(b, t * n, 3, cfg.heads, d // cfg.heads)
        q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]
        keys, values = (k, v) if past is None else (jnp.concatenate([past[0], k], 1), jnp.concatenate([past[1], v], 1))
        if anchor is not None:
            a = nn.LayerNorm(use_scale=False, use_bias=False, dtype=dt, name="anchor_norm")(anchor)
            akv = nn.Dense(2 * d, dtype=dt, name="anchor_kv")(a).reshape(b, n, 2, cfg.heads, d // cfg.heads)
            keys, values = jnp.concatenate([akv[:, :, 0], keys], 1), jnp.concatenate([akv[:, :, 1], values], 1)
        logits = attention_logits(q, keys, time_bias, n) + mask
        att = jax.nn.softmax(logits, axis=-1).astype(dt)
        h = jnp.einsum("bhqk,bkhd->bqhd", att, values).reshape(b, t, n, d)
        x = x + g1 * nn.Dense(d, dtype=dt)(h)
        h = nn.LayerNorm(use_scale=False, use_bias=False, dtype=dt)(x) * (1 + sc2) + sh2
        h = nn.Dense(d, dtype=dt)(nn.gelu(nn.Dense(cfg.mlp * d, dtype=dt)(h)))
        return x + g2 * h, (k, v)


class StochasticLayer(nn.Module):
    """The stochastic latent of ModelConfig.stochastic: a code per frame from a Gaussian prior given the
    frame's tokens after the transformer (or a posterior that also sees the true next latents), and a
    residual MLP over the tokens modulated by the code and the frame's conditioning (adaLN, zero-gated)."""

    cfg: ModelConfig

    @nn.compact
    def __call__(self, x, cond, target=None, noise=None):
        """x: (B, T, N, D) tokens; cond: (B, T, D); target: optional (B, T, 8, 8, C); noise: optional
        (B, T, S). Returns (x (B, T, N, D), {"prior_mean", "prior_logstd"} and with target
        {"post_mean", "post_logstd"}, each (B, T, S) float32)."""
        cfg, dt = self.cfg, self.cfg.compute_dtype
        b, t, _, d = x.shape
        seen = x.mean(axis=2).astype(jnp.float32)
        prior = nn.Dense(2 * cfg.stochastic, dtype=jnp.float32, name="prior_out")(
            nn.silu(nn.Dense(d, dtype=jnp.float32, name="prior_hidden")(seen)))
        out = dict(zip(("prior_mean", "prior_logstd"), _gaussian(prior)))
        mean, logstd = out["prior_mean"], out["prior_logstd"]
        if target is not None:
            ahead = nn.Dense(d, dtype=jnp.float32, name="post_target")(target.reshape(b, t, -1).astype(jnp.float32))
            post = nn.Dense(2 * cfg.stochastic, dtype=jnp.float32, name="post_out")(
                nn.silu(nn.Dense(d, dtype=jnp.float32, name="post_hidden")(jnp.concatenate([seen, ahead], -1))))
            mean, logstd = _gaussian(post)
            out |= {"post_mean": mean, "post_logstd": logstd}
        code = mean if noise is None else mean + jnp.exp(logstd) * noise
        c = cond + nn.Dense(d, dtype=dt, name="code_embed")(code.astype(dt))
        mod = nn.Dense(3 * d, dtype=dt, kernel_init=nn.initializers.zeros, name="code_mod")(nn.silu(c))[:, :, None]
        shift, scale, gate = jnp.split(mod, 3, axis=-1)
        h = nn.LayerNorm(use_scale=False, use_bias=False, dtype=dt)(x) * (1 + scale) + shift
        h = nn.Dense(d, dtype=dt, name="mlp_out")(nn.gelu(nn.Dense(cfg.mlp * d, dtype=dt, name="mlp_in")(h)))
        return x + gate * h, out


def _gaussian(params):
    """(..., 2S) -> the mean and the log std (..., S), the log std bounded to [-5, 2] (a smooth bound,
    so that neither a collapsed nor an exploding scale stops the gradient)."""
    mean, raw = jnp.split(params, 2, axis=-1)
    return mean, -1.5 + 3.5 * jnp.tanh(raw / 3.5)


class BlindBody(nn.Module):
    """The next proprioception of one blind path's groups (ModelConfig.blind_paths) from those groups'
    present (together) and the action alone: an MLP beside a linear map. The rest of an imagined body may
    drift, and a body part's response to its commands does not depend on it; the linear map carries
    the response between and beyond the commands the data holds as it is near them."""

    cfg: ModelConfig
    groups: tuple

    @nn.compact
    def __call__(self, proprio, action):
        """proprio (B, T, proprio_dim), action (B, T, action_dim), both standardised -> the next
        proprio (B, T, proprio_dim), meaningful in its groups' columns alone."""
        cfg = self.cfg
        own = jnp.concatenate([jnp.where(cfg.group_mask(self.groups), proprio, 0.0), action], -1).astype(jnp.float32)
        h = nn.silu(nn.Dense(cfg.dim, dtype=jnp.float32)(nn.silu(nn.Dense(cfg.dim, dtype=jnp.float32)(own))))
        return (proprio + nn.Dense(cfg.proprio_dim, dtype=jnp.float32)(h)
                + nn.Dense(cfg.proprio_dim, dtype=jnp.float32, name="linear")(own))


class Dynamics(nn.Module):
    """Latents, proprio, actions (B, T, ...) of frames 0..T-1 -> predictions for frames 1..T."""

    cfg: ModelConfig

    @nn.compact
    def __call__(self, z, proprio, action, valid=None, past=None, with_kv=False, anchor=None, time=None,
                 anchor_keep=None, target=None, noise=None):
        """z: (B, T, 8, 8, C); proprio: (B, T, 37) normalised; action: (B, T, 20) normalised;
        valid: optional (B, T) bool, False for empty slots of an imagination buffer; anchor: the
        episode's first frame's latents (B, 8, 8, C), and time: (B, T) int the T frames' indices in
        their episodes (the first frame's is 0), both required with cfg.anchor and unused without;
        anchor_keep: optional (B,) bool, False for samples that predict without their anchor
        (training's anchor dropout). With cfg.stochastic = S: target, optional (B, T, 8, 8, C) the true
        latents of frames 1..T (the posterior's input; entry t is prediction t's target; None: the code
        comes from the prior), and noise, optional (B, T, S) standard normal draws (None: the code is
        the distribution's mean).
        past: None, or one frame (T = 1) read after K-1 earlier ones: {"k", "v": (B, depth, K-1, N,
        heads, D/heads) their attention keys and values (with_kv's output), "valid": (B, K-1) bool}.
        Returns {"z": (B, T, 8, 8, C), "proprio": (B, T, 37), "success": (B, T) logits,
        "outcome": (B, T) logits, "progress": (B, T) logits of the task progress, "flow": (B, T, 8, 8, 2)
        in latent cells; with cfg.scene, "scene": (B, T, scene_dim) the standardised scene state},
        entry t being the prediction for frame t+1 (the flow warps frame t towards it); with cfg.stochastic, also
        "prior_mean", "prior_logstd" (B, T, S) and, given target, "post_mean", "post_logstd"; with with_kv or past, also
        "k", "v": (B, depth, T, N, heads, D/heads), the T frames' keys and values at every layer."""
        cfg, dt = self.cfg, self.cfg.compute_dtype
        b, t = z.shape[:2]
        n = cfg.tokens_per_frame
        if cfg.anchor and (anchor is None or time is None):
            raise ValueError("a model with an anchor frame predicts from the episode's first frame and each "
                             "frame's index in the episode: pass anchor= and time=")
        embed = nn.Dense(cfg.dim, dtype=dt)
        pos = self.param("pos", nn.initializers.normal(0.02), (n, cfg.dim)).astype(dt)
        x = embed(patchify(z, cfg.patch).astype(dt)) + pos
        anchor_tokens = embed(patchify(anchor[:, None], cfg.patch).astype(dt))[:, 0] + pos if cfg.anchor else None
        # the robot's next state from its state and the action alone (the joints follow their targets):
        # the frame's tokens are then conditioned on where the body and camera go, not only on the command
        body = jnp.concatenate([proprio, action], -1).astype(jnp.float32)
        h = nn.silu(nn.Dense(cfg.dim, dtype=jnp.float32)(nn.silu(nn.Dense(cfg.dim, dtype=jnp.float32)(body))))
        p_next = proprio + nn.Dense(cfg.proprio_dim, dtype=jnp.float32)(h)
        for name, groups in cfg.blind_paths:
            p_next = jnp.where(cfg.group_mask(groups), BlindBody(cfg, groups, name=name)(proprio, action), p_next)
        cond_in = jnp.concatenate([action, proprio, p_next], -1).astype(dt)
        cond = nn.Dense(cfg.dim, dtype=dt)(nn.silu(nn.Dense(cfg.dim, dtype=dt)(cond_in)))
        table = self.param("time_bias", nn.initializers.zeros, (cfg.heads, cfg.context))
        if past is None:
            time_bias, mask = relative_time_bias(table, t), attention_mask(t, n, cfg.context, valid)
        else:  # the last query row of a full window: this frame after the K-1 of the cache
            k = cfg.context
            if t != 1 or past["k"].shape[2] != k - 1:
                raise ValueError(f"a cached step reads one frame after {k - 1} cached ones; got {t} after "
                                 f"{past['k'].shape[2]}")
            time_bias = relative_time_bias(table, k)[:, -1:]
            allowed = jnp.concatenate([past["valid"], jnp.ones((b, 1), bool)], axis=1)
            mask = jnp.where(jnp.repeat(allowed, n, axis=1), 0.0, -1e9).astype(jnp.float32)[:, None, None, :]
        if cfg.anchor:  # the anchor's keys come first, seen by every query, biased by how long ago it was
            table_a = self.param("anchor_bias", nn.initializers.zeros, (cfg.heads, ANCHOR_SPANS))
            column = jnp.moveaxis(table_a[:, anchor_span(time)], 0, 1)[..., None]  # (B, heads, T, 1)
            time_bias = jnp.concatenate([column, jnp.broadcast_to(time_bias, (b,) + time_bias.shape)], axis=3)
            # the anchor's mask column is per sample only where samples drop it (training)
            seen = jnp.zeros((1, 1, 1, n), mask.dtype) if anchor_keep is None else \
                jnp.where(anchor_keep, 0.0, -1e9).astype(mask.dtype)[:, None, None, None]
            lead = max(seen.shape[0], mask.shape[0])
            mask = jnp.concatenate([jnp.broadcast_to(seen, (lead,) + mask.shape[1:3] + (n,)),
                                    jnp.broadcast_to(mask, (lead,) + mask.shape[1:])], axis=3)
        if cfg.scan_layers:  # past's keys and values by layer: (depth, B, (K-1)*N, heads, D/heads)
            cached = None if past is None else tuple(
                jnp.moveaxis(past[key], 1, 0).reshape((cfg.depth, b, -1) + past[key].shape[4:]) for key in ("k", "v"))
            layers = nn.scan(Block, variable_axes={"params": 0}, split_rngs={"params": True}, length=cfg.depth,
                             in_axes=(nn.broadcast, nn.broadcast, nn.broadcast, nn.broadcast if past is None else 0,
                                      nn.broadcast))
            x, stacked = layers(cfg, name="layers")(x, cond, time_bias, mask, cached, anchor_tokens)
            kvs = [(stacked[0][layer], stacked[1][layer]) for layer in range(cfg.depth)]
        else:
            kvs = []
            for layer in range(cfg.depth):
                cached = None if past is None else tuple(
                    past[key][:, layer].reshape((b, -1) + past[key].shape[4:]) for key in ("k", "v"))
                x, kv = Block(cfg)(x, cond, time_bias, mask, cached, anchor_tokens)
                kvs.append(kv)
        codes = {}
        if cfg.stochastic:
            x, codes = StochasticLayer(cfg, name="stochastic")(x, cond, target, noise)
        mod = nn.Dense(2 * cfg.dim, dtype=dt, kernel_init=nn.initializers.zeros)(nn.silu(cond))[:, :, None]
        shift, scale = jnp.split(mod, 2, axis=-1)
        h = nn.LayerNorm(use_scale=False, use_bias=False, dtype=dt)(x) * (1 + scale) + shift
        dz = nn.Dense(cfg.patch * cfg.patch * cfg.latent, dtype=jnp.float32, kernel_init=nn.initializers.zeros)(h)
        z_next = jnp.clip(z + unpatchify(dz.astype(jnp.float32), cfg.patch, cfg.latent), -1.0, 1.0)
        flow = nn.Dense(cfg.patch * cfg.patch * 2, dtype=jnp.float32, kernel_init=nn.initializers.zeros)(h)
        # plus the ego-motion field straight from the body's motion (the camera rides on the neck and base)
        ego = nn.Dense(LATENT_SIDE * LATENT_SIDE * 2, dtype=jnp.float32, kernel_init=nn.initializers.zeros)(
            nn.silu(cond).astype(jnp.float32)).reshape(b, t, LATENT_SIDE, LATENT_SIDE, 2)
        flow = unpatchify(flow.astype(jnp.float32), cfg.patch, 2) + ego
        pooled = h.mean(axis=2).astype(jnp.float32)
        width = cfg.proprio_dim + 3 + cfg.scene_width
        heads = nn.Dense(width, dtype=jnp.float32)(nn.silu(nn.Dense(cfg.dim, dtype=jnp.float32)(pooled)))
        # clipped like the standardised inputs, so that a long imagined rollout cannot diverge
        correction = heads[..., :cfg.proprio_dim]
        if cfg.blind:  # only a blind model's program holds the select: a carried compilation cache still serves the rest
            correction = jnp.where(cfg.blind_mask, 0.0, correction)
        p_out = jnp.clip(p_next + correction, -INPUT_CLIP, INPUT_CLIP)
        out = {"z": z_next, "proprio": p_out,
               "success": heads[..., cfg.proprio_dim], "outcome": heads[..., cfg.proprio_dim + 1],
               "progress": heads[..., cfg.proprio_dim + 2], "flow": flow, **codes}
        if cfg.scene:
            out["scene"] = heads[..., cfg.proprio_dim + 3:]
        if with_kv or past is not None:
            for i, key in enumerate(("k", "v")):
                out[key] = jnp.stack([kv[i].reshape((b, t, n) + kv[i].shape[2:]) for kv in kvs], axis=1)
        return out


class WorldModel(nn.Module):
    """Tokenizer and dynamics under one parameter tree; methods are the model's entry points."""

    cfg: ModelConfig

    def setup(self):
        self.encoder = Encoder(self.cfg)
        self.decoder = Decoder(self.cfg)
        self.dynamics = Dynamics(self.cfg)
        if self.cfg.refine:
            self.refiner = FrameRefiner(self.cfg)

    def encode(self, frames):
        """(..., S, S, 3) uint8 -> (..., 8, 8, C)."""
        lead = frames.shape[:-3]
        z = self.encoder(frames.reshape((-1,) + frames.shape[-3:]))
        return z.reshape(lead + z.shape[1:])

    def decode(self, z, prev, flow=None, with_keep=False):
        """(..., 8, 8, C) latents, the previous frames (..., S, S, 3) in [0, 1] and optionally the
        predicted flows (..., 8, 8, 2) -> (..., S, S, 3) float32 in [0, 1]; with_keep: and the keep
        gate's logits (..., S, S) (None without cfg.keep)."""
        lead = z.shape[:-3]
        flat = None if flow is None else flow.reshape((-1,) + flow.shape[-3:])
        x, keep = self.decoder(z.reshape((-1,) + z.shape[-3:]), prev.reshape((-1,) + prev.shape[-3:]), flat, True)
        x = x.reshape(lead + x.shape[1:])
        if not with_keep:
            return x
        return x, None if keep is None else keep.reshape(lead + keep.shape[1:])

    def denoise(self, noisy, t, base, z):
        """The frame generator's estimate of the clean residual (..., S, S, 3) in pixel units, from the
        noisy residual (..., S, S, 3) in pixel units at flow times t (...) in [0, 1] (noise at 0, the
        residual at 1), the decoded frames (..., S, S, 3) in [0, 1] and the predicted latents (..., 8, 8, C)."""
        lead = base.shape[:-3]
        flat = lambda x: x.reshape((-1,) + x.shape[len(lead):])
        out = self.refiner(flat(noisy) / REFINE_SIGMA, jnp.broadcast_to(t, lead).reshape(-1), flat(base), flat(z))
        return out.reshape(base.shape)

    def sample_frame(self, base, z, noise):
        """Frames (..., S, S, 3) in [0, 1] drawn by cfg.refine Euler steps of the frame generator from
        standard normal noise (..., S, S, 3), given the decoded frames (..., S, S, 3) in [0, 1] and the
        predicted latents (..., 8, 8, C). Along the straight path x_t = (1 - t) noise + t residual, a step
        from t to t + 1/n moves x towards the estimate by 1/(n - i) of the way, so the last step lands on it."""
        n = self.cfg.refine
        x = REFINE_SIGMA * noise
        for i in range(n):
            x = x + (self.denoise(x, jnp.full(base.shape[:-3], i / n), base, z) - x) / (n - i)
        return jnp.clip(base + x, 0.0, 1.0)

    def predict(self, z, proprio, action, valid=None, past=None, with_kv=False, anchor=None, time=None,
                anchor_keep=None, target=None, noise=None):
        return self.dynamics(z, proprio, action, valid, past, with_kv, anchor, time, anchor_keep, target, noise)

    def __call__(self, frames, proprio, action):
        z = self.encode(frames)
        pix = frames.astype(jnp.float32) / 255.0
        time = jnp.broadcast_to(jnp.arange(z.shape[1]), z.shape[:2])
        if self.cfg.refine:  # creates the generator's parameters
            self.denoise(jnp.zeros_like(pix), jnp.zeros(pix.shape[:2]), pix, z)
        # target: the stochastic code's posterior reads latents shaped as these (it exists only where given)
        return self.decode(z, pix), self.predict(
            z, proprio, action, anchor=z[:, 0], time=time, target=z if self.cfg.stochastic else None)


def init_params(cfg: ModelConfig, rng, window: int = 4):
    """Float32 parameters of a WorldModel for cfg."""
    cfg.validate()
    return _init_params(cfg, rng, window)


@functools.partial(jit_initialiser, static_argnums=(0, 2))
def _init_params(cfg: ModelConfig, rng, window: int):
    # one compilation: run op by op, the initialising forward pass compiles each operation apart (2x slower on a CPU)
    frames = jnp.zeros((1, window, cfg.size, cfg.size, 3), jnp.uint8)
    return WorldModel(cfg).init(rng, frames, jnp.zeros((1, window, cfg.proprio_dim)),
                                jnp.zeros((1, window, cfg.action_dim)))["params"]
