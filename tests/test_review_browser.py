"""`kbbatch review` end to end in a real headless Chromium: drag the crops, play a preview,
save, then render the saved manifest with the real CLI and check the clip follows the crops.

Needs Debian's `chromium` and `chromium-driver` (CI installs them); skips, saying so, without.
Set KBBATCH_REVIEW_SCREENSHOT=docs/review.jpg to refresh the README's screenshot.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from kbbatch.encode import decode_frames
from kbbatch.images import read_image
from kbbatch.manifest import load_manifest
from kbbatch.pipeline import ClipOptions
from kbbatch.presets import load_preset, with_overrides
from tests.conftest import PHOTOS, shared_photos
from tests.reviewserver import running_server

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
PHOTO_NAMES = ("33_landscape_sign_in_field.jpg", "10_animal_giraffe.jpg",
               "16_indoor_coffee_cup.png")
PHOTO_LONG_SIDE_PX = 1200
DURATION_S, FPS = 1.0, 10.0
SCREEN_DRAG_PX = (-110, 45)
README_WIDTH_PX = 1120


def browser():
    if not (Path(CHROMIUM).is_file() and Path(CHROMEDRIVER).is_file()):
        pytest.skip("no headless browser: install Debian's chromium and chromium-driver "
                    "(apt-get install -y chromium chromium-driver) to run this test")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                     "--window-size=1400,860", "--autoplay-policy=no-user-gesture-required"):
        options.add_argument(argument)
    # The driver is named explicitly, so Selenium Manager never looks for one online.
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


def small_copies(folder: Path) -> list[str]:
    """A few real photos, downscaled so the test stays quick."""
    wanted = [PHOTOS / n for n in PHOTO_NAMES if (PHOTOS / n).is_file()]
    if len(wanted) < 2:
        wanted = shared_photos(3)
    folder.mkdir()
    for photo in wanted:
        with Image.open(photo) as image:
            image.thumbnail((PHOTO_LONG_SIDE_PX, PHOTO_LONG_SIDE_PX))
            image.convert("RGB").save(folder / (photo.stem + ".jpg"), quality=92)
    return sorted(photo.stem + ".jpg" for photo in wanted)


def crop_picture(photo: np.ndarray, crop: dict, width_px: int, height_px: int) -> np.ndarray:
    left = round(crop["center_x"] - crop["width"] / 2)
    top = round(crop["center_y"] - crop["height"] / 2)
    window = photo[top : top + round(crop["height"]), left : left + round(crop["width"])]
    return cv2.resize(window, (width_px, height_px), interpolation=cv2.INTER_AREA)


def difference(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two pictures, slightly blurred (codec noise, parallax)."""
    blur = [cv2.GaussianBlur(x.astype(np.float32), (0, 0), 3) for x in (a, b)]
    return float(np.abs(blur[0] - blur[1]).mean())


def wait_for(driver, script: str, timeout_s: float = 120):
    deadline = time.monotonic() + timeout_s
    while True:
        value = driver.execute_script(script)
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"page never satisfied: {script}")
        time.sleep(0.2)


CROP_WIDTHS = """return [...document.querySelectorAll('#crop-start, #crop-end')]
  .map((box) => box.style.width);"""
VIDEO_PLAYING = """const v = document.getElementById('preview');
return v.readyState >= 2 && v.currentTime > 0 && !v.paused && !v.error ? v.videoWidth : 0;"""


