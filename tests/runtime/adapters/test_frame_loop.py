"""The one per-frame step (runtime/aefabmap_runtime/adapters/frame_loop.py): decode -> detect, bad frames counted."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.adapters.frame_loop import FrameLoop
from aefabmap_runtime.adapters.frames import BAD_FRAME_REASONS, FrameError, encode_frame
from aefabmap_runtime.core.records.json_schema import validate
from aefabmap_runtime.core.records.messages import StatsMessage

from .stream_fakes import FakeDetector, sample_images


def test_good_and_bad_frames_are_counted_per_reason(tmp_path):
    loop = FrameLoop(FakeDetector())
    images = sample_images(3, size=(64, 48))
    good, enc = encode_frame(images[0], "jpeg")
    out = loop.step(good, enc, 5)
    assert out.result is not None and out.result.stamp_ns == 5 and out.gray.shape == (48, 64)
    assert out.bad_reason is None and out.decode_ms > 0
    assert loop.step(good[:40], "image/jpeg", 6).bad_reason == "corrupt"
    assert loop.step(b"", "image/png", 7).bad_reason == "empty"
    rejected = loop.step(b"\x00" * 16, "mono8;4x4", 8)  # decodes; the detector refuses 4x4
    assert rejected.result is None and rejected.bad_reason == "rejected" and rejected.gray.shape == (4, 4)
    assert loop.step_image(images[0], 9).result.loop  # the same image again: a loop for the fake
    (tmp_path / "junk.png").write_bytes(b"not a png")
    assert loop.step_file(tmp_path / "junk.png", 10).result is None
    assert (loop.frames_in, loop.processed, loop.loops) == (6, 2, 1)
    assert set(loop.bad.counts) >= set(BAD_FRAME_REASONS)
    assert {k: v for k, v in loop.bad.counts.items() if v} == {"corrupt": 2, "empty": 1, "rejected": 1}
    assert loop.bad.total == 4 and loop.bad.last and len(loop.bad.last) <= 200
    msg = loop.stats_message(uptime_s=1.23456, dropped=2)
    assert (msg.frames_received, msg.frames_processed, msg.bad_total, msg.loops, msg.dropped) == (6, 2, 4, 1, 2)
    assert msg.uptime_s == 1.235 and msg.last_bad == loop.bad.last
    assert validate(msg.to_dict(), StatsMessage.json_schema()) is None


def test_strict_loop_raises_instead_of_skipping(tmp_path):
    loop = FrameLoop(FakeDetector(), strict=True)
    with pytest.raises(FrameError):
        loop.step(b"", "image/jpeg", 0)
    with pytest.raises(InputError):
        loop.step_file(tmp_path / "missing.png", 0)
    with pytest.raises(InputError):
        loop.step_image(np.zeros((4, 4), np.uint8), 0)
    assert loop.bad.total == 0 and loop.processed == 0


def test_a_model_failing_on_one_frame_is_counted_not_fatal():
    """A quantiser that passes the load-time probe but fails on some frame (BundleError from
    the model) costs that frame, counted as rejected; the running node goes on."""
    from aefabmap_runtime.errors import BundleError

    class FailsOnce(FakeDetector):
        def process(self, gray, stamp_ns):
            if stamp_ns == 2:
                raise BundleError("model returned word ids outside [0, 16)")
            return super().process(gray, stamp_ns)

    loop = FrameLoop(FailsOnce())
    image = sample_images(1, size=(64, 48))[0]
    outs = [loop.step_image(image, stamp) for stamp in (1, 2, 3)]
    assert [o.result is not None for o in outs] == [True, False, True]
    assert outs[1].bad_reason == "rejected" and "outside" in loop.bad.last
    with pytest.raises(BundleError):
        FrameLoop(FailsOnce(), strict=True).step_image(image, 2)
