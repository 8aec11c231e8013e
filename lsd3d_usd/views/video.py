"""MP4 clips from rendered frames via imageio-ffmpeg, a dependency (its wheels ship an ffmpeg
binary, so nothing else needs installing).

H.264 / yuv420p needs even sizes: frames are padded by edge replication to a multiple of
``block`` (2) rather than rescaled, so pixels stay exact. Written to a temp file, then
renamed (atomic).
"""
from __future__ import annotations

import os
from pathlib import Path

import imageio_ffmpeg
import numpy as np

from lsd3d_usd.errors import Lsd3dError


def ffmpeg_exe() -> str:
    """The bundled ffmpeg binary (or IMAGEIO_FFMPEG_EXE); one clear error when there is none,
    e.g. on a platform imageio-ffmpeg ships no binary for."""
    try:
        exe = imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError as e:
        raise Lsd3dError(f"MP4: imageio-ffmpeg found no ffmpeg binary ({' '.join(str(e).split())[:160]}); "
                         "set IMAGEIO_FFMPEG_EXE to an ffmpeg, or pass --no-video") from None
    return exe


def _pad(frame: np.ndarray, block: int) -> np.ndarray:
    h, w = frame.shape[:2]
    ph, pw = (-h) % block, (-w) % block
    if ph or pw:
        frame = np.pad(frame, ((0, ph), (0, pw), (0, 0)), mode="edge")
    return np.ascontiguousarray(frame)


def write_mp4(path, frames, fps: float, block: int = 2) -> Path:
    """Write uint8 RGB frames (iterable of (H,W,3), all the same size) as an H.264 MP4.

    Frames that can be read again (a list, or any iterable that is not its own iterator) are
    encoded a second time when ffmpeg ends before its input does (a broken pipe, or no file
    written; full test-suite runs met it now and then, ffmpeg saying nothing); a generator
    is consumed once and its failure raised."""
    ffmpeg_exe()   # a missing binary is one line before any frame is encoded
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    attempts = 1 if iter(frames) is frames else 2      # an iterator is read once
    for attempt in range(attempts):
        try:
            _encode(tmp, frames, fps, block)
            os.replace(tmp, path)
            return path
        except OSError:            # BrokenPipeError, ffmpeg's IOError, the file not written
            if attempt + 1 == attempts:
                raise
        finally:
            if tmp.exists():
                tmp.unlink()
    return path


def _encode(tmp: Path, frames, fps: float, block: int) -> None:
    gen = None
    size = None
    try:
        for f in frames:
            f = np.asarray(f)
            if f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3:
                raise ValueError(f"write_mp4: frames must be (H, W, 3) uint8, got {f.shape} {f.dtype}")
            f = _pad(f, block)
            if gen is None:
                size = (f.shape[1], f.shape[0])
                gen = imageio_ffmpeg.write_frames(str(tmp), size, fps=float(fps), codec="libx264",
                                                  pix_fmt_out="yuv420p", macro_block_size=1,
                                                  output_params=["-crf", "23"], ffmpeg_log_level="error")
                gen.send(None)
            elif (f.shape[1], f.shape[0]) != size:
                raise ValueError(f"write_mp4: frame size {f.shape[1]}x{f.shape[0]} differs from {size}")
            gen.send(f)
        if gen is None:
            raise ValueError("write_mp4: no frames")
        gen.close()
        gen = None
    finally:
        if gen is not None:
            gen.close()


def read_mp4(path) -> tuple[np.ndarray, float]:
    """Decode an MP4 back to uint8 RGB frames (n, H, W, 3) and its frame rate."""
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = gen.__next__()
    w, h = meta["size"]
    frames = [np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in gen]
    return (np.stack(frames) if frames else np.zeros((0, h, w, 3), np.uint8)), float(meta["fps"])
