import os

import cv2
import numpy as np
import pytest
from PIL import Image

from kbbatch.images import (
    ImageReadError,
    is_image_file,
    is_own_png,
    list_images,
    own_png_text,
    read_image,
)

from .conftest import run_in_child, textured_image


def save(path, array, mode=None, **kwargs):
    Image.fromarray(array, mode=mode).save(path, **kwargs) if mode else \
        Image.fromarray(array).save(path, **kwargs)
    return path


def test_exif_orientation_is_applied(tmp_path):
    image = Image.fromarray(textured_image(40, 60))
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 CW to display
    image.save(tmp_path / "rot.jpg", exif=exif.tobytes())
    assert read_image(tmp_path / "rot.jpg").shape == (60, 40, 3)


def test_sixteen_bit_grey_alpha_and_cmyk_become_rgb8(tmp_path):
    grey16 = (np.linspace(0, 65535, 50 * 40).reshape(40, 50)).astype(np.uint16)
    Image.fromarray(grey16).save(tmp_path / "g16.png")
    out = read_image(tmp_path / "g16.png")
    assert out.dtype == np.uint8 and out.shape == (40, 50, 3)
    assert out[0, 0, 0] == 0 and out[-1, -1, 0] == 255
    Image.fromarray(textured_image(30, 30)[..., 0]).save(tmp_path / "grey.png")
    assert read_image(tmp_path / "grey.png").shape == (30, 30, 3)
    rgba = np.zeros((20, 20, 4), np.uint8)
    rgba[..., 0] = 200
    rgba[:10, :, 3] = 255
    Image.fromarray(rgba, "RGBA").save(tmp_path / "alpha.png")
    out = read_image(tmp_path / "alpha.png")
    assert out[0, 0].tolist() == [200, 0, 0] and out[15, 0].tolist() == [0, 0, 0]
    Image.fromarray(textured_image(24, 24)).convert("CMYK").save(tmp_path / "cmyk.jpg")
    out = read_image(tmp_path / "cmyk.jpg")
    assert out.shape == (24, 24, 3)
    assert np.abs(out.astype(int) - textured_image(24, 24)).mean() < 20


@pytest.mark.parametrize("name, content, reason", [
    ("empty.jpg", b"", "empty"),
    ("text.jpg", b"this is not a photo", "not an image"),
])
def test_unreadable_files_name_the_file_and_reason(tmp_path, name, content, reason):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(ImageReadError, match=reason) as caught:
        read_image(tmp_path / name)
    assert name in str(caught.value)


def test_truncated_jpeg_is_reported(tmp_path):
    Image.fromarray(textured_image(200, 200)).save(tmp_path / "full.jpg", quality=95)
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageReadError, match="cut.jpg: is corrupt or truncated"):
        read_image(tmp_path / "cut.jpg")


def test_listing_takes_photos_of_any_case_and_skips_depth_maps(tmp_path):
    for name in ("a.JPG", "b.webp", "c.TIFF", "d.depth.png", ".hidden.jpg", "e.txt", "f.bmp"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in list_images(tmp_path)] == ["a.JPG", "b.webp", "c.TIFF", "f.bmp"]
    assert not is_image_file(tmp_path / "x.disparity.png")


