"""The batch on a real Ray cluster started here: a head node and a second node process on the
loopback address, each with one CPU and a small object store. No mocks: the drivers are real
`kbbatch --executor ray` processes, the faults are real SIGKILLs by process id."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from kbbatch.batch import REPORT_NAME, run_folder
from kbbatch.encode import decode_frames, palindrome_order, probe
from kbbatch.journal import JOURNAL_NAME
from kbbatch.pipeline import SCRATCH_PREFIX, ClipOptions
from kbbatch.presets import load_preset, with_overrides
from kbbatch.ray_executor import RayExecutor

from .conftest import shared_photos

ray = pytest.importorskip("ray", reason='Ray is not installed: pip install "kbbatch[ray]"')

pytestmark = pytest.mark.ray

PHOTO_WIDTH_PX = 320
DURATION_S, FPS = 0.6, 10.0
OBJECT_STORE_BYTES = 200_000_000
TASK_NAME = "ray::make_clip_from_bytes"


def free_port() -> int:
    with socket.socket() as probe_socket:
        probe_socket.bind(("127.0.0.1", 0))
        return probe_socket.getsockname()[1]


def processes() -> dict[int, tuple[int, str]]:
    """pid -> (parent pid, command line) of every process (Linux /proc)."""
    table = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        table[int(entry.name)] = (parent, command)
    return table


def descendants(roots: set[int], table: dict[int, tuple[int, str]]) -> set[int]:
    found = set(roots)
    grew = True
    while grew:
        more = {pid for pid, (parent, _) in table.items() if parent in found} - found
        found |= more
        grew = bool(more)
    return found


def kill_all(pids: set[int], sig: int = signal.SIGKILL) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, sig)


class LocalCluster:
    """`ray start` twice on 127.0.0.1 in a temporary folder; stopped by killing its processes by
    pid (never `ray stop`, which would stop every Ray on a shared machine)."""

    def __init__(self, depth_cache: Path) -> None:
        self.temp_dir = Path(tempfile.mkdtemp(prefix="kbray-", dir="/tmp"))  # short socket paths
        self.port = free_port()
        self.node_port = free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.env = dict(os.environ, RAY_AUTH_MODE="disabled", KBBATCH_CACHE=str(depth_cache),
                        RAY_health_check_period_ms="500",
                        RAY_health_check_failure_threshold="10")  # 5 s: the loaded machine
        self.env.pop("RAY_ADDRESS", None)
        self.ray = str(Path(sys.executable).with_name("ray"))
        common = ["--node-ip-address=127.0.0.1", "--num-cpus=1",
                  f"--object-store-memory={OBJECT_STORE_BYTES}", "--disable-usage-stats",
                  f"--temp-dir={self.temp_dir}"]
        self.start([self.ray, "start", "--head", f"--port={self.port}",
                    "--include-dashboard=false", *common])
        self.start([self.ray, "start", f"--address={self.address}",
                    f"--node-manager-port={self.node_port}", *common])

    def start(self, command: list[str]) -> None:
        done = subprocess.run(command, env=self.env, capture_output=True, text=True, timeout=120)
        if done.returncode != 0:
            self.stop()
            raise RuntimeError(f"{' '.join(command)} failed:\n{done.stdout}\n{done.stderr}")

    def second_node_raylet(self) -> int:
        marker = f"--node_manager_port={self.node_port}"
        return next(pid for pid, (_, command) in processes().items()
                    if "raylet" in command and marker in command)

    def second_node_clip_task(self) -> int | None:
        """The pid of a second-node worker that is making a clip right now, if any."""
        table = processes()
        workers = descendants({self.second_node_raylet()}, table)
        return next((pid for pid in workers if table[pid][1].startswith(TASK_NAME)), None)

    def kill_second_node(self) -> None:
        kill_all(descendants({self.second_node_raylet()}, processes()))

    def stop(self) -> None:
        table = processes()
        ours = {pid for pid, (_, command) in table.items() if str(self.temp_dir) in command}
        everything = descendants(ours, table)
        kill_all(everything, signal.SIGTERM)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and any(Path(f"/proc/{p}").exists() for p in everything):
            time.sleep(0.2)
        kill_all(everything)
        shutil.rmtree(self.temp_dir, ignore_errors=True)


@pytest.fixture(scope="module")
def photo_folder(tmp_path_factory) -> Path:
    """Four downscaled copies of shared photos (a clip in a second or two) and a corrupt one."""
    folder = tmp_path_factory.mktemp("ray-photos")
    for photo in shared_photos(4):
        image = cv2.imread(str(photo))
        height = round(image.shape[0] * PHOTO_WIDTH_PX / image.shape[1]) // 2 * 2
        small = cv2.resize(image, (PHOTO_WIDTH_PX, height), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(folder / f"{photo.stem}.png"), small)
    return folder


@pytest.fixture(scope="module")
def cluster(tmp_path_factory, photo_folder):
    running = LocalCluster(tmp_path_factory.mktemp("ray-depth-cache"))
    yield running
    running.stop()


def kbbatch_command(folder: Path, output: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "kbbatch", str(folder), "-o", str(output), "-p", "preview",
            "--duration", str(DURATION_S), "--fps", str(FPS), "--quiet", "--executor", "ray",
            *extra]


def run_kbbatch(cluster: LocalCluster, folder: Path, output: Path, *extra: str
                ) -> subprocess.CompletedProcess:
    env = dict(cluster.env, RAY_ADDRESS=cluster.address)
    return subprocess.run(kbbatch_command(folder, output, *extra), env=env, capture_output=True,
                          text=True, timeout=150)


def start_driver(cluster: LocalCluster, folder: Path, output: Path) -> subprocess.Popen:
    env = dict(cluster.env, RAY_ADDRESS=cluster.address)
    return subprocess.Popen(kbbatch_command(folder, output), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def while_running(driver: subprocess.Popen, condition, timeout_s: float = 120.0):
    """Poll condition() until it is true, the driver still running (the fault is mid-batch)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert driver.poll() is None, "the driver finished before the fault"
        if found := condition():
            return found
        time.sleep(0.02)
    raise AssertionError("timed out waiting for the batch")


