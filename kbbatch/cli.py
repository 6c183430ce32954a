"""Command line: thin click commands over the runners. `kbbatch FOLDER` renders a folder."""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import re
import signal
import sys
import threading
import unicodedata
from dataclasses import fields
from pathlib import Path

import click
from click.core import ParameterSource

from kbbatch import EXIT_INTERRUPTED
from kbbatch import depth as depth_stage
from kbbatch import models as model_registry
from kbbatch.batch import (
    CORES_PER_JOB,
    DISK_FULL,
    MEMORY_PER_JOB_GIB,
    PHOTOS_GONE,
    EmptyFolderError,
    RunReport,
    default_jobs,
    empty_folder_error,
    failed_before_a_job,
    last_run_lines,
    plan_folder,
    report_path,
    run_folder,
)
from kbbatch.depth import DepthOptions
from kbbatch.depth import cache as depth_cache
from kbbatch.device import DEVICE_ENV, DEVICE_NAMES, DeviceError, resolve_device
from kbbatch.images import scan_folder
from kbbatch.interrupts import deferred, held
from kbbatch.journal import FolderBusyError, JournalError
from kbbatch.manifest import ManifestError, load_manifest
from kbbatch.outputs import OutputFolderError
from kbbatch.pipeline import ClipOptions
from kbbatch.planners import PLANNER_NAMES
from kbbatch.presets import (
    Preset,
    PresetError,
    builtin_names,
    load_preset,
    setting_docs,
    with_overrides,
)
from kbbatch.ray_executor import RayExecutor, RayUnavailableError, import_ray
from kbbatch.streams import stdout_lost

JOBS_PER_CORE_MAX = 4
"""More local worker processes (or render threads) than this per core only thrash: --jobs 100000
forked until the machine stalled, and left an orphan hung after SIGTERM; --threads 1000 kept two
frames per thread in memory (35 MB each at 1080p, 140 MB at 4K)."""


def _most_per_machine() -> int:
    return JOBS_PER_CORE_MAX * (os.cpu_count() or 1)


def _threads_cap(context: click.Context, param: click.Parameter, value: int) -> int:
    most = _most_per_machine()
    if value > most:
        raise click.BadParameter(f"{value}: at most {most} here ({JOBS_PER_CORE_MAX} per core)",
                                 param=param)
    return value


EXIT_NOTHING_TO_DO = 3
"""Exit status of a batch over a folder without photos (0: all made, 1: some failed)."""



