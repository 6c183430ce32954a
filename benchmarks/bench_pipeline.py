"""Whole-clip speed against ffmpeg's own 2D Ken Burns, measured in one run.

    .venv/bin/python benchmarks/bench_pipeline.py [--photo PATH] [--preset slideshow]

Prints per-stage seconds for one photo, frames per second of the renderer at the preset size
(one thread and all threads, no encoding), the whole 3D clip's wall time, and the wall time of
ffmpeg's zoompan filter making a palindromic 2D clip of the same size, frame count, fps and
encoder settings, with the ratio 3D / 2D. Targets (issue 2): >= 25 frames/s at 1920x1080 and a
ratio <= 1.5.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from kbbatch.encode import ffmpeg_exe, quality_options
from kbbatch.images import read_image
from kbbatch.pipeline import ClipOptions, frame_at, make_clip, ordered_map, prepare_scene
from kbbatch.presets import Preset, load_preset

SHARED_PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "photos"
DEFAULT_PHOTO = "33_landscape_sign_in_field.jpg"


def zoompan_seconds(photo: Path, preset: Preset, output: Path) -> float:
    """ffmpeg's 2D Ken Burns: centred zoom in to 1.25 and back, same frames and encoder."""
    half = preset.frames_forward - 1
    zoom = f"1+{preset.zoom - 1}*(1-abs(1-on/{half}))"
    w, h = preset.width_px, preset.height_px
    filters = (
        f"crop='min(iw,ih*{w}/{h})':'min(ih,iw*{h}/{w})',scale={w}:{h},"
        f"zoompan=z='{zoom}':x='iw/2-iw/zoom/2':y='ih/2-ih/zoom/2':d=1:s={w}x{h}:fps={preset.fps}"
    )
    command = [
        ffmpeg_exe(), "-loglevel", "error", "-y", "-loop", "1", "-framerate", str(preset.fps),
        "-i", str(photo), "-vf", filters, "-frames:v", str(preset.frames_total),
        "-c:v", preset.codec, "-pix_fmt", preset.pix_fmt, "-movflags", "+faststart",
    ]
    for name, value in quality_options(preset).items():
        command += [f"-{name}", str(value)]
    started = time.perf_counter()
    subprocess.run([*command, str(output)], check=True)
    return time.perf_counter() - started


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photo", type=Path, default=SHARED_PHOTOS / DEFAULT_PHOTO)
    parser.add_argument("--preset", default="slideshow")
    parser.add_argument("--frames", type=int, default=30, help="frames timed per round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds timed for frames/s")
    args = parser.parse_args()
    if not args.photo.is_file():
        print(f"photo not found: {args.photo} (../shared is only on developer and CI machines)")
        return 2
    preset = load_preset(args.preset)
    threads = os.cpu_count() or 1
    options = ClipOptions(threads=threads, cache_depth=False)

    photo = read_image(args.photo)
    timings: dict[str, float] = {}
    prepared = prepare_scene(photo, args.photo, preset, options, timings)
    frame_at(prepared, preset, 0.5)  # compile the kernels outside the timings
    times = np.linspace(0, 1, args.frames).tolist()

    def frames_per_second(threads: int) -> list[float]:
        """Several rounds, since one round on a shared machine can catch a neighbour's burst."""
        rates = []
        for _ in range(args.rounds):
            started = time.perf_counter()
            for _ in ordered_map(lambda t: frame_at(prepared, preset, t), times, threads):
                pass
            rates.append(args.frames / (time.perf_counter() - started))
        return sorted(rates)

    fps_one = frames_per_second(1)
    fps_all = frames_per_second(threads)

    with tempfile.TemporaryDirectory() as scratch:
        result = make_clip(args.photo, Path(scratch) / "3d.mp4", preset, options, False)
        if result.status != "done":
            print(result.error)
            return 1
        seconds_2d = zoompan_seconds(args.photo, preset, Path(scratch) / "2d.mp4")

    print(f"photo {args.photo.name}, preset {preset.name} {preset.width_px}x{preset.height_px} "
          f"@ {preset.fps:g} fps, {preset.frames_forward} rendered / {preset.frames_total} "
          f"encoded frames, {threads} threads, {len(prepared.cloud):,} points")
    print(f"{'stage':<32}{'seconds':>10}")
    for stage, seconds in result.stage_seconds.items():
        print(f"{stage:<32}{seconds:>10.2f}")
    for label, rates in (("1 thread", fps_one), (f"{threads} threads", fps_all)):
        print(f"{f'render fps, {label}, median':<32}{np.median(rates):>10.1f}")
        print(f"{f'render fps, {label}, slowest':<32}{rates[0]:>10.1f}")
    print(f"{'3D clip, whole (s)':<32}{result.seconds:>10.2f}")
    print(f"{'2D zoompan clip (s)':<32}{seconds_2d:>10.2f}")
    print(f"{'ratio 3D / 2D':<32}{result.seconds / seconds_2d:>10.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
