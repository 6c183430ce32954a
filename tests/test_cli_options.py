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


def test_review_shows_a_render_command_that_repeats_its_preset_file_and_options(
        tmp_path, monkeypatch):
    """The page's command named a preset file by its stem (an unknown preset to render) and
    dropped --duration, --planner and --depth: what rendered was not what was reviewed."""
    import shlex

    from kbbatch.pipeline import ClipOptions
    from kbbatch.presets import load_preset
    from kbbatch.web.app import ReviewSession

    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine.toml").write_text('base = "preview"\ncrf = 30\n')
    photos = tmp_path / "photos"
    photos.mkdir()
    manifest = tmp_path / "manifest.json"
    manifest.write_text('{"version": 1, "images": {}}')
    given = ["--preset", "mine.toml", "--duration", "1.5", "--planner", "center",
             "--depth", "ramp", "--no-refine"]
    review = cli.review.make_context("kbbatch", [str(photos), "--manifest", str(manifest),
                                                 *given])
    session = ReviewSession(photos, manifest, load_preset("mine.toml"), ClipOptions(),
                            cli._render_options(review))
    program, *arguments = shlex.split(session.render_command())
    monkeypatch.chdir("/")  # the command is run from anywhere
    render = cli.render.make_context(program, arguments).params
    assert load_preset(render["preset_name"]).crf == 30
    assert (render["duration"], render["planner"], render["depth_backend"],
            render["no_refine"]) == (1.5, "center", "ramp", True)
    plain = cli.review.make_context("kbbatch", [str(photos), "--manifest", str(manifest)])
    assert cli._render_options(plain) == ()


def test_status_on_a_damaged_journal_says_so_in_one_line(tmp_path):
    from click.testing import CliRunner

    from kbbatch.journal import JOURNAL_NAME

    (tmp_path / JOURNAL_NAME).write_bytes(b"\x13garbage, not a database" * 700)
    result = CliRunner().invoke(cli.main, ["status", str(tmp_path)])
    assert result.exit_code == 1
    assert isinstance(result.exception, SystemExit)  # an error message, not a traceback
    assert result.output.startswith("Error: ") and JOURNAL_NAME in result.output


@pytest.mark.parametrize("arguments, message", [
    (["--settle", "nan"], "must be a finite number of seconds"),
    (["--settle", "inf"], "must be a finite number of seconds"),
    (["--settle", "-1"], "not in the range"),
])
def test_watch_refuses_a_settle_time_it_could_never_wait_out(tmp_path, arguments, message):
    from click.testing import CliRunner

    result = CliRunner().invoke(cli.main, ["watch", str(tmp_path / "in"), "--out",
                                           str(tmp_path / "out"), *arguments])
    assert result.exit_code == 2 and message in result.output


