import os
import subprocess
import sys
from pathlib import Path

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

from .conftest import textured_image


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
    done = subprocess.run([sys.executable, "-c", script, os.fsencode(folder)],
                          cwd=Path(__file__).resolve().parents[1], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    picture = (np.arange(30 * 40 * 3) % 251).astype(np.uint8).reshape(30, 40, 3)
    assert np.array_equal(read_image(folder / "plain.png"), picture)
    assert read_image(folder / "plain.jpg").shape == (30, 40, 3)
    with Image.open(folder / "grey16.png") as grey:
        assert grey.mode.startswith("I") and grey.getpixel((0, 0)) == 40000
    assert is_own_png(folder / "own.png") and not is_own_png(folder / "plain.png")
    assert own_png_text(folder / "own.png")["Comment"] == "kept"
    assert sorted(p.name for p in folder.iterdir()) == ["grey16.png", "own.png", "plain.jpg",
                                                         "plain.png"]  # no temporary left