def test_review_in_chromium_then_render_the_saved_manifest(tmp_path, monkeypatch):
    monkeypatch.setenv("SE_OFFLINE", "true")
    folder = tmp_path / "photos"
    names = small_copies(folder)
    # The first photo is all but flat (its own depth map, beside it): its clip's last frame
    # is then the edited crop, whatever depth the photo would otherwise get (without the
    # segmentation models the giraffe lies on the ground plane, and its far background moved
    # 30 levels away from the crop). This test is about the review and its manifest; the
    # other two photos still go through the depth stages (models or none).
    height, width = read_image(folder / names[0]).shape[:2]
    almost_flat = np.linspace(40000, 40100, height)[:, None].repeat(width, axis=1)
    cv2.imwrite(str(folder / (Path(names[0]).stem + ".disparity.png")),
                almost_flat.astype(np.uint16))
    manifest = tmp_path / "manifest.json"
    preset = with_overrides(load_preset("preview"), duration_s=DURATION_S, fps=FPS)
    driver = browser()
    try:
        with running_server(folder, manifest, preset, ClipOptions(threads=2)) as served:
            from selenium.webdriver import ActionChains, Keys
            from selenium.webdriver.common.by import By

            driver.get(served.url)
            auto = {p["name"]: p for p in served.wait_planned()["photos"]}
            wait_for(driver, "return document.getElementById('progress-text').textContent"
                             ".includes('planned') && !document.getElementById('crop-end').hidden")
            first = auto[names[0]]
            assert driver.find_element(By.ID, "photo-title").text == names[0]

            # Move the end crop, then shrink it by its corner handle (aspect stays 16:9). Down
            # where the automatic end crop has room below it, else up: without the
            # segmentation models, the first photo's automatic end crop reaches its bottom.
            auto_end = first["plan"]["end"]
            photo_height = read_image(folder / names[0]).shape[0]
            room_below = photo_height - (auto_end["center_y"] + auto_end["height"] / 2)
            drag_x, drag_y = SCREEN_DRAG_PX
            if room_below < 2 * drag_y:  # photo px against screen px: the photo is shown smaller
                drag_y = -drag_y
            end_box = driver.find_element(By.ID, "crop-end")
            ActionChains(driver).move_to_element(end_box).click_and_hold() \
                .move_by_offset(drag_x, drag_y).release().perform()
            handle = end_box.find_element(By.CLASS_NAME, "handle")
            ActionChains(driver).drag_and_drop_by_offset(handle, -60, -60).perform()
            assert "1 changed" in driver.find_element(By.ID, "save-button").text

            # Preview: rendered on demand, played in a loop.
            driver.find_element(By.ID, "preview-button").click()
            assert wait_for(driver, VIDEO_PLAYING) == 480
            shown = driver.execute_script("return document.getElementById('preview').currentTime")
            time.sleep(0.6)
            assert driver.execute_script(
                "return document.getElementById('preview').currentTime") != shown

            # Keyboard to the next photo: swap its crops, reset them, look at its depth map.
            body = driver.find_element(By.TAG_NAME, "body")
            body.send_keys(Keys.ARROW_RIGHT)
            assert driver.find_element(By.ID, "photo-title").text == names[1]
            widths = driver.execute_script(CROP_WIDTHS)
            driver.find_element(By.ID, "swap").click()
            assert driver.execute_script(CROP_WIDTHS) == widths[::-1]
            driver.find_element(By.ID, "reset").click()
            wait_for(driver, f"return JSON.stringify((() => {{ {CROP_WIDTHS} }})()) === "
                             f"'{json.dumps(widths, separators=(',', ':'))}'")
            driver.find_element(By.ID, "show-depth").click()
            wait_for(driver, "const d = document.getElementById('depth');"
                             "return !d.hidden && d.complete && d.naturalWidth > 0")
            # The third photo is excluded; then back to the first, where space plays the
            # (cached) preview again.
            driver.execute_script("document.activeElement.blur()")
            body.send_keys(Keys.ARROW_RIGHT)
            assert driver.find_element(By.ID, "photo-title").text == names[2]
            driver.find_element(By.ID, "exclude").click()
            driver.execute_script("document.activeElement.blur()")
            body.send_keys(Keys.ARROW_LEFT, Keys.ARROW_LEFT)
            assert driver.find_element(By.ID, "photo-title").text == names[0]
            body.send_keys(" ")
            wait_for(driver, VIDEO_PLAYING)

            screenshot = tmp_path / "review.png"
            driver.save_screenshot(str(screenshot))
            assert Image.open(screenshot).size[0] >= 1000
            if os.environ.get("KBBATCH_REVIEW_SCREENSHOT"):  # the README's picture
                with Image.open(screenshot) as picture:
                    height = round(picture.height * README_WIDTH_PX / picture.width)
                    picture.convert("RGB").resize((README_WIDTH_PX, height), Image.LANCZOS) \
                        .save(os.environ["KBBATCH_REVIEW_SCREENSHOT"], quality=85)

            driver.find_element(By.ID, "save-button").click()
            saved_text = wait_for(driver, """const s = document.getElementById('saved');
                return s.textContent.startsWith('Saved') ? s.textContent : '';""")
            assert str(manifest) in saved_text and "--manifest" in saved_text
    finally:
        driver.quit()

    saved = load_manifest(manifest)
    entry = saved.entry(names[0]).data
    assert saved.entry(names[1]) is None  # swapped, then reset: automatic again, no entry
    assert saved.entry(names[2]).data == {"exclude": True}
    before, after = first["plan"], entry
    for key in ("center_x", "center_y", "width"):
        assert after["start"][key] == pytest.approx(before["start"][key], abs=0.02)
    assert after["end"]["width"] < before["end"]["width"] - 10  # shrunk by the handle
    # the size its crops are pixels of (an old entry's, kept, scaled them twice after a resize)
    assert after["photo_size"] == {"width": first["width_px"], "height": first["height_px"]}
    moved_x = after["end"]["center_x"] - before["end"]["center_x"]
    moved_y = after["end"]["center_y"] - before["end"]["center_y"]
    # in the direction of the drag (less any clamping; the shrink moves the centre up a little)
    assert moved_x < -20 and (moved_y > 5 if drag_y > 0 else moved_y < -5)

    out = tmp_path / "clips"
    command = [sys.executable, "-m", "kbbatch", str(folder), "--manifest", str(manifest),
               "-o", str(out), "--preset", "preview", "--duration", str(DURATION_S),
               "--fps", str(FPS), "--quiet"]
    completed = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert completed.returncode == 0, completed.stderr
    frames = list(decode_frames(out / (Path(names[0]).stem + ".mp4"), 640, 360))
    forward = round(DURATION_S * FPS)
    assert len(frames) == 2 * forward - 2
    photo = read_image(folder / names[0])
    first_frame, end_frame = frames[0], frames[forward - 1]
    assert difference(first_frame, crop_picture(photo, after["start"], 640, 360)) < 12
    to_new = difference(end_frame, crop_picture(photo, after["end"], 640, 360))
    to_auto = difference(end_frame, crop_picture(photo, before["end"], 640, 360))
    print(f"end frame vs edited end crop {to_new:.1f}, vs automatic end crop {to_auto:.1f}")
    side_by_side = np.concatenate([end_frame, crop_picture(photo, after["end"], 640, 360)], 1)
    Image.fromarray(side_by_side).save(tmp_path / "end-frame-and-edited-crop.png")  # to look at
    # All but flat, the photo follows the crops within the encoder's and resampling's error.
    assert to_new < 6 and to_new < 0.5 * to_auto
    assert (out / (Path(names[1]).stem + ".mp4")).is_file()
    assert not (out / (Path(names[2]).stem + ".mp4")).exists()
    assert "1 photo(s) excluded" in completed.stdout