def test_images_are_written_and_read_under_a_folder_name_that_is_not_utf8(tmp_path):
    """cv2.imwrite took the name as UTF-8 and crashed the process (a segfault), so the
    writing runs in a child process: a crash fails the test, not the test run."""
    folder = tmp_path / os.fsdecode(b"caf\xe9")
    script = (
        "import sys, numpy as np\n"
        "from pathlib import Path\n"
        "from kbbatch.images import write_image\n"
        "folder = Path(sys.argv[1])\n"
        "picture = (np.arange(30 * 40 * 3) % 251).astype(np.uint8).reshape(30, 40, 3)\n"
        "write_image(folder / 'plain.png', picture)\n"
        "write_image(folder / 'plain.jpg', picture)\n"
        "write_image(folder / 'grey16.png', np.full((30, 40), 40000, np.uint16))\n"
        "write_image(folder / 'own.png', picture, own=True,\n"
        "            text={'Comment': 'kept'})\n"
    )
    run_in_child(script, folder)
    picture = (np.arange(30 * 40 * 3) % 251).astype(np.uint8).reshape(30, 40, 3)
    assert np.array_equal(read_image(folder / "plain.png"), picture)
    assert read_image(folder / "plain.jpg").shape == (30, 40, 3)
    with Image.open(folder / "grey16.png") as grey:
        assert grey.mode.startswith("I") and grey.getpixel((0, 0)) == 40000
    assert is_own_png(folder / "own.png") and not is_own_png(folder / "plain.png")
    assert own_png_text(folder / "own.png")["Comment"] == "kept"
    assert sorted(p.name for p in folder.iterdir()) == ["grey16.png", "own.png", "plain.jpg",
                                                         "plain.png"]  # no temporary left



def matrix_profile(description: str, primaries_d50: list[tuple[float, float, float]],
                   gamma: float) -> bytes:
    """A minimal ICC v2 RGB display profile: white point, three primaries (XYZ, D50) and one
    gamma curve per channel, as Adobe RGB (1998) and Display P3 are made."""
    import struct

    def fixed(value: float) -> bytes:
        return struct.pack(">i", round(value * 65536))

    def xyz_tag(x: float, y: float, z: float) -> bytes:
        return b"XYZ \0\0\0\0" + fixed(x) + fixed(y) + fixed(z)

    curve = b"curv\0\0\0\0" + struct.pack(">IH", 1, round(gamma * 256)) + b"\0\0"
    text = description.encode("ascii") + b"\0"
    desc = b"desc\0\0\0\0" + struct.pack(">I", len(text)) + text + b"\0" * 79
    desc += b"\0" * (-len(desc) % 4)
    d50 = (0.9642, 1.0, 0.8249)
    tags = [(b"desc", desc), (b"wtpt", xyz_tag(*d50)),
            *((name, xyz_tag(*xyz)) for name, xyz in zip((b"rXYZ", b"gXYZ", b"bXYZ"),
                                                          primaries_d50, strict=True)),
            (b"rTRC", curve), (b"gTRC", curve), (b"bTRC", curve)]
    offset, table, data = 128 + 4 + 12 * len(tags), b"", b""
    for name, body in tags:
        table += name + struct.pack(">II", offset + len(data), len(body))
        data += body
    body = struct.pack(">I", len(tags)) + table + data
    header = (struct.pack(">I", 128 + len(body)) + b"none" + bytes([2, 0x20, 0, 0]) + b"mntr"
              + b"RGB XYZ " + b"\0" * 12 + b"acsp" + b"\0" * 28  # to the rendering intent
              + fixed(d50[0]) + fixed(d50[1]) + fixed(d50[2]) + b"\0" * 48)
    assert len(header) == 128
    return header + body


ADOBE_RGB_D50 = [(0.60974, 0.31111, 0.01947), (0.20528, 0.62567, 0.06087),
                 (0.14919, 0.06322, 0.74457)]


