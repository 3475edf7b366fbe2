"""Deterministic synthetic loop sequence: the project's default demo data (nothing downloaded).

A large grayscale "world" texture (seeded gradients, low-frequency shading, random filled
shapes, lines and text-like glyph strings: plenty of ORB corners) is viewed by a camera
moving along a closed elliptic route that is traversed twice. The second lap revisits the
places of the first with a half-step phase shift, a small rotation/scale jitter, another
illumination gain/offset and fresh sensor noise, so revisits look alike without being
pixel-identical.

Ground truth: ``gt[i, j]`` is True when the camera centres of frames i and j are within
``revisit_radius`` (a fraction of the frame width, in world pixels) of each other and the
frames are at least ``min_separation`` frames apart (temporal neighbours are not loop
closures). ``gt`` is symmetric with a False diagonal; a detector is scored on
``gt[i, :i]`` (frame i revisits an earlier frame).

Everything is a pure function of (n_frames, seed, size): same inputs, same bytes.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError

_GLYPHS = "ABCDEFGHJKLMNPQRSTUVWXYZ0123456789#%&@"
_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)


@dataclass(frozen=True)
class SyntheticConfig:
    """Parameters of the synthetic world and route.

    world_scale: world size = world_scale x frame size (pixels).
    route_scale: ellipse semi-axes = route_scale x frame size (pixels); must keep the
        view inside the world: route_scale + 0.5 * max_zoom < world_scale / 2.
    laps: how many times the route is traversed (>= 2 for revisits).
    revisit_radius: ground-truth revisit distance as a fraction of the frame width.
    min_separation: None = half a lap; frames closer in time are never revisits.
    noise_sigma: std of additive Gaussian sensor noise (gray levels).
    shapes_per_mpx: random shapes per million world pixels.
    """

    world_scale: float = 4.0
    route_scale: float = 1.2
    laps: int = 2
    revisit_radius: float = 0.15
    min_separation: int | None = None
    noise_sigma: float = 3.0
    shapes_per_mpx: int = 450
    max_rotation_deg: float = 4.0
    max_zoom: float = 1.06

    def __post_init__(self) -> None:
        if self.laps < 1:
            raise ConfigError(f"laps must be >= 1, got {self.laps}")
        if self.route_scale + 0.5 * self.max_zoom * 1.1 >= self.world_scale / 2:
            raise ConfigError("route_scale too large for world_scale: the camera would leave the world")


def _check_size(size: tuple[int, int]) -> tuple[int, int]:
    try:
        w, h = int(size[0]), int(size[1])
    except (TypeError, ValueError, IndexError):
        raise ConfigError(f"size must be (width, height), got {size!r}") from None
    if not (32 <= w <= 640 and 32 <= h <= 480):
        raise ConfigError(f"frame size must be between 32x32 and 640x480 pixels, got {w}x{h}")
    return w, h


def render_world(seed: int, size: tuple[int, int], config: SyntheticConfig | None = None) -> np.ndarray:
    """The world texture, (world_scale*H, world_scale*W) uint8, deterministic in (seed, size)."""
    cfg = config or SyntheticConfig()
    w, h = _check_size(size)
    ww, wh = int(round(cfg.world_scale * w)), int(round(cfg.world_scale * h))
    rng = np.random.default_rng(seed)
    # Background: linear gradient + low-frequency shading.
    yy, xx = np.mgrid[0:wh, 0:ww].astype(np.float32)
    gx, gy = rng.uniform(-1, 1, size=2)
    grad = (gx * xx / ww + gy * yy / wh) * 60.0
    low = rng.uniform(0, 1, size=(max(2, wh // 160), max(2, ww // 160))).astype(np.float32)
    low = cv2.resize(low, (ww, wh), interpolation=cv2.INTER_CUBIC) * 80.0
    world = np.clip(90.0 + grad + low, 0, 255).astype(np.uint8)
    del xx, yy, grad, low
    unit = min(w, h)
    n_shapes = int(cfg.shapes_per_mpx * ww * wh / 1e6)
    for _ in range(n_shapes):
        kind = rng.integers(0, 6)
        cx, cy = int(rng.integers(0, ww)), int(rng.integers(0, wh))
        r = int(rng.uniform(0.02, 0.12) * unit) + 2
        color = int(rng.integers(0, 256))
        if kind == 0:
            cv2.rectangle(world, (cx - r, cy - r // 2), (cx + r, cy + r // 2), color, -1)
        elif kind == 1:
            cv2.circle(world, (cx, cy), r, color, -1, lineType=cv2.LINE_AA)
        elif kind == 2:
            k = int(rng.integers(3, 7))
            ang = np.sort(rng.uniform(0, 2 * np.pi, size=k))
            rad = rng.uniform(0.4, 1.0, size=k) * r
            pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], axis=1).astype(np.int32)
            cv2.fillPoly(world, [pts], color, lineType=cv2.LINE_AA)
        elif kind == 3:
            dx, dy = rng.integers(-2 * r, 2 * r + 1, size=2)
            cv2.line(world, (cx, cy), (cx + int(dx), cy + int(dy)), color, int(rng.integers(1, 4)))
        elif kind == 4:
            text = "".join(rng.choice(list(_GLYPHS), size=int(rng.integers(2, 7))))
            font = _FONTS[int(rng.integers(0, len(_FONTS)))]
            scale = rng.uniform(0.5, 1.8) * unit / 480
            cv2.putText(world, text, (cx, cy), font, scale, color, int(rng.integers(1, 3)), cv2.LINE_AA)
        else:
            # Checker patch: strong corners.
            n = int(rng.integers(2, 5))
            s = max(2, r // n)
            c2 = 255 - color
            for iy in range(n):
                for ix in range(n):
                    col = color if (ix + iy) % 2 == 0 else c2
                    x0, y0 = cx + ix * s, cy + iy * s
                    cv2.rectangle(world, (x0, y0), (x0 + s - 1, y0 + s - 1), col, -1)
    return cv2.GaussianBlur(world, (3, 3), 0.7)


@dataclass(frozen=True)
class CameraPose:
    """Camera pose in the world: centre (x, y) in world pixels, rotation (deg), zoom, lap."""

    x: float
    y: float
    rotation_deg: float
    zoom: float
    lap: int
    gain: float
    offset: float


def route_poses(n_frames: int, seed: int, size: tuple[int, int], config: SyntheticConfig | None = None) -> list[CameraPose]:
    """Camera poses of the n_frames frames along the closed route (laps x frames per lap)."""
    cfg = config or SyntheticConfig()
    w, h = _check_size(size)
    if not isinstance(n_frames, int) or n_frames < 2 * cfg.laps:
        raise ConfigError(f"n_frames must be an integer >= {2 * cfg.laps}, got {n_frames!r}")
    rng = np.random.default_rng(seed + 7919)
    per_lap = math.ceil(n_frames / cfg.laps)
    ww, wh = cfg.world_scale * w, cfg.world_scale * h
    ax, ay = cfg.route_scale * w, cfg.route_scale * h
    poses = []
    lap_light = [(1.0, 0.0)] + [
        (float(rng.uniform(0.8, 1.2)), float(rng.uniform(-20, 20))) for _ in range(cfg.laps - 1)
    ]
    for i in range(n_frames):
        lap, k = divmod(i, per_lap)
        phase = (k + (0.5 if lap % 2 else 0.0)) / per_lap * 2 * math.pi
        if lap == 0:
            rot, zoom = 0.0, 1.0
        else:
            rot = float(rng.uniform(-cfg.max_rotation_deg, cfg.max_rotation_deg))
            zoom = float(rng.uniform(1.0 / cfg.max_zoom, cfg.max_zoom))
        gain, offset = lap_light[lap]
        poses.append(
            CameraPose(ww / 2 + ax * math.cos(phase), wh / 2 + ay * math.sin(phase), rot, zoom, lap, gain, offset)
        )
    return poses


def render_view(world: np.ndarray, pose: CameraPose, size: tuple[int, int], noise: np.ndarray | None) -> np.ndarray:
    """Render the (H, W) uint8 view of the world from a pose; noise: optional (H, W) float32."""
    w, h = size
    a = math.radians(pose.rotation_deg)
    s = 1.0 / pose.zoom
    c, sn = s * math.cos(a), s * math.sin(a)
    # Output pixel (u, v) -> world (x, y) = centre + R*s*(u - w/2, v - h/2).
    m = np.array(
        [[c, -sn, pose.x - c * w / 2 + sn * h / 2], [sn, c, pose.y - sn * w / 2 - c * h / 2]], dtype=np.float64
    )
    view = cv2.warpAffine(world, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT)
    out = view.astype(np.float32) * pose.gain + pose.offset
    if noise is not None:
        out += noise
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def revisit_matrix(poses: list[CameraPose], size: tuple[int, int], config: SyntheticConfig | None = None) -> np.ndarray:
    """Ground-truth (N, N) bool revisit matrix of the poses (see module docstring)."""
    cfg = config or SyntheticConfig()
    w, _ = size
    n = len(poses)
    per_lap = math.ceil(n / cfg.laps)
    min_sep = cfg.min_separation if cfg.min_separation is not None else max(2, per_lap // 2)
    xy = np.array([[p.x, p.y] for p in poses], dtype=np.float64)
    d = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=2)
    idx = np.arange(n)
    far_in_time = np.abs(idx[:, None] - idx[None, :]) >= min_sep
    return (d <= cfg.revisit_radius * w) & far_in_time


def generate_loop_sequence(
    n_frames: int = 200,
    seed: int = 0,
    size: tuple[int, int] = (640, 480),
    config: SyntheticConfig | None = None,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Generate the sequence.

    n_frames: total frames over all laps; seed: the random seed; size: (width, height) in
    pixels, at most 640x480. Returns (images: list of (H, W) uint8, gt: (N, N) bool).
    """
    cfg = config or SyntheticConfig()
    w, h = _check_size(size)
    world = render_world(seed, (w, h), cfg)
    poses = route_poses(n_frames, seed, (w, h), cfg)
    rng = np.random.default_rng(seed + 104729)
    images = []
    for pose in poses:
        noise = rng.normal(0.0, cfg.noise_sigma, size=(h, w)).astype(np.float32) if cfg.noise_sigma > 0 else None
        images.append(render_view(world, pose, (w, h), noise))
    return images, revisit_matrix(poses, (w, h), cfg)


