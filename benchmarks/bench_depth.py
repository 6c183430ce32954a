"""Depth quality over ../shared/eval/depth, per backend, with timings at 1024 px.

    KBBATCH_MODELS=../shared/models .venv/bin/python benchmarks/bench_depth.py

Each prediction is aligned to the ground truth by least-squares scale and shift (in depth
where metric depth exists, in disparity otherwise), then: rel, log10, RMS (metres, or
disparity pixels), delta < 1.25^i, and depth-edge accuracy / completeness (mean distance in
pixels from predicted to true depth edges and back). Paper, NYU v2: rel 0.08, log10 0.03,
RMS 0.30, delta1 0.94; iBims-1 edge accuracy 2.02 px, completeness 5.44 px.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from kbbatch.camera import working_size
from kbbatch.depth import DepthOptions, SceneContext, estimate_disparity
from kbbatch.depth.onnx import DEPTH_MODELS
from kbbatch.depth.popup import popup_disparity
from kbbatch.images import read_image
from kbbatch.models import cached_path

EVAL = Path(__file__).resolve().parents[2] / "shared" / "eval" / "depth"
EDGE_CANNY = (30, 80)


def samples() -> list[Path]:
    return sorted(p.parent for p in EVAL.glob("*/*/meta.json"))


def ground_truth(sample: Path) -> tuple[np.ndarray, str]:
    """(values, space): metric depth in metres, or disparity in pixels; 0 marks invalid."""
    depth_png = sample / "depth_mm.png"
    if depth_png.is_file():
        return cv2.imread(str(depth_png), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000, "depth"
    return np.load(sample / "disp.npy").astype(np.float64), "disparity"


def align(prediction_disparity: np.ndarray, truth: np.ndarray, space: str, valid: np.ndarray
          ) -> np.ndarray:
    """Least-squares scale and shift of the prediction, in the truth's space."""
    predicted = prediction_disparity if space == "disparity" else 1.0 / np.maximum(
        prediction_disparity, 1e-3)
    a = np.stack([predicted[valid], np.ones(valid.sum())], axis=1)
    (scale, shift), *_ = np.linalg.lstsq(a, truth[valid], rcond=None)
    floor = truth[valid].min() * 0.1
    return np.maximum(scale * predicted + shift, floor)


