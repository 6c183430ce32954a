"""Choosing the executor on the command line, where Ray is not installed."""

from __future__ import annotations

import subprocess
import sys

from kbbatch.ray_executor import RAY_INSTALL_HINT

# None in sys.modules makes `import ray` fail as if it were not installed
WITHOUT_RAY = ("import sys; sys.modules['ray'] = None; from kbbatch.cli import main; "
               "main(sys.argv[1:])")


def test_asking_for_ray_without_the_extra_says_how_to_install_it(tmp_path):
    (tmp_path / "photos").mkdir()
    done = subprocess.run([sys.executable, "-c", WITHOUT_RAY, str(tmp_path / "photos"), "-o",
                           str(tmp_path / "out"), "--executor", "ray"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert "--executor ray needs Ray" in done.stderr
    assert RAY_INSTALL_HINT in done.stderr
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "out").exists()  # checked before anything is touched
