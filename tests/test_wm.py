"""The world model: metrics against hand-computed values, every module one step, causality and
the sliding context, imagination consistent with training, the loss falling, resume after a kill,
a non-finite loss stopping the run, make train's smoke preset with eval.json."""

import dataclasses
import functools
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import serialization

from sim_data.config import override
from sim_data.dataset.cache import TrainingCache
from sim_data.policies.registry import ClippedPolicy, PolicySource
from sim_data.sim.scene import SCENE_STATE_NAMES
from wm import checkpoint as CK
from wm import imagine as I
from wm import judge as J
from wm import metrics as M
from wm import quality as E
from wm.checkpoint import (
    bundle_holds,
    load_run_config,
    load_trained,
    training_fingerprints,
    training_policies,
    training_seeds,
    training_status,
    write_bundle,
)
from wm.checkpoint import main as checkpoint_main
from wm.config import SMOKE_MODEL, check_dataset, make_config
from wm.judge import load_judge
from wm.model import (
    INPUT_CLIP,
    Decoder,
    WorldModel,
    anchor_span,
    attention_logits,
    attention_mask,
    depth_to_space,
    init_params,
    relative_time_bias,
    space_to_depth,
)
from wm.train import Run, TrainingDiverged, check_run_config, compute_norm, kept_at, model_batch
from wm.train import main as train_main

CFG = SMOKE_MODEL


@functools.cache
def compiled(module, method=None, **kwargs):
    """module.apply(variables, *args, method=method, **kwargs) compiled as one program: run op by op, a
    convolutional model compiles each operation apart, which costs most of these tests' time on a CPU."""
    return jax.jit(functools.partial(module.apply, method=method, **kwargs))


# the imagination's pieces as the library's scans run them: compiled
init_state = jax.jit(I.init_state, static_argnums=0)
imagine_step = jax.jit(I.step, static_argnums=0)


def test_psnr_ssim_auroc_hand_values():
    a = np.full((2, 8, 8, 3), 100, np.uint8)
    assert M.psnr(a, a + 1)[0] == pytest.approx(10 * np.log10(255**2))
    assert M.psnr(a, a)[0] == np.inf
    assert M.ssim(a, a)[0] == pytest.approx(1.0)
    c1 = (0.01 * 255) ** 2  # constant images: only the luminance term remains
    assert M.ssim(a, a + 20)[0] == pytest.approx((2 * 100 * 120 + c1) / (100**2 + 120**2 + c1))
    assert M.auroc([0.1, 0.4, 0.35, 0.8], [0, 0, 1, 1]) == pytest.approx(0.75)
    assert M.auroc([0.5, 0.5, 0.2], [1, 0, 0]) == pytest.approx(0.75)  # a tie counts one half
    assert np.isnan(M.auroc([0.1, 0.2], [1, 1]))
    rng = np.random.default_rng(0)  # against counting every positive-negative pair, ties one half
    s, y = np.round(rng.random(60), 1), np.arange(60) % 3 == 0
    pairs = s[y][:, None] - s[~y][None]
    assert M.auroc(s, y) == pytest.approx(((pairs > 0).sum() + 0.5 * (pairs == 0).sum()) / pairs.size)
    assert M.accuracy([0.2, 0.7, 0.6], [0, 1, 0]) == pytest.approx(2 / 3)


def test_view_shift_measures_a_known_translation():
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(0)
    img = (gaussian_filter(rng.random((64, 64, 3)), (2, 2, 0)) * 2550 % 255).astype(np.uint8)[None]
    moved = np.concatenate([np.roll(img, (dy, dx), axis=(1, 2)) for dy, dx in ((0, 0), (0, 2), (3, 0), (4, 3))])
    np.testing.assert_allclose(M.view_shift(np.repeat(img, 4, axis=0), moved), [0, 2, 3, 5], atol=0.25)
    # an unrelated pair registers at no translation: NaN, not a centroid of noise hundreds of pixels away
    other = (gaussian_filter(rng.random((64, 64, 3)), (2, 2, 0)) * 2550 % 255).astype(np.uint8)[None]
    assert np.isnan(M.view_shift(img, other)).all()


def test_warp_shifts_pixels_bilinearly_and_clamps_at_the_border():
    from wm.model import warp

    rng = np.random.default_rng(0)
    img = jnp.asarray(rng.random((2, 64, 64, 3)), jnp.float32)
    np.testing.assert_array_equal(warp(img, jnp.zeros((2, 8, 8, 2))), img)
    one_px = jnp.zeros((2, 8, 8, 2)).at[..., 1].set(1 / 8)  # one latent cell is 8 pixels at 64 px
    got = np.asarray(warp(img, one_px))
    np.testing.assert_allclose(got[:, :, :-1], img[:, :, 1:], atol=1e-6)  # pixel x reads x + 1
    np.testing.assert_allclose(got[:, :, -1], img[:, :, -1], atol=1e-6)  # clamped at the right edge
    half_up = jnp.zeros((2, 8, 8, 2)).at[..., 0].set(-0.5 / 8)
    np.testing.assert_allclose(np.asarray(warp(img, half_up))[:, 1:], 0.5 * (img[:, 1:] + img[:, :-1]), atol=1e-6)
    grad = jax.grad(lambda f: warp(img, f).sum())(one_px * 0.3)  # the flow learns from the pixels
    assert float(jnp.abs(grad).max()) > 0


def test_block_flow_finds_a_known_shift_cell_by_cell_and_trusts_no_flat_cell():
    from scipy.ndimage import gaussian_filter

    from wm.model import block_flow, warp

    rng = np.random.default_rng(0)
    prev = gaussian_filter(rng.random((1, 64, 64, 3)), (0, 1, 1, 0)).astype(np.float32)
    prev[:, :, 32:] = 0.5  # the right half flat: nothing to match there
    shift = np.zeros((1, 8, 8, 2), np.float32)
    shift[:, :4, :4] = (3 / 8, -2 / 8)  # the top-left quarter's content moves up 3 and right 2 pixels
    nxt = warp(jnp.asarray(prev), jnp.asarray(shift))
    flow, conf = (np.asarray(x) for x in block_flow(jnp.asarray(prev), nxt, radius=4))
    assert flow.shape == (1, 8, 8, 2) and conf.shape == (1, 8, 8)
    # the bilinear upsampling blends the quarter's shift into its neighbours' edges: interior cells are exact
    np.testing.assert_array_equal(flow[0, :3, :3], shift[0, :3, :3])
    np.testing.assert_array_equal(flow[0, 5:, :3], 0.0)  # textured and still
    assert conf[0, :3, :3].min() > 0.5 and conf[0, 5:, :3].min() > 0.5
    np.testing.assert_array_equal(flow[0, :, 5:], 0.0)  # flat: every shift ties, the smallest wins
    np.testing.assert_array_equal(conf[0, :, 5:], 0.0)
    with pytest.raises(ValueError, match="w_flow"):
        make_config("smoke", ["w_flow=0.1", "model.warp=false"])
    with pytest.raises(ValueError, match="flow_radius"):
        make_config("smoke", ["w_flow=0.1", "flow_radius=0"])


def test_the_flow_term_is_the_confidence_weighted_distance_from_the_matched_flow():
    from wm.train import _flow_loss

    flow = np.zeros((1, 2, 8, 8, 2), np.float32)
    flow[0, 0, 0, 0] = (0.5, -0.25)
    truth = np.zeros_like(flow)
    conf = np.zeros((1, 2, 8, 8), np.float32)
    conf[0, 0, 0, 0] = 0.5
    # one cell of 128 differs, by 0.75 cells summed over (dy, dx), at confidence 0.5
    np.testing.assert_allclose(_flow_loss(flow, truth, conf), 0.5 * 0.75 / 128, rtol=1e-6)


@pytest.mark.slow
def test_the_flow_term_joins_the_loss_once_a_pass(model_and_inputs):
    from wm.train import loss_fn

    params, frames, proprio, action = model_and_inputs
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    cfg = make_config("smoke", ["w_flow=0.3"])
    total, parts = jax.jit(loss_fn, static_argnums=3)(params, batch, norm, cfg)
    passes = [k for k in parts if k.startswith("flow")]
    assert len(passes) == 1 + cfg.rollout_passes and all(float(parts[k]) > 0 for k in passes)
    rest = sum(float(v) for k, v in parts.items() if k.startswith("flow"))
    _, plain = jax.jit(loss_fn, static_argnums=3)(params, batch, norm, dataclasses.replace(cfg, w_flow=0.0))
    np.testing.assert_allclose(float(total), float(plain["loss"]) + 0.3 * rest, rtol=1e-5)


def test_sub_pixel_decoder_unfolds_channels_into_pixels():
    x = np.arange(2 * 4 * 4 * 12, dtype=np.float32).reshape(2, 4, 4, 12)
    np.testing.assert_array_equal(space_to_depth(depth_to_space(x, 2), 2), x)
    # output pixel (2i+a, 2j+b), channel c, is input (i, j)'s channel (2a+b)C + c
    np.testing.assert_array_equal(depth_to_space(x, 2)[:, 3, 1, 2], x[:, 1, 0, (2 * 1 + 1) * 3 + 2])
    cfg = dataclasses.replace(CFG, upsample="shuffle")
    dec = Decoder(cfg)
    z, prev = jnp.zeros((2, 8, 8, cfg.latent)), jnp.full((2, 64, 64, 3), 0.25)
    params = jax.jit(dec.init)(jax.random.PRNGKey(0), z, prev)  # one program: op by op, each initialiser compiles apart
    convs = [v["kernel"].shape for k, v in params["params"].items() if k.startswith("Conv_")]
    assert [s[-1] for s in convs[1:4]] == [4 * c for c in cfg.channels[::-1]]  # 4x wider, at the lower resolution
    out = compiled(dec)(params, z, prev)
    assert out.shape == (2, 64, 64, 3) and abs(float(out.mean()) - 0.25) < 0.05  # starts near a copy of prev


def test_bfloat16_decoder_frames_agree_with_float32(model_and_inputs):
    """Mixed precision (every convolution in bf16, the output conv included) moves a decoded frame by
    little more than bf16's rounding: the same parameters decode alike in both dtypes."""
    params, frames, _, _ = model_and_inputs
    z = compiled(WorldModel(CFG), WorldModel.encode)({"params": params}, frames)
    prev = frames.astype(np.float32) / 255.0
    out = {dt: compiled(WorldModel(dataclasses.replace(CFG, dtype=dt)), WorldModel.decode)({"params": params}, z, prev)
           for dt in ("float32", "bfloat16")}
    err = np.abs(np.asarray(out["bfloat16"]) - np.asarray(out["float32"]))
    assert out["bfloat16"].dtype == jnp.float32 and err.mean() < 5e-4 and err.max() < 0.01, (err.mean(), err.max())


def test_keep_gate_copies_the_unwarped_previous_frame_exactly():
    cfg = dataclasses.replace(CFG, keep=True)
    dec = Decoder(cfg)
    rng = np.random.default_rng(0)
    z = jnp.asarray(rng.normal(size=(2, 8, 8, cfg.latent)), jnp.float32)
    prev = jnp.asarray(rng.integers(0, 256, (2, 64, 64, 3)) / 255.0, jnp.float32)
    flow = jnp.full((2, 8, 8, 2), 0.3)  # a warp that alone would move every pixel
    params = jax.jit(dec.init)(jax.random.PRNGKey(0), z, prev, flow)  # one program, as in the test above
    out_conv = next(k for k, v in params["params"].items() if k.startswith("Conv_") and v["kernel"].shape[-1] == 5)

    def with_keep_bias(b):
        p = jax.tree_util.tree_map(lambda x: x, params)
        p["params"][out_conv]["bias"] = p["params"][out_conv]["bias"].at[4].set(b)
        return compiled(dec, with_keep=True)(p, z, prev, flow)

    kept, logits = with_keep_bias(50.0)
    assert logits.shape == (2, 64, 64) and bool((logits > 0).all())
    np.testing.assert_array_equal(np.asarray(kept), np.asarray(prev))  # exactly, warp or not
    composed, logits = with_keep_bias(-50.0)
    assert bool((logits < 0).all()) and float(jnp.abs(composed - prev).max()) > 1e-3
    # a threshold above the logits keeps nothing: the frame is the composed one of the same parameters
    p = jax.tree_util.tree_map(lambda x: x, params)
    p["params"][out_conv]["bias"] = p["params"][out_conv]["bias"].at[4].set(50.0)
    strict = compiled(Decoder(dataclasses.replace(cfg, keep_threshold=1e9)))(p, z, prev, flow)
    np.testing.assert_array_equal(np.asarray(strict), np.asarray(compiled(Decoder(dataclasses.replace(cfg, keep=False)))(
        {"params": {**p["params"], out_conv: {"kernel": p["params"][out_conv]["kernel"][..., :4],
                                              "bias": p["params"][out_conv]["bias"][:4]}}}, z, prev, flow)))
    with pytest.raises(ValueError, match="w_keep"):
        make_config("smoke", ["model.keep=true", "w_keep=0"])
    with pytest.raises(ValueError, match="keep needs compose"):
        dataclasses.replace(CFG, keep=True, compose=False, warp=False).validate()


def test_keep_loss_labels_the_pixels_the_next_frame_leaves_unchanged():
    from wm.train import _keep_loss

    prev = np.zeros((1, 2, 2, 3), np.float32)
    target = prev.copy()
    target[0, 0, 1, 2] = 1.0 / 255  # one channel of one pixel changes by a level
    target[0, 1, 1] = 0.4 / 255  # under half a level: the same 8-bit value
    logits = np.array([[[3.0, -2.0], [1.0, 0.5]]], np.float32)
    labels = np.array([[[1.0, 0.0], [1.0, 1.0]]])
    want = np.mean(np.maximum(logits, 0) - logits * labels + np.log1p(np.exp(-np.abs(logits))))
    np.testing.assert_allclose(float(_keep_loss(jnp.asarray(logits), jnp.asarray(target), jnp.asarray(prev))), want,
                               rtol=1e-6)


@pytest.fixture(scope="module")
def model_and_inputs():
    params = init_params(CFG, jax.random.PRNGKey(0), window=6)
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (2, 6, 64, 64, 3)).astype(np.uint8)
    proprio = rng.normal(size=(2, 6, 37)).astype(np.float32)
    action = rng.normal(size=(2, 6, 20)).astype(np.float32)
    # non-zero output layers, so that every input reaches the predictions (numpy's noise: no compilation)
    noise = np.random.default_rng(1)
    params = jax.tree_util.tree_map(lambda x: x + 0.05 * noise.standard_normal(x.shape).astype(np.float32), params)
    return params, frames, proprio, action


def test_time_bias_in_the_product_equals_an_added_bias_and_its_gradient():
    """The learned bias by frame distance, folded into the query-key product, gives the logits and the
    table's gradient of a bias added to the logits by hand; the mask is causal over `context` frames
    and masks empty key slots."""
    t, n, h, d, context = 5, 3, 2, 4, 3
    rng = np.random.default_rng(0)  # numpy's noise: jax.random would compile its generator per shape
    q, k = (rng.standard_normal((2, t * n, h, d)).astype(np.float32) for _ in "qk")
    table = rng.standard_normal((h, context)).astype(np.float32)
    weight = rng.standard_normal((2, h, t * n, t * n)).astype(np.float32)
    frame = np.arange(t * n) // n

    def by_hand(table):  # token by token: the bias of query token i and key token j
        dist = frame[:, None] - frame[None, :]
        bias = jnp.where((dist >= 0) & (dist < context), table[:, np.clip(dist, 0, context - 1)], 0.0)
        return jnp.einsum("bqhd,bkhd->bhqk", q, k) / np.sqrt(d) + bias[None]

    # each side compiled as one program (op by op, each operation compiles apart)
    folded = lambda table: attention_logits(q, k, relative_time_bias(table, t), n)
    np.testing.assert_allclose(jax.jit(folded)(table), jax.jit(by_hand)(table), rtol=1e-5, atol=1e-5)
    g_folded = jax.jit(jax.grad(lambda tb: jnp.sum(folded(tb) * weight)))(table)
    g_hand = jax.jit(jax.grad(lambda tb: jnp.sum(by_hand(tb) * weight)))(table)
    np.testing.assert_allclose(g_folded, g_hand, rtol=1e-4, atol=1e-4)
    assert np.abs(g_hand).min() > 0

    valid = np.ones((2, t), bool)
    valid[1, 0] = False
    mask = np.asarray(attention_mask(t, n, context, jnp.asarray(valid)))
    assert mask.shape == (2, 1, t * n, t * n)
    allowed = (frame[:, None] - frame[None, :] >= 0) & (frame[:, None] - frame[None, :] < context)
    np.testing.assert_array_equal(mask[0, 0] == 0, allowed)
    np.testing.assert_array_equal(mask[1, 0] == 0, allowed & (frame[None, :] != 0))


def test_modules_shapes_causality_and_context(model_and_inputs):
    params, frames, proprio, action = model_and_inputs
    m = WorldModel(CFG)
    z = compiled(m, WorldModel.encode)({"params": params}, frames)
    assert z.shape == (2, 6, 8, 8, CFG.latent) and float(jnp.abs(z).max()) <= 1.0
    prev = frames.astype(np.float32) / 255.0
    x = compiled(m, WorldModel.decode)({"params": params}, z, prev)
    assert x.shape == frames.shape and 0.0 <= float(x.min()) and float(x.max()) <= 1.0
    out = compiled(m, WorldModel.predict)({"params": params}, z, proprio, action)
    assert out["z"].shape == z.shape and out["proprio"].shape == proprio.shape and out["success"].shape == (2, 6)
    assert out["flow"].shape == (2, 6, 8, 8, 2)
    warped = compiled(m, WorldModel.decode)({"params": params}, z, prev, out["flow"])
    assert float(jnp.abs(warped - x).max()) > 1e-3  # the flow reaches the frame
    # frame 4 changed: predictions made at frames 0..3 are unchanged, at frame 4 they change
    z2 = z.at[:, 4].set(-z[:, 4])
    out2 = compiled(m, WorldModel.predict)({"params": params}, z2, proprio, action)
    np.testing.assert_allclose(out2["z"][:, :4], out["z"][:, :4], atol=1e-5)
    assert float(jnp.abs(out2["z"][:, 4] - out["z"][:, 4]).max()) > 1e-3
    # the prediction at frame 5 sees frames 2..5 (context 4): frame 1 does not matter
    z3 = z.at[:, 1].set(-z[:, 1])
    out3 = compiled(m, WorldModel.predict)({"params": params}, z3, proprio, action)
    np.testing.assert_allclose(out3["z"][:, 5], out["z"][:, 5], atol=1e-5)
    assert float(jnp.abs(out3["z"][:, 2] - out["z"][:, 2]).max()) > 1e-3


