"""The map journal (runtime/aefabmap_runtime/adapters/map_journal.py): frames between snapshots survive a kill,
a full disk loses only the frames it could not take, and hostile journals are refused or cut."""

from __future__ import annotations

import dataclasses
import errno
import os
import struct
import zlib

import numpy as np
import pytest

from aefabmap_runtime.errors import StateError
from aefabmap_runtime.adapters import map_journal, state_dir
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.map_journal import MapJournal, replay_journal, segments
from aefabmap_runtime.adapters.state_dir import (
    MapStateDir,
    SnapshotPolicy,
    Snapshotter,
    bundle_id,
    load_into,
)
from aefabmap_runtime.core.decide.candidates import CandidateConfig
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.map.map_events import MapListener
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence
from tests.conftest import make_synthetic_bundle

CONFIG = DetectorConfig(exclude=3, max_places=30)  # evictions and verified loops within 60 frames
N = 60


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return make_synthetic_bundle(tmp_path_factory.mktemp("b") / "bundle")


@pytest.fixture(scope="module")
def images():
    return generate_loop_sequence(N, seed=2, size=(160, 120))[0]


def _public(res) -> dict:
    d = res.to_dict()
    d.pop("timings_ms", None)
    return d


@pytest.fixture(scope="module")
def reference(bundle, images):
    """The uninterrupted run's results."""
    det = load_detector(bundle, CONFIG)
    return [_public(det.process(img, i)) for i, img in enumerate(images)]


def _live(bundle, path, images, *, places=15, stop_with_snapshot=False, between=None):
    """A node's run over `images` with a journal and snapshots every `places` places; no final
    snapshot unless asked (as a kill -9 or a failed final write). between(i) runs before frame i.
    Returns (detector, journal report, snapshotter)."""
    det = load_detector(bundle, CONFIG)
    with MapStateDir(path, bundle_id(det.manifest)) as d:
        load_into(det, d)
        errors = []
        journal = MapJournal(d, det, on_error=errors.append)
        snap = Snapshotter(det, d, SnapshotPolicy(seconds=None, places=places), journal=journal, on_error=errors.append)
        first = det.next_sequence
        for i, img in enumerate(images, first):
            if between is not None:
                between(i)
            det.process(img, i)
            snap.after_frame()
        if stop_with_snapshot:
            snap.final()
        journal.close()
        report = journal.report()
    assert all("\n" not in str(e) for e in errors)
    return det, report, snap


def _restart(bundle, path, images, reference):
    """Load the state from `path` and run the frames after it: they must give the uninterrupted
    run's results. Returns the loaded detector's (frames, places)."""
    det = load_detector(bundle, CONFIG)
    with MapStateDir(path, bundle_id(det.manifest)) as d:
        load_into(det, d)
    loaded = (det.next_sequence, det.n_places)
    got = [_public(det.process(img, i)) for i, img in enumerate(images[loaded[0]:], loaded[0])]
    assert got == reference[loaded[0]:]
    return loaded


def test_a_kill_between_snapshots_loses_no_frame(bundle, images, reference, tmp_path):
    det, report, snap = _live(bundle, tmp_path / "s", images[:40])
    assert [info.path.name for info in snap.saved] == ["snap-000001", "snap-000002"]  # at frames 18 and 33
    assert report.frames_kept == report.frames_processed == 40 and report.frames_not_written == 0
    assert [b for b, _ in segments(tmp_path / "s")] == [33]  # the older segments went with their snapshots
    assert _restart(bundle, tmp_path / "s", images, reference) == (40, det.n_places)


def test_a_clean_stop_leaves_the_snapshot_alone(bundle, images, tmp_path):
    _, report, _ = _live(bundle, tmp_path / "s", images[:20], stop_with_snapshot=True)
    assert report.frames_kept == 20 and not segments(tmp_path / "s")


def test_the_journal_of_a_restarted_run_continues_the_chain(bundle, images, reference, tmp_path):
    _live(bundle, tmp_path / "s", images[:25])
    det, report, _ = _live(bundle, tmp_path / "s", images[25:45])
    assert det.next_sequence == 45 and report.frames_kept == 45
    assert _restart(bundle, tmp_path / "s", images, reference) == (45, det.n_places)


