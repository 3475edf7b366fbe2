#!/usr/bin/env python
"""Instructions an aarch64 core executes to describe a keypoint: the learned descriptor's forms against ORB's tests.

No board is needed: the kernels are cross-built for aarch64 and run under QEMU user emulation
with a plugin that counts the guest's executed instructions (scripts/aarch64_instructions/).
Each count is the difference between runs at two repeat counts, per keypoint and call (the
learned descriptor: one orientation; ORB: oriented and upright in one call). Instructions are not
time: a core's speed per instruction differs between these forms. Needs aarch64-linux-gnu-gcc and
a dynamically linked qemu-aarch64 (Debian: gcc-aarch64-linux-gnu, qemu-user).

    python scripts/aarch64_instructions.py --json instructions.json

With --board WORKDIR (a deploy/check_aarch64.sh work folder that was run with a bundle: the
board's Python and wheels, and the kernels built for aarch64 in this checkout) it also counts
whole frames of `aefabmap eval` for each --model: the instructions between the first A and the
first B frames of --images, over B - A, in all and by the library they run in (onnxruntime: the
words; the compiled kernels; OpenCV; numpy; Python; the C library).

    python scripts/aarch64_instructions.py --board /tmp/aefabmap-aarch64 --model BRIEF_BUNDLE \
        --model LEARNED_BUNDLE --images DATA/lip6_outdoor --gt DATA/lip6_outdoor/ground_truth.npy
"""

from __future__ import annotations

import argparse
import bisect
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from aefabmap_runtime.core.kernels.native import LEARNED_FORMS

HERE = Path(__file__).resolve().parent / "aarch64_instructions"
REPO = HERE.parents[1]
KERNELS = REPO / "runtime" / "aefabmap_runtime" / "core" / "kernels" / "kernels.c"
#: learned_describe's forms an aarch64 core runs, by their numbers in kernels.c (their order in LEARNED_FORMS).
FORMS = {name: LEARNED_FORMS.index(name) for name in ("neon-dotprod", "neon", "plain")}
#: QEMU's CPU models: with the dot-product instructions (Raspberry Pi 5's core) and without (Pi 3's).
CPUS = ("cortex-a76", "cortex-a53")
KEYPOINTS = 1000
#: Where a frame's instructions run, by the file mapped at their address (the first pattern that
#: matches its path; none: "other", e.g. code generated at run time).
LIBRARIES = (("onnxruntime", r"onnxruntime"), ("aefabmap kernels", r"/_kernels\."), ("OpenCV", r"cv2|opencv"),
             ("numpy", r"numpy|openblas"), ("Python", r"python3|libpython|lib-dynload"),
             ("C library", r"/lib(c|m|stdc\+\+|gcc_s|pthread)[.-]|/ld-linux"))
#: `aefabmap eval` on the board's Python, leaving the process's memory map in $MAPS_OUT at exit.
EVAL_LEAVING_MAPS = ("import atexit, os, runpy; "
                     "atexit.register(lambda: open(os.environ['MAPS_OUT'], 'w').write(open('/proc/self/maps').read())); "
                     "runpy.run_module('aefabmap', run_name='__main__', alter_sys=True)")


class Unavailable(RuntimeError):
    """The cross compiler or the emulator is missing."""


def build(work: Path) -> tuple[Path, Path]:
    """The counting plugin (host) and the describing program (aarch64), built in `work`."""
    for tool in ("gcc", "aarch64-linux-gnu-gcc", "qemu-aarch64"):
        if shutil.which(tool) is None:
            raise Unavailable(f"{tool} is not installed")
    plugin, program = work / "libinsn.so", work / "describe_count"
    subprocess.run(["gcc", "-shared", "-fPIC", "-O2", str(HERE / "insn_plugin.c"), "-o", str(plugin)], check=True)
    # The flags setup.py builds the kernels with.
    subprocess.run(["aarch64-linux-gnu-gcc", "-O3", "-ffp-contract=off", str(HERE / "describe_count.c"), str(KERNELS),
                    "-lm", "-o", str(program)], check=True)
    return plugin, program


def executed(plugin: Path | str, program: Path, cpu: str, args: list[str]) -> tuple[int, str]:
    """Instructions the program executes on the CPU model, and its output (the descriptors' digest).
    plugin: the counting plugin, with its arguments if any ("PATH,blocks=FILE")."""
    run = subprocess.run(["qemu-aarch64", "-cpu", cpu, "-L", "/usr/aarch64-linux-gnu", "-plugin", str(plugin),
                          str(program), *args], capture_output=True, text=True, timeout=600, check=False)
    found = re.search(r"instructions (\d+)", run.stderr)
    if run.returncode != 0 or found is None:
        raise RuntimeError(f"{program.name} {' '.join(args)} on {cpu} failed: {run.stderr.strip()[-300:]}")
    return int(found.group(1)), run.stdout.strip()