def test_imagination_step_equals_the_teacher_forced_prediction(model_and_inputs):
    params, frames, proprio, action = model_and_inputs
    norm = I.Norm(jnp.zeros(37), jnp.ones(37), jnp.zeros(20), jnp.ones(20))
    m = WorldModel(CFG)
    c = 3
    z = compiled(m, WorldModel.encode)({"params": params}, frames[:, :c])
    tf = compiled(m, WorldModel.predict)({"params": params}, z, proprio[:, :c], action[:, :c])
    st = init_state(CFG, params, norm, frames[:, :c], proprio[:, :c], action[:, :c - 1])
    st = imagine_step(CFG, params, norm, st, action[:, c - 1])
    np.testing.assert_allclose(st.z[:, -1], tf["z"][:, -1], atol=1e-5)
    np.testing.assert_allclose(st.proprio[:, -1], tf["proprio"][:, -1], atol=1e-4)
    got = I.open_loop(CFG, params, norm, frames[:, :c], proprio[:, :c], action[:, :c - 1], action[:, c - 1:])
    assert got["frames"].shape == (2, 4, 64, 64, 3) and got["frames"].dtype == jnp.uint8
    assert got["success"].shape == (2, 4) and float(got["success"].min()) >= 0.0


def test_open_loop_across_segments_equals_stepping_one_action_at_a_time(model_and_inputs):
    params, frames, proprio, action = model_and_inputs
    norm = I.Norm(jnp.full(37, 0.1), jnp.full(37, 2.0), jnp.full(20, -0.2), jnp.full(20, 0.5))
    h = I.SEGMENT + 3  # two compiled segments, the second padded with actions whose steps are dropped
    actions = jax.random.uniform(jax.random.PRNGKey(3), (2, h, 20), minval=-1.0, maxval=1.0)
    got = I.open_loop(CFG, params, norm, frames[:, :2], proprio[:, :2], action[:, :1], actions)
    st = init_state(CFG, params, norm, frames[:, :2], proprio[:, :2], action[:, :1])
    frames_ref, success_ref = [], []
    for t in range(h):
        st = imagine_step(CFG, params, norm, st, actions[:, t])
        frames_ref.append(I.to_uint8(st.frame))
        success_ref.append(st.success)
    assert got["frames"].shape == (2, h, 64, 64, 3) and got["features"].shape[:2] == (2, h)
    diff = np.abs(np.asarray(got["frames"], np.int16) - np.asarray(jnp.stack(frames_ref, 1), np.int16))
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3  # a rounding step at most, on a few pixels
    np.testing.assert_allclose(got["success"], jnp.stack(success_ref, 1), atol=1e-5)
    with pytest.raises(ValueError, match="at least one step"):
        I.open_loop(CFG, params, norm, frames[:, :2], proprio[:, :2], action[:, :1], actions[:, :0])
    # asked for its features alone, it returns those of the whole call and leaves the frames on the device
    alone = I.open_loop(CFG, params, norm, frames[:, :2], proprio[:, :2], action[:, :1], actions, keys=("features",))
    assert list(alone) == ["features"]
    np.testing.assert_array_equal(alone["features"], got["features"])
    with pytest.raises(ValueError, match="returns some of frames, proprio"):
        I.open_loop(CFG, params, norm, frames[:, :2], proprio[:, :2], action[:, :1], actions, keys=("image",))


def test_observed_features_read_the_true_episode_as_exact_imagination_would(model_and_inputs):
    params, frames, proprio, action = model_and_inputs
    norm = I.Norm(jnp.full(37, 0.1), jnp.full(37, 2.0), jnp.full(20, -0.2), jnp.full(20, 0.5))
    m = WorldModel(CFG)
    t_max = I.SEGMENT + 3  # two compiled segments, the second padded
    frames, proprio, action = (np.concatenate([x] * 5, axis=1)[:, :t_max + 1] for x in (frames, proprio, action))
    x = np.asarray(I.observed_features(CFG, params, norm, frames, proprio, action[:, :t_max]))
    assert x.shape == (2, t_max, I.feature_dim(CFG))
    # one frame of context, two, a full context of 4 with the oldest dropped, across the segments' seam
    encode, features = compiled(m, WorldModel.encode), jax.jit(I.step_features)
    for t in (0, 1, 4, I.SEGMENT - 1, I.SEGMENT, t_max - 1):
        c0 = max(0, t + 1 - CFG.context)
        st = init_state(CFG, params, norm, frames[:, c0:t + 1], proprio[:, c0:t + 1], action[:, c0:t])
        st = imagine_step(CFG, params, norm, st, action[:, t])
        truth = st.replace(z=st.z.at[:, -1].set(encode({"params": params}, frames[:, t + 1])),
                           proprio=st.proprio.at[:, -1].set(norm.proprio(proprio[:, t + 1])))
        np.testing.assert_allclose(x[:, t], features(norm, truth, action[:, t]), atol=2e-5, err_msg=str(t))


# two layers: with one, a frame's prediction reads only the frames in its window whatever the mode
DEEP = dataclasses.replace(CFG, depth=2, imagine="window")


@pytest.fixture(scope="module")
def deep_params():
    params = init_params(DEEP, jax.random.PRNGKey(1), window=6)
    noise = np.random.default_rng(2)
    return jax.tree_util.tree_map(lambda x: x + 0.05 * noise.standard_normal(x.shape).astype(np.float32), params)


def _long_inputs(frames, proprio, action, reps=3):
    """The fixture's 6 frames repeated reps times (18 frames against a context of 4), proprio jittered
    so that no frame's inputs repeat."""
    frames, proprio, action = (np.concatenate([x] * reps, axis=1) for x in (frames, proprio, action))
    return frames, proprio + np.random.default_rng(5).normal(size=proprio.shape).astype(np.float32), action


def _assert_cached_steps_match_the_forward_pass(cfg, params, frames, proprio, action):
    m, cache_cfg = WorldModel(cfg), dataclasses.replace(cfg, imagine="cache")
    z = compiled(m, WorldModel.encode)({"params": params}, frames)
    anchor = z[:, 0] if cfg.anchor else None
    time = jnp.broadcast_to(jnp.arange(z.shape[1]), z.shape[:2])
    full = compiled(m, WorldModel.predict)({"params": params}, z, proprio, action, anchor=anchor, time=time)
    b, t, k = z.shape[0], z.shape[1], cfg.context
    cache = I.empty_cache(cache_cfg, b)
    valid = jnp.zeros((b, k), bool)
    one = jax.jit(functools.partial(I.predict_next, cache_cfg))
    for i in range(t):
        lo = max(0, i + 1 - k)
        pad = k - (i + 1 - lo)
        window = [np.concatenate([np.zeros((b, pad) + x.shape[2:], x.dtype), x[:, lo:i + 1]], axis=1)
                  for x in (np.asarray(z), proprio, action)]
        valid = jnp.concatenate([valid[:, 1:], jnp.ones((b, 1), bool)], axis=1)
        out, cache = one(params, *window, valid, cache, anchor, jnp.full((b,), i))
        for key in ("z", "proprio", "success", "outcome", "progress", "flow"):
            np.testing.assert_allclose(out[key], full[key][:, i], rtol=1e-4, atol=1e-4, err_msg=f"{key} at {i}")
    assert cache[0].shape == (b, cfg.depth, k - 1, cfg.tokens_per_frame, cfg.heads, cfg.dim // cfg.heads)
    return full


@pytest.mark.slow
def test_cached_steps_equal_the_training_forward_pass_over_a_long_window(model_and_inputs, deep_params):
    """One frame at a time through the key-value cache gives what the training forward pass gives
    over the whole sequence (sliding attention over K frames at every layer): each output at each
    frame, from the first frame (no cache) to frames whose window has long slid past the start."""
    _, frames, proprio, action = model_and_inputs
    _assert_cached_steps_match_the_forward_pass(DEEP, deep_params, *_long_inputs(frames, proprio, action))


SCANNED = dataclasses.replace(DEEP, scan_layers=True)


def _stacked(params, depth: int):
    """An unrolled model's parameters (dynamics/Block_<i>/...) in the scanned layout (dynamics/layers/...,
    each leaf stacked on a leading depth axis)."""
    dyn = dict(params["dynamics"])
    blocks = [dyn.pop(f"Block_{i}") for i in range(depth)]
    dyn["layers"] = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *blocks)
    return {**params, "dynamics": dyn}


@pytest.mark.slow
def test_scanned_layers_compute_what_the_unrolled_layers_compute_each_with_its_own_parameters(
        model_and_inputs, deep_params):
    """The scanned model's parameters carry a leading depth axis, each layer drawn apart at init; given the
    unrolled model's parameters stacked, it predicts what the unrolled model predicts (every output and
    every layer's keys and values), and its cached steps equal its forward pass."""
    _, frames, proprio, action = model_and_inputs
    own = init_params(SCANNED, jax.random.PRNGKey(1), window=6)["dynamics"]["layers"]
    assert all(x.shape[0] == DEEP.depth for x in jax.tree_util.tree_leaves(own))
    kernel = own["Dense_1"]["kernel"]
    assert kernel.ndim == 3 and not np.allclose(kernel[0], kernel[1])
    params = _stacked(deep_params, DEEP.depth)
    z = compiled(WorldModel(DEEP), WorldModel.encode)({"params": deep_params}, frames)
    want = compiled(WorldModel(DEEP), WorldModel.predict, with_kv=True)({"params": deep_params}, z, proprio, action)
    got = compiled(WorldModel(SCANNED), WorldModel.predict, with_kv=True)({"params": params}, z, proprio, action)
    assert sorted(got) == sorted(want)
    for key in want:
        np.testing.assert_allclose(got[key], want[key], rtol=1e-5, atol=1e-5, err_msg=key)
    _assert_cached_steps_match_the_forward_pass(SCANNED, params, *_long_inputs(frames, proprio, action))


ANCHORED = dataclasses.replace(DEEP, anchor=True)


@pytest.mark.slow  # the anchor is an option no preset uses: its compile-heavy tests run with make test-slow
def test_an_anchored_model_sees_the_first_frame_at_every_step_and_caches_alike(model_and_inputs):
    """With an anchor the predictions long after the context has slid past the first frame still
    change with it (without one they cannot), and the cached steps are the forward pass's."""
    _, frames, proprio, action = model_and_inputs
    params = init_params(ANCHORED, jax.random.PRNGKey(1), window=6)
    noise = np.random.default_rng(2)
    params = jax.tree_util.tree_map(lambda x: x + 0.05 * noise.standard_normal(x.shape).astype(np.float32), params)
    assert "anchor_kv" in params["dynamics"]["Block_0"] and "anchor_bias" in params["dynamics"]
    frames, proprio, action = _long_inputs(frames, proprio, action)
    full = _assert_cached_steps_match_the_forward_pass(ANCHORED, params, frames, proprio, action)
    m = WorldModel(ANCHORED)
    z = compiled(m, WorldModel.encode)({"params": params}, frames)
    time = jnp.broadcast_to(jnp.arange(z.shape[1]), z.shape[:2])
    other = compiled(m, WorldModel.predict)({"params": params}, z, proprio, action, anchor=z[:, 3], time=time)
    late = slice(ANCHORED.context + 2, None)  # frames whose window no longer holds frame 0 or 3
    assert np.abs(np.asarray(other["z"][:, late]) - np.asarray(full["z"][:, late])).max() > 1e-3
    with pytest.raises(ValueError, match="anchor"):
        compiled(m, WorldModel.predict)({"params": params}, z, proprio, action, time=time)
    with pytest.raises(ValueError, match="time"):
        compiled(m, WorldModel.predict)({"params": params}, z, proprio, action, anchor=z[:, 0])
    # imagination takes the context's first frame as the anchor unless told the episode's
    norm = I.Norm(jnp.zeros(37), jnp.ones(37), jnp.zeros(20), jnp.ones(20))
    st = init_state(ANCHORED, params, norm, frames[:, 4:6], proprio[:, 4:6], action[:, 4:5])
    np.testing.assert_allclose(st.anchor, z[:, 4], atol=1e-6)
    st = init_state(ANCHORED, params, norm, frames[:, 4:6], proprio[:, 4:6], action[:, 4:5], anchor=frames[:, 0])
    np.testing.assert_allclose(st.anchor, z[:, 0], atol=1e-6)
    np.testing.assert_array_equal(st.clock, [1, 1])
    st = init_state(ANCHORED, params, norm, frames[:, 4:6], proprio[:, 4:6], action[:, 4:5], anchor=frames[:, 0],
                    start=jnp.array([4, 4]))
    np.testing.assert_array_equal(st.clock, [5, 5])
    np.testing.assert_array_equal(I.step(ANCHORED, params, norm, st, action[:, 5]).clock, [6, 6])
    assert init_state(DEEP, params, norm, frames[:, 4:6], proprio[:, 4:6], action[:, 4:5]).anchor.shape == (2, 0)


def test_anchor_spans_group_frame_distances_as_documented():
    got = anchor_span(jnp.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 191, 192, 1000, -3]))
    np.testing.assert_array_equal(got, [0, 1, 2, 3, 4, 4, 5, 5, 6, 6, 7, 14, 15, 15, 0])


@pytest.mark.slow
def test_the_anchor_is_weighed_by_its_age_and_dropped_per_sample(model_and_inputs):
    """An anchored model's predictions change with the frames' indices in the episode (the anchor's
    bias by span); a sample whose anchor is dropped predicts the same whatever its anchor, while the
    others still see theirs."""
    _, frames, proprio, action = model_and_inputs
    params = init_params(ANCHORED, jax.random.PRNGKey(1), window=6)
    noise = np.random.default_rng(2)
    params = jax.tree_util.tree_map(lambda x: x + 0.05 * noise.standard_normal(x.shape).astype(np.float32), params)
    m = WorldModel(ANCHORED)
    z = compiled(m, WorldModel.encode)({"params": params}, frames)
    predict = compiled(m, WorldModel.predict)
    early = jnp.broadcast_to(jnp.arange(z.shape[1]), z.shape[:2])
    a = predict({"params": params}, z, proprio, action, anchor=z[:, 0], time=early)
    b = predict({"params": params}, z, proprio, action, anchor=z[:, 0], time=early + 100)
    assert np.abs(np.asarray(a["z"]) - np.asarray(b["z"])).max() > 1e-3
    keep = jnp.array([False, True])
    c = predict({"params": params}, z, proprio, action, anchor=z[:, 0], time=early, anchor_keep=keep)
    d = predict({"params": params}, z, proprio, action, anchor=z[:, 3], time=early, anchor_keep=keep)
    np.testing.assert_allclose(c["z"][0], d["z"][0], atol=1e-6)
    assert np.abs(np.asarray(c["z"][1]) - np.asarray(d["z"][1])).max() > 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["cache", "window"])
def test_anchored_imagination_gives_each_frame_its_index_in_the_episode(model_and_inputs, mode):
    """Both imagination modes give every frame the index the training pass gives it (indices 0-4 each
    have a span of their own, so an index off by one changes the prediction): a context of two frames
    from frame 2 (start=2) steps to the training pass's prediction over frames 2-3 at indices 2-3, and
    the true episode read step by step (observed_features) has the training pass's heads over frames
    0..t at indices 0..t."""
    _, frames, proprio, action = model_and_inputs
    cfg = dataclasses.replace(ANCHORED, imagine=mode)
    params = init_params(cfg, jax.random.PRNGKey(1), window=6)
    noise = np.random.default_rng(2)
    params = jax.tree_util.tree_map(lambda x: x + 0.05 * noise.standard_normal(x.shape).astype(np.float32), params)
    norm = I.Norm(jnp.zeros(37), jnp.ones(37), jnp.zeros(20), jnp.ones(20))
    proprio, action = np.asarray(norm.proprio(proprio)), np.asarray(norm.action(action))  # the model's inputs
    m = WorldModel(cfg)
    z = compiled(m, WorldModel.encode)({"params": params}, frames)
    b = z.shape[0]
    later = compiled(m, WorldModel.predict)({"params": params}, z[:, 2:4], proprio[:, 2:4], action[:, 2:4],
                                            anchor=z[:, 0], time=jnp.broadcast_to(2 + jnp.arange(2), (b, 2)))
    st = init_state(cfg, params, norm, frames[:, 2:4], proprio[:, 2:4], action[:, 2:3], anchor=frames[:, 0],
                    start=jnp.array([2] * b))
    out, _ = I.predict_next(cfg, params, st.z, st.proprio, st.action.at[:, -1].set(action[:, 3]), st.valid,
                            (st.k, st.v), st.anchor, st.clock)
    np.testing.assert_allclose(out["z"], later["z"][:, 1], rtol=1e-4, atol=1e-4)
    wrong = compiled(m, WorldModel.predict)({"params": params}, z[:, 2:4], proprio[:, 2:4], action[:, 2:4],
                                            anchor=z[:, 0], time=jnp.broadcast_to(jnp.arange(2), (b, 2)))
    assert np.abs(np.asarray(wrong["z"][:, 1]) - np.asarray(out["z"])).max() > 1e-3  # the index matters
    t = frames.shape[1] - 1
    x = np.asarray(I.observed_features(cfg, params, norm, frames, proprio, action[:, :t]))
    full = compiled(m, WorldModel.predict)({"params": params}, z[:, :t], proprio[:, :t], action[:, :t],
                                           anchor=z[:, 0], time=jnp.broadcast_to(jnp.arange(t), (b, t)))
    heads = np.stack([jax.nn.sigmoid(full[key]) for key in ("success", "outcome", "progress")], -1)
    np.testing.assert_allclose(x[:, :cfg.context, -3:], heads[:, :cfg.context], atol=1e-5)


