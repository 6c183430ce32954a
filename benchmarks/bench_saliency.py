"""ISNet, the depth stage's cost, against cheaper versions of it: how much faster, and how
much the pop-up cards change.

    KBBATCH_MODELS=../shared/models .venv/bin/python benchmarks/bench_saliency.py [--sizes 768 640]
        [--aspect] [--no-int8]

ISNet is most of the depth stage with the segmentation models (issue 10's goal: depth, plan
and fill within 3 s a photo on 2 cores). Its export fixes the input at 1024 px and casts to
fp16 around every layer. The variants, each built here in a temporary folder from the
cached model (needs the `onnx` package of the test extra):
- `any-N`: the graph with its traced resize sizes made relative to the input (the same
  output to the bit at 1024), run at N x N;
- `aspect-1024` (with --aspect): the same graph at 1024 on the long side and the photo's
  own aspect, fewer pixels for a photo that is not square;
- `int8`: fp32 weights, then onnxruntime's static QDQ quantisation (uint8 activations, int8
  weights, min/max ranges), calibrated on the even-numbered photos and scored on the odd
  ones only, so its score is on photos it never saw.
Per photo and variant: ISNet's seconds (the median of 2 runs after one warm-up) and the
share of working pixels whose pop-up disparity differs from the shipped model's by more
than 5 % (0 = the same cards).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from kbbatch import models, segment
from kbbatch.camera import working_size
from kbbatch.depth import DepthOptions, estimate_disparity
from kbbatch.images import read_image
from kbbatch.pipeline import resize_to

PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "photos"
MODEL = "isnet-dis-medium"
CHANGED = 0.05
"""Relative disparity change above which a pixel's card counts as changed."""


def any_size_graph(source: Path, target: Path) -> None:
    """ISNet with every traced constant resize size [h, w] (a power-of-two fraction of 1024)
    replaced by ceil(input / stride): its max-pools round up, so each level is that size."""
    import onnx
    from onnx import helper, numpy_helper

    model = onnx.load(str(source))
    graph = model.graph
    base = graph.input[0].type.tensor_type.shape.dim[2].dim_value
    constants = {node.output[0]: numpy_helper.to_array(node.attribute[0].t)
                 for node in graph.node if node.op_type == "Constant"}
    added = [helper.make_node("Shape", [graph.input[0].name], ["size/input"], start=2, end=4)]
    made: dict[int, str] = {}
    for node in graph.node:
        if node.op_type != "Concat":
            continue
        for index, name in enumerate(node.input):
            value = constants.get(name)
            if value is None or value.shape != (2,) or value[0] != value[1] \
                    or base % int(value[0]):
                continue
            stride = base // int(value[0])
            if stride not in made:
                made[stride] = f"size/{stride}"
                graph.initializer.extend([
                    numpy_helper.from_array(np.array([stride - 1] * 2, np.int64),
                                            f"size/{stride}/less"),
                    numpy_helper.from_array(np.array([stride] * 2, np.int64),
                                            f"size/{stride}/stride")])
                added += [helper.make_node("Add", ["size/input", f"size/{stride}/less"],
                                           [f"size/{stride}/sum"]),
                          helper.make_node("Div", [f"size/{stride}/sum",
                                                   f"size/{stride}/stride"], [made[stride]])]
            node.input[index] = made[stride]
    for value in [*graph.input, *graph.output]:
        for axis in (2, 3):
            value.type.tensor_type.shape.dim[axis].dim_param = f"side{axis}"
    del graph.value_info[:]
    nodes = [*added, *graph.node]
    del graph.node[:]
    graph.node.extend(nodes)
    onnx.save(model, str(target))


def fp32_graph(source: Path, target: Path) -> None:
    """The graph with its fp16 weights, constants and casts in fp32 (quantisation needs it)."""
    import onnx
    from onnx import TensorProto, numpy_helper

    model = onnx.load(str(source))
    graph = model.graph
    for index, tensor in enumerate(graph.initializer):
        if tensor.data_type == TensorProto.FLOAT16:
            graph.initializer[index].CopyFrom(numpy_helper.from_array(
                numpy_helper.to_array(tensor).astype(np.float32), tensor.name))
    for node in graph.node:
        for attribute in node.attribute:
            if node.op_type == "Cast" and attribute.name == "to" \
                    and attribute.i == TensorProto.FLOAT16:
                attribute.i = TensorProto.FLOAT
            if attribute.type == onnx.AttributeProto.TENSOR \
                    and attribute.t.data_type == TensorProto.FLOAT16:
                attribute.t.CopyFrom(numpy_helper.from_array(
                    numpy_helper.to_array(attribute.t).astype(np.float32), attribute.t.name))
    for value in [*graph.input, *graph.output, *graph.value_info]:
        if value.type.tensor_type.elem_type == TensorProto.FLOAT16:
            value.type.tensor_type.elem_type = TensorProto.FLOAT
    onnx.save(model, str(target))


