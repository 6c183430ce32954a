"""The depth cache's size bound: least recently used entries go first, the newest stay, and a
reader never sees a partial entry while another process writes and evicts."""

import logging
import multiprocessing
import time

import numpy as np
import pytest

from kbbatch.depth import DepthResult
from kbbatch.depth import cache as depth_cache

SIDE_PX = 256  # one entry: 256 KiB of float32 plus the npz header
TICK_S = 0.03
"""Between cache operations: longer than the file system's coarse timestamp tick (1-10 ms)."""


def key(index: int) -> str:
    return f"{index:032x}"


def result(value: float, side_px: int = SIDE_PX) -> DepthResult:
    return DepthResult(np.full((side_px, side_px), value, np.float32), "ramp", "test")


def present() -> set[int]:
    return {int(path.stem, 16) for path in depth_cache.cache_dir().glob("*.npz")}


def test_past_its_bound_the_least_recently_used_entries_go(monkeypatch):
    monkeypatch.setenv(depth_cache.CACHE_MAX_ENV, "1")  # 1 MiB: three entries fit, not four
    for index in range(3):
        depth_cache.store(key(index), result(index + 1))
        time.sleep(TICK_S)
    assert present() == {0, 1, 2}
    assert depth_cache.load(key(0)).disparity[0, 0] == 1  # read: now the most recently used
    time.sleep(TICK_S)
    depth_cache.store(key(3), result(4))
    assert present() == {0, 2, 3}, "the least recently used entry (1) should have gone"
    for index in range(4, 8):
        time.sleep(TICK_S)
        depth_cache.store(key(index), result(index + 1))
    assert present() == {5, 6, 7}
    total = sum(path.stat().st_size for path in depth_cache.cache_dir().glob("*.npz"))
    assert total <= 2**20
    for index in (5, 6, 7):
        assert depth_cache.load(key(index)).disparity[0, 0] == index + 1


def test_a_map_added_to_an_entry_keeps_the_folder_in_its_bound(monkeypatch):
    monkeypatch.setenv(depth_cache.CACHE_MAX_ENV, "0.8")  # three entries, not with a map
    for index in range(3):
        depth_cache.store(key(index), result(index))
        time.sleep(TICK_S)
    depth_cache.add_saliency(key(1), np.full((SIDE_PX, SIDE_PX), 0.7, np.float32))
    assert present() == {1, 2}, "the least recently used entry (0) should have gone"
    total = sum(path.stat().st_size for path in depth_cache.cache_dir().glob("*.npz"))
    assert total <= 0.8 * 2**20
    image = np.zeros((SIDE_PX, SIDE_PX, 3), np.uint8)
    assert depth_cache.load(key(1), image).segmentation.known_saliency()[0, 0] == (
        pytest.approx(0.7, abs=1e-4))


def test_an_entry_larger_than_the_bound_is_still_kept(monkeypatch):
    monkeypatch.setenv(depth_cache.CACHE_MAX_ENV, "0.1")
    depth_cache.store(key(1), result(1))
    time.sleep(TICK_S)
    depth_cache.store(key(2), result(2))
    assert present() == {2}


def test_the_bound_defaults_to_2_gb_and_a_bad_value_is_refused(monkeypatch, caplog):
    monkeypatch.delenv(depth_cache.CACHE_MAX_ENV, raising=False)
    assert depth_cache.cache_max_bytes() == 2048 * 2**20
    monkeypatch.setenv(depth_cache.CACHE_MAX_ENV, "500")
    assert depth_cache.cache_max_bytes() == 500 * 2**20
    for value in ("lots", "inf", "nan", "-5"):  # inf failed every photo with an OverflowError
        monkeypatch.setenv(depth_cache.CACHE_MAX_ENV, value)
        with pytest.raises(depth_cache.CacheSettingError, match=f"={value!r} is not a size"):
            depth_cache.cache_max_bytes()
    with caplog.at_level(logging.WARNING):  # a library caller's store: said, kept to the default
        depth_cache.store(key(1), result(1))
    assert present() == {1}
    assert "'-5' is not a size in MB" in caplog.text