@pytest.mark.slow
def test_cached_imagination_is_the_window_until_frames_leave_it_and_reads_true_episodes_as_training(
        model_and_inputs, deep_params):
    """Open loop from C context frames: the cache and the window agree while the buffer still holds
    every frame (K - C + 1 steps) and part after it (the window's oldest frames lose their context,
    the cache's keep theirs); the cached observed features are the training forward pass's heads."""
    _, frames, proprio, action = model_and_inputs
    norm = I.Norm(jnp.full(37, 0.1), jnp.full(37, 2.0), jnp.full(20, -0.2), jnp.full(20, 0.5))
    cache_cfg = dataclasses.replace(DEEP, imagine="cache")
    c, h = 2, 8
    actions = jax.random.uniform(jax.random.PRNGKey(3), (2, h, 20), minval=-1.0, maxval=1.0)
    args = (norm, frames[:, :c], proprio[:, :c], action[:, :c - 1], actions)
    win, cached = I.open_loop(DEEP, deep_params, *args), I.open_loop(cache_cfg, deep_params, *args)
    same = DEEP.context - c + 1
    np.testing.assert_allclose(cached["success"][:, :same], win["success"][:, :same], atol=1e-5)
    np.testing.assert_allclose(cached["features"][:, :same], win["features"][:, :same], atol=1e-4)
    assert np.abs(cached["features"][:, same + 1:] - win["features"][:, same + 1:]).max() > 1e-3

    m = WorldModel(DEEP)
    reps = 3
    frames, proprio, action = (np.concatenate([x] * reps, axis=1) for x in (frames, proprio, action))
    t = frames.shape[1] - 1
    x = np.asarray(I.observed_features(cache_cfg, deep_params, norm, frames, proprio, action[:, :t]))
    z = compiled(m, WorldModel.encode)({"params": deep_params}, frames)
    full = compiled(m, WorldModel.predict)({"params": deep_params}, z[:, :t], norm.proprio(proprio[:, :t]),
                                           norm.action(action[:, :t]))
    heads = np.stack([jax.nn.sigmoid(full[key]) for key in ("success", "outcome", "progress")], -1)
    np.testing.assert_allclose(x[..., -3:], heads, atol=1e-5)
    window = np.asarray(I.observed_features(DEEP, deep_params, norm, frames, proprio, action[:, :t]))
    np.testing.assert_allclose(window[:, :DEEP.context, -3:], heads[:, :DEEP.context], atol=1e-5)
    assert np.abs(window[:, DEEP.context + 1:, -3:] - heads[:, DEEP.context + 1:]).max() > 1e-4


def test_imagine_mode_is_checked():
    with pytest.raises(ValueError, match="imagine must be one of"):
        dataclasses.replace(CFG, imagine="kv").validate()


def test_reencoding_imagination_feeds_back_the_latents_of_the_decoded_8_bit_frame(model_and_inputs):
    params, frames, proprio, action = model_and_inputs
    norm = I.Norm(jnp.zeros(37), jnp.ones(37), jnp.zeros(20), jnp.ones(20))
    m = WorldModel(CFG)
    c = 3
    st0 = init_state(CFG, params, norm, frames[:, :c], proprio[:, :c], action[:, :c - 1])
    plain = imagine_step(CFG, params, norm, st0, action[:, c - 1])
    re_cfg = dataclasses.replace(CFG, reencode=True)
    again = imagine_step(re_cfg, params, norm, st0, action[:, c - 1])
    np.testing.assert_array_equal(again.frame, plain.frame)  # the same prediction and frame
    np.testing.assert_allclose(again.proprio, plain.proprio, atol=1e-6)
    shown = I.to_uint8(again.frame)
    np.testing.assert_allclose(again.z[:, -1], compiled(m, WorldModel.encode)({"params": params}, shown),
                               atol=1e-5)
    np.testing.assert_allclose(again.z[:, :-1], plain.z[:, :-1])
    assert float(jnp.abs(again.z[:, -1] - plain.z[:, -1]).max()) > 1e-3


def _identity_norm_and_batch(frames, proprio, action):
    """A Norm that leaves proprio and actions as they are, and a loss batch of the inputs with no
    success or progress."""
    norm = I.Norm(jnp.zeros(37), jnp.ones(37), jnp.zeros(20), jnp.ones(20))
    batch = {"frames": frames, "proprio": proprio, "action": action, "success": np.zeros((2, 6), bool),
             "progress": np.zeros((2, 6), np.float32), "outcome": np.zeros((2,), bool)}
    return norm, batch


def _smoke_loss(model_and_inputs):
    """(params, norm, batch, the smoke preset's config, loss_fn jitted with the config static): one
    program a configuration, where op by op each operation would compile apart."""
    from wm.train import loss_fn

    params, frames, proprio, action = model_and_inputs
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    return params, norm, batch, make_config("smoke"), jax.jit(loss_fn, static_argnums=3)


@pytest.mark.slow
def test_reencoded_rollout_passes_change_only_the_passes(model_and_inputs):
    params, norm, batch, cfg, loss = _smoke_loss(model_and_inputs)
    parts = {}
    for model_re, passes_re in ((False, False), (True, False), (True, True)):
        c = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, reencode=model_re), reencode_passes=passes_re)
        parts[model_re, passes_re] = loss(params, batch, norm, c)[1]
    plain, only_model, both = parts[False, False], parts[True, False], parts[True, True]
    for k in plain:  # model.reencode alone is an imagination setting: training is unchanged
        np.testing.assert_allclose(only_model[k], plain[k], rtol=1e-6, err_msg=k)
    for k in ("latent", "pixel", "proprio", "recon"):  # teacher forcing: the same
        np.testing.assert_allclose(both[k], plain[k], rtol=1e-6, err_msg=k)
    assert abs(float(both["latent_pass1"]) - float(plain["latent_pass1"])) > 1e-6


@pytest.mark.slow
def test_proprio_noise_moves_what_reads_the_body_only_where_training_draws_it(model_and_inputs):
    params, norm, batch, cfg, loss = _smoke_loss(model_and_inputs)
    noisy = dataclasses.replace(cfg, proprio_noise=2.0)
    rng = jax.random.PRNGKey(3)
    plain, drawn = loss(params, batch, norm, cfg, rng)[1], loss(params, batch, norm, noisy, rng)[1]
    for k in ("proprio", "latent", "proprio_pass1"):  # the predictions read the noisy body, later passes included
        assert abs(float(drawn[k]) - float(plain[k])) > 1e-6, k
    again = loss(params, batch, norm, noisy, rng)[1]
    np.testing.assert_array_equal(again["proprio"], drawn["proprio"])  # the draw follows rng alone
    unseeded = loss(params, batch, norm, noisy)[1]  # validation draws nothing: the plain loss
    for k in plain:
        np.testing.assert_allclose(unseeded[k], loss(params, batch, norm, cfg)[1][k], rtol=1e-6, err_msg=k)


@pytest.mark.parametrize("setting", ["proprio_noise=-0.1", "context_noise=-0.1"])
def test_a_negative_noise_is_refused(setting):
    with pytest.raises(ValueError, match="context_noise and proprio_noise"):
        make_config("smoke", [setting])


@jax.jit
def _first_pass(params, frames, proprio, action):
    """The teacher-forced pass's decoded frames (B, T-1, S, S, 3) in [0, 1], as loss_fn decodes them."""
    m = WorldModel(CFG)
    z = m.apply({"params": params}, frames, method=WorldModel.encode)
    pred = m.apply({"params": params}, z, proprio, action, method=WorldModel.predict)
    return m.apply({"params": params}, pred["z"][:, :-1], frames[:, :-1] / 255.0, pred["flow"][:, :-1],
                   method=WorldModel.decode)


def _assert_adds_only(term: str, weight: float, passes: int, plain: tuple, with_term: tuple) -> list[str]:
    """That a loss_fn output (total, parts) with a weighted term holds the term once per pass beside
    every part of the plain output unchanged, and its total is the plain one's plus weight times the
    term's parts; returns their names."""
    (plain_total, plain_parts), (total, parts) = plain, with_term
    tags = [term] + [f"{term}_pass{k}" for k in range(1, 1 + passes)]
    assert term not in plain_parts and all(t in parts for t in tags)
    for k in set(plain_parts) - {"loss"}:  # every other term as before
        np.testing.assert_allclose(parts[k], plain_parts[k], rtol=1e-5, err_msg=k)
    np.testing.assert_allclose(total, plain_total + weight * sum(parts[t] for t in tags), rtol=1e-5)
    return tags


@pytest.mark.slow
def test_the_perceptual_loss_adds_the_weighted_lpips_of_every_fourth_predicted_frame(model_and_inputs):
    from wm import perceptual
    from wm.train import loss_fn

    params, frames, proprio, action = model_and_inputs
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    cfg = make_config("smoke")
    loss = jax.jit(loss_fn, static_argnums=3)  # the plain configuration's program is the reencode test's
    plain_total, plain = loss(params, batch, norm, cfg)
    with_lpips = dataclasses.replace(cfg, w_lpips=0.5)
    total, parts = loss(params, batch, norm, with_lpips, None, perceptual.params())
    tags = _assert_adds_only("lpips", 0.5, cfg.rollout_passes, (plain_total, plain), (total, parts))
    assert all(0.0 < float(parts[t]) < 1.0 for t in tags)

    # frames 1 and 5 of the window, read by LPIPS' own 8-bit path
    shown, true = np.asarray(I.to_uint8(_first_pass(params, frames, proprio, action)[:, ::4])), frames[:, 1::4]
    ref = perceptual.lpips(shown.reshape(-1, 64, 64, 3), true.reshape(-1, 64, 64, 3)).mean()
    np.testing.assert_allclose(parts["lpips"], ref, atol=2e-3)
    with pytest.raises(ValueError, match="w_lpips"):
        loss_fn(params, batch, norm, with_lpips)
    with pytest.raises(ValueError, match="w_lpips"):
        make_config("smoke", ["w_lpips=-1"])


@pytest.mark.slow
def test_the_read_loss_adds_the_probes_action_difference_on_every_fourth_predicted_frame(model_and_inputs):
    from sim_data.policies.bc import BCPolicy, PolicyNetConfig
    from sim_data.policies.bc import init_params as policy_params
    from sim_data.policies.registry import PolicySource
    from wm.probes import make_probes, read_dims, read_loss
    from wm.train import loss_fn

    params, frames, proprio, action = model_and_inputs
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    net = PolicyNetConfig(width=4, hidden=8, chunk=2, size=64)
    unit = {"proprio_mean": np.zeros(37), "proprio_std": np.ones(37), "action_mean": np.zeros(20),
            "action_std": np.ones(20)}
    pol = policy_params(net, jax.random.PRNGKey(3), unit, use_proprio=True)
    pol["net"]["head"]["kernel"] = pol["net"]["head"]["kernel"] + 0.1  # zero-initialised: the frames must matter
    probes = make_probes([PolicySource("mug/conv/1", "learned", "mug", BCPolicy(net), pol, {})], ["mug", "wipe"])
    batch |= {"task": np.array([0, 1], np.int32), "start": np.array([0, 7], np.int32)}  # window 1 is wipe's
    cfg = make_config("smoke")
    loss = jax.jit(loss_fn, static_argnums=3)
    plain_total, plain = loss(params, batch, norm, cfg)
    total, parts = loss(params, batch, norm, dataclasses.replace(cfg, w_read=0.5), None, None, probes)
    tags = _assert_adds_only("read", 0.5, cfg.rollout_passes, (plain_total, plain), (total, parts))
    assert all(float(parts[t]) > 0.0 for t in tags)

    # window 0 (mug) alone, its frames 1 and 5 at steps 1 and 5 with their own proprioception
    pred, true = _first_pass(params, frames, proprio, action)[0, ::4], frames[0, 1::4] / 255.0
    want = read_loss(probes, pred, true, proprio[0, 1::4], np.array([1, 5], np.int32), np.zeros(2, np.int32))
    np.testing.assert_allclose(parts["read"], want, rtol=1e-4)
    # read_closure weighs the hands' closure commands in the same frames' reading
    _, closed = loss(params, batch, norm, dataclasses.replace(cfg, w_read=0.5, read_closure=10.0), None, None, probes)
    want = read_loss(probes, pred, true, proprio[0, 1::4], np.array([1, 5], np.int32), np.zeros(2, np.int32),
                     read_dims(10.0))
    np.testing.assert_allclose(closed["read"], want, rtol=1e-4)
    with pytest.raises(ValueError, match="w_read"):
        loss_fn(params, batch, norm, dataclasses.replace(cfg, w_read=0.5))


def test_grip_focus_weighs_the_frames_errors_around_the_hands_grip_sites(model_and_inputs):
    from wm.train import grip_weights, loss_fn, weighted_mse

    # by hand: a 4 x 4 frame, the right site on pixel (row 1, column 2)'s centre, the left behind the camera
    grip = np.array([[[[np.nan, np.nan], [2.5 / 4, 1.5 / 4]]]], np.float32)  # (1, 1, 2, 2) as (x, y)
    w = np.asarray(grip_weights(grip, 4, 3.0, 0.25))[0, 0]
    rows, cols = np.mgrid[0:4, 0:4]
    d2 = ((cols + 0.5) / 4 - 2.5 / 4) ** 2 + ((rows + 0.5) / 4 - 1.5 / 4) ** 2
    np.testing.assert_allclose(w, 1 + 3 * np.exp(-d2 / (2 * 0.25**2)), rtol=1e-6)
    assert w[1, 2] == pytest.approx(4.0) and w.argmax() == 1 * 4 + 2
    err = np.arange(48, dtype=np.float32).reshape(1, 4, 4, 3) / 48
    np.testing.assert_allclose(weighted_mse(err, 0 * err, w[None]), (w[..., None] * err[0] ** 2).sum() / (w.sum() * 3),
                               rtol=1e-6)
    np.testing.assert_allclose(weighted_mse(err, 0 * err), np.mean(err**2), rtol=1e-6)

    # through loss_fn: the teacher-forced pass's pixel term is its frames' error so weighted; the rest as before
    params, frames, proprio, action = model_and_inputs
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    batch["grip_px"] = np.random.default_rng(5).uniform(0, 1, (2, 6, 2, 2)).astype(np.float32)
    cfg = make_config("smoke")
    loss = jax.jit(loss_fn, static_argnums=3)
    _, plain = loss(params, batch, norm, cfg)
    _, parts = loss(params, batch, norm, dataclasses.replace(cfg, grip_focus=4.0))
    pred, target = _first_pass(params, frames, proprio, action), frames[:, 1:] / 255.0
    want = weighted_mse(pred, target, grip_weights(batch["grip_px"][:, 1:], 64, 4.0, cfg.grip_radius))
    np.testing.assert_allclose(parts["pixel"], want, rtol=1e-4)
    np.testing.assert_allclose(plain["pixel"], np.mean((np.asarray(pred) - target) ** 2), rtol=1e-4)
    assert abs(float(parts["pixel"]) - float(plain["pixel"])) > 1e-6
    np.testing.assert_allclose(parts["latent"], plain["latent"], rtol=1e-6)
    with pytest.raises(ValueError, match="grip_focus"):
        make_config("smoke", ["grip_focus=-1"])


def test_action_contrast_is_the_log_share_of_the_true_actions_prediction():
    target = np.zeros((2, 3, 4), np.float32)
    pred = np.full_like(target, 0.1)
    pred[1] = 0.0  # window 1 predicted exactly
    other = np.full_like(target, 0.3)
    # window 0: d_true 0.01, d_other 0.09 -> log(1 + 1/9); window 1: d_true 0 -> 0
    np.testing.assert_allclose(M.action_contrast(pred, other, target), np.log1p(1 / 9) / 2, rtol=1e-5)
    # the same prediction whatever the actions: window 0 log 2, window 1 (exact) 0
    np.testing.assert_allclose(M.action_contrast(pred, pred, target), np.log(2) / 2, rtol=1e-5)


@pytest.mark.slow
def test_the_action_contrast_term_predicts_the_window_again_under_another_windows_actions(model_and_inputs):
    from wm.train import loss_fn

    params, frames, proprio, action = model_and_inputs
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    cfg = make_config("smoke")
    loss = jax.jit(loss_fn, static_argnums=3)
    plain_total, plain = loss(params, batch, norm, cfg)
    total, parts = loss(params, batch, norm, dataclasses.replace(cfg, w_contrast=0.5))
    for k in set(plain) - {"loss"}:  # every other term as before
        np.testing.assert_allclose(parts[k], plain[k], rtol=1e-5, err_msg=k)
    np.testing.assert_allclose(total, plain_total + 0.5 * parts["contrast"], rtol=1e-5)

    @jax.jit
    def predictions(params):  # the teacher-forced latents under the windows' own actions and under the other's
        m = WorldModel(CFG)
        z = m.apply({"params": params}, frames, method=WorldModel.encode)
        own = m.apply({"params": params}, z, proprio, action, method=WorldModel.predict)["z"][:, :-1]
        swapped = m.apply({"params": params}, z, proprio, action[::-1], method=WorldModel.predict)["z"][:, :-1]
        return own, swapped, z[:, 1:]

    own, swapped, target = predictions(params)  # a batch of 2: rolling by one swaps the windows' actions
    assert not np.allclose(own, swapped)
    np.testing.assert_allclose(parts["contrast"], M.action_contrast(own, swapped, target), rtol=1e-4)
    assert 0.0 < float(parts["contrast"]) < 1.0
    with pytest.raises(ValueError, match="w_contrast"):
        make_config("smoke", ["w_contrast=-1"])
    with pytest.raises(ValueError, match="batch >= 2"):
        make_config("smoke", ["w_contrast=0.1", "batch=1"])


def test_gaussian_kl_is_the_closed_form_summed_over_the_code():
    # KL(N(1, 0.5^2) || N(0, 1)) = log 2 + (0.25 + 1) / 2 - 1/2; a Gaussian against itself 0
    q_mean, q_logstd = np.array([[1.0, 0.3]]), np.log(np.array([[0.5, 2.0]]))
    p_mean, p_logstd = np.array([[0.0, 0.3]]), np.array([[0.0, np.log(2.0)]])
    np.testing.assert_allclose(M.gaussian_kl(q_mean, q_logstd, p_mean, p_logstd), [np.log(2) + 0.625 - 0.5],
                               rtol=1e-6)


@pytest.fixture(scope="module")
def stochastic_model(model_and_inputs):
    """A model with a stochastic code of 3, its parameters perturbed so that the code reaches the outputs."""
    cfg = dataclasses.replace(CFG, stochastic=3)
    params = init_params(cfg, jax.random.PRNGKey(0), window=6)
    noise = np.random.default_rng(2)
    return cfg, jax.tree_util.tree_map(lambda x: x + 0.05 * noise.standard_normal(x.shape).astype(np.float32), params)


