"""runtime/aefabmap_runtime/tools/node_process.py: a process's resident memory from /proc."""

from __future__ import annotations

import os

import pytest

from aefabmap_runtime.tools.node_process import process_rss_mb, rss_mb_of_status


def test_rss_of_this_process_is_positive():
    if not os.path.exists("/proc/self/status"):
        pytest.skip("no /proc")
    assert process_rss_mb("self") > 1
    assert process_rss_mb(2**22 + 12345) is None  # no such process


@pytest.mark.parametrize(
    ("text", "mb"),
    [
        ("Name:\tpython\nVmRSS:\t  2048 kB\n", 2.0),
        # A process in the middle of exec (or exiting) has no memory yet (any more): not a sample.
        ("Name:\tpython\nVmRSS:\t     0 kB\n", None),
        ("Name:\tkthreadd\n", None),
        ("VmRSS:\n", None),
        ("VmRSS:\tlots kB\n", None),
    ],
)
def test_rss_of_a_status_text(text, mb):
    assert rss_mb_of_status(text) == mb
