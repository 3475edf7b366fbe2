"""scripts/aarch64_instructions.py: executed instructions per keypoint on emulated aarch64 cores."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import aarch64_instructions as ai  # noqa: E402

TOOLS = all(shutil.which(t) for t in ("gcc", "aarch64-linux-gnu-gcc", "qemu-aarch64"))


@pytest.mark.skipif(not TOOLS, reason="needs aarch64-linux-gnu-gcc and qemu-aarch64 (gcc-aarch64-linux-gnu, qemu-user)")
def test_each_form_is_counted_and_the_dot_products_run_only_where_the_core_has_them(tmp_path):
    result = ai.count(tmp_path)
    a76, a53 = result["cpus"]["cortex-a76"], result["cpus"]["cortex-a53"]
    for cpu in (a76, a53):
        assert cpu["learned_forms_same_bytes"] and cpu["orb_per_orientation"] > 0
    learned = a76["learned_per_orientation"]
    assert learned["neon-dotprod"] < learned["neon"] < learned["plain"]
    # A Cortex-A53 has no dot products: that form gives way to the next, instruction for instruction.
    assert a53["learned_per_orientation"]["neon-dotprod"] == a53["learned_per_orientation"]["neon"]


def test_a_missing_tool_is_one_line_and_a_failure(monkeypatch, capsys):
    monkeypatch.setattr(ai.shutil, "which", lambda tool: None)
    assert ai.main([]) == 1
    assert capsys.readouterr().err.strip().count("\n") == 0


def test_board_frames_need_a_model_a_sequence_and_two_counts(tmp_path, capsys):
    assert ai.main(["--board", str(tmp_path)]) == 2
    assert ai.main(["--board", str(tmp_path), "--model", "m", "--images", "i", "--gt", "g", "--frames", "5", "5"]) == 2
    assert "--board needs" in capsys.readouterr().err


def test_frame_subsets_link_the_first_frames_and_slice_the_truth(tmp_path):
    import numpy as np

    images = tmp_path / "seq"
    images.mkdir()
    for i in range(6):
        (images / f"{i:03d}.png").write_bytes(b"x")
    np.save(tmp_path / "gt.npy", np.eye(6, dtype=bool))
    work = tmp_path / "work"
    work.mkdir()
    (a, ga), (b, gb) = ai.frame_subsets(images, tmp_path / "gt.npy", (2, 5), work)
    assert sorted(p.name for p in a.iterdir()) == ["000.png", "001.png"] and len(list(b.iterdir())) == 5
    assert np.load(ga).shape == (2, 2) and np.load(gb).shape == (5, 5)
    with pytest.raises(RuntimeError, match="fewer than 9"):
        ai.frame_subsets(images, tmp_path / "gt.npy", (9, 10), tmp_path / "other")


def test_instructions_are_attributed_to_the_file_mapped_at_their_address():
    maps = "\n".join([
        "400000-916000 r-xp 00000000 fe:00 1 /board/sysroot/usr/bin/python3.11",
        "930000-a5f000 rw-p 00520000 fe:00 1 /board/sysroot/usr/bin/python3.11",
        "5500000000-5500100000 r-xp 00000000 fe:00 2 /board/site/onnxruntime/capi/libonnxruntime.so.1.20.1",
        "5500200000-5500300000 r-xp 00000000 fe:00 3 /repo/runtime/aefabmap_runtime/core/kernels/_kernels.so",
        "5500400000-5500500000 r-xp 00000000 fe:00 4 /board/site/numpy/_core/_multiarray_umath.so",
        "5500600000-5500700000 r-xp 00000000 00:00 0",
        "5500800000-5500900000 r-xp 00000000 fe:00 5 /board/sysroot/lib/aarch64-linux-gnu/libc.so.6",
    ])
    blocks = "\n".join(["400010 7", "5500000400 100", "5500000800 1", "5500200000 20", "5500400000 3",
                        "5500600000 4", "5500800010 5", "a00000 9", "6000000000 2"])
    split = ai.by_library(blocks, maps)
    assert split["Python"] == 7 and split["onnxruntime"] == 101 and split["aefabmap kernels"] == 20
    assert split["numpy"] == 3 and split["C library"] == 5 and split["OpenCV"] == 0
    # Anonymous code, a block in a mapping that is not executable, and one outside every mapping.
    assert split["other"] == 4 + 9 + 2 and sum(split.values()) == 151


@pytest.mark.skipif(not TOOLS, reason="needs aarch64-linux-gnu-gcc and qemu-aarch64 (gcc-aarch64-linux-gnu, qemu-user)")
def test_the_plugins_blocks_add_up_to_its_total(tmp_path):
    plugin, program = ai.build(tmp_path)
    blocks = tmp_path / "blocks.txt"
    total, _ = ai.executed(f"{plugin},blocks={blocks}", program, "cortex-a53", ["orb", "1"])
    assert total > 0 and sum(int(line.split()[1]) for line in blocks.read_text().splitlines()) == total
