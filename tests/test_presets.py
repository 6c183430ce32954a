import tomllib
from importlib import resources

import pytest
from click.testing import CliRunner

from kbbatch.cli import main
from kbbatch.presets import PresetError, builtin_names, load_preset, schema, with_overrides


def test_every_shipped_preset_loads_as_its_file_says():
    assert {"slideshow", "social", "square", "preview", "4k", "reference"} <= set(builtin_names())
    for name in builtin_names():
        data = tomllib.loads(resources.files("kbbatch.presets").joinpath(f"{name}.toml")
                             .read_text())
        preset = load_preset(name)
        assert preset.name == name
        for setting, value in data.items():
            assert getattr(preset, setting) == value, (name, setting)
        assert preset.frames_total == 2 * preset.frames_forward - 2


def write(path, text):
    path.write_text(text)
    return str(path)


def test_a_preset_extends_a_shipped_one_and_sets_only_what_differs(tmp_path):
    mine = load_preset(write(tmp_path / "mine.toml", 'base = "slideshow"\ncrf = 30\n'))
    slideshow = load_preset("slideshow")
    assert mine.name == "mine" and mine.crf == 30
    assert mine.description == "slideshow with changes"
    assert (mine.width_px, mine.fps, mine.codec) == (slideshow.width_px, slideshow.fps,
                                                      slideshow.codec)
    # A chain of files, each relative to the one that names it.
    (tmp_path / "team").mkdir()
    write(tmp_path / "team" / "base.toml", 'base = "../mine.toml"\nfps = 24\n'
                                           'description = "our look"\n')
    top = load_preset(write(tmp_path / "top.toml", 'base = "team/base.toml"\nzoom = 1.5\n'))
    assert (top.crf, top.fps, top.zoom) == (30, 24.0, 1.5)
    assert load_preset(str(tmp_path / "team" / "base.toml")).description == "our look"
    assert top.description == "team/base.toml with changes"  # a base's words are its own
    write(tmp_path / "loop.toml", 'base = "loop2.toml"\n')
    write(tmp_path / "loop2.toml", 'base = "loop.toml"\n')
    with pytest.raises(PresetError, match="loops back"):
        load_preset(str(tmp_path / "loop.toml"))
    with pytest.raises(PresetError, match="unknown preset 'slidesho'"):
        load_preset(write(tmp_path / "typo.toml", 'base = "slidesho"\n'))


def test_without_a_base_every_setting_but_the_description_is_required(tmp_path):
    lines = [f"{k} = {v!r}".replace("'", '"') for k, v in vars(load_preset("preview")).items()
             if k not in ("name", "description")]
    assert load_preset(write(tmp_path / "full.toml", "\n".join(lines))).description == ""
    with pytest.raises(PresetError, match=r"part.toml: missing setting\(s\) 'codec'; give "
                       r"them, or start the file with base = \"slideshow\""):
        load_preset(write(tmp_path / "part.toml", "\n".join(lines[:-4] + lines[-3:])))
    # an empty file: one line, not twelve "required property" errors
    with pytest.raises(PresetError, match=r"empty.toml: missing setting\(s\) 'width_px', "):
        load_preset(write(tmp_path / "empty.toml", ""))


@pytest.mark.parametrize("line, message", [
    ('crf = "high"', r"setting 'crf': 'high' is not of type 'integer'"),
    ("width_px = 641", r"setting 'width_px': 641 is not a multiple of 2"),
    ("fps = nan", r"setting 'fps' must be a finite number"),
    ("fps = 0", r"setting 'fps': 0 is less than the minimum of 1"),
    ('easing = "bounce"', r"setting 'easing': 'bounce' is not one of \['linear', 'ease-in-out'"),
    ("bogus = 1", r"unknown setting\(s\) bogus; known: base, name, description"),
    ("width_px = [", r"not valid TOML"),
    ('codec = "libx999"', r"setting 'codec': ffmpeg .* has no video encoder 'libx999'"),
    ('pix_fmt = "yuv999p"', r"setting 'pix_fmt': libx264 cannot write 'yuv999p'; it offers .*"
                            r"yuv420p"),
    ('encoder_preset = "fastest"', r"setting 'encoder_preset': ffmpeg refuses libx264 with "
                                   r"encoder_preset 'fastest'"),
])
def test_errors_name_the_file_and_the_setting(tmp_path, line, message):
    path = write(tmp_path / "mine.toml", f'base = "preview"\n{line}\n')
    with pytest.raises(PresetError, match=r"mine.toml: " + message):
        load_preset(path)


