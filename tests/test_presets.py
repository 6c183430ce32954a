import pytest

from kbbatch.presets import PresetError, builtin_names, load_preset, with_overrides

SHIPPED = {
    "slideshow": (1920, 1080, 30), "social": (1080, 1920, 30), "square": (1080, 1080, 30),
    "preview": (640, 360, 25), "4k": (3840, 2160, 30),
}


def test_shipped_presets_load_with_their_sizes():
    assert set(SHIPPED) <= set(builtin_names())
    for name, (width, height, fps) in SHIPPED.items():
        preset = load_preset(name)
        assert (preset.width_px, preset.height_px, preset.fps) == (width, height, fps)
        assert preset.frames_total == 2 * preset.frames_forward - 2


def test_preset_from_path_and_errors_name_the_field(tmp_path):
    text = (tmp_path / "mine.toml")
    base = (load_preset("preview"))
    lines = [f'{k} = {v!r}'.replace("'", '"') for k, v in vars(base).items() if k != "name"]
    text.write_text("\n".join(lines))
    assert load_preset(str(text)).name == "mine"
    text.write_text("\n".join(lines).replace("crf = 28", 'crf = "high"'))
    with pytest.raises(PresetError, match=r"mine.toml: setting 'crf' must be an integer"):
        load_preset(str(text))
    text.write_text("\n".join(lines).replace("width_px = 640", "width_px = 641"))
    with pytest.raises(PresetError, match="'width_px' must be even"):
        load_preset(str(text))
    text.write_text("\n".join(lines) + "\nbogus = 1")
    with pytest.raises(PresetError, match="unknown setting"):
        load_preset(str(text))
    text.write_text("width_px = [")
    with pytest.raises(PresetError, match="not valid TOML"):
        load_preset(str(text))


def test_unknown_preset_and_override_validation():
    with pytest.raises(PresetError, match="unknown preset 'nope'"):
        load_preset("nope")
    with pytest.raises(PresetError, match="'easing' must be one of"):
        with_overrides(load_preset("preview"), easing="bounce")
    assert with_overrides(load_preset("preview"), duration_s=1.0).frames_forward == 25
