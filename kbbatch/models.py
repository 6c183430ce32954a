"""The model registry (what each network is, where it comes from, how to feed it) and the cache.

Nothing is downloaded on import or implicitly: `kbbatch models pull NAME` is the only way a
file enters the cache, and a file is kept only when its sha256 matches.
"""

from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)

MODELS_ENV = "KBBATCH_MODELS"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class ModelError(RuntimeError):
    pass


@dataclass(frozen=True)
class ModelSpec:
    """One network: identity, provenance and its input/output convention."""

    name: str
    filename: str
    role: str  # depth | salient | semantic | detector | inpaint
    licence: str
    url: str | None  # None: not published as a single file; place it in the cache by hand
    sha256: str | None  # None: no checksum known to us; `pull --sha256` pins the one you trust
    input_size: int  # side of the square input, or the target short side with size_multiple
    size_multiple: int = 0  # >0: keep the aspect, sides rounded to this multiple
    scale: float = 1 / 255  # pixel values are multiplied by this before mean/std
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    channels: str = "RGB"
    layout: str = "NCHW"
    output: str = ""  # what the first output means


REGISTRY: dict[str, ModelSpec] = {
    spec.name: spec
    for spec in (
        ModelSpec(
            "depth-anything-v2-small", "depth_anything_v2_small.onnx", "depth", "Apache-2.0",
            "https://huggingface.co/onnx-community/depth-anything-v2-small/resolve/main/onnx/model.onnx",
            None, input_size=518, size_multiple=14, mean=IMAGENET_MEAN, std=IMAGENET_STD,
            output="relative disparity (larger is nearer)",
        ),
        ModelSpec(
            "midas-v21-small", "midas_v21_small_256.onnx", "depth", "MIT",
            "https://github.com/isl-org/MiDaS/releases/download/v2_1/model-small.onnx",
            None, input_size=256, mean=IMAGENET_MEAN, std=IMAGENET_STD,
            output="relative inverse depth (larger is nearer)",
        ),
        ModelSpec(
            "isnet-dis-medium", "isnet_dis_medium.onnx", "salient",
            "ISNet/DIS weights, redistributed in the AGPL npm package "
            "@imgly/background-removal-data 1.4.5",
            None, "b6e8497ba978a6f5fbb647e419d2696cd80df5a23cb6a8ea532021911bd76acb",
            input_size=1024, scale=1 / 256, mean=(0.5, 0.5, 0.5),
            output="salient-object probability 0..1",
        ),
        ModelSpec(
            "deeplabv3-mnv2-pascal", "deeplabv3_mnv2_pascal_257.onnx", "semantic",
            "Apache-2.0 (TF-Lite DeepLabV3-MobileNetV2, converted)",
            None, "48a46b346ca7e2e96760b8a10a302046a3b5a9ce55e59d4c659c36d9cbd44118",
            input_size=257, scale=1 / 127.5, mean=(1.0, 1.0, 1.0), layout="NHWC",
            output="PASCAL VOC class scores (21)",
        ),
        ModelSpec(
            "yolox-nano", "yolox_nano_coco_416.onnx", "detector", "Apache-2.0 (Megvii YOLOX)",
            "https://github.com/Megvii-BaseDetection/YOLOX/releases/download/0.1.1rc0/yolox_nano.onnx",
            "695e750a5d5754bb5a8d5325643b59282191a7e7a564e435a415fd3c578eab14",
            input_size=416, scale=1.0, channels="BGR",
            output="COCO boxes, raw grid outputs (80 classes)",
        ),
        ModelSpec(
            "lama", "lama_fp32.onnx", "inpaint", "Apache-2.0", None, None,
            input_size=512, output="RGB image 0..255 (LaMa / MI-GAN convention: image + mask)",
        ),
    )
}


def models_dir() -> Path:
    """The cache folder: $KBBATCH_MODELS, else the user's cache dir."""
    override = os.environ.get(MODELS_ENV)
    if override:
        return Path(override).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("kbbatch")) / "models"


def cached_path(name: str) -> Path | None:
    """The cached file of a registered model, or None when it is not in the cache."""
    spec = REGISTRY[name]
    path = models_dir() / spec.filename
    return path if path.is_file() else None