@pytest.mark.parametrize("base, message", [
    ("4K", r"mine.toml: setting 'base': unknown preset '4K'"),  # the file was not named
    ("", r"mine.toml: setting 'base': '' should be non-empty"),  # was "a folder": the cwd
    ("./gone.toml", r"mine.toml: setting 'base': .*gone.toml: preset file not found"),
])
def test_a_bad_base_is_blamed_on_the_file_that_names_it(tmp_path, base, message):
    path = write(tmp_path / "mine.toml", f'base = "{base}"\nfps = 10\n')
    with pytest.raises(PresetError, match=message):
        load_preset(path)


def test_whole_numbers_written_with_a_point_are_whole_numbers(tmp_path):
    """`width_px = 640.0` passed the schema (a JSON Schema integer) and then failed at every
    photo with "'float' object cannot be interpreted as an integer"."""
    preset = load_preset(write(tmp_path / "mine.toml", 'base = "preview"\nwidth_px = 640.0\n'
                                                       "height_px = 360.0\ncrf = 30.0\n"))
    assert (preset.width_px, preset.height_px, preset.crf) == (640, 360, 30)
    assert all(type(value) is int for value in (preset.width_px, preset.height_px, preset.crf))


def test_reference_preset_is_the_papers_automatic_clip():
    reference = load_preset("reference")  # section 3.4: 75 linear steps at 25 fps
    assert (reference.frames_forward, reference.fps, reference.easing) == (75, 25, "linear")
    assert (reference.zoom, reference.max_shift_px) == (1.25, 100)


def test_presets_command_lists_every_preset_and_setting():
    output = CliRunner().invoke(main, ["presets"]).output
    for name in builtin_names():
        assert f"\n{name}: " in f"\n{output}"
    for setting in schema()["properties"]:
        assert f"  {setting} " in output


def test_schema_easings_are_the_cameras():
    from kbbatch.camera import EASINGS

    assert schema()["properties"]["easing"]["enum"] == list(EASINGS)


def test_unknown_preset_and_override_validation():
    with pytest.raises(PresetError, match="unknown preset 'nope'"):
        load_preset("nope")
    with pytest.raises(PresetError, match="setting 'easing': 'bounce' is not one of"):
        with_overrides(load_preset("preview"), easing="bounce")
    assert with_overrides(load_preset("preview"), duration_s=1.0).frames_forward == 25


@pytest.mark.parametrize("arguments, option", [
    (["--fps", "nan"], "--fps"), (["--fps", "0"], "--fps"), (["--duration", "-1"], "--duration"),
    (["--preset", "nope"], "--preset"),
])
def test_cli_blames_the_option_that_is_wrong(tmp_path, arguments, option):
    result = CliRunner().invoke(main, ["render", str(tmp_path), *arguments])
    assert result.exit_code == 2
    assert f"Invalid value for {option}:" in result.output
    assert "Traceback" not in result.output


def test_a_preset_naming_an_encoder_this_ffmpeg_lacks_fails_at_load(tmp_path):
    from kbbatch.encode import _encoders

    absent = [c for c in ("h264_videotoolbox", "hevc_videotoolbox", "h264_mf", "h264_omx")
              if c not in _encoders()]
    if not absent:
        pytest.skip("this ffmpeg has every platform's hardware encoder")
    path = write(tmp_path / "mac.toml", f'base = "slideshow"\ncodec = "{absent[0]}"\n')
    with pytest.raises(PresetError, match=rf"mac.toml: setting 'codec': ffmpeg .* has no video "
                                          rf"encoder '{absent[0]}'"):
        load_preset(path)