@pytest.mark.slow
def test_a_stochastic_model_reads_its_code_from_the_posterior_in_training_and_the_prior_in_imagination(
        model_and_inputs, stochastic_model):
    _, frames, proprio, action = model_and_inputs
    cfg, params = stochastic_model
    assert "stochastic" not in init_params(CFG, jax.random.PRNGKey(0), window=6)["dynamics"]  # off: as before
    m = WorldModel(cfg)
    z = compiled(m, WorldModel.encode)({"params": params}, frames)
    predict = compiled(m, WorldModel.predict)
    draws = np.random.default_rng(3).standard_normal((2, 6, 3)).astype(np.float32)
    prior_mean = predict({"params": params}, z, proprio, action)
    prior_draw = predict({"params": params}, z, proprio, action, noise=draws)
    post_mean = predict({"params": params}, z, proprio, action, target=z)
    assert set(prior_mean) >= {"prior_mean", "prior_logstd"} and "post_mean" not in prior_mean
    assert post_mean["post_mean"].shape == (2, 6, 3)
    for other in (prior_draw, post_mean):  # the code reaches the prediction
        assert float(jnp.abs(other["z"] - prior_mean["z"]).max()) > 1e-4
    np.testing.assert_allclose(prior_draw["prior_mean"], prior_mean["prior_mean"], atol=1e-6)
    # a draw of zero noise is the mean
    zero = predict({"params": params}, z, proprio, action, noise=np.zeros_like(draws))
    np.testing.assert_allclose(zero["z"], prior_mean["z"], atol=1e-6)
    # imagination's step under the same draw for its last slot equals the window's prediction there
    norm = I.Norm(jnp.zeros(37), jnp.ones(37), jnp.zeros(20), jnp.ones(20))
    c = 3
    tf = predict({"params": params}, z[:, :c], proprio[:, :c], action[:, :c], noise=draws[:, :c])
    st = init_state(cfg, params, norm, frames[:, :c], proprio[:, :c], action[:, :c - 1])
    stepped = imagine_step(cfg, params, norm, st, action[:, c - 1], draws[:, c - 1])
    np.testing.assert_allclose(stepped.z[:, -1], tf["z"][:, -1], atol=1e-5)
    central = imagine_step(cfg, params, norm, st, action[:, c - 1])
    assert float(jnp.abs(central.z[:, -1] - stepped.z[:, -1]).max()) > 1e-4
    # closed loop: a key gives one imagination, another key another
    policy = {"action": jnp.full((20,), 0.3)}
    runs = [I.closed_loop(cfg, HoldStill(), 4, params, norm, policy, frames[:, :2], proprio[:, :2], action[:, :1],
                          jax.random.PRNGKey(k)) for k in (0, 0, 1)]
    np.testing.assert_array_equal(runs[0]["frames"], runs[1]["frames"])
    assert float(jnp.abs(runs[0]["features"] - runs[2]["features"]).max()) > 1e-4
    # an episode's draws are its own, whatever its row: the batch reversed gives its episodes reversed
    flipped = I.closed_loop(cfg, HoldStill(), 4, params, norm, policy, frames[::-1, :2], proprio[::-1, :2],
                            action[::-1, :1], jax.random.PRNGKey(0))
    np.testing.assert_allclose(flipped["features"][::-1], runs[0]["features"], atol=1e-5)
    with pytest.raises(ValueError, match="stochastic"):
        dataclasses.replace(CFG, stochastic=-1).validate()


def test_the_code_divergence_is_balanced_and_counted_above_its_free_nats():
    from wm.train import _code_kl

    # two frames with a target and a last one without: KL 0.8181 (N(1, 0.25) against N(0, 1)) and 0
    pred = {"post_mean": np.array([[[1.0], [0.0], [9.0]]]), "post_logstd": np.log(np.array([[[0.5], [1.0], [1.0]]])),
            "prior_mean": np.zeros((1, 3, 1)), "prior_logstd": np.zeros((1, 3, 1))}
    kl = np.log(2) + 0.625 - 0.5
    mean, balanced = _code_kl(pred, 0.0)
    np.testing.assert_allclose([mean, balanced], [kl / 2, kl / 2], rtol=1e-6)  # the last frame left out
    # below the free nats the posterior's share counts the free nats (frame 0 its KL, frame 1 0.5); the
    # prior's share is always the divergence
    np.testing.assert_allclose(_code_kl(pred, 0.5)[1], 0.8 * kl / 2 + 0.2 * (kl + 0.5) / 2, rtol=1e-6)
    # the prior learns 0.8 of the gradient, the posterior 0.2
    grads = jax.grad(lambda p: _code_kl(p, 0.0)[1])({k: jnp.asarray(v, jnp.float32) for k, v in pred.items()})
    np.testing.assert_allclose(grads["prior_mean"][0, 0], -0.8 * 1.0 / 2, rtol=1e-5)  # d/dmu_p (mu_q - mu_p)^2 / 2
    np.testing.assert_allclose(grads["post_mean"][0, 0], 0.2 * 1.0 / 2, rtol=1e-5)


@pytest.mark.slow
def test_the_code_divergence_enters_the_loss_above_its_free_nats(model_and_inputs, stochastic_model):
    from wm.train import loss_fn

    _, frames, proprio, action = model_and_inputs
    cfg_model, params = stochastic_model
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    cfg = dataclasses.replace(make_config("smoke"), model=cfg_model, rollout_passes=1, w_kl=0.01)
    loss = jax.jit(loss_fn, static_argnums=3)
    # far above any divergence, the posterior's share of a frame's term is the free nats: 0.2 of them, a pass each
    low_total, low = loss(params, batch, norm, dataclasses.replace(cfg, free_nats=1000.0))
    high_total, _ = loss(params, batch, norm, dataclasses.replace(cfg, free_nats=2000.0))
    np.testing.assert_allclose(high_total - low_total, 0.01 * 0.2 * 1000.0 * 2, rtol=1e-4)
    assert {"kl", "kl_pass1"} <= set(low) and float(low["kl"]) > 0.0
    # at no free nats the term is the divergence itself (0.8 + 0.2 of the same value)
    total, parts = loss(params, batch, norm, dataclasses.replace(cfg, free_nats=0.0))
    np.testing.assert_allclose(total - low_total, 0.01 * 0.2 * (parts["kl"] + parts["kl_pass1"] - 2000.0), rtol=1e-4)
    # training draws codes from the posterior (rng given); validation takes its mean
    drawn = loss(params, batch, norm, cfg, jax.random.PRNGKey(0))[1]
    assert abs(float(drawn["latent"]) - float(low["latent"])) > 0
    with pytest.raises(ValueError, match="w_kl"):
        make_config("smoke", ["w_kl=0"])


@pytest.mark.slow
def test_the_judge_reads_the_scene_state_imagination_and_observation_predict(model_and_inputs):
    # a model with the scene head: each imagined step carries the head's prediction for the new frame,
    # its step features hold it in the "scene" columns, and the features of a true episode hold the
    # prediction from the true context, so the judge reads the same quantity from both
    _, frames, proprio, action = model_and_inputs
    cfg = dataclasses.replace(CFG, scene=True)
    noise = np.random.default_rng(3)
    params = jax.tree_util.tree_map(lambda x: x + 0.05 * noise.standard_normal(x.shape).astype(np.float32),
                                    init_params(cfg, jax.random.PRNGKey(0), window=6))
    norm = _identity_norm_and_batch(frames, proprio, action)[0]
    cols = I.feature_columns(cfg, ("scene",))
    assert len(cols) == cfg.scene_dim and I.feature_dim(cfg) == I.feature_dim(CFG) + cfg.scene_dim
    st = init_state(cfg, params, norm, frames[:, :1], proprio[:, :1], action[:, :0])
    assert st.scene.shape == (2, cfg.scene_dim) and not np.asarray(st.scene).any()
    acts = st.action.at[:, -1].set(norm.action(action[:, 0]))
    want = I.predict_next(cfg, params, st.z, st.proprio, acts, st.valid, (st.k, st.v), st.anchor, st.clock)[0]["scene"]
    nxt = imagine_step(cfg, params, norm, st, action[:, 0])
    np.testing.assert_allclose(nxt.scene, want, atol=1e-5)
    assert np.asarray(want).std() > 1e-3  # the head's output, not a constant
    np.testing.assert_allclose(np.asarray(jax.jit(I.step_features)(norm, nxt, action[:, 0]))[:, cols], want, atol=1e-5)
    other = imagine_step(cfg, params, norm, st, -action[:, 0])
    assert np.abs(np.asarray(other.scene) - np.asarray(nxt.scene)).max() > 1e-4  # it follows the action
    seen = np.asarray(I.observed_features(cfg, params, norm, frames[:, :2], proprio[:, :2], action[:, :1]))
    np.testing.assert_allclose(seen[:, 0, cols], want, atol=1e-4)
    assert len(I.feature_columns(CFG, ("latent", "scene"))) == 4 * CFG.latent  # no scene head: no columns
    with pytest.raises(ValueError, match="no columns"):
        I.feature_columns(CFG, ("scene",))


@pytest.mark.slow  # an option no preset uses (make test-slow runs it)
def test_blind_groups_of_the_next_body_state_read_only_their_present_and_the_action(model_and_inputs):
    # the blind columns (joint velocities, base velocity) come out the same under other frames and
    # another state of the rest of the body, and move with their own present and the action; the
    # other columns are the plain model's of the same shared parameters, frames and all
    _, frames, proprio, action = model_and_inputs
    cfg = dataclasses.replace(CFG, blind=("joint_vel", "base"))
    params = init_params(cfg, jax.random.PRNGKey(0), window=6)
    blind = np.zeros(cfg.proprio_dim, bool)
    blind[16:35] = True
    np.testing.assert_array_equal(np.asarray(cfg.blind_mask), blind)
    m = WorldModel(cfg)
    predict = compiled(m, WorldModel.predict)
    z = compiled(m, WorldModel.encode)({"params": params}, frames)
    out = predict({"params": params}, z, proprio, action)["proprio"]
    noise = np.random.default_rng(0).standard_normal(proprio.shape).astype(np.float32)
    for moved in (predict({"params": params}, -z[:, ::-1], proprio, action)["proprio"],
                  predict({"params": params}, z, np.where(blind, proprio, proprio + noise), action)["proprio"]):
        np.testing.assert_allclose(moved[..., blind], out[..., blind], atol=1e-6)
        assert float(jnp.abs(moved[..., ~blind] - out[..., ~blind]).max()) > 1e-4
    own = predict({"params": params}, z, np.where(blind, proprio + noise, proprio), action)["proprio"]
    assert float(jnp.abs((own - noise)[..., blind] - out[..., blind]).max()) > 1e-4  # beyond the residual
    acted = predict({"params": params}, z, proprio, action + noise[..., :action.shape[-1]])["proprio"]
    assert float(jnp.abs(acted[..., blind] - out[..., blind]).max()) > 1e-4
    # with the linear map zeroed, the blind columns move by exactly its map of their present and the action
    no_linear = jax.tree_util.tree_map(jnp.zeros_like, params["dynamics"]["blind"]["linear"])
    flat = {**params, "dynamics": {**params["dynamics"], "blind": {**params["dynamics"]["blind"], "linear": no_linear}}}
    lin = params["dynamics"]["blind"]["linear"]
    own_in = np.concatenate([np.where(blind, proprio, 0.0), action], -1)
    np.testing.assert_allclose(out[..., blind], np.clip(predict({"params": flat}, z, proprio, action)["proprio"]
                               + own_in @ lin["kernel"] + lin["bias"], -INPUT_CLIP, INPUT_CLIP)[..., blind],
                               atol=1e-4)
    plain_params = {**params, "dynamics": {k: v for k, v in params["dynamics"].items() if k != "blind"}}
    plain = compiled(WorldModel(CFG), WorldModel.predict)({"params": plain_params}, z, proprio, action)["proprio"]
    np.testing.assert_allclose(out[..., ~blind], plain[..., ~blind], atol=1e-6)
    assert float(jnp.abs(out[..., blind] - plain[..., blind]).max()) > 1e-4
    # two paths: the arms' groups read each other, the base reads the base alone, each with its own parameters
    two = dataclasses.replace(CFG, blind=("joints", "joint_vel", "base"), blind_alone=("base",))
    two.validate()
    assert two.blind_paths == (("blind", ("joints", "joint_vel")), ("blind_base", ("base",)))
    arms, base = np.zeros(two.proprio_dim, bool), np.zeros(two.proprio_dim, bool)
    arms[:32], base[32:35] = True, True
    np.testing.assert_array_equal(two.blind_mask, arms | base)
    params2 = init_params(two, jax.random.PRNGKey(0), window=6)
    assert {"blind", "blind_base"} <= set(params2["dynamics"])
    predict2 = compiled(WorldModel(two), WorldModel.predict)
    out2 = predict2({"params": params2}, z, proprio, action)["proprio"]
    arms_moved = predict2({"params": params2}, z, np.where(arms, proprio + noise, proprio), action)["proprio"]
    base_moved = predict2({"params": params2}, z, np.where(base, proprio + noise, proprio), action)["proprio"]
    np.testing.assert_allclose(arms_moved[..., base], out2[..., base], atol=1e-6)  # the base ignores the arms
    np.testing.assert_allclose(base_moved[..., arms], out2[..., arms], atol=1e-6)  # and the arms the base
    assert float(jnp.abs(arms_moved[..., arms] - out2[..., arms]).max()) > 1e-4
    assert float(jnp.abs(base_moved[..., base] - out2[..., base]).max()) > 1e-4
    for bad in (("legs",), ("base", "joint_vel"), ("base", "base")):
        with pytest.raises(ValueError, match="proprioception groups"):
            dataclasses.replace(CFG, blind=bad).validate()
    for blind, alone in ((("joints", "base"), ("hands",)), (("joints", "base"), ("base", "joints")), ((), ("base",))):
        with pytest.raises(ValueError, match="groups of blind"):
            dataclasses.replace(CFG, blind=blind, blind_alone=alone).validate()
    with pytest.raises(ValueError, match="proprio_dim"):
        dataclasses.replace(CFG, blind=("base",), proprio_dim=12).validate()


@pytest.mark.slow
def test_the_scene_head_predicts_the_standardised_scene_state_and_its_error_enters_the_loss(model_and_inputs):
    from wm.train import loss_fn

    params0, frames, proprio, action = model_and_inputs
    cfg_model = dataclasses.replace(CFG, scene=True)
    assert cfg_model.scene_dim == len(SCENE_STATE_NAMES)
    noise = np.random.default_rng(3)
    params = jax.tree_util.tree_map(lambda x: x + 0.05 * noise.standard_normal(x.shape).astype(np.float32),
                                    init_params(cfg_model, jax.random.PRNGKey(0), window=6))
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    scene = np.random.default_rng(4).normal(2.0, 3.0, (2, 6, cfg_model.scene_dim)).astype(np.float32)
    mean, std = scene.mean((0, 1)), scene.std((0, 1))
    norm = norm.replace(scene_mean=jnp.asarray(mean), scene_std=jnp.asarray(std))
    batch["scene"] = scene
    cfg = dataclasses.replace(make_config("smoke"), model=cfg_model, rollout_passes=0, w_scene=0.5)
    m = WorldModel(cfg_model)
    z = compiled(m, WorldModel.encode)({"params": params}, frames)
    pred = compiled(m, WorldModel.predict)({"params": params}, z, proprio, action)
    assert pred["scene"].shape == (2, 6, cfg_model.scene_dim)
    want = np.mean((np.asarray(pred["scene"])[:, :-1] - (scene[:, 1:] - mean) / std) ** 2)
    loss = jax.jit(loss_fn, static_argnums=3)
    total, parts = loss(params, batch, norm, cfg)
    np.testing.assert_allclose(parts["scene"], want, rtol=1e-4)
    plain_total, plain = loss(params, batch, norm, dataclasses.replace(cfg, w_scene=1.5))
    np.testing.assert_allclose(plain_total - total, 1.0 * want, rtol=1e-4)  # the weight scales the term alone
    assert "scene" not in loss(params0, batch, norm, make_config("smoke"))[1]  # without the head: no term


def test_the_norm_carries_the_scene_statistics_of_the_training_split_through_norm_json(smoke_dataset):
    _, data, _ = smoke_dataset
    cache = TrainingCache(data)
    norm = compute_norm(cache)
    rows = np.concatenate([cache.episode(i)["scene"] for i in cache.select("train")])
    np.testing.assert_allclose(norm.scene_mean, rows.mean(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(norm.scene_std, np.maximum(rows.std(0), 1e-2), rtol=1e-4)
    back = I.Norm.from_dict(json.loads(json.dumps(norm.to_dict())))
    np.testing.assert_array_equal(back.scene_std, norm.scene_std)
    old = {k: v for k, v in norm.to_dict().items() if not k.startswith("scene")}  # a norm.json written before
    assert I.Norm.from_dict(old).scene_mean is None and "scene_mean" not in I.Norm.from_dict(old).to_dict()
    with pytest.raises(ValueError, match="no scene state"):
        I.Norm.from_dict(old).scene(rows)
    far = norm.scene(rows[:3] + 1e6)  # an object far from anywhere training saw it: clipped as the inputs are
    np.testing.assert_array_equal(far, np.full_like(rows[:3], I.INPUT_CLIP))
    with pytest.raises(ValueError, match="w_scene"):
        make_config("smoke", ["model.scene=true", "w_scene=0"])
    check_dataset(make_config("smoke", ["model.scene=true"]), cache)
    with pytest.raises(ValueError, match="24 scene-state values a frame, model.scene_dim is 23"):
        check_dataset(make_config("smoke", ["model.scene=true", "model.scene_dim=23"]), cache)


def _whole_smoke_run(smoke_dataset, out: Path, setting: str):
    """`wm.train --config smoke` with one setting, judge and eval.json included: its eval.json's PSNR
    checked finite; returns load_trained(out)."""
    _, data, _ = smoke_dataset
    assert train_main(["--config", "smoke", "--data", str(data), "--out", str(out), setting]) == 0
    report = json.loads((out / "eval.json").read_text())
    assert all(np.isfinite(report["frame_quality"]["psnr"]))
    return load_trained(out)


@pytest.mark.slow
def test_a_stochastic_model_trains_fits_its_judge_on_sampled_imaginations_and_writes_eval_json(smoke_dataset,
                                                                                             tmp_path):
    out = tmp_path / "stochastic"
    cfg, params, _ = _whole_smoke_run(smoke_dataset, out, "model.stochastic=4")
    assert cfg.model.stochastic == 4 and "prior_out" in params["dynamics"]["stochastic"]
    log = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["kl"]) for r in log if "kl" in r)