class DefaultCommandGroup(click.Group):
    """A group whose first argument, when it is not a command, goes to the `render` command."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in ("--help", "-h",
                                                                      "--version"):
            args = ["render", *args]
        return super().parse_args(ctx, args)


class NamedPath(click.Path):
    """A path option that refuses the empty string: `-o "$OUT"` with OUT unset wrote clips,
    journal and report into the current folder."""

    def convert(self, value, param, ctx):
        if isinstance(value, str) and not value.strip():
            self.fail("an empty path (an unset variable in a script?); name a folder or file",
                      param, ctx)
        return super().convert(value, param, ctx)


TIMED_LOG_FORMAT = "%(asctime)s %(levelname)s %(message)s"
"""The log of the long-running commands (review, watch): one record per line, timestamped."""


def one_line(text: str) -> str:
    """Control characters shown escaped: a newline in a file name once split one log record
    into two lines (a script reading the log line by line saw half a name), and an escape
    sequence in a name could drive the terminal."""
    return "".join(ascii(char)[1:-1] if unicodedata.category(char) == "Cc" else char
                   for char in text)


class OneLineFormatter(logging.Formatter):
    def formatMessage(self, record: logging.LogRecord) -> str:  # noqa: N802 (logging's name)
        return one_line(super().formatMessage(record))


def _log_to_terminal(level: int, line_format: str = "%(message)s") -> None:
    """Warnings (and, for the daemon and review, progress) to stderr, one line per record.
    A no-op where logging is already set up (a host program, pytest)."""
    handler = logging.StreamHandler()
    handler.setFormatter(OneLineFormatter(line_format))
    logging.basicConfig(level=level, handlers=[handler])


@click.group(cls=DefaultCommandGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="kbbatch")
def main() -> None:
    """Turn every photo in a folder into a 3D Ken Burns clip.

    \b
    kbbatch photos/ --preset slideshow      render a folder (same as `kbbatch render ...`)
    kbbatch presets                         list the presets and their settings
    """


def _shared(*decorators):
    """Options declared once and given to every command that takes them."""

    def apply(command):
        for decorator in reversed(decorators):
            command = decorator(command)
        return command

    return apply


preset_options = _shared(
    click.option("-p", "--preset", "preset_name", default="slideshow", show_default=True,
                 help="Preset name or path to a .toml file (see `kbbatch presets`)."),
    click.option("--duration", type=float, help="Override the preset's forward duration (s)."),
    click.option("--fps", type=float, help="Override the preset's frame rate."),
)
scene_options = _shared(
    click.option("--planner", type=click.Choice(PLANNER_NAMES), default="auto",
                 show_default=True, help="How the start and end crops are chosen."),
    click.option("--depth", "depth_backend", type=click.Choice(depth_stage.BACKEND_NAMES),
                 default="auto", show_default=True, help="Where depth comes from."),
    click.option("--depth-model", type=click.Choice(sorted(
        n for n, s in model_registry.REGISTRY.items() if s.role == "depth")),
        help="Depth network for --depth onnx/auto (default: the first one cached)."),
    click.option("--no-adjust", is_flag=True, help="Do not flatten salient objects into cards."),
    click.option("--no-refine", is_flag=True, help="Plain bilinear upsampling of depth."),
)
manifest_option = click.option(
    "--manifest", "manifest_path", type=NamedPath(exists=True, dir_okay=False, path_type=Path),
    help="JSON manifest of per-image crops and overrides.")
device_option = click.option(
    "--device", type=click.Choice(DEVICE_NAMES), default="auto", show_default=True,
    envvar=DEVICE_ENV, show_envvar=True,
    help="Where frames are rendered: auto (a CUDA GPU when torch sees one, else the CPU), "
    "cpu or cuda.")
save_depth_option = click.option(
    "--save-depth", is_flag=True,
    help="Also write a 16-bit disparity PNG and a coloured preview per clip.")


def _preset(options: dict) -> Preset:
    """The preset of `preset_options`; an error blames the option that caused it."""
    try:
        preset = load_preset(options.pop("preset_name"))
    except PresetError as error:
        raise click.BadParameter(str(error), param_hint="--preset") from error
    overrides = []
    for hint, setting, value in (("--duration", "duration_s", options.pop("duration")),
                                 ("--fps", "fps", options.pop("fps"))):
        try:
            preset = with_overrides(preset, **{setting: value})
        except PresetError as error:
            raise click.BadParameter(str(error), param_hint=hint) from error
        if value is not None:
            overrides.append((setting, value))
    options["preset_overrides"] = tuple(overrides)  # for _clip_options: an entry's preset too
    return preset


def _clip_options(options: dict, **more) -> ClipOptions:
    """The ClipOptions of `scene_options`, plus what the command adds; the models cache is
    checked here, once, before any photo."""
    try:
        model_registry.check_cache()
        depth_cache.cache_max_bytes()
    except (model_registry.ModelError, depth_cache.CacheSettingError) as error:
        raise click.ClickException(str(error)) from error
    depth = DepthOptions(backend=options.pop("depth_backend"), model=options.pop("depth_model"),
                         adjust=not options.pop("no_adjust"),
                         refine=not options.pop("no_refine"))
    try:  # a network asked for and absent: said once, not at every photo
        if depth.model:
            model_registry.required_path(depth.model)
        elif depth.backend == "onnx":
            depth_stage.get_backend(depth, None)
    except (depth_stage.DepthError, model_registry.ModelError) as error:
        raise click.BadParameter(str(error), param_hint="--depth-model" if depth.model
                                 else "--depth") from error
    if "device" in options:
        device = options.pop("device")
        if device == "cuda":  # fail before anything is written; auto resolves where it renders
            try:
                resolve_device(device)
            except DeviceError as error:
                raise click.BadParameter(str(error), param_hint="--device") from error
        more["device"] = device
    return ClipOptions(planner=options.pop("planner"), depth=depth,
                       preset_overrides=options.pop("preset_overrides", ()), **more)


def _finite_number(context: click.Context, param: click.Parameter, value: float) -> float:
    """click's float ranges let NaN (and inf past a lower bound) by: refused by name here."""
    if not math.isfinite(value):
        raise click.BadParameter(f"must be a finite number, got {value}", param=param)
    return value


