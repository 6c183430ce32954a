"""The batch on a Ray cluster: one remote task per photo, the journal and the files on the driver.

No shared file system is assumed. The driver sends each photo's bytes (and its depth file, if
any) through Ray's object store; a worker makes the clip in its own temporary folder with the
same one-clip pipeline as the local executor and sends the clip's bytes back; the driver writes
it atomically and the runner records it once in the journal. Networks are cached per worker
process (kbbatch.models keeps one session per model file), and Ray reuses worker processes, so
they load once per worker, not once per photo.
"""

from __future__ import annotations

import os
import signal
import tempfile
from collections.abc import Iterable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, replace
from pathlib import Path

from kbbatch.depth.file import find_depth_file
from kbbatch.images import atomic_output
from kbbatch.manifest import ManifestEntry
from kbbatch.pipeline import (
    CLIP_SUFFIX,
    SCRATCH_PREFIX,
    ClipJob,
    ClipOptions,
    ClipResult,
    make_clip,
    remove_stale_scratch,
)
from kbbatch.presets import Preset

RAY_INSTALL_HINT = 'pip install "kbbatch[ray]"'

SYSTEM_FAILURE_RETRIES = 3
"""A photo whose worker process or node dies is run again elsewhere this many times."""

IN_FLIGHT_PER_SLOT = 2
"""Tasks submitted per clip slot of the cluster: enough to keep workers busy while the driver
writes results, few enough that photos wait on the driver rather than in the object store."""


class RayUnavailableError(RuntimeError):
    pass


def import_ray():
    """Ray, or an error that says how to install it."""
    try:
        import ray
    except ImportError as error:
        raise RayUnavailableError(f"--executor ray needs Ray, which is not installed: "
                                  f"{RAY_INSTALL_HINT}") from error
    return ray


@dataclass(frozen=True)
class PhotoPayload:
    """What a worker needs of one photo: its name, its bytes and its depth files' bytes."""

    name: str
    photo: bytes
    depth_files: dict[str, bytes]  # file name -> bytes (a sidecar map, a manifest's 'depth')
    clip_name: str
    entry: ManifestEntry | None

    @property
    def size_bytes(self) -> int:
        return len(self.photo) + sum(len(data) for data in self.depth_files.values())


@dataclass(frozen=True)
class WorkerOutcome:
    """A clip made on a worker: the result and the files it wrote (clip, depth pictures)."""

    result: ClipResult
    files: dict[str, bytes]
    node: str
    pid: int


def payload_for(job: ClipJob) -> PhotoPayload:
    """Read a job's photo and depth files on the driver (a failure here is the worker's too)."""
    depth_files = {}
    sidecar = find_depth_file(job.source)
    if sidecar is not None:
        depth_files[sidecar.name] = sidecar.read_bytes()
    entry = job.entry
    if entry is not None and entry.depth_file is not None and entry.depth_file.is_file():
        depth_files[entry.depth_file.name] = entry.depth_file.read_bytes()
    return PhotoPayload(job.source.name, job.source.read_bytes(), depth_files, job.output.name,
                        entry)


def make_clip_from_bytes(payload: PhotoPayload, preset: Preset, options: ClipOptions
                         ) -> WorkerOutcome:
    """The unit of work on a worker: photo bytes in, clip bytes and the ClipResult out."""
    remove_stale_scratch()  # of workers killed mid-clip on this node
    with tempfile.TemporaryDirectory(prefix=f"{SCRATCH_PREFIX}{os.getpid()}-") as scratch:
        inbox, outbox = Path(scratch) / "in", Path(scratch) / "out"
        inbox.mkdir()
        outbox.mkdir()
        source = inbox / payload.name
        source.write_bytes(payload.photo)
        for name, data in payload.depth_files.items():
            (inbox / name).write_bytes(data)
        entry = payload.entry
        if entry is not None and entry.depth_file is not None:
            data = dict(entry.data, depth=entry.depth_file.name)
            entry = replace(entry, data=data, manifest=inbox / entry.manifest.name)
        result = make_clip(source, outbox / payload.clip_name, preset, options,
                           show_progress=False, entry=entry)
        files = {}
        if result.status == "done":
            files = {path.name: path.read_bytes() for path in outbox.iterdir() if path.is_file()}
        result.error = result.error and result.error.replace(str(inbox), "<worker>")
    return WorkerOutcome(result, files, os.uname().nodename, os.getpid())


def write_outcome(job: ClipJob, outcome: WorkerOutcome) -> ClipResult:
    """Write a worker's files beside the job's output, each atomically, and name them as here."""
    result = outcome.result
    result.source = str(job.source)
    if result.error:
        result.error = result.error.replace("<worker>", str(job.source.parent))
    if result.status != "done":
        return result
    try:
        for name, data in outcome.files.items():
            path = job.output.parent / name
            with atomic_output(path, CLIP_SUFFIX if name == job.output.name else path.suffix
                               ) as temp_path:
                temp_path.write_bytes(data)
        result.output = str(job.output)
    except OSError as error:
        result.status, result.output = "failed", None
        result.error = f"{job.output}: the clip could not be written ({error.strerror or error})"
    return result


