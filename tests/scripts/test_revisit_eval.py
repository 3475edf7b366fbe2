"""scripts/revisit_eval.py: every drive evaluated by day and at night, the splits summed."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from aefabmap_runtime.tools.frame_evidence import MISS_REASONS

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import revisit_eval as re_  # noqa: E402
import revisit_sequences as rs  # noqa: E402

DRIVES = {"0001TP": 9, "Seq05VD": 7}


def _camvid(root: Path, drives: dict[str, int] = DRIVES) -> Path:
    """Textured frames (ORB finds corners on them) in CamVid's drive_frame naming, `drives`:
    {drive: frames}."""
    camvid = root / "train" / "camvid"
    camvid.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for drive, n in drives.items():
        for f in range(n):
            img = cv2.resize(rng.integers(0, 256, (24, 32), dtype=np.uint8), (160, 120), interpolation=cv2.INTER_NEAREST)
            cv2.imwrite(str(camvid / f"{drive}_{f:05d}.png"), img)
    return root


def test_the_sums_add_up_every_drive_by_day_and_at_night(tmp_path, synthetic_bundle, capsys):
    data = _camvid(tmp_path / "data")
    out = tmp_path / "r.json"
    assert re_.main(["--model", str(synthetic_bundle), "--data", str(data), "--sequences", str(tmp_path / "seq"),
                     "--step", "2", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    printed = capsys.readouterr().out.splitlines()
    assert [line.split("|")[1].strip() for line in printed[2:]] == ["day", "night"]
    for light in re_.LIGHTS:
        drives = doc["drives"][light]
        assert set(drives) == set(DRIVES)
        for drive, n in DRIVES.items():  # every second-pass frame is a revisit
            assert drives[drive]["revisits"] == int(rs.revisit_order(n, 2)[1].any(axis=1).sum())
        total = doc["sums"][light]
        assert total["revisits"] == sum(d["revisits"] for d in drives.values())
        assert total["verified"] == sum(d["verified"] for d in drives.values())
        missed = total["revisits"] - total["verified"] - total["wrong_place"]
        assert sum(total["misses"].values()) == missed
    assert doc["eval_options"] == list(re_.EVAL_OPTIONS)


def test_sequences_are_written_once_and_extra_eval_options_pass_through(tmp_path, synthetic_bundle):
    data = _camvid(tmp_path / "data")
    seq = tmp_path / "seq"
    re_.main(["--model", str(synthetic_bundle), "--data", str(data), "--sequences", str(seq), "--step", "2"])
    gt = seq / "night-step2" / "Seq05VD" / "gt.npy"
    before = gt.stat().st_mtime_ns
    out = tmp_path / "r.json"
    re_.main(["--model", str(synthetic_bundle), "--data", str(data), "--sequences", str(seq), "--step", "2",
              "--json", str(out), "--", "--verify-bruteforce", "1"])
    assert gt.stat().st_mtime_ns == before
    assert json.loads(out.read_text())["eval_options"][-2:] == ["--verify-bruteforce", "1"]


def test_a_failing_eval_or_missing_drives_stop_with_a_message(tmp_path, synthetic_bundle):
    data = _camvid(tmp_path / "data")
    with pytest.raises(SystemExit, match="eval failed"):
        re_.main(["--model", str(tmp_path / "no-bundle"), "--data", str(data), "--sequences", str(tmp_path / "s"),
                  "--step", "2"])
    with pytest.raises(SystemExit, match="no CamVid"):
        re_.main(["--model", str(synthetic_bundle), "--data", str(tmp_path / "empty"), "--sequences",
                  str(tmp_path / "s2")])


def test_summed_adds_each_key_and_reason():
    one = {"revisits": 3, "verified": 2, "wrong_place": 0, "true_place_checked": 3,
           "misses": {"no_model": 1, "nfa_below_0": 0}}
    two = {"revisits": 4, "verified": 1, "wrong_place": 1, "true_place_checked": 2,
           "misses": {"no_model": 0, "nfa_below_0": 2}}
    total = re_.summed({"a": one, "b": two})
    assert (total["revisits"], total["verified"], total["wrong_place"], total["true_place_checked"]) == (7, 3, 1, 5)
    assert total["misses"]["no_model"] == 1 and total["misses"]["nfa_below_0"] == 2
    assert set(total["misses"]) >= set(MISS_REASONS)


def test_reverse_evaluates_the_sequences_driven_back(tmp_path, synthetic_bundle):
    drives = {"0001TP": 33, "0006R0": 35}  # first passes of 17 and 18 frames: room for the frames between
    data = _camvid(tmp_path / "data", drives)
    out = tmp_path / "r.json"
    assert re_.main(["--model", str(synthetic_bundle), "--data", str(data), "--sequences",
                     str(tmp_path / "seq"), "--step", "2", "--reverse", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["reverse"] is True
    for light in re_.LIGHTS:
        for drive, n in drives.items():
            folder = tmp_path / "seq" / f"{light}-step2-reverse" / drive
            assert np.array_equal(np.load(folder / "gt.npy"), rs.revisit_order(n, 2, reverse=True, gap=rs.GAP)[1])
            assert doc["drives"][light][drive]["revisits"] == len(range(1, n, 2))