executor_options = _shared(
    click.option("--executor", "executor_name", type=click.Choice(["local", "ray"]),
                 default="local", show_default=True,
                 help="Make clips on this machine, or as tasks on a Ray cluster."),
    click.option("--ray-address", help="Ray cluster to join (default: $RAY_ADDRESS, else "
                 "Ray starts on this machine)."),
    click.option("--ray-cpus-per-clip", type=click.FloatRange(min=1), default=1.0,
                 show_default=True, callback=_finite_number,
                 help="CPUs a clip reserves on a Ray worker (threads)."),
    click.option("--ray-gpus-per-clip", type=click.FloatRange(min=0), default=0.0,
                 show_default=True, callback=_finite_number,
                 help="GPUs (or a fraction) a clip reserves on a worker."),
    click.option("--ray-shared-fs", is_flag=True,
                 help="Every Ray node sees the photos and the output folder at the same paths: "
                 "send paths, not bytes; workers write the clips in place."),
)


@main.command()
@click.argument("folder", type=NamedPath(exists=True, file_okay=False, path_type=Path))
@click.option("-o", "--output", type=NamedPath(file_okay=False, path_type=Path),
              help="Output folder (default: FOLDER/kenburns).")
@preset_options
@scene_options
@device_option
@manifest_option
@save_depth_option
@click.option("--threads", type=click.IntRange(min=1), default=ClipOptions().threads,
              show_default=True, callback=_threads_cap, help="Frames rendered in parallel.")
