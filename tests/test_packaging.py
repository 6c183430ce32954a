"""Plug-in folders planners/ and presets/ install inside kbbatch, never as top-level packages."""

import subprocess
import sys
import zipfile
from pathlib import Path

import kbbatch.planners
import kbbatch.presets

REPO = Path(__file__).resolve().parents[1]


def test_plugin_folders_import_as_kbbatch_subpackages():
    assert Path(kbbatch.planners.__file__).parent.name == "planners"
    assert Path(kbbatch.presets.__file__).parent.name == "presets"
    assert "slideshow" in kbbatch.presets.builtin_names()


def test_wheel_holds_planners_and_presets_under_kbbatch(tmp_path):
    tracked = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True,
                             check=True).stdout.split()
    source = tmp_path / "src"
    for name in tracked:
        if (REPO / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            (source / name).write_bytes((REPO / name).read_bytes())
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                    "-w", str(tmp_path / "dist"), str(source)],
                   check=True, capture_output=True)
    (wheel,) = (tmp_path / "dist").glob("kbbatch-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "kbbatch/planners/auto.py" in names
    assert "kbbatch/presets/__init__.py" in names
    assert "kbbatch/presets/slideshow.toml" in names
    top_level = {name.split("/")[0] for name in names if "dist-info" not in name}
    assert top_level == {"kbbatch"}