def per_keypoint(plugin: Path, program: Path, cpu: str, args: list[str]) -> tuple[int, str]:
    """Instructions per keypoint and call (runs of 1 and 3 calls), and the descriptors' digest."""
    once, digest = executed(plugin, program, cpu, [*args, "1"])
    thrice, again = executed(plugin, program, cpu, [*args, "3"])
    if digest != again:
        raise RuntimeError(f"{' '.join(args)} on {cpu}: the descriptors differ between runs")
    return round((thrice - once) / 2 / KEYPOINTS), digest


def count(work: Path) -> dict:
    """Per CPU model: instructions per keypoint of each learned form and of ORB, and whether every
    learned form gave the same descriptors."""
    plugin, program = build(work)
    result = {"keypoints": KEYPOINTS, "cpus": {}}
    for cpu in CPUS:
        learned = {name: per_keypoint(plugin, program, cpu, ["learned", str(form)]) for name, form in FORMS.items()}
        orb, _ = per_keypoint(plugin, program, cpu, ["orb"])
        result["cpus"][cpu] = {
            "learned_per_orientation": {name: n for name, (n, _) in learned.items()},
            "orb_per_orientation": round(orb / 2),
            "learned_forms_same_bytes": len({d for _, d in learned.values()}) == 1,
        }
    return result