class FakeDisk:
    """A disk of `budget` bytes at the OS boundary: journal writes (os.write) and snapshot files
    fail with ENOSPC once it is spent (a write crossing it is cut short, as a real disk does)."""

    def __init__(self, monkeypatch, budget: int) -> None:
        self.left = budget
        real_write, real_file = os.write, state_dir._write_file

        def write(fd, data):
            if self.left <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            n = real_write(fd, bytes(data[: self.left]))
            self.left -= n
            return n

        def write_file(path, data):
            if self.left < len(data):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            self.left -= len(data)
            real_file(path, data)

        monkeypatch.setattr(map_journal, "_os_write", write)
        monkeypatch.setattr(state_dir, "_write_file", write_file)


def test_a_full_disk_loses_only_the_frames_it_could_not_take(bundle, images, reference, tmp_path, monkeypatch):
    disk = FakeDisk(monkeypatch, budget=10**12)

    def fill(i):
        if i == 27:
            disk.left = 8000  # a few frames more, then full
    det, report, snap = _live(bundle, tmp_path / "s", images[:50], stop_with_snapshot=True, between=fill)
    assert det.next_sequence == 50 and snap.failures >= 1  # the final snapshot did not fit either
    assert report.write_failures >= 1 and report.error == "disk full"
    assert 27 < report.frames_kept < 50 and report.frames_not_written == 50 - report.frames_kept
    assert "not written (disk full)" in report.line() and f"{report.places_kept} places kept on disk" in report.line()
    monkeypatch.undo()
    assert _restart(bundle, tmp_path / "s", images, reference) == (report.frames_kept, report.places_kept)


def test_when_space_returns_a_snapshot_catches_up(bundle, images, reference, tmp_path, monkeypatch):
    disk = FakeDisk(monkeypatch, budget=10**12)
    clock = [0.0]

    def fill_then_free(i):
        clock[0] += 1.0
        disk.left = 8000 if i == 22 else (10**12 if i == 35 else disk.left)

    det = load_detector(bundle, CONFIG)
    with MapStateDir(tmp_path / "s", bundle_id(det.manifest)) as d:
        journal = MapJournal(d, det, clock=lambda: clock[0])
        snap = Snapshotter(det, d, SnapshotPolicy(seconds=None, places=100), journal=journal, retry_s=5.0,
                           clock=lambda: clock[0])
        behind = []
        for i, img in enumerate(images[:45]):
            fill_then_free(i)
            det.process(img, i)
            snap.after_frame()
            behind.append(journal.behind)
        journal.close()
        report = journal.report()
    assert any(behind) and not behind[-1]  # behind while full, caught up once space returned
    assert report.frames_kept == 45 and report.frames_not_written == 0 and report.write_failures >= 1
    assert _restart(bundle, tmp_path / "s", images, reference) == (45, det.n_places)


