"""CLI options are declared once: render, plan, watch and review take the same scene options,
and the choices come from the planner and depth-backend registries."""

import pytest

from kbbatch import cli
from kbbatch.depth import BACKEND_NAMES, DepthError, DepthOptions, get_backend
from kbbatch.planners import PLANNER_NAMES, PLANNERS

SHARED = ("preset_name", "duration", "fps", "planner", "depth_backend", "depth_model",
          "no_adjust", "no_refine")


@pytest.mark.parametrize("command", [cli.render, cli.plan, cli.watch, cli.review])
def test_every_scene_command_takes_the_shared_options(command):
    params = {p.name: p for p in command.params}
    assert set(SHARED) <= set(params)
    assert tuple(params["planner"].type.choices) == PLANNER_NAMES
    assert tuple(params["depth_backend"].type.choices) == BACKEND_NAMES


def test_watch_takes_what_render_takes_for_a_clip():
    watch = {p.name for p in cli.watch.params}
    assert {"save_depth", "manifest_path"} <= watch


def test_registries_name_their_members():
    assert all(planner.name == name for name, planner in PLANNERS.items())
    with pytest.raises(DepthError, match="unknown depth backend 'nope'; available: auto, file"):
        get_backend(DepthOptions(backend="nope"), None)
    assert get_backend(DepthOptions(backend="ramp"), None).name == "ramp"


RAY_OPTIONS = ("executor_name", "ray_address", "ray_cpus_per_clip", "ray_gpus_per_clip",
               "ray_shared_fs")


@pytest.mark.parametrize("command", [cli.render, cli.watch])
def test_the_batch_and_the_daemon_take_the_same_ray_options(command, tmp_path):
    assert set(RAY_OPTIONS) <= {p.name for p in command.params}
    args = [str(tmp_path), "--executor", "ray"] + (["--out", str(tmp_path)] if command is cli.watch
                                                   else [])
    assert command.make_context("kbbatch", [*args, "--ray-shared-fs"]).params["ray_shared_fs"]
    assert not command.make_context("kbbatch", args).params["ray_shared_fs"]  # copies by default