def test_nvenc_without_an_nvidia_gpu_blames_the_codec_at_load(tmp_path):
    from kbbatch.encode import _encoders, encoder_refusal

    path = write(tmp_path / "nvenc.toml",
                 'base = "slideshow"\ncodec = "h264_nvenc"\nencoder_preset = "p5"\n')
    if "h264_nvenc" not in _encoders():
        with pytest.raises(PresetError, match="has no video encoder 'h264_nvenc'"):
            load_preset(path)
        return
    if encoder_refusal("h264_nvenc", "yuv420p", "p5", 18) is None:
        assert load_preset(path).codec == "h264_nvenc"  # a machine with a working NVENC
        return
    with pytest.raises(PresetError, match=r"nvenc.toml: setting 'codec': ffmpeg refuses "
                                          r"h264_nvenc with codec 'h264_nvenc': .*needs an "
                                          r"NVIDIA GPU and its driver"):
        load_preset(path)


def test_a_shipped_name_means_the_shipped_preset_whatever_the_current_folder_holds(
        tmp_path, monkeypatch):
    """`kbbatch photos -o preview --preset preview` worked once; the second run took the new
    output folder for a preset file and failed (a file named 4k did the same)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "preview").mkdir()
    (tmp_path / "4k").write_text("not toml at all\n")
    shipped = tomllib.loads(resources.files("kbbatch.presets").joinpath("preview.toml")
                            .read_text())
    assert load_preset("preview").width_px == shipped["width_px"]
    assert load_preset("4k").name == "4k"
    with pytest.raises(PresetError, match="a folder, not a preset file"):
        load_preset("preview/")


def test_a_preset_file_in_another_encoding_is_refused_by_name_and_a_bom_is_read(tmp_path):
    utf16 = tmp_path / "utf16.toml"
    utf16.write_text('base = "preview"\n', encoding="utf-16")
    with pytest.raises(PresetError, match=r"utf16\.toml: not a UTF-8 text file"):
        load_preset(str(utf16))
    bom = tmp_path / "bom.toml"
    bom.write_text('base = "preview"\ncrf = 30\n', encoding="utf-8-sig")
    assert load_preset(str(bom)).crf == 30


@pytest.mark.parametrize("codec", ["rawvideo", "gif"])
def test_a_codec_no_mp4_holds_fails_when_the_preset_loads_not_at_every_photo(tmp_path, codec):
    path = write(tmp_path / f"{codec}.toml", f'base = "preview"\ncodec = "{codec}"\n'
                 + ('pix_fmt = "rgb8"\n' if codec == "gif" else ""))
    with pytest.raises(PresetError, match=rf"{codec}\.toml: setting 'codec'.*container"):
        load_preset(path)


def test_a_preset_with_several_bad_settings_names_them_all(tmp_path):
    path = tmp_path / "odd.toml"
    path.write_text('base = "preview"\nwidth_px = 1921\nheight_px = 1081\n')
    with pytest.raises(PresetError) as caught:
        load_preset(str(path))
    message = str(caught.value)
    assert "setting 'width_px': 1921 is not a multiple of 2" in message, message
    assert "setting 'height_px': 1081 is not a multiple of 2" in message, message


def test_a_base_loop_through_dot_dot_and_a_long_chain_are_refused_by_name(tmp_path):
    """`base = "../pre/a.toml"` inside pre/a.toml grew the path until a traceback (file name
    too long); a chain of 1,200 bases overflowed the stack."""
    (tmp_path / "pre").mkdir()
    (tmp_path / "pre" / "a.toml").write_text('base = "../pre/a.toml"\n')
    with pytest.raises(PresetError, match="loops back to itself"):
        load_preset(str(tmp_path / "pre" / "a.toml"))
    for index in range(40):
        (tmp_path / f"c{index}.toml").write_text(f'base = "c{index + 1}.toml"\n')
    (tmp_path / "c40.toml").write_text('base = "preview"\n')
    with pytest.raises(PresetError, match="more than 16 bases deep"):
        load_preset(str(tmp_path / "c0.toml"))
    assert load_preset(str(tmp_path / "c30.toml")).width_px == 640  # ten deep: fine


def test_a_huge_file_given_as_a_preset_is_refused_unread(tmp_path):
    """A 3 GB file given as a preset was read whole: a MemoryError ended the batch."""
    huge = tmp_path / "huge.toml"
    with huge.open("wb") as handle:
        handle.truncate(3 << 30)  # sparse: no disk space taken
    with pytest.raises(PresetError, match=r"huge.toml: is larger than any preset"):
        load_preset(str(huge))
