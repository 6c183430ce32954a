"""Model registry, cache and pull against a real HTTP server on 127.0.0.1."""

import hashlib
import http.server
import os
import re
import threading
from dataclasses import replace

import numpy as np
import pytest
from onnx import TensorProto, helper

from kbbatch import models
from kbbatch.depth import DepthOptions, estimate_disparity
from kbbatch.depth.onnx import OnnxDepth

from .conftest import textured_image


def tiny_depth_model(input_shape=(1, 3, None, None), keep_channels: bool = False) -> bytes:
    """A graph that returns the channel mean of its input: bright pixels read as near. With
    keep_channels, it returns its input as is: three maps, like a segmenter's class scores."""
    node = (helper.make_node("Identity", ["pixel_values"], ["predicted_depth"]) if keep_channels
            else helper.make_node("ReduceMean", ["pixel_values"], ["predicted_depth"], axes=[1],
                                  keepdims=0))
    output_shape = list(input_shape) if keep_channels else [1, *input_shape[2:]]
    graph = helper.make_graph(
        [node], "tiny-depth",
        [helper.make_tensor_value_info("pixel_values", TensorProto.FLOAT, list(input_shape))],
        [helper.make_tensor_value_info("predicted_depth", TensorProto.FLOAT, output_shape)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    return model.SerializeToString()


@pytest.fixture
def server():
    """Serves /good (the model), /truncated (promises more bytes than it sends)."""
    payload = tiny_depth_model()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802
            self.send_response(200)
            self.send_header("Content-Length", str(len(payload)))
            self.end_headers()
            body = payload if self.path == "/good" else payload[: len(payload) // 3]
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}", payload
    httpd.shutdown()


def spec_for(url: str, sha256: str | None):
    return replace(models.REGISTRY["depth-anything-v2-small"], url=url, sha256=sha256)


def test_pull_verifies_and_caches(tmp_path, server):
    base, payload = server
    good = hashlib.sha256(payload).hexdigest()
    path = models.pull(spec_for(f"{base}/good", good), tmp_path, progress=False)
    assert path.read_bytes() == payload
    assert path.name == "depth_anything_v2_small.onnx"


def test_pull_refuses_a_wrong_checksum(tmp_path, server):
    base, _ = server
    with pytest.raises(models.ModelError, match="sha256 mismatch"):
        models.pull(spec_for(f"{base}/good", "0" * 64), tmp_path, progress=False)
    assert not list(tmp_path.glob("*.onnx"))


def test_pull_refuses_a_truncated_download(tmp_path, server):
    base, payload = server
    with pytest.raises(models.ModelError):
        models.pull(spec_for(f"{base}/truncated", hashlib.sha256(payload).hexdigest()),
                    tmp_path, progress=False)
    assert not list(tmp_path.glob("*.onnx"))


def test_unpinned_model_needs_the_users_checksum(tmp_path, server):
    base, payload = server
    actual = hashlib.sha256(payload).hexdigest()
    with pytest.raises(models.ModelError, match=actual):
        models.pull(spec_for(f"{base}/good", None), tmp_path, progress=False)
    assert not list(tmp_path.glob("*.onnx"))
    path = models.pull(spec_for(f"{base}/good", None), tmp_path, sha256=actual, progress=False)
    assert path.is_file()
    # pulled again without the checksum: the cached file was deleted ("not kept")
    assert models.pull(spec_for(f"{base}/good", None), tmp_path, progress=False) == path
    assert path.read_bytes() == payload
    placed = tmp_path / "placed"  # a file the user put there by hand is never removed either
    placed.mkdir()
    (placed / path.name).write_bytes(b"the user's own export")
    models.pull(spec_for(f"{base}/good", None), placed, progress=False)
    assert (placed / path.name).read_bytes() == b"the user's own export"


def test_missing_model_error_names_the_pull_command(tmp_path, monkeypatch):
    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))
    assert models.cached_path("midas-v21-small") is None
    with pytest.raises(models.ModelError, match="kbbatch models pull midas-v21-small"):
        models.load("midas-v21-small")


