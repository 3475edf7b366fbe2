"""Named run presets ("profiles"): one line picks a configuration whose per-frame cost is measured.

A profile fixes what the model must be (keypoints per frame, vocabulary size K, quantiser
variant) and how the node runs (threads, map memory cap, frame queue). `aefabmap run --profile
NAME` applies the run settings (explicit options still win) and refuses a bundle that is not
the profile's model, since the measured cost (deploy/README.md, "Board profile") holds for that model only.
"""

from __future__ import annotations

from dataclasses import dataclass

from aefabmap_runtime.errors import ConfigError


@dataclass(frozen=True)
class RunProfile:
    """keypoints: ORB/SIFT keypoints per frame the bundle was trained with (features.max_features).
    feature_kind / words / variant: the bundle's feature kind, K and quantiser variant
    ("kmeans-flat", "kmeans-indexed", "kmeans-tree", "ae-fp32", "ae-int8"). threads: onnxruntime and OpenCV threads
    (BLAS already runs one thread per frame). memory_mb: cap of the map (MiB, keypoints of the
    places included). queue: frames kept while busy (older ones dropped).
    """

    name: str
    feature_kind: str
    keypoints: int
    words: int
    variant: str
    threads: int
    memory_mb: float
    queue: int
    train_command: str

    def check_bundle(self, manifest: dict) -> None:
        """Raise ConfigError unless the bundle (its manifest) is this profile's model."""
        features, q = manifest.get("features", {}), manifest.get("quantizer", {})
        have = bundle_variants(q)
        want = {"features": self.feature_kind, "keypoints": self.keypoints, "words": self.words}
        got = {"features": features.get("kind"), "keypoints": features.get("max_features"),
               "words": manifest.get("vocabulary_size")}
        if got != want or self.variant not in have:
            raise ConfigError(
                f"profile {self.name!r} runs {self.feature_kind} {self.keypoints} keypoints, {self.words} words, "
                f"{self.variant}; the bundle has {got['features']} {got['keypoints']} keypoints, {got['words']} words, "
                f"{' / '.join(have)}. Train one with: {self.train_command}"
            )

    @property
    def quantizer_variant(self) -> str:
        """The DetectorConfig.quantizer_variant of `variant`."""
        return {"ae-int8": "int8", "kmeans-flat": "flat", "kmeans-flat-fp32": "flat-fp32"}.get(self.variant, "fp32")


def bundle_variants(quantizer: dict) -> tuple[str, ...]:
    """Quantiser variants a bundle can run, from its manifest quantizer entry (its default first)."""
    qtype = quantizer.get("type")
    if qtype == "kmeans":
        flat = ("kmeans-flat", "kmeans-flat-fp32")
        return ("kmeans-indexed",) + flat if "index" in quantizer else flat
    if qtype == "kmeans-tree":
        return ("kmeans-tree",)
    return ("ae-fp32", "ae-int8")


#: The presets, by name. "board": one core of a small ARM board (Raspberry Pi 4/5 class)
#: running the node beside a camera driver and a SLAM back-end. Its quantiser is the flat
#: search: the vocabulary tree is faster but less accurate on Lip6, and the inverted index was
#: not faster at 32 buckets (docs/results.md, "Quantisation in O(log K)").
PROFILES = {
    "board": RunProfile(
        name="board",
        feature_kind="orb",
        keypoints=500,
        words=3000,
        variant="kmeans-flat",
        threads=1,
        memory_mb=64.0,
        queue=2,
        train_command="aefabmap train --images DATA/train/camvid DATA/train/scene15 --features orb "
        "--quantizer kmeans --words 3000 --seed 0 --out bundles/orb_kmeans_3000",
    ),
}


def get_profile(name: str) -> RunProfile:
    """The profile called `name`; ConfigError naming the known ones otherwise."""
    try:
        return PROFILES[name]
    except (KeyError, TypeError):
        raise ConfigError(f"profile must be one of {tuple(PROFILES)}, got {str(name)[:40]!r}") from None
