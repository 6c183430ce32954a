"""Encoding: raw RGB frames piped into ffmpeg, in palindromic order, into one file.

The ffmpeg binary is the one on PATH, else the one shipped in the imageio-ffmpeg wheel.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import re
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import ffmpeg
import numpy as np

from kbbatch.interrupts import held
from kbbatch.presets import Preset

FFMPEG_STOP_MESSAGE = "Immediate exit requested"
"""What ffmpeg says when a stop signal arrives before its first frame (it then also reports the
read it broke off)."""

FFMPEG_CUT_FRAME_MESSAGE = "< expected frame_size"
"""What ffmpeg says of the frame a stop signal cut in half (it stops reading mid-frame, then
reports the short packet): stopped, not failed (seen under load, where the signal so often
lands inside a 170 kB frame)."""

FFMPEG_DISK_FULL_MESSAGES = {"No space left on device": errno.ENOSPC,
                             "Disk quota exceeded": errno.EDQUOT}
"""What ffmpeg says when the clip's disk has no room left: raised as an OSError of that errno
(kbbatch.images.is_disk_full), so that the photo is not failed for it."""

FFMPEG_SIGNALLED_STATUS = 255
"""ffmpeg's exit status after it caught SIGTERM or SIGINT and stopped (its errors exit with 1
and say why on stderr; a signal leaves stderr empty at -loglevel error)."""


STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
"""Signals that ask a process to stop (ffmpeg catches them and exits with
FFMPEG_SIGNALLED_STATUS); any other signal that ends it is a failure."""


class EncoderStoppedError(RuntimeError):
    """ffmpeg was ended by a signal from outside (a service manager stopping every process of
    the service): an interruption, not a failure of the photo."""


class EncodeError(RuntimeError):
    pass


class EncoderError(EncodeError):
    """An encoder setting this ffmpeg cannot use; `field` names the preset setting."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


TRIAL_SIZE_PX = 256
"""Side of the two black frames a preset's encoder settings are tried on when it loads (NVENC
refuses frames narrower than about 145 px)."""

NVENC_SUFFIX = "_nvenc"
"""NVIDIA's hardware encoders (h264_nvenc, hevc_nvenc, av1_nvenc): they need an NVIDIA GPU
and driver, and take a constant-quality level (-cq) where software encoders take -crf."""


@functools.cache
def ffmpeg_exe() -> str:
    """Path of the ffmpeg binary to use."""
    found = shutil.which("ffmpeg")
    if found:
        return found
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


@functools.cache
def _encoders() -> frozenset[str]:
    """Video encoders this ffmpeg binary offers."""
    listing = subprocess.run([ffmpeg_exe(), "-hide_banner", "-encoders"], capture_output=True,
                             text=True, check=True).stdout
    return frozenset(m.group(1) for m in re.finditer(r"^ V\S* (\S+)", listing, re.MULTILINE))


@functools.cache
def _pixel_formats(codec: str) -> frozenset[str]:
    """Pixel formats an encoder lists (empty when it lists none)."""
    text = subprocess.run([ffmpeg_exe(), "-hide_banner", "-h", f"encoder={codec}"],
                          capture_output=True, text=True).stdout
    found = re.search(r"Supported pixel formats: (.*)", text)
    return frozenset(found.group(1).split()) if found else frozenset()


def check_encoder(preset: Preset) -> None:
    """Raise EncoderError unless this ffmpeg can encode with the preset's codec, pix_fmt and
    encoder_preset: known lists first, then two tiny frames through the real command."""
    _check_encoder(preset.codec, preset.pix_fmt, preset.encoder_preset, preset.crf)


