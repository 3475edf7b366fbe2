"""scripts/revisit_sequences.py: the revisit order, its ground truth and the folders it writes."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import revisit_sequences as rs  # noqa: E402


@pytest.mark.parametrize("n, step", [(13, 4), (12, 6), (7, 2), (3, 6)])
def test_every_second_pass_frame_revisits_exactly_its_first_pass_neighbours(n, step):
    order, gt = rs.revisit_order(n, step)
    assert sorted(order) == sorted(set(order)) and len(order) == len(range(0, n, step)) + len(range(step // 2, n, step))
    n_first = len(range(0, n, step))
    assert not np.triu(gt).any()  # a frame only revisits earlier frames
    assert not gt[:n_first].any()  # the first pass revisits nothing
    for i in range(n_first, len(order)):
        revisited = {order[j] for j in np.flatnonzero(gt[i])}
        expected = {f for f in (order[i] - step // 2, order[i] + step // 2) if f in order[:n_first]}
        assert revisited == expected and revisited


@pytest.mark.parametrize("n, step", [(13, 4), (12, 6), (7, 2)])
def test_driven_back_the_second_pass_runs_backwards_after_the_gap(n, step):
    forward, gt_forward = rs.revisit_order(n, step)
    order, gt = rs.revisit_order(n, step, reverse=True, gap=5)
    n_first = len(range(0, n, step))
    assert order[:n_first] == forward[:n_first] and order[n_first:n_first + 5] == [None] * 5
    assert order[n_first + 5:] == forward[n_first:][::-1]
    assert not gt[: n_first + 5].any() and not np.triu(gt).any()
    for i in range(n_first + 5, len(order)):  # each revisits what it revisits forwards, nothing else
        assert np.array_equal(gt[i, :n_first], gt_forward[forward.index(order[i]), :n_first])
        assert not gt[i, n_first:].any()
        assert i - np.flatnonzero(gt[i]).max() > 5  # beyond the gap


def test_reverse_writes_the_next_drives_frames_between_and_darkens_alike(tmp_path):
    camvid = tmp_path / "data" / "train" / "camvid"
    camvid.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for drive, n in (("0001TP", 33), ("Seq05VD", 40)):
        for f in range(n):
            cv2.imwrite(str(camvid / f"{drive}_{f:05d}.png"), rng.integers(0, 256, (8, 8), dtype=np.uint8))
    for reverse in (False, True):
        rs.main(["--data", str(tmp_path / "data"), "--out", str(tmp_path / str(reverse)), "--step", "2", "--night",
                 *(["--reverse"] if reverse else [])])
    forward = sorted((tmp_path / "False" / "0001TP" / "images").iterdir())
    back = sorted((tmp_path / "True" / "0001TP" / "images").iterdir())
    order, gt = rs.revisit_order(33, 2, reverse=True, gap=rs.GAP)
    assert len(back) == len(order) and np.array_equal(np.load(tmp_path / "True" / "0001TP" / "gt.npy"), gt)
    n_first = len(range(0, 33, 2))
    seq05 = sorted(camvid.glob("Seq05VD_*"))[::2][: rs.GAP]  # the next drive's first pass
    assert [cv2.imread(str(p), 0).tolist() for p in back[n_first:n_first + rs.GAP]] == \
        [cv2.imread(str(p), 0).tolist() for p in seq05]
    # The same night frame either way: the second pass backwards is the forward one reversed.
    assert [cv2.imread(str(p), 0).tolist() for p in back[n_first + rs.GAP:]] == \
        [cv2.imread(str(p), 0).tolist() for p in forward[n_first:][::-1]]
    # Seq05VD's frames between come from 0001TP, the drive after it in name order (wrapping round).
    between = sorted((tmp_path / "True" / "Seq05VD" / "images").iterdir())[20: 20 + rs.GAP]
    assert [cv2.imread(str(p), 0).tolist() for p in between] == \
        [cv2.imread(str(p), 0).tolist() for p in sorted(camvid.glob("0001TP_*"))[::2][: rs.GAP]]


def test_reverse_without_frames_enough_between_says_so_in_one_line(tmp_path):
    camvid = tmp_path / "data" / "train" / "camvid"
    camvid.mkdir(parents=True)
    for f in range(4):
        cv2.imwrite(str(camvid / f"0006R0_{f:05d}.png"), np.zeros((8, 8), np.uint8))
    with pytest.raises(SystemExit, match=f"needs {rs.GAP} first-pass frames of other CamVid drives"):
        rs.main(["--data", str(tmp_path / "data"), "--out", str(tmp_path / "out"), "--reverse"])


@pytest.mark.parametrize("step", [0, 1, 3, -2])
def test_an_odd_or_too_small_step_is_refused(step):
    with pytest.raises(ValueError, match="step"):
        rs.revisit_order(10, step)


def test_main_writes_one_sequence_per_drive_in_revisit_order(tmp_path):
    camvid = tmp_path / "data" / "train" / "camvid"
    camvid.mkdir(parents=True)
    for drive, n in (("0001TP", 9), ("Seq05VD", 5)):
        for f in range(n):
            cv2.imwrite(str(camvid / f"{drive}_{f:05d}.png"), np.full((8, 8), 10 * f, np.uint8))
    (camvid / "notes.txt").write_text("not an image")
    rs.main(["--data", str(tmp_path / "data"), "--out", str(tmp_path / "out"), "--step", "4"])
    for drive, n in (("0001TP", 9), ("Seq05VD", 5)):
        seq = tmp_path / "out" / drive
        order, gt = rs.revisit_order(n, 4)
        files = sorted((seq / "images").iterdir())
        assert [cv2.imread(str(p), 0)[0, 0] for p in files] == [10 * f for f in order]
        assert np.array_equal(np.load(seq / "gt.npy"), gt)


def test_night_darkens_the_second_pass_only_and_repeats_exactly(tmp_path):
    camvid = tmp_path / "data" / "train" / "camvid"
    camvid.mkdir(parents=True)
    for f in range(6):
        cv2.imwrite(str(camvid / f"0006R0_{f:05d}.png"), np.full((16, 16), 200, np.uint8))
    for run in ("a", "b"):
        rs.main(["--data", str(tmp_path / "data"), "--out", str(tmp_path / run), "--step", "2", "--night"])
    files = sorted((tmp_path / "a" / "0006R0" / "images").iterdir())
    first = len(range(0, 6, 2))
    day = [cv2.imread(str(p), 0) for p in files[:first]]
    night = [cv2.imread(str(p), 0) for p in files[first:]]
    assert all((d == 200).all() for d in day)
    expected = 255 * rs.NIGHT["gain"] * (200 / 255) ** rs.NIGHT["gamma"]  # before noise
    assert all(abs(float(n.mean()) - expected) < 3 and n.std() > 0 for n in night)
    again = sorted((tmp_path / "b" / "0006R0" / "images").iterdir())
    assert all(np.array_equal(cv2.imread(str(p), 0), cv2.imread(str(q), 0)) for p, q in zip(files, again))


def test_main_without_camvid_says_so_in_one_line(tmp_path):
    with pytest.raises(SystemExit, match="no CamVid training drives"):
        rs.main(["--data", str(tmp_path), "--out", str(tmp_path / "out")])
