"""One Markdown table from several `aefabmap eval --json` files (scripts/eval_matrix.sh).

    python -m aefabmap_runtime.tools.results_table RESULT.json [...]

Columns: the verified output first (recall at 100 % precision, tolerant and strict, and its
false positives), then the raw FAB-MAP score the run used (`fabmap_score`: llr in the matrix)
with its own recall, AUC and false positives (every frame predicts its best place).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from aefabmap_runtime.errors import InputError

COLUMNS = (
    "bundle", "sequence", "verified R@100P tol", "verified R@100P strict", "verified FP",
    "raw R@100P tol", "raw AUC tol", "raw FP", "ms/frame",
)


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def row(doc: dict, name: str) -> list[str]:
    """Table cells of one eval JSON document (name: the bundle's label)."""
    v = doc.get("verified", {})
    images = Path(doc.get("images", "?"))
    sequence = images.parent.name if images.name == "images" else images.name
    raw = doc.get("fabmap_score") or doc.get("scorer", "raw")
    ms = doc.get("ms_per_frame", {}).get("total", {}).get("median")
    return [
        name, sequence,
        _pct(v.get("recall_at_100p_tolerant")), _pct(v.get("recall_at_100p")), str(v.get("false_positives", "-")),
        f"{_pct(doc.get('recall_at_100p_tolerant'))} ({raw})", _pct(doc.get("auc_tolerant")),
        str(doc.get("false_positives", "-")), "-" if ms is None else f"{ms:.1f}",
    ]


def table(paths: list[Path]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for p in paths:
        try:
            doc = json.loads(Path(p).read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read eval result {p}: {exc}") from exc
        lines.append("| " + " | ".join(row(doc, Path(doc.get("model", p)).name)) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    try:
        print(table([Path(a) for a in args]))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 4
    return 0


if __name__ == "__main__":
    sys.exit(main())