def test_watch_refuses_its_inbox_as_the_output_folder(tmp_path):
    """It said another kbbatch held the folder (its own inbox lock), which none did."""
    from click.testing import CliRunner

    result = CliRunner().invoke(cli.main, ["watch", str(tmp_path), "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "--out must be a folder other than the inbox" in result.output
    assert "another kbbatch" not in result.output


def test_watch_refuses_an_inbox_whose_folder_is_missing(tmp_path):
    """A share not mounted yet (or a typo): the daemon made the whole path and watched an empty
    local folder that the share then hid. An inbox in an existing folder is still made."""
    from click.testing import CliRunner

    missing = tmp_path / "share" / "inbox"
    result = CliRunner().invoke(cli.main, ["watch", str(missing), "--out", str(tmp_path / "o")])
    assert result.exit_code == 1
    assert f"{missing}: no such inbox, nor its folder" in result.output
    assert not (tmp_path / "share").exists() and not (tmp_path / "o").exists()
    (tmp_path / "a-file").write_text("x")
    result = CliRunner().invoke(cli.main, ["watch", str(tmp_path / "a-file"), "--out",
                                           str(tmp_path / "o")])
    assert result.exit_code == 2 and "is a file" in result.output

def test_plan_prints_the_render_command_that_repeats_its_options(tmp_path):
    """A manifest holds crops only: `plan --duration 1.5` wrote nothing of the duration, and
    the render that followed used the preset's."""
    import shlex

    from click.testing import CliRunner
    from PIL import Image

    from .conftest import textured_image

    (tmp_path / "photos").mkdir()
    Image.fromarray(textured_image(180, 320)).save(tmp_path / "photos" / "a.jpg")
    manifest = tmp_path / "m.json"
    result = CliRunner().invoke(cli.main, ["plan", str(tmp_path / "photos"), "-o", str(manifest),
                                           "--preset", "preview", "--duration", "1.5",
                                           "--depth", "ramp", "--quiet"])
    assert result.exit_code == 0, result.output
    [line] = [line for line in result.output.splitlines() if line.startswith("render them")]
    program, *arguments = shlex.split(line.removeprefix("render them with: "))
    render = cli.render.make_context(program, arguments).params
    assert (render["preset_name"], render["duration"], render["depth_backend"]) == (
        "preview", 1.5, "ramp")


def test_plan_carries_a_renamed_photos_entry_and_the_render_names_it(tmp_path):
    """A photo renamed after `plan`: the second plan kept the old entry without a word and
    planned the photo afresh (its crops lost), and the render it suggested failed on the
    old entry; the render alone did not say the photo is there under a new name."""
    import json

    from click.testing import CliRunner
    from PIL import Image

    from .conftest import textured_image

    photos, manifest = tmp_path / "photos", tmp_path / "m.json"
    photos.mkdir()
    Image.fromarray(textured_image(180, 320)).save(photos / "cup.jpg")
    options = ["--preset", "preview", "--depth", "ramp", "--quiet"]
    render = [str(photos), "-o", str(tmp_path / "out"), "--manifest", str(manifest),
              "--duration", "0.4", *options]
    result = CliRunner().invoke(cli.main, ["plan", str(photos), "-o", str(manifest), *options])
    assert result.exit_code == 0 and "NOTE" not in result.output, result.output
    planned = json.loads(manifest.read_text())
    planned["images"]["cup.jpg"]["exclude"] = False  # the user's, carried with the crops
    manifest.write_text(json.dumps(planned))
    (photos / "cup.jpg").rename(photos / "mug.jpg")
    result = CliRunner().invoke(cli.main, render)
    assert result.exit_code == 1, result.output
    assert "image 'cup.jpg': no photo of that file name" in result.output
    assert "'mug.jpg' has the bytes it was planned for (renamed?): give the entry its name" \
        in result.output, result.output
    result = CliRunner().invoke(cli.main, ["plan", str(photos), "-o", str(manifest), *options])
    assert result.exit_code == 0, result.output
    assert "the entry of 'cup.jpg' is now 'mug.jpg''s" in result.output, result.output
    assert json.loads(manifest.read_text())["images"] == {"mug.jpg": planned["images"]["cup.jpg"]}
    result = CliRunner().invoke(cli.main, render)
    assert result.exit_code == 0, result.output


def test_plan_checks_where_the_manifest_goes_before_planning(tmp_path):
    """Into a folder that cannot be written (or under a file), plan worked through every
    photo and then ended in a traceback, the planning lost."""
    from click.testing import CliRunner
    from PIL import Image

    from .conftest import textured_image

    (tmp_path / "photos").mkdir()
    Image.fromarray(textured_image(180, 320)).save(tmp_path / "photos" / "a.jpg")
    (tmp_path / "afile").write_text("a file, not a folder")
    result = CliRunner().invoke(cli.main, ["plan", str(tmp_path / "photos"), "-o",
                                           str(tmp_path / "afile" / "m.json"), "--depth",
                                           "ramp", "--quiet"])
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit)
    assert "afile: output folder is not writable" in result.output
    assert "plan(s) written" not in result.output


@pytest.mark.parametrize("arguments, message", [
    (["--depth", "onnx"], "no depth network is cached"),
    (["--depth-model", "midas-v21-small"], "model midas-v21-small is not in"),
])
def test_a_depth_network_asked_for_and_absent_is_said_once_at_start(
        tmp_path, monkeypatch, arguments, message):
    """It failed every photo with a line that did not name the photo."""
    from click.testing import CliRunner

    from kbbatch import models
    from tests.test_models import tiny_depth_model

    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path / "no-models"))
    (tmp_path / "photos").mkdir()
    result = CliRunner().invoke(cli.main, [str(tmp_path / "photos"), "-o", str(tmp_path / "o"),
                                           *arguments])
    assert result.exit_code == 2 and message in result.output
    assert not (tmp_path / "o").exists()
    # a cached model named beside --depth file (maps of one's own) is no error
    (tmp_path / "no-models").mkdir()
    (tmp_path / "no-models" / models.REGISTRY["midas-v21-small"].filename).write_bytes(
        tiny_depth_model())
    with_file = CliRunner().invoke(cli.main, [str(tmp_path / "photos"), "-o",
                                              str(tmp_path / "o"), "--depth", "file",
                                              "--depth-model", "midas-v21-small"])
    assert with_file.exit_code == 3 and "no photos here" in with_file.output