GRID_LOADED = """[...document.querySelectorAll('#grid figure img')]
  .filter((img) => img.complete && img.naturalWidth > 0).length"""


def test_a_photo_name_that_is_not_utf8_shows_with_the_others(tmp_path):
    """Its stray byte reached the page as a lone surrogate, encodeURIComponent threw, and no
    photo showed ("cannot load: URI malformed"); the server did not find it either."""
    from kbbatch.images import write_image

    from .conftest import textured_image

    folder = tmp_path / "photos"
    folder.mkdir()
    odd = os.fsdecode(b"0caf\xe9.jpg")  # sorts first: it broke the whole list
    for seed, name in enumerate((odd, "b.jpg")):
        write_image(folder / name, textured_image(180, 320, seed))
    preset = with_overrides(load_preset("preview"), duration_s=DURATION_S, fps=FPS)
    driver = browser()
    try:
        with running_server(folder, tmp_path / "m.json", preset, ClipOptions(threads=2)) as served:
            assert served.get("/api/photos/0caf%E9.jpg/image").status == 200
            driver.get(served.url)
            served.wait_planned()
            assert wait_for(driver, f"return {GRID_LOADED} === 2", 60)
            assert "cannot load" not in driver.execute_script(
                "return document.getElementById('progress-text').textContent")
    finally:
        driver.quit()
