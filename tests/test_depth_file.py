import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
from PIL import Image

from kbbatch.depth import DepthError, estimate_disparity

from .conftest import run_in_child, textured_image


def test_user_depth_png_beside_the_photo_is_honoured(tmp_path):
    photo = tmp_path / "scene.jpg"
    photo.write_bytes(b"unused")
    depth = np.full((50, 80), 4000, np.uint16)
    depth[10:30, 20:50] = 1000  # a near box
    cv2.imwrite(str(tmp_path / "scene.depth.png"), depth)
    result = estimate_disparity(textured_image(100, 160), photo)
    assert result.backend == "file" and result.disparity.shape == (100, 160)
    assert result.disparity[40, 70] == pytest.approx(4 * result.disparity[90, 5], rel=1e-3)


def test_user_disparity_npy_keeps_its_convention(tmp_path):
    photo = tmp_path / "p.png"
    disparity = np.linspace(1, 2, 40 * 60, dtype=np.float32).reshape(40, 60)
    np.save(tmp_path / "p.disparity.npy", disparity)
    result = estimate_disparity(textured_image(40, 60), photo)
    np.testing.assert_allclose(result.disparity, disparity, rtol=1e-5)


@pytest.mark.parametrize("data, reason", [
    (np.full((40, 60), np.nan, np.float32), "NaN"),
    (np.full((40, 60), 3.0, np.float32), "constant"),
    (np.linspace(1, 2, 40 * 40, dtype=np.float32).reshape(40, 40), "aspect"),
    (np.eye(40, 60, dtype=bool) | True, r"true/false values \(a mask\?\), not depths"),
])
def test_bad_depth_files_get_a_clear_error(tmp_path, data, reason):
    photo = tmp_path / "bad.jpg"
    np.save(tmp_path / "bad.depth.npy", data)
    with pytest.raises(DepthError, match=reason) as caught:
        estimate_disparity(textured_image(40, 60), photo)
    assert "bad.depth.npy" in str(caught.value)


def test_a_text_file_named_npy_is_said_to_be_no_npy_file(tmp_path):
    (tmp_path / "b.disparity.npy").write_text("not an array")
    with pytest.raises(DepthError, match=r"b.disparity.npy: not a readable .npy array \(it "
                       r"does not begin as a NumPy .npy file does\)"):
        estimate_disparity(textured_image(40, 60), tmp_path / "b.jpg")


def write_exr(path, channels: dict) -> None:
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def test_openexr_depth_pass_with_an_infinite_sky_is_honoured(tmp_path):
    photo = tmp_path / "render.png"
    depth = np.full((40, 60), np.inf, np.float32)  # a renderer's empty sky
    depth[20:] = 8.0
    depth[25:35, 10:30] = 2.0  # a near box on the ground
    colour = np.zeros((40, 60), np.float32)
    write_exr(tmp_path / "render.depth.exr", {"R": colour, "G": colour, "B": colour,
                                              "ViewLayer.Depth.Z": depth})
    result = estimate_disparity(textured_image(80, 120), photo)
    assert result.backend == "file" and result.disparity.shape == (80, 120)
    assert result.disparity[60, 40] == pytest.approx(4 * result.disparity[45, 100], rel=1e-3)
    # The sky takes the farthest known depth: as far as the ground, not a division by zero.
    assert result.disparity[5, 5] == pytest.approx(result.disparity[45, 100], rel=1e-3)


