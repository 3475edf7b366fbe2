"""The runtime works under the unit's MemoryDenyWriteExecute= and SystemCallFilter=.

numpy, OpenCV, onnxruntime and zenoh are native code: if one of them generated code at run time
(a JIT needs writable+executable memory) or made a system call outside @system-service, the
service would crash on the board. systemd is not running here, so unit_sandbox.py installs the
same seccomp filters the unit asks systemd for, and the runtime's work runs under them.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from tests.deploy.unit_file import REPO, read_unit, sandbox_available, sandbox_prefix

pytestmark = pytest.mark.skipif(not sandbox_available(), reason="needs Linux, libseccomp and systemd-analyze")


def _sandboxed(argv: list[str], timeout_s: float) -> subprocess.CompletedProcess:
    """Run argv under the unit's seccomp filters, with this checkout importable."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    return subprocess.run([*sandbox_prefix(read_unit()["Service"]), *argv], check=False,
                          capture_output=True, text=True, timeout=timeout_s, env=env)


def test_sandbox_denies_what_the_unit_denies():
    probe = textwrap.dedent(
        """
        import mmap, os
        rw = mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE)
        try:
            mmap.mmap(-1, 4096, prot=mmap.PROT_WRITE | mmap.PROT_EXEC)
            print("write+execute mapped")
        except PermissionError:
            print("write+execute denied")
        try:
            os.chroot("/")
            print("chroot allowed")
        except PermissionError:
            print("chroot denied")
        """
    )
    out = _sandboxed([sys.executable, "-c", probe], timeout_s=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split("\n")[:2] == ["write+execute denied", "chroot denied"]


def test_onnxruntime_runs_in_the_sandbox(tmp_path):
    onnx = pytest.importorskip("onnx")
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper

    weights = numpy_helper.from_array(np.arange(12, dtype=np.float32).reshape(4, 3), "W")
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["X", "W"], ["Y"]), helper.make_node("ArgMax", ["Y"], ["I"], axis=1)],
        "probe", [helper.make_tensor_value_info("X", TensorProto.FLOAT, [None, 4])],
        [helper.make_tensor_value_info("I", TensorProto.INT64, [None, 1])], [weights],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, tmp_path / "probe.onnx")
    code = textwrap.dedent(
        f"""
        import numpy as np, onnxruntime as ort
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 2
        session = ort.InferenceSession(r"{tmp_path / 'probe.onnx'}", opts, providers=["CPUExecutionProvider"])
        x = np.random.default_rng(0).random((256, 4), dtype=np.float32)
        (idx,) = session.run(None, {{"X": x}})
        assert idx.shape == (256, 1) and (idx == 2).all(), idx
        print("onnxruntime ok")
        """
    )
    out = _sandboxed([sys.executable, "-c", code], timeout_s=120)
    assert out.returncode == 0 and "onnxruntime ok" in out.stdout, out.stderr[-2000:]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_demo_runs_in_the_sandbox(tmp_path):
    """Publisher, `aefabmap run` (OpenCV, numpy, zenoh, MCAP) and the replay check, all filtered."""
    out = _sandboxed([sys.executable, "-m", "aefabmap.cli.main", "demo", "--frames", "40", "--rate", "20",
                      "--out", str(tmp_path / "demo")], timeout_s=240)
    assert out.returncode == 0, (out.stdout + out.stderr)[-3000:]
    assert "replay --check: check OK" in out.stdout
    assert (tmp_path / "demo" / "demo.mcap").stat().st_size > 0


def test_kernels_run_ahead_of_time_compiled_when_the_jit_is_denied():
    """numba (extra `fast`) cannot map write+execute memory under the unit: importing the runtime
    must not fail, numba must not be offered, and the kernels must run on the ahead-of-time
    compiled library (where it is built) with the numpy path's results."""
    code = textwrap.dedent(
        """
        import numpy as np
        from aefabmap_runtime.core.kernels import compiled
        from aefabmap_runtime.core.kernels.bits import nearest_two
        from aefabmap_runtime.core.rank.fabmap import FabMap2
        from aefabmap_runtime.tools.synthetic_observations import random_tree, synthetic_observations

        def scores():
            engine = FabMap2(random_tree(200, 0), synthetic_observations(20, 200, 30, 1))
            for o in synthetic_observations(30, 200, 30, 2):
                engine.add(o)
            return engine.localize(synthetic_observations(1, 200, 30, 3)[0], add=False).loglik

        rng = np.random.default_rng(0)
        a, b = rng.integers(0, 256, (300, 32), np.uint8), rng.integers(0, 256, (400, 32), np.uint8)
        form = compiled.backend()
        compiled_out = scores(), nearest_two(a, b)
        compiled.use("numpy")
        numpy_out = scores(), nearest_two(a, b)
        assert np.array_equal(compiled_out[0], numpy_out[0])
        assert all(np.array_equal(x, y) for x, y in zip(compiled_out[1], numpy_out[1]))
        print(form, "|", ",".join(compiled.backends()))
        """
    )
    out = _sandboxed([sys.executable, "-c", code], timeout_s=120)
    assert out.returncode == 0, out.stderr[-2000:]
    form, offered = out.stdout.strip().split(" | ", 1)
    assert "numba" not in offered
    from aefabmap_runtime.core.kernels import native

    assert form == ("native" if native.available() else "numpy")