def test_onnx_backend_pre_and_post_processing(tmp_path, monkeypatch):
    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))
    (tmp_path / "depth_anything_v2_small.onnx").write_bytes(tiny_depth_model())
    spec = models.REGISTRY["depth-anything-v2-small"]
    # Aspect kept, short side 518, sides multiples of 14.
    width, height = models.input_size_for(spec, 1024, 683)
    assert (width, height) == (770, 518) and width % 14 == 0  # 776.6 rounded to a multiple
    batch = models.prepare_input(spec, np.full((10, 20, 3), 255, np.uint8), (28, 14))
    assert batch.shape == (1, 3, 14, 28)
    np.testing.assert_allclose(batch[0, :, 0, 0], (1 - np.array(spec.mean)) / spec.std, rtol=1e-5)
    image = textured_image(120, 180)
    image[:, :90] = 250  # bright left half: the tiny model calls it near
    image[:, 90:] = 10
    result = estimate_disparity(image, None, DepthOptions(backend="auto", adjust=False))
    assert result.backend == "onnx" and result.source == "depth-anything-v2-small"
    assert result.disparity.shape == (120, 180)
    assert result.disparity[:, :80].min() > result.disparity[:, 100:].max()
    with pytest.raises(models.ModelError, match="constant"):
        OnnxDepth("depth-anything-v2-small").disparity(np.full((50, 50, 3), 90, np.uint8),
                                                       None, None)


def test_sessions_take_their_share_of_the_cores_and_the_chosen_provider(tmp_path, monkeypatch):
    path = tmp_path / "tiny.onnx"
    path.write_bytes(tiny_depth_model())
    cores = models.usable_cores()
    monkeypatch.delenv(models.PROVIDER_ENV, raising=False)
    try:
        models.share_cores(1)
        alone = models.session(path)
        assert alone.get_session_options().intra_op_num_threads == cores
        assert alone.get_session_options().inter_op_num_threads == 1
        models.share_cores(cores)  # one job per core: one thread each
        assert models.session(path).get_session_options().intra_op_num_threads == 1
        models.share_cores(4 * cores)  # never below one thread
        assert models.session(path).get_session_options().intra_op_num_threads == 1
    finally:
        models.share_cores(1)
    monkeypatch.setenv(models.PROVIDER_ENV, "cpu")
    assert models.session(path).get_providers() == ["CPUExecutionProvider"]
    import onnxruntime

    if "CUDAExecutionProvider" not in onnxruntime.get_available_providers():
        assert models.execution_provider() == "CPUExecutionProvider"
        monkeypatch.setenv(models.PROVIDER_ENV, "cuda")
        with pytest.raises(models.ModelError, match="KBBATCH_PROVIDER=cuda: this onnxruntime "
                                                    "offers .*CPUExecutionProvider"):
            models.execution_provider()
    if "AzureExecutionProvider" in onnxruntime.get_available_providers():
        # listed as available, it ran nothing: the report said the models ran on Azure
        monkeypatch.setenv(models.PROVIDER_ENV, "AzureExecutionProvider")
        with pytest.raises(models.ModelError, match="KBBATCH_PROVIDER=AzureExecutionProvider: "
                           "AzureExecutionProvider calls a remote endpoint"):
            models.execution_provider()


def test_a_damaged_model_in_the_cache_stops_the_run_at_start_naming_the_file(
        tmp_path, monkeypatch):
    """A truncated download under a model's name failed every photo with onnxruntime's
    "Protobuf parsing failed", and the daemon filed every good photo in failed/."""
    from click.testing import CliRunner

    from kbbatch import models
    from kbbatch.cli import main

    spec = models.REGISTRY["isnet-dis-medium"]
    assert spec.sha256, "a pinned model"
    (tmp_path / spec.filename).write_bytes(b"garbage, not the network")
    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))
    with pytest.raises(models.ModelError, match=rf"{spec.filename}: not the file of model"):
        models.check_cache()
    (tmp_path / "photos").mkdir()
    for command in (["plan", str(tmp_path / "photos"), "-o", str(tmp_path / "m.json")],
                    ["watch", str(tmp_path / "photos"), "--out", str(tmp_path / "out")]):
        result = CliRunner().invoke(main, command)
        assert result.exit_code == 1 and isinstance(result.exception, SystemExit), command
        assert f"{spec.filename}: not the file of model isnet-dis-medium" in result.output
    assert not (tmp_path / "photos" / "failed").exists()


def test_a_provider_this_onnxruntime_lacks_stops_the_run_with_no_model_cached_too(
        tmp_path, monkeypatch):
    """Said to stop the run, a misspelt KBBATCH_PROVIDER went unsaid when no model was cached
    (the run made its clips, exit 0, and the first model pulled later failed on it)."""
    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))  # an empty cache
    monkeypatch.setenv(models.PROVIDER_ENV, "Bogus")
    with pytest.raises(models.ModelError, match="KBBATCH_PROVIDER=Bogus: this onnxruntime offers"):
        models.check_cache()
    monkeypatch.delenv(models.PROVIDER_ENV)
    models.check_cache()  # unset: nothing to check, onnxruntime is not needed


