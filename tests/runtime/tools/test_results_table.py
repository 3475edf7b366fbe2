"""The matrix summary reads eval JSON files into one Markdown table."""

from __future__ import annotations

import json

from aefabmap_runtime.tools.results_table import main, table


def test_one_row_per_result_verified_first(tmp_path, capsys):
    doc = {"model": "/b/orb_kmeans_2000", "images": "/d/validation/corridor/images", "fabmap_score": "llr",
           "recall_at_100p_tolerant": 0.257, "auc_tolerant": 0.703, "false_positives": 558,
           "ms_per_frame": {"total": {"median": 12.34}},
           "verified": {"recall_at_100p_tolerant": 0.925, "recall_at_100p": 0.0, "false_positives": 0}}
    p = tmp_path / "a.json"
    p.write_text(json.dumps(doc))
    lines = table([p]).splitlines()
    assert lines[0].startswith("| bundle | sequence | verified R@100P tol")
    assert lines[2] == "| orb_kmeans_2000 | corridor | 92.5 | 0.0 | 0 | 25.7 (llr) | 70.3 | 558 | 12.3 |"
    assert main([str(p)]) == 0 and "orb_kmeans_2000" in capsys.readouterr().out
    assert main([str(tmp_path / "missing.json")]) == 4
    assert main([]) == 2