def test_a_wide_gamut_photo_is_read_in_srgb_by_its_embedded_profile(tmp_path):
    """Read as if it were sRGB, an Adobe RGB photo came out dull."""
    from PIL import ImageCms

    icc = matrix_profile("Adobe RGB (1998) test", ADOBE_RGB_D50, 563 / 256)
    colours = [(220, 30, 30), (30, 180, 40), (30, 40, 220), (230, 180, 140)]
    chart = np.zeros((64, 64 * len(colours), 3), np.uint8)
    for index, colour in enumerate(colours):
        chart[:, index * 64:(index + 1) * 64] = colour
    adobe = ImageCms.ImageCmsProfile(__import__("io").BytesIO(icc))
    wide = ImageCms.profileToProfile(Image.fromarray(chart), ImageCms.createProfile("sRGB"),
                                     adobe, outputMode="RGB")
    stored = np.asarray(wide)
    assert np.abs(stored.astype(int) - chart).max() > 25  # the file's numbers are not sRGB's
    for name, options in (("wide.png", {}), ("wide.jpg", {"quality": 98, "subsampling": 0}),
                          ("wide.tif", {})):
        wide.save(tmp_path / name, icc_profile=icc, **options)
        read = read_image(tmp_path / name).astype(int)
        centres = read[32, 32::64]
        assert np.abs(centres - np.array(colours)).max() <= 8, (name, centres)  # JPEG: 6
    Image.fromarray(chart).save(tmp_path / "plain.png")  # no profile: as it is
    assert np.array_equal(read_image(tmp_path / "plain.png"), chart)
    wide.save(tmp_path / "broken.png", icc_profile=b"not a profile")  # a damaged one: as it is
    assert np.array_equal(read_image(tmp_path / "broken.png"), stored)


def test_upright_size_is_the_size_read_image_gives(tmp_path):
    from kbbatch.images import upright_size

    plain = tmp_path / "plain.jpg"
    Image.fromarray(np.full((40, 60, 3), 100, np.uint8)).save(plain)
    turned = tmp_path / "turned.jpg"
    exif = Image.Exif()
    exif[0x0112] = 6  # the camera held on its side
    Image.fromarray(np.full((40, 60, 3), 100, np.uint8)).save(turned, exif=exif)
    floats = tmp_path / "floats.tif"
    assert cv2.imwrite(str(floats), np.full((30, 50, 3), 0.5, np.float32))  # Pillow cannot
    for path in (plain, turned, floats):
        height, width = read_image(path).shape[:2]
        assert upright_size(path) == (width, height), path
    assert upright_size(turned) == (40, 60)


def test_a_decoder_warning_names_the_photo(tmp_path, caplog):
    """A JPEG whose EXIF block is damaged: Pillow's "Corrupt EXIF data" warning was printed
    with no photo named."""
    import logging
    import warnings

    path = tmp_path / "holiday.jpg"
    Image.fromarray(np.full((40, 60, 3), 100, np.uint8)).save(path)
    data = path.read_bytes()
    exif = b"Exif\x00\x00II*\x00\x08\x00\x00\x00\xff\xff" + b"\x00" * 20  # 65535 entries
    path.write_bytes(data[:2] + b"\xff\xe1" + (len(exif) + 2).to_bytes(2, "big") + exif
                     + data[2:])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # none escapes unnamed
        with caplog.at_level(logging.WARNING, logger="kbbatch"):
            assert read_image(path).shape == (40, 60, 3)
    assert any(str(path) in r.getMessage() and "EXIF" in r.getMessage()
               for r in caplog.records), caplog.text


def test_reading_a_damaged_exif_for_its_time_or_size_prints_no_unnamed_warning(tmp_path):
    """The journal's look at a photo's capture time (and `plan`'s at its size) let Pillow's
    warnings of a damaged EXIF block out raw, with no photo named, before the read that names
    it."""
    import warnings

    from kbbatch.images import capture_time, upright_size

    path = tmp_path / "holiday.jpg"
    Image.fromarray(np.full((40, 60, 3), 100, np.uint8)).save(path)
    data = path.read_bytes()
    exif = (b"Exif\x00\x00II*\x00\x08\x00\x00\x00\x05\x00"
            b"\x0f\x01\x02\x00\xff\x00\x00\x00\x40\x00\x00\x00")  # a tag past the end
    path.write_bytes(data[:2] + b"\xff\xe1" + (len(exif) + 2).to_bytes(2, "big") + exif
                     + data[2:])
    exif_time = Image.Exif()
    exif_time.get_ifd(0x8769)[0x9003] = "2024:05:01 10:00:00"  # DateTimeOriginal
    timed = tmp_path / "timed.jpg"
    Image.fromarray(np.full((40, 60, 3), 100, np.uint8)).save(timed, exif=exif_time)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # raised, a warning made capture_time say None
        assert capture_time(timed) == "2024:05:01 10:00:00"
        assert capture_time(path) is None
        assert upright_size(path) == (60, 40)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        capture_time(path)
        upright_size(path)
    assert caught == []


