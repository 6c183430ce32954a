"""Encoding: raw RGB frames piped into ffmpeg, in palindromic order, into one file.

The ffmpeg binary is the one on PATH, else the one shipped in the imageio-ffmpeg wheel.
"""

from __future__ import annotations

import functools
import re
import shutil
import subprocess
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import ffmpeg
import numpy as np

from kbbatch.presets import Preset


class EncodeError(RuntimeError):
    pass


@functools.cache
def ffmpeg_exe() -> str:
    """Path of the ffmpeg binary to use."""
    found = shutil.which("ffmpeg")
    if found:
        return found
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


def palindrome_order(frames_forward: int) -> list[int]:
    """Indices of a forward-then-back clip: 0..N-1, then N-2..1 (the ends are not repeated)."""
    forward = list(range(frames_forward))
    return forward + forward[-2:0:-1]


def encoder_command(path: Path, preset: Preset, container: str = "mp4") -> list[str]:
    """The ffmpeg command that reads raw RGB frames on stdin and writes the clip."""
    stream = ffmpeg.input(
        "pipe:", format="rawvideo", pix_fmt="rgb24",
        s=f"{preset.width_px}x{preset.height_px}", framerate=preset.fps,
    )
    options: dict[str, object] = {
        "vcodec": preset.codec,
        "pix_fmt": preset.pix_fmt,
        "crf": preset.crf,
        "r": preset.fps,
        "format": container,
    }
    if preset.encoder_preset:
        options["preset"] = preset.encoder_preset
    if container == "mp4":
        options["movflags"] = "+faststart"
    if preset.codec == "libvpx-vp9":
        options["b:v"] = 0  # constant quality with crf
    out = ffmpeg.output(stream, str(path), **options).global_args("-loglevel", "error", "-nostdin")
    return ffmpeg.compile(out.overwrite_output(), cmd=ffmpeg_exe())


def encode_frames(path: Path, frames: Iterable[np.ndarray], preset: Preset) -> int:
    """Write frames (H, W, 3 uint8 RGB) to path with the preset's encoder; returns the count."""
    process = subprocess.Popen(
        encoder_command(path, preset), stdin=subprocess.PIPE, stderr=subprocess.PIPE
    )
    count = 0
    try:
        for frame in frames:
            if frame.shape != (preset.height_px, preset.width_px, 3) or frame.dtype != np.uint8:
                expected = (preset.height_px, preset.width_px, 3)
                raise EncodeError(f"frame {count} has shape {frame.shape} {frame.dtype}, "
                                  f"expected {expected} uint8")
            process.stdin.write(np.ascontiguousarray(frame).data)
            count += 1
        process.stdin.close()
    except BrokenPipeError:
        pass
    except BaseException:
        process.kill()
        process.wait()
        raise
    stderr = process.stderr.read().decode(errors="replace")
    if process.wait() != 0:
        raise EncodeError(f"ffmpeg failed writing {path}: {stderr.strip()[-800:]}")
    return count


@dataclass(frozen=True)
class VideoInfo:
    width_px: int
    height_px: int
    fps: float
    duration_s: float
    codec: str


def probe(path: Path) -> VideoInfo:
    """Stream facts from ffmpeg's own report (the wheel ships no ffprobe)."""
    result = subprocess.run(
        [ffmpeg_exe(), "-hide_banner", "-i", str(path)], capture_output=True, text=True
    )
    report = result.stderr
    video = re.search(r"Video: (\w+).*?, (\d+)x(\d+).*?, ([\d.]+) fps", report)
    duration = re.search(r"Duration: (\d+):(\d+):([\d.]+)", report)
    if not video or not duration:
        raise EncodeError(f"{path}: ffmpeg found no video stream ({report.strip()[-300:]})")
    hours, minutes, seconds = duration.groups()
    return VideoInfo(
        width_px=int(video.group(2)),
        height_px=int(video.group(3)),
        fps=float(video.group(4)),
        duration_s=int(hours) * 3600 + int(minutes) * 60 + float(seconds),
        codec=video.group(1),
    )


def decode_frames(path: Path, width_px: int, height_px: int) -> Iterator[np.ndarray]:
    """Every frame of a video as (H, W, 3) uint8 RGB."""
    process = subprocess.Popen(
        [ffmpeg_exe(), "-loglevel", "error", "-i", str(path), "-f", "rawvideo",
         "-pix_fmt", "rgb24", "pipe:"],
        stdout=subprocess.PIPE,
    )
    frame_bytes = width_px * height_px * 3
    try:
        while True:
            chunk = process.stdout.read(frame_bytes)
            if len(chunk) < frame_bytes:
                break
            yield np.frombuffer(chunk, np.uint8).reshape(height_px, width_px, 3)
    finally:
        process.stdout.close()
        process.wait()
