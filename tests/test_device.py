"""--device: declared once for render and watch; cuda without a GPU fails at start, clearly;
the run report says where frames were rendered and on which provider each network ran."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from kbbatch import cli, models
from kbbatch.batch import REPORT_NAME, run_folder
from kbbatch.depth import DepthOptions
from kbbatch.device import DEVICE_NAMES, DeviceError, cuda_available, resolve_device
from kbbatch.images import write_image
from kbbatch.pipeline import ClipOptions

from .conftest import textured_image
from .test_models import tiny_depth_model


@pytest.mark.parametrize("command", [cli.render, cli.watch])
def test_render_and_watch_take_the_device_option(command):
    [option] = [p for p in command.params if p.name == "device"]
    assert tuple(option.type.choices) == DEVICE_NAMES
    assert option.envvar == "KBBATCH_DEVICE"


def test_cpu_is_always_there_and_auto_falls_back_to_it():
    assert resolve_device("cpu") == "cpu"
    available, _ = cuda_available()
    assert resolve_device("auto") == ("cuda" if available else "cpu")
    with pytest.raises(DeviceError, match="unknown device 'tpu'"):
        resolve_device("tpu")


AUTO_IN_A_CHILD = """
import sys


class AskedForTorch:  # records an import of torch, whether or not torch is installed
    asked = False

    def find_spec(self, name, path=None, target=None):
        AskedForTorch.asked = AskedForTorch.asked or name == "torch"


sys.meta_path.insert(0, AskedForTorch())
from kbbatch import device
device.GPU_DRIVER_FILES = (sys.argv[1],)
print(device.resolve_device("auto"), AskedForTorch.asked)
"""


def test_auto_asks_torch_only_where_a_gpu_driver_is(tmp_path):
    """Importing torch to ask cost every run and daemon worker 1.5 to 2 s on a CPU machine.
    (The child records the import asked for: read from sys.modules, the test failed where torch
    is not installed, as after the README's first line, which installs no torch.)"""
    pattern = str(tmp_path / "nvidia*")

    def auto_in_a_child() -> str:
        done = subprocess.run([sys.executable, "-c", AUTO_IN_A_CHILD, pattern],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        return done.stdout.strip()

    assert auto_in_a_child() == "cpu False"
    (tmp_path / "nvidiactl").touch()
    available, _ = cuda_available()
    assert auto_in_a_child() == f"{'cuda' if available else 'cpu'} True"


def test_cuda_without_a_gpu_is_a_clear_error_at_start(tmp_path):
    available, reason = cuda_available()
    if available:
        pytest.skip("this machine has a CUDA GPU")
    assert "torch" in reason
    folder = tmp_path / "photos"
    folder.mkdir()
    write_image(folder / "a.png", textured_image(60, 80))
    for command in (["render", str(folder)], ["watch", str(folder), "--out",
                                              str(tmp_path / "out")]):
        result = CliRunner().invoke(cli.main, [*command, "--device", "cuda"])
        assert result.exit_code == 2, result.output
        assert "Invalid value for --device: cannot render on cuda: " in result.output
        assert reason in result.output
    assert not (folder / "kenburns").exists() and not (tmp_path / "out").exists(), \
        "nothing may be written before the device is known"
    result = CliRunner().invoke(cli.main, ["render", str(folder)],
                                env={"KBBATCH_DEVICE": "cuda"})
    assert result.exit_code == 2 and "cannot render on cuda" in result.output


def test_run_report_names_the_device_and_the_provider_each_network_ran_on(
        tmp_path, monkeypatch, quick_preset):
    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path / "models"))
    monkeypatch.setenv(models.PROVIDER_ENV, "cpu")
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "depth_anything_v2_small.onnx").write_bytes(tiny_depth_model())
    folder = tmp_path / "photos"
    folder.mkdir()
    image = textured_image(120, 180)
    image[:, :90] = np.maximum(image[:, :90], 200)  # a bright near half for the tiny network
    write_image(folder / "a.png", image)
    options = ClipOptions(threads=2, depth=DepthOptions(backend="onnx", adjust=False))
    report = run_folder(folder, tmp_path / "out", quick_preset, options, show_progress=False)
    assert [r.status for r in report.results] == ["done"], report.results[0].error
    written = json.loads((tmp_path / "out" / REPORT_NAME).read_text())
    assert written["device"] == "cpu" and written["clips"][0]["device"] == "cpu"
    assert written["onnx_providers"]["depth_anything_v2_small.onnx"] == "CPUExecutionProvider"


def test_without_torch_auto_is_the_cpu_and_cuda_says_how_to_get_it(monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "torch", None)  # import torch fails
    assert resolve_device("auto") == "cpu"
    with pytest.raises(DeviceError, match=r"torch is not installed \(pip install "
                                          r"'kbbatch\[torch\]'\)"):
        resolve_device("cuda")


def test_auto_is_resolved_where_the_frames_are_rendered(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    write_image(folder / "a.png", textured_image(90, 160))
    result = CliRunner().invoke(cli.main, ["render", str(folder), "-o", str(tmp_path / "out"),
                                           "--preset", "preview", "--duration", "0.4",
                                           "--fps", "10", "--quiet", "--device", "auto"])
    assert result.exit_code == 0, result.output
    written = json.loads((tmp_path / "out" / REPORT_NAME).read_text())
    assert written["device"] == "auto"
    assert written["clips"][0]["device"] == resolve_device("auto")
