"""The batch on a Ray cluster: one remote task per photo, the journal on the driver.

By default no shared file system is assumed. The driver sends each photo's bytes (and its depth
file, if any) through Ray's object store; a worker makes the clip in its own temporary folder
with the same one-clip pipeline as the local executor and sends the clip's bytes back; the
driver writes it atomically and the runner records it once in the journal.

With shared_fs (`--ray-shared-fs`), every node sees the photos and the output folder at the same
paths: the driver sends only the job's paths, the worker checks that it sees the same input
files as the driver and makes the clip with make_clip straight to the job's output path (make_clip
writes under a hidden temporary name and renames it whole), and only the ClipResult comes back;
the driver checks that it sees the clip the worker made before the runner records it.

Networks are cached per worker process (kbbatch.models keeps one session per model file), and
Ray reuses worker processes, so they load once per worker, not once per photo.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import pickle
import signal
import socket
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, replace
from pathlib import Path

from kbbatch.depth.file import find_depth_file
from kbbatch.fingerprint import file_sha256
from kbbatch.images import (
    atomic_output,
    depth_image_names,
    is_disk_full,
    is_users_file,
)
from kbbatch.journal import source_fingerprint
from kbbatch.manifest import ManifestEntry, ManifestError
from kbbatch.pipeline import (
    CLIP_SUFFIX,
    SCRATCH_PREFIX,
    ClipJob,
    ClipOptions,
    ClipResult,
    apply_entry,
    joined_notes,
    make_clip,
    own_clip_mark,
    remove_stale_depth_images,
    remove_stale_scratch,
    users_files_note,
)
from kbbatch.presets import Preset
from kbbatch.settings import env_number

log = logging.getLogger(__name__)

RAY_INSTALL_HINT = 'pip install "kbbatch[ray]"'

SYSTEM_FAILURE_RETRIES = 3
"""A photo whose worker process or node dies is run again elsewhere this many times."""

IN_FLIGHT_PER_SLOT = 2
"""Tasks submitted per clip slot of the cluster: enough to keep workers busy while the driver
writes results, few enough that photos wait on the driver rather than in the object store."""

SHARED_FS_HINT = ("--ray-shared-fs needs the photos, their depth files and the output folder at "
                  "the same paths on every node")

CLIP_VISIBLE_WAIT_S = 2.0
"""How long the driver waits to see a clip a worker renamed on a shared file system (a network
file system's attribute cache may lag the worker's rename by a moment)."""


RAY_CONNECT_TIMEOUT_S = 10.0
"""How long a cluster's head may take to accept a connection: ray.init waited without end (and
logged its retries) for a head that is not there."""

RAY_NODE_WAIT_ENV = "KBBATCH_RAY_NODE_WAIT_S"
RAY_NODE_WAIT_S = 30.0
"""How long a cluster may take to show a node with the resources a clip asks for (a node still
joining; an autoscaler's takes minutes: $KBBATCH_RAY_NODE_WAIT_S) before the run is refused:
Ray itself waits for one without end, and says nothing."""


def node_wait_s() -> float:
    try:
        return env_number(RAY_NODE_WAIT_ENV, RAY_NODE_WAIT_S)
    except ValueError as error:
        raise RayUnavailableError(f"{error} (seconds to wait for the cluster's nodes)") from None


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
    mark: str | None = None  # the clip's mark, made on the driver (make_clip)


@dataclass(frozen=True)
class SharedPaths:
    """What a worker needs of one photo when every node sees the same folders: the job as it
    is, and each input file's size and time as the driver sees them (the journal's test of the
    same file), to be found the same on the worker."""

    job: ClipJob
    inputs: dict[str, str]  # path -> "size:mtime_ns" on the driver (photo, depth files)
    mark: str | None = None  # the clip's mark, made on the driver (make_clip)


@dataclass(frozen=True)
class WorkerOutcome:
    """A clip made on a worker: the result and the files it wrote (clip, depth pictures), or,
    on a shared file system, no files and the clip's size and time as the worker saw them."""

    result: ClipResult
    files: dict[str, bytes]
    node: str
    pid: int
    clip_stat: str | None = None  # "size:mtime_ns" of the clip written in place


def depth_files_of(job: ClipJob) -> list[Path]:
    """The depth map files a job's clip reads, as the driver sees them: the photo's sidecar
    and the file its manifest entry names."""
    files = []
    sidecar = find_depth_file(job.source)
    if sidecar is not None:
        files.append(sidecar)
    entry = job.entry
    if entry is not None and entry.depth_file is not None and entry.depth_file.is_file():
        files.append(entry.depth_file)
    return files


