"""A hostile model bundle: paths that leave the bundle, lying .npy headers, out-of-range
settings and word ids are refused with one BundleError line (CLI exit code 3)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from aefabmap_runtime.errors import BundleError, InputError
from aefabmap_runtime.adapters.bundle_reader import load_bundle, sha256_file
from aefabmap_runtime.adapters.mcap_log import McapLogWriter


def _manifest(bundle) -> dict:
    return json.loads((bundle / "manifest.json").read_text())


def _write_manifest(bundle, manifest: dict) -> None:
    (bundle / "manifest.json").write_text(json.dumps(manifest))


def _rename_in_manifest(bundle, old: str, new: str) -> None:
    """Make the manifest name ``new`` (with ``old``'s checksum) where it named ``old``."""
    m = _manifest(bundle)
    m["files"] = {(new if k == old else k): v for k, v in m["files"].items()}
    q = m["quantizer"]["files"]
    q.update({k: new for k, v in q.items() if v == old})
    _write_manifest(bundle, m)


def _replace_array(bundle, name: str, array: np.ndarray) -> None:
    """Write ``array`` as ``name`` and record its checksum: only the content is hostile."""
    np.save(bundle / name, array, allow_pickle=False)
    m = _manifest(bundle)
    m["files"][name] = sha256_file(bundle / name)
    _write_manifest(bundle, m)


@pytest.mark.parametrize(
    "name",
    ["../../../../etc/passwd", "/etc/passwd", "sub/vocabulary.npy", "..", ".", "", "vocabulary.npy/", "a\\..\\b",
     "vocab\x00.npy"],
)
def test_manifest_paths_outside_the_bundle_are_refused(synthetic_bundle, name):
    _rename_in_manifest(synthetic_bundle, "vocabulary.npy", name)
    with pytest.raises(BundleError, match="not a plain file name inside the bundle"):
        load_bundle(synthetic_bundle)


def test_refusal_does_not_reveal_whether_an_outside_path_exists(synthetic_bundle, tmp_path):
    (tmp_path / "exists.npy").write_bytes(b"secret")
    messages = []
    for name in ("../exists.npy", "../missing.npy"):
        _rename_in_manifest(synthetic_bundle, "vocabulary.npy" if not messages else "../exists.npy", name)
        with pytest.raises(BundleError) as info:
            load_bundle(synthetic_bundle)
        messages.append(str(info.value).replace(name, "NAME"))
    assert messages[0] == messages[1]


def test_symlink_leaving_the_bundle_is_refused_before_it_is_opened(synthetic_bundle, tmp_path):
    outside = tmp_path / "outside.npy"
    os.replace(synthetic_bundle / "tree_p.npy", outside)
    os.symlink(outside, synthetic_bundle / "tree_p.npy")
    with pytest.raises(BundleError, match="tree_p.npy is not a regular file"):
        load_bundle(synthetic_bundle)
    # even a symlink to a file of the bundle: only plain files are read
    os.unlink(synthetic_bundle / "tree_p.npy")
    os.replace(outside, synthetic_bundle / "tree_p_real.npy")
    os.symlink("tree_p_real.npy", synthetic_bundle / "tree_p.npy")
    with pytest.raises(BundleError, match="tree_p.npy is not a regular file"):
        load_bundle(synthetic_bundle)


def test_manifest_symlink_and_fifo_are_refused(synthetic_bundle, tmp_path):
    target = tmp_path / "m.json"
    os.replace(synthetic_bundle / "manifest.json", target)
    os.symlink(target, synthetic_bundle / "manifest.json")
    with pytest.raises(BundleError, match="manifest.json is not a regular file"):
        load_bundle(synthetic_bundle)
    os.unlink(synthetic_bundle / "manifest.json")
    os.replace(target, synthetic_bundle / "manifest.json")
    os.unlink(synthetic_bundle / "tree_a.npy")
    os.mkfifo(synthetic_bundle / "tree_a.npy")  # opening it for reading would block forever
    with pytest.raises(BundleError, match="tree_a.npy is not a regular file"):
        load_bundle(synthetic_bundle)


@pytest.mark.parametrize("files", [["tree_p.npy"], "tree_p.npy", {"tree_p.npy": 5}, None])
def test_malformed_files_table_is_refused(synthetic_bundle, files):
    m = _manifest(synthetic_bundle)
    m["files"] = files
    _write_manifest(synthetic_bundle, m)
    with pytest.raises(BundleError, match="files"):
        load_bundle(synthetic_bundle)


@pytest.mark.parametrize("qfiles", [{"centroids": ["vocabulary.npy"]}, {"centroids": 3}, ["vocabulary.npy"]])
def test_malformed_quantizer_files_are_refused(synthetic_bundle, qfiles):
    m = _manifest(synthetic_bundle)
    m["quantizer"]["files"] = qfiles
    _write_manifest(synthetic_bundle, m)
    with pytest.raises(BundleError, match="quantizer"):
        load_bundle(synthetic_bundle)


def _npy_with_header(shape, dtype="<f8", payload: bytes = b"\x00" * 64) -> bytes:
    """A .npy v1.0 file whose header claims ``shape`` but holds only ``payload``."""
    header = repr({"descr": dtype, "fortran_order": False, "shape": shape}).encode()
    pad = (-(10 + len(header) + 1)) % 64
    header += b" " * pad + b"\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + payload


@pytest.mark.parametrize(
    ("name", "shape", "dtype"),
    [
        ("tree_p.npy", (10**12,), "<f8"),
        ("train_obs_indices.npy", (10**12,), "<u2"),
        ("train_obs_indptr.npy", (2**62, 2**62), "<i8"),
        ("vocabulary.npy", (10**6, 10**6), "<f4"),
    ],
)
def test_npy_header_claiming_a_huge_shape_is_refused_without_allocating(synthetic_bundle, name, shape, dtype):
    path = synthetic_bundle / name
    path.write_bytes(_npy_with_header(shape, dtype))
    m = _manifest(synthetic_bundle)
    m["files"][name] = sha256_file(path)
    _write_manifest(synthetic_bundle, m)
    with pytest.raises(BundleError, match=name):
        load_bundle(synthetic_bundle).quantizer()


@pytest.mark.parametrize(
    ("name", "array"),
    [
        ("tree_parent.npy", np.zeros(64, np.float64)),  # wrong dtype kind
        ("tree_p.npy", np.full(64, 5, np.int64)),
        ("train_obs_indices.npy", lambda a: -a.astype(np.int32) - 1),  # negative word ids
        ("train_obs_indices.npy", lambda a: a + 0.5),
        ("train_obs_indptr.npy", np.arange(21, dtype=np.float64)),
        ("train_obs_indptr.npy", np.full(21, -1, np.int64)),
        ("vocabulary.npy", np.zeros((64, 256), np.int64)),
        ("vocabulary.npy", np.zeros((64, 256), np.complex64)),
        ("vocabulary.npy", np.full((64, 256), np.nan, np.float32)),
    ],
    ids=lambda v: v if isinstance(v, str) else getattr(v, "dtype", "edited"),
)
def test_arrays_of_the_wrong_kind_or_range_are_refused_naming_the_file(synthetic_bundle, name, array):
    if callable(array):  # an edit of the bundle's own array (keeps its length consistent)
        array = array(np.load(synthetic_bundle / name))
    _replace_array(synthetic_bundle, name, array)
    with pytest.raises(BundleError, match=name.replace(".", r"\.")):
        load_bundle(synthetic_bundle).quantizer()


@pytest.mark.parametrize(
    "features",
    [
        {"kind": "orb", "max_features": 10**12, "long_side": 640},
        {"kind": "orb", "max_features": -1},
        {"kind": "orb", "max_features": True},
        {"kind": "orb", "max_features": 1.5},
        {"kind": "orb", "long_side": 10**12},
        {"kind": "orb", "long_side": "640"},
        {"kind": ["orb"]},
        {"kind": "orb", "rootsift": "yes"},
        "orb",
    ],
)
def test_out_of_range_feature_settings_are_refused(synthetic_bundle, features):
    m = _manifest(synthetic_bundle)
    m["features"] = features
    _write_manifest(synthetic_bundle, m)
    with pytest.raises(BundleError, match="feature"):
        load_bundle(synthetic_bundle)


def _cli(*args, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "aefabmap.cli.main", *args], check=False, capture_output=True,
                          text=True, timeout=timeout)


