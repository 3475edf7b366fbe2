"""The README's main job: `aefabmap demo` end to end (two processes over loopback Zenoh)."""

from __future__ import annotations

import pytest

from aefabmap.cli.main import main
from aefabmap_runtime.adapters.mcap_log import McapLogReader


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_demo_runs_end_to_end(tmp_path, capsys):
    code = main(["demo", "--out", str(tmp_path), "--frames", "80", "--rate", "5", "--timeout", "60"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "replay --check: check OK" in out
    reader = McapLogReader(tmp_path / "demo.mcap")
    images = sum(1 for _ in reader.frames())
    # Every processed frame has its image and result logged; a loaded machine may drop a few
    # frames (newest-wins queue), which the runtime counts rather than queueing latency.
    assert images == len(reader.results) >= 60
    assert reader.manifest is not None and reader.manifest["format"] == "aefabmap-bundle"
    # The second lap revisits the first: the shipped bundle must find at least one loop.
    assert any(r.loop for r in reader.results)
    assert "LOOP" in out
