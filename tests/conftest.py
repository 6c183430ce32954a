"""Shared fixtures: the real photos and models in ../shared, skipped with a reason when absent."""

from __future__ import annotations

import ctypes
import fcntl
import signal
import socket
import struct
from pathlib import Path

import numpy as np
import pytest

from kbbatch.presets import load_preset, with_overrides

CLONE_NEWNET = 0x40000000
SIOCGIFFLAGS, SIOCSIFFLAGS, IFF_UP = 0x8913, 0x8914, 0x1


def isolate_network() -> bool:
    """Put the test run (and every process it starts) in a network namespace of its own that
    has nothing but the loopback device. Ray rewrites 127.0.0.1 into the host's own interface
    address when it connects or starts a node; here that is 127.0.0.1 again, so the tests'
    clusters, daemons and web servers can only ever talk over loopback. Needs root (as on the
    development machines and CI); elsewhere the tests run as they are."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.unshare(CLONE_NEWNET) != 0:
        return False
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        request = struct.pack("16sH", b"lo", 0)
        flags = struct.unpack("16sH", fcntl.ioctl(probe, SIOCGIFFLAGS, request))[1]
        fcntl.ioctl(probe, SIOCSIFFLAGS, struct.pack("16sH", b"lo", flags | IFF_UP))
    return True


NETWORK_ISOLATED = isolate_network()  # at import: before any test starts a thread or a process


def hear_ctrl_c() -> None:
    """Started in the background of a shell without job control (`pytest ... &`), the run
    inherits SIGINT ignored, and so does every kbbatch it starts: each Ctrl-C test then found
    kbbatch deaf to it (7 failures). The tests are about a terminal's Ctrl-C: it is heard."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


hear_ctrl_c()  # at import, as above: the pytest-xdist workers and every process started inherit it

SHARED = Path(__file__).resolve().parents[2] / "shared"
PHOTOS = SHARED / "photos"


def shared_photos(count: int) -> list[Path]:
    if not PHOTOS.is_dir():
        pytest.skip(f"real photos not found at {PHOTOS} (../shared exists only for developers/CI)")
    photos = sorted(p for p in PHOTOS.iterdir() if p.suffix.lower() in (".jpg", ".png"))
    if len(photos) < count:
        pytest.skip(f"need {count} photos in {PHOTOS}, found {len(photos)}")
    return photos[:count]


@pytest.fixture
def quick_preset():
    """A small, short preset so that real clips encode in about a second."""
    return with_overrides(load_preset("preview"), duration_s=0.6, fps=10.0)


def textured_image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A smooth but distinctive colour texture (random noise would defeat video codecs)."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    channels = []
    for _ in range(3):
        fy, fx, phase = rng.uniform(0.02, 0.09, 2).tolist() + [rng.uniform(0, 6.28)]
        channels.append(127.5 + 120 * np.sin(rows * fy + cols * fx + phase))
    return np.stack(channels, axis=-1).astype(np.uint8)


@pytest.fixture(autouse=True)
def isolated_depth_cache(tmp_path_factory, monkeypatch):
    """Tests never read or write the user's depth cache."""
    monkeypatch.setenv("KBBATCH_CACHE", str(tmp_path_factory.mktemp("depth-cache")))


@pytest.fixture(autouse=True)
def signals_as_they_were():
    """What a test's in-process run did to this process's signal handling is undone: an
    entry point that ignores signals once stopped left the test process ignoring Ctrl-C and
    SIGTERM, and every batch the later tests started inherited that (it then ran through
    the Ctrl-C it was tested with)."""
    import signal

    numbers = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    handlers = {number: signal.getsignal(number) for number in numbers}
    yield
    for number, handler in handlers.items():
        if signal.getsignal(number) is not handler and handler is not None:
            signal.signal(number, handler)


def run_in_child(script: str, folder: Path) -> str:
    """Run a Python script in a fresh process with folder's bytes as sys.argv[1] (a name that
    is not UTF-8 reaches it as the OS gives it) and return its stdout; it must succeed."""
    import os
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", script, os.fsencode(folder)],
                          cwd=Path(__file__).resolve().parents[1], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout
