"""Frame and outcome metrics: PSNR, SSIM, accuracy, AUROC (numpy); how much the actions explain the
predicted future (action_contrast) and the divergence of two Gaussians (gaussian_kl), in jax.numpy:
the training loss uses them too."""

from __future__ import annotations

import cv2
import jax.numpy as jnp
import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.stats import mannwhitneyu


def psnr(pred, true, axis=(-3, -2, -1)) -> np.ndarray:
    """Peak signal-to-noise ratio in dB of uint8 (or [0, 255] float) images, reduced over `axis`.
    Identical images give +inf."""
    return psnr_of_mse(np.mean((np.asarray(pred, np.float64) - np.asarray(true, np.float64)) ** 2, axis=axis))


def psnr_of_mse(err) -> np.ndarray:
    """PSNR in dB (the shape of err) of mean squared errors (any shape) of [0, 255] pixels; an error of 0
    gives +inf."""
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(255.0**2 / np.asarray(err, np.float64))


def ssim(pred, true) -> np.ndarray:
    """Structural similarity of (..., H, W, 3) uint8 images, per image: a Gaussian window (sigma
    1.5, truncated at 3.5 sigma: the 11-tap window of Wang et al. 2004), K1 = 0.01, K2 = 0.03,
    L = 255, averaged over pixels and channels."""
    x = np.asarray(pred, np.float64)
    y = np.asarray(true, np.float64)
    lead = x.shape[:-3]
    x = x.reshape((-1,) + x.shape[-3:])
    y = y.reshape((-1,) + y.shape[-3:])
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2

    def blur(a):
        return gaussian_filter(a, sigma=(0, 1.5, 1.5, 0), truncate=3.5, mode="reflect")

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return s.mean(axis=(1, 2, 3)).reshape(lead)


def auroc(scores, labels) -> float:
    """Area under the ROC curve (the probability that a random positive scores above a random
    negative, ties counting one half): scipy's Mann-Whitney U of the positives over the pairs; nan
    when a class is absent."""
    s = np.asarray(scores, np.float64)
    y = np.asarray(labels, bool)
    pos, neg = s[y], s[~y]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    return float(mannwhitneyu(pos, neg).statistic / (len(pos) * len(neg)))


def auroc_within_groups(scores, labels, groups) -> tuple[float, dict]:
    """AUROC within each group (a task) and their mean over the groups holding both outcomes: a
    score that only tells the groups apart (one task succeeds more often than another) earns 0.5
    here, where the pooled auroc credits it. Returns (mean, {group: auroc}); nan where no group has
    both outcomes (a group with one outcome is nan in the dict and left out of the mean)."""
    s, y, g = np.asarray(scores, np.float64), np.asarray(labels, bool), np.asarray(groups)
    each = {str(k): auroc(s[g == k], y[g == k]) for k in sorted(set(g.tolist()))}
    defined = [v for v in each.values() if np.isfinite(v)]
    return (float(np.mean(defined)) if defined else float("nan")), each


def accuracy(prob, labels, threshold: float = 0.5) -> float:
    """The share of predictions, probabilities prob (N,) at or above threshold read as positive, that match
    labels (N,) bool."""
    return float(np.mean((np.asarray(prob) >= threshold) == np.asarray(labels, bool)))


def view_shift(a, b) -> np.ndarray:
    """How far the whole view moved between images a and b, (N, H, W, 3) uint8 each: the length in
    pixels of the global translation that registers b onto a (phase correlation of the grey images
    under a Hann window, OpenCV's sub-pixel peak), per pair: (N,) float. A robot whose body stays in
    place keeps its head camera's view still, so an imagined frame shifted against the true one has
    moved the body, or the whole scene.

    NaN where no translation registers the pair: the correlation's peak is no higher than
    4 / sqrt(H W) (about the highest value an unrelated pair's surface reaches, whose values spread
    as 1 / sqrt(H W); OpenCV's sub-pixel centroid of such a surface can land hundreds of pixels away),
    or the shift exceeds half the frame (phase correlation wraps around there)."""
    a = np.asarray(a, np.float32).mean(axis=-1)
    b = np.asarray(b, np.float32).mean(axis=-1)
    h, w = a.shape[-2:]
    window = cv2.createHanningWindow((w, h), cv2.CV_32F)
    out = []
    for x, y in zip(a, b, strict=True):
        (dx, dy), peak = cv2.phaseCorrelate(x, y, window)
        measurable = peak > 4.0 / np.sqrt(h * w) and abs(dx) <= w / 2 and abs(dy) <= h / 2
        out.append(np.hypot(dx, dy) if measurable else np.nan)
    return np.array(out)


def window_contrast(pred, other, target):
    """Per window (B,), log(1 + d_true / d_other): the negative log of the true actions' share when the
    future is attributed by inverse squared error between the prediction under the window's own
    actions, pred (B, T, ...), and under another window's, other (same shape), against the true
    latents target. log 2 where the actions change nothing; below it where the own actions' prediction
    is the better one, towards 0 as it becomes the far better one."""
    axes = tuple(range(1, pred.ndim))
    d_true = jnp.mean((pred - target) ** 2, axis=axes)
    d_other = jnp.mean((other - target) ** 2, axis=axes)
    return jnp.log1p(d_true / (d_other + 1e-8))


def action_contrast(pred, other, target):
    """How little the actions explain the future: window_contrast's mean over the windows (log 2 where
    the actions change nothing; towards 0 as the own actions' prediction becomes the far better one)."""
    return jnp.mean(window_contrast(pred, other, target))


def gaussian_kl(mean_q, logstd_q, mean_p, logstd_p):
    """KL(q || p) in nats between diagonal Gaussians given by their means and log standard deviations
    (..., S), summed over the last axis: (...)."""
    var_q, var_p = jnp.exp(2 * logstd_q), jnp.exp(2 * logstd_p)
    return jnp.sum(logstd_p - logstd_q + (var_q + (mean_q - mean_p) ** 2) / (2 * var_p) - 0.5, axis=-1)
