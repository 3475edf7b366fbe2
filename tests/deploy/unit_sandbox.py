"""Run a command under the restrictions of deploy/aefabmap.service that a process can put on itself.

systemd is not running here (nor in CI containers), so this applies, with libseccomp, the same
kernel filters systemd installs for the unit: NoNewPrivileges=, SystemCallFilter= (an allow list;
other calls fail with EPERM as SystemCallErrorNumber=EPERM says; other architectures are killed, as
SystemCallArchitectures=native) and MemoryDenyWriteExecute= (systemd's seccomp rules: no mapping
both writable and executable, no mprotect/pkey_mprotect adding PROT_EXEC, no SHM_EXEC). Children
inherit the filters.

Usage: python unit_sandbox.py --allow @system-service [--deny @privileged ...] -- COMMAND [ARG...]
Group names are expanded with `systemd-analyze syscall-filter`.
"""

from __future__ import annotations

import argparse
import ctypes
import errno
import os
import subprocess
import sys

SCMP_ACT_ALLOW = 0x7FFF0000
SCMP_CMP_MASKED_EQ = 7
PROT_WRITE, PROT_EXEC = 0x2, 0x4
SHM_EXEC = 0o100000
PR_SET_NO_NEW_PRIVS = 38


def scmp_act_errno(code: int) -> int:
    return 0x00050000 | (code & 0xFFFF)


class ScmpArgCmp(ctypes.Structure):
    _fields_ = [("arg", ctypes.c_uint), ("op", ctypes.c_int), ("datum_a", ctypes.c_uint64), ("datum_b", ctypes.c_uint64)]


def _libseccomp() -> ctypes.CDLL:
    lib = ctypes.CDLL("libseccomp.so.2", use_errno=True)
    lib.seccomp_init.restype = ctypes.c_void_p
    lib.seccomp_init.argtypes = [ctypes.c_uint32]
    lib.seccomp_rule_add_array.argtypes = [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int, ctypes.c_uint,
                                           ctypes.POINTER(ScmpArgCmp)]
    lib.seccomp_syscall_resolve_name.argtypes = [ctypes.c_char_p]
    lib.seccomp_load.argtypes = [ctypes.c_void_p]
    lib.seccomp_release.argtypes = [ctypes.c_void_p]
    return lib


def expand_group(entry: str, seen: set[str] | None = None) -> set[str]:
    """System-call names of a systemd group such as @system-service (recursively), or {entry}."""
    if not entry.startswith("@"):
        return {entry}
    seen = set() if seen is None else seen
    if entry in seen:
        return set()
    seen.add(entry)
    out = subprocess.run(["systemd-analyze", "syscall-filter", entry], check=True, capture_output=True, text=True)
    names: set[str] = set()
    for line in out.stdout.splitlines()[1:]:
        word = line.strip()
        if word and not word.startswith("#"):
            names |= expand_group(word, seen)
    return names


def _add(lib: ctypes.CDLL, ctx: int, action: int, name: str, *cmps: tuple[int, int, int]) -> None:
    nr = lib.seccomp_syscall_resolve_name(name.encode())
    if nr < 0:  # not a system call of this architecture (e.g. mmap2 on 64-bit)
        return
    array = (ScmpArgCmp * len(cmps))(*(ScmpArgCmp(a, SCMP_CMP_MASKED_EQ, m, v) for a, m, v in cmps)) if cmps else None
    rc = lib.seccomp_rule_add_array(ctx, action, nr, len(cmps), array)
    if rc < 0:
        raise OSError(-rc, f"seccomp_rule_add {name}: {os.strerror(-rc)}")


def _load(lib: ctypes.CDLL, ctx: int) -> None:
    rc = lib.seccomp_load(ctx)
    lib.seccomp_release(ctx)
    if rc < 0:
        raise OSError(-rc, f"seccomp_load: {os.strerror(-rc)}")


def apply(allow: list[str], deny: list[str]) -> None:
    """Install both filters on this process (irreversible)."""
    allowed = set().union(*(expand_group(g) for g in allow)) - set().union(*(expand_group(g) for g in deny))
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_NO_NEW_PRIVS)")
    lib = _libseccomp()

    # The write-execute filter first: once the allow list is loaded, seccomp() itself is denied.
    deny_eperm = scmp_act_errno(errno.EPERM)
    ctx = lib.seccomp_init(SCMP_ACT_ALLOW)
    for name in ("mmap", "mmap2"):
        _add(lib, ctx, deny_eperm, name, (2, PROT_WRITE | PROT_EXEC, PROT_WRITE | PROT_EXEC))
    for name in ("mprotect", "pkey_mprotect"):
        _add(lib, ctx, deny_eperm, name, (2, PROT_EXEC, PROT_EXEC))
    _add(lib, ctx, deny_eperm, "shmat", (2, SHM_EXEC, SHM_EXEC))
    _load(lib, ctx)

    ctx = lib.seccomp_init(scmp_act_errno(errno.EPERM))
    for name in sorted(allowed):
        _add(lib, ctx, SCMP_ACT_ALLOW, name)
    _load(lib, ctx)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--allow", action="append", required=True, help="system calls or @groups to allow")
    p.add_argument("--deny", action="append", default=[], help="system calls or @groups removed from --allow")
    p.add_argument("command", nargs=argparse.REMAINDER)
    args = p.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        p.error("no command")
    apply(args.allow, args.deny)
    os.execvp(command[0], command)
    return 127  # not reached


if __name__ == "__main__":
    sys.exit(main())