@click.option("--force", is_flag=True, help="Redo clips that are already up to date.")
@click.option("--fail-fast", is_flag=True, help="Stop at the first photo that fails.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
@executor_options
def render(folder: Path, output: Path | None, manifest_path: Path | None, save_depth: bool,
           threads: int, force: bool, fail_fast: bool, quiet: bool, **shared) -> None:
    """Render every photo in FOLDER to a palindromic 3D Ken Burns clip."""
    _log_to_terminal(logging.WARNING)
    preset = _preset(shared)
    options = _clip_options(shared, threads=threads, save_depth=save_depth)
    output = output or folder / "kenburns"
    _check_depth_beside_photos(save_depth, folder, output)
    manifest = _load_manifest(manifest_path)
    executor = _executor(shared)
    try:
        report = run_folder(folder, output, preset, options, show_progress=not quiet,
                            manifest=manifest, force=force, fail_fast=fail_fast,
                            executor=executor)
    except (OutputFolderError, FolderBusyError, RayUnavailableError) as error:
        raise click.ClickException(str(error)) from error
    except EmptyFolderError as error:
        click.echo(f"Error: {error}", err=True)
        sys.exit(EXIT_NOTHING_TO_DO)
    except KeyboardInterrupt:
        click.echo("\ninterrupted: no partial clip is left; run again to finish", err=True)
        sys.exit(EXIT_INTERRUPTED)
    try:
        _print_summary(report)
    except OSError as error:  # the clips and the report are made: said, not failed
        click.echo(f"NOTE the summary could not be printed ({stdout_lost(error)}); the run "
                   f"report has it: {report_path(Path(report.output_folder))}", err=True)
    if report.unwritten:  # the clips are made, but whoever reads the report is not told
        click.echo(f"Error: {report.unwritten}", err=True)
    if report.stopped_by == DISK_FULL:
        click.echo(f"stopped: {report.no_space[0].error}; the photos after it were not "
                   "started: free some space and run again to finish", err=True)
        sys.exit(1)  # incomplete, as when photos fail
    if report.stopped_by == PHOTOS_GONE:
        click.echo(f"stopped: {report.folder}: removed or renamed during the run; "
                   f"{len(report.not_started)} photo(s) not started (run kbbatch on the folder "
                   "where it is now to finish)", err=True)
        sys.exit(1)
    if report.stopped_by:
        click.echo(f"stopped by {report.stopped_by} after the clip in progress; run again to "
                   "finish", err=True)
        sys.exit(EXIT_INTERRUPTED)
    if report.not_started:  # --fail-fast: the summary's counts alone read as a whole run
        click.echo(f"ended at its first failure (--fail-fast): {len(report.not_started)} "
                   "photo(s) not started; run again to finish", err=True)
    sys.exit(1 if report.failed or report.interrupted or report.unwritten else 0)


def _check_depth_beside_photos(save_depth: bool, photos: Path, clips: Path) -> None:
    """--save-depth writes `<clip>.disparity.png`, the name of a user's depth map: written
    beside the photos, the next run would read the tool's own map as the user's. (The same
    folder by its file, too: a bind mount of the photo folder resolves to another path.)"""
    same = photos.is_dir() and clips.is_dir() and os.path.samefile(photos, clips)
    if save_depth and same:
        raise click.ClickException(
            f"{clips}: --save-depth writes <name>.disparity.png beside each clip, which kbbatch "
            "reads as the depth map of the photo of that name; write the clips to another "
            "folder (-o/--out)")


def _executor(options: dict) -> RayExecutor | None:
    """The executor of `executor_options` (None: this machine); Ray is checked to be installed
    before any photo is touched."""
    name = options.pop("executor_name")
    executor = RayExecutor(options.pop("ray_address"), options.pop("ray_cpus_per_clip"),
                           options.pop("ray_gpus_per_clip"),
                           shared_fs=options.pop("ray_shared_fs"))
    if name == "local":
        return None
    try:
        import_ray()
        executor.connect()  # refused here, before the output folder is touched
    except RayUnavailableError as error:
        raise click.ClickException(str(error)) from error
    return executor


def _load_manifest(path: Path | None):
    if path is None:
        return None
    try:
        return load_manifest(path)
    except ManifestError as error:
        raise click.BadParameter(str(error), param_hint="--manifest") from error


@main.command()
@click.argument("folder", type=NamedPath(exists=True, file_okay=False, path_type=Path))
@click.option("-o", "--output", "manifest_path", type=NamedPath(dir_okay=False, path_type=Path),
              default=Path("manifest.json"), show_default=True, help="Manifest to write.")
@preset_options
@scene_options
@click.option("--replan", is_flag=True,
              help="Plan again photos whose entries in an existing manifest already have "
                   "crops (their other fields are kept).")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def plan(folder: Path, manifest_path: Path, replan: bool, quiet: bool, **shared) -> None:
    """Plan every photo in FOLDER and write an editable manifest with preview pictures.

    Edit the crops, then render with `kbbatch FOLDER --manifest MANIFEST`. Into an existing
    manifest, entries with crops (edited by hand, or in `kbbatch review`) are kept.
    """
    _log_to_terminal(logging.WARNING)
    import shlex

    render_options = _render_options(click.get_current_context())
    preset = _preset(shared)
    options = _clip_options(shared)
    try:
        results = plan_folder(folder, manifest_path, preset, options, show_progress=not quiet,
                              replan=replan)
    except EmptyFolderError as error:
        click.echo(f"Error: {error}", err=True)
        sys.exit(EXIT_NOTHING_TO_DO)
    except OSError as error:  # the folder, or where the manifest and previews go
        raise click.ClickException(str(error) if isinstance(error, OutputFolderError) else
                                   f"{error.filename or manifest_path}: "
                                   f"{error.strerror or error}") from error
    done = [r for r in results if r.status == "done"]
    kept = [r for r in results if r.status == "kept"]
    previews = (f"; previews in {manifest_path.with_name(manifest_path.stem + '-previews')}"
                if done else "")
    click.echo(f"{len(done)} plan(s) written to {manifest_path}{previews}")
    if kept:
        click.echo(f"{len(kept)} entr{'y' if len(kept) == 1 else 'ies'} with crops or "
                   "excluded kept as they were " + ("(saved while planning)" if replan else
                                                    "(--replan plans them again)"))
    # The manifest holds crops: the preset, duration and depth options are the command's.
    # as bytes: a folder name that is not UTF-8 is printed as the shell must be given it
    click.echo(os.fsencode("render them with: " + shlex.join([
        "kbbatch", str(folder.absolute()), "--manifest", str(manifest_path.absolute()),
        *render_options])))
    for result in results:
        if result.note:
            click.echo(one_line(f"NOTE {result.note}"), err=True)
    failed = [r for r in results if r.status == "failed"]
    for result in failed:
        click.echo(one_line(f"FAILED {result.error}"), err=True)
    sys.exit(1 if failed else 0)


@main.command()
@click.argument("folder", type=NamedPath(exists=True, file_okay=False, path_type=Path))
@click.option("--manifest", "manifest_path", type=NamedPath(dir_okay=False, path_type=Path),
              default=Path("manifest.json"), show_default=True,
              help="Manifest to edit (created on the first save).")
@preset_options
@scene_options
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on; anything but a local one exposes the page.")
@click.option("--port", type=click.IntRange(0, 65535), default=8765, show_default=True,
              help="Port (0: any free one).")
@click.option("--open", "open_browser", is_flag=True, help="Open the page in a web browser.")
def review(folder: Path, manifest_path: Path, host: str, port: int, open_browser: bool,
           **shared) -> None:
    """Review and edit every photo's plan in a web page, then save the manifest.

    Render the saved manifest with `kbbatch FOLDER --manifest MANIFEST`.
    """
    from kbbatch.web.app import ReviewServer, ReviewSession

    _log_to_terminal(logging.INFO, TIMED_LOG_FORMAT)
    logging.getLogger("werkzeug").setLevel(logging.WARNING)  # no line per request
    render_options = _render_options(click.get_current_context())
    preset = _preset(shared)
    options = _clip_options(shared)
    try:
        session = ReviewSession(folder, manifest_path, preset, options, render_options)
    except ManifestError as error:
        raise click.BadParameter(str(error), param_hint="--manifest") from error
    for link in session.links_out:
        click.echo(one_line(f"NOTE {link}: a link to a photo outside the folder; not shown (the "
                            "review serves only what lies inside it); the batch renders it "
                            "with its automatic plan"), err=True)
    if not session.photos:  # a page of nothing to review: said as the batch says it
        click.echo(f"Error: {empty_folder_error(folder, scan_folder(folder))}", err=True)
        sys.exit(EXIT_NOTHING_TO_DO)
    chosen = click.get_current_context().get_parameter_source("port") != ParameterSource.DEFAULT
    try:
        try:
            server = ReviewServer(session, host, port)
        except OSError as error:  # a second review (another user's) on the default port
            if chosen or error.errno != errno.EADDRINUSE:
                raise
            server = ReviewServer(session, host, 0)
            click.echo(f"NOTE port {port} is in use (another review?); this one is on "
                       f"{server.port}", err=True)
    except OSError as error:
        raise click.ClickException(f"cannot listen on {host}:{port} ({error.strerror or error});"
                                   " choose another --host or --port") from error

    def ready(url: str) -> None:
        click.echo(f"kbbatch review: {len(session.photos)} photo(s) of {session.folder} at {url}"
                   f"\nsaving to {session.manifest_path}; Ctrl-C stops")
        if open_browser:
            import webbrowser

            # The browser is started with a file's name, not the address: its command line
            # is open to every user of the machine, and the address carries the token.
            with held():  # a stop between the page's making and its clean-up's left it
                redirect = redirect_page(url)
                cleanup.callback(redirect.unlink, missing_ok=True)
            removal = threading.Timer(REDIRECT_PAGE_S, redirect.unlink, kwargs={"missing_ok": True})
            removal.daemon = True  # the browser has read it by then
            removal.start()
            if not webbrowser.open(redirect.as_uri()):
                click.echo("NOTE no web browser could be started here; open the address above "
                           "in one", err=True)

    def stop(*_: object) -> None:
        if not deferred():  # else raised at the end of the held() block
            raise KeyboardInterrupt  # a stop, or the terminal closed: cleaned up as Ctrl-C is

    signal.signal(signal.SIGTERM, stop)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, stop)
    if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:  # `nohup`: ignored
        signal.signal(signal.SIGHUP, stop)
    with contextlib.ExitStack() as cleanup:
        try:
            server.serve(ready)
        except KeyboardInterrupt:
            click.echo("stopped")


