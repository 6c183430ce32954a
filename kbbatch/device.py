"""Which device renders the frames: the CPU (numba kernels) or a CUDA GPU (torch).

`--device cuda` is checked when a command starts, so that on a machine without a GPU it fails
at once with the reason, not at the first frame; `auto` is resolved by the process that renders
(a daemon worker, a cluster node), once. torch is an optional extra (`kbbatch[torch]`).
"""

from __future__ import annotations

import functools
import glob
import os
import sys

DEVICE_NAMES = ("auto", "cpu", "cuda")
"""`auto`: CUDA when torch sees a GPU, else the CPU."""

TORCH_CPU = "torch-cpu"
"""The GPU code path on torch's CPU device: how CI tests it and the benchmark compares it; not
offered by --device (the numba kernels are the faster CPU path)."""

DEVICE_ENV = "KBBATCH_DEVICE"
"""Default of --device, for a daemon or an executor started without command-line options."""


GPU_DRIVER_FILES = ("/dev/nvidia*", "/dev/dxg", "/dev/kfd", "/proc/driver/nvidia")
"""Files a Linux machine has where torch could see a GPU: NVIDIA's devices (also in a container
given a GPU), WSL 2's GPU device, ROCm's (AMD builds of torch answer torch.cuda too)."""


def gpu_driver_present() -> bool:
    """Whether a GPU driver could be there, without importing torch: that import costs 1.5 to
    2 s in every run and daemon worker, which `auto` on a machine without a GPU need not pay.
    Where it cannot be told from files (Windows), torch is asked."""
    if sys.platform == "darwin":  # no CUDA build of torch for macOS
        return False
    if os.name != "posix":
        return True
    return any(glob.glob(pattern) for pattern in GPU_DRIVER_FILES)


class DeviceError(ValueError):
    """A device that cannot be used here; the message says why and what to do."""


def cuda_available() -> tuple[bool, str]:
    """Whether torch sees a CUDA GPU, and if not, why.

    The check goes through NVML, not the CUDA runtime, so that the daemon's worker processes,
    forked after it, can still start CUDA themselves."""
    os.environ.setdefault("PYTORCH_NVML_BASED_CUDA_CHECK", "1")
    try:
        import torch
    except ImportError:
        return False, "torch is not installed (pip install 'kbbatch[torch]')"
    if not torch.cuda.is_available():
        build = f"CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        return False, f"torch {torch.__version__} ({build}) sees no CUDA GPU"
    return True, ""


def resolve_device(name: str) -> str:
    """`cpu` or `cuda` for a --device value; DeviceError when `cuda` cannot be had."""
    if name not in DEVICE_NAMES:
        raise DeviceError(f"unknown device {name!r}; choose one of {', '.join(DEVICE_NAMES)}")
    if name == "cpu" or (name == "auto" and not gpu_driver_present()):
        return "cpu"
    available, reason = cuda_available()
    if available:
        return "cuda"
    if name == "cuda":
        raise DeviceError(f"cannot render on cuda: {reason}; use --device cpu or auto")
    return "cpu"


def torch_device(device: str) -> str:
    """The torch device of a resolved device other than `cpu`."""
    return "cpu" if device == TORCH_CPU else device


@functools.cache
def frames_device(name: str) -> str:
    """The device this process renders frames on for a --device value: resolved where the
    frames are made (a daemon worker, a cluster node), once per process."""
    return name if name == TORCH_CPU else resolve_device(name)