@pytest.mark.slow
def test_a_model_with_the_scene_head_trains_on_the_cached_scene_state_and_writes_eval_json(smoke_dataset, tmp_path):
    out = tmp_path / "scene"
    cfg, params, norm = _whole_smoke_run(smoke_dataset, out, "model.scene=true")
    assert cfg.model.scene and norm.scene_std is not None
    log = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["scene"]) for r in log if "scene" in r) and any("scene" in r for r in log)


@pytest.mark.slow
def test_a_model_with_the_frame_generator_trains_writes_eval_json_and_travels_in_a_bundle(smoke_dataset, tmp_path):
    out = tmp_path / "refine"
    cfg, params, _ = _whole_smoke_run(smoke_dataset, out, "model.refine=2")
    assert cfg.model.refine == 2 and "refiner" in params
    log = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    trained = [r for r in log if "refine" in r]
    assert trained and all(np.isfinite(r["refine"]) and r["grad_norm_refiner"] > 0 for r in trained)
    write_bundle(out, tmp_path / "bundle")
    back_cfg, back, _ = load_trained(tmp_path / "bundle")
    assert back_cfg.model.refine == 2
    np.testing.assert_allclose(back["refiner"]["Conv_2"]["kernel"], params["refiner"]["Conv_2"]["kernel"], atol=1e-2)


@pytest.mark.slow
def test_a_run_with_grip_focus_trains_on_the_caches_grip_pixels_with_its_frame_generator(smoke_dataset, tmp_path):
    _, data, _ = smoke_dataset
    out = tmp_path / "grip"
    assert train_main(["--config", "smoke", "--data", str(data), "--out", str(out), "grip_focus=4", "model.refine=2",
                       "steps=4", "log_every=2", "eval_every=4", "ckpt_every=4", "judge_episodes=0",
                       "eval_episodes=2"]) == 0
    cfg, _, _ = load_trained(out)
    assert cfg.grip_focus == 4.0
    log = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert any("refine" in r for r in log) and all(np.isfinite(r["pixel"]) for r in log if "pixel" in r)


def test_learning_rate_is_a_function_of_the_step():
    from wm.train import learning_rate

    # smoke: lr 3e-3, warmup 5, 40 steps, the last quarter (10 steps) decaying linearly to 0
    wsd = learning_rate(make_config("smoke", ["steps=40", "cooldown=0.25"]))
    got = [float(wsd(s)) for s in (0, 1, 5, 20, 30, 35, 40)]
    np.testing.assert_allclose(got, [0.0, 6e-4, 3e-3, 3e-3, 3e-3, 1.5e-3, 0.0], rtol=1e-6, atol=1e-12)
    # without cooldown: the warmup, then a cosine to 5% of lr at the last step
    cos = learning_rate(make_config("smoke", ["steps=40"]))
    mid = 5 + (40 - 5) / 2
    np.testing.assert_allclose([float(cos(5)), float(cos(mid)), float(cos(40))],
                               [3e-3, 3e-3 * (0.05 + 0.95 * 0.5), 1.5e-4], rtol=1e-5)
    with pytest.raises(ValueError, match="cooldown"):
        make_config("smoke", ["cooldown=1.5"])
    with pytest.raises(ValueError, match="max_minutes"):
        make_config("smoke", ["max_minutes=-1"])
    with pytest.raises(ValueError, match="anchor_drop"):
        make_config("smoke", ["anchor_drop=1.0"])
    for bad in ("eval_every=0", "ckpt_every=0", "log_every=0", "val_batches=0"):
        with pytest.raises(ValueError, match="must be >= 1"):
            make_config("smoke", [bad])
    for bad in ("grad_clip=0", "weight_decay=-1", "lr=0"):
        with pytest.raises(ValueError, match="grad_clip > 0"):
            make_config("smoke", [bad])


class HoldStill:
    """A policy of the protocol that counts its steps and sends a constant action."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["image"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        assert obs["image"].dtype == jnp.uint8 and obs["proprio"].shape[-1] == 37
        return jnp.broadcast_to(params["action"], (obs["image"].shape[0], 20)), carry + 1


def test_closed_loop_with_a_policy(model_and_inputs):
    params, frames, proprio, action = model_and_inputs
    norm = I.Norm(jnp.zeros(37), jnp.ones(37), jnp.zeros(20), jnp.ones(20))
    got = I.closed_loop(CFG, HoldStill(), 5, params, norm, {"action": jnp.full((20,), 0.3)}, frames[:, :2],
                        proprio[:, :2], action[:, :1], jax.random.PRNGKey(0))
    assert got["frames"].shape == (2, 5, 64, 64, 3) and got["proprio"].shape == (2, 5, 37)
    np.testing.assert_allclose(got["action"], 0.3)
    # across compiled segments: the same steps as one open-loop scan under the same actions
    h = I.SEGMENT + 2
    longer = I.closed_loop(CFG, HoldStill(), h, params, norm, {"action": jnp.full((20,), 0.3)}, frames[:, :2],
                           proprio[:, :2], action[:, :1], jax.random.PRNGKey(0))
    scan = I.open_loop(CFG, params, norm, frames[:, :2], proprio[:, :2], action[:, :1], jnp.full((2, h, 20), 0.3))
    assert longer["frames"].shape[1] == h
    for k in ("frames", "success", "features"):
        np.testing.assert_allclose(np.asarray(longer[k], np.float32), np.asarray(scan[k], np.float32), atol=1e-4)


def _synthetic_episodes(rng, n, t_max=12, f=5):
    """Episodes of two tasks whose success is an integral: the mean of feature 0 over valid steps > 0."""
    lengths = rng.integers(6, t_max + 1, n)
    x = rng.normal(size=(n, t_max, f)).astype(np.float32) + rng.normal(size=(n, 1, f)).astype(np.float32)
    mask = np.arange(t_max)[None] < lengths[:, None]
    x = np.where(mask[..., None], x, 0.0)
    label = (x[..., 0] * mask).sum(1) / lengths > 0
    return {"features": x, "mask": mask, "task": ["a" if i % 2 else "b" for i in range(n)], "label": label}


def test_episode_judge_learns_an_integral_and_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    train, val = _synthetic_episodes(rng, 256), _synthetic_episodes(rng, 128)
    judge, metrics = J.fit(train, val, ("a", "b"), steps=400, progress=False)
    p = J.judge_episodes(judge, val)
    assert M.accuracy(p, val["label"]) >= 0.85 and metrics["val_auroc"] >= 0.9
    J.save_judge(judge, metrics, tmp_path)
    back = J.load_judge(tmp_path)
    assert back.tasks == ("a", "b")
    np.testing.assert_allclose(J.judge_episodes(back, val), p, rtol=1e-5, atol=1e-6)
    assert json.loads((tmp_path / "judge.json").read_text())["metrics"]["kept_step"] >= 25
    with pytest.raises(ValueError, match="not 'c'"):
        back.probability(val["features"][:2], "c")
    with pytest.raises(ValueError, match="successes and failures"):
        J.fit({**train, "label": np.zeros(256, bool)}, None, ("a", "b"), steps=5, progress=False)
    assert J.load_judge(tmp_path / "nothing") is None


@pytest.mark.slow  # an option no preset uses (make test-slow runs it)
def test_a_judge_pooling_its_features_own_mean_reads_them_beside_the_per_step_network_and_round_trips(tmp_path):
    rng = np.random.default_rng(3)
    train, val = _synthetic_episodes(rng, 96), _synthetic_episodes(rng, 32)
    judge, metrics = J.fit(train, val, ("a", "b"), steps=40, seed=1, progress=False, raw_mean=True)
    plain, _ = J.fit(train, val, ("a", "b"), steps=40, seed=1, progress=False)
    assert judge.raw_mean and metrics["raw_mean"] and not plain.raw_mean
    f, w = train["features"].shape[-1], J.WIDTH
    # the layer after the pooling reads the F features' masked mean beside mean, max, first, last and the task
    assert judge.params["Dense_3"]["kernel"].shape[1:] == (5 * w + f, w)
    assert plain.params["Dense_3"]["kernel"].shape[1:] == (5 * w, w)
    p = J.judge_episodes(judge, val)
    assert not np.allclose(p, J.judge_episodes(plain, val), atol=1e-3)
    padded = {**val, "features": np.where(val["mask"][..., None], val["features"], 1e3).astype(np.float32)}
    np.testing.assert_allclose(J.judge_episodes(judge, padded), p, rtol=1e-5, atol=1e-6)  # masked steps unread
    J.save_judge(judge, metrics, tmp_path)
    assert json.loads((tmp_path / "judge.json").read_text())["raw_mean"] is True
    back = J.load_judge(tmp_path)
    assert back.raw_mean
    np.testing.assert_allclose(J.judge_episodes(back, val), p, rtol=1e-5, atol=1e-6)


def test_an_ensemble_judge_reads_the_mean_of_its_members_and_round_trips(tmp_path):
    rng = np.random.default_rng(1)
    train, val = _synthetic_episodes(rng, 64), _synthetic_episodes(rng, 32)
    judge, metrics = J.fit(train, val, ("a", "b"), steps=50, seed=4, progress=False, lr=1e-3, members=3)
    assert judge.members == 3 and metrics["members"] == 3 and len(metrics["kept_step"]) == 3
    alone = [J.fit(train, val, ("a", "b"), steps=50, seed=s, progress=False, lr=1e-3)[0] for s in (4, 5, 6)]
    each = [J.judge_episodes(j, val) for j in alone]
    assert not np.allclose(each[0], each[1], atol=1e-3)  # the members differ by their seeds
    np.testing.assert_allclose(J.judge_episodes(judge, val), np.mean(each, axis=0), rtol=1e-5, atol=1e-6)
    assert metrics["val_auroc"] == pytest.approx(M.auroc(np.mean(each, axis=0), val["label"]), abs=1e-6)
    (tmp_path / "three").mkdir()
    J.save_judge(judge, metrics, tmp_path / "three")
    back = J.load_judge(tmp_path / "three")
    assert back.members == 3
    np.testing.assert_allclose(J.judge_episodes(back, val), J.judge_episodes(judge, val), rtol=1e-5, atol=1e-6)
    # a judge saved as one member's parameters, without "members" (the format before ensembles), loads as one
    one = alone[0]
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "judge.msgpack").write_bytes(
        serialization.to_bytes(jax.tree_util.tree_map(lambda p: p[0], one.params)))
    meta = {"tasks": ["a", "b"], "mean": one.mean.tolist(), "std": one.std.tolist(), "width": J.WIDTH,
            "columns": one.columns.tolist(), "feature_dim": one.feature_dim, "metrics": {}}
    (tmp_path / "old" / "judge.json").write_text(json.dumps(meta))
    old = J.load_judge(tmp_path / "old")
    assert old.members == 1
    np.testing.assert_allclose(J.judge_episodes(old, val), each[0], rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="at least one member"):
        J.fit(train, val, ("a", "b"), steps=5, progress=False, members=0)


def test_a_judge_kept_at_its_last_step_is_the_judge_fit_without_validation():
    rng = np.random.default_rng(3)
    train, val = _synthetic_episodes(rng, 64), _synthetic_episodes(rng, 32)
    fit = functools.partial(J.fit, train, tasks=("a", "b"), steps=60, seed=2, progress=False, lr=1e-3, members=2)
    last, m_last = fit(val, select="last")
    unvalidated, _ = fit(None)
    best, m_best = fit(val)
    assert m_last["kept_step"] == [60, 60] and m_last["select"] == "last" and m_best["select"] == "best"
    np.testing.assert_array_equal(J.judge_episodes(last, val), J.judge_episodes(unvalidated, val))
    assert "val_auroc" in m_last  # still scored on the validation episodes, only not kept by them
    assert all(k % 25 == 0 or k == 60 for k in m_best["kept_step"])
    if m_best["kept_step"] != [60, 60]:
        assert not np.allclose(J.judge_episodes(best, val), J.judge_episodes(last, val))
    with pytest.raises(ValueError, match="best or its last"):
        fit(val, select="first")
    with pytest.raises(ValueError, match="judge_select"):
        make_config("smoke", ["judge_select=first"])


@pytest.mark.parametrize("n", [J.BATCH + 44, J.BATCH - 56])
def test_the_judges_batches_are_the_rows_its_draws_name_gathered_where_the_episodes_are(n):
    """Each step's batch is gathered on the device (more training episodes than a batch) or is every
    episode (at most a batch); either way each member is bit for bit the judge that a loop over
    host-gathered batches (the rows rng.choice names, seeded by the member) gives."""
    rng = np.random.default_rng(2)
    train, val = _synthetic_episodes(rng, n), _synthetic_episodes(rng, 16)
    judge, metrics = J.fit(train, val, ("a", "b"), steps=30, seed=3, progress=False, lr=1e-3, members=2)
    mean, std = J._standardisation(train["features"], train["mask"])

    def arrays(d):
        return ((d["features"] - mean) / std, d["mask"], np.array(["ab".index(t) for t in d["task"]], np.int32),
                d["label"].astype(np.float32))

    tr, va = arrays(train), arrays(val)
    for member, seed in enumerate((3, 4)):
        params = J.JudgeNet(2).init(jax.random.PRNGKey(seed), *tr[:3])["params"]
        state, draws = J._optimizer(1e-3).init(params), np.random.default_rng(seed)
        best, best_loss = params, np.inf
        for k in range(1, 31):
            idx = draws.choice(n, J.BATCH, replace=True) if n > J.BATCH else np.arange(n)
            params, state, _ = J._update((2, False), 1e-3, params, state, *(a[idx] for a in tr))
            if k % 25 == 0 or k == 30:
                loss = float(J._loss((2, False), params, *va))
                if loss < best_loss:
                    best, best_loss, kept = params, loss, k
        assert metrics["kept_step"][member] == kept
        for got, want in zip(jax.tree_util.tree_leaves(judge.params), jax.tree_util.tree_leaves(best), strict=True):
            np.testing.assert_array_equal(got[member], np.asarray(want))


class _Episodes:
    """A training cache's episode table alone: ids 0-5999 train, 6000-6999 validation, two tasks."""

    root = Path("data/cache")

    def __init__(self):
        self.episodes = [{"task": "ab"[i % 2], "success": i % 4 == 0, "policy": "scripted"} for i in range(7000)]

    def select(self, split):
        return list(range(6000, 7000)) if split == "val" else list(range(6000))


def test_the_judge_learns_from_every_training_episode_with_a_bounded_validation_set(tmp_path, monkeypatch):
    """judge_episodes at or above the training episodes imagines every one of them; the validation
    episodes stay at VAL_EPISODES however many the judge learns from (fit_judge's selection)."""
    imagined = []
    monkeypatch.setattr(J, "dataset_policies", lambda root: {})
    monkeypatch.setattr(J, "imagine_episodes", lambda *a: imagined.append(list(a[4])) or {"ids": a[4]})
    monkeypatch.setattr(J, "fit", lambda train, val, tasks, *a, **k: (tasks, {"n": len(train["ids"])}))
    monkeypatch.setattr(J, "save_judge", lambda *a: None)
    cfg = make_config("smoke", ["judge_episodes=8192"])
    assert J.fit_judge(cfg, None, None, _Episodes(), list(range(6000)), tmp_path, progress=False) == {
        "n": 6000, "inputs": list(cfg.judge_inputs), "labels": "simulated"}
    train, val = imagined
    assert train == list(range(6000)) and len(val) == J.VAL_EPISODES == 256
    assert set(val) <= set(range(6000, 7000)) and len(set(val)) == 256
    imagined.clear()
    J.fit_judge(make_config("smoke", ["judge_episodes=400"]), None, None, _Episodes(), list(range(6000)), tmp_path,
                progress=False)
    assert len(imagined[0]) == 400 and len(imagined[1]) == 100  # a quarter below the bound, as before


def test_a_second_judge_learns_from_the_same_imaginations_and_labels_reading_its_own_inputs(tmp_path, monkeypatch):
    imagined, fits, saved = [], [], []
    monkeypatch.setattr(J, "dataset_policies", lambda root: {})
    monkeypatch.setattr(J, "imagine_episodes", lambda *a: imagined.append(a[4]) or _readings(a[4], 0.5))
    monkeypatch.setattr(J, "fit", lambda train, val, tasks, steps, seed, progress, columns, *a:
                        fits.append((train, val, columns, steps)) or (len(fits), {"n": len(fits)}))
    monkeypatch.setattr(J, "save_judge", lambda judge, metrics, out, name: saved.append((judge, name)))
    cfg = make_config("smoke", ["judge_episodes=64", "judge2_inputs=proprio,action"])
    got = J.fit_judge(cfg, None, None, _Episodes(), list(range(6000)), tmp_path, progress=False)
    assert len(imagined) == 2  # the training and validation episodes imagined once, for both judges
    assert [f[3] for f in fits] == [cfg.judge_steps] * 2  # judge2_steps=0: the first judge's steps
    (train1, val1, cols1, _), (train2, val2, cols2, _) = fits
    assert train1 is train2 and val1 is val2
    assert cols1.tolist() == I.feature_columns(cfg.model, cfg.judge_inputs).tolist()
    assert cols2.tolist() == I.feature_columns(cfg.model, ("proprio", "action")).tolist()
    assert saved == [(1, "judge"), (2, "judge2")]
    assert got["n"] == 1 and got["judge2"] == {"n": 2, "inputs": ["proprio", "action"], "labels": "simulated"}
    assert not J.judges_fit(cfg, tmp_path)
    (tmp_path / "judge.json").write_text("{}")
    assert J.judges_fit(make_config("smoke", ["judge_episodes=64"]), tmp_path) and not J.judges_fit(cfg, tmp_path)
    with pytest.raises(ValueError, match="judge2_inputs are among"):
        make_config("smoke", ["judge2_inputs=proprio,frames"])
    # the second judge trained longer than the first, on the same imaginations
    fits.clear()
    J.fit_judge(make_config("smoke", ["judge_episodes=64", "judge2_inputs=proprio", "judge2_steps=45"]), None, None,
                _Episodes(), list(range(6000)), tmp_path, progress=False)
    assert [f[3] for f in fits] == [20, 45]
    with pytest.raises(ValueError, match="judge2_steps >= 0"):
        make_config("smoke", ["judge2_steps=-1"])
    with pytest.raises(ValueError, match="name its inputs with judge2_inputs"):
        make_config("smoke", ["judge2_steps=45"])
    # judge_episodes=0 switches every judge off (wm.train fits none), a second one its preset names included
    full = make_config("full", ["judge_episodes=0"])
    assert full.judge_inputs == ("proprio", "action") and "action" in full.judge2_inputs
    assert "scene" not in full.judge2_inputs and "latent" in full.judge2_inputs


