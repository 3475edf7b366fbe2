#!/usr/bin/env python
"""Report on AE-VQ bundles next to their k-means baselines (figures of docs/results.md, AE section).

For every bundle: quantiser cost on one thread (ms per 500 real Lip6 descriptors, median of
wall and of process CPU time), int8-vs-fp32 word agreement on Lip6 descriptors (AE), the
held-out matching-pair word agreement (share of held-out training pairs -- homography warps and
consecutive CamVid frames -- whose two descriptors get the same word; the same pairs for every
bundle of a feature kind), the AE's training time and held-out loss curve, and the Lip6 /
corridor figures from `aefabmap eval --json` files named <bundle>_<lip6|corridor>.json.

    python scripts/ae_report.py --data DATA --results R1 [R2 ...] --out OUT.json --plot CURVES.png BUNDLE [...]

Lip6 descriptors are only timed and compared here, never trained on.
"""

from __future__ import annotations

import os

# One thread for every library: the figures are per-core costs (set before numpy loads BLAS).
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from aefabmap_runtime.adapters.bundle_reader import load_bundle  # noqa: E402
from aefabmap_runtime.adapters.frames import load_image  # noqa: E402
from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor  # noqa: E402
from aefabmap_trainer.ae_quantizer import PAIR_VAL_FRACTION  # noqa: E402
from aefabmap_trainer.train import cached_match_pairs, find_training_images  # noqa: E402

SEED = 0


def lip6_vectors(data: Path, features: FeatureConfig, n: int) -> np.ndarray:
    """The first n descriptor vectors of Lip6 Outdoor frames, in frame order."""
    fx = FeatureExtractor(features)
    out, total = [], 0
    for p in sorted((data / "lip6_outdoor").glob("*.jpg")) + sorted((data / "lip6_outdoor").glob("*.png")):
        v = features.spec.vectors(fx.extract(load_image(p)).descriptors)
        out.append(v)
        total += v.shape[0]
        if total >= n:
            break
    return np.concatenate(out)[:n]


def time_ms(fn, x: np.ndarray, repeats: int) -> dict:
    """Median wall and process-CPU milliseconds of fn(x)."""
    fn(x)  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn(x)
        wall.append((time.perf_counter() - t) * 1000)
        cpu.append((time.process_time() - c) * 1000)
    return {"wall_ms": round(float(np.median(wall)), 3), "cpu_ms": round(float(np.median(cpu)), 3)}