def payload_for(job: ClipJob, mark: str | None) -> PhotoPayload:
    """Read a job's photo and depth files on the driver (a failure here is the worker's too)."""
    depth_files = {path.name: path.read_bytes() for path in depth_files_of(job)}
    return PhotoPayload(job.source.name, job.source.read_bytes(), depth_files, job.output.name,
                        job.entry, mark)


def shared_paths_for(job: ClipJob, mark: str | None) -> SharedPaths:
    """A job's paths, made absolute (a worker's working folder is not the driver's), and its
    input files' size and time on the driver (nothing is read)."""
    entry = job.entry
    if entry is not None:
        entry = replace(entry, manifest=entry.manifest.absolute())
    job = replace(job, source=job.source.absolute(), output=job.output.absolute(), entry=entry)
    inputs = {str(path): source_fingerprint(path) for path in [job.source, *depth_files_of(job)]}
    return SharedPaths(job, inputs, mark)


def worker_node() -> str:
    """This worker's machine and Ray node, for messages (loopback nodes share a host name)."""
    import ray

    if not ray.is_initialized():  # a direct call, outside Ray (asking would start Ray here)
        return os.uname().nodename
    return f"{os.uname().nodename} (id {ray.get_runtime_context().get_node_id()[:12]})"


def clip_on_worker(source: Path, output: Path, preset: Preset, options: ClipOptions,
                   entry: ManifestEntry | None, mark: str | None) -> ClipResult:
    """make_clip as every Ray task runs it, after removing the frame stores of workers killed
    mid-clip on this node."""
    remove_stale_scratch()
    return make_clip(source, output, preset, options, show_progress=False, entry=entry,
                     mark=mark)


def make_clip_from_bytes(payload: PhotoPayload, preset: Preset, options: ClipOptions
                         ) -> WorkerOutcome:
    """The unit of work on a worker: photo bytes in, clip bytes and the ClipResult out."""
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
        result = clip_on_worker(source, outbox / payload.clip_name, preset, options, entry,
                                payload.mark)
        files = {}
        if result.status == "done":
            files = {path.name: path.read_bytes() for path in outbox.iterdir() if path.is_file()}
        result.error = result.error and result.error.replace(str(inbox), "<worker>")
    return WorkerOutcome(result, files, worker_node(), os.getpid())


def make_clip_in_place(task: SharedPaths, preset: Preset, options: ClipOptions
                       ) -> WorkerOutcome:
    """The unit of work on a worker when every node sees the same folders: paths in, the clip
    made at the job's output path (renamed there whole), only the ClipResult out."""
    job, node = task.job, worker_node()
    problem = shared_path_problem(task, node)
    if problem is not None:
        return WorkerOutcome(ClipResult(str(job.source), None, "failed", 0.0, error=problem), {},
                             node, os.getpid())
    result = clip_on_worker(job.source, job.output, preset, options, job.entry, task.mark)
    clip_stat = None
    if result.status == "done":
        with contextlib.suppress(OSError):  # renamed, then gone: the driver's check fails it
            clip_stat = source_fingerprint(job.output)
    return WorkerOutcome(result, {}, node, os.getpid(), clip_stat)


def shared_path_problem(task: SharedPaths, node: str) -> str | None:
    """Why this node cannot make the job in place, or None: an input file it does not see, or
    sees changed, or no output folder (which make_clip would create here, unseen elsewhere)."""
    for path, driver_stat in task.inputs.items():
        try:
            here = source_fingerprint(Path(path))
        except OSError as error:
            missing = error.errno in (errno.ENOENT, errno.ENOTDIR)
            reason = "not found" if missing else f"unreadable ({error.strerror or error})"
            return f"{path}: {reason} on Ray node {node}; {SHARED_FS_HINT}"
        if here != driver_stat:
            return (f"{path}: on Ray node {node} this file differs from the driver's (size and "
                    f"time {here}, the driver's {driver_stat}); {SHARED_FS_HINT}")
    folder = task.job.output.parent
    if not folder.is_dir():
        return f"{folder}: output folder not found on Ray node {node}; {SHARED_FS_HINT}"
    return None


