import cv2
import numpy as np
import pytest

from kbbatch.depth import DepthError, estimate_disparity

from .conftest import textured_image


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
])
def test_bad_depth_files_get_a_clear_error(tmp_path, data, reason):
    photo = tmp_path / "bad.jpg"
    np.save(tmp_path / "bad.depth.npy", data)
    with pytest.raises(DepthError, match=reason) as caught:
        estimate_disparity(textured_image(40, 60), photo)
    assert "bad.depth.npy" in str(caught.value)
