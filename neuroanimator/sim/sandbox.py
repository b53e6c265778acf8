"""MuJoCo compiles what users send in a process that can open no file.

Every model that did not come with the code (an upload, a model folder given to ``neuro train --mjcf``,
a stored artifact's MJCF) is parsed and compiled here, never in the caller's process:

- ``load_source(path, entry, limits)``: the child reads the source into memory (``bundle.read_source``),
  confines itself, then makes the bundle from those bytes (``bundle.bundle_files``);
- ``compile_xml(xml, assets)``: the child confines itself, then compiles the MJCF with its assets as
  MuJoCo's virtual file system.

The child confines itself with Linux Landlock (``landlock.deny_all``: no path can be opened, no TCP
port used), so whatever element of the MJCF names a file, and whatever MuJoCo does with it, only the
bytes it was given can be read. It also runs under ``Limits.compile_memory_bytes`` of address space and
``compile_seconds`` of CPU time (killed past it, or past ``WALL_FACTOR`` times that of wall-clock
time), at the lowest CPU priority, and only the compiled
model comes back (MuJoCo's binary MJB, loaded from memory), so a costly model costs the caller
nothing. Where the kernel has no Landlock the child still runs with those caps and says so
(``confined`` in the reply); a service that must not run unconfined refuses then (``require_landlock``).

Each child is forked from a fork server that has imported MuJoCo once (milliseconds, not the half
second of a new interpreter). The pipe carries frames: one JSON line (its ``blobs``: the byte lengths
of what follows), then the blobs; never pickles.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import json
import logging
import multiprocessing
import os
import resource
import signal
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal, NoReturn, NotRequired, TypedDict, cast

import mujoco
import numpy as np

from neuroanimator.sim import landlock
from neuroanimator.sim.bundle import (
    Asset,
    AssetKind,
    Bundle,
    Limits,
    SourceError,
    SourceFiles,
    SourceProblem,
    bundle_files,
    read_source,
)
from neuroanimator.sim.errors import ModelError

log = logging.getLogger(__name__)
MJB = "model.mjb"
CACHE_SIZE = 32
_CLONE_NEWUSER = 0x10000000
NICE = 19  # the child's niceness: a model compiling takes the CPU the services leave
WALL_FACTOR = 3.0  # wall-clock time per second of CPU a child may take (a loaded machine is slower)
MAX_REPLY = 1 << 30  # bytes of a child's reply (the MJB and the assets)
_cache: OrderedDict[str, bytes] = OrderedDict()
_cache_lock = threading.Lock()
_mp: Any = None
_mp_lock = threading.Lock()
_warned = False


class Unconfined(ModelError):
    """The sandbox cannot confine MuJoCo here (no Landlock) and the caller requires it."""


# ---------------------------------------------------------------------------- frames
class Work(TypedDict):
    """What the caller asks of a child: ``mode`` "source" reads and bundles ``path`` (with its
    ``entry``), "compile" compiles the blobs (the MJCF, then the files named by ``assets``)."""

    mode: Literal["source", "compile"]
    path: NotRequired[str]
    entry: NotRequired[str | None]
    assets: NotRequired[list[str]]


class Request(Work):
    """The caller's frame header: the work, the caps (``Limits`` as JSON), whether confinement is
    required, and the empty folder that becomes the child's root."""

    limits: dict[str, Any]  # asdict(Limits): the fields of Limits by name, read back by Limits(**limits)
    require_landlock: bool
    root: str


class AssetMeta(TypedDict):
    """An asset of a bundled source, as the child describes it (its bytes are a blob)."""

    name: str
    sha256: str
    kind: AssetKind
    source: str


class ReplyError(TypedDict):
    """Why a child could not do its work: a ``SourceError`` kind, or "unconfined"."""

    kind: SourceProblem | Literal["unconfined"]
    message: str


class Reply(TypedDict, total=False):
    """The child's frame header: for "source" the bundle (``xml`` to ``name``; the blobs are the
    assets' bytes, then the MJB) and ``confined``; for "compile" only ``confined`` (the blob is the
    MJB); or only ``error``."""

    xml: str
    entry: str
    files: list[str]
    assets: list[AssetMeta]
    name: str | None
    confined: bool
    error: ReplyError


