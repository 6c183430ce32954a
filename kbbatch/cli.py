"""Command line: thin click commands over kbbatch.batch. `kbbatch FOLDER` renders a folder."""

from __future__ import annotations

import sys
from dataclasses import fields
from pathlib import Path

import click

from kbbatch import depth as depth_stage
from kbbatch import models as model_registry
from kbbatch.batch import ClipOptions, OutputFolderError, RunReport, plan_folder, run_folder
from kbbatch.depth import DepthOptions
from kbbatch.manifest import ManifestError, load_manifest
from kbbatch.presets import Preset, PresetError, builtin_names, load_preset, with_overrides
from planners import PLANNER_NAMES


class DefaultCommandGroup(click.Group):
    """A group whose first argument, when it is not a command, goes to the `render` command."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in ("--help", "-h",
                                                                      "--version"):
            args = ["render", *args]
        return super().parse_args(ctx, args)


@click.group(cls=DefaultCommandGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="kbbatch")
def main() -> None:
    """Turn every photo in a folder into a 3D Ken Burns clip.

    \b
    kbbatch photos/ --preset slideshow      render a folder (same as `kbbatch render ...`)
    kbbatch presets                         list the presets and their settings
    """


def _load_preset(name: str, duration: float | None, fps: float | None) -> Preset:
    try:
        return with_overrides(load_preset(name), duration_s=duration, fps=fps)
    except PresetError as error:
        raise click.BadParameter(str(error), param_hint="--preset") from error


@main.command()
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path),
              help="Output folder (default: FOLDER/kenburns).")
@click.option("-p", "--preset", "preset_name", default="slideshow", show_default=True,
              help="Preset name or path to a .toml file (see `kbbatch presets`).")
@click.option("--planner", type=click.Choice(PLANNER_NAMES), default="auto", show_default=True,
              help="How the start and end crops are chosen.")
@click.option("--manifest", "manifest_path", type=click.Path(exists=True, dir_okay=False,
              path_type=Path), help="JSON manifest of per-image crops and overrides.")
@click.option("--depth", "depth_backend", type=click.Choice(depth_stage.BACKEND_NAMES),
              default="auto", show_default=True, help="Where depth comes from.")
@click.option("--depth-model", type=click.Choice(sorted(
    n for n, s in model_registry.REGISTRY.items() if s.role == "depth")),
    help="Depth network for --depth onnx/auto (default: the first one cached).")
@click.option("--no-adjust", is_flag=True, help="Do not flatten salient objects into cards.")
@click.option("--no-refine", is_flag=True, help="Plain bilinear upsampling of depth.")
@click.option("--save-depth", is_flag=True,
              help="Also write a 16-bit disparity PNG and a coloured preview per clip.")
@click.option("--duration", type=float, help="Override the preset's forward duration (s).")
@click.option("--fps", type=float, help="Override the preset's frame rate.")
@click.option("--threads", type=int, default=ClipOptions().threads, show_default=True,
              help="Frames rendered in parallel.")
@click.option("--force", is_flag=True, help="Redo clips that are already up to date.")
@click.option("--fail-fast", is_flag=True, help="Stop at the first photo that fails.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def render(folder: Path, output: Path | None, preset_name: str, planner: str,
           manifest_path: Path | None, depth_backend: str, depth_model: str | None,
           no_adjust: bool, no_refine: bool, save_depth: bool, duration: float | None,
           fps: float | None, threads: int, force: bool, fail_fast: bool,
           quiet: bool) -> None:
    """Render every photo in FOLDER to a palindromic 3D Ken Burns clip."""
    preset = _load_preset(preset_name, duration, fps)
    output = output or folder / "kenburns"
    depth = DepthOptions(backend=depth_backend, model=depth_model, adjust=not no_adjust,
                         refine=not no_refine)
    options = ClipOptions(planner=planner, depth=depth, threads=threads, save_depth=save_depth)
    manifest = _load_manifest(manifest_path)
    try:
        report = run_folder(folder, output, preset, options, show_progress=not quiet,
                            manifest=manifest, force=force, fail_fast=fail_fast)
    except OutputFolderError as error:
        raise click.ClickException(str(error)) from error
    _print_summary(report)
    sys.exit(1 if report.failed else 0)


def _load_manifest(path: Path | None):
    if path is None:
        return None
    try:
        return load_manifest(path)
    except ManifestError as error:
        raise click.BadParameter(str(error), param_hint="--manifest") from error


@main.command()
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("-o", "--output", "manifest_path", type=click.Path(dir_okay=False, path_type=Path),
              default=Path("manifest.json"), show_default=True, help="Manifest to write.")
@click.option("-p", "--preset", "preset_name", default="slideshow", show_default=True)
@click.option("--planner", type=click.Choice(PLANNER_NAMES), default="auto", show_default=True)
@click.option("--depth", "depth_backend", type=click.Choice(depth_stage.BACKEND_NAMES),
              default="auto", show_default=True)
@click.option("--quiet", is_flag=True)
def plan(folder: Path, manifest_path: Path, preset_name: str, planner: str, depth_backend: str,
         quiet: bool) -> None:
    """Plan every photo in FOLDER and write an editable manifest with preview pictures.

    Edit the crops, then render with `kbbatch FOLDER --manifest MANIFEST`.
    """
    preset = _load_preset(preset_name, None, None)
    options = ClipOptions(planner=planner, depth=DepthOptions(backend=depth_backend))
    results = plan_folder(folder, manifest_path, preset, options, show_progress=not quiet)
    done = [r for r in results if r.status == "done"]
    click.echo(f"{len(done)} plan(s) written to {manifest_path}; previews in "
               f"{manifest_path.with_name(manifest_path.stem + '-previews')}")
    for result in results:
        if result.status != "done":
            click.echo(f"FAILED {result.error}", err=True)
    sys.exit(1 if len(done) < len(results) else 0)


@main.command()
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--manifest", "manifest_path", type=click.Path(dir_okay=False, path_type=Path),
              default=Path("manifest.json"), show_default=True,
              help="Manifest to edit (created on the first save).")
@click.option("-p", "--preset", "preset_name", default="slideshow", show_default=True,
              help="Preset of photos whose entry names none.")
@click.option("--planner", type=click.Choice(PLANNER_NAMES), default="auto", show_default=True)
@click.option("--depth", "depth_backend", type=click.Choice(depth_stage.BACKEND_NAMES),
              default="auto", show_default=True)
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on; anything but a local one exposes the page.")
@click.option("--port", type=click.IntRange(0, 65535), default=8765, show_default=True,
              help="Port (0: any free one).")
@click.option("--open", "open_browser", is_flag=True, help="Open the page in a web browser.")
def review(folder: Path, manifest_path: Path, preset_name: str, planner: str,
           depth_backend: str, host: str, port: int, open_browser: bool) -> None:
    """Review and edit every photo's plan in a web page, then save the manifest.

    Render the saved manifest with `kbbatch FOLDER --manifest MANIFEST`.
    """
    import logging

    from kbbatch.web.app import ReviewServer, ReviewSession

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    logging.getLogger("werkzeug").setLevel(logging.WARNING)  # no line per request
    preset = _load_preset(preset_name, None, None)
    options = ClipOptions(planner=planner, depth=DepthOptions(backend=depth_backend))
    try:
        session = ReviewSession(folder, manifest_path, preset, options)
    except ManifestError as error:
        raise click.BadParameter(str(error), param_hint="--manifest") from error
    try:
        server = ReviewServer(session, host, port)
    except OSError as error:
        raise click.ClickException(f"cannot listen on {host}:{port} ({error.strerror or error});"
                                   " choose another --port") from error

    def ready(url: str) -> None:
        click.echo(f"kbbatch review: {len(session.photos)} photo(s) of {session.folder} at {url}"
                   f"\nsaving to {session.manifest_path}; Ctrl-C stops")
        if open_browser:
            import webbrowser

            webbrowser.open(url)

    try:
        server.serve(ready)
    except KeyboardInterrupt:
        click.echo("stopped")


def _print_summary(report: RunReport) -> None:
    done = [r for r in report.results if r.status == "done"]
    skipped = [r for r in report.results if r.status == "skipped"]
    excluded = [r for r in report.results if r.status == "excluded"]
    click.echo(f"\n{len(done)} clip(s) made in {report.output_folder}, {len(skipped)} already "
               f"up to date, {len(report.failed)} failed, preset {report.preset}")
    if excluded:
        click.echo(f"{len(excluded)} photo(s) excluded by the manifest")
    if done:
        mean = sum(r.seconds for r in done) / len(done)
        click.echo(f"{mean:.1f} s per photo on average")
    for result in report.failed:
        click.echo(f"FAILED {result.error}", err=True)
    if not report.results:
        click.echo("no photos found (jpg, jpeg, png, webp, tif, tiff, bmp)", err=True)


@main.command()
def presets() -> None:
    """List the shipped presets with their settings."""
    names = [f.name for f in fields(Preset) if f.name not in ("name", "description")]
    for preset_name in builtin_names():
        preset = load_preset(preset_name)
        click.echo(f"{preset.name}: {preset.description}")
        click.echo("  " + ", ".join(f"{n}={getattr(preset, n)}" for n in names))


@main.group()
def models() -> None:
    """The model registry and cache (set KBBATCH_MODELS to use another folder)."""


@models.command("list")
def models_list() -> None:
    """Registered models, their licence and whether each is cached."""
    click.echo(f"cache: {model_registry.models_dir()}")
    for spec in model_registry.REGISTRY.values():
        cached = "cached" if model_registry.cached_path(spec.name) else "missing"
        pinned = "sha256 pinned" if spec.sha256 else "no sha256 registered"
        click.echo(f"{spec.name:<24} {spec.role:<9} {cached:<8} {pinned}; {spec.licence}")
        click.echo(f"{'':<24} {spec.url or 'no single-file download: place ' + spec.filename}")


@models.command("pull")
@click.argument("name", type=click.Choice(sorted(model_registry.REGISTRY)))
@click.option("--sha256", help="The checksum you trust, for models without a registered one.")
def models_pull(name: str, sha256: str | None) -> None:
    """Download a model into the cache, verifying its sha256."""
    try:
        path = model_registry.pull(model_registry.REGISTRY[name], sha256=sha256)
    except model_registry.ModelError as error:
        raise click.ClickException(str(error)) from error
    click.echo(f"{name}: {path}")


@main.command()
@click.argument("inbox", type=click.Path(file_okay=False, path_type=Path))
@click.option("--out", "outbox", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder the clips are written to (the job journal lives there too).")
@click.option("-p", "--preset", "preset_name", default="slideshow", show_default=True)
@click.option("--manifest", "manifest_path", type=click.Path(exists=True, dir_okay=False,
              path_type=Path), help="JSON manifest of per-image crops and overrides.")
@click.option("--planner", type=click.Choice(PLANNER_NAMES), default="auto", show_default=True)
@click.option("--depth", "depth_backend", type=click.Choice(depth_stage.BACKEND_NAMES),
              default="auto", show_default=True)
@click.option("--jobs", type=click.IntRange(min=1), default=1, show_default=True,
              help="Photos processed in parallel (processes).")
@click.option("--poll", is_flag=True, help="Poll the folder instead of inotify (network shares).")
@click.option("--settle", "settle_s", type=float, default=2.0, show_default=True,
              help="Seconds a photo's size and time must stay unchanged before it is taken.")
@click.option("--keep-sources", is_flag=True, help="Leave finished photos in the inbox.")
def watch(inbox: Path, outbox: Path, preset_name: str, manifest_path: Path | None, planner: str,
          depth_backend: str, jobs: int, poll: bool, settle_s: float, keep_sources: bool
          ) -> None:
    """Watch INBOX and turn every photo that arrives into a clip in --out, day and night."""
    import logging

    from kbbatch.watch import WatchSettings
    from kbbatch.watch import watch as run_daemon

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    preset = _load_preset(preset_name, None, None)
    options = ClipOptions(planner=planner, depth=DepthOptions(backend=depth_backend))
    settings = WatchSettings(inbox, outbox, preset, options, _load_manifest(manifest_path),
                             jobs, poll, settle_s, keep_sources)
    try:
        sys.exit(run_daemon(settings))
    except OutputFolderError as error:
        raise click.ClickException(str(error)) from error


@main.command()
@click.argument("outbox", type=click.Path(exists=True, file_okay=False, path_type=Path))
def status(outbox: Path) -> None:
    """Counts and failures from the job journal in OUTBOX."""
    from kbbatch.journal import JOURNAL_NAME
    from kbbatch.watch import status_lines

    if not (outbox / JOURNAL_NAME).is_file():
        raise click.ClickException(f"{outbox}: no job journal here ({JOURNAL_NAME})")
    for line in status_lines(outbox):
        click.echo(line)