def test_cli_reports_a_hostile_bundle_in_one_line_with_exit_code_3(synthetic_bundle, tmp_path):
    log_path = tmp_path / "empty.mcap"
    with McapLogWriter(log_path):
        pass
    indices = np.load(synthetic_bundle / "train_obs_indices.npy")
    _replace_array(synthetic_bundle, "train_obs_indices.npy", -indices.astype(np.int32) - 1)
    proc = _cli("replay", str(log_path), "--model", str(synthetic_bundle))
    assert proc.returncode == 3, proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert "train_obs_indices.npy" in proc.stderr
    _rename_in_manifest(synthetic_bundle, "vocabulary.npy", "../../../../etc/passwd")
    images = tmp_path / "images"
    images.mkdir()
    proc = _cli("eval", "--model", str(synthetic_bundle), "--images", str(images), "--gt", str(tmp_path / "gt.npy"))
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    np.save(tmp_path / "gt.npy", np.zeros((1, 1), bool))
    import cv2

    cv2.imwrite(str(images / "0000.png"), np.zeros((48, 64), np.uint8))
    proc = _cli("eval", "--model", str(synthetic_bundle), "--images", str(images), "--gt", str(tmp_path / "gt.npy"),
                "--no-progress")
    assert proc.returncode == 3, proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert "etc/passwd" in proc.stderr and "not a plain file name" in proc.stderr