def random_views(
    seed: int = 0,
    size: tuple[int, int] = (640, 480),
    config: SyntheticConfig | None = None,
) -> Iterator[np.ndarray]:
    """An endless stream of (H, W) uint8 views of the world of (seed, size) from random poses
    (centre uniform over the route's bounding box, rotation within +-180 deg, zoom within
    max_zoom, gain/offset jittered) without sensor noise: every frame differs from the
    others (a soak source that does not repeat; its cost per view: docs/results.md,
    "Streaming"). Revisits happen
    by chance when two poses fall close. Deterministic in (seed, size)."""
    cfg = config or SyntheticConfig()
    w, h = _check_size(size)
    world = render_world(seed, (w, h), cfg)
    ww, wh = cfg.world_scale * w, cfg.world_scale * h
    ax, ay = cfg.route_scale * w, cfg.route_scale * h
    rng = np.random.default_rng(seed + 15485863)
    while True:
        x, y, rot, zoom, gain, offset = (
            rng.uniform(ww / 2 - ax, ww / 2 + ax), rng.uniform(wh / 2 - ay, wh / 2 + ay), rng.uniform(-180, 180),
            rng.uniform(1.0 / cfg.max_zoom, cfg.max_zoom), rng.uniform(0.85, 1.15), rng.uniform(-15, 15))
        yield render_view(world, CameraPose(float(x), float(y), float(rot), float(zoom), 0, float(gain),
                                            float(offset)), (w, h), None)