def edges(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    log_values = np.log(np.maximum(values, 1e-6))
    low, high = np.percentile(log_values[valid], (1, 99))
    scaled = np.clip((log_values - low) / max(high - low, 1e-6) * 255, 0, 255).astype(np.uint8)
    return (cv2.Canny(scaled, *EDGE_CANNY) > 0) & valid


def edge_distance(source: np.ndarray, target: np.ndarray) -> float:
    if not source.any() or not target.any():
        return float("nan")
    distance = cv2.distanceTransform((~target).astype(np.uint8), cv2.DIST_L2, 5)
    return float(distance[source].mean())


def metrics(prediction: np.ndarray, truth: np.ndarray, space: str) -> dict[str, float]:
    valid = truth > 0
    aligned = align(prediction, truth, space, valid)
    p, g = aligned[valid], truth[valid]
    ratio = np.maximum(p / g, g / p)
    predicted_edges, true_edges = edges(aligned, valid), edges(truth, valid)
    return {
        "rel": float(np.mean(np.abs(p - g) / g)),
        "log10": float(np.mean(np.abs(np.log10(p) - np.log10(g)))),
        "rms": float(np.sqrt(np.mean((p - g) ** 2))),
        **{f"d{i}": float(np.mean(ratio < 1.25**i)) for i in (1, 2, 3)},
        "edge_acc_px": edge_distance(predicted_edges, true_edges),
        "edge_comp_px": edge_distance(true_edges, predicted_edges),
    }


def popup_without_cards(image: np.ndarray) -> np.ndarray:
    return popup_disparity(image, [])


def backends() -> dict[str, Callable[[np.ndarray], np.ndarray]]:
    def via(options: DepthOptions) -> Callable[[np.ndarray], np.ndarray]:
        return lambda image: estimate_disparity(image, None, options).disparity

    rows = {
        "ramp (vertical prior)": via(DepthOptions(backend="ramp")),
        "popup, no cards": popup_without_cards,
        "popup (horizon, cards)": via(DepthOptions(backend="popup")),
    }
    for model in DEPTH_MODELS:
        if cached_path(model):
            rows[f"onnx {model}, plain"] = via(DepthOptions("onnx", model, False, False))
            rows[f"onnx {model}, adjusted+refined"] = via(DepthOptions("onnx", model))
    return rows


REFINE_FACTOR = 4


def refinement_rows() -> None:
    """Refinement against plain bilinear upsampling: the truth, downsampled 4x, brought back up
    guided by the photo, scored against the truth at full size."""
    from kbbatch.depth.refine import refine

    print(f"\nupsampling the truth from 1/{REFINE_FACTOR} size (disparity space, valid pixels)")
    print(f"{'method':<20}{'rel':>10}{'edge_acc_px':>13}{'edge_comp_px':>14}")
    scores: dict[str, list[list[float]]] = {"bilinear": [], "refine (ours)": []}
    for sample in samples():
        truth, space = ground_truth(sample)
        disparity = 1.0 / np.where(truth > 0, truth, np.inf) if space == "depth" else truth
        valid = truth > 0
        if valid.mean() < 0.5:
            continue  # sparse ground truth (KITTI) says nothing about edges
        image = read_image(next(sample.glob("rgb.*")))
        filled = cv2.inpaint(disparity.astype(np.float32), (~valid).astype(np.uint8), 3,
                             cv2.INPAINT_NS)
        height, width = filled.shape
        small = cv2.resize(filled, (width // REFINE_FACTOR, height // REFINE_FACTOR),
                           interpolation=cv2.INTER_AREA)
        candidates = {
            "bilinear": cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR),
            "refine (ours)": refine(small, image),
        }
        true_edges = edges(disparity, valid)
        for name, upsampled in candidates.items():
            rel = float(np.mean(np.abs(upsampled[valid] - disparity[valid]) / disparity[valid]))
            predicted_edges = edges(np.maximum(upsampled, 1e-6), valid)
            scores[name].append([rel, edge_distance(predicted_edges, true_edges),
                                 edge_distance(true_edges, predicted_edges)])
    for name, rows in scores.items():
        rel, accuracy, completeness = np.nanmean(rows, axis=0)
        print(f"{name:<20}{rel:>10.4f}{accuracy:>13.2f}{completeness:>14.2f}")


def main() -> int:
    if not EVAL.is_dir():
        print(f"evaluation data not found at {EVAL} (../shared is developer/CI only)")
        return 2
    results: dict[str, list[dict[str, float]]] = {}
    seconds: dict[str, list[float]] = {}
    for sample in samples():
        rgb = next(sample.glob("rgb.*"))
        image = read_image(rgb)
        truth, space = ground_truth(sample)
        width, height = working_size(image.shape[1], image.shape[0])
        working = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
        SceneContext(working)  # models load lazily inside the first timed backend
        for name, backend in backends().items():
            started = time.perf_counter()
            prediction = backend(working)
            seconds.setdefault(name, []).append(time.perf_counter() - started)
            prediction = cv2.resize(prediction, (truth.shape[1], truth.shape[0]),
                                    interpolation=cv2.INTER_LINEAR)
            row = metrics(np.maximum(prediction, 1e-3), truth, space)
            row["sample"] = f"{sample.parent.name}/{sample.name}"
            results.setdefault(name, []).append(row)
    columns = ("rel", "log10", "rms", "d1", "d2", "d3", "edge_acc_px", "edge_comp_px")
    print(f"{len(samples())} samples; mean over samples (RMS mixes metres and disparity px)")
    print(f"{'backend':<34}" + "".join(f"{c:>13}" for c in columns) + f"{'s/image':>10}")
    for name, rows in results.items():
        cells = []
        for column in columns:
            values = [r[column] for r in rows if not np.isnan(r[column])]
            cells.append(f"{np.mean(values):>13.3f}" if values else f"{'n/a':>13}")
        print(f"{name:<34}" + "".join(cells) + f"{np.median(seconds[name]):>10.2f}")
    print("n/a: the map has no depth edges to compare")
    refinement_rows()
    if "--json" in sys.argv:
        print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