REDIRECT_PAGE_S = 60.0
"""How long `review --open`'s redirect page (which holds the token) is left for the browser."""


def redirect_page(url: str) -> Path:
    """A page only this user can read (mode 0600) that sends a browser on to url."""
    import html
    import tempfile

    descriptor, name = tempfile.mkstemp(prefix="kbbatch-review-", suffix=".html")
    quoted = html.escape(url, quote=True)
    with os.fdopen(descriptor, "w", encoding="utf-8") as page:
        page.write(f'<!doctype html><meta http-equiv="refresh" content="0;url={quoted}">'
                   f'<title>kbbatch review</title><a href="{quoted}">kbbatch review</a>\n')
    return Path(name)


RENDER_REPEATS = ("preset_name", "duration", "fps", "planner", "depth_backend", "depth_model",
                  "no_adjust", "no_refine")
"""Options of `preset_options` and `scene_options` that a printed render command repeats."""


def _render_options(context: click.Context) -> tuple[str, ...]:
    """The RENDER_REPEATS options given on the command line, as a render command repeats them:
    a preset file by its absolute path, since the command may be run from another folder."""
    arguments: list[str] = []
    for param in context.command.params:
        if (param.name not in RENDER_REPEATS
                or context.get_parameter_source(param.name) in (None, ParameterSource.DEFAULT)):
            continue
        value = context.params[param.name]
        flag = max(param.opts, key=len)
        if param.name == "preset_name" and value not in builtin_names():
            value = str(Path(value).absolute())
        if isinstance(param, click.Option) and param.is_flag:
            arguments += [flag] if value else []
        else:
            arguments += [flag, str(value)]
    return tuple(arguments)


