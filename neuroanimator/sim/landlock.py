"""Linux Landlock through its three system calls: a process that can open no file and make no TCP
connection from now on.

Why Landlock: it needs no privilege (no root, no user namespaces, no setuid helper), works inside
containers, and restricts a process *and everything it later starts* in the kernel, whatever library
does the opening (MuJoCo's C++ parser included). An empty ruleset that handles every filesystem right
denies every ``open`` of a path; files already open (the pipes to the parent) keep working. Landlock has
been in Linux since 5.13 (ABI 1); newer ABIs add rights (rename across folders, truncate, device ioctls,
TCP, signals and abstract sockets), and ``deny_all`` handles every right the running kernel knows.

Shapes of the kernel's structures: ``struct landlock_ruleset_attr {u64 handled_access_fs;
u64 handled_access_net; u64 scoped;}``, passed with the size of the fields the ABI knows.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

# The generic syscall numbers (the same on x86_64 and aarch64).
_CREATE_RULESET, _RESTRICT_SELF = 444, 446
_CREATE_RULESET_VERSION = 1
_PR_SET_NO_NEW_PRIVS = 38

# Filesystem rights by the ABI that introduced them.
_FS_RIGHTS = {1: (1 << 13) - 1, 2: 1 << 13, 3: 1 << 14, 5: 1 << 15}
_NET_RIGHTS = 0b11  # ABI 4: bind and connect TCP
_SCOPES = 0b11  # ABI 6: abstract UNIX sockets and signals outside the sandbox


class Unavailable(OSError):
    """The kernel (or the container's seccomp filter) offers no Landlock."""


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def abi_version() -> int:
    """The Landlock ABI the running kernel offers; 0 where there is none (not Linux, too old, or
    disabled at boot or by a seccomp filter)."""
    if platform.system() != "Linux" or platform.machine() not in ("x86_64", "aarch64"):
        return 0
    libc = _libc()
    version = libc.syscall(
        _CREATE_RULESET, None, ctypes.c_size_t(0), ctypes.c_uint32(_CREATE_RULESET_VERSION)
    )
    return max(0, int(version))


def deny_all() -> int:
    """Restrict this process and its future children: no path can be opened (read, written, listed,
    executed, created or removed), no TCP port bound or connected, no signal sent outside. Call it in a
    process with one thread (Landlock restricts the calling thread and what it starts). Returns the ABI
    used; ``Unavailable`` where Landlock is missing."""
    abi = abi_version()
    if abi < 1:
        raise Unavailable("Linux Landlock is not available (Linux 5.13 or newer, with Landlock enabled)")
    fs = sum(bits for since, bits in _FS_RIGHTS.items() if abi >= since)
    fields = [fs]
    if abi >= 4:
        fields.append(_NET_RIGHTS)
    if abi >= 6:
        fields.append(_SCOPES)
    attr = (ctypes.c_uint64 * len(fields))(*fields)
    libc = _libc()
    fd = int(libc.syscall(_CREATE_RULESET, ctypes.byref(attr), ctypes.c_size_t(ctypes.sizeof(attr)), 0))
    if fd < 0:
        err = ctypes.get_errno()
        raise Unavailable(err, f"landlock_create_ruleset: {os.strerror(err)}")
    try:
        if libc.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"prctl(PR_SET_NO_NEW_PRIVS): {os.strerror(err)}")
        if libc.syscall(_RESTRICT_SELF, fd, 0) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"landlock_restrict_self: {os.strerror(err)}")
    finally:
        os.close(fd)
    return abi