def pull(spec: ModelSpec, directory: Path | None = None, sha256: str | None = None,
         progress: bool = True) -> Path:
    """Download a model into the cache, keeping it only if its sha256 is the expected one.

    The expected hash is the registry's, or the one given (for models we cannot pin).
    pooch downloads to a temporary file and moves it into place only when complete.
    """
    import pooch

    directory = directory or models_dir()
    expected = (sha256 or spec.sha256 or "").lower() or None
    if spec.url is None:
        raise ModelError(f"{spec.name} has no single-file download; put {spec.filename} "
                         f"in {directory} yourself")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:  # a file of that name, or no right to make it
        raise ModelError(f"{directory}: the model cache cannot be made there "
                         f"({error.strerror or error})") from error
    cached_before = (directory / spec.filename).is_file()
    try:
        path = Path(pooch.retrieve(
            spec.url, known_hash=f"sha256:{expected}" if expected else None,
            fname=spec.filename, path=directory, progressbar=progress,
        ))
    except ValueError as error:  # pooch's checksum mismatch
        raise ModelError(f"{spec.name}: download refused, sha256 mismatch ({error})") from error
    except Exception as error:
        raise ModelError(f"{spec.name}: download from {spec.url} failed ({error})") from error
    if expected is None and cached_before:  # the user's (or a --sha256 pull's): never removed
        return path
    if expected is None:
        from kbbatch.fingerprint import file_sha256

        actual = file_sha256(path)
        path.unlink()
        raise ModelError(
            f"{spec.name}: no checksum is registered for this file, so it was not kept. Its "
            f"sha256 is {actual}; if that is the file the publisher lists, run "
            f"`kbbatch models pull {spec.name} --sha256 {actual}`"
        )
    return path


PROVIDER_ENV = "KBBATCH_PROVIDER"
PROVIDER_NAMES = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider"}
"""Short names for $KBBATCH_PROVIDER; a full onnxruntime provider name works as well."""

REMOTE_PROVIDERS = ("AzureExecutionProvider",)
"""Providers onnxruntime lists as available that run no network on this machine: named in
$KBBATCH_PROVIDER, the report said the models ran on Azure while each ran on the CPU."""

_jobs_sharing_cores = 1


def share_cores(jobs: int) -> None:
    """Say that `jobs` processes share this machine's cores; called by a runner in each worker
    before the first session, so that N jobs run about `cores` threads, not N x cores."""
    global _jobs_sharing_cores
    _jobs_sharing_cores = max(1, jobs)
    _session.cache_clear()