def _print_summary(report: RunReport) -> None:
    done = [r for r in report.results if r.status == "done"]
    skipped = [r for r in report.results if r.status == "skipped"]
    excluded = [r for r in report.results if r.status == "excluded"]
    click.echo(f"\n{len(done)} clip(s) made in {report.output_folder}, {len(skipped)} already "
               f"up to date, {len(report.failed)} failed, preset {report.preset}")
    if excluded:
        click.echo(f"{len(excluded)} photo(s) excluded by the manifest")
    removed = [r for r in report.results if r.status == "removed"]
    if removed:
        click.echo(f"{len(removed)} photo(s) removed from the folder during the run")
    if report.interrupted:
        click.echo(f"{len(report.interrupted)} clip(s) interrupted (their encoder was "
                   "stopped); run again to finish", err=True)
    if done:
        mean = sum(r.seconds for r in done) / len(done)
        click.echo(f"{mean:.1f} s per photo on average")
    for result in report.results:
        if result.note:
            click.echo(one_line(f"NOTE {result.note}"), err=True)
    for note in report.notes:
        click.echo(one_line(f"NOTE {note}"), err=True)
    for result in report.failed:
        click.echo(one_line(f"FAILED {result.error}"), err=True)


@main.command()
def presets() -> None:
    """List the shipped presets with their settings, and what each setting means."""
    names = [f.name for f in fields(Preset) if f.name not in ("name", "description")]
    for preset_name in builtin_names():
        preset = load_preset(preset_name)
        click.echo(f"{preset.name}: {preset.description}")
        click.echo("  " + ", ".join(f"{n}={getattr(preset, n)}" for n in names))
    click.echo("\nsettings of a preset file (a path works wherever a name does):")
    for name, meaning in setting_docs().items():
        click.echo(f"  {name:<15} {meaning}")