def write_sequence(
    out_dir: str | Path,
    images: list[np.ndarray],
    gt: np.ndarray,
    *,
    jpeg_quality: int = 95,
    info: dict | None = None,
) -> list[Path]:
    """Write images as ``frame_000000.jpg``... plus ``gt.npy`` (and ``sequence.json`` with info).

    Returns the image paths in order. Raises InputError when the directory is not writable.
    """
    out = Path(out_dir)
    if gt.shape != (len(images), len(images)):
        raise ConfigError(f"gt must be ({len(images)}, {len(images)}), got {gt.shape}")
    try:
        out.mkdir(parents=True, exist_ok=True)
        paths = []
        for i, img in enumerate(images):
            p = out / f"frame_{i:06d}.jpg"
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
            if not ok:
                raise InputError(f"cannot encode frame {i}")
            p.write_bytes(buf.tobytes())
            paths.append(p)
        np.save(out / "gt.npy", np.asarray(gt, dtype=bool), allow_pickle=False)
        meta = {"n_frames": len(images), "format": "frame_%06d.jpg", "gt": "gt.npy (N, N) bool"}
        meta.update(info or {})
        (out / "sequence.json").write_text(json.dumps(meta, indent=2, default=str))
    except OSError as exc:
        raise InputError(f"cannot write synthetic sequence to {out}: {exc.strerror or exc}") from exc
    return paths


def make_demo_sequence(
    out_dir: str | Path,
    n_frames: int = 200,
    seed: int = 0,
    size: tuple[int, int] = (640, 480),
    config: SyntheticConfig | None = None,
) -> list[Path]:
    """Generate and write the demo sequence in one call; returns the image paths."""
    cfg = config or SyntheticConfig()
    images, gt = generate_loop_sequence(n_frames, seed, size, cfg)
    info = {"generator": "aefabmap_runtime.tools.synthetic_route", "seed": seed, "size": list(size), "config": asdict(cfg)}
    return write_sequence(out_dir, images, gt, info=info)
