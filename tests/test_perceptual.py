"""LPIPS (wm.perceptual) against what the metric must do: nothing between a frame and itself, the
same both ways, more the more a frame is corrupted, more for a blur than for a one-level change of
brightness, the same figure whatever the batch a frame is read in."""

import cv2
import numpy as np
import pytest

from wm.perceptual import CHUNK, lpips


@pytest.fixture(scope="module")
def frames():
    """Eight 64 x 64 frames of smooth structure (blurred noise), like rendered scenes more than noise."""
    rng = np.random.default_rng(0)
    raw = rng.integers(0, 256, (8, 64, 64, 3), dtype=np.uint8)
    return np.stack([cv2.GaussianBlur(f, (0, 0), 2.0) for f in raw])


def test_identical_frames_are_at_zero_and_the_distance_is_symmetric(frames):
    np.testing.assert_allclose(lpips(frames, frames), 0.0, atol=1e-6)
    other = frames[::-1].copy()
    d = lpips(frames, other)
    assert d.shape == (8,) and d.dtype == np.float32 and (d > 0.01).all()
    np.testing.assert_allclose(d, lpips(other, frames), rtol=1e-4, atol=1e-6)


def test_the_distance_grows_with_the_corruption(frames):
    rng = np.random.default_rng(1)
    noise = rng.normal(size=frames.shape)
    means = [lpips(frames, np.clip(frames + s * noise, 0, 255).astype(np.uint8)).mean() for s in (2, 8, 32)]
    assert means[0] < means[1] < means[2]
    blurred = np.stack([cv2.GaussianBlur(f, (0, 0), 2.0) for f in frames])
    brighter = np.clip(frames.astype(int) + 1, 0, 255).astype(np.uint8)
    assert lpips(frames, blurred).mean() > 10 * lpips(frames, brighter).mean()


def test_a_frame_reads_the_same_in_any_batch_and_shapes_are_checked(frames):
    many = np.concatenate([frames] * (CHUNK // 8 + 1))  # over one chunk: the last one padded
    other = many[::-1].copy()
    d = lpips(many, other)
    assert d.shape == (len(many),)
    np.testing.assert_allclose(d[:3], lpips(many[:3], other[:3]), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(d[-3:], lpips(many[-3:], other[-3:]), rtol=1e-4, atol=1e-6)
    assert lpips(frames[:0], frames[:0]).shape == (0,)
    with pytest.raises(ValueError, match="LPIPS"):
        lpips(frames, frames[:, :32])
