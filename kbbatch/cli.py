"""Command line: thin click commands over kbbatch.batch. `kbbatch FOLDER` renders a folder."""

from __future__ import annotations

import sys
from dataclasses import fields
from pathlib import Path

import click

from kbbatch import depth as depth_stage
from kbbatch.batch import ClipOptions, RunReport, run_folder
from kbbatch.presets import Preset, PresetError, builtin_names, load_preset, with_overrides
from planners import PLANNER_NAMES


class DefaultCommandGroup(click.Group):
    """A group whose first argument, when it is not a command, goes to the `render` command."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in ("--help", "-h",
                                                                      "--version"):  # fmt: skip
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
@click.option("--planner", type=click.Choice(PLANNER_NAMES), default="center", show_default=True,
              help="How the start and end crops are chosen.")
@click.option("--depth", "depth_backend", type=click.Choice(depth_stage.BACKEND_NAMES),
              default="auto", show_default=True, help="Where depth comes from.")
@click.option("--duration", type=float, help="Override the preset's forward duration (s).")
@click.option("--fps", type=float, help="Override the preset's frame rate.")
@click.option("--threads", type=int, default=ClipOptions().threads, show_default=True,
              help="Frames rendered in parallel.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def render(folder: Path, output: Path | None, preset_name: str, planner: str,
           depth_backend: str, duration: float | None, fps: float | None, threads: int,
           quiet: bool) -> None:  # fmt: skip
    """Render every photo in FOLDER to a palindromic 3D Ken Burns clip."""
    preset = _load_preset(preset_name, duration, fps)
    output = output or folder / "kenburns"
    options = ClipOptions(planner=planner, depth=depth_backend, threads=threads)
    report = run_folder(folder, output, preset, options, show_progress=not quiet)
    _print_summary(report)
    sys.exit(1 if report.failed else 0)


def _print_summary(report: RunReport) -> None:
    done = [r for r in report.results if r.status == "done"]
    click.echo(f"\n{len(done)} clip(s) made in {report.output_folder}, "
               f"{len(report.failed)} failed, preset {report.preset}")  # fmt: skip
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
