"""A corpus of awkward inputs, generated on the fly (nothing binary is committed)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image

from .conftest import textured_image

LATIN1_NAME = os.fsdecode(b"caf\xe9 latin-1.jpg")
"""A name whose bytes are not UTF-8 (from a Latin-1 zip file): Python holds it with surrogates,
which SQLite, ffmpeg-python and OpenCV refuse."""
LONG_NAME = "L" * 240 + ".jpg"
"""A valid 244-byte name: its temporary clip's name, and its depth map's, would pass 255."""
GOOD = ("grey.png", "alpha.png", "sixteen.png", "cmyk.jpg", "rotated.jpg", "name with spaces é.jpg",
        "twin.jpg", "twin.png", LATIN1_NAME, LONG_NAME)
BAD = ("empty.jpg", "truncated.jpg", "cut_short.jpg", "text.jpg")


def write_corpus(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    base = textured_image(180, 320, seed=9)
    Image.fromarray(base[..., 1]).save(folder / "grey.png")
    rgba = np.dstack([base, np.full(base.shape[:2], 200, np.uint8)])
    Image.fromarray(rgba, "RGBA").save(folder / "alpha.png")
    Image.fromarray(base[..., 0].astype(np.uint16) * 257).save(folder / "sixteen.png")
    Image.fromarray(base).convert("CMYK").save(folder / "cmyk.jpg")
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(base).save(folder / "rotated.jpg", exif=exif.tobytes())
    Image.fromarray(base).save(folder / "name with spaces é.jpg")
    Image.fromarray(base).save(folder / "twin.jpg")
    for name in (LATIN1_NAME, LONG_NAME):
        Image.fromarray(base[:, ::-1]).save(folder / name, format="JPEG")
    Image.fromarray(base[::-1]).save(folder / "twin.png")
    (folder / "empty.jpg").write_bytes(b"")
    full = (folder / "twin.jpg").read_bytes()
    (folder / "truncated.jpg").write_bytes(full[: len(full) // 2])
    # cut short, but ending as a JPEG ends: it decodes, its lower part blank grey
    (folder / "cut_short.jpg").write_bytes(full[: len(full) // 2] + b"\xff\xd9")
    (folder / "text.jpg").write_text("this is a text file with a .jpg name")