def write_outcome(job: ClipJob, outcome: WorkerOutcome) -> ClipResult:
    """Write a worker's files beside the job's output, each atomically, and name them as here."""
    result = outcome.result
    result.source = str(job.source)
    if result.error:
        result.error = result.error.replace("<worker>", str(job.source.parent))
    if result.status != "done":
        return result
    try:
        users = []
        # the clip first, its depth images after (as make_clip writes them)
        for name, data in sorted(outcome.files.items(), key=lambda f: f[0] != job.output.name):
            path = job.output.parent / name
            if name != job.output.name and is_users_file(path):
                users.append(path)  # the user's file: never replaced (save_depth_images)
                continue
            with atomic_output(path, CLIP_SUFFIX if name == job.output.name else path.suffix,
                               make_folder=False) as temp_path:
                temp_path.write_bytes(data)
        result.output = str(job.output)
        if users:
            result.note = joined_notes(result.note, users_files_note(users))
        if not set(depth_image_names(job.output.name)) & set(outcome.files):
            remove_stale_depth_images(job.output)  # made again without --save-depth
    except OSError as error:
        result.output = None
        if is_disk_full(error):
            result.found_disk_full(job.output.parent, error.strerror)
        else:
            result.status = "failed"
            result.error = (f"{job.output}: the clip could not be written "
                            f"({error.strerror or error})")
    return result


def check_in_place(job: ClipJob, outcome: WorkerOutcome) -> ClipResult:
    """A clip a worker renamed into the shared output folder: the driver must see that very
    file (same size and time) at the job's path, else the folder is not shared after all."""
    result = outcome.result
    result.source = str(job.source)
    if result.status != "done":
        return result
    deadline = time.monotonic() + CLIP_VISIBLE_WAIT_S
    while True:
        try:
            seen = source_fingerprint(job.output)
        except OSError:
            seen = None
        if seen is not None and seen == outcome.clip_stat:
            result.output = str(job.output)
            return result
        if time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    result.status, result.output = "failed", None
    where = "no file" if seen is None else f"another file (size and time {seen})"
    result.error = (f"{job.output}: the clip made on Ray node {outcome.node} is not what the "
                    f"driver sees at this path ({where}); {SHARED_FS_HINT}")
    return result


def pickled_bytes(value: object) -> int:
    """The size of what Ray sends for a value (its pickle, as Ray serializes task data)."""
    return len(pickle.dumps(value, protocol=5))


