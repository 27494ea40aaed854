"""MP4 files of RGB frames: H.264 (libx264, yuv420p) through PyAV, one frame per control step.

    with Mp4Writer(path, fps=20) as w:
        w.append(frames)               # (T, H, W, 3) uint8; appends continue the file's clock
    frames = read_mp4(path)            # (T, H, W, 3) uint8

H.264 in yuv420p plays in browsers, slide software and LeRobot's decoders (PyAV, torchcodec); PyAV's
wheels bundle libx264. B-frames are off so that every frame's presentation time is its index over
fps from 0, which LeRobot's timestamp lookups rely on.
"""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path
from typing import Self

import av
import numpy as np

CODEC = "libx264"
PIX_FMT = "yuv420p"
CRF = 18  # the frames are small (64 px): a low constant-rate factor keeps the sharp edges for a few kB more


class Mp4Writer:
    """Appends (T, H, W, 3) uint8 RGB frames of one size to an MP4 file, written under a temporary
    name and renamed when closed without an error (a reader never sees half a file).

    Args:
      path: the .mp4 file.
      fps: frames per second (an integer: the clock counts frames).
      gop: frames between key frames (None: the encoder's default); small values make seeking
        to any frame cheap at some size.
      crf: H.264 constant-rate factor (lower: better and larger).
    """

    def __init__(self, path: Path, fps: int, gop: int | None = None, crf: int = CRF):
        self.path = Path(path)
        self.fps = int(fps)
        self.frames = 0  # frames appended so far: the next frame's presentation index
        self._tmp = self.path.with_name(self.path.name + f".tmp{os.getpid()}")
        self._options = {"crf": str(crf), "bf": "0", **({"g": str(gop)} if gop else {})}
        self._container = av.open(str(self._tmp), mode="w", format="mp4")
        self._stream = None

    def _open_stream(self, height: int, width: int) -> None:
        if height % 2 or width % 2:
            raise ValueError(f"{self.path}: yuv420p needs even frame sizes, got {height}x{width}")
        self._stream = self._container.add_stream(CODEC, rate=self.fps, options=self._options)
        self._stream.height, self._stream.width, self._stream.pix_fmt = height, width, PIX_FMT
        self._stream.time_base = Fraction(1, self.fps)

    def append(self, frames: np.ndarray) -> tuple[float, float]:
        """Encodes frames (T, H, W, 3) uint8 RGB after those already appended.

        Returns (from_s, to_s): the first frame's presentation time and the time just after the last.
        """
        frames = np.asarray(frames)
        if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
            raise ValueError(f"{self.path}: frames must be (T, H, W, 3) uint8, got {frames.shape} {frames.dtype}")
        if self._stream is None:
            self._open_stream(*frames.shape[1:3])
        elif frames.shape[1:3] != (self._stream.height, self._stream.width):
            raise ValueError(f"{self.path}: frames of {frames.shape[1:3]} after frames of "
                             f"{(self._stream.height, self._stream.width)}")
        start = self.frames
        for frame in frames:
            vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            vf.pts = self.frames
            self._container.mux(self._stream.encode(vf))
            self.frames += 1
        return start / self.fps, self.frames / self.fps

    def bytes_written(self) -> int:
        """The file's size so far (the encoder's buffered frames not counted)."""
        return self._tmp.stat().st_size

    def close(self) -> None:
        """Flushes the encoder and renames the file to its name."""
        if self._stream is not None:
            self._container.mux(self._stream.encode(None))
        self._container.close()
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        """Drops the unfinished file."""
        self._container.close()
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_mp4(path: Path, frames: np.ndarray, fps: int, gop: int | None = None) -> Path:
    """Writes frames (T, H, W, 3) uint8 RGB to one MP4 file; returns its path."""
    with Mp4Writer(path, fps, gop) as w:
        w.append(frames)
    return Path(path)


def read_mp4(path: Path) -> np.ndarray:
    """Every frame of an MP4 file's first video stream: (T, H, W, 3) uint8 RGB."""
    with av.open(str(path)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    if not frames:
        raise ValueError(f"{path}: no video frames")
    return np.stack(frames)