@main.group()
def models() -> None:
    """The model registry and cache (set KBBATCH_MODELS to use another folder)."""


@models.command("list")
def models_list() -> None:
    """Registered models, their licence and whether each is cached."""
    try:
        model_registry.check_models_dir()  # a file there: refused, as every command does
        click.echo(f"cache: {model_registry.models_dir()}")
        provider = model_registry.execution_provider()
    except model_registry.ModelError as error:
        raise click.ClickException(str(error)) from error
    click.echo(f"onnxruntime: {provider}, {model_registry.session_threads()} thread(s) per "
               f"session (set {model_registry.PROVIDER_ENV} to choose the provider)")
    problems = []
    for spec in model_registry.REGISTRY.values():
        path = model_registry.cached_path(spec.name)
        if path is None:  # a folder or a pipe under its name: no "missing", as a run says
            problem = model_registry.no_file_problem(spec)
        else:
            damage = model_registry.cache_problem(spec, path)
            problem = f"{path}: {damage}" if damage else None
        cached = "DAMAGED" if problem else "missing" if path is None else "cached"
        pinned = "sha256 pinned" if spec.sha256 else "no sha256 registered"
        click.echo(f"{spec.name:<24} {spec.role:<9} {cached:<8} {pinned}; {spec.licence}")
        click.echo(f"{'':<24} {spec.url or 'no single-file download: place ' + spec.filename}")
        if problem:
            problems.append(problem)
    for problem in problems:  # a damaged file stops every run: said here too
        click.echo(problem, err=True)


@models.command("pull")
@click.argument("name", type=click.Choice(sorted(model_registry.REGISTRY)))
@click.option("--sha256", callback=lambda _context, _param, value: _sha256_hex(value),
              help="The checksum you trust, for models without a registered one.")
def models_pull(name: str, sha256: str | None) -> None:
    """Download a model into the cache, verifying its sha256."""
    try:
        path = model_registry.pull(model_registry.REGISTRY[name], sha256=sha256)
    except model_registry.ModelError as error:
        raise click.ClickException(str(error)) from error
    click.echo(f"{name}: {path}")


def _sha256_hex(value: str | None) -> str | None:
    """64 hex digits, checked before the download (a typo was found only after it)."""
    if value is not None and not re.fullmatch(r"[0-9a-fA-F]{64}", value.strip()):
        raise click.BadParameter(f"{value!r} is not a sha256 (64 hex digits)",
                                 param_hint="'--sha256'")
    return value.strip().lower() if value is not None else None


def _finite_seconds(context: click.Context, param: click.Parameter, value: float) -> float:
    """A number of seconds, refused when NaN or infinite (click's ranges let NaN by)."""
    if not math.isfinite(value):
        raise click.BadParameter(f"must be a finite number of seconds, got {value}",
                                 param=param)
    return value


