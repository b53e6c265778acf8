"""MuJoCo compiles what users send in a process that can open no file: ``python -m
neuroanimator.sim.sandbox``.

Every model that did not come with the code (an upload, a model folder given to ``neuro train --mjcf``,
a stored artifact's MJCF) is parsed and compiled here, never in the caller's process:

- ``load_source(path, entry, limits)``: the child reads the source into memory (``bundle.read_source``),
  confines itself, then makes the bundle from those bytes (``bundle.bundle_files``);
- ``compile_xml(xml, assets)``: the child confines itself, then compiles the MJCF with its assets as
  MuJoCo's virtual file system.

The child confines itself with Linux Landlock (``landlock.deny_all``: no path can be opened, no TCP
port used), so whatever element of the MJCF names a file, and whatever MuJoCo does with it, only the
bytes it was given can be read. It also runs under ``Limits.compile_memory_bytes`` of address space and
``compile_seconds`` of wall-clock time (killed past it), at a lower CPU priority, and only the compiled
model comes back (MuJoCo's binary MJB, loaded from memory), so a costly model costs the caller
nothing. Where the kernel has no Landlock the child still runs with those caps and says so
(``confined`` in the reply); a service that must not run unconfined refuses then (``require_landlock``).

The pipes carry frames: one JSON line (its ``blobs``: the byte lengths of what follows), then the blobs.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import json
import logging
import os
import resource
import subprocess
import sys
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import IO, Any

import mujoco
import numpy as np

from neuroanimator.sim import landlock
from neuroanimator.sim.bundle import (
    Asset,
    Bundle,
    Limits,
    SourceError,
    SourceFiles,
    bundle_files,
    read_source,
)
from neuroanimator.sim.errors import ModelError

log = logging.getLogger(__name__)
ROOT = Path(__file__).resolve().parents[2]
MJB = "model.mjb"
CACHE_SIZE = 32
_CLONE_NEWUSER = 0x10000000
NICE = 5  # the child's niceness above its caller's: a model compiling never slows the services
_cache: OrderedDict[str, bytes] = OrderedDict()
_cache_lock = threading.Lock()
_warned = False


class Unconfined(ModelError):
    """The sandbox cannot confine MuJoCo here (no Landlock) and the caller requires it."""


# ---------------------------------------------------------------------------- frames
def write_frame(out: IO[bytes], header: dict[str, Any], blobs: list[bytes] = ()) -> None:  # type: ignore[assignment]
    out.write(json.dumps({**header, "blobs": [len(b) for b in blobs]}).encode() + b"\n")
    for b in blobs:
        out.write(b)
    out.flush()


def read_frame(stream: IO[bytes], max_header: int = 1 << 24) -> tuple[dict[str, Any], list[bytes]]:
    line = stream.readline(max_header)
    if not line.endswith(b"\n"):
        raise EOFError("the frame ended early")
    header: dict[str, Any] = json.loads(line)
    blobs = []
    for n in header.pop("blobs"):
        data = stream.read(int(n))
        if len(data) != int(n):
            raise EOFError("the frame ended early")
        blobs.append(data)
    return header, blobs


# ---------------------------------------------------------------------------- the caller's side
def available() -> bool:
    """Whether this kernel lets the sandbox confine MuJoCo (Linux Landlock)."""
    return landlock.abi_version() >= 1


def _run(
    request: dict[str, Any], blobs: list[bytes], limits: Limits, require_landlock: bool
) -> tuple[dict[str, Any], list[bytes]]:
    """Run one request in a fresh child; its reply, or ``SourceError`` (``too_costly`` when a cap
    stopped it)."""
    empty = tempfile.mkdtemp(prefix="neuro-sandbox-")  # the child's root: an empty folder
    request = {**request, "limits": asdict(limits), "require_landlock": require_landlock, "root": empty}
    try:
        return _talk(request, blobs, limits)
    finally:
        with contextlib.suppress(OSError):
            os.rmdir(empty)


def _talk(request: dict[str, Any], blobs: list[bytes], limits: Limits) -> tuple[dict[str, Any], list[bytes]]:
    global _warned
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        "OMP_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
    }
    # stderr to a file, not a pipe: a chatty child never blocks on it
    with tempfile.TemporaryFile() as errors:
        proc = subprocess.Popen(
            [sys.executable, "-m", "neuroanimator.sim.sandbox"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=errors,
            env=env,
            cwd="/",
        )
        out = _exchange(proc, request, blobs, limits.compile_seconds)
        if "reply" not in out:
            errors.seek(0)
            _no_reply(proc, errors.read()[-4096:], limits, timed_out=bool(out.get("timed_out")))
    header, data = out["reply"]
    if "error" in header:
        kind, message = header["error"]["kind"], header["error"]["message"]
        if kind == "unconfined":
            raise Unconfined(message)
        raise SourceError(kind, message)
    if not header.get("confined") and not _warned:
        _warned = True
        log.warning("MuJoCo compiles models unconfined: this kernel has no Linux Landlock")
    return header, data


def _exchange(
    proc: subprocess.Popen[bytes], request: dict[str, Any], blobs: list[bytes], seconds: float
) -> dict[str, Any]:
    """Send the request and read the reply within ``seconds`` (the child is killed past them)."""
    out: dict[str, Any] = {}

    def talk() -> None:
        assert proc.stdin is not None and proc.stdout is not None
        try:
            write_frame(proc.stdin, request, blobs)
            proc.stdin.close()
            out["reply"] = read_frame(proc.stdout, 1 << 30)
        except (OSError, EOFError, ValueError) as exc:
            out["error"] = exc

    talker = threading.Thread(target=talk, daemon=True)
    talker.start()
    talker.join(seconds)
    if talker.is_alive() or "reply" not in out:
        out["timed_out"] = talker.is_alive()
        proc.kill()
    proc.wait()
    talker.join(1.0)
    return out


def _no_reply(proc: subprocess.Popen[bytes], err: bytes, limits: Limits, timed_out: bool) -> None:
    """``SourceError`` for a child stopped by a cap (or crashed): which cap, and what to do."""
    if timed_out:
        raise SourceError(
            "too_costly",
            f"the model took more than {limits.compile_seconds:g} s to read and compile "
            "(COMPILE_SECONDS): refused; make it smaller (fewer bodies, smaller files, fewer replicas)",
        )
    tail = err.decode(errors="replace").strip().splitlines()[-1:] if err else []
    why = (
        "out of memory"
        if proc.returncode in (-6, -9, 134, 137) or any("memory" in t.lower() for t in tail)
        else "it crashed"
    )
    log.warning("the model sandbox ended without a reply", extra={"rc": proc.returncode, "stderr": tail})
    raise SourceError(
        "too_costly",
        f"the model could not be compiled within {limits.compile_memory_bytes >> 20:,} MiB of memory "
        f"(COMPILE_MEMORY_MB): MuJoCo stopped ({why}); make it smaller",
    )


def _model_of(mjb: bytes) -> mujoco.MjModel:
    return mujoco.MjModel.from_binary_path(MJB, {MJB: mjb})


def required() -> bool:
    """Whether this process (and what it starts) must refuse to compile unconfined: ``REQUIRE_LANDLOCK``
    in the environment (the trainer's services set it from their settings)."""
    return os.environ.get("REQUIRE_LANDLOCK", "").strip().lower() in ("1", "true", "yes")


def load_source(
    path: str | Path, entry: str | None, limits: Limits, require_landlock: bool | None = None
) -> tuple[Bundle, mujoco.MjModel]:
    """The bundle of a source (``bundle`` tells how it is read) and its compiled model, made in a child
    that can read nothing else (``Unconfined`` where Landlock is missing and ``require_landlock``,
    by default ``required()``)."""
    require_landlock = required() if require_landlock is None else require_landlock
    src = Path(path).absolute()
    header, blobs = _run({"mode": "source", "path": str(src), "entry": entry}, [], limits, require_landlock)
    *datas, mjb = blobs
    assets = tuple(
        Asset(a["name"], a["sha256"], a["kind"], a["source"], d)
        for a, d in zip(header["assets"], datas, strict=True)
    )
    for a in assets:  # the child's word is checked: the names are the content's
        if hashlib.sha256(a.data).hexdigest() != a.sha256 or not a.name.startswith(a.sha256):
            raise SourceError(
                "compile_error", f"the sandbox returned an asset that is not its content: {a.name}"
            )
    bundle = Bundle(
        xml=header["xml"],
        assets=assets,
        entry=header["entry"],
        files=tuple(header["files"]),
        name=header.get("name"),
    )
    return bundle, _model_of(mjb)


def compile_xml(
    xml: str, assets: Mapping[str, bytes] | None = None, limits: Limits | None = None
) -> mujoco.MjModel:
    """An MJCF compiled in the sandbox with ``assets`` as its files (and nothing else); the same MJCF and
    assets compile once per process (the last ``CACHE_SIZE`` are kept)."""
    assets = dict(assets or {})
    h = hashlib.sha256(xml.encode())
    for name in sorted(assets):
        h.update(name.encode() + b"\0" + hashlib.sha256(assets[name]).digest())
    key = h.hexdigest()
    with _cache_lock:
        mjb = _cache.get(key)
        if mjb is not None:
            _cache.move_to_end(key)
    if mjb is None:
        names = sorted(assets)
        _, blobs = _run(
            {"mode": "compile", "assets": names},
            [xml.encode(), *(assets[n] for n in names)],
            limits or Limits(),
            required(),
        )
        mjb = blobs[0]
        with _cache_lock:
            _cache[key] = mjb
            while len(_cache) > CACHE_SIZE:
                _cache.popitem(last=False)
    return _model_of(mjb)


# ---------------------------------------------------------------------------- the child
def _mjb(m: mujoco.MjModel) -> bytes:
    buf = np.zeros(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, buf)
    return buf.tobytes()


def _empty_root(folder: str | None) -> bool:
    """Make ``folder`` (empty) this process's root, so that no path outside the given files even exists:
    MuJoCo's messages then cannot tell a server's file that exists from one that does not (Landlock
    stops the reading, not ``stat``). Root may ``chroot``; other users first enter a user namespace of
    their own, where Linux allows it. Best effort: False where neither is allowed."""
    if not folder:
        return False
    try:
        if os.geteuid() != 0:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.unshare(_CLONE_NEWUSER) != 0:
                return False
        os.chroot(folder)
        os.chdir("/")
        return True
    except OSError:
        return False


def _confine(require: bool, empty: str | None = None) -> bool:
    _empty_root(empty)
    try:
        landlock.deny_all()
        return True
    except landlock.Unavailable as exc:
        if require:
            raise Unconfined(
                f"models are compiled only where MuJoCo can be confined, and this server cannot: {exc}"
            ) from exc
        return False


def _serve(header: dict[str, Any], blobs: list[bytes]) -> tuple[dict[str, Any], list[bytes]]:
    limits = Limits(**header["limits"])
    require = bool(header.get("require_landlock"))
    if header["mode"] == "source":
        sf: SourceFiles = read_source(header["path"], header.get("entry"), limits)
        confined = _confine(require, header.get("root"))
        bundle, m = bundle_files(sf, limits)
        meta = [
            {"name": a.name, "sha256": a.sha256, "kind": a.kind, "source": a.source} for a in bundle.assets
        ]
        reply: dict[str, Any] = {
            "xml": bundle.xml,
            "entry": bundle.entry,
            "files": list(bundle.files),
            "assets": meta,
        }
        reply |= {"name": bundle.name}
        return {**reply, "confined": confined}, [*(a.data for a in bundle.assets), _mjb(m)]
    confined = _confine(require, header.get("root"))
    xml, *datas = blobs
    vfs = dict(zip(header["assets"], datas, strict=True))
    try:
        m = mujoco.MjModel.from_xml_string(xml.decode(), vfs or None)
    except Exception as exc:
        raise ModelError(f"malformed MJCF: {exc}") from exc
    return {"confined": confined}, [_mjb(m)]


def main() -> int:
    """The child: one request on stdin, one reply on stdout."""
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing but the reply on the pipe
    header, blobs = read_frame(stdin, 1 << 30)
    limits = Limits(**header["limits"])
    resource.setrlimit(resource.RLIMIT_AS, (limits.compile_memory_bytes, limits.compile_memory_bytes))
    cpu = int(limits.compile_seconds) + 1
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 1))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    os.nice(NICE)
    try:
        reply, data = _serve(header, blobs)
    except Unconfined as exc:
        reply, data = {"error": {"kind": "unconfined", "message": str(exc)}}, []
    except SourceError as exc:
        reply, data = {"error": {"kind": exc.kind, "message": str(exc)}}, []
    except ModelError as exc:
        reply, data = {"error": {"kind": "compile_error", "message": str(exc)}}, []
    except MemoryError:
        reply, data = {"error": {"kind": "too_costly", "message": _memory_message(limits)}}, []
    write_frame(stdout, reply, data)
    return 0


def _memory_message(limits: Limits) -> str:
    return (
        f"the model could not be compiled within {limits.compile_memory_bytes >> 20:,} MiB of memory "
        "(COMPILE_MEMORY_MB): make it smaller"
    )


if __name__ == "__main__":
    sys.exit(main())