def test_every_command_refuses_a_bad_bound_at_start(tmp_path, monkeypatch):
    """Before, it was only logged (and only by a run that stored depth)."""
    from click.testing import CliRunner

    from kbbatch.cli import main

    (tmp_path / "photos").mkdir()
    monkeypatch.setenv(depth_cache.CACHE_MAX_ENV, "abc")
    for command in (["render", str(tmp_path / "photos")],
                    ["plan", str(tmp_path / "photos"), "-o", str(tmp_path / "m.json")],
                    ["watch", str(tmp_path / "photos"), "--out", str(tmp_path / "out")]):
        run = CliRunner().invoke(main, command)
        assert run.exit_code != 0 and "KBBATCH_CACHE_MAX_MB='abc' is not a size" in run.output, (
            command, run.output)
    assert not (tmp_path / "out").exists() and not (tmp_path / "m.json").exists()


def test_a_damaged_entry_is_a_miss_not_an_error():
    depth_cache.store(key(1), result(1))
    path = depth_cache.cache_dir() / f"{key(1)}.npz"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])  # truncated by a bad copy
    assert depth_cache.load(key(1)) is None


def test_an_entry_of_values_no_disparity_has_is_a_miss_not_a_failed_photo():
    """Edited by hand (a valid file, a few NaN pixels), an entry failed its photo on every
    run: "disparity has no positive finite maximum", the cache never named."""
    for index, spoil in enumerate((lambda d: d.__setitem__((slice(2, 4), slice(2, 4)), np.nan),
                                   lambda d: d.fill(np.inf), lambda d: d.fill(-1.0)), 1):
        depth_cache.store(key(index), result(1.0))
        path = depth_cache.cache_dir() / f"{key(index)}.npz"
        with np.load(path) as data:
            arrays = dict(data)
        spoil(arrays["disparity"])
        np.savez(path, **arrays)
        assert depth_cache.load(key(index)) is None


WATCHED = 99
"""The entry the reader reads: the writer rewrites it in place, each time followed by another
entry that pushes the folder past its bound; it is never the least recently used one, so a
miss can only mean a reader met a partial file."""


def write_and_evict(rounds: int) -> None:
    """Another process: rewrites the watched entry and fills the cache past its bound."""
    for index in range(rounds):
        depth_cache.store(key(WATCHED), result(float(1 + index % 2), 1024))
        depth_cache.store(key(1 + index % 5), result(7.0, 1024))


def test_a_reader_never_sees_a_partial_entry_while_another_process_writes(monkeypatch):
    monkeypatch.setenv(depth_cache.CACHE_MAX_ENV, "10")  # 4 MiB entries: constant eviction
    depth_cache.store(key(WATCHED), result(1.0, 1024))
    writer = multiprocessing.get_context("fork").Process(target=write_and_evict, args=(40,))
    writer.start()
    reads = 0
    try:
        while writer.is_alive():
            loaded = depth_cache.load(key(WATCHED))
            assert loaded is not None, "the entry was missing or partial while being rewritten"
            reads += 1
            assert loaded.disparity.shape == (1024, 1024)
            values = np.unique(loaded.disparity)
            assert len(values) == 1 and values[0] in (1.0, 2.0), f"mixed entry: {values[:5]}"
    finally:
        writer.join(timeout=60)
    assert writer.exitcode == 0
    assert reads > 10, "the reader did not overlap the writer"
    assert len(list(depth_cache.cache_dir().glob("*.npz"))) <= 2, "the bound was not kept"
    assert not list(depth_cache.cache_dir().glob(".*part*")), "a temporary file was left"


def test_a_cache_that_cannot_be_written_is_said_once(tmp_path, monkeypatch, caplog):
    """KBBATCH_CACHE naming a file turned caching off without a word."""
    (tmp_path / "a-file").write_text("not a folder")
    monkeypatch.setenv(depth_cache.CACHE_ENV, str(tmp_path / "a-file"))
    with caplog.at_level(logging.WARNING):
        depth_cache.store(key(1), result(1))
        depth_cache.store(key(2), result(2))
    assert depth_cache.load(key(1)) is None
    assert caplog.text.count("depth cache cannot be written") == 1
    assert "a-file" in caplog.text


