#!/usr/bin/env python
"""Instructions an aarch64 core executes to describe a keypoint: the learned descriptor's forms against ORB's tests.

No board is needed: the kernels are cross-built for aarch64 and run under QEMU user emulation
with a plugin that counts the guest's executed instructions (scripts/aarch64_instructions/).
Each count is the difference between runs at two repeat counts, per keypoint and call (the
learned descriptor: one orientation; ORB: oriented and upright in one call). Instructions are not
time: a core's speed per instruction differs between these forms. Needs aarch64-linux-gnu-gcc and
a dynamically linked qemu-aarch64 (Debian: gcc-aarch64-linux-gnu, qemu-user).

    python scripts/aarch64_instructions.py --json instructions.json
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent / "aarch64_instructions"
KERNELS = HERE.parents[1] / "runtime" / "aefabmap_runtime" / "core" / "kernels" / "kernels.c"
#: learned_describe's form numbers on aarch64 (kernels.c), named as native.LEARNED_FORMS names them.
FORMS = {"neon-dotprod": 3, "neon": 4, "plain": 5}
#: QEMU's CPU models: with the dot-product instructions (Raspberry Pi 5's core) and without (Pi 3's).
CPUS = ("cortex-a76", "cortex-a53")
KEYPOINTS = 1000


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


def executed(plugin: Path, program: Path, cpu: str, args: list[str]) -> tuple[int, str]:
    """Instructions the program executes on the CPU model, and its output (the descriptors' digest)."""
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the counts here")
    args = ap.parse_args(argv)
    try:
        with tempfile.TemporaryDirectory() as work:
            result = count(Path(work))
    except (Unavailable, RuntimeError, subprocess.CalledProcessError) as e:
        print(f"aarch64_instructions: {e}", file=sys.stderr)
        return 1
    for cpu, figures in result["cpus"].items():
        orb = figures["orb_per_orientation"]
        print(f"{cpu}: ORB's tests {orb} instructions per keypoint and orientation")
        for name, n in figures["learned_per_orientation"].items():
            print(f"{cpu}: learned, {name:>12}: {n:6d} ({n / orb:.1f}x ORB's)")
        if not figures["learned_forms_same_bytes"]:
            print(f"{cpu}: the learned forms gave different descriptors!", file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0 if all(f["learned_forms_same_bytes"] for f in result["cpus"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