def encode_frame(header: Request | Reply, blobs: Sequence[bytes] = ()) -> bytes:
    """One JSON line (with ``blobs``: the byte lengths of what follows), then the blobs. Never pickle:
    the child's reply is read by its caller, and a compromised child must not run code there."""
    head = json.dumps({**header, "blobs": [len(b) for b in blobs]}).encode() + b"\n"
    return b"".join([head, *blobs])


def decode_frame(frame: bytes) -> tuple[dict[str, object], list[bytes]]:
    """The JSON object of a frame's first line (``blobs`` taken out) and the blobs that follow it."""
    end = frame.index(b"\n")
    header = json.loads(frame[:end])
    blobs, at = [], end + 1
    for n in header.pop("blobs"):
        blobs.append(frame[at : at + int(n)])
        at += int(n)
    if at != len(frame):
        raise ValueError("the frame's blobs do not add up to its length")
    return header, blobs


def _decode_request(frame: bytes) -> tuple[Request, list[bytes]]:
    """A request frame, as ``encode_frame`` wrote it in the caller (read as such, not checked)."""
    header, blobs = decode_frame(frame)
    return cast(Request, header), blobs


def _decode_reply(frame: bytes) -> tuple[Reply, list[bytes]]:
    """A reply frame; not checked here: what the caller uses of it is (the assets' names and
    content in ``load_source``, the MJB by MuJoCo)."""
    header, blobs = decode_frame(frame)
    return cast(Reply, header), blobs


# ---------------------------------------------------------------------------- the caller's side
def available() -> bool:
    """Whether this kernel lets the sandbox confine MuJoCo (Linux Landlock)."""
    return landlock.abi_version() >= 1


def _run(work: Work, blobs: list[bytes], limits: Limits, require_landlock: bool) -> tuple[Reply, list[bytes]]:
    """Run one request in a fresh child; its reply, or ``SourceError`` (``too_costly`` when a cap
    stopped it)."""
    empty = tempfile.mkdtemp(prefix="neuro-sandbox-")  # the child's root: an empty folder
    request: Request = {**work, "limits": asdict(limits), "require_landlock": require_landlock, "root": empty}
    try:
        return _talk(request, blobs, limits)
    finally:
        with contextlib.suppress(OSError):
            os.rmdir(empty)


def _context() -> Any:
    """The fork server the children come from: one process per caller that has imported MuJoCo once,
    so a child starts in milliseconds instead of the half second an interpreter takes."""
    global _mp
    with _mp_lock:
        if _mp is None:
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload([__name__])
            _mp = ctx
    return _mp


def _talk(request: Request, blobs: list[bytes], limits: Limits) -> tuple[Reply, list[bytes]]:
    global _warned
    ctx = _context()
    mine, theirs = ctx.Pipe(duplex=True)
    proc = ctx.Process(target=_child, args=(theirs,), daemon=True, name="mujoco-sandbox")
    proc.start()
    theirs.close()
    out = _exchange(proc, mine, encode_frame(request, blobs), WALL_FACTOR * limits.compile_seconds + 5.0)
    mine.close()
    if out.reply is None:
        _no_reply(proc.exitcode, limits, out.timed_out and proc.exitcode != -signal.SIGXCPU)
    header, data = _decode_reply(out.reply)
    if "error" in header:
        kind, message = header["error"]["kind"], header["error"]["message"]
        if kind == "unconfined":
            raise Unconfined(message)
        raise SourceError(kind, message)
    if not header.get("confined") and not _warned:
        _warned = True
        log.warning("MuJoCo compiles models unconfined: this kernel has no Linux Landlock")
    return header, data


@dataclass
class _Exchanged:
    """What came of talking to a child: its reply frame, the error that ended the talk, and whether it
    ran out of time (or was still running with nothing said)."""

    reply: bytes | None = None
    error: BaseException | None = None
    timed_out: bool = False


