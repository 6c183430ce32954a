"""Throughput of the batch with the local executor and with Ray (1 and 2 worker processes).

    KBBATCH_MODELS=../shared/models .venv/bin/python benchmarks/bench_scale.py [--photos 4]

The same photos from ../shared/photos (originals, so the bytes moved are real) with the preview
preset, the depth cache off so that every run does all the work. Each configuration first makes
one untimed clip per worker (worker start, imports, networks loaded, JIT), then the timed batch.
Prints photos per minute, the mean clip time measured inside make_clip, Ray's overhead per photo
(driver wall time per photo minus the clip time, with one worker: object store, scheduling,
scratch files, writing the clip), and the bytes each clip moved between driver and worker (the
task's arguments and result, pickled: photo in and clip out, or with --ray-shared-fs, the row
`ray, 1 worker, shared fs`, only paths in and the ClipResult out).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from kbbatch.batch import RunReport, run_folder
from kbbatch.pipeline import ClipOptions
from kbbatch.presets import load_preset, with_overrides

SHARED_PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "photos"


def timed_batch(folder: Path, output: Path, preset, options: ClipOptions, executor
                ) -> tuple[float, RunReport]:
    started = time.perf_counter()
    report = run_folder(folder, output, preset, options, show_progress=False, force=True,
                        executor=executor)
    wall_s = time.perf_counter() - started
    if report.failed:
        sys.exit(f"failed: {[r.error for r in report.failed]}")
    return wall_s, report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", type=int, default=4)
    parser.add_argument("--preset", default="preview")
    parser.add_argument("--duration", type=float, help="override the preset's duration (s)")
    args = parser.parse_args()
    import ray

    from kbbatch.ray_executor import RayExecutor

    photos = sorted(p for p in SHARED_PHOTOS.glob("*") if p.suffix.lower() in (".jpg", ".png"))
    if len(photos) < args.photos + 2:
        sys.exit(f"need {args.photos + 2} photos in {SHARED_PHOTOS}")
    preset = with_overrides(load_preset(args.preset), duration_s=args.duration)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="kbbatch-bench-scale-") as scratch:
        work = Path(scratch)
        warm = {1: work / "warm-1", 2: work / "warm-2"}  # one photo per worker
        timed = work / "timed"
        for folder, chosen in ((warm[1], photos[-1:]), (warm[2], photos[-2:]),
                               (timed, photos[:args.photos])):
            folder.mkdir()
            for photo in chosen:
                shutil.copy(photo, folder / photo.name)
        rows = []
        for label, workers in (("local, 1 thread", 0), ("local, 2 threads", 0),
                               ("ray, 1 worker", 1), ("ray, 1 worker, shared fs", 1),
                               ("ray, 2 workers", 2)):
            threads = 2 if label == "local, 2 threads" else 1
            options = ClipOptions(threads=threads, cache_depth=False)
            executor, start_s, moved = None, 0.0, []
            if workers:
                clock = time.perf_counter()
                ray.init(address="local", num_cpus=workers, include_dashboard=False,
                         log_to_driver=False, object_store_memory=200_000_000)
                start_s = time.perf_counter() - clock
                executor = RayExecutor(cpus_per_clip=1, bytes_moved=moved,
                                       shared_fs=label.endswith("shared fs"))
            warm_s, _ = timed_batch(warm[max(1, workers)], work / f"out-warm-{len(rows)}", preset,
                                    options, executor)
            moved.clear()
            wall_s, report = timed_batch(timed, work / f"out-{len(rows)}", preset, options,
                                         executor)
            clip_s = sum(r.seconds for r in report.results) / len(report.results)
            rows.append((label, start_s, warm_s, wall_s, clip_s, moved[:]))
            if workers:
                ray.shutdown()
    print(f"{args.photos} photos from {SHARED_PHOTOS}, preset {preset.name} "
          f"({preset.width_px}x{preset.height_px}, {preset.duration_s} s), depth cache off; "
          f"{os.cpu_count()} cores, load average {load_before:.1f} before, "
          f"{os.getloadavg()[0]:.1f} after\n")
    print(f"{'executor':25} {'ray start s':>11} {'warm-up s':>9} {'batch s':>8} "
          f"{'photos/min':>10} {'clip s':>7} {'s/photo':>8} {'overhead s':>16} "
          f"{'kB moved/clip':>13}")
    for label, start_s, warm_s, wall_s, clip_s, moved in rows:
        per_photo = wall_s / args.photos
        overhead_s = per_photo - clip_s
        overhead = (f"{overhead_s:6.3f} ({100 * overhead_s / clip_s:4.1f} %)"
                    if label.startswith("ray, 1 worker") else f"{'':16}")
        kb = f"{sum(moved) / len(moved) / 1e3:13.1f}" if moved else f"{'':13}"
        print(f"{label:25} {start_s:11.1f} {warm_s:9.1f} {wall_s:8.1f} "
              f"{60 * args.photos / wall_s:10.1f} {clip_s:7.2f} {per_photo:8.2f} {overhead} {kb}")


if __name__ == "__main__":
    main()
