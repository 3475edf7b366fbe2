"""The map on disk (runtime/aefabmap_runtime/adapters/state_dir.py): round trip, crash safety, hostile files."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError, StateError
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.state_dir import (
    CURRENT_NAME,
    FORMAT_VERSION,
    MANIFEST_NAME,
    MapStateDir,
    SnapshotPolicy,
    Snapshotter,
    bundle_id,
    load_into,
)
from aefabmap_runtime.core.detector import DetectorConfig
from tests.conftest import cli_args, make_synthetic_bundle

CONFIG = DetectorConfig(scorer="fabmap", exclude=3, max_places=30, verification=DetectorConfig().verification)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return make_synthetic_bundle(tmp_path_factory.mktemp("b") / "bundle", vocabulary_size=64)


def words_stream(n, seed=0, v=64):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, v, 40) for _ in range(n)]


def _public(res) -> dict:
    d = res.to_dict()
    d.pop("timings_ms", None)
    return d


def _run(det, stream):
    return [_public(det.process_words(w)) for w in stream]


def _saved(bundle, path, n=20, config=CONFIG):
    det = load_detector(bundle, config)
    _run(det, words_stream(40)[:n])
    with MapStateDir(path, bundle_id(det.manifest)) as d:
        d.save(det.state())
    return det


def test_save_load_round_trip_continues_the_run(bundle, tmp_path):
    stream = words_stream(60) + words_stream(20)  # the last 20 frames revisit the first 20
    whole = load_detector(bundle, CONFIG)
    expected = _run(whole, stream)
    first = load_detector(bundle, CONFIG)
    got = _run(first, stream[:37])
    with MapStateDir(tmp_path / "s", bundle_id(first.manifest)) as d:
        info = d.save(first.state())
        assert info.n_places == first.n_places and info.nbytes > 0
    second = load_detector(bundle, CONFIG)
    with MapStateDir(tmp_path / "s", bundle_id(second.manifest)) as d:
        assert load_into(second, d)
    got += _run(second, stream[37:])
    assert got == expected
    assert any(r["evicted_place"] is not None for r in expected)
    assert got[37]["sequence"] == 37  # frame numbers continue


def test_empty_directory_loads_nothing(bundle, tmp_path):
    det = load_detector(bundle, CONFIG)
    with MapStateDir(tmp_path / "new", bundle_id(det.manifest)) as d:
        assert not load_into(det, d)


def test_failed_write_keeps_the_previous_snapshot(bundle, tmp_path, monkeypatch):
    det = _saved(bundle, tmp_path / "s", n=10)
    before = det.state()
    _run(det, words_stream(10, seed=5))
    real_replace = os.replace

    def crash(src, dst, *a, **k):
        if "snap-" in str(src) or CURRENT_NAME in str(dst):
            raise OSError(28, "No space left on device")
        return real_replace(src, dst, *a, **k)

    with MapStateDir(tmp_path / "s", bundle_id(det.manifest)) as d:
        monkeypatch.setattr(os, "replace", crash)
        with pytest.raises(StateError, match="No space left"):
            d.save(det.state())
        monkeypatch.setattr(os, "replace", real_replace)
        assert d.current() == "snap-000001"
        loaded = d.load()
    assert loaded.scalars["sequence"] == before.scalars["sequence"] == 10
    assert not [p for p in (tmp_path / "s").iterdir() if p.name.startswith(".tmp")]


def test_crash_between_rename_and_current_keeps_the_previous_snapshot(bundle, tmp_path, monkeypatch):
    det = _saved(bundle, tmp_path / "s", n=10)
    _run(det, words_stream(5, seed=6))
    real_replace = os.replace

    def crash(src, dst, *a, **k):
        if CURRENT_NAME in str(dst):
            raise OSError(5, "Input/output error")
        return real_replace(src, dst, *a, **k)

    with MapStateDir(tmp_path / "s", bundle_id(det.manifest)) as d:
        monkeypatch.setattr(os, "replace", crash)
        with pytest.raises(StateError):
            d.save(det.state())
        monkeypatch.setattr(os, "replace", real_replace)
        assert d.load().scalars["sequence"] == 10
        d.save(det.state())  # the next save goes past the orphaned snapshot
        assert d.load().scalars["sequence"] == 15


def test_snapshots_rotate_keeping_current_and_previous(bundle, tmp_path):
    det = load_detector(bundle, CONFIG)
    with MapStateDir(tmp_path / "s", bundle_id(det.manifest)) as d:
        for w in words_stream(4):
            det.process_words(w)
            d.save(det.state())
        assert sorted(p.name for p in (tmp_path / "s").iterdir() if p.name.startswith("snap")) == [
            "snap-000003", "snap-000004"]


def test_directory_is_locked_by_one_process(bundle, tmp_path):
    with MapStateDir(tmp_path / "s", "x"), pytest.raises(StateError, match="in use"):
        MapStateDir(tmp_path / "s", "x").open()


def _snap(path):
    return path / (path / CURRENT_NAME).read_text().strip()


def _refused(bundle, path, config=CONFIG) -> str:
    det = load_detector(bundle, config)
    with MapStateDir(path, bundle_id(det.manifest)) as d, pytest.raises(StateError) as info:
        load_into(det, d)
    msg = str(info.value)
    assert "\n" not in msg and len(msg) < 300
    return msg


def _rewrite_array(path, key, array):
    """Replace one array with its checksum updated (only the core's checks can refuse it)."""
    import hashlib
    import io

    snap = _snap(path)
    buf = io.BytesIO()
    np.save(buf, array)
    (snap / f"{key}.npy").write_bytes(buf.getvalue())
    doc = json.loads((snap / MANIFEST_NAME).read_text())
    doc["arrays"][key]["sha256"] = hashlib.sha256(buf.getvalue()).hexdigest()
    (snap / MANIFEST_NAME).write_text(json.dumps(doc))


def test_truncated_array_is_refused(bundle, tmp_path):
    _saved(bundle, tmp_path / "s")
    p = _snap(tmp_path / "s") / "scorer.places.postings.npy"
    p.write_bytes(p.read_bytes()[:-8])
    assert "checksum" in _refused(bundle, tmp_path / "s")


def test_lying_npy_header_is_refused(bundle, tmp_path):
    import hashlib

    _saved(bundle, tmp_path / "s")
    snap = _snap(tmp_path / "s")
    p = snap / "place_frame.npy"
    data = p.read_bytes().replace(b"'shape': (64,)", b"'shape': (9999999999,)")
    p.write_bytes(data)
    doc = json.loads((snap / MANIFEST_NAME).read_text())
    doc["arrays"]["place_frame"]["sha256"] = hashlib.sha256(data).hexdigest()
    (snap / MANIFEST_NAME).write_text(json.dumps(doc))
    assert "place_frame" in _refused(bundle, tmp_path / "s")


def test_wrong_shape_and_out_of_range_ids_are_refused(bundle, tmp_path):
    _saved(bundle, tmp_path / "s")
    _rewrite_array(tmp_path / "s", "last_used", np.zeros((3, 3), np.int64))
    assert "last_used" in _refused(bundle, tmp_path / "s")
    _saved(bundle, tmp_path / "t")
    _rewrite_array(tmp_path / "t", "scorer.places.free", np.array([10**9], np.int64))
    assert "free" in _refused(bundle, tmp_path / "t")
    _saved(bundle, tmp_path / "u")
    post = np.load(_snap(tmp_path / "u") / "scorer.places.words.npy")
    post[0] = 64  # a word id == vocabulary size
    _rewrite_array(tmp_path / "u", "scorer.places.words", post)
    assert "words" in _refused(bundle, tmp_path / "u")


def test_other_bundle_and_newer_format_are_refused(bundle, tmp_path):
    _saved(bundle, tmp_path / "s")
    other = make_synthetic_bundle(tmp_path / "other", vocabulary_size=64, seed=1)
    assert "another model bundle" in _refused(other, tmp_path / "s")
    snap = _snap(tmp_path / "s")
    doc = json.loads((snap / MANIFEST_NAME).read_text())
    doc["version"] = FORMAT_VERSION + 1
    (snap / MANIFEST_NAME).write_text(json.dumps(doc))
    assert "newer" in _refused(bundle, tmp_path / "s")


def test_settings_mismatch_is_refused(bundle, tmp_path):
    _saved(bundle, tmp_path / "s")
    assert "scorer" in _refused(bundle, tmp_path / "s", DetectorConfig(scorer="bow", exclude=3))


def test_symlinks_leaving_the_directory_are_refused(bundle, tmp_path):
    _saved(bundle, tmp_path / "s")
    outside = tmp_path / "outside.npy"
    np.save(outside, np.zeros(64, np.int64))
    p = _snap(tmp_path / "s") / "last_used.npy"
    p.unlink()
    p.symlink_to(outside)
    assert "last_used" in _refused(bundle, tmp_path / "s")
    _saved(bundle, tmp_path / "t")
    (tmp_path / "t" / CURRENT_NAME).write_text("../s/snap-000001\n")
    assert "does not name a snapshot" in _refused(bundle, tmp_path / "t")
    _saved(bundle, tmp_path / "u")
    snap = _snap(tmp_path / "u")
    snap.rename(tmp_path / "elsewhere")
    snap.symlink_to(tmp_path / "elsewhere")
    assert "not a directory" in _refused(bundle, tmp_path / "u")


def test_snapshot_policy_parse():
    assert SnapshotPolicy.parse("30s") == SnapshotPolicy(seconds=30.0, places=None)
    assert SnapshotPolicy.parse("5m") == SnapshotPolicy(seconds=300.0, places=None)
    assert SnapshotPolicy.parse("100p") == SnapshotPolicy(seconds=None, places=100)
    for bad in ("", "0s", "10", "1.5p", "-3s", "10x"):
        with pytest.raises(ConfigError):
            SnapshotPolicy.parse(bad)


def test_snapshotter_saves_every_n_places(bundle, tmp_path):
    det = load_detector(bundle, DetectorConfig(exclude=3))
    with MapStateDir(tmp_path / "s", bundle_id(det.manifest)) as d:
        snap = Snapshotter(det, d, SnapshotPolicy(seconds=None, places=5))
        for w in words_stream(23):
            det.process_words(w)
            snap.after_frame()
        # 20 frames entered the map (exclude 3): a snapshot after each 5.
        assert [s.n_places for s in snap.saved] == [5, 10, 15, 20]
        snap.final()
        assert d.load().scalars["sequence"] == 23


def test_snapshotter_keeps_running_when_a_snapshot_fails(bundle, tmp_path, monkeypatch):
    det = load_detector(bundle, DetectorConfig(exclude=0))
    errors = []
    with MapStateDir(tmp_path / "s", bundle_id(det.manifest)) as d:
        snap = Snapshotter(det, d, SnapshotPolicy(seconds=None, places=1), on_error=errors.append)
        monkeypatch.setattr(d, "save", lambda state: (_ for _ in ()).throw(StateError("disk full")))
        det.process_words(words_stream(1)[0])
        det.process_words(words_stream(1)[0])
        snap.after_frame()
    assert snap.failures == 1 and len(errors) == 1


def _write_log(path, images, first_seq: int) -> None:
    from aefabmap_runtime.adapters.frames import encode_frame
    from aefabmap_runtime.adapters.mcap_log import McapLogWriter

    with McapLogWriter(path) as w:
        for i, img in enumerate(images):
            payload, encoding = encode_frame(img, "png")
            w.write_image(payload, encoding, (first_seq + i) * 10**8, sequence=first_seq + i)


def test_replay_builds_a_map_offline_and_continues_it(bundle, tmp_path, capsys):
    """`replay --state`: a map built from one log is loaded by the replay of the next log; the
    results are those of one replay over both."""

    from aefabmap.cli import replay as cli_replay
    from aefabmap_runtime.adapters.replay import replay
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images = generate_loop_sequence(120, seed=2, size=(160, 120))[0][:70]  # revisits from frame 63 on
    _write_log(tmp_path / "all.mcap", images, 0)
    _write_log(tmp_path / "a.mcap", images[:60], 0)
    _write_log(tmp_path / "b.mcap", images[60:], 60)
    from aefabmap_runtime.core.run_config import logged_run_config

    # These logs carry no run configuration, so `replay` runs them as such logs ran (logged_run_config).
    as_logged = logged_run_config({}).detector
    whole = replay(load_detector(bundle, as_logged), tmp_path / "all.mcap", out_path=tmp_path / "all_out.mcap")
    assert whole.frames_processed == 70
    for name in ("a", "b"):
        args = cli_args("replay", tmp_path / f"{name}.mcap", "--model", bundle, "--out", tmp_path / f"{name}_out.mcap",
                        "--state", tmp_path / "state")
        assert cli_replay.main(args) == 0
    capsys.readouterr()
    from aefabmap_runtime.adapters.mcap_log import McapLogReader

    def results(path):
        reader = McapLogReader(path)
        for _ in reader.frames():  # results are collected while reading
            pass
        docs = [r.to_dict() for r in reader.results]
        return [{k: v for k, v in d.items() if k not in ("timings_ms", "stamp_ns")} for d in docs]

    split = results(tmp_path / "a_out.mcap") + results(tmp_path / "b_out.mcap")
    assert [d["sequence"] for d in split] == list(range(70))
    assert split == results(tmp_path / "all_out.mcap")
    assert any(d["loop"] and d["verified_frame"] < 60 for d in split[60:])


def test_background_snapshots_write_in_a_thread_and_final_waits(bundle, tmp_path):
    det = load_detector(bundle, DetectorConfig(exclude=0))
    with MapStateDir(tmp_path / "s", bundle_id(det.manifest)) as d:
        snap = Snapshotter(det, d, SnapshotPolicy(seconds=None, places=3), background=True)
        for w in words_stream(10):
            det.process_words(w)
            snap.after_frame()
        snap.final()
        assert snap._writer is None and len(snap.saved) >= 2
        assert d.load().scalars["sequence"] == 10


def test_eval_saves_the_map_it_built_and_will_not_overwrite_one(bundle, tmp_path, caplog):
    from aefabmap.cli.main import main
    from aefabmap_runtime.tools.synthetic_route import (
        generate_loop_sequence,
        write_sequence,
    )

    images, gt = generate_loop_sequence(12, seed=1, size=(160, 120))
    write_sequence(tmp_path / "seq", images, gt)
    argv = ["eval", "--model", str(bundle), "--images", str(tmp_path / "seq"), "--gt", str(tmp_path / "seq" / "gt.npy"),
            "--exclude", "2", "--no-progress", "--state", str(tmp_path / "state")]
    assert main(argv) == 0
    det = load_detector(bundle, DetectorConfig(exclude=2))
    with MapStateDir(tmp_path / "state", bundle_id(det.manifest)) as d:
        assert load_into(det, d)
    assert det.n_places == 10 and det.next_sequence == 12
    assert main(argv) == 2  # DIR already holds a map
    assert "already holds a map" in caplog.text


def test_a_corrupt_current_snapshot_names_the_previous_one(bundle, tmp_path):
    det = _saved(bundle, tmp_path / "s", n=10)
    with MapStateDir(tmp_path / "s", bundle_id(det.manifest)) as d:
        d.save(det.state())
    p = _snap(tmp_path / "s") / "last_used.npy"
    p.write_bytes(p.read_bytes()[:-1])
    msg = _refused(bundle, tmp_path / "s")
    assert "checksum" in msg and "snap-000001" in msg
    (tmp_path / "s" / CURRENT_NAME).write_text("snap-000001\n")
    det2 = load_detector(bundle, CONFIG)
    with MapStateDir(tmp_path / "s", bundle_id(det2.manifest)) as d:
        assert load_into(det2, d) and det2.next_sequence == 10


def test_malformed_manifest_and_missing_array_are_refused(bundle, tmp_path):
    _saved(bundle, tmp_path / "s")
    (_snap(tmp_path / "s") / MANIFEST_NAME).write_bytes(b"{not json")
    assert "not valid JSON" in _refused(bundle, tmp_path / "s")
    _saved(bundle, tmp_path / "t")
    doc = json.loads((_snap(tmp_path / "t") / MANIFEST_NAME).read_text())
    doc["arrays"]["../../etc/passwd"] = {"sha256": "0" * 64}
    (_snap(tmp_path / "t") / MANIFEST_NAME).write_text(json.dumps(doc))
    assert "bad array entry" in _refused(bundle, tmp_path / "t")
    _saved(bundle, tmp_path / "u")
    (_snap(tmp_path / "u") / "scorer.places.alive.npy").unlink()
    assert "scorer.places.alive" in _refused(bundle, tmp_path / "u")


@pytest.mark.timeout(60)
@pytest.mark.parametrize("what", ["fifo-current", "fifo-array", "device-array", "directory-array",
                                  "fifo-manifest"])
def test_special_files_in_a_state_are_refused_in_one_line_without_hanging(bundle, tmp_path, what):
    """A FIFO (no writer: a plain open blocks forever), a character device (a read never ends) or
    a directory where the state has a file."""
    import stat as stat_module

    path = tmp_path / "s"
    _saved(bundle, path)
    snap = _snap(path)
    target = {"fifo-current": path / CURRENT_NAME, "fifo-array": snap / "last_used.npy",
              "device-array": snap / "place_frame.npy", "directory-array": snap / "last_used.npy",
              "fifo-manifest": snap / "manifest.json"}[what]
    target.unlink()
    if what.startswith("fifo"):
        os.mkfifo(target)
    elif what == "device-array":
        try:
            os.mknod(target, 0o644 | stat_module.S_IFCHR, os.makedev(1, 5))  # like /dev/zero
        except PermissionError:
            pytest.skip("creating a device node needs root")
    else:
        target.mkdir()
    assert "not a regular file" in _refused(bundle, path)


def _snapshot_bytes(path) -> int:
    """Bytes a snapshot directory takes on a tmpfs (4 KiB pages per file)."""
    return sum(-(-p.stat().st_size // 4096) * 4096 for p in path.iterdir()) + 4096


def test_a_full_disk_drops_the_older_snapshot_before_the_newest_map(bundle, tmp_path):
    """State on a small real tmpfs: two snapshots fit, a third does not. The third save used to
    fail, leaving the map of the older current snapshot; now the snapshot before the current one
    is dropped and the newest map is written."""
    from .stream_fakes import mounted_tmpfs

    det = load_detector(bundle, CONFIG)
    _run(det, words_stream(40)[:20])
    probe = tmp_path / "probe"
    with MapStateDir(probe, bundle_id(det.manifest)) as d:
        size = _snapshot_bytes(d.save(det.state()).path)
    disk = tmp_path / "disk"
    disk.mkdir()
    with mounted_tmpfs(disk, size=f"{(5 * size // 2) // 1024}k"):
        with MapStateDir(disk, bundle_id(det.manifest)) as d:
            d.save(det.state())
            d.save(det.state())
            _run(det, words_stream(40, seed=1)[:5])  # the map grew since
            info = d.save(det.state())
            assert info.n_places == det.n_places and d.current() == info.path.name
            snaps = sorted(p.name for p in disk.iterdir() if p.name.startswith("snap-"))
            assert snaps == ["snap-000002", info.path.name]  # the oldest gave way, the previous is kept
        again = load_detector(bundle, CONFIG)
        with MapStateDir(disk, bundle_id(det.manifest)) as d:
            assert load_into(again, d) and again.n_places == det.n_places