@pytest.mark.parametrize(
    "content",
    [
        _npy_with_header((10**6, 10**6), "|b1"),  # claims a TB
        _npy_with_header((3, 3), "|b1", payload=b"\x01" * 9),  # fits the file, not the sequence
        _npy_with_header((2, 2), "<c8", payload=b"\x00" * 32),
        b"\x93NUMPY\x03\x00" + b"\x00" * 60,  # unsupported format version
        b"\x93NUMPY\x01\x00\xff",  # truncated header
        b"not an npy file at all",
    ],
)
def test_ground_truth_header_is_checked_before_loading(tmp_path, content):
    from aefabmap_runtime.tools.sequence_eval import load_ground_truth

    path = tmp_path / "gt.npy"
    path.write_bytes(content)
    with pytest.raises(InputError, match="ground truth"):
        load_ground_truth(path, 2)


def test_ground_truth_that_fits_loads(tmp_path):
    from aefabmap_runtime.tools.sequence_eval import load_ground_truth

    np.save(tmp_path / "gt.npy", np.eye(3, dtype=np.uint8))
    assert load_ground_truth(tmp_path / "gt.npy", 3).dtype == bool


def test_cli_eval_with_a_lying_ground_truth_header_exits_4_in_one_line(synthetic_bundle, tmp_path):
    import cv2

    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "0000.png"), np.zeros((48, 64), np.uint8))
    (tmp_path / "gt.npy").write_bytes(_npy_with_header((10**6, 10**6), "|b1"))
    proc = _cli("eval", "--model", str(synthetic_bundle), "--images", str(images), "--gt", str(tmp_path / "gt.npy"),
                "--no-progress")
    assert proc.returncode == 4, proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert "gt.npy" in proc.stderr


@pytest.mark.parametrize("edit", [
    lambda m: m.update(detector={}),
    lambda m: m.update(detector="abc"),
    lambda m: m.update(detector={"pzge": "x", "pzgne": 0.0}),
    lambda m: m.update(detector={"pzge": 0.39, "pzgne": float("nan")}),
    lambda m: m.update(detector={"pzge": 0.1, "pzgne": 0.5}),
    lambda m: m.update(detector={"pzge": True, "pzgne": 0.0}),
    lambda m: m["quantizer"].update(files={}),
    lambda m: m["features"].update(max_features="many"),
], ids=["detector-empty", "detector-string", "pzge-string", "pzgne-nan", "pzgne-above-pzge", "pzge-bool",
        "quantizer-files-empty", "features-bad"])
def test_malformed_manifest_fields_are_one_line_errors_before_any_frame(synthetic_bundle, edit):
    """A bundle whose manifest fields have the wrong type or range is refused when it is loaded,
    as a BundleError (CLI exit 3), never a traceback and never on the first frame."""
    from aefabmap_runtime.adapters.bundle_reader import load_detector

    m = _manifest(synthetic_bundle)
    edit(m)
    _write_manifest(synthetic_bundle, m)
    with pytest.raises(BundleError) as info:
        load_detector(synthetic_bundle)
    assert "\n" not in str(info.value)