def start_ray(ray, address: str | None) -> None:
    """Join the cluster at address (or $RAY_ADDRESS), else start Ray on this machine alone."""
    address = address or os.environ.get("RAY_ADDRESS")
    try:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:  # "local": never join a cluster someone else started here with `ray start`
            ray.init(address="local", include_dashboard=False, log_to_driver=False)
    except (ConnectionError, ValueError, RuntimeError) as error:
        where = f"the Ray cluster at {address}" if address else "a local Ray instance"
        raise RayUnavailableError(f"could not start or join {where}: {error}") from error


def unreadable_result(job: ClipJob, error: OSError) -> ClipResult:
    return ClipResult(str(job.source), None, "failed", 0.0,
                      error=f"{job.source}: unreadable ({error.strerror or error})")


@dataclass(frozen=True)
class RayExecutor:
    """Clips made by Ray tasks: on this machine (no address) or on the cluster at address."""

    address: str | None = None
    cpus_per_clip: float = 1.0
    gpus_per_clip: float = 0.0
    bytes_moved: list[int] | None = None  # per clip, photo + clip bytes, when asked for

    def connect(self):
        """Ray, started or joined, and the remote clip function with this executor's resources."""
        ray = import_ray()
        if not ray.is_initialized():
            start_ray(ray, self.address)
        remote_clip = ray.remote(
            num_cpus=self.cpus_per_clip, num_gpus=self.gpus_per_clip,
            max_retries=SYSTEM_FAILURE_RETRIES, retry_exceptions=False,
            max_calls=0,  # keep worker processes (and their networks) for the next photo
        )(make_clip_from_bytes)
        return ray, remote_clip

    def worker_options(self, options: ClipOptions) -> ClipOptions:
        return replace(options, threads=max(1, round(self.cpus_per_clip)))

    def render(self, jobs: Iterable[ClipJob], preset: Preset, options: ClipOptions,
               show_progress: bool) -> Iterator[tuple[ClipJob, ClipResult]]:
        ray, remote_clip = self.connect()
        worker_options = self.worker_options(options)
        slots = int(ray.cluster_resources().get("CPU", 1) // self.cpus_per_clip)
        in_flight = max(2, IN_FLIGHT_PER_SLOT * slots)
        pending: dict = {}  # object ref -> (job, bytes sent)
        queue = iter(jobs)
        try:
            exhausted = False
            while pending or not exhausted:
                while not exhausted and len(pending) < in_flight:
                    job = next(queue, None)
                    if job is None:
                        exhausted = True
                        break
                    try:
                        payload = payload_for(job)
                    except OSError as error:
                        yield job, unreadable_result(job, error)
                        continue
                    ref = remote_clip.remote(payload, preset, worker_options)
                    pending[ref] = (job, payload.size_bytes)
                if not pending:
                    continue
                (ref,), _ = ray.wait(list(pending), num_returns=1)
                job, sent = pending.pop(ref)
                yield job, self.collect(ray, ref, job, sent)
        finally:
            for ref in pending:
                ray.cancel(ref)

    def collect(self, ray, ref, job: ClipJob, sent: int) -> ClipResult:
        """The result of a finished task, written here; a task Ray gave up on is a failure."""
        try:
            outcome: WorkerOutcome = ray.get(ref)
        except ray.exceptions.RayError as error:
            summary = str(error).strip().splitlines()[0] if str(error).strip() else ""
            return ClipResult(str(job.source), None, "failed", 0.0,
                              error=f"{job.source}: the Ray task failed after "
                                    f"{SYSTEM_FAILURE_RETRIES} retries "
                                    f"({type(error).__name__}: {summary})")
        if self.bytes_moved is not None:
            self.bytes_moved.append(sent + sum(len(data) for data in outcome.files.values()))
        return write_outcome(job, outcome)


class RayClipPool:
    """The daemon's worker pool on Ray: submit() takes what the daemon's process pool takes and
    returns a Future of the ClipResult; the clip is made by a Ray task and written here."""

    def __init__(self, executor: RayExecutor) -> None:
        self.executor = executor
        self.pending: set = set()

    def start(self) -> RayClipPool:
        """Start or join Ray; Ray's driver installs its own SIGTERM handler (it exits at once),
        so the daemon's handlers are put back."""
        handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
        self.ray, self.remote_clip = self.executor.connect()
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
        return self

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        """Like ProcessPoolExecutor.shutdown: wait for the clips in flight, or cancel them."""
        if cancel_futures or not wait:
            for ref in list(self.pending):
                self.ray.cancel(ref)
        elif self.pending:
            self.ray.wait(list(self.pending), num_returns=len(self.pending))

    def submit(self, _local_render, source: Path, output: Path, preset: Preset,
               options: ClipOptions, entry: ManifestEntry | None) -> Future:
        """Like ProcessPoolExecutor.submit(_local_render, ...), but the clip is made on Ray."""
        job, future = ClipJob(source, output, entry), Future()
        try:
            payload = payload_for(job)
        except OSError as error:
            future.set_result(unreadable_result(job, error))
            return future
        ref = self.remote_clip.remote(payload, preset, self.executor.worker_options(options))
        self.pending.add(ref)

        def finished(_: object) -> None:
            self.pending.discard(ref)
            try:
                future.set_result(self.executor.collect(self.ray, ref, job, payload.size_bytes))
            except BaseException as error:  # handed to the daemon, which fails the photo
                future.set_exception(error)

        ref.future().add_done_callback(finished)
        return future