def frame_subsets(images: Path, gt: Path, counts: tuple[int, int], work: Path) -> list[tuple[Path, Path]]:
    """For each count n: a folder linking the first n frames of `images` and their (n, n) ground truth."""
    import numpy as np

    frames = sorted(p for p in images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    truth = np.load(gt)
    subsets = []
    for n in counts:
        if n > len(frames):
            raise RuntimeError(f"{images} has {len(frames)} frames, fewer than {n}")
        folder = work / f"first{n}"
        (folder / "images").mkdir(parents=True)
        for f in frames[:n]:
            (folder / "images" / f.name).symlink_to(f.resolve())
        np.save(folder / "gt.npy", truth[:n, :n])
        subsets.append((folder / "images", folder / "gt.npy"))
    return subsets


def _board_python(board: Path, cpu: str, plugin: str | None = None) -> tuple[list[str], dict]:
    """The command (QEMU, with the counting plugin and its arguments if given, then the board's
    Python) and the environment that run Python as the board would, on one thread."""
    env = {"PYTHONPATH": f"{board / 'site'}:{REPO}:{REPO / 'runtime'}", "OMP_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1", "OPENCV_FOR_THREADS_NUM": "1", "PATH": "/usr/bin:/bin"}
    return ["qemu-aarch64", "-cpu", cpu, "-L", str(board / "sysroot"), *(["-plugin", plugin] if plugin else []),
            str(board / "sysroot" / "usr" / "bin" / "python3.11")], env


def by_library(blocks: str, maps: str) -> dict[str, int]:
    """Instructions by LIBRARIES of the plugin's per-block counts ("ADDRESS COUNT" lines, hexadecimal
    address) under a /proc/self/maps listing of the same process."""
    ranges = []
    for line in maps.splitlines():
        parts = line.split(maxsplit=5)
        if len(parts) == 6 and "x" in parts[1]:
            low, high = (int(v, 16) for v in parts[0].split("-"))
            ranges.append((low, high, parts[5]))
    ranges.sort()
    starts = [low for low, _, _ in ranges]
    totals = dict.fromkeys([name for name, _ in LIBRARIES] + ["other"], 0)
    for line in blocks.splitlines():
        address, n = line.split()
        at = int(address, 16)
        i = bisect.bisect_right(starts, at) - 1
        path = ranges[i][2] if i >= 0 and at < ranges[i][1] else ""
        totals[next((name for name, pattern in LIBRARIES if re.search(pattern, path)), "other")] += int(n)
    return totals


def check_board(board: Path) -> None:
    """Raises unless the board's Python loads this checkout's kernels built for aarch64."""
    command, env = _board_python(board, CPUS[0])
    probe = "from aefabmap_runtime.core.kernels import native; raise SystemExit(0 if native.available() else 1)"
    if subprocess.run([*command, "-c", probe], env=env, check=False, timeout=600).returncode != 0:
        raise RuntimeError("the kernels built for aarch64 are missing or stale: run deploy/check_aarch64.sh")


def emulated_eval(plugin: Path, board: Path, model: Path, images: Path, gt: Path, cpu: str,
                  exclude: int) -> tuple[int, dict[str, int]]:
    """Instructions of one emulated `aefabmap eval` (one thread; Python writes its bytecode caches),
    in all and by_library."""
    with tempfile.TemporaryDirectory() as scratch:
        blocks, maps = Path(scratch) / "blocks.txt", Path(scratch) / "maps.txt"
        command, env = _board_python(board, cpu, f"{plugin},blocks={blocks}")
        run = subprocess.run([*command, "-c", EVAL_LEAVING_MAPS, "eval", "--model", str(model),
                              "--images", str(images), "--gt", str(gt), "--exclude", str(exclude),
                              "--fabmap-score", "llr", "--no-progress"], env={**env, "MAPS_OUT": str(maps)},
                             capture_output=True, text=True, check=False, timeout=3600)
        found = re.search(r"instructions (\d+)", run.stderr)
        if run.returncode != 0 or found is None or not blocks.exists() or not maps.exists():
            raise RuntimeError(f"emulated eval of {model} failed: {run.stderr.strip()[-300:]}")
        return int(found.group(1)), by_library(blocks.read_text(), maps.read_text())


def eval_per_frame(plugin: Path, board: Path, model: Path, subsets: list[tuple[Path, Path]], cpu: str,
                   exclude: int) -> tuple[int, dict[str, int]]:
    """Instructions per frame of emulated `aefabmap eval` between the two subsets (after a run over
    the longer one has compiled every module it imports: neither count pays for compiling), in all
    and by_library."""
    emulated_eval(plugin, board, model, *subsets[1], cpu, exclude)
    (first, first_split), (last, last_split) = (emulated_eval(plugin, board, model, images, gt, cpu, exclude)
                                                for images, gt in subsets)
    frames = len(list(subsets[1][0].iterdir())) - len(list(subsets[0][0].iterdir()))
    return round((last - first) / frames), {name: round((last_split[name] - first_split[name]) / frames)
                                            for name in last_split}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the counts here")
    ap.add_argument("--board", type=Path, help="a deploy/check_aarch64.sh work folder: also count eval's frames")
    ap.add_argument("--model", type=Path, action="append", default=[], help="a bundle (repeat: one count each)")
    ap.add_argument("--images", type=Path, help="frames for eval, sorted by name")
    ap.add_argument("--gt", type=Path, help="their ground truth (N x N)")
    ap.add_argument("--frames", type=int, nargs=2, default=(30, 70), metavar=("A", "B"))
    ap.add_argument("--exclude", type=int, default=50, help="eval's exclusion window (frames)")
    args = ap.parse_args(argv)
    if args.board and not (args.model and args.images and args.gt and 0 < args.frames[0] < args.frames[1]):
        print("aarch64_instructions: --board needs --model, --images, --gt and frames 0 < A < B", file=sys.stderr)
        return 2
    try:
        with tempfile.TemporaryDirectory() as work:
            result = count(Path(work))
            if args.board:
                check_board(args.board)
                subsets = frame_subsets(args.images, args.gt, tuple(args.frames), Path(work))
                plugin = Path(work) / "libinsn.so"
                counted = {cpu: {str(m): eval_per_frame(plugin, args.board, m, subsets, cpu, args.exclude)
                                 for m in args.model} for cpu in CPUS}
                result["eval_frames"] = {
                    "images": str(args.images), "frames": list(args.frames),
                    "per_frame": {cpu: {m: n for m, (n, _) in per.items()} for cpu, per in counted.items()},
                    "per_frame_by_library": {cpu: {m: split for m, (_, split) in per.items()}
                                             for cpu, per in counted.items()}}
    except (Unavailable, RuntimeError, OSError, ValueError, subprocess.CalledProcessError,
            subprocess.TimeoutExpired) as e:
        print(f"aarch64_instructions: {e}", file=sys.stderr)
        return 1
    for cpu, figures in result["cpus"].items():
        orb = figures["orb_per_orientation"]
        print(f"{cpu}: ORB's tests {orb} instructions per keypoint and orientation")
        for name, n in figures["learned_per_orientation"].items():
            print(f"{cpu}: learned, {name:>12}: {n:6d} ({n / orb:.1f}x ORB's)")
        if not figures["learned_forms_same_bytes"]:
            print(f"{cpu}: the learned forms gave different descriptors!", file=sys.stderr)
    frames = result.get("eval_frames", {})
    for cpu, per_model in frames.get("per_frame", {}).items():
        for model, n in per_model.items():
            split = ", ".join(f"{name} {k / 1e6:.1f}" for name, k in frames["per_frame_by_library"][cpu][model].items())
            print(f"{cpu}: eval, {model}: {n / 1e6:.1f} million instructions per frame ({split})")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0 if all(f["learned_forms_same_bytes"] for f in result["cpus"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