def check_reachable(ray, address: str) -> None:
    """A head address (`host:port` or `ray://host:port`) that takes no connection: refused with
    the reason. Ray reads 127.0.0.1 as this machine's own address, and so is it tried here."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        return  # "auto", or a form Ray's own message explains
    hosts = [host.strip("[]")]
    if host in ("127.0.0.1", "localhost"):
        hosts.append(ray.util.get_node_ip_address())
    for candidate in hosts:
        try:
            socket.create_connection((candidate, int(port)), RAY_CONNECT_TIMEOUT_S).close()
            return
        except OSError as error:
            reason = error.strerror or str(error) or type(error).__name__
    raise RayUnavailableError(f"could not reach the Ray cluster at {address}: {reason} (is its "
                              "head running, and is that its address?)")


def check_resources(ray, cpus_per_clip: float, gpus_per_clip: float, wait_s: float) -> None:
    """A clip asking for more than any node offers: refused, after wait_s for such a node to
    join, naming what the nodes have."""
    deadline = time.monotonic() + wait_s
    said = False
    while True:
        offers = [node["Resources"] for node in ray.nodes() if node.get("Alive")]
        if any(offer.get("CPU", 0) >= cpus_per_clip and offer.get("GPU", 0) >= gpus_per_clip
               for offer in offers):
            return
        if time.monotonic() >= deadline:
            break
        if not said:
            log.warning("no Ray node offers %g CPU(s) and %g GPU(s) for a clip yet; waiting "
                        "up to %.0f s for one to join", cpus_per_clip, gpus_per_clip, wait_s)
            said = True
        time.sleep(1.0)
    nodes = "; ".join(f"{offer.get('CPU', 0):g} CPU(s), {offer.get('GPU', 0):g} GPU(s)"
                      for offer in offers) or "none alive"
    raise RayUnavailableError(
        f"no node of the Ray cluster offers {cpus_per_clip:g} CPU(s) and {gpus_per_clip:g} "
        f"GPU(s) for a clip (its nodes: {nodes}); lower --ray-cpus-per-clip or "
        "--ray-gpus-per-clip")


def start_ray(ray, address: str | None) -> None:
    """Join the cluster at address (or $RAY_ADDRESS), else start Ray on this machine alone."""
    address = address or os.environ.get("RAY_ADDRESS")
    if address:
        check_reachable(ray, address)
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
    bytes_moved: list[int] | None = None
    """When given, each clip appends the bytes it moved between driver and worker: its task's
    arguments and its result, pickled (the photo and the clip, unless shared_fs)."""
    shared_fs: bool = False  # every node sees the folders: paths travel, not bytes

    def connect(self):
        """Ray, started or joined, and the remote clip function with this executor's resources."""
        ray = import_ray()
        if not ray.is_initialized():
            # Ray's driver installs its own SIGTERM handler (a C++ dump and exit at once):
            # the runner's handlers, which finish the clip in progress, are put back.
            in_main = threading.current_thread() is threading.main_thread()
            handlers = ({sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
                        if in_main else {})
            start_ray(ray, self.address)
            for sig, handler in handlers.items():
                signal.signal(sig, handler)
            # once, when Ray is started or joined (the command does that before the run)
            joined = self.address or os.environ.get("RAY_ADDRESS")
            check_resources(ray, self.cpus_per_clip, self.gpus_per_clip,
                            node_wait_s() if joined else 0.0)
        remote_clip = ray.remote(
            num_cpus=self.cpus_per_clip, num_gpus=self.gpus_per_clip,
            max_retries=SYSTEM_FAILURE_RETRIES, retry_exceptions=False,
            max_calls=0,  # keep worker processes (and their networks) for the next photo
        )(make_clip_in_place if self.shared_fs else make_clip_from_bytes)
        return ray, remote_clip

    def submit(self, remote_clip, job: ClipJob, preset: Preset, options: ClipOptions
               ) -> tuple[object, int]:
        """Start a job's task: its object ref and the bytes sent (0 unless bytes_moved), or
        the photo's failure where the driver cannot read (or stat) it."""
        try:  # of the job as given: what follows rewrites its entry for the worker
            mark = own_clip_mark(job.source, job.content or file_sha256(job.source), preset,
                                 options, job.entry)
        except OSError as error:
            return unreadable_result(job, error), 0
        if job.entry is not None and "preset" in job.entry.data:
            # The entry's preset file lies beside the manifest on the driver, which a worker
            # may not see: it travels loaded (a bad one is the worker's to report, as here).
            with contextlib.suppress(ManifestError):
                preset, _ = apply_entry(job.entry, preset, options)
                data = {k: v for k, v in job.entry.data.items() if k != "preset"}
                job = replace(job, entry=replace(job.entry, data=data))
        try:
            task = shared_paths_for(job, mark) if self.shared_fs else payload_for(job, mark)
        except OSError as error:
            return unreadable_result(job, error), 0
        arguments = (task, preset, self.worker_options(options))
        sent = pickled_bytes(arguments) if self.bytes_moved is not None else 0
        return remote_clip.remote(*arguments), sent

    def worker_options(self, options: ClipOptions) -> ClipOptions:
        return replace(options, threads=max(1, round(self.cpus_per_clip)))

    def render(self, jobs: Iterable[ClipJob], preset: Preset, options: ClipOptions,
               show_progress: bool) -> Iterator[tuple[ClipJob, ClipResult]]:
        ray, remote_clip = self.connect()
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
                    ref, sent = self.submit(remote_clip, job, preset, options)
                    if isinstance(ref, ClipResult):
                        yield job, ref
                        continue
                    pending[ref] = (job, sent)
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
            self.bytes_moved.append(sent + pickled_bytes(outcome))
        return check_in_place(job, outcome) if self.shared_fs else write_outcome(job, outcome)


class RayClipPool:
    """The daemon's worker pool on Ray: submit() takes what the daemon's process pool takes and
    returns a Future of the ClipResult; the clip is made by a Ray task and written here."""

    def __init__(self, executor: RayExecutor) -> None:
        self.executor = executor
        self.pending: set = set()

    def start(self) -> RayClipPool:
        """Start or join Ray (connect keeps the daemon's signal handlers)."""
        self.ray, self.remote_clip = self.executor.connect()
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
        ref, sent = self.executor.submit(self.remote_clip, job, preset, options)
        if isinstance(ref, ClipResult):
            future.set_result(ref)
            return future
        self.pending.add(ref)

        def finished(_: object) -> None:
            self.pending.discard(ref)
            try:
                future.set_result(self.executor.collect(self.ray, ref, job, sent))
            except BaseException as error:  # handed to the daemon, which fails the photo
                future.set_exception(error)

        ref.future().add_done_callback(finished)
        return future