def journal_rows(output: Path) -> dict[str, tuple[str, int]]:
    """photo name -> (state, attempts) from the journal (which keys jobs by the photo's path)."""
    with sqlite3.connect(output / JOURNAL_NAME) as connection:
        rows = connection.execute("SELECT source, state, attempts FROM jobs").fetchall()
    return {Path(source).name: (state, attempts) for source, state, attempts in rows}


def assert_complete_clips(output: Path, photos: list[Path]) -> None:
    """One whole clip per photo and nothing else: no partial or temporary file."""
    assert sorted(p.name for p in output.iterdir() if not p.name.startswith(".kbbatch-journal")
                  and p.name != REPORT_NAME) == sorted(f"{p.stem}.mp4" for p in photos)
    preset = quick_preset()
    frames = len(palindrome_order(preset.frames_forward))
    for photo in photos:
        clip = output / f"{photo.stem}.mp4"
        assert probe(clip).width_px == preset.width_px  # a whole file that ffmpeg reads
        assert sum(1 for _ in decode_frames(clip, preset.width_px, preset.height_px)) == frames


def psnr_db(first: np.ndarray, second: np.ndarray) -> float:
    error = np.mean((first.astype(np.float64) - second.astype(np.float64)) ** 2)
    return float("inf") if error == 0 else 10 * np.log10(255.0**2 / error)