def working_photo(path: Path) -> np.ndarray:
    photo = read_image(path)
    return resize_to(photo, *working_size(photo.shape[1], photo.shape[0]))


def int8_graph(fp32: Path, target: Path, calibration: list[Path]) -> None:
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    spec = models.REGISTRY[MODEL]

    class Photos(CalibrationDataReader):
        def __init__(self) -> None:
            self.left = iter(calibration)

        def get_next(self) -> dict | None:
            path = next(self.left, None)
            return None if path is None else {
                "input": models.prepare_input(spec, working_photo(path))}

    quantize_static(str(fp32), str(target), Photos(), quant_format=QuantFormat.QDQ,
                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                    calibrate_method=CalibrationMethod.MinMax)


def session_mask(path: Path, side: int, keep_aspect: bool = False
                 ) -> Callable[[np.ndarray], np.ndarray]:
    """A stand-in for segment.salient_mask running another graph at side x side, or with
    keep_aspect at side on the long side and the photo's aspect (in multiples of 32)."""
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = models.session_threads()
    options.enable_mem_pattern = False
    session = onnxruntime.InferenceSession(str(path), options,
                                           providers=["CPUExecutionProvider"])
    spec = models.REGISTRY[MODEL]

    def salient(image: np.ndarray) -> np.ndarray:
        height, width = image.shape[:2]
        size = (side, side)
        if keep_aspect:
            short = max(32, round(side * min(width, height) / max(width, height) / 32) * 32)
            size = (side, short) if width >= height else (short, side)
        batch = models.prepare_input(spec, image, size)
        output = session.run(None, {session.get_inputs()[0].name: batch})[0][0, 0]
        return cv2.resize(output.astype(np.float32), (image.shape[1], image.shape[0]),
                          interpolation=cv2.INTER_LINEAR)

    return salient


def seconds(salient: Callable[[np.ndarray], np.ndarray], image: np.ndarray) -> float:
    salient(image)
    runs = []
    for _ in range(2):
        started = time.perf_counter()
        salient(image)
        runs.append(time.perf_counter() - started)
    return statistics.median(runs)


def disparity_with(salient: Callable[[np.ndarray], np.ndarray], image: np.ndarray
                   ) -> np.ndarray:
    shipped = segment.salient_mask
    segment.salient_mask = salient
    try:
        return estimate_disparity(image, None, DepthOptions(backend="popup")).disparity
    finally:
        segment.salient_mask = shipped


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[768, 640])
    parser.add_argument("--aspect", action="store_true",
                        help="also the any-size graph at 1024 on the long side, aspect kept")
    parser.add_argument("--no-int8", action="store_true", help="skip the quantised variant")
    args = parser.parse_args()
    source = models.cached_path(MODEL)
    photos = sorted(p for p in PHOTOS.glob("*") if p.suffix.lower() in {".jpg", ".png"})
    if source is None or not photos:
        print(f"needs {MODEL} (KBBATCH_MODELS=../shared/models) and ../shared/photos")
        return 2
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        any_size_graph(source, folder / "any.onnx")
        variants = {f"any-{side}": session_mask(folder / "any.onnx", side)
                    for side in args.sizes}
        if args.aspect:
            variants["aspect-1024"] = session_mask(folder / "any.onnx", 1024, keep_aspect=True)
        if not args.no_int8:
            fp32_graph(source, folder / "fp32.onnx")
            int8_graph(folder / "fp32.onnx", folder / "int8.onnx", photos[0::2])
            variants["int8"] = session_mask(folder / "int8.onnx", 1024)
        print("| photo | shipped s | " + " | ".join(f"{name} s / changed" for name in variants)
              + " |")
        print("|---" * (2 + len(variants)) + "|")
        for number, path in enumerate(photos):
            image = working_photo(path)
            shipped = disparity_with(segment.salient_mask, image)
            cells = [path.name[:24], f"{seconds(segment.salient_mask, image):.2f}"]
            for name, salient in variants.items():
                if name == "int8" and number % 2 == 0:
                    cells.append("(calibration)")
                    continue
                changed = np.abs(disparity_with(salient, image) - shipped) > CHANGED * shipped
                cells.append(f"{seconds(salient, image):.2f} / {changed.mean():.4f}")
            print("| " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