def test_the_warm_up_fits_both_judges_on_placeholders_and_hands_back_the_first(monkeypatch):
    """warm_judge runs each judge's fit once (their programs differ in their input columns), so that
    the run's own fit loads both from the compilation cache."""
    columns = []
    monkeypatch.setattr(J, "dataset_policies", lambda root: {})
    monkeypatch.setattr(J, "warm_imagination", lambda *a: None)
    monkeypatch.setattr(J, "fit", lambda train, val, tasks, steps, seed, progress, cols, *a:
                        columns.append(cols.tolist()) or (len(columns), {}))
    cfg = make_config("smoke", ["judge_episodes=64", "judge2_inputs=proprio"])
    assert J.warm_judge(cfg, None, None, _Rollouts(), list(range(6000))) == 1
    assert columns == [I.feature_columns(cfg.model, cfg.judge_inputs).tolist(),
                       I.feature_columns(cfg.model, ("proprio",)).tolist()]


def _readings(ids, value):
    """An imagine_episodes-shaped dict whose every feature is `value`."""
    return {"features": np.full((len(ids), 3, 2), value, np.float32), "mask": np.ones((len(ids), 3), bool),
            "task": ["ab"[i % 2] for i in ids], "label": np.array([i % 4 == 0 for i in ids])}


def test_a_judge_with_observed_episodes_learns_from_both_readings_and_is_kept_on_imaginations(tmp_path, monkeypatch):
    got = {}
    monkeypatch.setattr(J, "dataset_policies", lambda root: {})
    monkeypatch.setattr(J, "imagine_episodes", lambda *a: _readings(a[4], 0.0))
    monkeypatch.setattr(J, "observe_episodes", lambda *a: _readings(a[4], 1.0))
    monkeypatch.setattr(J, "fit", lambda train, val, *a, **k: got.update(train=train, val=val) or (None, {}))
    monkeypatch.setattr(J, "save_judge", lambda *a: None)
    J.fit_judge(make_config("smoke", ["judge_episodes=8192", "judge_observed=1"]), None, None, _Episodes(),
                list(range(6000)), tmp_path, progress=False)
    train, val = got["train"], got["val"]
    assert train["features"].shape == (12000, 3, 2) and train["task"] == ["ab"[i % 2] for i in range(6000)] * 2
    assert (train["features"][:6000] == 0).all() and (train["features"][6000:] == 1).all()
    np.testing.assert_array_equal(train["label"], np.tile([i % 4 == 0 for i in range(6000)], 2))
    assert len(val["label"]) == J.VAL_EPISODES and (val["features"] == 0).all()  # kept on imaginations alone


class _Rollouts(_Episodes):
    """_Episodes of 3 steps each, every third a rollout of a learned policy."""

    def __init__(self):
        super().__init__()
        for i, ep in enumerate(self.episodes):
            ep.update(length=4, seed=i, **({"policy": "bc"} if i % 3 == 0 else {}))


def test_a_judge_of_replayed_labels_learns_what_the_imagined_actions_achieved(tmp_path, monkeypatch):
    """judge_labels=replayed: the rollouts' closed-loop imaginations (their policy in the dataset's)
    take the simulator's outcome of their imagined actions, in training and validation; the
    scripted episodes and the true readings keep their labels; judge.json says so."""
    got, replays = {}, []

    def simulate(task, actions, keys, engine):
        replays.append((task, len(actions), engine))
        return np.zeros((1, len(actions)), bool)  # what the imagined actions do: fail

    monkeypatch.setattr(J, "dataset_policies", lambda root: {"bc": object()})
    wide = I.feature_dim(make_config("smoke").model)  # the step features' width: the action columns are read
    monkeypatch.setattr(J, "imagine_episodes", lambda *a: {**_readings(a[4], 0.0),
                                                           "features": np.zeros((len(a[4]), 3, wide), np.float32)})
    monkeypatch.setattr(J, "observe_episodes", lambda *a: {**_readings(a[4], 1.0),
                                                           "features": np.ones((len(a[4]), 3, wide), np.float32)})
    monkeypatch.setattr(J, "simulate_actions", simulate)
    monkeypatch.setattr(J, "fit", lambda train, val, *a, **k: got.update(train=train, val=val) or (None, {}))
    monkeypatch.setattr(J, "save_judge", lambda judge, metrics, out, name: got.update(metrics=metrics))
    cache = _Rollouts()
    J.fit_judge(make_config("smoke", ["judge_episodes=600", "judge_observed=1", "judge_labels=replayed"]), None,
                I.Norm(np.zeros(37), np.ones(37), np.zeros(20), np.ones(20)), cache, list(range(6000)), tmp_path,
                progress=False)
    train_ids = J.spread(list(range(6000)), 600)
    closed = np.array([i % 3 == 0 for i in train_ids])
    truth = np.array([i % 4 == 0 for i in train_ids])  # the labels the imaginations came with (_readings)
    np.testing.assert_array_equal(got["train"]["label"][:600], truth & ~closed)  # the rollouts now fail
    np.testing.assert_array_equal(got["train"]["label"][600:], truth)  # the true readings keep theirs
    val_ids = J.spread(list(range(6000, 7000)), 150)
    np.testing.assert_array_equal(got["val"]["label"], np.array([i % 4 == 0 and i % 3 != 0 for i in val_ids]))
    # training's spread picks task a's episodes alone (every tenth id), validation's both tasks (150 of
    # 1000 spread evenly, every third a rollout): one replay a task and split, each in the batch of the
    # largest (one compiled rollout)
    closed_val = [i for i in val_ids if i % 3 == 0]
    assert closed.sum() == 200 and len(closed_val) == 51
    assert sorted(r[:2] for r in replays) == [("a", 200), ("a", 200), ("b", 200)]
    m = got["metrics"]
    assert m["labels"] == "replayed" and m["relabelled"]["train"]["closed_loop"] == closed.sum()
    assert m["relabelled"]["train"]["changed"] == (closed & truth).sum()
    with pytest.raises(ValueError, match="judge_labels"):
        make_config("smoke", ["judge_labels=imagined"])


def test_the_judge_warm_up_replays_what_the_fit_replays(tmp_path, monkeypatch):
    """warm_judge with judge_labels=replayed runs the simulator once per task with closed-loop rows, on
    the batch, episode length and keys of fit_judge's own replay: the fit then loads its programs."""
    calls = {"fit": [], "warm": []}
    into = calls["fit"]

    def simulate(task, actions, keys, engine):
        into.append((task, actions.shape, keys.shape, str(keys.dtype), engine))  # simulate_actions casts the actions
        return np.zeros((1, len(actions)), bool)

    wide = I.feature_dim(make_config("smoke").model)
    monkeypatch.setattr(J, "dataset_policies", lambda root: {"bc": object()})
    monkeypatch.setattr(J, "imagine_episodes", lambda *a: {**_readings(a[4], 0.0),
                                                           "features": np.zeros((len(a[4]), 3, wide), np.float32)})
    monkeypatch.setattr(J, "warm_imagination", lambda *a: None)
    monkeypatch.setattr(J, "simulate_actions", simulate)
    monkeypatch.setattr(J, "fit", lambda *a, **k: (None, {}))
    monkeypatch.setattr(J, "save_judge", lambda *a: None)
    cfg = make_config("smoke", ["judge_episodes=600", "judge_labels=replayed"])
    norm = I.Norm(np.zeros(37), np.ones(37), np.zeros(20), np.ones(20))
    J.fit_judge(cfg, None, norm, _Rollouts(), list(range(6000)), tmp_path, progress=False)
    into = calls["warm"]
    J.warm_judge(cfg, None, norm, _Rollouts(), list(range(6000)))
    assert calls["warm"] == [(t, (200, 3, 20), (200, 2), "uint32", calls["fit"][0][-1]) for t in "ab"]
    assert set(calls["fit"]) == set(calls["warm"])
    into = calls["none"] = []
    J.warm_judge(make_config("smoke", ["judge_episodes=600"]), None, norm, _Rollouts(), list(range(6000)))
    assert calls["none"] == []  # simulated labels replay nothing


@pytest.mark.slow
def test_observed_episodes_are_the_true_episodes_features_and_join_the_imagined(smoke_dataset, smoke_world_model):
    _, data, _ = smoke_dataset
    cfg, params, norm = load_trained(smoke_world_model)
    cache = TrainingCache(data)
    ids = cache.select("train")[:3]
    assert len(ids) >= 2
    seen = J.observe_episodes(cfg.model, params, norm, cache, ids, cfg.camera, progress=False)
    for row, i in enumerate(ids):
        ep = cache.episode(i, cameras=[cfg.camera])
        x = np.asarray(I.observed_features(cfg.model, params, norm, ep["frames"][cfg.camera][None], ep["proprio"][None],
                                           ep["action"][None, :-1]))[0]
        assert seen["mask"][row].sum() == len(x) and not seen["features"][row, len(x):].any()
        np.testing.assert_allclose(seen["features"][row, :len(x)], x, atol=1e-3)
        assert seen["label"][row] == bool(cache.episodes[i]["success"]) and seen["task"][row] == cache.episodes[i]["task"]
    dreamt = J.imagine_episodes(cfg.model, params, norm, cache, ids, cfg.camera, progress=False)
    both = J.join_episodes(dreamt, seen)
    assert both["features"].shape == (2 * len(ids),) + seen["features"].shape[1:]
    assert both["task"] == dreamt["task"] + seen["task"]
    np.testing.assert_array_equal(both["features"][len(ids):], seen["features"])
    np.testing.assert_array_equal(both["label"], np.concatenate([dreamt["label"], seen["label"]]))


def test_a_judge_reads_only_its_chosen_feature_columns(tmp_path):
    cfg = SMOKE_MODEL
    f = I.feature_dim(cfg)
    feature_columns = I.feature_columns
    assert feature_columns(cfg, ("success",)).tolist() == [f + I.SUCCESS_FEATURE]
    assert feature_columns(cfg, ("outcome",)).tolist() == [f + I.OUTCOME_FEATURE]
    assert feature_columns(cfg, ("progress",)).tolist() == [f + I.PROGRESS_FEATURE] == [f - 1]
    assert feature_columns(cfg, ("action",)).tolist() == list(range(cfg.proprio_dim, cfg.proprio_dim + cfg.action_dim))
    without_actions = feature_columns(cfg, ("proprio", "latent", "success", "outcome", "progress"))
    assert len(without_actions) == f - cfg.action_dim and not set(without_actions) & set(feature_columns(cfg, ("action",)))
    with pytest.raises(ValueError, match="feature groups"):
        feature_columns(cfg, ("pixels",))
    assert "scene" not in make_config("smoke").judge_inputs  # read where named: earlier runs' configs stand
    with pytest.raises(ValueError, match="only a model with model.scene"):
        make_config("smoke", ["judge_inputs=latent,scene"])
    make_config("smoke", ["model.scene=true", "judge_inputs=latent,scene"])

    rng = np.random.default_rng(0)
    train, val = _synthetic_episodes(rng, 256), _synthetic_episodes(rng, 64)
    judge, metrics = J.fit(train, val, ("a", "b"), steps=200, progress=False, columns=[0, 1])
    scrambled = {**val, "features": val["features"].copy()}
    scrambled["features"][..., 2:] = rng.normal(size=scrambled["features"][..., 2:].shape)
    np.testing.assert_array_equal(J.judge_episodes(judge, scrambled), J.judge_episodes(judge, val))
    J.save_judge(judge, metrics, tmp_path)
    back = J.load_judge(tmp_path)
    assert back.columns.tolist() == [0, 1] and back.feature_dim == 5
    np.testing.assert_allclose(J.judge_episodes(back, val), J.judge_episodes(judge, val), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="5 columns"):
        back.probability(val["features"][:2, :, :4], "a")
    meta = json.loads((tmp_path / "judge.json").read_text())
    del meta["columns"], meta["feature_dim"]  # a judge saved before input selection read every column
    (tmp_path / "judge.json").write_text(json.dumps(meta))
    assert J.load_judge(tmp_path).columns.tolist() == [0, 1]


# The tests of the trained smoke model (smoke_world_model) come after those that need none: under xdist
# the other worker trains it meanwhile.


def test_action_dependence_is_the_contrast_term_on_windows_from_the_episodes_starts(smoke_dataset, smoke_world_model):
    from wm.train import loss_fn

    _, data, _ = smoke_dataset
    cfg, params, norm = load_trained(smoke_world_model)
    cache = TrainingCache(data)
    ids = [i for i in cache.select("train") if cache.episodes[i]["length"] >= cfg.window][:2]
    assert len(ids) == 2
    got = E.action_dependence(cfg, params, norm, cache, ids)
    eps = [cache.episode(i, cameras=[cfg.camera]) for i in ids]
    w = cfg.window
    batch = {"frames": np.stack([e["frames"][cfg.camera][:w] for e in eps]),
             "proprio": np.stack([e["proprio"][:w] for e in eps]),
             "action": np.stack([e["action"][:w] for e in eps]),
             "success": np.zeros((2, w), bool), "progress": np.zeros((2, w), np.float32), "outcome": np.zeros((2,), bool)}
    _, parts = jax.jit(loss_fn, static_argnums=3)(params, batch, norm, dataclasses.replace(cfg, w_contrast=0.5))
    np.testing.assert_allclose(got["action_contrast"], parts["contrast"], rtol=1e-4)
    assert got["windows"] == 2 and got["own_actions_better"] in (0.0, 0.5, 1.0)
    assert "note" in E.action_dependence(cfg, params, norm, cache, ids[:1])
    report = json.loads((smoke_world_model / "eval.json").read_text())  # every model's eval.json carries it
    dep = report["action_dependence"]
    assert report["summary"]["action_contrast"] == dep.get("action_contrast") and ("note" in dep or dep["windows"] >= 2)


def test_loss_falls_on_a_tiny_dataset(smoke_world_model):
    # the log of `make train CONFIG=smoke` on the smoke dataset (Run.train's), shared with the other tests
    losses = [json.loads(line)["loss"] for line in (smoke_world_model / "metrics.jsonl").read_text().splitlines()]
    assert len(losses) == 6 and losses[-1] < 0.6 * losses[0], losses


class Killed(Exception):
    pass


class DyingLoader:
    """The run's loader, killed when the run asks for batch number `dies_at`."""

    def __init__(self, loader, dies_at):
        self.loader, self.dies_at, self.taken = loader, dies_at, 0

    def __next__(self):
        self.taken += 1
        if self.taken == self.dies_at:
            raise Killed
        return next(self.loader)

    def __getattr__(self, name):
        return getattr(self.loader, name)


@pytest.mark.slow
def test_resume_after_a_kill_matches_an_uninterrupted_run(smoke_dataset, smoke_world_model, tmp_path):
    _, data, _ = smoke_dataset
    cfg = make_config("smoke")
    # the uninterrupted run: the last checkpoint of `make train CONFIG=smoke` on the same data (a copy)
    shutil.copytree(smoke_world_model, tmp_path / "whole")
    whole = Run(cfg, data, tmp_path / "whole")
    assert whole.restore() == cfg.steps
    killed = Run(cfg, data, tmp_path / "killed")
    killed.loader = DyingLoader(killed.loader, dies_at=14)  # after the checkpoint of step 10
    with pytest.raises(Killed):
        killed.train(progress=False)
    again = Run(cfg, data, tmp_path / "killed")
    assert again.restore() == 10
    again.train(progress=False)
    for a, b in zip(jax.tree_util.tree_leaves(whole.state["params"]), jax.tree_util.tree_leaves(again.state["params"]),
                    strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)


@pytest.mark.slow  # an edge of the kill-and-resume path; make test keeps a cut-short run's resume
def test_a_run_killed_between_its_best_and_latest_checkpoints_resumes(smoke_dataset, smoke_world_model, tmp_path):
    _, data, _ = smoke_dataset
    cfg = make_config("smoke")
    shutil.copytree(smoke_world_model, tmp_path / "whole")
    whole = Run(cfg, data, tmp_path / "whole")
    whole.restore()
    first = Run(cfg, data, tmp_path / "run")
    first.loader = DyingLoader(first.loader, dies_at=14)  # after the checkpoints of step 10
    with pytest.raises(Killed):
        first.train(progress=False)

    def resumed(dies_at_latest_save=None):
        run = Run(cfg, data, tmp_path / "run")
        assert run.restore() == 10
        run.restore = lambda: 10  # already restored; best_val forgotten, so step 20 is a best
        run.best_val = math.inf
        if dies_at_latest_save is not None:
            save = run.latest.save

            def dying_save(step, *args, **kwargs):
                if step == dies_at_latest_save:
                    raise Killed
                return save(step, *args, **kwargs)

            run.latest.save = dying_save
        return run

    second = resumed(dies_at_latest_save=20)
    with pytest.raises(Killed):
        second.train(progress=False)
    assert second.best.all_steps() == [20] and second.latest.all_steps() == [10]
    third = resumed()
    third.train(progress=False)  # saves step 20's best again: kept, not refused
    assert third.latest.latest_step() == cfg.steps
    for a, b in zip(jax.tree_util.tree_leaves(whole.state["params"]), jax.tree_util.tree_leaves(third.state["params"]),
                    strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)