def eval_figures(results: list[Path], name: str, seq: str) -> dict | None:
    for r in results:
        p = r / f"{name}_{seq}.json"
        if p.is_file():
            d = json.loads(p.read_text())
            v = d.get("verified") or {}
            return {"raw_r100_tol": d.get("recall_at_100p_tolerant"), "raw_auc_tol": d.get("auc_tolerant"),
                    "ver_r100_tol": v.get("recall_at_100p_tolerant"), "ver_auc_tol": v.get("auc_tolerant"),
                    "variant": d.get("quantizer_variant"), "file": str(p)}
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundles", nargs="+", type=Path)
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("AEFABMAP_DATA", "data")))
    ap.add_argument("--results", nargs="+", type=Path, default=[])
    ap.add_argument("--cache", type=Path, default=None, help="feature/pair cache of the training runs")
    ap.add_argument("--warp-images", type=int, default=600, help="pair settings of the runs (ae_matrix.sh: 600)")
    ap.add_argument("--frame-pairs", type=int, default=400, help="(ae_matrix.sh: 400)")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--plot", type=Path, default=None, help="PNG of the AE held-out loss curves")
    args = ap.parse_args()

    files = find_training_images([args.data / "train" / "camvid", args.data / "train" / "scene15"])
    lip6: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    pairs: dict[str, object] = {}
    report: dict = {"load_average": os.getloadavg(), "bundles": {}}
    for path in args.bundles:
        b = load_bundle(path)
        m = b.manifest
        fc = FeatureConfig.from_dict(m["features"])
        kind = fc.kind
        if kind not in lip6:
            lip6[kind] = (lip6_vectors(args.data, fc, 500), lip6_vectors(args.data, fc, 20_000))
            _, val = cached_match_pairs(files, fc, args.cache, warp_images=args.warp_images, frame_pairs=args.frame_pairs,
                                        seed=SEED, show_progress=False).split(PAIR_VAL_FRACTION, SEED)
            pairs[kind] = val
        x500, x20k = lip6[kind]
        q = m["quantizer"]
        entry: dict = {"features": kind, "words": m["vocabulary_size"] if "vocabulary_size" in m else None,
                       "type": q["type"]}
        variants = ("fp32", "int8") if q["type"] == "ae" else ("fp32",)
        words = {}
        for var in variants:
            quant = b.quantizer(var, threads=1)
            entry[f"cost_{var}"] = time_ms(quant.quantize, x500, args.repeats)
            words[var] = quant.quantize(x20k)
            val = pairs[kind]
            entry[f"pair_word_agreement_{var}"] = round(float(np.mean(quant.quantize(val.a) == quant.quantize(val.b))), 4)
        entry["held_out_pairs"] = len(pairs[kind])
        if q["type"] == "ae":
            entry["int8_agreement_lip6"] = round(float(np.mean(words["fp32"] == words["int8"])), 4)
            entry["int8_agreement_train"] = q.get("int8_agreement")
            t = q["train"]
            entry["train"] = {k: t.get(k) for k in ("seconds", "epochs", "best_epoch", "stop_reason", "val_loss",
                                                     "n_train", "n_val", "n_pairs_train", "n_pairs_val", "loss")}
            entry["train"]["arch"] = t["config"].get("arch", "paper")
            entry["train"]["latent_dim"] = q["latent_dim"]
            entry["train"]["match_weight"] = t["config"].get("match_weight", 0.0)
            entry["history"] = t.get("history", [])
            entry["timings"] = q.get("timings")
            entry["search"] = q.get("search")  # a re-vocabulary (tree) of another bundle's encoder
        for seq in ("lip6", "corridor"):
            entry[seq] = eval_figures(args.results, path.name, seq)
        report["bundles"][path.name] = entry
        print(path.name, json.dumps({k: v for k, v in entry.items() if k != "history"}), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    if args.plot:
        plot_curves(report, args.plot)
    print(markdown(report))
    print(f"wrote {args.out}")


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def markdown(report: dict) -> str:
    """One row per bundle: Lip6 and corridor (raw LLR / verified, tolerant R@100P and AUC), the
    held-out pair word agreement, int8 cost and agreement, AE training time and epochs."""
    head = ("bundle", "Lip6 raw R@100P", "Lip6 raw AUC", "Lip6 ver R@100P", "Lip6 ver AUC",
            "corr raw R@100P", "corr raw AUC", "corr ver R@100P", "corr ver AUC",
            "pair words same", "ms/500 (CPU)", "int8=fp32 (Lip6)", "train s / epochs")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, e in report["bundles"].items():
        cells = [name]
        for seq in ("lip6", "corridor"):
            f = e.get(seq) or {}
            cells += [_pct(f.get("raw_r100_tol")), _pct(f.get("raw_auc_tol")),
                      _pct(f.get("ver_r100_tol")), _pct(f.get("ver_auc_tol"))]
        var = "int8" if e["type"] == "ae" else "fp32"
        cells.append(_pct(e.get(f"pair_word_agreement_{var}")))
        cells.append(f"{e[f'cost_{var}']['cpu_ms']:.1f}")
        cells.append(_pct(e.get("int8_agreement_lip6")))
        t = e.get("train")
        # Manifests of bundles trained before wall-clock times left them carry "seconds".
        secs = "-" if not t or t.get("seconds") is None else f"{t['seconds']:.0f}"
        cells.append("-" if not t else f"{secs} / {t['epochs']} ({t['stop_reason']})")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_epoch_panels(runs: dict[str, list[dict]], panels: list[tuple[str, object]], xlabel: str, out: Path) -> None:
    """One line per run in each panel: panels are (title, value of one history record) pairs,
    runs map a name to its per-epoch history (a manifest's quantizer.train.history)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4))
    for name, h in runs.items():
        ep = [r["epoch"] for r in h]
        for ax, (_, value) in zip(axes, panels):
            ax.plot(ep, [value(r) for r in h], marker=".", label=name)
    for ax, (title, _) in zip(axes, panels):
        ax.set(title=title, xlabel=xlabel)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)


def plot_curves(report: dict, out: Path) -> None:
    """Held-out reconstruction BCE and matching loss per epoch of every AE bundle."""
    aes = {n: e["history"] for n, e in report["bundles"].items()
           if e["type"] == "ae" and e.get("history") and not e.get("search")}
    if not aes:
        return
    plot_epoch_panels(aes, [
        ("held-out reconstruction BCE (nats/element)", lambda r: r["val_recon"]),
        ("held-out matching loss (InfoNCE, 256-pair batches)",
         lambda r: r["val_match"] if r.get("val_match") is not None else np.nan),
    ], "epoch", out)


if __name__ == "__main__":
    main()