def test_the_run_report_names_the_folders_by_their_absolute_paths(tmp_path, monkeypatch):
    import json

    from click.testing import CliRunner
    from PIL import Image

    from .conftest import textured_image

    (tmp_path / "photos").mkdir()
    Image.fromarray(textured_image(180, 320)).save(tmp_path / "photos" / "a.jpg")
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(cli.main, ["photos", "-o", "photos/../out", "--depth", "ramp",
                                           "--planner", "center", "--preset", "preview",
                                           "--duration", "0.6", "--fps", "10", "--quiet"])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "out" / "kbbatch-report.json").read_text())
    assert report["folder"] == str(tmp_path / "photos")
    # the output folder as it is found again, in the report and in the summary
    assert report["output_folder"] == str(tmp_path / "out")
    assert f"1 clip(s) made in {tmp_path / 'out'}," in result.output


def test_render_refuses_more_threads_than_four_per_core(tmp_path):
    """--threads 1000 kept two frames per thread in memory (a typo away from running out)."""
    import os

    from click.testing import CliRunner

    (tmp_path / "in").mkdir()
    most = cli.JOBS_PER_CORE_MAX * (os.cpu_count() or 1)
    result = CliRunner().invoke(cli.main, ["render", str(tmp_path / "in"), "-o",
                                           str(tmp_path / "out"), "--threads", str(most + 1)])
    assert result.exit_code == 2 and f"at most {most} here" in result.output, result.output
    assert not (tmp_path / "out").exists()


def test_status_names_a_failed_photo_once(tmp_path):
    from click.testing import CliRunner

    from kbbatch.journal import Journal

    photo = tmp_path / "IMG_1.jpg"
    journal = Journal(tmp_path / "out")
    try:
        journal.start(photo, "1:1", "settings", "IMG_1.mp4", "content")
        journal.finish(photo, "failed", 1.0, f"{photo}: EncodeError: ffmpeg failed")
    finally:
        journal.close()
    result = CliRunner().invoke(cli.main, ["status", str(tmp_path / "out")])
    assert f"FAILED {photo}: EncodeError: ffmpeg failed" in result.output, result.output
    assert result.output.count(str(photo)) == 1