def test_a_float_image_of_zero_to_one_is_not_read_as_black(tmp_path):
    """0-1 floats (a 32-bit TIFF from a raw converter) were divided by 255: a black clip."""
    ramp = np.tile(np.linspace(0.0, 1.0, 256, dtype=np.float32), (16, 1))
    Image.fromarray(ramp, mode="F").save(tmp_path / "unit.tif")
    read = read_image(tmp_path / "unit.tif")
    assert read.shape == (16, 256, 3)
    assert abs(int(read[0, -1, 0]) - 255) <= 1 and abs(int(read[0, 128, 0]) - 128) <= 1
    Image.fromarray(ramp * 255.0, mode="F").save(tmp_path / "bytes.tif")  # 0-255 as before
    assert np.abs(read_image(tmp_path / "bytes.tif").astype(int) - read.astype(int)).max() <= 1
    hot = ramp.copy()
    hot[0, :3] = (1.02, 4.0, 12.0)  # highlights above 1: it was read as 0-255, nearly black
    Image.fromarray(hot, mode="F").save(tmp_path / "hot.tif")
    read_hot = read_image(tmp_path / "hot.tif")
    assert np.abs(read_hot[1:].astype(int) - read[1:].astype(int)).max() <= 1
    assert (read_hot[0, :3] == 255).all()  # clipped
    stars = np.full((16, 256), 0.5, np.float32)  # a dark 0-255 sky, its stars at 255
    stars[3, ::50] = 255.0
    Image.fromarray(stars, mode="F").save(tmp_path / "stars.tif")
    read_stars = read_image(tmp_path / "stars.tif")
    assert read_stars[0, 0, 0] <= 1 and read_stars[3, 0, 0] == 255
    colour = np.dstack([ramp, ramp[:, ::-1], np.full_like(ramp, 0.5)])  # BGR for OpenCV
    colour[0, 0] = 3.0
    assert cv2.imwrite(str(tmp_path / "merged.tif"), colour)  # an HDR merge's float RGB TIFF
    read_colour = read_image(tmp_path / "merged.tif")  # Pillow cannot open it
    assert read_colour.shape == (16, 256, 3)
    assert np.abs(read_colour[1:, :, 2].astype(int) - read[1:, :, 0]).max() <= 1  # blue
    assert abs(int(read_colour[5, 10, 0]) - 128) <= 1  # red: 0.5
    alpha = np.ones_like(ramp)
    alpha[:, :128] = 0.0  # its left half transparent: over black, as other images
    assert cv2.imwrite(str(tmp_path / "cutout.tif"), np.dstack([colour, alpha]))
    read_cutout = read_image(tmp_path / "cutout.tif")
    assert read_cutout[:, :128].max() == 0
    assert np.array_equal(read_cutout[1:, 128:], read_colour[1:, 128:])


def test_an_animated_photo_is_read_from_its_first_frame_and_says_so(tmp_path, caplog):
    import logging

    frames = [Image.fromarray(np.full((32, 48, 3), level, np.uint8)) for level in (40, 200)]
    frames[0].save(tmp_path / "moving.webp", save_all=True, append_images=frames[1:],
                   lossless=True, duration=100)
    with caplog.at_level(logging.WARNING):
        read = read_image(tmp_path / "moving.webp")
    assert abs(int(read.mean()) - 40) <= 1
    assert "moving.webp: holds 2 frames or pages; the first is used" in caplog.text
