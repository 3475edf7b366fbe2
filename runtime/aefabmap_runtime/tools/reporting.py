"""Human-facing outputs of an evaluation: a text table, PR-curve plot, score-matrix image."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError

# (column, metric key, percent?): tolerant metrics first (a match within the tolerance counts),
# then strict (the exact frame), then false positives (predicted loops that are wrong).
TABLE_KEYS = (
    ("R@100P tolerant", "recall_at_100p_tolerant", True),
    ("AUC tolerant", "auc_tolerant", True),
    ("maxF1 tolerant", "max_f1_tolerant", True),
    ("R@100P strict", "recall_at_100p", True),
    ("AUC strict", "auc", True),
    ("maxF1 strict", "max_f1", True),
    ("FP tolerant", "false_positives", False),
    ("FP strict", "false_positives_strict", False),
)


def format_table(rows: dict[str, dict]) -> str:
    """Markdown table of the headline metrics (percent; false positives as counts) and median
    total ms per frame, one row per method in the order given (the product's output first)."""
    head = "| method | " + " | ".join(k for k, _, _ in TABLE_KEYS) + " | ms/frame |"
    lines = [head, "|" + "---|" * (len(TABLE_KEYS) + 2)]
    for name, m in rows.items():
        vals = " | ".join(_cell(m.get(key), pct) for _, key, pct in TABLE_KEYS)
        ms = m.get("ms_per_frame", {}).get("total", {}).get("median", float("nan"))
        lines.append(f"| {name} | {vals} | {ms:.1f} |")
    return "\n".join(lines)


def _cell(value, percent: bool) -> str:
    if value is None:
        return "-"
    return f"{100 * value:.1f}" if percent else str(int(value))


def require_plotting():
    """matplotlib.pyplot with a headless backend; ConfigError when it is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise ConfigError("--plot needs matplotlib (pip install 'aefabmap[plot]')") from exc
    return plt


def save_pr_plot(rows: dict[str, dict], path: Path) -> None:
    """PR curves (tolerant solid, strict dashed) of each method into a PNG."""
    plt = require_plotting()
    fig, ax = plt.subplots(figsize=(6, 5), dpi=110)
    for name, m in rows.items():
        for suffix, style in (("_tolerant", "-"), ("", "--")):
            c = m[f"_curve{suffix}"]
            label = f"{name} {'tolerant' if suffix else 'strict'} (AUC {m['auc' + suffix]:.2f})"
            ax.plot(np.r_[0, c.recall], np.r_[1, c.precision], style, label=label, drawstyle="steps-post")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title("Loop closure precision-recall")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def save_score_matrix(matrix: np.ndarray | None, path: Path) -> None:
    """Score matrix (query row i, place frame column j) as a colour PNG, via OpenCV only."""
    if matrix is None:
        raise InputError("no score matrix was kept for this run")
    m = np.asarray(matrix, np.float32)
    top = float(m.max()) if m.size else 0.0
    img = (255 * np.clip(m / top if top > 0 else m, 0, 1)).astype(np.uint8)
    colour = cv2.applyColorMap(img, cv2.COLORMAP_VIRIDIS)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), colour):
        raise InputError(f"could not write image {path}")