def test_openexr_without_a_depth_channel_or_corrupt_gets_a_clear_error(tmp_path):
    plane = np.ones((40, 60), np.float32)
    write_exr(tmp_path / "a.depth.exr", {"N.X": plane, "N.Y": plane})
    with pytest.raises(DepthError, match=r"a\.depth\.exr: no depth channel among \['N.X', 'N.Y'\]"):
        estimate_disparity(textured_image(40, 60), tmp_path / "a.jpg")
    (tmp_path / "b.depth.exr").write_bytes(b"v/1\x01 not really an exr")
    with pytest.raises(DepthError, match=r"b\.depth\.exr: not a readable OpenEXR file"):
        estimate_disparity(textured_image(40, 60), tmp_path / "b.jpg")
    rng = np.random.default_rng(1)
    write_exr(tmp_path / "whole.exr", {"Z": rng.random((400, 600), dtype=np.float32)})
    whole = (tmp_path / "whole.exr").read_bytes()
    (tmp_path / "c.depth.exr").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(DepthError, match=r"c\.depth\.exr: not a readable OpenEXR file"):
        estimate_disparity(textured_image(400, 600), tmp_path / "c.jpg")


def test_openexr_without_its_package_says_how_to_install_it(tmp_path, monkeypatch):

    write_exr(tmp_path / "c.depth.exr", {"Z": np.ones((40, 60), np.float32)})
    monkeypatch.setitem(sys.modules, "OpenEXR", None)  # as on a machine without the extra
    with pytest.raises(DepthError, match=r'c\.depth\.exr: .*pip install "kbbatch\[exr\]"'):
        estimate_disparity(textured_image(40, 60), tmp_path / "c.jpg")


def test_unknown_pixels_beside_an_object_take_the_depth_behind_it_not_the_farthest(tmp_path):
    """A depth sensor's shadow beside an object (zeros) was set to the farthest depth of the
    whole map: a pit beside the outline that the move tore open into shards of fill."""
    from kbbatch.depth.file import disparity_from_map

    depth = np.full((40, 60), 5.0, np.float32)  # a wall 5 m away
    depth[:8] = 40.0  # far away through a window at the top
    depth[15:35, 20:30] = 2.0  # an object in front of the wall
    depth[15:35, 30:34] = 0.0  # its shadow on the wall: unknown
    depth[0, 0] = 0.0  # unknown, with only far pixels around
    photo = np.full((40, 60, 3), 120, np.uint8)  # the wall and the shadow on it, grey
    photo[15:35, 20:30] = (200, 30, 40)  # the object, red
    disparity = disparity_from_map(depth, "depth", tmp_path / "a.depth.png", photo)
    assert disparity[20:30, 30:34] == pytest.approx(1 / 5.0)  # the wall behind, not 1/40
    assert disparity[0, 0] == pytest.approx(1 / 40.0)
    assert disparity[20, 25] == pytest.approx(1 / 2.0) and disparity[20, 45] == pytest.approx(0.2)


def test_unknown_pixels_of_an_objects_colour_take_its_depth(tmp_path):
    """A depth sensor leaves its frame's edge unknown, across objects too (TUM RGB-D: a chair
    at the left edge). Filled from the far side, the chair's edge went to the floor's depth:
    a sliver torn off the chair by a dotted crack in the frame."""
    from kbbatch.depth.file import disparity_from_map

    depth = np.full((240, 320), 4.0, np.float32)  # the floor
    depth[80:200, 0:120] = 1.5  # a chair reaching the left edge
    photo = np.full((240, 320, 3), 150, np.uint8)
    photo[80:200, 0:120] = (110, 30, 60)  # maroon
    photo[100:160, 200:230] = 10  # a black leg of something farther...
    photo[160:200, 140:230] = 10  # ... beside a black part of the chair
    depth[160:200, 140:230] = 1.5
    depth[:, 0:4] = 0.0  # the sensor's frame edge
    depth[100:160, 200:230] = 0.0  # the black leg, missed
    disparity = disparity_from_map(depth, "depth", tmp_path / "a.depth.png", photo)
    assert disparity[84:196, 0:4] == pytest.approx(1 / 1.5)  # the chair's edge, on the chair
    assert disparity[0:76, 0:4] == pytest.approx(1 / 4.0)  # the floor's, on the floor
    assert disparity[204:, 0:4] == pytest.approx(1 / 4.0)
    # The leg is not torn to the chair's depth, but for its foot, within reach of the chair's
    # black part it touches: their colours cannot tell them apart.
    assert disparity[100:150, 200:230] == pytest.approx(1 / 4.0)