def usable_cores() -> int:
    """Cores this process may run on (its affinity, which containers and taskset narrow)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def session_threads() -> int:
    """Intra-op threads of each session: this process's share of the cores."""
    return max(1, usable_cores() // _jobs_sharing_cores)


def check_models_dir() -> None:
    """A $KBBATCH_MODELS that is a file is refused; one that does not exist (a typo?) is said,
    as the run then has no networks."""
    folder = models_dir()
    if os.environ.get(MODELS_ENV):
        if folder.exists() and not folder.is_dir():
            raise ModelError(f"{MODELS_ENV}={folder}: a file, not a folder of models")
        if not folder.exists():
            log.warning("%s=%s: no such folder; running without any network", MODELS_ENV,
                        folder)


def check_cache() -> None:
    """Raise ModelError, naming the file, when a cached model cannot be used (cache_problem),
    or when $KBBATCH_PROVIDER names a provider this onnxruntime lacks. Checked once at start:
    found at each photo instead, the daemon filed every good photo as failed for a damaged
    download. The folder itself as check_models_dir."""
    check_models_dir()
    for spec in REGISTRY.values():  # said as "missing", the run went on without the network
        problem = no_file_problem(spec)
        if problem:
            raise ModelError(problem)
    cached = [(spec, cached_path(spec.name)) for spec in REGISTRY.values()]
    cached = [(spec, path) for spec, path in cached if path is not None]
    if cached or os.environ.get(PROVIDER_ENV, "").strip():  # set: meant, even with no model
        execution_provider()
    for spec, path in cached:
        problem = cache_problem(spec, path)
        if problem:
            raise ModelError(f"{path}: {problem}")


def no_file_problem(spec: ModelSpec) -> str | None:
    """What is wrong where something under a model's file name is no file (a folder, a pipe
    or a broken link), naming it; None where there is a file or nothing."""
    path = models_dir() / spec.filename
    if os.path.lexists(path) and not path.is_file():
        return (f"{path}: has model {spec.name}'s name but is no file (a folder, a pipe or a "
                f"broken link); {_remedy(spec)}")
    return None


def _remedy(spec: ModelSpec) -> str:
    if spec.url:
        return f"remove it, or run `kbbatch models pull {spec.name}`"
    return (f"remove it, or put the real {spec.filename} there (it has no single-file download; "
            "see the README's Models)")


def cache_problem(spec: ModelSpec, path: Path) -> str | None:
    """Why a cached model file cannot be used, or None: unreadable; not the registry's file
    (its sha256 pinned); or, with no checksum known, not loadable or not a network of its
    role (EXPECTED_TENSORS)."""
    try:
        stat = path.stat()
        actual = _sha256(path, stat.st_size, stat.st_mtime_ns)
    except OSError as error:
        return f"model {spec.name} cannot be read ({error.strerror or error})"
    if spec.sha256 is not None:
        if actual != spec.sha256.lower():
            return (f"not the file of model {spec.name} (sha256 {actual[:16]}..., expected "
                    f"{spec.sha256[:16]}...): damaged or another file; {_remedy(spec)}")
        return None
    other = next((o for o in REGISTRY.values() if o.sha256 and o.sha256.lower() == actual), None)
    if other is not None:  # its tensors can pass for the role's (ISNet's are a depth net's)
        return (f"the file of model {other.name} ({other.role}), not of {spec.name}; "
                f"{_remedy(spec)}")
    if spec.role not in EXPECTED_TENSORS:
        return None
    try:
        probe = _probe_session(path)
    except Exception as error:  # onnxruntime's own exception types, not exported
        first_line = (str(error).strip().splitlines() or [""])[0]
        return (f"model {spec.name} cannot be loaded, damaged or not an ONNX network "
                f"({first_line[:200]}); {_remedy(spec)}")
    problem = tensors_problem(spec, probe)
    del probe  # gone before the daemon forks its workers (see _probe_session)
    return problem


def _probe_session(path: Path):
    """A throwaway one-thread CPU session, to read a model's tensors. Not the cached one: a
    session with a thread pool alive in the daemon when it forked its workers left them
    hung at their first photo (seen with a depth network: no clip in 90 s, 0 % CPU)."""
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    return onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


EXPECTED_TENSORS: dict[str, tuple[tuple[tuple[int, ...], ...], tuple[tuple[int, ...], ...]]] = {
    "depth": (((1, 3, 0, 0),), ((1, 0, 0), (1, 1, 0, 0), (0, 0))),
    "inpaint": (((1, 3, 0, 0), (1, 1, 0, 0)), ((1, 3, 0, 0),)),
}
"""The tensors a network of an unpinned role must take and give, by role: the first inputs in
order (each one shape) and the first output (one of the shapes); 0 is any size. A file we hold no
checksum for is checked this way at start: another kind of network under the name (a segmenter
saved as the depth model) failed at every photo with onnxruntime's own words."""


def tensors_problem(spec: ModelSpec, created) -> str | None:
    """How a session's tensors differ from its role's, or None."""
    def fits(shape: list, wanted: tuple[int, ...]) -> bool:
        return len(shape) == len(wanted) and all(
            want == 0 or not isinstance(dim, int) or dim == want  # named dims are free
            for dim, want in zip(shape, wanted, strict=True))

    inputs_wanted, outputs_wanted = EXPECTED_TENSORS[spec.role]
    inputs, outputs = created.get_inputs(), created.get_outputs()
    given = [list(tensor.shape) for tensor in inputs]
    kind = f"not a {spec.role} network of {spec.name}'s kind"
    if len(inputs) < len(inputs_wanted) or not all(
            fits(shape, wanted) for shape, wanted in zip(given, inputs_wanted, strict=False)):
        return (f"{kind}: it takes {_shapes(given)}, expected {_shapes(inputs_wanted)}; "
                f"{_remedy(spec)}")
    gives = _shapes([list(outputs[0].shape)] if outputs else [])
    if not outputs or not any(fits(list(outputs[0].shape), shape) for shape in outputs_wanted):
        return (f"{kind}: it gives {gives}, expected {_shapes(outputs_wanted, ' or ')}; "
                f"{_remedy(spec)}")
    if not same_aspect(given[0][-2:], list(outputs[0].shape)[-2:]):
        # a detector's (1, 3549, 85) fits (1, N, N): an image of its input's shape does not
        return (f"{kind}: it gives {gives} for {_shapes(given[:1])}, not an image of the "
                f"input's shape; {_remedy(spec)}")
    return None


def same_aspect(input_hw: list, output_hw: list) -> bool:
    """Whether an output image, where both its size and the input's are fixed, has the input's
    height-to-width ratio (within a pixel of rounding: networks give a half or a quarter size)."""
    sizes = [*input_hw, *output_hw]
    if not all(isinstance(size, int) and size > 0 for size in sizes):
        return True  # a free size: known only when it runs
    in_h, in_w, out_h, out_w = sizes
    return abs(out_h * in_w - out_w * in_h) <= max(in_h, in_w)


def _shapes(shapes, joiner: str = ", ") -> str:
    """Shapes as people read them: a free size (named, unknown or 0) is N."""
    return joiner.join("(" + ", ".join(str(d) if isinstance(d, int) and d > 0 else "N"
                                     for d in shape) + ")" for shape in shapes) or "nothing"


def session_input_size(created, free_size: tuple[int, int]) -> tuple[int, int]:
    """(width, height) to feed a session's first (NCHW) input: a dimension its export fixes
    takes that size, a free one free_size's (an export with the height alone fixed passed the
    start-up check, then failed at every photo)."""
    height, width = list(created.get_inputs()[0].shape)[2:4]

    def fixed(value: object) -> int | None:
        return value if isinstance(value, int) and value > 0 else None

    return fixed(width) or free_size[0], fixed(height) or free_size[1]


@functools.cache
def _sha256(path: Path, size_bytes: int, mtime_ns: int) -> str:
    """A model file's sha256, once per process for a given size and time."""
    from kbbatch.fingerprint import file_sha256

    return file_sha256(path)


def execution_provider() -> str:
    """The onnxruntime provider: $KBBATCH_PROVIDER if set, else CUDA where the installed
    onnxruntime has it (the `onnxruntime-gpu` build), else CPU."""
    import onnxruntime

    available = onnxruntime.get_available_providers()
    wanted = os.environ.get(PROVIDER_ENV, "").strip()
    if not wanted:
        return PROVIDER_NAMES["cuda"] if PROVIDER_NAMES["cuda"] in available else \
            PROVIDER_NAMES["cpu"]
    provider = PROVIDER_NAMES.get(wanted.lower(), wanted)
    local = ", ".join(p for p in available if p not in REMOTE_PROVIDERS)
    if provider in REMOTE_PROVIDERS:  # listed as available, it runs nothing here
        raise ModelError(f"{PROVIDER_ENV}={wanted}: {provider} calls a remote endpoint, it "
                         f"runs no network on this machine; this onnxruntime offers {local}")
    if provider not in available:
        raise ModelError(f"{PROVIDER_ENV}={wanted}: this onnxruntime offers {local} (CUDA "
                         "needs the onnxruntime-gpu extra)")
    return provider


_providers_used: dict[str, str] = {}


def providers_used() -> dict[str, str]:
    """The model files this process ran, and the provider each session really runs on
    (onnxruntime falls back to the CPU when CUDA cannot start)."""
    return dict(_providers_used)


def session(path: Path):
    """An onnxruntime session for a model file, created once per process for each version of
    the file (a model pulled again while the daemon runs is the one used next), on the chosen
    provider and with this process's share of the cores."""
    stat = path.stat()
    return _session(path, stat.st_size, stat.st_mtime_ns)


@functools.cache
def _session(path: Path, size_bytes: int, mtime_ns: int):
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = session_threads()
    options.inter_op_num_threads = 1
    options.execution_mode = onnxruntime.ExecutionMode.ORT_SEQUENTIAL
    # The memory pattern is learnt over a session's first two runs, and one of them ran ISNet
    # in 3.2 s instead of 1.8 s (measured on the 2-core machine); without it every run after
    # the first took 1.8 s, with the same output to the bit.
    options.enable_mem_pattern = False
    provider = execution_provider()
    # CUDA sessions keep the CPU provider for the operators CUDA lacks.
    providers = [provider] if provider == PROVIDER_NAMES["cpu"] else [provider,
                                                                       PROVIDER_NAMES["cpu"]]
    created = onnxruntime.InferenceSession(str(path), options, providers=providers)
    _providers_used[path.name] = created.get_providers()[0]
    log.info("%s on %s, %d thread(s)", path.name, _providers_used[path.name],
             options.intra_op_num_threads)
    return created


def required_path(name: str) -> Path:
    """The cached file of a registered model; the error says how to get it."""
    path = cached_path(name)
    if path is None:
        raise ModelError(f"model {name} is not in {models_dir()}; run `kbbatch models pull "
                         f"{name}` (or set {MODELS_ENV})")
    return path


def load(name: str):
    """The session of a registered, cached model."""
    return session(required_path(name))


def prepare_input(spec: ModelSpec, image_rgb: np.ndarray, size: tuple[int, int] | None = None
                  ) -> np.ndarray:
    """Resize and normalise an RGB uint8 image as the model expects; returns a batch of one."""
    width, height = size or (spec.input_size, spec.input_size)
    resized = cv2.resize(image_rgb, (width, height), interpolation=cv2.INTER_AREA
                         if width < image_rgb.shape[1] else cv2.INTER_LINEAR)
    if spec.channels == "BGR":
        resized = resized[..., ::-1]
    data = (resized.astype(np.float32) * spec.scale - np.float32(spec.mean)) / np.float32(spec.std)
    if spec.layout == "NCHW":
        data = data.transpose(2, 0, 1)
    return np.ascontiguousarray(data[None], dtype=np.float32)


def input_size_for(spec: ModelSpec, width: int, height: int) -> tuple[int, int]:
    """The network input size for an image: square, or aspect kept on a size multiple."""
    if not spec.size_multiple:
        return spec.input_size, spec.input_size
    scale = spec.input_size / min(width, height)
    step = spec.size_multiple

    def rounded(value: float) -> int:
        return max(step, int(round(value * scale / step)) * step)

    return rounded(width), rounded(height)
