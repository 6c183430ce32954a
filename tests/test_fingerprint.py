"""One fingerprint of every input of a clip: the journal re-makes a clip when any input changed
(a depth map beside the photo, a manifest's depth file edited in place, a network that appears
in the models folder) and skips it when none did; the depth cache keys on the depth inputs."""

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from kbbatch.batch import run_folder
from kbbatch.depth import DepthOptions
from kbbatch.fingerprint import depth_inputs, file_sha256
from kbbatch.manifest import manifest_from_data
from kbbatch.pipeline import ClipOptions, cached_disparity, clip_fingerprints
from kbbatch.presets import load_preset

from .conftest import SHARED, shared_photos, textured_image

PRESET = load_preset("preview")
DEFAULTS = ClipOptions()


def depth_map(path: Path, height: int, width: int, seed: int = 0) -> Path:
    """A 16-bit depth PNG: farther towards the top, with a near blob placed by the seed."""
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    depth = 1000 + 40000 * (1 - rows / height)
    centre = (height * (0.3 + 0.1 * seed), width * 0.5)
    depth[(rows - centre[0]) ** 2 + (cols - centre[1]) ** 2 < (height / 6) ** 2] = 800
    Image.fromarray(depth.astype(np.uint16)).save(path)
    return path


@pytest.fixture
def photo(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("KBBATCH_MODELS", str(tmp_path / "models"))  # no network present
    (tmp_path / "photos").mkdir()
    path = tmp_path / "photos" / "a.png"
    Image.fromarray(textured_image(120, 180)).save(path)
    return path


def fingerprint(photo: Path, options: ClipOptions = DEFAULTS, entry=None) -> str:
    return clip_fingerprints(photo, file_sha256(photo), PRESET, options, entry)[0]


def depth_key(photo: Path, options: DepthOptions = DEFAULTS.depth) -> str:
    return depth_inputs(photo, file_sha256(photo), options).digest((120, 180))


def test_a_depth_map_added_beside_the_photo_changes_clip_and_depth_key(photo):
    clip_before, depth_before, popup_before = (
        fingerprint(photo), depth_key(photo), depth_key(photo, DepthOptions(backend="popup")))
    depth_map(photo.with_name("other.depth.png"), 120, 180)  # another photo's map
    assert (fingerprint(photo), depth_key(photo)) == (clip_before, depth_before)
    depth_map(photo.with_name("a.depth.png"), 120, 180)
    assert fingerprint(photo) != clip_before
    assert depth_key(photo) != depth_before
    # --depth popup never reads the map, so its depth is still the cached one
    assert depth_key(photo, DepthOptions(backend="popup")) == popup_before


def test_a_manifest_depth_file_edited_in_place_changes_the_fingerprint(photo):
    manifest_path = photo.parent / "manifest.json"
    depth_path = depth_map(photo.parent / "maps.depth.png", 120, 180, seed=0)
    manifest = manifest_from_data({"images": {"a.png": {"depth": "maps.depth.png"}}},
                                  manifest_path)
    entry = manifest.entry("a.png")
    before_clip, before_depth = fingerprint(photo, entry=entry), fingerprint(photo)
    assert before_clip != before_depth, "the manifest's map is an input"
    stat = depth_path.stat()
    depth_map(depth_path, 120, 180, seed=2)  # new bytes, same name, size and time
    os.utime(depth_path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert fingerprint(photo, entry=entry) != before_clip
    depth_options = DepthOptions(file=str(depth_path))
    assert depth_inputs(photo, file_sha256(photo), depth_options).depth_file.sha256 == \
        file_sha256(depth_path)


def test_a_model_appearing_changes_the_fingerprint_and_the_depth_cache_is_not_reused(
        photo, tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    ramp = ClipOptions(depth=DepthOptions(backend="ramp"))
    image = textured_image(120, 180)
    cache = Path(os.environ["KBBATCH_CACHE"])
    clip_before, depth_before = fingerprint(photo, ramp), depth_key(photo)
    cached_disparity(image, photo, ramp)
    assert len(list(cache.glob("*.npz"))) == 1

    (models / "lama_fp32.onnx").write_bytes(b"inpainting weights")  # shapes frames, not depth
    clip_with_lama = fingerprint(photo, ramp)
    assert clip_with_lama != clip_before
    assert depth_key(photo) == depth_before
    cached_disparity(image, photo, ramp)
    assert len(list(cache.glob("*.npz"))) == 1, "depth was recomputed for an inpainting model"

    (models / "yolox_nano_coco_416.onnx").write_bytes(b"detector weights")
    assert fingerprint(photo, ramp) not in (clip_before, clip_with_lama)
    assert depth_key(photo) != depth_before
    cached_disparity(image, photo, ramp)
    assert len(list(cache.glob("*.npz"))) == 2, "depth made without the detector was reused"


def test_settings_that_do_not_shape_the_clip_leave_the_fingerprint_alone(photo):
    before = fingerprint(photo, ClipOptions(threads=1))
    assert fingerprint(photo, ClipOptions(threads=8)) == before
    assert fingerprint(photo, ClipOptions(threads=1, planner="2d")) != before
    shutil.copy(photo, photo.with_name("copy.png"))  # same bytes under another name
    assert fingerprint(photo.with_name("copy.png"), ClipOptions(threads=1)) == before


def test_batch_skips_unchanged_and_remakes_after_a_depth_map_or_a_model_appears(
        tmp_path, monkeypatch, quick_preset):
    """Real photo, real ffmpeg, real detector: the journal's up-to-date check end to end."""
    [source] = shared_photos(1)
    real_detector = SHARED / "models" / "yolox_nano_coco_416.onnx"
    if not real_detector.is_file():
        pytest.skip(f"real detector not found at {real_detector} (../shared is developer/CI only)")
    models = tmp_path / "models"
    models.mkdir()
    monkeypatch.setenv("KBBATCH_MODELS", str(models))
    folder, out = tmp_path / "in", tmp_path / "out"
    folder.mkdir()
    photo = folder / source.name
    shutil.copy(source, photo)
    options = ClipOptions(threads=2)

    def statuses() -> list[str]:
        report = run_folder(folder, out, quick_preset, options, show_progress=False)
        return [(r.status, r.depth_backend) for r in report.results]

    assert statuses() == [("done", "popup")]
    assert statuses() == [("skipped", "popup")]  # as the report of the run that made it says
    with Image.open(photo) as image:
        width, height = image.size
    depth_map(folder / f"{photo.stem}.depth.png", height // 4, width // 4)
    assert statuses() == [("done", "file")], "a depth map added beside the photo was ignored"
    assert statuses() == [("skipped", "file")]
    shutil.copy(real_detector, models / real_detector.name)
    assert statuses() == [("done", "file")], "a detector that appeared later was ignored"
    assert statuses() == [("skipped", "file")]