def test_a_map_with_an_upper_case_suffix_is_found_and_a_photo_named_depth_is_a_photo(tmp_path):
    """`cat.depth.PNG` was left out of the photos as a map yet never used as one; and
    `dive.depth.40m.jpg`, a photo, was left out of the folder without a word."""
    from kbbatch.images import list_images

    depth = np.full((50, 80), 4000, np.uint16)
    depth[10:30, 20:50] = 1000
    cv2.imwrite(str(tmp_path / "cat.depth.PNG"), depth)
    (tmp_path / "cat.jpg").write_bytes(b"unused")
    result = estimate_disparity(textured_image(100, 160), tmp_path / "cat.jpg")
    assert result.backend == "file" and "cat.depth.PNG" in result.source
    for name in ("dive.depth.40m.jpg", "stereo.disparity.test.png", "plain.jpg"):
        cv2.imwrite(str(tmp_path / name), textured_image(20, 30))
    assert sorted(p.name for p in list_images(tmp_path)) == [
        "cat.jpg", "dive.depth.40m.jpg", "plain.jpg", "stereo.disparity.test.png"]
    cv2.imwrite(str(tmp_path / "dog.Depth.Png"), depth)  # any spelling of the suffix
    assert "dog.Depth.Png" in estimate_disparity(textured_image(100, 160),
                                                 tmp_path / "dog.jpg").source
    # The photo's name says "disparity"; its map's own suffix says depth, and rules.
    cv2.imwrite(str(tmp_path / "stereo.disparity.test.depth.png"), depth)
    result = estimate_disparity(textured_image(100, 160), tmp_path / "stereo.disparity.test.png")
    assert result.disparity[40, 70] == pytest.approx(4 * result.disparity[90, 5], rel=1e-3)


def test_a_colour_mapped_picture_is_refused_as_a_depth_map_and_grey_as_colour_is_read(
        tmp_path):
    """A false-colour depth picture was read from its blue channel: depth out of order."""
    gradient = np.tile(np.linspace(10, 250, 60).astype(np.uint8), (40, 1))
    cv2.imwrite(str(tmp_path / "a.disparity.png"),
                cv2.applyColorMap(gradient, cv2.COLORMAP_TURBO))
    with pytest.raises(DepthError, match=r"a.disparity.png: is a colour picture"):
        estimate_disparity(textured_image(40, 60), tmp_path / "a.jpg")
    cv2.imwrite(str(tmp_path / "b.disparity.png"), cv2.merge([gradient] * 3))
    result = estimate_disparity(textured_image(40, 60), tmp_path / "b.jpg")
    assert result.disparity[20, 55] > result.disparity[20, 5]
    np.save(tmp_path / "c.disparity.npy", gradient[None].astype(np.float32))  # (1, H, W)
    assert estimate_disparity(textured_image(40, 60), tmp_path / "c.jpg").backend == "file"
    records = np.zeros((40, 60), dtype=[("near", "f4"), ("far", "f4")])
    np.save(tmp_path / "d.depth.npy", records)  # named the photo, as a TypeError
    with pytest.raises(DepthError, match=r"d.depth.npy: holds .* not numbers"):
        estimate_disparity(textured_image(40, 60), tmp_path / "d.jpg")


def test_a_float64_map_beyond_float32s_range_is_read_and_a_complex_one_refused(tmp_path):
    """Cast to float32, depths of 1e-60 all became 0 ("fewer than half of its pixels hold a
    positive value") and 1e300 infinite; complex values lost their imaginary parts with a
    warning and were used."""
    depth = np.ones((40, 60))
    depth[10:30, 20:40] = 0.25  # a near square
    for scale in (1e-60, 1e300):
        np.save(tmp_path / f"{scale:g}.depth.npy", depth * scale)
        result = estimate_disparity(textured_image(40, 60), tmp_path / f"{scale:g}.jpg")
        assert result.disparity[20, 30] == pytest.approx(4 * result.disparity[2, 2], rel=1e-3)
    np.save(tmp_path / "c.depth.npy", depth.astype(complex))
    with pytest.raises(DepthError, match=r"c.depth.npy: holds complex numbers"):
        estimate_disparity(textured_image(40, 60), tmp_path / "c.jpg")