def test_a_run_cut_short_is_left_unevaluated_and_the_rerun_finishes_it(smoke_dataset, tmp_path):
    _, data, _ = smoke_dataset
    out = tmp_path / "run"
    args = ["--config", "smoke", "--data", str(data), "--out", str(out)]
    assert train_main([*args, "max_minutes=1e-6"]) == 0  # stops at its first logged step
    assert json.loads((out / "train_status.json").read_text()) == {"step": 5, "steps": 30, "cut_short": True}
    assert not (out / "eval.json").exists()
    # validated on the eval_every grid alone, as an uninterrupted run: the stop at step 5 chose nothing, so
    # the rerun keeps the step an uninterrupted run keeps
    assert json.loads((out / "checkpoints" / "5" / "loader" / "metadata").read_text())["best_val"] == math.inf
    assert train_main(args) == 0
    assert json.loads((out / "train_status.json").read_text())["cut_short"] is False
    assert (out / "eval.json").exists()
    steps = [json.loads(line)["step"] for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert steps == [5, 10, 15, 20, 25, 30]


def test_the_loader_batch_carries_the_first_frames_only_to_an_anchored_model():
    frames = np.arange(2 * 3 * 4 * 4 * 3, dtype=np.uint8).reshape(2, 3, 4, 4, 3)
    batch = {"frames": {"head_cam": frames}, "first_frames": {"head_cam": frames[:, 0] + 1}, "start": np.array([0, 7]),
             **{k: np.zeros((2, 3)) for k in ("proprio", "action", "success", "progress", "scene")}, "outcome": np.zeros(2)}
    assert "anchor" not in model_batch(batch, "head_cam")
    anchored = model_batch(batch, "head_cam", anchor=True)
    np.testing.assert_array_equal(anchored["anchor"], frames[:, 0] + 1)
    np.testing.assert_array_equal(anchored["start"], [0, 7])


@pytest.mark.slow
def test_an_anchored_model_trains_fits_its_judge_and_writes_eval_json(smoke_dataset, tmp_path):
    """The whole run of a model with an anchor frame: its windows' first frames from the loader, the
    anchor through every training pass, and eval.json's open- and closed-loop imaginations."""
    cfg, params, _ = _whole_smoke_run(smoke_dataset, tmp_path / "anchored", "model.anchor=true")
    assert cfg.model.anchor and "anchor_kv" in params["dynamics"]["Block_0"]


def test_non_finite_loss_stops_without_a_checkpoint(smoke_dataset, tmp_path):
    _, data, _ = smoke_dataset
    run = Run(make_config("smoke"), data, tmp_path / "nan")
    # NaN inputs, of the norm's own float32 type (a weakly typed array would compile the step again)
    run.norm = dataclasses.replace(run.norm, proprio_mean=jnp.full(37, jnp.nan, jnp.float32))
    with pytest.raises(TrainingDiverged, match="non-finite"):
        run.train(progress=False)
    assert run.latest.latest_step() is None


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="unknown setting"):
        make_config("smoke", ["model.width=3"])
    with pytest.raises(ValueError, match="multiples"):
        make_config("smoke", ["eval_every=3"])
    assert override(make_config("smoke"), ["model.dim=48"]).model.dim == 48


def test_program_match_against_hand_computed_psnr():
    """Three programs' truths of constant frames 0, 10 and 40; imagined as the truths, but program 0 off
    by 2 everywhere, and program 1 drawn at 30 in group 0 (nearer program 2's truth than its own)."""
    truth = np.zeros((2, 3, 2, 2, 2, 3))
    truth[:, 1], truth[:, 2] = 10.0, 40.0
    pred = truth.copy()
    pred[:, 0] += 2.0
    pred[0, 1] = 30.0
    got = E.program_match(pred, truth)
    db = lambda mse: 10 * math.log10(255.0**2 / mse)
    assert got["match"].tolist() == [1.0, 0.5, 1.0]
    np.testing.assert_allclose(got["own_psnr_db"], [db(4), (db(400) + 100.0) / 2, 100.0])  # exact at 100 dB
    # program 0 off by 2: nearest other truth 10 (MSE 64 and 64); program 1: 40 at 10 away, then 0 at 10 away
    np.testing.assert_allclose(got["nearest_other_psnr_db"], [db(64), db(100), db(900)])
    np.testing.assert_allclose(got["truth_separation_psnr_db"], [db(100), db(100), db(900)])
    with pytest.raises(ValueError, match=">= 2 programs"):
        E.program_match(pred[:, :1], truth[:, :1])


def test_make_train_smoke_writes_eval_json(smoke_world_model):
    out = smoke_world_model
    report = json.loads((out / "eval.json").read_text())
    fq = report["frame_quality"]
    assert fq["horizons"] == [1, 4] and len(fq["psnr"]) == 2 and len(fq["copy_last_psnr"]) == 2
    assert len(fq["view_shift_px"]) == 2 and all(0.0 <= x <= 1.0 for x in fq["still_share"])
    assert len(fq["view_shift_unregistered"]) == 2
    # LPIPS beside PSNR, the imagined frames' and copy-last's (whose first horizon copies a frame 1 step old)
    assert len(fq["lpips"]) == 2 and all(x > 0 for x in fq["lpips"]) and all(x >= 0 for x in fq["copy_last_lpips"])
    assert report["summary"]["lpips_h8"] is None  # the smoke preset's horizons stop at 4
    ctrl = report["controllability"]
    assert ctrl["groups"] == 1 and 0.0 <= ctrl["match_accuracy"] <= 1.0
    for key in ("own_psnr_db", "nearest_other_psnr_db", "truth_separation_psnr_db"):
        assert sorted(ctrl[key]) == sorted(ctrl["programs"]) and all(math.isfinite(v) for v in ctrl[key].values())
    assert report["success_prediction"]["episodes"] >= 1 and (out / "eval_frames.png").stat().st_size > 0
    sens = report["action_sensitivity"]  # the smoke data's task episodes: swaps where both outcomes occur
    assert sens["swaps"] == 0 and "note" in sens or 0.0 <= sens["follows_actions"] <= 1.0
    assert "success_follows_actions" in report["summary"]
    # the smoke data holds no episode of a learned policy: the policy-in-the-loop figure says so
    assert report["policy_in_the_loop"]["episodes"] == 0 and report["policy_in_the_loop"]["split"] is None
    assert report["summary"]["action_divergence_h8"] is None
    assert (out / "best").is_dir() and (out / "metrics.jsonl").exists()


def test_a_run_keeps_its_best_validated_or_its_last_parameters_as_its_preset_says(smoke_world_model):
    log = [json.loads(line) for line in (smoke_world_model / "metrics.jsonl").read_text().splitlines()]
    cfg = make_config("smoke")  # its data has no validation split: the training loss stands in for it
    validated = [(r.get("val_loss", r["loss"]), r["step"]) for r in log if r["step"] % cfg.eval_every == 0]
    assert len(validated) == 3  # the smoke run (select "best") kept the step of its lowest validation loss
    assert [int(d.name) for d in (smoke_world_model / "best").iterdir() if d.name.isdigit()] == [min(validated)[1]]
    assert kept_at("best", False, 0.5, math.inf) and not kept_at("best", True, 0.6, 0.5)
    assert not kept_at("last", False, 0.1, math.inf) and kept_at("last", True, 0.9, 0.1)
    assert make_config("demo").select == "last" and make_config("full").select == "best"
    with pytest.raises(ValueError, match="select is best or last"):
        make_config("smoke", ["select=first"])


def test_a_bundle_carries_the_model_in_bfloat16_and_refuses_a_damaged_copy(smoke_world_model, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(smoke_world_model, run)
    episodes = _synthetic_episodes(np.random.default_rng(0), 32)
    judge, metrics = J.fit(episodes, None, ("a", "b"), steps=5, progress=False)
    J.save_judge(judge, metrics, run)
    bundle = tmp_path / "bundle"
    assert not bundle_holds(run, bundle)
    assert checkpoint_main([str(run), str(bundle)]) == 0
    assert bundle_holds(run, bundle)
    refit = tmp_path / "refit"  # the same run with its judge fit again from another seed
    shutil.copytree(run, refit)
    J.save_judge(J.fit(episodes, None, ("a", "b"), steps=5, seed=1, progress=False)[0], metrics, refit)
    assert not bundle_holds(refit, bundle)
    (refit / "judge.msgpack").write_bytes((run / "judge.msgpack").read_bytes())
    assert bundle_holds(refit, bundle)
    status = json.loads((refit / "train_status.json").read_text())
    (refit / "train_status.json").write_text(json.dumps({**status, "step": status["step"] + 1}))
    assert not bundle_holds(refit, bundle)  # trained on: a new bundle
    cfg, params, norm = load_trained(run)
    b_cfg, b_params, b_norm = load_trained(bundle)
    assert b_cfg == cfg and b_norm.to_dict() == norm.to_dict()
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(b_params), strict=True):
        np.testing.assert_array_equal(np.asarray(b), np.asarray(jnp.asarray(a, jnp.bfloat16), np.float32))
    assert training_status(bundle) == training_status(run) and training_seeds(bundle) == training_seeds(run)
    assert training_policies(bundle) == training_policies(run)
    assert training_fingerprints(bundle) == training_fingerprints(run)
    assert load_run_config(bundle) == load_run_config(run) and len(training_seeds(run)) > 0
    np.testing.assert_array_equal(J.judge_episodes(load_judge(bundle), episodes), J.judge_episodes(judge, episodes))
    assert all(f.stat().st_size <= 15 * 2**20 for f in bundle.iterdir())
    shard = bundle / "params-0.msgpack"
    data = bytearray(shard.read_bytes())
    data[-1] ^= 1
    shard.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="params-0.msgpack does not match its SHA-256"):
        load_trained(bundle)
    with pytest.raises(ValueError, match="not a bundle"):
        write_bundle(run, run / "..")
    other = tmp_path / "other"  # a bundle whose configuration names another model than its parameters
    write_bundle(run, other)
    meta = json.loads((other / "bundle.json").read_text())
    meta["files"]["config.json"]["train"]["model"]["dim"] *= 2
    (other / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="bundle.json does not match its own SHA-256"):  # edited by hand
        load_trained(other)
    meta["meta_sha256"] = CK._meta_digest(meta)  # as written so by other code
    (other / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="do not fit its configuration's model .* another version of wm.model"):
        load_trained(other)
    meta["files"]["config.json"]["train"]["model"]["new_setting"] = 1
    meta["meta_sha256"] = CK._meta_digest(meta)
    (other / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"settings this code does not know \(new_setting\)"):
        load_trained(other)


def test_a_run_directory_refuses_another_configuration_naming_what_differs(tmp_path):
    cfg = make_config("demo")
    check_run_config(cfg, tmp_path / "data", tmp_path)
    check_run_config(cfg, tmp_path / "data", tmp_path)  # the same run resumes
    with pytest.raises(ValueError, match=r"differs: data\)"):
        check_run_config(cfg, tmp_path / "other", tmp_path)
    with pytest.raises(ValueError, match=r"differs: train.lr\)"):
        check_run_config(dataclasses.replace(cfg, lr=cfg.lr * 2), tmp_path / "data", tmp_path)
    # a run written before a model setting existed resumes with that setting's default, and only with it
    saved = json.loads((tmp_path / "config.json").read_text())
    del saved["train"]["model"]["anchor"]
    (tmp_path / "config.json").write_text(json.dumps(saved))
    check_run_config(cfg, tmp_path / "data", tmp_path)
    with pytest.raises(ValueError, match=r"differs: train.model.anchor\)"):
        check_run_config(dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, anchor=True)), tmp_path / "data",
                      tmp_path)


def test_success_only_writes_each_held_out_episodes_read_outs_beside_their_summary(smoke_dataset, smoke_world_model,
                                                                                   tmp_path):
    _, data, _ = smoke_dataset
    assert E.main(["--wm", str(smoke_world_model), "--data", str(data), "--out", str(tmp_path), "--success-only",
                   "eval_episodes=50"]) == 0
    rep = json.loads((tmp_path / "success_episodes.json").read_text())
    cache = TrainingCache(data)
    ids = [i for i in cache.select(rep["split"]) if cache.episodes[i]["policy_kind"] != "play"]
    rows = rep["episodes"]
    assert ids and [r["episode_id"] for r in rows] == [cache.episodes[i]["episode_id"] for i in ids]
    assert [r["success"] for r in rows] == [bool(cache.episodes[i]["success"]) for i in ids]
    assert rep["summary"]["episodes"] == len(rows) and not (tmp_path / "eval.json").exists()
    assert all(0.0 <= r["imagined"] <= 1.0 and 0.0 <= r["on_truth"] <= 1.0 for r in rows)
    # the summary's headline accuracy is that of the rows' imagined read-out at 0.5
    hits = np.mean([(r["imagined"] >= 0.5) == r["success"] for r in rows])
    assert rep["summary"]["accuracy"] == pytest.approx(hits)
    # on_truth: the same read-out of the true episode's observed features, recomputed here
    cfg, params, norm = load_trained(smoke_world_model)
    ep = cache.episode(ids[0], cameras=[cfg.camera])
    x = np.asarray(I.observed_features(cfg.model, params, norm, ep["frames"][cfg.camera][None], ep["proprio"][None],
                                       ep["action"][None, :-1]))
    judge = load_judge(smoke_world_model)
    want = judge.probability(x, rows[0]["task"])[0] if judge is not None and judge.knows(rows[0]["task"]) \
        else np.asarray(I.episode_success(x[..., I.SUCCESS_FEATURE], rows[0]["task"]))[0]
    assert rows[0]["on_truth"] == pytest.approx(float(want), abs=1e-6)


def test_an_episodes_success_read_is_its_highest_step_for_a_latched_task_else_its_last():
    """The simulator keeps the mug's and wipe's success once met and judges the others on the last step:
    a base that drives through step_back's band and on past it fails, though it was inside on the way."""
    steps = np.array([[0.1, 0.9, 0.8, 0.2], [0.1, 0.2, 0.3, 0.7]])
    np.testing.assert_allclose(I.episode_success(steps, "mug"), [0.9, 0.7])
    np.testing.assert_allclose(I.episode_success(steps, "wipe"), [0.9, 0.7])
    for task in ("step_back", "airfryer", "shelf", "arcade"):
        np.testing.assert_allclose(I.episode_success(steps, task), [0.2, 0.7])


def _without_generator(params) -> dict:
    """A refining model's parameters less the frame generator's: those of the same model without it."""
    return {k: v for k, v in params.items() if k != "refiner"}


@pytest.fixture(scope="module")
def refining_model(model_and_inputs):
    """A model with a two-step frame generator: its untrained parameters and ones perturbed so that
    the generator's output convolution is no longer zero."""
    cfg = dataclasses.replace(CFG, refine=2, refine_channels=(8, 16))
    params = init_params(cfg, jax.random.PRNGKey(0), window=6)
    noise = np.random.default_rng(4)
    moved = jax.tree_util.tree_map(lambda x: x + 0.05 * noise.standard_normal(x.shape).astype(np.float32), params)
    return cfg, params, moved


def test_an_untrained_frame_generator_returns_the_decoded_frame_and_imagination_is_unchanged(
        model_and_inputs, refining_model):
    _, frames, proprio, action = model_and_inputs
    cfg, params, _ = refining_model
    assert "refiner" in params and "refiner" not in init_params(CFG, jax.random.PRNGKey(0), window=6)
    base = jnp.asarray(np.random.default_rng(0).random((2, 64, 64, 3)), jnp.float32)
    z = jnp.zeros((2, 8, 8, cfg.latent))
    noise = jnp.asarray(np.random.default_rng(1).standard_normal(base.shape), jnp.float32)
    np.testing.assert_array_equal(compiled(WorldModel(cfg), WorldModel.sample_frame)({"params": params}, base, z, noise),
                                  base)
    # the whole imagined step: the same frame and latents as the model without the generator
    plain = _without_generator(params)
    norm = I.Norm(jnp.zeros(37), jnp.ones(37), jnp.zeros(20), jnp.ones(20))
    got = [imagine_step(c, p, norm, init_state(c, p, norm, frames[:, :3], proprio[:, :3], action[:, :2]), action[:, 2])
           for c, p in ((cfg, params), (CFG, plain))]
    np.testing.assert_array_equal(got[0].frame, got[1].frame)
    np.testing.assert_array_equal(got[0].z, got[1].z)


def test_the_frame_generator_steps_along_the_straight_path_to_its_estimate(refining_model):
    cfg, _, params = refining_model
    m = WorldModel(cfg)
    rng = np.random.default_rng(2)
    base = jnp.asarray(rng.random((2, 64, 64, 3)) * 0.8 + 0.1, jnp.float32)
    z = jnp.asarray(rng.uniform(-1, 1, (2, 8, 8, cfg.latent)), jnp.float32)
    noise = jnp.asarray(rng.standard_normal(base.shape), jnp.float32)
    denoise = compiled(m, WorldModel.denoise)
    # two Euler steps by hand: from 0.2 noise at t=0 half way to the estimate, then onto the estimate at t=1/2
    x = 0.2 * noise
    x = x + (denoise({"params": params}, x, jnp.zeros(2), base, z) - x) / 2
    x = denoise({"params": params}, x, jnp.full(2, 0.5), base, z)
    got = compiled(m, WorldModel.sample_frame)({"params": params}, base, z, noise)
    np.testing.assert_allclose(got, np.clip(base + x, 0, 1), atol=1e-5)
    assert float(jnp.abs(got - base).max()) > 1e-3  # trained, it moves the frame
    # another draw of noise gives another frame
    other = compiled(m, WorldModel.sample_frame)({"params": params}, base, z, -noise)
    assert float(jnp.abs(other - got).max()) > 1e-4


@pytest.mark.slow  # the frame generator: only the GPU presets train it
def test_the_frame_generator_noise_follows_the_episode_and_its_step_not_the_batch():
    a = I.refine_noise(jnp.array([11, 11], jnp.uint32), jnp.array([3, 5]), (4, 4, 3))
    b = I.refine_noise(jnp.array([12, 11, 11], jnp.uint32), jnp.array([7, 3, 5]), (4, 4, 3))
    np.testing.assert_array_equal(a, b[1:])
    assert float(jnp.abs(a[0] - a[1]).max()) > 0.1  # another step, another draw
    other = I.refine_noise(jnp.array([12], jnp.uint32), jnp.array([3]), (4, 4, 3))
    assert float(jnp.abs(other[0] - a[0]).max()) > 0.1  # another episode, another draw
    many = I.refine_noise(jnp.arange(64, dtype=jnp.uint32), jnp.zeros(64, jnp.int32), (8, 8, 3))
    np.testing.assert_allclose(float(jnp.std(many)), 1.0, atol=0.05)
    # an episode's draw is its context's first frame's hash: equal frames, equal draws
    frames = np.random.default_rng(0).integers(0, 256, (3, 8, 8, 3)).astype(np.uint8)
    frames[2] = frames[0]
    h = np.asarray(I.frame_hash(frames))
    assert h[0] == h[2] != h[1]
    frames[2, 4, 4, 1] ^= 1  # one level of one pixel
    assert np.asarray(I.frame_hash(frames))[2] != h[0]