@pytest.fixture(scope="module")
def reference(photo_folder, tmp_path_factory) -> tuple[Path, Path, list[Path]]:
    """A folder of three photos and a corrupt one, its clips by the local executor (the
    reference for every executor), and the three photos."""
    photos = sorted(photo_folder.iterdir())[:3]
    folder = tmp_path_factory.mktemp("reference") / "in"
    folder.mkdir()
    for photo in photos:
        (folder / photo.name).write_bytes(photo.read_bytes())
    (folder / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg" * 50)
    local = folder.parent / "local"
    with pytest.MonkeyPatch.context() as env:  # the user's depth cache stays untouched
        env.setenv("KBBATCH_CACHE", str(tmp_path_factory.mktemp("reference-depth-cache")))
        report = run_folder(folder, local, quick_preset(), ClipOptions(threads=1),
                            show_progress=False)
    assert [Path(r.source).name for r in report.failed] == ["broken.jpg"]
    return folder, local, photos


def quick_preset():
    return with_overrides(load_preset("preview"), duration_s=DURATION_S, fps=FPS)


def assert_same_clips(ours: Path, theirs: Path, photos: list[Path]) -> None:
    """Each photo's clip in ours equals the one in theirs: bit for bit, or every frame at
    60 dB PSNR or more."""
    preset = quick_preset()
    for photo in photos:
        mine, reference_clip = ours / f"{photo.stem}.mp4", theirs / f"{photo.stem}.mp4"
        if mine.read_bytes() == reference_clip.read_bytes():
            continue
        width, height = preset.width_px, preset.height_px
        for a, b in zip(decode_frames(mine, width, height),
                        decode_frames(reference_clip, width, height), strict=True):
            assert psnr_db(a, b) >= 60.0, photo.name


def test_ray_clips_equal_the_local_ones_and_a_corrupt_photo_fails_alone(
        cluster, reference, tmp_path):
    folder, local, photos = reference

    done = run_kbbatch(cluster, folder, tmp_path / "ray", "--ray-address", cluster.address)

    assert done.returncode == 1, done.stderr  # the corrupt photo failed, the batch went on
    assert "broken.jpg" in done.stderr and str(folder / "broken.jpg") in done.stderr
    report = json.loads((tmp_path / "ray" / REPORT_NAME).read_text())
    states = {Path(clip["source"]).name: clip["status"] for clip in report["clips"]}
    assert states == {p.name: "done" for p in photos} | {"broken.jpg": "failed"}
    assert_complete_clips(tmp_path / "ray", photos)
    assert {s: a for s, (_, a) in journal_rows(tmp_path / "ray").items()} == {
        p.name: 1 for p in photos} | {"broken.jpg": 1}
    assert_same_clips(tmp_path / "ray", local, photos)


SHARED_FS_BYTES_PER_CLIP = 16_000
"""Paths, settings and a ClipResult: a few kB. Any photo or clip here is larger."""


def test_with_a_shared_file_system_only_paths_travel_and_the_clips_equal_the_local_ones(
        cluster, reference, tmp_path, monkeypatch):
    """The driver in this process, so that the executor's bytes_moved can be read."""
    folder, local, photos = reference
    for name, value in cluster.env.items():
        if name.startswith("RAY_"):
            monkeypatch.setenv(name, value)
    moved: list[int] = []
    executor = RayExecutor(cluster.address, shared_fs=True, bytes_moved=moved)
    try:
        report = run_folder(folder, tmp_path / "ray", quick_preset(), ClipOptions(threads=1),
                            show_progress=False, executor=executor)
    finally:
        ray.shutdown()

    states = {Path(r.source).name: r.status for r in report.results}
    assert states == {p.name: "done" for p in photos} | {"broken.jpg": "failed"}
    assert_complete_clips(tmp_path / "ray", photos)
    assert {s: a for s, (_, a) in journal_rows(tmp_path / "ray").items()} == {
        p.name: 1 for p in photos} | {"broken.jpg": 1}  # each made once
    assert_same_clips(tmp_path / "ray", local, photos)
    smallest_file = min(p.stat().st_size for p in [*photos, *(tmp_path / "ray").glob("*.mp4")])
    assert len(moved) == len(photos) + 1  # the corrupt photo, too, failed on a worker
    assert max(moved) < min(SHARED_FS_BYTES_PER_CLIP, smallest_file), moved


def test_with_ray_shared_fs_a_photo_the_workers_cannot_see_fails_naming_node_and_path(
        cluster, photo_folder, tmp_path):
    """The photo's folder is a file system mounted in the driver's own mount namespace (as a
    disk mounted on the driver's machine alone would be): the driver lists and reads it, and
    on every worker that folder is empty. (It was /proc/self/fd/N, a directory the driver
    held open; the journal now keys photos by their folder resolved, which that is not.)"""
    folder = tmp_path / "driver-only"
    folder.mkdir()
    photo = sorted(photo_folder.iterdir())[0]
    inside = " ".join(shlex.quote(part) for part in kbbatch_command(
        folder, tmp_path / "out", "--ray-shared-fs"))
    script = (f"mount -t tmpfs tmpfs {shlex.quote(str(folder))} && "
              f"cp {shlex.quote(str(photo))} {shlex.quote(str(folder))}/ && exec {inside}")
    env = dict(cluster.env, RAY_ADDRESS=cluster.address)
    probe = subprocess.run(["unshare", "--mount", "--propagation", "private", "true"],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"no mount namespace of its own here: {probe.stderr.strip()}")
    done = subprocess.run(["unshare", "--mount", "--propagation", "private", "sh", "-c", script],
                          env=env, capture_output=True, text=True, timeout=150)

    assert done.returncode == 1, done.stderr
    path = f"{folder}/{photo.name}"
    assert re.search(rf"{re.escape(path)}: not found on Ray node \S+ \(id [0-9a-f]{{12}}\)",
                     done.stderr), done.stderr
    assert "--ray-shared-fs needs the photos" in done.stderr
    report = json.loads((tmp_path / "out" / REPORT_NAME).read_text())
    assert [(c["source"], c["status"]) for c in report["clips"]] == [(path, "failed")]
    assert not list((tmp_path / "out").glob("*.mp4"))
    assert journal_rows(tmp_path / "out") == {photo.name: ("failed", 1)}
    assert not list(folder.iterdir()), "the driver's mount was seen outside its namespace"


def done_clips(output: Path) -> set[str]:
    """Clips the journal records as finished (none while the driver is still creating it)."""
    if not (output / JOURNAL_NAME).is_file():
        return set()
    try:
        rows = journal_rows(output)
    except sqlite3.OperationalError:  # its table not created yet
        return set()
    return {Path(source).stem + ".mp4" for source, (state, _) in rows.items() if state == "done"}


def test_a_killed_driver_is_rerun_without_redoing_or_losing_a_clip(
        cluster, photo_folder, tmp_path):
    photos = sorted(photo_folder.iterdir())
    output = tmp_path / "out"
    driver = start_driver(cluster, photo_folder, output)
    while_running(driver, lambda: done_clips(output))
    driver.send_signal(signal.SIGKILL)
    driver.communicate()
    # A clip renamed into place just before the kill, but not yet journaled as done, is made
    # again by the rerun (nothing lost); the journal says which clips count as finished.
    first = {name: (output / name).stat().st_mtime_ns for name in done_clips(output)}
    assert 0 < len(first) < len(photos), "killed mid-batch"
    # the report is the one written as the run started: unfinished
    assert json.loads((output / REPORT_NAME).read_text())["finished_at"] is None

    rerun = run_kbbatch(cluster, photo_folder, output)

    assert rerun.returncode == 0, rerun.stderr
    report = json.loads((output / REPORT_NAME).read_text())
    states = {Path(clip["source"]).stem + ".mp4": clip["status"] for clip in report["clips"]}
    assert {n for n, s in states.items() if s == "skipped"} == set(first)
    assert {n for n, s in states.items() if s == "done"} == {
        f"{p.stem}.mp4" for p in photos} - set(first)
    assert {n: output.joinpath(n).stat().st_mtime_ns for n in first} == first  # not redone
    assert_complete_clips(output, photos)
    assert all(state == "done" for state, _ in journal_rows(output).values())


def test_ctrl_c_cancels_the_outstanding_clips_and_exits_non_zero(cluster, photo_folder, tmp_path):
    output = tmp_path / "out"
    driver = start_driver(cluster, photo_folder, output)
    while_running(driver, cluster.second_node_clip_task)
    driver.send_signal(signal.SIGINT)
    stdout, stderr = driver.communicate(timeout=30)

    assert driver.returncode == 130, stderr  # the batch's exit status when interrupted
    assert "interrupted" in stderr
    assert not [p for p in output.iterdir() if ".part" in p.name]
    assert all(state != "done" or (output / f"{Path(source).stem}.mp4").is_file()
               for source, (state, _) in journal_rows(output).items())
    deadline = time.monotonic() + 15  # the cancelled clips stop on the workers
    while cluster.second_node_clip_task() is not None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert cluster.second_node_clip_task() is None


def test_sigterm_finishes_the_clips_in_progress_and_says_so(cluster, photo_folder, tmp_path):
    """Ray's driver put in its own SIGTERM handler: the batch died at once (exit 1 or 134,
    Ray's C++ stack dump, no summary, stopped_by null), its clip in progress unfinished."""
    output = tmp_path / "out"
    driver = start_driver(cluster, photo_folder, output)
    while_running(driver, cluster.second_node_clip_task)
    driver.send_signal(signal.SIGTERM)
    stdout, stderr = driver.communicate(timeout=120)
    assert driver.returncode == 130, stderr
    assert "SIGTERM received" not in stderr  # Ray's own handler's dump
    report = json.loads((output / REPORT_NAME).read_text())
    assert report["stopped_by"] == "SIGTERM"
    assert not [p for p in output.iterdir() if ".part" in p.name]
    assert any(state == "done" for state, _ in journal_rows(output).values())


def test_the_daemon_on_ray_with_a_shared_fs_makes_every_arrival_and_stops_on_sigterm(
        cluster, photo_folder, tmp_path):
    """With --ray-shared-fs (the inbox and outbox are seen by both nodes): the daemon's pool
    hands its jobs to the executor as the batch does, whose copying mode the batch tests
    cover, so this one covers the clips written in place by workers for the daemon."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    photos = sorted(photo_folder.iterdir())[:3]
    command = [sys.executable, "-m", "kbbatch", "watch", str(inbox), "--out", str(outbox),
               "-p", "preview", "--settle", "0.5", "--jobs", "2", "--executor", "ray",
               "--ray-shared-fs"]
    env = dict(cluster.env, RAY_ADDRESS=cluster.address)
    daemon = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
    for photo in photos:
        (inbox / photo.name).write_bytes(photo.read_bytes())
    (inbox / "broken.jpg").write_bytes(b"not a photo at all" * 100)
    arrived = {p.name for p in photos} | {"broken.jpg"}
    handled = lambda: {p.name for p in inbox.glob("*/*") if p.suffix != ".json"}  # noqa: E731
    while_running(daemon, lambda: handled() == arrived, timeout_s=150)
    daemon.send_signal(signal.SIGTERM)
    log, _ = daemon.communicate(timeout=60)

    assert daemon.returncode == 0, log
    assert sorted(p.name for p in (inbox / "done").iterdir()) == sorted(p.name for p in photos)
    assert (inbox / "failed" / "broken.jpg").is_file()
    assert sorted(p.name for p in outbox.glob("*.mp4")) == sorted(f"{p.stem}.mp4" for p in photos)
    assert journal_rows(outbox) == {p.name: ("done", 1) for p in photos} | {
        "broken.jpg": ("failed", 1)}


def test_a_worker_node_killed_mid_clip_has_its_photo_made_elsewhere_once(
        cluster, photo_folder, tmp_path):
    """Runs last in this module: the second node stays dead."""
    photos = sorted(photo_folder.iterdir())
    output = tmp_path / "out"
    driver = start_driver(cluster, photo_folder, output)
    busy = while_running(driver, cluster.second_node_clip_task)
    cluster.kill_second_node()
    time.sleep(0.5)
    assert not processes().get(busy, (0, ""))[1].startswith(TASK_NAME), "the clip was killed"

    stdout, stderr = driver.communicate(timeout=150)

    assert driver.returncode == 0, stderr
    report = json.loads((output / REPORT_NAME).read_text())
    assert sorted(clip["status"] for clip in report["clips"]) == ["done"] * len(photos)
    assert_complete_clips(output, photos)
    assert journal_rows(output) == {p.name: ("done", 1) for p in photos}  # recorded once each
    # the killed worker's scratch folder was removed by a later clip on this machine
    assert not list(Path(tempfile.gettempdir()).glob(f"{SCRATCH_PREFIX}{busy}-*"))


def test_a_manifest_entrys_preset_file_travels_loaded_to_a_worker_that_cannot_see_it(
        tmp_path, monkeypatch):
    """The entry's preset file lies beside the manifest on the driver; a worker (another
    machine, or a scratch folder) looked for it where it runs. Run through the task function
    itself, from another folder, after the file is gone: no cluster needed to see it."""
    from PIL import Image

    from kbbatch.depth import DepthOptions
    from kbbatch.encode import read_clip_mark
    from kbbatch.fingerprint import file_sha256
    from kbbatch.manifest import load_manifest
    from kbbatch.pipeline import ClipJob, clip_fingerprints
    from kbbatch.ray_executor import make_clip_from_bytes

    from .conftest import textured_image

    Image.fromarray(textured_image(180, 320)).save(tmp_path / "a.jpg")
    look = tmp_path / "m" / "look.toml"
    look.parent.mkdir()
    look.write_text('base = "preview"\nwidth_px = 256\nheight_px = 144\nfps = 10\n'
                    'duration_s = 0.4\n')
    ramp = np.tile(np.linspace(1000, 60000, 320).astype(np.uint16), (180, 1))
    cv2.imwrite(str(tmp_path / "m" / "a-map.depth.png"), ramp)
    (tmp_path / "m" / "manifest.json").write_text(
        '{"version": 1, "images": {"a.jpg": {"preset": "look.toml", "duration_s": 0.3, '
        '"depth": "a-map.depth.png"}}}')
    entry = load_manifest(tmp_path / "m" / "manifest.json").entry("a.jpg")
    sent = []

    class RemoteClip:  # what Ray's remote function receives
        def remote(self, *arguments):
            sent.append(arguments)
            return "ref"

    options = ClipOptions(planner="center", depth=DepthOptions(backend="ramp"))
    job = ClipJob(tmp_path / "a.jpg", tmp_path / "out" / "a.mp4", entry)
    RayExecutor().submit(RemoteClip(), job, load_preset("slideshow"), options)
    [(payload, preset, worker_options)] = sent
    assert (preset.width_px, preset.duration_s) == (256, 0.3)
    content = file_sha256(tmp_path / "a.jpg")
    wanted = clip_fingerprints(tmp_path / "a.jpg", content, load_preset("slideshow"), options,
                               entry)
    look.unlink()
    monkeypatch.chdir("/")
    outcome = make_clip_from_bytes(payload, preset, worker_options)
    assert outcome.result.status == "done", outcome.result.error
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(outcome.files["a.mp4"])
    assert probe(clip).width_px == 256
    # Marked as the driver marks the clip of this entry (the worker's copy of it names its
    # scratch map and no preset file): after a lost journal the clip is known by its mark.
    assert read_clip_mark(clip) == (content, wanted[0])


def test_an_address_with_no_ray_head_is_refused_at_once(photo_folder, tmp_path):
    """ray.init waited without end, logging its retries, for a head that is not there."""
    output = tmp_path / "out"
    command = kbbatch_command(photo_folder, output, "--ray-address", f"127.0.0.1:{free_port()}")
    run = subprocess.run(command, capture_output=True, text=True, timeout=90)
    assert run.returncode == 1, run.stderr
    assert "could not reach the Ray cluster at 127.0.0.1:" in run.stderr, run.stderr
    assert not output.exists()


def test_resources_no_node_offers_are_refused_naming_what_the_nodes_have(
        cluster, photo_folder, tmp_path):
    """Ray waited without end and without a word for a node with a GPU (or 2 CPUs) per clip."""
    output = tmp_path / "out"
    env = dict(cluster.env, RAY_ADDRESS=cluster.address, KBBATCH_RAY_NODE_WAIT_S="2")
    run = subprocess.run(kbbatch_command(photo_folder, output, "--ray-gpus-per-clip", "1"),
                         env=env, capture_output=True, text=True, timeout=150)
    assert run.returncode == 1, run.stderr
    assert "no node of the Ray cluster offers 1 CPU(s) and 1 GPU(s) for a clip" in run.stderr
    assert "(its nodes: 1 CPU(s), 0 GPU(s)" in run.stderr, run.stderr  # (one, if killed before)
    assert "waiting up to 2 s" in run.stderr
    assert not output.exists()