def _exchange(proc: Any, conn: Any, frame: bytes, seconds: float) -> _Exchanged:
    """Send the request and read the reply within ``seconds`` (the child is killed past them)."""
    out = _Exchanged()

    def talk() -> None:
        try:
            conn.send_bytes(frame)
            if conn.poll(seconds):
                out.reply = conn.recv_bytes(MAX_REPLY)
        except (OSError, EOFError, ValueError) as exc:
            out.error = exc

    talker = threading.Thread(target=talk, daemon=True)
    talker.start()
    talker.join(seconds)
    if talker.is_alive() or out.reply is None:
        out.timed_out = talker.is_alive() or (out.error is None and proc.exitcode is None)
        proc.kill()
    proc.join(10)
    talker.join(1.0)
    return out


def _no_reply(exitcode: int | None, limits: Limits, waited_out: bool) -> NoReturn:
    """``SourceError`` for a child stopped by a cap (or crashed): which cap, and what to do.
    ``waited_out``: it was killed after ``WALL_FACTOR`` times its CPU cap in wall time without using
    the cap up: the machine was too busy to give the (lowest-priority) child its CPU."""
    if waited_out:
        raise SourceError(
            "too_costly",
            f"the model was not compiled within {WALL_FACTOR * limits.compile_seconds + 5.0:g} s: the "
            "machine is busy (a model compiles at the lowest priority); try again, or make it smaller",
        )
    if exitcode == -signal.SIGXCPU:
        raise SourceError(
            "too_costly",
            f"the model took more than {limits.compile_seconds:g} s of CPU to read and compile "
            "(COMPILE_SECONDS): refused; make it smaller (fewer bodies, smaller files, fewer replicas)",
        )
    log.warning("the model sandbox ended without a reply", extra={"exitcode": exitcode})
    why = "out of memory" if exitcode in (-6, -9, 1) else f"exit status {exitcode}"
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


def _serve(header: Request, blobs: list[bytes]) -> tuple[Reply, list[bytes]]:
    limits = Limits(**header["limits"])
    require = bool(header.get("require_landlock"))
    if header["mode"] == "source":
        sf: SourceFiles = read_source(header["path"], header.get("entry"), limits)
        confined = _confine(require, header.get("root"))
        bundle, m = bundle_files(sf, limits)
        meta: list[AssetMeta] = [
            {"name": a.name, "sha256": a.sha256, "kind": a.kind, "source": a.source} for a in bundle.assets
        ]
        reply: Reply = {
            "xml": bundle.xml,
            "entry": bundle.entry,
            "files": list(bundle.files),
            "assets": meta,
            "name": bundle.name,
            "confined": confined,
        }
        return reply, [*(a.data for a in bundle.assets), _mjb(m)]
    confined = _confine(require, header.get("root"))
    xml, *datas = blobs
    vfs = dict(zip(header["assets"], datas, strict=True))
    try:
        m = mujoco.MjModel.from_xml_string(xml.decode(), vfs or None)
    except Exception as exc:
        raise ModelError(f"malformed MJCF: {exc}") from exc
    return {"confined": confined}, [_mjb(m)]


def _child(conn: Any) -> None:
    """The child: one request from the pipe, one reply to it. It caps its memory and CPU time, lowers
    its priority, then (in ``_serve``) reads what it must and confines itself before MuJoCo parses."""
    header, blobs = _decode_request(conn.recv_bytes())
    limits = Limits(**header["limits"])
    resource.setrlimit(resource.RLIMIT_AS, (limits.compile_memory_bytes, limits.compile_memory_bytes))
    cpu = max(1, round(limits.compile_seconds))  # SIGXCPU past it, SIGKILL a second later
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 1))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    os.nice(NICE)
    reply: Reply
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
    conn.send_bytes(encode_frame(reply, data))
    conn.close()


def _memory_message(limits: Limits) -> str:
    return (
        f"the model could not be compiled within {limits.compile_memory_bytes >> 20:,} MiB of memory "
        "(COMPILE_MEMORY_MB): make it smaller"
    )


def load_bundle(path: str | Path, entry: str | None = None, limits: Limits | None = None) -> Bundle:
    """The bundle of an MJCF file, a model folder or an archive of one, made in the sandbox
    (``load_source`` without the compiled model)."""
    return load_source(path, entry, limits or Limits())[0]