@main.command()
@click.argument("inbox", type=NamedPath(file_okay=False, path_type=Path))
@click.option("--out", "outbox", required=True, type=NamedPath(file_okay=False, path_type=Path),
              help="Folder the clips are written to (the job journal lives there too).")
@preset_options
@scene_options
@device_option
@manifest_option
@save_depth_option
@click.option("--jobs", type=click.IntRange(min=1), default=None,
              help="Photos processed in parallel (worker processes). Default: one per "
              f"{CORES_PER_JOB} cores and per {MEMORY_PER_JOB_GIB} GiB of memory, at least 1 "
              f"(here: {default_jobs()}); each worker renders with cores/jobs threads.")
@click.option("--poll", is_flag=True, help="Poll the folder instead of inotify (network shares).")
@click.option("--settle", "settle_s", type=click.FloatRange(min=0), default=2.0,
              show_default=True, callback=_finite_seconds,
              help="Seconds a photo's size and time must stay unchanged before it is taken.")
@click.option("--keep-sources", is_flag=True, help="Leave finished photos in the inbox.")
@executor_options
def watch(inbox: Path, outbox: Path, manifest_path: Path | None, save_depth: bool, jobs: int | None,
          poll: bool, settle_s: float, keep_sources: bool, **shared) -> None:
    """Watch INBOX and turn every photo that arrives into a clip in --out, day and night."""
    from kbbatch.watch import DONE_FOLDER, FAILED_FOLDER, WatchSettings
    from kbbatch.watch import watch as run_daemon

    _log_to_terminal(logging.INFO, TIMED_LOG_FORMAT)
    # its lock is the output folder's: a busy error (realpath: a link in a loop is the
    # daemon's to refuse, not a traceback here)
    if os.path.realpath(inbox) == os.path.realpath(outbox):
        raise click.UsageError(f"{outbox}: --out must be a folder other than the inbox")
    for filed in (DONE_FOLDER, FAILED_FOLDER):  # clips among the filed photos or failures
        folder = os.path.realpath(inbox / filed)
        if os.path.commonpath([folder, os.path.realpath(outbox)]) == folder:
            raise click.UsageError(f"{outbox}: --out must not be in the inbox's {filed}/ "
                                   "folder, where the daemon files photos")
    local_jobs_max = _most_per_machine()
    if jobs is not None and jobs > local_jobs_max and shared.get("executor_name") != "ray":
        raise click.UsageError(f"--jobs {jobs}: at most {local_jobs_max} worker processes "
                               f"here ({JOBS_PER_CORE_MAX} per core); each one renders a photo")
    preset = _preset(shared)
    options = _clip_options(shared, save_depth=save_depth)
    _check_depth_beside_photos(save_depth, inbox, outbox)
    executor = _executor(shared)
    settings = WatchSettings(inbox, outbox, preset, options, _load_manifest(manifest_path),
                             jobs or default_jobs(), poll, settle_s, keep_sources, executor)
    try:
        sys.exit(run_daemon(settings))
    except (OutputFolderError, FolderBusyError, JournalError,
            RayUnavailableError) as error:
        raise click.ClickException(str(error)) from error


@main.command()
@click.argument("outbox", type=NamedPath(exists=True, file_okay=False, path_type=Path))
def status(outbox: Path) -> None:
    """Counts and failures from the job journal in OUTBOX."""
    from kbbatch.journal import JOURNAL_NAME
    from kbbatch.watch import status_lines

    if not (outbox / JOURNAL_NAME).is_file():
        raise click.ClickException(f"{outbox}: no job journal here ({JOURNAL_NAME})")
    try:
        lines = status_lines(outbox, failed_before_a_job(outbox))
    except JournalError as error:  # damaged: said in one line, as render and watch say it
        raise click.ClickException(str(error)) from error
    for line in [*lines, *last_run_lines(outbox)]:
        click.echo(one_line(line))
