"""TUM RGB-D folders in, TUM trajectories out.

A folder holds ``rgb.txt`` and ``depth.txt`` (``timestamp path`` lines, ``#`` comments) or an
``associations.txt`` (``t_rgb rgb_path t_depth depth_path``), optionally ``groundtruth.txt``
(``timestamp tx ty tz qx qy qz qw``, camera-to-world) and ``camera.yaml`` (``fx: ...`` lines with
fx, fy, cx, cy and optionally depth_scale). Depth PNGs are 16-bit, value / depth_scale = metres
(TUM: 5000). Format reference: https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.errors import DataNotFoundError, ImageDecodeError, InputError
from aefabmap.slam.poses import make_pose, matrix_to_quaternion, quaternion_to_matrix

#: TUM's depth scale: a 16-bit depth value of 5000 is one metre.
TUM_DEPTH_SCALE = 5000.0
#: Largest time difference (s) when pairing RGB with depth or frames with ground truth (TUM's associate.py).
MAX_DT = 0.02


@dataclass
class RgbdSequence:
    """An RGB-D sequence: N frames in time order.

    stamps: (N,) float64 seconds; rgb, depth: N image paths; camera: (fx, fy, cx, cy) pixels;
    depth_scale: depth value per metre; groundtruth: (N, 4, 4) camera-to-world poses of the
    frames (NaN where the ground truth has no pose within MAX_DT), or None without ground truth.
    """

    root: Path
    stamps: np.ndarray
    rgb: list[Path]
    depth: list[Path]
    camera: tuple[float, float, float, float]
    depth_scale: float = TUM_DEPTH_SCALE
    groundtruth: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.stamps.size)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        fx, fy, cx, cy = self.camera
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def gray(self, i: int) -> np.ndarray:
        """Frame i as a grayscale (H, W) uint8 image."""
        img = cv2.imread(str(self.rgb[i]), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ImageDecodeError(f"cannot read image {self.rgb[i]}")
        return img

    def depth_m(self, i: int) -> np.ndarray:
        """Depth of frame i, (H, W) float32 metres, 0 where unknown."""
        d = cv2.imread(str(self.depth[i]), cv2.IMREAD_UNCHANGED)
        if d is None or d.ndim != 2:
            raise ImageDecodeError(f"cannot read depth image {self.depth[i]} (16-bit single-channel PNG expected)")
        return d.astype(np.float32) / np.float32(self.depth_scale)


def _rows(path: Path) -> list[list[str]]:
    """Whitespace-separated fields of the non-comment, non-empty lines of a text file."""
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise DataNotFoundError(f"cannot read {path}: {exc.strerror or exc}") from exc
    return [ln.split() for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]


def _stamped_paths(path: Path) -> tuple[np.ndarray, list[str]]:
    rows = _rows(path)
    try:
        return np.array([float(r[0]) for r in rows]), [r[1] for r in rows]
    except (ValueError, IndexError) as exc:
        raise InputError(f"{path}: expected 'timestamp path' lines") from exc


def associate(a: np.ndarray, b: np.ndarray, max_dt: float = MAX_DT) -> list[tuple[int, int]]:
    """Pairs (i, j) of stamps a[i], b[j] within max_dt of each other, closest first, each index once."""
    if a.size == 0 or b.size == 0:
        return []
    diff = np.abs(a[:, None] - b[None, :])
    cand = np.argwhere(diff <= max_dt)
    cand = cand[np.argsort(diff[cand[:, 0], cand[:, 1]], kind="stable")]
    used_a, used_b, pairs = set(), set(), []
    for i, j in cand.tolist():
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def read_camera_yaml(path: Path) -> tuple[tuple[float, float, float, float], float]:
    """((fx, fy, cx, cy), depth_scale) from ``key: value`` lines (depth_scale defaults to TUM's)."""
    values = {}
    for line in path.read_text().splitlines():
        key, sep, rest = line.partition(":")
        if sep:
            try:
                values[key.strip()] = float(rest.split("#")[0].strip())
            except ValueError:
                continue  # lists (distortion) and comments
    try:
        camera = tuple(values[k] for k in ("fx", "fy", "cx", "cy"))
    except KeyError as exc:
        raise InputError(f"{path}: no {exc.args[0]} value") from None
    return camera, values.get("depth_scale", TUM_DEPTH_SCALE)


def read_rgbd_folder(root: str | Path, camera: tuple[float, float, float, float] | None = None,
                     depth_scale: float | None = None) -> RgbdSequence:
    """Read a TUM RGB-D folder (see the module docstring).

    camera / depth_scale override camera.yaml; without either, InputError. Frames are the
    rows of associations.txt, else rgb.txt paired with depth.txt by time (MAX_DT).
    """
    root = Path(root)
    if not root.is_dir():
        raise DataNotFoundError(f"RGB-D folder {root} does not exist")
    yaml_cam, yaml_scale = (None, TUM_DEPTH_SCALE)
    if (root / "camera.yaml").is_file():
        yaml_cam, yaml_scale = read_camera_yaml(root / "camera.yaml")
    cam = camera or yaml_cam
    if cam is None:
        raise InputError(f"{root}: no camera.yaml; give the intrinsics (--camera fx,fy,cx,cy)")
    if (root / "associations.txt").is_file():
        rows = _rows(root / "associations.txt")
        try:
            stamps = np.array([float(r[0]) for r in rows])
            rgb, depth = [r[1] for r in rows], [r[3] for r in rows]
        except (ValueError, IndexError) as exc:
            raise InputError(f"{root / 'associations.txt'}: expected 't_rgb rgb t_depth depth' lines") from exc
    elif (root / "rgb.txt").is_file() and (root / "depth.txt").is_file():
        t_rgb, rgb_all = _stamped_paths(root / "rgb.txt")
        t_d, d_all = _stamped_paths(root / "depth.txt")
        pairs = associate(t_rgb, t_d)
        stamps = np.array([t_rgb[i] for i, _ in pairs])
        rgb, depth = [rgb_all[i] for i, _ in pairs], [d_all[j] for _, j in pairs]
    else:
        raise DataNotFoundError(f"{root}: neither associations.txt nor rgb.txt + depth.txt")
    if stamps.size < 2:
        raise DataNotFoundError(f"{root}: fewer than 2 RGB-D frames")
    order = np.argsort(stamps, kind="stable")
    seq = RgbdSequence(root, stamps[order], [root / rgb[i] for i in order], [root / depth[i] for i in order],
                       tuple(float(v) for v in cam), float(depth_scale or yaml_scale))
    if (root / "groundtruth.txt").is_file():
        t_gt, poses = read_tum_trajectory(root / "groundtruth.txt")
        gt = np.full((len(seq), 4, 4), np.nan)
        for i, j in associate(seq.stamps, t_gt):
            gt[i] = poses[j]
        seq.groundtruth = gt
    return seq


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (N,) s, poses (N, 4, 4) camera-to-world) of a TUM trajectory file."""
    rows = _rows(Path(path))
    try:
        a = np.array([[float(v) for v in r[:8]] for r in rows if len(r) >= 8])
    except ValueError as exc:
        raise InputError(f"{path}: expected 'timestamp tx ty tz qx qy qz qw' lines") from exc
    if a.size == 0:
        return np.zeros(0), np.zeros((0, 4, 4))
    return a[:, 0], np.stack([make_pose(quaternion_to_matrix(r[4:8]), r[1:4]) for r in a])


def write_tum_trajectory(path: str | Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """Write (N,) stamps (s) and (N, 4, 4) camera-to-world poses as a TUM trajectory file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, T in zip(stamps, poses):
        q = matrix_to_quaternion(T[:3, :3])
        lines.append(f"{t:.6f} " + " ".join(f"{v:.6f}" for v in (*T[:3, 3], *q)))
    path.write_text("\n".join(lines) + "\n")