def test_an_entry_keeps_isnets_map_for_the_planner():
    """A cache hit ran ISNet again (1.7 s) for every photo a vertical or square preset frames:
    an entry now keeps the map the depth stage worked out, at 16-bit levels."""
    from kbbatch.depth import SceneContext

    image = np.zeros((SIDE_PX, SIDE_PX, 3), np.uint8)
    saliency = np.random.default_rng(0).random((SIDE_PX, SIDE_PX)).astype(np.float32)
    stored = DepthResult(result(1.0).disparity, "popup", "test",
                         SceneContext.known(image, saliency))
    depth_cache.store(key(1), stored)
    depth_cache.store(key(2), result(2.0))  # no map worked out: none kept
    loaded = depth_cache.load(key(1), image).segmentation.known_saliency()
    assert np.abs(loaded - saliency).max() <= 0.5 / depth_cache.SALIENCY_LEVELS + 1e-7
    assert np.array_equal(loaded >= 0.5, saliency >= 0.5)  # the planner's threshold
    assert depth_cache.load(key(2), image).segmentation is None
    depth_cache.add_saliency(key(2), saliency)  # worked out later, by the planner
    assert np.allclose(depth_cache.load(key(2), image).segmentation.known_saliency(),
                       loaded)
    assert depth_cache.load(key(2)).disparity[0, 0] == 2.0
    assert depth_cache.load(key(1)).segmentation is None  # no photo to tie it to
    other_size = np.zeros((SIDE_PX // 2, SIDE_PX, 3), np.uint8)
    assert depth_cache.load(key(1), other_size).segmentation is None


def test_only_the_depth_stages_own_map_frames_where_isnet_is_not_run_for_framing():
    """A map the planner added to an entry (a vertical preset framed the photo first) made a
    later `slideshow` plan differ from one without that history: there only the depth stage's
    own map is used."""
    from kbbatch.depth import SceneContext
    from kbbatch.pipeline import plan_request
    from kbbatch.presets import load_preset

    image = np.zeros((SIDE_PX, SIDE_PX, 3), np.uint8)
    saliency = np.full((SIDE_PX, SIDE_PX), 0.9, np.float32)
    depth = np.full((SIDE_PX, SIDE_PX), 2.0, np.float32)
    preset = load_preset("slideshow")
    depth_cache.store(key(1), DepthResult(result(1.0).disparity, "popup", "test",
                                          SceneContext.known(image, saliency)))
    depth_cache.store(key(2), DepthResult(result(1.0).disparity, "popup", "test"))
    depth_cache.add_saliency(key(2), saliency)  # worked out later, by the planner
    own = plan_request(image, depth_cache.load(key(1), image), depth, preset)
    added = plan_request(image, depth_cache.load(key(2), image), depth, preset)
    assert own.known_saliency() is not None and added.known_saliency() is None
    assert added.saliency() is not None  # where framing is free, the planner reads it
    fresh = plan_request(image, DepthResult(result(1.0).disparity, "popup", "test",
                                            SceneContext(image)), depth, preset)
    assert fresh.known_saliency() is None


def test_the_users_own_cache_is_private(tmp_path, monkeypatch):
    """Depth maps, plans and preview clips of photos in a private folder sat in a 755 cache
    under a 755 home: every user of the machine could read them."""
    import stat

    from kbbatch.depth import cache

    monkeypatch.delenv(cache.CACHE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    cache._made_private.cache_clear()
    made = cache.cache_dir()
    assert made == tmp_path / "xdg" / "kbbatch" / "depth"
    assert stat.S_IMODE(made.stat().st_mode) == 0o700
    made.chmod(0o755)  # an earlier version's
    cache._made_private.cache_clear()
    assert stat.S_IMODE(cache.cache_dir().stat().st_mode) == 0o700
    # a cache named on purpose (KBBATCH_CACHE, perhaps shared) keeps its mode
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o755)
    monkeypatch.setenv(cache.CACHE_ENV, str(shared))
    assert cache.cache_dir() == shared and stat.S_IMODE(shared.stat().st_mode) == 0o755