@functools.cache
def _check_encoder(codec: str, pix_fmt: str, encoder_preset: str, crf: int) -> None:
    if codec not in _encoders():
        raise EncoderError("codec", f"ffmpeg ({ffmpeg_exe()}) has no video encoder {codec!r}")
    formats = _pixel_formats(codec)
    if formats and pix_fmt not in formats:
        raise EncoderError("pix_fmt", f"{codec} cannot write {pix_fmt!r}; it offers "
                                      f"{', '.join(sorted(formats))}")
    refusal = encoder_refusal(codec, pix_fmt, encoder_preset, crf)
    if refusal is None:
        return
    # An encoder that fails without the speed preset too (no GPU for NVENC) is the culprit.
    if encoder_preset and encoder_refusal(codec, pix_fmt, "", crf) is None:
        field, value = "encoder_preset", encoder_preset
    else:
        field, value = "codec", codec
    if codec.endswith(NVENC_SUFFIX):
        refusal += (f" ({codec} is NVIDIA's hardware encoder: it needs an NVIDIA GPU and its "
                    "driver; use libx264 or libx265 without one)")
    raise EncoderError(field, f"ffmpeg refuses {codec} with {field} {value!r}: {refusal}")


def encoder_refusal(codec: str, pix_fmt: str, encoder_preset: str, crf: int) -> str | None:
    """Why ffmpeg fails to encode two tiny frames with these settings into an MP4 file, as a
    clip is written (None: it does not). Into the null muxer, codecs that no MP4 holds (gif,
    rawvideo) passed, and then every photo failed."""
    trial = Preset("trial", "", TRIAL_SIZE_PX, TRIAL_SIZE_PX, 25.0, 0.08, "linear", 1.0, "in",
                   0.0, codec, crf, pix_fmt, encoder_preset)
    frames = np.zeros((2, TRIAL_SIZE_PX, TRIAL_SIZE_PX, 3), np.uint8).tobytes()
    try:
        with tempfile.TemporaryDirectory(prefix="kbbatch-encoder-check-") as folder:
            command = encoder_command(Path(folder) / "trial.mp4", trial)
            result = subprocess.run(command, input=frames, capture_output=True)
    except OSError:  # no room for a temporary folder: the encoder alone, into no file
        command = encoder_command(Path(os.devnull), trial, container="null")
        result = subprocess.run(command, input=frames, capture_output=True)
    if result.returncode == 0:
        return None
    return " ".join(result.stderr.decode(errors="replace").strip().splitlines()[:2])


def palindrome_order(frames_forward: int) -> list[int]:
    """Indices of a forward-then-back clip: 0..N-1, then N-2..1 (the ends are not repeated)."""
    forward = list(range(frames_forward))
    return forward + forward[-2:0:-1]


def quality_options(preset: Preset) -> dict[str, object]:
    """ffmpeg output options for the preset's quality and speed, in its encoder's terms."""
    options: dict[str, object] = {}
    if preset.codec.endswith(NVENC_SUFFIX):  # constant quality, as crf is for x264
        options.update({"rc": "vbr", "cq": preset.crf, "b:v": 0})
    else:
        options["crf"] = preset.crf
    if preset.codec == "libvpx-vp9":
        options["b:v"] = 0  # constant quality with crf
    if preset.encoder_preset:
        options["preset"] = preset.encoder_preset
    return options


OUTPUT_PLACEHOLDER = "kbbatch-output-placeholder.mp4"
"""The output name ffmpeg-python builds the command with, then replaced by the real path:
ffmpeg-python hashes every name as UTF-8, so a folder whose name is not (bytes the file system
accepts, read back as surrogates) failed every clip; the OS takes such a name as it is."""


COLOUR_STANDARD = "bt709"
"""Frames are sRGB, whose primaries are BT.709's: a clip is converted to YUV with BT.709's
matrix (at any size) and tagged so. Untagged, with swscale's default BT.601 matrix, players that
take untagged HD video for BT.709 shifted every clip's colours (a green of 180 read as 155)."""


def with_colour_tags(stream, pix_fmt: str):
    """The frames converted with BT.709's matrix (for a YUV format) and tagged as BT.709 (the
    frame tags: ffmpeg's own -color_* options lost the primaries and transfer on the way)."""
    tags: dict[str, str] = {"color_primaries": COLOUR_STANDARD, "color_trc": COLOUR_STANDARD}
    if is_yuv(pix_fmt):
        stream = stream.filter("scale", out_color_matrix=COLOUR_STANDARD, out_range="tv")
        tags.update(colorspace=COLOUR_STANDARD, range="tv")
    return stream.filter("setparams", **tags)