def test_a_damaged_png_map_is_said_in_one_line_without_opencvs_own(tmp_path):
    """OpenCV printed its own `[ERROR:0@3.9] global grfmt_png.cpp:296 readHeader ...` lines
    above the tool's message; they are kept off the terminal (a child process: OpenCV
    writes them to its own standard error, which capsys does not see)."""
    (tmp_path / "a.depth.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    script = (
        "import sys\n"
        "from pathlib import Path\n"
        "import numpy as np\n"
        "from kbbatch.depth import DepthError, estimate_disparity\n"
        "try:\n"
        "    estimate_disparity(np.zeros((40, 60, 3), np.uint8), Path(sys.argv[1]) / 'a.jpg')\n"
        "except DepthError as error:\n"
        "    print(error)\n"
    )
    run = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True,
                         text=True, timeout=120)
    assert run.stdout.strip() == f"{tmp_path / 'a.depth.png'}: not a readable image"
    assert "grfmt" not in run.stderr and "ERROR" not in run.stderr, run.stderr


def test_a_map_beside_a_photo_in_a_folder_whose_name_is_not_utf8_is_read(tmp_path):
    """cv2.imread took the name as UTF-8 and crashed the process (a segfault): the reading
    runs in a child process, so a crash fails the test, not the test run."""
    folder = tmp_path / os.fsdecode(b"caf\xe9")
    folder.mkdir()
    depth = np.full((50, 80), 4000, np.uint16)
    depth[10:30, 20:50] = 1000
    Image.fromarray(depth).save(folder / "scene.depth.png")
    script = (
        "import sys\n"
        "from pathlib import Path\n"
        "import numpy as np\n"
        "from kbbatch.depth import estimate_disparity\n"
        "result = estimate_disparity(np.zeros((100, 160, 3), np.uint8),\n"
        "                            Path(sys.argv[1]) / 'scene.jpg')\n"
        "print(result.backend, round(float(result.disparity[40, 70] / "
        "result.disparity[90, 5]), 3))\n"
    )
    assert run_in_child(script, folder).split() == ["file", "4.0"]


def test_a_map_kbbatch_saved_from_another_photo_is_not_taken_for_this_ones(
        tmp_path, quick_preset, monkeypatch, caplog):
    """--save-depth into a folder of photos left `IMG_1.disparity.png` of one photo beside
    another `IMG_1.jpg`, which a later run took for its depth map."""
    import logging
    import shutil

    from kbbatch.batch import run_folder
    from kbbatch.depth import DepthOptions
    from kbbatch.images import is_own_png, write_image
    from kbbatch.pipeline import ClipOptions

    monkeypatch.setenv("KBBATCH_MODELS", str(tmp_path / "no-models"))
    first, second = tmp_path / "xa", tmp_path / "xb"
    first.mkdir()
    second.mkdir()
    Image.fromarray(textured_image(180, 320)).save(first / "IMG_1.jpg")
    Image.fromarray(textured_image(180, 320, seed=1)).save(second / "IMG_1.jpg")
    saving = ClipOptions(planner="center", depth=DepthOptions(backend="popup"), threads=2,
                         save_depth=True)
    assert run_folder(first, second, quick_preset, saving, False).results[0].status == "done"
    saved = second / "IMG_1.disparity.png"
    assert is_own_png(saved)

    with caplog.at_level(logging.WARNING):
        report = run_folder(second, tmp_path / "out", quick_preset,
                            ClipOptions(planner="center", threads=2), False)
    assert report.results[0].status == "done"
    assert report.results[0].depth_backend != "file"
    said = [r.getMessage() for r in caplog.records if "not used as the depth map" in
            r.getMessage()]
    assert said == [f"{saved}: not used as the depth map of {second / 'IMG_1.jpg'}: kbbatch "
                    "wrote it (--save-depth) from another photo"]
    with pytest.raises(DepthError, match="--depth file needs"):
        estimate_disparity(textured_image(180, 320, seed=1), second / "IMG_1.jpg",
                           DepthOptions(backend="file"))

    # beside the photo it was made from, it is that photo's depth
    shutil.copy(saved, first / "IMG_1.disparity.png")
    assert estimate_disparity(textured_image(180, 320), first / "IMG_1.jpg").backend == "file"

    # edited in an editor, it loses kbbatch's mark and is the user's map: used
    with Image.open(saved) as edited:
        edited.load()
    edited.save(saved)
    assert not is_own_png(saved)
    assert estimate_disparity(textured_image(180, 320, seed=1),
                              second / "IMG_1.jpg").backend == "file"

    # a map kbbatch wrote that records no photo (an earlier version's) is not taken either
    write_image(saved, np.arange(180 * 320, dtype=np.uint16).reshape(180, 320), own=True)
    assert estimate_disparity(textured_image(180, 320, seed=1),
                              second / "IMG_1.jpg").backend != "file"


