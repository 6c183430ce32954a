"""Frame renderer speed on each available device, at 1080p and 4K; with a GPU, the whole clip.

    .venv/bin/python benchmarks/bench_gpu.py [--photo PATH] [--frames N] [--presets slideshow,4k]

Devices: `cpu` (the numba kernels, all threads), `torch-cpu` (the GPU code path on torch's CPU
device) and `cuda` (when torch sees a GPU). For each preset it prints frames/s of rendering
alone (frames back in host memory, no encoding) and the PSNR of each torch device's frames
against the numba frames. With CUDA it also prints the whole clip on the GPU against ffmpeg's
2D zoompan of the same size and encoder, and encoding the same frames with NVENC against
libx264. Goal (issue 15): >= 300 frames/s at 1080p on an H100-class GPU.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from kbbatch.device import TORCH_CPU, cuda_available, torch_device
from kbbatch.encode import encode_frames, encoder_refusal
from kbbatch.images import read_image
from kbbatch.pipeline import (
    ClipOptions,
    disparity_scale,
    frame_at,
    frame_view,
    make_clip,
    ordered_map,
    prepare_scene,
)
from kbbatch.presets import Preset, load_preset

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import DEFAULT_PHOTO, SHARED_PHOTOS, zoompan_seconds  # noqa: E402


def psnr_db(first: np.ndarray, second: np.ndarray) -> float:
    error = np.mean((first.astype(np.float64) - second.astype(np.float64)) ** 2)
    return float("inf") if error == 0 else float(10 * np.log10(255.0**2 / error))


def numba_frames(prepared, preset: Preset, times: list[float]) -> tuple[float, np.ndarray]:
    threads = os.cpu_count() or 1
    frame_at(prepared, preset, times[0])  # compile outside the timing
    started = time.perf_counter()
    frames = np.stack(list(ordered_map(lambda t: frame_at(prepared, preset, t), times,
                                       threads)))
    return len(times) / (time.perf_counter() - started), frames


def torch_frames(prepared, preset: Preset, times: list[float], device: str
                 ) -> tuple[float, np.ndarray, int]:
    """Frames/s of the torch renderer, the cloud already uploaded (once per clip)."""
    import torch

    from kbbatch.render_torch import TorchRenderer

    renderer = TorchRenderer(prepared.cloud, torch_device(device), disparity_scale(prepared))
    views = [frame_view(prepared, preset, t) for t in times]
    step = renderer.frames_per_launch()
    renderer.render_frames(views[:1]).cpu()  # warm-up: allocator, kernels
    if renderer.device.type == "cuda":
        torch.cuda.synchronize()
    started = time.perf_counter()
    frames = [renderer.render_frames(views[i:i + step]).cpu().numpy()
              for i in range(0, len(views), step)]
    return len(times) / (time.perf_counter() - started), np.concatenate(frames), step


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photo", type=Path, default=SHARED_PHOTOS / DEFAULT_PHOTO)
    parser.add_argument("--presets", default="slideshow,4k")
    parser.add_argument("--frames", type=int, default=8, help="frames timed per device")
    args = parser.parse_args()
    if not args.photo.is_file():
        print(f"photo not found: {args.photo} (../shared is only on developer and CI machines)")
        return 2
    has_cuda, why_not = cuda_available()
    try:
        import torch  # noqa: F401

        devices = [TORCH_CPU] + (["cuda"] if has_cuda else [])
    except ImportError:
        devices = []
    photo = read_image(args.photo)
    print(f"photo {args.photo.name}; {os.cpu_count()} cores; CUDA: "
          f"{'yes' if has_cuda else why_not}")
    print(f"{'preset':<11}{'size':>11}{'points':>12}{'device':>11}{'per launch':>12}"
          f"{'frames/s':>10}{'PSNR dB':>9}")
    for name in args.presets.split(","):
        preset = load_preset(name)
        prepared = prepare_scene(photo, args.photo, preset, ClipOptions(), {})
        times = np.linspace(0, 1, args.frames).tolist()
        size = f"{preset.width_px}x{preset.height_px}"
        rate, reference = numba_frames(prepared, preset, times)
        row = f"{name:<11}{size:>11}{len(prepared.cloud):>12,}"
        print(f"{row}{'cpu':>11}{'1':>12}{rate:>10.2f}{'-':>9}", flush=True)
        for device in devices:
            rate, frames, step = torch_frames(prepared, preset, times, device)
            worst = min(psnr_db(a, b) for a, b in zip(frames, reference, strict=True))
            print(f"{row}{device:>11}{step:>12}{rate:>10.2f}{worst:>9.1f}", flush=True)
        if has_cuda:
            whole_clip_on_gpu(args.photo, preset, reference)
    return 0


def whole_clip_on_gpu(photo: Path, preset: Preset, frames: np.ndarray) -> None:
    """The clip with --device cuda against ffmpeg's 2D zoompan; NVENC against libx264."""
    options = ClipOptions(device="cuda")
    with tempfile.TemporaryDirectory() as scratch:
        result = make_clip(photo, Path(scratch) / "3d.mp4", preset, options, False)
        seconds_2d = zoompan_seconds(photo, preset, Path(scratch) / "2d.mp4")
        print(f"  {preset.name}: 3D clip on cuda {result.seconds:.2f} s "
              f"({result.stage_seconds}), 2D zoompan {seconds_2d:.2f} s, ratio "
              f"{result.seconds / seconds_2d:.2f}")
        for codec, encoder_preset in (("libx264", preset.encoder_preset), ("h264_nvenc", "p5")):
            trial = replace(preset, codec=codec, encoder_preset=encoder_preset)
            refusal = encoder_refusal(codec, preset.pix_fmt, encoder_preset, preset.crf)
            if refusal:
                print(f"  {codec}: not usable here ({refusal})")
                continue
            started = time.perf_counter()
            clip = frames[np.arange(preset.frames_total) % len(frames)]  # a clip's length
            count = encode_frames(Path(scratch) / f"{codec}.mp4", iter(clip), trial)
            seconds = time.perf_counter() - started
            print(f"  encode {count} frames {codec}: {seconds:.2f} s ({count / seconds:.0f} "
                  "frames/s)")


if __name__ == "__main__":
    sys.exit(main())