def is_yuv(pix_fmt: str) -> bool:
    return pix_fmt.startswith(("yuv", "nv", "p010", "p016"))  # yuvj* too


CLIP_MARK = re.compile(rb"kbbatch clip of sha256:([0-9a-f]{64}) settings:([0-9a-f]{16,64})")
"""The comment kbbatch writes into each clip: the photo's bytes and settings it was made from
(pipeline.clip_fingerprints), so that a clip the journal has no record of (the journal deleted,
the folder copied without it) is still known as this photo's, and not made again beside itself
under a content name."""

CLIP_MARK_SEARCH_BYTES = 4 << 20
"""How far into a clip its mark is looked for: `+faststart` puts the metadata, with the
comment, before the frames (a 2-minute 4K clip's index is well under this)."""


def clip_mark(content: str, settings: str) -> str:
    return f"kbbatch clip of sha256:{content} settings:{settings}"


def read_clip_mark(path: Path) -> tuple[str, str] | None:
    """(photo sha256, settings digest) from a clip's mark; None for a file without one, and
    for what kbbatch never writes at a clip's name (a link, a pipe: reading one would block)."""
    if path.is_symlink() or not path.is_file():
        return None
    try:
        with path.open("rb") as handle:
            head = handle.read(CLIP_MARK_SEARCH_BYTES)
    except OSError:
        return None
    found = CLIP_MARK.search(head)
    return (found[1].decode(), found[2].decode()) if found else None


def encoder_command(path: Path, preset: Preset, container: str = "mp4",
                    comment: str | None = None) -> list[str]:
    """The ffmpeg command that reads raw RGB frames on stdin and writes the clip."""
    stream = ffmpeg.input(
        "pipe:", format="rawvideo", pix_fmt="rgb24",
        s=f"{preset.width_px}x{preset.height_px}", framerate=preset.fps,
    )
    stream = with_colour_tags(stream, preset.pix_fmt)
    options: dict[str, object] = {
        "vcodec": preset.codec,
        "pix_fmt": preset.pix_fmt,
        "r": preset.fps,
        "format": container,
        **quality_options(preset),
    }
    if container == "mp4":
        options["movflags"] = "+faststart"
        if preset.codec in HEVC_ENCODERS:  # ffmpeg tags HEVC `hev1`, which Apple's players
            options["tag:v"] = "hvc1"  # and editors refuse: they play `hvc1` only
    if comment is not None:
        options["metadata"] = f"comment={comment}"
    out = ffmpeg.output(stream, OUTPUT_PLACEHOLDER, **options).global_args(
        "-loglevel", "error", "-nostdin")
    command = ffmpeg.compile(out.overwrite_output(), cmd=ffmpeg_exe())
    return [str(path) if arg == OUTPUT_PLACEHOLDER else arg for arg in command]


HEVC_ENCODERS = ("libx265", "hevc_nvenc")
"""Encoders of HEVC, whose MP4s are tagged `hvc1` (QuickTime, Final Cut and iOS play no other)."""


KILL_REASONS = {
    signal.SIGXFSZ: "the file size limit, `ulimit -f`, was reached",
    signal.SIGKILL: "killed outright: often the kernel's out-of-memory killer",
}
"""What a signal that kills ffmpeg usually means, said with its name."""


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:  # a real-time signal has no name
        return f"signal {number}"


def caught_stop(status: int, stderr: str) -> bool:
    """Whether ffmpeg exited because it caught a stop signal: its signal status, with nothing
    on stderr or what a stop leaves there (the stop itself, or the frame it cut short; frames
    are written whole, so only a stop cuts one)."""
    return status == FFMPEG_SIGNALLED_STATUS and (
        not stderr.strip() or FFMPEG_STOP_MESSAGE in stderr or FFMPEG_CUT_FRAME_MESSAGE in stderr)