def test_a_network_of_another_kind_under_a_depth_models_name_stops_the_run_at_start(
        tmp_path, monkeypatch):
    """No checksum is known for the depth networks: a segmenter saved under the name failed at
    every photo with onnxruntime's words ("returned shape (1, 3, 518, 770)")."""
    from click.testing import CliRunner

    from kbbatch.cli import main

    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))
    path = tmp_path / "depth_anything_v2_small.onnx"
    path.write_bytes(tiny_depth_model(keep_channels=True))
    with pytest.raises(models.ModelError, match=r"depth_anything_v2_small.onnx: not a depth "
                       r"network of depth-anything-v2-small's kind: it gives \(1, 3, N, N\)"):
        models.check_cache()
    (tmp_path / "photos").mkdir()
    result = CliRunner().invoke(main, ["plan", str(tmp_path / "photos"), "-o",
                                       str(tmp_path / "m.json")])
    assert result.exit_code == 1 and "not a depth network" in result.output
    path.write_bytes(tiny_depth_model()[:40])  # a download cut short
    with pytest.raises(models.ModelError, match="depth_anything_v2_small.onnx: model "
                       "depth-anything-v2-small cannot be loaded"):
        models.check_cache()
    path.write_bytes(tiny_depth_model())
    models.check_cache()


def test_a_detector_or_segmenter_under_a_depth_models_name_stops_the_run_at_start(
        tmp_path, monkeypatch):
    """YOLOX's (1, 3549, 85) fitted a depth map's (1, N, N), and ISNet's (1, 1, 1024, 1024) is a
    depth network's shape: both passed the start check, and every photo then failed or got
    a saliency mask for its depth."""
    import shutil

    from .conftest import SHARED

    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))
    path = tmp_path / "depth_anything_v2_small.onnx"
    graph = helper.make_graph(  # a detector's rows of box scores: (1, 96, 32) from 32 x 32
        [helper.make_node("Reshape", ["images", "rows"], ["output"])], "tiny-detector",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, 32, 32])],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, [1, 96, 32])],
        [helper.make_tensor("rows", TensorProto.INT64, [3], [1, 96, 32])])
    detector = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    detector.ir_version = 8
    path.write_bytes(detector.SerializeToString())
    with pytest.raises(models.ModelError, match=r"not a depth network of depth-anything-v2-"
                       r"small's kind: it gives \(1, 96, 32\) for \(1, 3, 32, 32\), not an "
                       r"image of the input's shape"):
        models.check_cache()
    path.write_bytes(tiny_depth_model((1, 3, 32, 48)))  # a real depth net's fixed size passes
    models.check_cache()
    for name in ("isnet_dis_medium.onnx", "yolox_nano_coco_416.onnx"):
        real = SHARED / "models" / name
        if not real.is_file():
            pytest.skip(f"{real} is absent (../shared holds the real segmentation models)")
        shutil.copyfile(real, path)
        with pytest.raises(models.ModelError, match=r"depth_anything_v2_small.onnx: the file "
                           r"of model (isnet-dis-medium \(salient\)|yolox-nano \(detector\)), "
                           r"not of depth-anything-v2-small"):
            models.check_cache()


@pytest.mark.parametrize("input_shape", [(1, 3, 42, 56), (1, 3, 42, None)])
def test_a_depth_network_exported_at_a_fixed_size_is_fed_that_size(tmp_path, monkeypatch,
                                                                    input_shape):
    """Exports of Depth Anything at a fixed 518 x 518 are common; fed the photo's aspect at
    518 on the short side, onnxruntime refused every photo. With the height alone fixed, the
    start-up check passed and every photo failed."""
    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))
    (tmp_path / "depth_anything_v2_small.onnx").write_bytes(tiny_depth_model(input_shape))
    models.check_cache()
    image = textured_image(120, 180)
    image[:, :90] = 250
    image[:, 90:] = 10
    result = estimate_disparity(image, None, DepthOptions(backend="auto", adjust=False))
    assert result.source == "depth-anything-v2-small" and result.disparity.shape == (120, 180)
    assert result.disparity[:, :80].min() > result.disparity[:, 100:].max()


def test_a_models_folder_that_is_a_file_or_missing_is_said(tmp_path, monkeypatch, caplog):
    from click.testing import CliRunner

    from kbbatch.cli import main

    (tmp_path / "afile").write_text("not a folder")
    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path / "afile"))
    with pytest.raises(models.ModelError, match=r"KBBATCH_MODELS=.*afile: a file, not a folder"):
        models.check_cache()
    pulled = CliRunner().invoke(main, ["models", "pull", "yolox-nano"])
    assert pulled.exit_code == 1 and "afile: the model cache cannot be made there" in \
        pulled.output and "Traceback" not in pulled.output
    listed = CliRunner().invoke(main, ["models", "list"])  # it listed all as missing, status 0
    assert listed.exit_code == 1 and "afile: a file, not a folder of models" in listed.output
    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path / "modles"))  # a typo
    models.check_cache()
    assert "modles: no such folder; running without any network" in caplog.text