def test_an_openexr_map_in_a_folder_whose_name_is_not_utf8_is_read(tmp_path):
    folder = tmp_path / os.fsdecode(b"caf\xe9")
    folder.mkdir()
    depth = np.full((40, 60), 8.0, np.float32)
    depth[10:30, 20:40] = 2.0
    write_exr(tmp_path / "ascii.exr", {"Z": depth})
    (folder / "scene.depth.exr").write_bytes((tmp_path / "ascii.exr").read_bytes())
    result = estimate_disparity(textured_image(40, 60), folder / "scene.jpg")
    assert result.backend == "file"
    assert result.disparity[20, 30] == pytest.approx(4 * result.disparity[2, 2], rel=1e-3)


def test_a_map_smaller_than_the_photo_is_refined_onto_its_colour_edges(tmp_path):
    """A user's map at a quarter of the size (a phone's depth, a network run elsewhere) was
    enlarged bilinearly: every edge a ramp of depths between object and background, off the
    object's real outline, that the move smeared into faint copies of the edge."""
    height, width = 240, 360
    image = textured_image(height, width, seed=2) // 4 + 20
    image[:, 181:] += 150  # an object right of column 181 (not on the map's grid)
    depth = np.where(np.arange(width) > 180, 1000, 5000).astype(np.uint16)[None]
    depth = cv2.resize(depth.repeat(height, 0), (width // 4, height // 4),
                       interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(tmp_path / "a.depth.png"), depth)
    (tmp_path / "a.jpg").write_bytes(b"unused")
    row = estimate_disparity(image, tmp_path / "a.jpg").disparity[height // 2]
    near, far = row.max(), row.min()
    assert near == pytest.approx(1 / 1000, rel=0.05) and far == pytest.approx(1 / 5000, rel=0.05)
    assert int(np.argmax(row > 0.5 * (near + far))) == 181
    assert not ((row > far * 1.01) & (row < near * 0.99)).any(), "no depth between the sides"


def test_a_map_name_that_is_no_regular_file_is_said_not_passed_over(tmp_path, caplog):
    """A named pipe or a link to /dev/zero under the photo's map name was passed over without
    a word: the clip was made with the pop-up depth, and nobody knew why."""
    import logging

    from kbbatch.depth.file import find_depth_file

    for stem, make in (("piped", lambda path: os.mkfifo(path)),
                       ("linked", lambda path: path.symlink_to("/dev/zero"))):
        photo = tmp_path / f"{stem}.jpg"
        Image.fromarray(textured_image(60, 80, seed=1)).save(photo)
        make(tmp_path / f"{stem}.depth.png")
        with caplog.at_level(logging.WARNING):
            assert find_depth_file(photo) is None
            assert find_depth_file(photo) is None  # looked for again: said once
        said = [r.getMessage() for r in caplog.records if f"{stem}.depth.png" in r.getMessage()]
        assert len(said) == 1 and "not a regular file" in said[0], said


def test_a_depth_and_a_disparity_map_of_one_photo_are_said_once(tmp_path, caplog):
    """Both beside the photo, the depth map was used without a word: a user who meant the
    disparity map saw its depth reversed and never knew why."""
    import logging

    from kbbatch.depth.file import find_depth_file

    photo = tmp_path / "both.jpg"
    Image.fromarray(textured_image(60, 80, seed=1)).save(photo)
    ramp = np.tile(np.linspace(1000, 9000, 80).astype(np.uint16), (60, 1))
    cv2.imwrite(str(tmp_path / "both.depth.png"), ramp)
    np.save(tmp_path / "both.disparity.npy", ramp.astype(np.float32))
    with caplog.at_level(logging.WARNING):
        assert find_depth_file(photo).name == "both.depth.png"
        assert find_depth_file(photo).name == "both.depth.png"  # looked for again: said once
    said = [r.getMessage() for r in caplog.records if "both.jpg" in r.getMessage()]
    assert said == [f"{photo}: both.depth.png and both.disparity.npy are maps of this "
                    "photo; both.depth.png is used (depth before disparity, PNG before .npy "
                    "before .exr): remove the others"], said


def test_a_map_with_no_photo_of_its_name_is_said_not_passed_over(tmp_path):
    """A photo saved under a map's name (`holiday.depth.png`), or a map whose photo was
    renamed, was left out without a word: a folder of only such files said "no photos here"
    naming none of them, and beside other photos the report's notes were empty."""
    import subprocess

    from kbbatch.images import LONE_MAP_REASON, scan_folder

    cv2.imwrite(str(tmp_path / "holiday.depth.png"), textured_image(20, 30))
    cv2.imwrite(str(tmp_path / "stereo.disparity.png"), textured_image(20, 30))
    np.save(tmp_path / "cat.depth.npy", np.ones((20, 30), np.float32))
    (tmp_path / "cat.HEIC").write_bytes(b"a photo in a format not read: its map is no orphan")
    cv2.imwrite(str(tmp_path / "sunset.depth-preview.png"), textured_image(20, 30))
    scan = scan_folder(tmp_path)
    assert [p.name for p in scan.lone_maps] == ["holiday.depth.png", "stereo.disparity.png",
                                                 "sunset.depth-preview.png"]
    run = subprocess.run([sys.executable, "-m", "kbbatch", str(tmp_path), "-o",
                          str(tmp_path / "out")], capture_output=True, text=True, timeout=120)
    assert run.returncode == 3, run.stderr
    assert f"holiday.depth.png, stereo.disparity.png, sunset.depth-preview.png: " \
        f"{LONE_MAP_REASON}" in run.stderr, \
        run.stderr
    cv2.imwrite(str(tmp_path / "holiday.jpg"), textured_image(20, 30))  # its photo comes
    assert [p.name for p in scan_folder(tmp_path).lone_maps] == [
        "stereo.disparity.png", "sunset.depth-preview.png"]


def test_a_photos_bad_map_fails_the_photo_by_its_name(tmp_path, quick_preset):
    """The failure named only `a.depth.png`: which photo failed was left to guess."""
    from kbbatch.batch import run_folder
    from kbbatch.pipeline import ClipOptions

    photo = tmp_path / "in" / "a.jpg"
    photo.parent.mkdir()
    Image.fromarray(textured_image(180, 320)).save(photo)
    (tmp_path / "in" / "a.depth.png").write_bytes(b"no picture")
    report = run_folder(tmp_path / "in", tmp_path / "out", quick_preset,
                        ClipOptions(planner="center", threads=2), False)
    assert report.results[0].status == "failed"
    assert report.results[0].error.startswith(f"{photo}: {tmp_path / 'in' / 'a.depth.png'}: ")