def test_a_control_character_in_a_name_cannot_split_a_line_or_drive_the_terminal(tmp_path):
    """A newline in a photo's name once split its FAILED line (and its log record) in two."""
    import logging
    import subprocess
    import sys

    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "two\nlines.jpg").write_bytes(b"\xff\xd8 not a jpeg")
    (folder / "red\x1b[31m.jpg").write_bytes(b"\xff\xd8 not a jpeg")
    run = subprocess.run([sys.executable, "-m", "kbbatch", str(folder), "-o", str(tmp_path / "out"),
                          "--preset", "preview", "--quiet"], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 1, run.stderr
    failed = [line for line in run.stderr.splitlines() if line.startswith("FAILED")]
    assert len(failed) == 2, run.stderr
    assert any("two\\nlines.jpg" in line for line in failed), failed
    assert any("red\\x1b[31m.jpg" in line for line in failed), failed
    assert "\x1b" not in run.stderr

    record = logging.LogRecord("kbbatch", logging.WARNING, __file__, 1, "%s: skipped", ("a\nb",),
                               None)
    assert cli.OneLineFormatter(cli.TIMED_LOG_FORMAT).format(record).endswith(" a\\nb: skipped")


def test_save_depth_refuses_the_photo_folder_by_any_path(tmp_path):
    """--save-depth's maps, written among the photos, are read as the user's on the next run:
    refused for the folder itself, a link to it, and a bind mount of it (another path to the
    same folder, which resolving did not see)."""
    import subprocess

    from click.testing import CliRunner

    photos = tmp_path / "photos"
    photos.mkdir()
    (tmp_path / "link").symlink_to(photos)
    paths = [photos, tmp_path / "link"]
    mount = tmp_path / "mount"
    mount.mkdir()
    bound = subprocess.run(["mount", "--bind", str(photos), str(mount)], capture_output=True)
    if bound.returncode == 0:
        paths.append(mount)
    try:
        for path in paths:
            result = CliRunner().invoke(cli.main, ["render", str(photos), "-o", str(path),
                                                   "--save-depth"])
            assert result.exit_code == 1, (path, result.output)
            assert "--save-depth writes <name>.disparity.png" in result.output, path
    finally:
        if bound.returncode == 0:
            subprocess.run(["umount", "-l", str(mount)], check=False)
    if bound.returncode != 0:  # the folder and the link were checked
        pytest.skip(f"cannot bind-mount here: {bound.stderr.decode().strip()}")


def test_fps_and_duration_on_the_command_line_apply_under_an_entrys_own_preset(tmp_path):
    """`--fps 10 --duration 2` made a photo whose manifest entry names a preset at that
    preset's 25 fps and 1 s, without a word (the entry's preset was loaded afresh)."""
    import json

    from click.testing import CliRunner
    from PIL import Image

    from kbbatch.encode import probe
    from tests.conftest import textured_image

    photos = tmp_path / "photos"
    photos.mkdir()
    for seed, name in enumerate(("a.jpg", "b.jpg")):
        Image.fromarray(textured_image(180, 320, seed)).save(photos / name)
    (tmp_path / "tiny.toml").write_text(
        'base = "preview"\nwidth_px = 160\nheight_px = 90\nduration_s = 1\nfps = 25\n')
    manifest = tmp_path / "m.json"
    manifest.write_text(json.dumps({"version": 1, "images": {"a.jpg": {"preset": "tiny.toml"},
                                                             "b.jpg": {"preset": "tiny.toml",
                                                                       "duration_s": 1.5}}}))
    result = CliRunner().invoke(cli.main, [
        str(photos), "-o", str(tmp_path / "out"), "-p", "preview",
        "--manifest", str(manifest), "--fps", "10", "--duration", "2", "--depth", "ramp",
        "--quiet"])
    assert result.exit_code == 0, result.output
    a, b = (probe(tmp_path / "out" / name) for name in ("a.mp4", "b.mp4"))
    assert a.fps == pytest.approx(10) and b.fps == pytest.approx(10)
    assert (a.width_px, b.width_px) == (160, 160)  # the entry's preset, not the run's
    # 2 s forward, then back; the entry's own duration_s beats --duration
    assert a.duration_s == pytest.approx((2 * 20 - 2) / 10, abs=0.15)
    assert b.duration_s == pytest.approx((2 * 15 - 2) / 10, abs=0.15)