def _snapshot_pages(path) -> int:
    return sum(-(-p.stat().st_size // 4096) * 4096 for p in path.iterdir()) + 4096


def test_state_on_a_small_tmpfs_that_fills_mid_run(bundle, images, reference, tmp_path):
    """A real disk: a tmpfs that a filler takes over at frame 30. The frames processed, the frames
    and places kept on disk, and a restart that loads exactly those and continues identically."""
    from .stream_fakes import mounted_tmpfs

    disk = tmp_path / "disk"
    disk.mkdir()
    with mounted_tmpfs(disk, size="1m"):
        state = disk / "state"

        def fill(i):
            """From frame 30 on another writer takes whatever space is free (the first time, all but
            a few pages): the disk stays full, whatever the node frees."""
            if i < 30:
                return
            with open(disk / "filler", "ab", buffering=0) as fh:
                try:
                    while True:
                        fh.write(b"\0" * 4096)
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC
            if i == 30:
                os.truncate(disk / "filler", os.path.getsize(disk / "filler") - 3 * 4096)

        _, report, snap = _live(bundle, state, images[:50], places=10, stop_with_snapshot=True, between=fill)
        print(f"tmpfs: {report.line()}")
        assert report.frames_processed == 50 and snap.failures >= 1
        assert 30 <= report.frames_kept < 50 and report.frames_not_written > 0 and report.error == "disk full"
        assert _restart(bundle, state, images, reference) == (report.frames_kept, report.places_kept)
        (disk / "filler").unlink()  # space returns: the restarted node's state is whole again
        _, report, _ = _live(bundle, state, images[report.frames_kept:55], stop_with_snapshot=True)
        assert report.frames_kept == 55 and report.frames_not_written == 0


# -- hostile journals ----------------------------------------------------------------------------

def _journaled(bundle, images, path, n=12):
    """A state directory whose map is all journal (no snapshot): n frames in journal-000000000000."""
    _live(bundle, path, images[:n], places=1000)
    return path / "journal-000000000000"


def _load(bundle, path, config=CONFIG):
    det = load_detector(bundle, config)
    with MapStateDir(path, bundle_id(det.manifest)) as d:
        return det, replay_journal(det, d)


def _load_map(bundle, path):
    """The snapshot, then the journal (what a starting node loads)."""
    det = load_detector(bundle, CONFIG)
    with MapStateDir(path, bundle_id(det.manifest)) as d:
        return det, state_dir.load_map(det, d)[1]


def _refused(bundle, path, config=CONFIG) -> str:
    with pytest.raises(StateError) as info:
        _load(bundle, path, config)
    msg = str(info.value)
    assert "\n" not in msg and len(msg) < 300
    return msg


def _record_offsets(seg) -> list[int]:
    data, at, out = seg.read_bytes(), 0, []
    while at < len(data):
        out.append(at)
        at += 8 + struct.unpack_from("<I", data, at)[0]
    return out


def test_a_journal_cut_off_mid_record_loads_up_to_its_last_whole_record(bundle, images, tmp_path):
    seg = _journaled(bundle, images, tmp_path / "s")
    offsets = _record_offsets(seg)  # header + 12 frames
    with open(seg, "r+b") as fh:
        fh.truncate(offsets[9] + 20)
    det, replay = _load(bundle, tmp_path / "s")
    assert det.next_sequence == 8 and replay.frames == 8 and "cut off" in replay.cut


def test_a_damaged_record_stops_the_replay_before_it(bundle, images, tmp_path):
    seg = _journaled(bundle, images, tmp_path / "s")
    offsets = _record_offsets(seg)
    data = bytearray(seg.read_bytes())
    data[offsets[5] + 40] ^= 0xFF
    seg.write_bytes(bytes(data))
    det, replay = _load(bundle, tmp_path / "s")
    assert det.next_sequence == 4 and "checksum" in replay.cut


def test_an_oversized_length_is_a_cut_not_an_allocation(bundle, images, tmp_path):
    seg = _journaled(bundle, images, tmp_path / "s")
    offsets = _record_offsets(seg)
    data = bytearray(seg.read_bytes())
    struct.pack_into("<I", data, offsets[3], 0xFFFFFFF0)
    seg.write_bytes(bytes(data))
    det, replay = _load(bundle, tmp_path / "s")
    assert det.next_sequence == 2 and "cut off" in replay.cut


def _forge(seg, index, edit) -> None:
    """Rewrite record `index`'s payload with edit(bytearray) and a valid checksum."""
    data = bytearray(seg.read_bytes())
    at = _record_offsets(seg)[index]
    payload = bytearray(data[at + 8: at + 8 + struct.unpack_from("<I", data, at)[0]])
    edit(payload)
    seg.write_bytes(bytes(data[:at]) + struct.pack("<II", len(payload), zlib.crc32(payload)) + bytes(payload)
                    + bytes(data[at + 8 + struct.unpack_from("<I", data, at)[0]:]))


def test_forged_records_are_refused_in_one_line(bundle, images, tmp_path):
    seg = _journaled(bundle, images, tmp_path / "a")
    _forge(seg, 3, lambda p: struct.pack_into("<q", p, 1, 7))  # record 3 claims frame 7
    assert "out of order" in _refused(bundle, tmp_path / "a")
    seg = _journaled(bundle, images, tmp_path / "b")
    _forge(seg, 2, lambda p: struct.pack_into("<i", p, 30, 10**6))  # a word id past the vocabulary
    assert "word ids" in _refused(bundle, tmp_path / "b")
    seg = _journaled(bundle, images, tmp_path / "c")
    _forge(seg, 2, lambda p: p.extend(b"\0" * 32))  # a keypoint more than the record says
    assert "does not hold" in _refused(bundle, tmp_path / "c")
    seg = _journaled(bundle, images, tmp_path / "d")
    _forge(seg, 0, lambda p: p.__setitem__(slice(0, 2), b"X{"))
    assert "header" in _refused(bundle, tmp_path / "d")


def test_a_journal_of_another_bundle_or_settings_is_refused(bundle, images, tmp_path):
    _journaled(bundle, images, tmp_path / "s")
    assert "other detector settings (exclude)" in _refused(bundle, tmp_path / "s", DetectorConfig(exclude=4, max_places=30))
    # Another track memory (a journal written before its default changed) is named as the difference.
    older = dataclasses.replace(CONFIG, candidates=CandidateConfig(track_memory=3))
    assert "(candidates.track_memory)" in _refused(bundle, tmp_path / "s", older)
    other = make_synthetic_bundle(tmp_path / "other", seed=1)
    det = load_detector(other, CONFIG)
    with MapStateDir(tmp_path / "s", bundle_id(det.manifest)) as d, pytest.raises(StateError, match="another model bundle"):
        replay_journal(det, d)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("what", ["fifo", "directory", "symlink"])
def test_a_special_file_as_a_segment_is_refused_without_hanging(bundle, images, tmp_path, what):
    seg = _journaled(bundle, images, tmp_path / "s")
    outside = tmp_path / "outside"
    outside.write_bytes(seg.read_bytes())
    seg.unlink()
    {"fifo": lambda: os.mkfifo(seg), "directory": seg.mkdir, "symlink": lambda: seg.symlink_to(outside)}[what]()
    msg = _refused(bundle, tmp_path / "s")
    assert "journal-000000000000" in msg


def test_a_zero_length_segment_is_a_cut_like_a_damaged_header(bundle, images, reference, tmp_path):
    """The attack: an empty segment (a crash of the filesystem, a truncation) refused the whole state,
    so the node exited 3 and was not restarted; a damaged header only warned. Now both are a cut:
    the snapshot and every frame before the segment load, nothing else is removed."""
    _live(bundle, tmp_path / "s", images[:25])  # a snapshot at frame 18, journal-000000000018 holds 18..24
    seg = tmp_path / "s" / "journal-000000000018"
    seg.write_bytes(b"")
    det, replay = _load_map(bundle, tmp_path / "s")
    assert det.next_sequence == 18 and "journal-000000000018" in replay.cut and "empty" in replay.cut
    assert seg.exists() and replay.removed == 0
    assert [_public(det.process(img, i)) for i, img in enumerate(images[18:22], 18)] == reference[18:22]

    _live(bundle, tmp_path / "t", images[:25])  # an empty segment the snapshot already covers
    (tmp_path / "t" / "journal-000000000003").write_bytes(b"")
    det, replay = _load_map(bundle, tmp_path / "t")
    assert det.next_sequence == 25 and replay.cut is None


def test_segments_after_a_gap_are_not_replayed_and_are_removed(bundle, images, reference, tmp_path):
    seg = _journaled(bundle, images, tmp_path / "s")
    orphan = tmp_path / "s" / "journal-000000000020"
    orphan.write_bytes(seg.read_bytes())  # frames written after a gap (their base state is not on disk)
    det, replay = _load(bundle, tmp_path / "s")
    assert det.next_sequence == 12 and replay.removed == 1 and not orphan.exists()
    got = [_public(det.process(img, i)) for i, img in enumerate(images[12:20], 12)]
    assert got == reference[12:20]


def test_journal_records_round_trip_the_detector_input(bundle, images):
    det = load_detector(bundle, CONFIG)
    taken = []

    class Taken(MapListener):
        def frame_taken(self, sequence, words, stamp_ns, features):
            taken.append((sequence, words, stamp_ns, features))

    det.add_listener(Taken())
    det.process(images[0], 123)
    (_, words, _, feats), = taken
    seq, w, s, f = map_journal.decode_frame(map_journal.encode_frame(det, *taken[0]), det, "r")
    assert (seq, s) == (0, 123) and np.array_equal(w, words) and f.image_shape == feats.image_shape
    assert all(np.array_equal(a, b) for a, b in ((f.keypoints, feats.keypoints), (f.sizes, feats.sizes),
                                                   (f.descriptors, feats.descriptors), (f.upright, feats.upright)))
    # A frame of format 1 (no upright descriptors; features flag 1) still reads, without them.
    old = map_journal.encode_frame(det, 0, words, 123, dataclasses.replace(feats, upright=None))
    assert old[21] == 1  # after b"F", sequence, stamp and the keypoint count
    _, _, _, f = map_journal.decode_frame(old, det, "r")
    assert f.upright is None and np.array_equal(f.descriptors, feats.descriptors)
    with pytest.raises(StateError, match="does not hold"):  # a flag of 2 without the upright rows
        map_journal.decode_frame(old[:21] + b"\x02" + old[22:], det, "r")


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_run_with_its_state_on_a_tmpfs_that_fills_says_what_it_kept(bundle, images, tmp_path):
    """`aefabmap run --state` as a process on a tmpfs too small for the run's map: the node goes on,
    says at stop how many places it kept and how many frames it could not write (log line and
    summary), exits 0, and a restart loads exactly what it said it kept."""
    import json

    from aefabmap_runtime.tools.synthetic_route import write_sequence
    from tests.runtime.adapters.stream_fakes import mounted_tmpfs, run_node_process

    write_sequence(tmp_path / "seq", images, np.zeros((N, N), bool))
    disk = tmp_path / "disk"
    disk.mkdir()
    with mounted_tmpfs(disk, size="160k"):
        node = run_node_process(["--model", str(bundle), "--mcap", str(tmp_path / "a.mcap"), "--queue", "256",
                                 "--state", str(disk / "state"), "--snapshot-every", "10p", "--exclude", "3"],
                                tmp_path / "seq", N - 1)
        assert node.returncode == 0, node.stderr
        assert "Traceback" not in node.stderr
        state = json.loads(node.stdout.strip().splitlines()[-1])["state"]
        line = [x for x in node.stderr.splitlines() if "state: " in x and "kept on disk" in x]
        print(line[-1])
        assert state["frames_processed"] == N and 0 < state["frames_kept"] < N and state["error"] == "disk full"
        assert f"{state['places_kept']} places kept on disk" in line[-1] and "not written (disk full)" in line[-1]
        det = load_detector(bundle, DetectorConfig(exclude=3))
        with MapStateDir(disk / "state", bundle_id(det.manifest)) as d:
            assert load_into(det, d)
        assert (det.next_sequence, det.n_places) == (state["frames_kept"], state["places_kept"])


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_node_whose_state_has_an_empty_segment_starts_and_continues_the_snapshot(bundle, images, tmp_path):
    """`aefabmap run --state` as a process over a state whose current segment is empty: it starts
    (it used to exit 3), warns once naming the segment, and goes on from the snapshot's frame."""
    from aefabmap_runtime.tools.synthetic_route import write_sequence
    from tests.runtime.adapters.stream_fakes import run_node_process

    _live(bundle, tmp_path / "s", images[:25])  # a snapshot at frame 18, then journal-000000000018
    (tmp_path / "s" / "journal-000000000018").write_bytes(b"")
    write_sequence(tmp_path / "seq", images[18:24], np.zeros((6, 6), bool))
    node = run_node_process(["--model", str(bundle), "--mcap", str(tmp_path / "a.mcap"), "--queue", "64",
                             "--state", str(tmp_path / "s"), "--exclude", "3", "--max-places", "30"],
                            tmp_path / "seq", 23)
    assert node.returncode == 0, node.stderr
    assert "Traceback" not in node.stderr
    assert [d["sequence"] for d in node.results] == list(range(18, 24))
    warned = [x for x in node.stderr.splitlines() if x.startswith("WARNING") and "journal-000000000018" in x]
    assert len(warned) == 1 and "empty" in warned[0]