def test_models_list_says_damaged_and_how_to_mend_a_model_with_no_download(tmp_path,
                                                                          monkeypatch):
    from click.testing import CliRunner

    from kbbatch.cli import main

    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))
    spec = models.REGISTRY["isnet-dis-medium"]
    (tmp_path / spec.filename).write_bytes(b"garbage")
    listed = CliRunner().invoke(main, ["models", "list"])
    assert re.search(r"isnet-dis-medium +salient +DAMAGED", listed.output), listed.output
    assert "put the real isnet_dis_medium.onnx there (it has no single-file download" in \
        listed.output  # `models pull` cannot fetch it: that advice was a dead end
    # a folder under a model's name: listed "missing" (status 0), while every run refused it
    depth = models.REGISTRY["midas-v21-small"]
    (tmp_path / depth.filename).mkdir()
    listed = CliRunner().invoke(main, ["models", "list"])
    assert re.search(r"midas-v21-small +depth +DAMAGED", listed.output), listed.output
    assert f"{tmp_path / depth.filename}: has model midas-v21-small's name but is no file" in \
        listed.output


def test_running_a_network_sends_no_telemetry_and_leaves_no_files(tmp_path):
    """onnxruntime 1.29 and later send usage telemetry to Microsoft from Linux unless told not
    to before they load; on import they wrote a session file into TMPDIR (a batch whose TMPDIR
    was a small disk found a stray `.ses` there) and a database under ~/.cache/Microsoft."""
    import os
    import subprocess
    import sys

    model = tmp_path / "tiny.onnx"
    model.write_bytes(tiny_depth_model())
    home, temporary = tmp_path / "home", tmp_path / "tmp"
    home.mkdir()
    temporary.mkdir()
    script = ("import kbbatch, numpy, onnxruntime; from kbbatch import models; "
              f"session = models.session(__import__('pathlib').Path({str(model)!r})); "
              "session.run(None, {'pixel_values': numpy.ones((1, 3, 8, 8), numpy.float32)}); "
              "import os; print(os.environ['ORT_DISABLE_TELEMETRY'])")
    environment = {key: value for key, value in os.environ.items()
                   if key not in ("ORT_DISABLE_TELEMETRY", "XDG_CACHE_HOME")}
    environment.update(HOME=str(home), TMPDIR=str(temporary))
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env=environment, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "1"
    assert list(temporary.iterdir()) == []
    assert list(home.rglob("*")) == [], "onnxruntime wrote its telemetry files"
    # a user who wants onnxruntime's telemetry keeps their own setting
    environment["ORT_DISABLE_TELEMETRY"] = "0"
    kept = subprocess.run([sys.executable, "-c", "import os, kbbatch; "
                           "print(os.environ['ORT_DISABLE_TELEMETRY'])"],
                          capture_output=True, text=True, env=environment, timeout=120)
    assert kept.stdout.strip() == "0", kept.stderr


def test_a_folder_or_pipe_under_a_models_name_stops_the_run_at_start(tmp_path, monkeypatch):
    """Listed as "missing", and the run went on without that network, saying nothing."""
    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))
    spec = models.REGISTRY["yolox-nano"]
    for make in (lambda path: path.mkdir(), os.mkfifo,
                 lambda path: path.symlink_to(tmp_path / "nowhere.onnx")):
        path = tmp_path / spec.filename
        make(path)
        with pytest.raises(models.ModelError, match=rf"{spec.filename}: has model "
                           rf"{spec.name}'s name but is no file"):
            models.check_cache()
        if path.is_dir() and not path.is_symlink():
            path.rmdir()
        else:
            path.unlink()
    models.check_cache()


@pytest.mark.parametrize("given", ["zz", "abc", "g" * 64])
def test_a_sha256_that_is_no_checksum_is_refused_before_any_download(tmp_path, monkeypatch,
                                                                    given):
    """`models pull --sha256 zz` downloaded the whole file, then failed in pooch's words."""
    from click.testing import CliRunner

    from kbbatch.cli import main

    monkeypatch.setenv(models.MODELS_ENV, str(tmp_path))
    monkeypatch.setattr(models, "pull", lambda *a, **k: pytest.fail("downloaded"))
    result = CliRunner().invoke(main, ["models", "pull", "midas-v21-small", "--sha256", given])
    assert result.exit_code == 2, result.output
    assert f"Invalid value for '--sha256': '{given}' is not a sha256 (64 hex digits)" in \
        result.output
