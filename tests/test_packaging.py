"""Plug-in folders planners/ and presets/ install inside kbbatch, never as top-level packages."""

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

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


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None,
                    reason="needs root and setpriv to run as an account with no writable home")
def test_a_service_account_with_no_writable_home_can_run_kbbatch(tmp_path):
    """The README's systemd unit runs as a service user; with no writable home and a
    root-owned install, numba found nowhere to cache its kernels and every command failed at
    import ("cannot cache function")."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA", "XDG_"))}
    env["HOME"] = "/nonexistent"
    as_nobody = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable]
    readable = subprocess.run([*as_nobody, "-c", "import numba, click; from importlib.util "
                               "import find_spec; open(find_spec('kbbatch.cli').origin).read()"],
                              capture_output=True, env=env, cwd="/")
    if readable.returncode != 0:
        pytest.skip("this checkout or its venv cannot be read by another account")
    run = subprocess.run([*as_nobody, "-m", "kbbatch", "--version"],
                         capture_output=True, text=True, env=env, cwd="/")
    assert run.returncode == 0, run.stderr
    assert "version" in run.stdout