def test_the_frame_generator_steps_towards_a_known_posterior_in_time_order(refining_model):
    """A denoiser that knows the residual is +a or -a (equally likely) everywhere returns its exact
    posterior mean a tanh(x t a / ((1 - t) sigma)^2); sampling from it, each pixel ends near +a or -a,
    which it only does if the sampler walks the path from noise (t = 0) to the residual (t = 1) as the
    loss trains it."""
    from wm.model import REFINE_SIGMA

    a = 0.1

    class Oracle(WorldModel):
        def denoise(self, noisy, t, base, z):
            t = jnp.broadcast_to(t, base.shape[:-3])[..., None, None, None]
            return a * jnp.tanh(noisy * t * a / ((1 - t) * REFINE_SIGMA) ** 2)

    cfg, params, _ = refining_model
    cfg = dataclasses.replace(cfg, refine=16)
    base = jnp.full((2, 64, 64, 3), 0.5)
    noise = jnp.asarray(np.random.default_rng(5).standard_normal(base.shape), jnp.float32)
    got = np.asarray(jax.jit(functools.partial(Oracle(cfg).apply, method=Oracle.sample_frame))(
        {"params": params}, base, jnp.zeros((2, 8, 8, cfg.latent)), noise)) - 0.5
    assert np.mean(np.abs(np.abs(got) - a)) < 0.1 * a  # each pixel at +a or -a
    assert 0.4 < np.mean(got > 0) < 0.6


@pytest.mark.slow  # the frame generator: only the GPU presets train it
def test_the_frame_generator_leaves_what_the_keep_gate_keeps(model_and_inputs):
    _, frames, proprio, action = model_and_inputs
    cfg = dataclasses.replace(CFG, refine=2, refine_channels=(8, 16), keep=True)
    rng = np.random.default_rng(6)
    params = jax.tree_util.tree_map(lambda x: x + 0.05 * rng.standard_normal(x.shape).astype(np.float32),
                                    init_params(cfg, jax.random.PRNGKey(0), window=6))
    norm = I.Norm(jnp.zeros(37), jnp.ones(37), jnp.zeros(20), jnp.ones(20))
    st = init_state(cfg, params, norm, frames[:, :3], proprio[:, :3], action[:, :2])
    stepped = imagine_step(cfg, params, norm, st, action[:, 2])
    # the gate's decision, from the same prediction as the step's
    plain = _without_generator(params)
    no_gen = dataclasses.replace(cfg, refine=0)
    unrefined = imagine_step(no_gen, plain, norm, init_state(no_gen, plain, norm, frames[:, :3], proprio[:, :3],
                                                            action[:, :2]), action[:, 2])
    m = WorldModel(cfg)
    out = compiled(m, WorldModel.predict)({"params": params}, st.z, st.proprio,
                                          st.action.at[:, -1].set(action[:, 2]), st.valid)
    _, keep = compiled(m, WorldModel.decode, with_keep=True)({"params": params}, out["z"][:, -1], st.frame,
                                                              out["flow"][:, -1])
    kept = np.asarray(keep) > cfg.keep_threshold
    assert 0 < kept.mean() < 1
    np.testing.assert_array_equal(np.asarray(stepped.frame)[kept], np.asarray(st.frame)[kept])
    assert float(jnp.abs(stepped.frame - unrefined.frame).max()) > 1e-3  # the generator moves the rest


@pytest.mark.slow  # the frame generator: only the GPU presets train it
def test_the_frame_generator_learns_apart_from_the_rest_of_the_model(model_and_inputs, refining_model):
    from wm.train import _refine_loss, loss_fn

    _, frames, proprio, action = model_and_inputs
    cfg_model, params, moved = refining_model
    model = WorldModel(cfg_model)
    rng = np.random.default_rng(3)
    decoded = jnp.asarray(rng.random((2, 5, 64, 64, 3)), jnp.float32)
    target = jnp.asarray(rng.random((2, 5, 64, 64, 3)), jnp.float32)
    z = jnp.asarray(rng.uniform(-1, 1, (2, 5, 8, 8, cfg_model.latent)), jnp.float32)
    # untrained (an estimate of no residual), the loss is the decoded frames' squared error on the picked
    # frames: with 2 passes, pass 1 takes frames 1 (and 7, 13, ... beyond these 5)
    loss = jax.jit(_refine_loss, static_argnums=(0, 5, 6))
    got = loss(model, params, decoded, z, target, 1, 2, jax.random.PRNGKey(0))
    np.testing.assert_allclose(got, np.mean((np.asarray(decoded)[:, 1:2] - np.asarray(target)[:, 1:2]) ** 2), rtol=1e-5)
    # its gradient reaches the generator's parameters only, never the frames or latents it reads
    grads = jax.grad(lambda p, d: loss(model, p, d, z, target, 0, 2, jax.random.PRNGKey(0)), argnums=(0, 1))(
        moved, decoded)
    norms = {k: float(optax.tree.norm(v)) for k, v in grads[0].items()}
    assert norms["refiner"] > 0 and all(v == 0 for k, v in norms.items() if k != "refiner")
    assert float(jnp.abs(grads[1]).max()) == 0
    # in the whole loss: one part per pass, and the parts of the rest as without the generator
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    cfg = dataclasses.replace(make_config("smoke"), model=cfg_model, rollout_passes=1)
    _, parts = jax.jit(loss_fn, static_argnums=3)(moved, batch, norm, cfg)
    plain = _without_generator(moved)
    _, base_parts = jax.jit(loss_fn, static_argnums=3)(plain, batch, norm, dataclasses.replace(cfg, model=CFG))
    assert {"refine", "refine_pass1"} <= set(parts) and float(parts["refine"]) > 0
    for k in ("pixel", "pixel_pass1", "latent_pass1", "recon"):
        np.testing.assert_allclose(parts[k], base_parts[k], rtol=1e-6)
    np.testing.assert_allclose(parts["loss"] - base_parts["loss"], parts["refine"] + parts["refine_pass1"], rtol=1e-5)
    with pytest.raises(ValueError, match="w_refine"):
        make_config("smoke", ["model.refine=2", "w_refine=0"])
    with pytest.raises(ValueError, match="rollout_passes"):
        make_config("smoke", ["model.refine=2", "window=2", "rollout_passes=1"])


@pytest.mark.slow  # the frame generator: only the GPU presets train it
def test_an_optimiser_step_moves_the_rest_of_the_model_as_without_the_generator(model_and_inputs, refining_model):
    from wm.train import jitted_train_step, make_optimizer

    _, frames, proprio, action = model_and_inputs
    cfg_model, _, moved = refining_model
    norm, batch = _identity_norm_and_batch(frames, proprio, action)
    # a clip low enough to act on every step: the generator's gradient must not shrink the others'
    cfg = dataclasses.replace(make_config("smoke"), model=cfg_model, rollout_passes=1, grad_clip=0.05)
    plain_cfg = dataclasses.replace(cfg, model=CFG)
    plain = _without_generator(moved)
    fresh = functools.partial(jax.tree_util.tree_map, jnp.copy)  # the step donates its state's buffers
    # past the warmup, whose first step has a learning rate of 0 (the optimiser counts its own steps)
    def past_warmup(c, p):
        opt = make_optimizer(c)
        state = opt.init(fresh(p))
        return jax.tree_util.tree_map(lambda x: jnp.full_like(x, 10) if x.dtype == jnp.int32 and x.ndim == 0 else x,
                                      state)

    states = [{"params": fresh(p), "opt": past_warmup(c, p), "step": jnp.full((), 10, jnp.int32)}
              for c, p in ((cfg, moved), (plain_cfg, plain))]
    (with_gen, parts), (without, base_parts) = (jitted_train_step(c, st, batch, norm)
                                                for c, st in zip((cfg, plain_cfg), states))
    for got, ref in zip(jax.tree_util.tree_leaves(_without_generator(with_gen["params"])),
                        jax.tree_util.tree_leaves(without["params"])):
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(parts["grad_norm"], base_parts["grad_norm"], rtol=1e-5)
    assert float(parts["grad_norm"]) > cfg.grad_clip  # the clip acted
    step_size = optax.tree.norm(jax.tree_util.tree_map(lambda a, b: a - b, without["params"], plain))
    assert float(step_size) > 0
    assert float(parts["grad_norm_refiner"]) > 0
    moved_by = optax.tree.norm(jax.tree_util.tree_map(lambda a, b: a - b, with_gen["params"]["refiner"],
                                                      moved["refiner"]))
    assert float(moved_by) > 0
    with pytest.raises(ValueError, match="refine_channels"):
        dataclasses.replace(CFG, refine=2, refine_channels=(12, 16)).validate()


def _train_in_process(data: Path, cache: Path, *args: str) -> None:
    """`wm.train --config smoke` (steps=2, no judge or eval.json) in a fresh process whose persistent
    compilation cache, in `cache`, keeps every program it compiles."""
    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
           "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0"}
    subprocess.run([sys.executable, "-m", "wm.train", "--config", "smoke", "--data", str(data), "steps=2",
                    "judge_episodes=0", "--no-eval", *args], check=True, env=env, capture_output=True)


def _cached(cache: Path, program: str) -> set:
    return {p.name for p in cache.glob(f"jit_{program}-*")}


@pytest.mark.slow
def test_a_warmed_cache_serves_the_training_programs_to_the_run_that_trains(smoke_dataset, tmp_path):
    _, data, _ = smoke_dataset
    cache = tmp_path / "cache"
    _train_in_process(data, cache, "--warm")
    warmed = _cached(cache, "train_step")
    assert len(warmed) == 1 and _cached(cache, "_init_params")
    _train_in_process(data, cache, "--out", str(tmp_path / "run"))
    # a step of another program (another configuration, shape or placement) would add its own entry
    assert _cached(cache, "train_step") == warmed
    assert json.loads((tmp_path / "run" / "train_status.json").read_text())["step"] == 2


def test_the_moving_average_follows_the_hand_computed_warmed_decay():
    from wm.train import ema_update, initial_state, kept_params

    params = {"w": jnp.array([1.0, -2.0]), "b": jnp.array(0.5)}
    cfg = make_config("smoke", ["ema=0.5"])
    state = initial_state(cfg, params)
    np.testing.assert_array_equal(state["ema"]["w"], params["w"])
    assert kept_params(state) is state["ema"]
    assert "ema" not in initial_state(make_config("smoke"), params)
    # step 0: decay min(0.5, 1/10) = 0.1; step 5: min(0.5, 6/15) = 0.4; step 100: 0.5
    new = {"w": jnp.array([3.0, 2.0]), "b": jnp.array(1.5)}
    for step, decay in ((0, 0.1), (5, 0.4), (100, 0.5)):
        got = ema_update(params, new, 0.5, jnp.int32(step))
        np.testing.assert_allclose(got["w"], decay * np.array([1.0, -2.0]) + (1 - decay) * np.array([3.0, 2.0]),
                                   rtol=1e-6)
        np.testing.assert_allclose(got["b"], decay * 0.5 + (1 - decay) * 1.5, rtol=1e-6)
    with pytest.raises(ValueError, match="ema is a decay"):
        make_config("smoke", ["ema=1.0"])


@pytest.mark.slow
def test_a_run_with_a_moving_average_validates_and_keeps_the_average(smoke_dataset, tmp_path):
    _, data, _ = smoke_dataset
    run = Run(make_config("smoke", ["steps=10", "log_every=5", "eval_every=5", "judge_episodes=0", "select=last",
                                    "ema=0.9"]), data, tmp_path / "run")
    run.val = run.val or run.loader  # the smoke data has no validation split: the training windows stand in
    run.train(progress=False)
    kept = run.best_params()
    batch = run._val_batches[0]
    on = {name: float(jax.device_get(run._loss(p, batch, run.norm))["loss"])
          for name, p in (("ema", run.state["ema"]), ("params", run.state["params"]))}
    assert run.validate()["val_loss"] == pytest.approx(on["ema"]) and on["ema"] != on["params"]
    moved = 0.0
    for k, e, p in zip(jax.tree_util.tree_leaves(kept), jax.tree_util.tree_leaves(run.state["ema"]),
                       jax.tree_util.tree_leaves(run.state["params"]), strict=True):
        np.testing.assert_array_equal(np.asarray(k), np.asarray(e))
        moved = max(moved, float(np.max(np.abs(np.asarray(e) - np.asarray(p)))))
    assert moved > 0  # the average lags the parameters


@pytest.mark.slow
def test_the_warm_up_validates_with_the_state_its_step_returned(smoke_dataset, tmp_path):
    """On a GPU the train step donates the state it is given (its buffers are deleted): the warm-up's
    validation loss must use the step's new state. The CPU keeps donated buffers, so the step here
    deletes them as a GPU would; the smoke data has no validation split, so the training windows stand
    in for it."""
    _, data, _ = smoke_dataset
    run = Run(make_config("smoke", ["steps=2", "judge_episodes=0"]), data, tmp_path / "run")
    run.val = run.val or run.loader
    step = run._step

    def donating(state, batch, norm):
        out = step(state, batch, norm)
        jax.tree_util.tree_map(lambda x: x.delete(), state)
        return out

    run._step = donating
    run.warm()
    assert run._val_batches  # the validation loss ran


@pytest.mark.slow  # what only the GPU chain uses (pipeline --warm-eval)
def test_the_after_training_warm_up_runs_the_programs_the_finished_run_then_runs(smoke_dataset, tmp_path):
    """warm_after_training, given a started run's configuration and normalisation, runs the programs
    that the run runs once trained (its judge's imaginations and fit, eval.json) with parameters of
    zeros: the run that then trains compiles none of them again (a model width no other test trains,
    so that every program is new here)."""
    from experiments.timing import compile_snapshot
    from wm.train import warm_after_training

    _, data, _ = smoke_dataset
    args = ["steps=2", "model.dim=24", "judge_episodes=2", "judge_steps=3"]
    run = Run(make_config("smoke", args), data, tmp_path / "run")  # config.json and norm.json, as training starts
    run.loader.close()

    def compiled(step) -> set:  # the programs `step` compiled
        before = compile_snapshot()
        step()
        return {name for name, (count, _) in compile_snapshot()["by_program"].items()
                if count > before["by_program"].get(name, (0, 0.0))[0]}

    after = {"init_state", "_open_loop_segment", "_teacher_forced_pair"}
    assert after <= compiled(lambda: warm_after_training(run.cfg, data, run.norm))
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["best", "checkpoints", "config.json", "norm.json"]
    trained = compiled(lambda: train_main(["--config", "smoke", "--data", str(data), "--out", str(tmp_path / "run"),
                                           *args]))
    assert (tmp_path / "run" / "eval.json").exists() and "train_step" in trained
    assert not trained & (after | {"_closed_loop_start", "_closed_loop_segment", "_update", "_judge_loss", "_probability"})


def test_imagination_chunks_are_64_or_the_next_power_of_two():
    assert [I.chunk_size(n) for n in (1, 3, 64, 65, 5000)] == [1, 4, 64, 64, 64]
    parts = list(I.padded_chunks(list(range(150))))
    assert [(s, len(p), n) for s, p, n in parts] == [(0, 64, 64), (64, 64, 64), (128, 64, 22)]
    assert parts[2][1][-1] == 149 and parts[2][1][22:] == [149] * 42


def test_the_judges_closed_loop_runs_each_checkpoints_episodes_as_one_slot_and_puts_rows_back(monkeypatch):
    """Episodes of three checkpoints (3, 1 and 2 of them, interleaved): each chunk stacks whole
    checkpoints (padded to the most episodes of one), and every episode gets the row imagined from its
    own first frame with its own checkpoint's parameters."""
    class Cache:
        def episode(self, i, cameras):
            return {"frames": {"head_cam": np.full((5, 2, 2, 3), i, np.uint8)}, "proprio": np.zeros((5, 37))}

    calls = []

    def fake_closed_loop(cfg, policy, horizon, params, norm, policy_params, frames, proprio, ctx, rng):
        assert isinstance(policy, ClippedPolicy)  # imagined with the actions as the robot applies them
        p = policy.policy.count(policy_params)
        w = np.repeat(np.asarray(policy_params["w"]), len(frames) // p)  # each row's parameter set
        calls.append((p, len(frames)))
        return {"features": np.broadcast_to((frames[:, 0, 0, 0, 0] * 1000.0 + w)[:, None, None], (len(frames), horizon, 1))}

    monkeypatch.setattr(J, "closed_loop", fake_closed_loop)
    src = {n: PolicySource(f"mug/conv/{n}", "learned", "mug", object(), {"w": np.float32(n)}, {}) for n in (1, 2, 3)}
    group = [(10, src[1]), (11, src[2]), (12, src[1]), (13, src[3]), (14, src[1]), (15, src[3])]
    assert J.checkpoint_rows(group, 8) == ([(src[1], [10, 12, 14]), (src[2], [11, 11, 11]), (src[3], [13, 15, 15])], 3)
    # a checkpoint of more episodes than a chunk: even slots of at most the chunk
    assert J.checkpoint_rows(group, 2) == ([(src[1], [10, 12]), (src[1], [14, 14]), (src[2], [11, 11]),
                                            (src[3], [13, 15])], 2)
    x = J._closed_loop_features(SimpleNamespace(action_dim=20), None, None, Cache(), group, "head_cam", 4, object(), 0)
    assert x.shape == (6, 4, 1)
    np.testing.assert_array_equal(x[:, 0, 0], [10001, 11002, 12001, 13003, 14001, 15003])
    assert calls == [(2, 6), (2, 6)]  # chunk_size(6) = 8 rows: two checkpoints of 3, the last chunk padded
    many = [(20 + k, src[1]) for k in range(70)]  # on the CPU a chunk is 64 episodes: slots of 35, one a call
    calls.clear()
    x = J._closed_loop_features(SimpleNamespace(action_dim=20), None, None, Cache(), many, "head_cam", 4, object(), 0)
    np.testing.assert_array_equal(x[:, 0, 0], [(20 + k) * 1000 + 1 for k in range(70)])
    assert calls == [(1, 35), (1, 35)]