def encode_frames(path: Path, frames: Iterable[np.ndarray], preset: Preset,
                  comment: str | None = None) -> int:
    """Write frames (H, W, 3 uint8 RGB) to path with the preset's encoder; returns the count.
    comment: written into the clip's metadata (clip_mark)."""
    process = None
    count = 0
    try:
        # Its own session: a stop signal sent to the whole process group (a shell, a
        # supervisor) is the runner's to act on; the runner then finishes or ends the clip
        # itself. Started with Ctrl-C held: one inside Popen left an encoder no one could stop.
        with held():
            process = subprocess.Popen(
                encoder_command(path, preset, comment=comment), stdin=subprocess.PIPE,
                stderr=subprocess.PIPE,
                start_new_session=True,
            )
        for frame in frames:
            if frame.shape != (preset.height_px, preset.width_px, 3) or frame.dtype != np.uint8:
                expected = (preset.height_px, preset.width_px, 3)
                raise EncodeError(f"frame {count} has shape {frame.shape} {frame.dtype}, "
                                  f"expected {expected} uint8")
            # ffmpeg ended early: its status and stderr say why (a broken pipe raised while
            # the frames were made is not its: caught here, the encoder was left waiting)
            try:
                process.stdin.write(np.ascontiguousarray(frame).data)
            except BrokenPipeError:
                break
            count += 1
        with contextlib.suppress(BrokenPipeError):
            process.stdin.close()
    except BaseException:
        if process is not None:
            process.kill()
            process.wait()
        raise
    stderr = process.stderr.read().decode(errors="replace")
    status = process.wait()
    killer = -status if status < 0 else None
    if killer in STOP_SIGNALS or caught_stop(status, stderr):
        cause = _signal_name(killer) if killer else "a signal"
        raise EncoderStoppedError(f"ffmpeg was stopped by {cause} while writing {path}; the "
                                  "photo is not at fault and is taken again")
    if killer is not None:  # a failure: the photo is not taken again
        why = KILL_REASONS.get(killer)
        raise EncodeError(f"ffmpeg was killed by {_signal_name(killer)}"
                          f"{f' ({why})' if why else ''} writing {path} "
                          f"{stderr.strip()[-800:]}".rstrip())
    if status != 0:
        for message, number in FFMPEG_DISK_FULL_MESSAGES.items():
            if message in stderr:
                raise OSError(number, f"ffmpeg: {message}", str(path))
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
    """Stream facts, as imageio-ffmpeg reads them (the wheel ships no ffprobe)."""
    import imageio_ffmpeg

    try:
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        reader.close()
    except (OSError, RuntimeError, StopIteration) as error:
        reason = (str(error).strip().splitlines() or ["no metadata"])[-1]
        raise EncodeError(f"{path}: ffmpeg found no video stream ({reason})") from error
    width_px, height_px = meta["size"]
    return VideoInfo(width_px=width_px, height_px=height_px, fps=float(meta["fps"]),
                     duration_s=float(meta["duration"]), codec=meta["codec"])


def is_cut_short_clip(path: Path, written_size_bytes: int) -> bool:
    """Whether the file at a clip's name is what is left of the clip kbbatch wrote there, cut
    short (a copy that stopped, a failing disk): smaller, an MP4 from its first box, and not
    readable to its end. Anything else at that name (a video the user saved over it, trimmed
    in an editor; any other file) is the user's, never replaced."""
    try:
        size = path.stat().st_size
        with path.open("rb") as handle:
            head = handle.read(8)
    except OSError:
        return False
    if size >= written_size_bytes:
        return False
    if len(head) < 8:  # stopped within the first box's header (empty: failed at its start):
        # its size, under 2**24 (its first three bytes zero), then `ftyp` (a note is no box)
        return head[:3] == bytes(min(3, len(head))) and b"ftyp".startswith(head[4:])
    if head[4:8] != b"ftyp":
        return False
    return not is_whole_clip(path, if_unknown=True)


def is_whole_clip(path: Path, if_unknown: bool = False) -> bool:
    """Whether ffmpeg reads a clip's video to its end (its packets, not decoded: fast);
    if_unknown where ffmpeg could not be asked."""
    command = [ffmpeg_exe(), "-v", "error", "-xerror", "-i", str(path), "-map", "0:v:0",
               "-c", "copy", "-f", "null", "-"]
    try:
        return subprocess.run(command, stdin=subprocess.DEVNULL, capture_output=True,
                              timeout=120).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return if_unknown


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
