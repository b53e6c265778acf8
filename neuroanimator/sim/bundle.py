"""A model as users ship it -> a self-contained ``Bundle``: one MJCF and the asset files it uses.

A source is an MJCF file, a folder that holds the model, or a ``.zip`` / ``.tar.gz`` / ``.tgz`` of
such a folder. It is read in two steps, in the sandbox's process (``sandbox``):

1. ``read_source`` (before the process is confined) takes the source's files into memory: an archive's
   members under the caps of ``Limits`` (checked while extracting: its headers are not trusted), a
   folder's files, or a plain file with the files of its folder. Nothing is written to disk.
2. ``bundle_files`` (once the process can open no path at all) gives MuJoCo those files as its virtual
   file system and parses the entry (named by ``entry``: its path inside, or a file name found once; or
   the only MJCF that no other includes). Whatever the MJCF asks to read (``<include>``, meshes,
   textures, height fields, skins, ``<flexcomp file>``, sub-models, and what later MuJoCo versions add)
   is read from those files or not at all: the kernel, not a list of elements, draws that boundary. A
   file named outside them is refused alike whether it exists on the server or not.

The bundle's MJCF is MuJoCo's own (``MjSpec.to_xml``: no includes, no directories) and names each asset
by its content, ``<sha256><extension>``; with the assets as a virtual file system it compiles with
nothing else. Every problem is a ``SourceError`` whose ``kind`` says which (for a service to map to a
status) and whose message names the file by its path inside the source, never a server path.
"""

from __future__ import annotations

import hashlib
import os
import posixpath
import re
import stat
import struct
import tarfile
import xml.etree.ElementTree as ET
import zipfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import IO, Any, Literal
from xml.parsers import expat

import mujoco

from neuroanimator.sim.errors import ModelError

SourceProblem = Literal[
    "not_found",
    "not_xml",
    "compile_error",
    "missing_file",
    "outside_model",
    "unsafe_archive",
    "archive_too_large",
    "file_too_large",
    "mesh_too_large",
    "plugin_refused",
    "entry",
    "bad_timestep",
    "too_costly",
]
AssetKind = Literal["mesh", "texture", "hfield", "skin"]
ARCHIVE_SUFFIXES = (".zip", ".tar.gz", ".tgz")
MESH_TYPES = (".stl", ".obj", ".msh")
FIRST_PARTY_PLUGIN = "mujoco."  # MuJoCo's own plugins: mujoco.elasticity.cable, mujoco.pid, ...
MAX_NAME_BYTES = 255  # one path component, as Linux allows
MAX_PATH_BYTES = 1024  # a whole path inside a source
_MiB = 1 << 20


class SourceError(ModelError):
    """A model source that cannot become a bundle; ``kind`` says which problem, the message names it."""

    def __init__(self, kind: SourceProblem, message: str) -> None:
        super().__init__(message)
        self.kind: SourceProblem = kind

    def __reduce__(self) -> tuple[type[SourceError], tuple[SourceProblem, str]]:
        # raised in a worker process (a seed, a compile), it reaches the parent whole
        return type(self), (self.kind, str(self))


@dataclass(frozen=True)
class Limits:
    """Caps on what a source may hold and cost. An archive's files are counted (folders too) and
    measured while extracting, against the archive's own size for the compression ratio; compiling
    runs in a process with ``compile_seconds`` of CPU time and ``compile_memory_bytes`` of
    address space (``sandbox``)."""

    max_bytes: int = 256 * _MiB  # everything extracted from an archive (or read from a folder)
    max_files: int = 5000  # files and folders in an archive (files in a folder)
    max_ratio: float = 100.0  # extracted bytes per archive byte ...
    ratio_from: int = 4 * _MiB  # ... checked once this much is extracted (small text compresses well)
    max_file_bytes: int = 64 * _MiB  # one asset file
    max_xml_bytes: int = 8 * _MiB  # one .xml file (MuJoCo's parser takes ~50 bytes of memory per byte)
    max_mesh_vertices: int = 200_000  # one mesh
    min_timestep: float = 1e-4  # seconds: below, a second of motion is over 10,000 MuJoCo steps
    compile_seconds: float = 10.0
    compile_memory_bytes: int = 2048 * _MiB


@dataclass(frozen=True)
class Asset:
    """One file the model uses, named by its content: ``name`` = ``<sha256><extension>``."""

    name: str
    sha256: str
    kind: AssetKind
    source: str  # where it was found, relative to the entry's folder (else to the model's folder)
    data: bytes = field(repr=False)


@dataclass(frozen=True)
class Bundle:
    """A model and the assets it uses: ``xml`` compiles with ``vfs()`` and nothing else."""

    xml: str
    assets: tuple[Asset, ...]
    entry: str  # the entry XML, relative to the model's folder (for messages)
    files: tuple[str, ...]  # the XML files it was made of: the entry, then its includes
    name: str | None = None  # the entry's ``model`` attribute, if it has one

    def vfs(self) -> dict[str, bytes]:
        """The assets as MuJoCo's virtual file system: ``MjModel.from_xml_string(xml, vfs)``."""
        return {a.name: a.data for a in self.assets}


@dataclass
class SourceFiles:
    """A source's files in memory, by their path inside it (``/``-separated, no ``..``)."""

    files: dict[str, bytes]
    entry: str | None  # as the caller named it
    label: str  # for messages: "archive 'm.zip'", "folder 'tinybot'", "'pend.xml'"
    plain: str | None = None  # the entry of a plain-file source


# ---------------------------------------------------------------------------- archives
def _archive_kind(name: str) -> str | None:
    lower = name.lower()
    if lower.endswith(".zip"):
        return "zip"
    if lower.endswith((".tar.gz", ".tgz")):
        return "tar"
    return None


def _member_path(name: str, archive: str) -> str | None:
    """The relative path an archive member extracts to; None for the archive's own folder."""
    if "\\" in name or "\x00" in name:
        raise SourceError("unsafe_archive", f"{archive}: entry {name!r} has a backslash or NUL in its name")
    p = PurePosixPath(name)
    if p.is_absolute() or re.match(r"^[A-Za-z]:", name):
        raise SourceError("unsafe_archive", f"{archive}: entry {name!r} is an absolute path")
    if ".." in p.parts:
        raise SourceError("unsafe_archive", f"{archive}: entry {name!r} climbs out of the archive ('..')")
    parts = [s for s in p.parts if s not in ("", ".")]
    if len(name.encode()) > MAX_PATH_BYTES or any(len(s.encode()) > MAX_NAME_BYTES for s in parts):
        raise SourceError(
            "unsafe_archive",
            f"{archive}: entry {name[:60]!r}... has a name over {MAX_NAME_BYTES} bytes or a path over "
            f"{MAX_PATH_BYTES} bytes",
        )
    return "/".join(parts) if parts else None


class _Extractor:
    """Reads members into memory while counting files, folders and bytes against ``Limits``."""

    def __init__(self, name: str, size: int, limits: Limits) -> None:
        self.name = name
        self.size = max(1, size)
        self.limits = limits
        self.entries = 0
        self.bytes = 0
        self.files: dict[str, bytes] = {}
        self.folders: set[str] = set()

    def count(self) -> None:
        self.entries += 1
        if self.entries > self.limits.max_files:
            raise SourceError(
                "archive_too_large", f"{self.name}: more than {self.limits.max_files} files and folders"
            )

    def folder(self, rel: str) -> None:
        self.count()
        if rel in self.files:
            raise SourceError("unsafe_archive", f"{self.name}: {rel} is both a file and a folder")
        self.folders.add(rel)

    def add(self, rel: str, stream: IO[bytes], declared: int) -> None:
        lim = self.limits
        self.count()
        # an MJCF is parsed whole by MuJoCo (about 50 bytes of memory per byte): its own, smaller cap
        cap = lim.max_xml_bytes if rel.lower().endswith(".xml") else lim.max_file_bytes
        if declared > cap:
            raise SourceError(
                "file_too_large", f"{self.name}: {rel} is {declared:,} bytes; one such file may have {cap:,}"
            )
        if rel in self.files:
            raise SourceError("unsafe_archive", f"{self.name}: {rel} appears twice")
        parents = {"/".join(rel.split("/")[:i]) for i in range(1, rel.count("/") + 1)}
        if (
            rel in self.folders
            or any(p in self.files for p in parents)
            or any(f.startswith(rel + "/") for f in self.files)
        ):
            raise SourceError("unsafe_archive", f"{self.name}: {rel} is both a file and a folder")
        chunks: list[bytes] = []
        written = 0
        while chunk := stream.read(1 << 16):
            written += len(chunk)
            self.bytes += len(chunk)
            if written > cap:
                raise SourceError(
                    "file_too_large", f"{self.name}: {rel} is over {cap:,} bytes once extracted"
                )
            if self.bytes > lim.max_bytes:
                raise SourceError(
                    "archive_too_large", f"{self.name}: more than {lim.max_bytes:,} bytes once extracted"
                )
            if self.bytes > lim.ratio_from and self.bytes > lim.max_ratio * self.size:
                raise SourceError(
                    "archive_too_large",
                    f"{self.name}: extracts to over {lim.max_ratio:g} times its own size "
                    f"({self.size:,} bytes); refused as a compression bomb",
                )
            chunks.append(chunk)
        self.files[rel] = b"".join(chunks)
        self.folders.update(parents)


def extract(archive: Path, limits: Limits) -> dict[str, bytes]:
    """A .zip's or .tar.gz's files, by path, in memory: plain files and folders only (no links,
    devices, absolute paths, ``..``, encrypted members, a name both a file and a folder), within
    ``limits``. Raises ``SourceError``."""
    ex = _Extractor(archive.name, archive.stat().st_size, limits)
    if _archive_kind(archive.name) == "zip":
        try:
            with zipfile.ZipFile(archive) as zf:
                for info in zf.infolist():
                    rel = _member_path(info.filename, archive.name)
                    if stat.S_ISLNK(info.external_attr >> 16):
                        raise SourceError(
                            "unsafe_archive", f"{archive.name}: entry {info.filename!r} is a link"
                        )
                    if info.flag_bits & 0x1:
                        raise SourceError(
                            "unsafe_archive",
                            f"{archive.name}: entry {info.filename!r} is encrypted; upload an unencrypted archive",
                        )
                    if rel is None:
                        continue
                    if info.is_dir():
                        ex.folder(rel)
                        continue
                    with zf.open(info) as stream:
                        ex.add(rel, stream, info.file_size)
        except SourceError:
            raise
        except Exception as exc:  # a damaged zip makes zipfile raise anything: its errors, zlib's, seeks
            raise SourceError(
                "unsafe_archive", f"{archive.name}: not a readable zip archive ({exc})"
            ) from exc
        return ex.files
    try:
        with tarfile.open(archive, mode="r|gz") as tf:
            for member in tf:
                rel = _member_path(member.name, archive.name)
                if member.isdir():
                    if rel is not None:
                        ex.folder(rel)
                    continue
                if not member.isfile():
                    what = "a link" if member.issym() or member.islnk() else "not a plain file"
                    raise SourceError("unsafe_archive", f"{archive.name}: entry {member.name!r} is {what}")
                if rel is None:
                    continue
                content = tf.extractfile(member)
                if content is not None:
                    ex.add(rel, content, member.size)
    except SourceError:
        raise
    except (
        Exception
    ) as exc:  # a damaged tar.gz makes tarfile raise anything (an OverflowError in a pax header)
        raise SourceError(
            "unsafe_archive", f"{archive.name}: not a readable .tar.gz archive ({exc})"
        ) from exc
    return ex.files


def _folder_files(root: Path, limits: Limits, label: str) -> dict[str, bytes]:
    """The plain files under ``root`` (links that leave it are left out), within ``limits``."""
    out: dict[str, bytes] = {}
    total = 0
    real_root = os.path.realpath(root)
    for folder, dirs, names in os.walk(root):
        dirs.sort()
        for name in sorted(names):
            path = Path(folder) / name
            real = os.path.realpath(path)
            if not real.startswith(real_root + os.sep) or not os.path.isfile(real):
                continue
            if len(out) >= limits.max_files:
                raise SourceError(
                    "archive_too_large",
                    f"{label} holds more than {limits.max_files} files: give a folder that holds the model only",
                )
            size = os.path.getsize(real)
            total += size
            if size > limits.max_file_bytes or total > limits.max_bytes:
                if size > limits.max_file_bytes and name.lower().endswith(".xml"):
                    raise SourceError(
                        "file_too_large",
                        f"{path.relative_to(root).as_posix()} is {size:,} bytes; one file may have "
                        f"{limits.max_file_bytes:,}",
                    )
                continue  # too large to be the model's; MuJoCo finds it missing if it is used
            out[path.relative_to(root).as_posix()] = Path(real).read_bytes()
    return out


def read_source(path: str | Path, entry: str | None, limits: Limits) -> SourceFiles:
    """A source's files in memory (see the module's text); reads nothing but ``path`` (and, for a
    folder or a plain file, the files under its folder)."""
    src = Path(path)
    if not src.exists():
        raise SourceError("not_found", f"{src.name!r} does not exist")
    if src.is_dir():
        label = f"folder {src.name!r}"
        return SourceFiles(_folder_files(src, limits, label), entry, label)
    if _archive_kind(src.name) is not None:
        return SourceFiles(extract(src, limits), entry, f"archive {src.name!r}")
    if entry is not None:
        raise SourceError(
            "entry", f"--entry names a file inside a folder or an archive; {src.name!r} is a file"
        )
    size = src.stat().st_size
    if size > limits.max_xml_bytes:
        raise SourceError(
            "file_too_large", f"{src.name} is {size:,} bytes; an MJCF file may have {limits.max_xml_bytes:,}"
        )
    folder = src.resolve().parent
    files = _folder_files(folder, limits, f"the folder of {src.name!r}")
    files[src.name] = src.read_bytes()
    return SourceFiles(files, None, repr(src.name), plain=src.name)


# ---------------------------------------------------------------------------- the entry
def _is_mjcf(data: bytes) -> bool:
    return b"<mujoco" in data[:4096]


def _parse(files: dict[str, bytes], name: str) -> ET.Element:
    try:
        return ET.fromstring(files[name])
    except ET.ParseError as exc:  # its message ends with the line and column
        raise SourceError("not_xml", f"{name} is not XML: {exc}") from exc


def _find_entry(sf: SourceFiles) -> str:
    files = sf.files
    if sf.plain is not None:
        return sf.plain
    mjcfs = sorted(n for n, data in files.items() if n.lower().endswith(".xml") and _is_mjcf(data))
    listed = ", ".join(mjcfs[:10]) or "none"
    if sf.entry is not None:
        rel = PurePosixPath(sf.entry.replace("\\", "/"))
        if rel.is_absolute() or ".." in rel.parts:
            raise SourceError("entry", f"the entry {sf.entry!r} must be a path inside {sf.label}")
        if rel.as_posix() in files:
            return rel.as_posix()
        named = [n for n in mjcfs if PurePosixPath(n).name == rel.name]
        if len(named) == 1:
            return named[0]
        raise SourceError(
            "entry",
            f"{sf.label} has no MJCF {sf.entry!r}"
            + (" (several by that name)" if named else f"; its MJCF files: {listed}"),
        )
    included = set()
    for n in mjcfs:
        try:
            tree = ET.fromstring(files[n])
        except ET.ParseError:
            continue
        for inc in tree.iter("include"):
            included.add(posixpath.normpath(posixpath.join(posixpath.dirname(n), inc.get("file", ""))))
    tops = [n for n in mjcfs if n not in included]
    if len(tops) == 1:
        return tops[0]
    if not tops:
        raise SourceError("entry", f"{sf.label} holds no MJCF file (an XML whose root element is <mujoco>)")
    raise SourceError(
        "entry", f"{sf.label} holds several MJCF files ({listed}): name the entry (--entry FILE)"
    )


def _lookup(files: dict[str, bytes], folder: str, name: str) -> str | None:
    """The key of ``name`` (relative to ``folder``) among the source's files, or None."""
    if not name or name.startswith("/") or re.match(r"^[A-Za-z]:", name):
        return None
    key = posixpath.normpath(posixpath.join(folder, name.replace("\\", "/")))
    return key if key in files and not key.startswith("../") else None


def _xml_files(entry: str, files: dict[str, bytes]) -> list[str]:
    """The entry and the files it includes, as far as they are among the source's files (for messages
    and the plugin check only: MuJoCo decides what it reads, from the same files)."""
    out, queue = [entry], [entry]
    while queue:
        name = queue.pop(0)
        try:
            tree = ET.fromstring(files[name])
        except ET.ParseError:
            continue
        _check_plugins(tree, name)
        for inc in [*tree.iter("include"), *(m for a in tree.iter("asset") for m in a.iter("model"))]:
            found = _lookup(files, posixpath.dirname(entry), inc.get("file", "")) or _lookup(
                files, posixpath.dirname(name), inc.get("file", "")
            )
            if found and found not in out:
                out.append(found)
                queue.append(found)
    return out


def _check_plugins(tree: ET.Element, where: str) -> None:
    """Plugins are native code from shared libraries: only MuJoCo's own are accepted. A ``<plugin>``
    without a ``plugin`` attribute uses an instance, declared (and checked) under ``<extension>``."""
    for el in tree.iter("plugin"):
        name = el.get("plugin")
        if name is not None and not name.startswith(FIRST_PARTY_PLUGIN):
            raise SourceError(
                "plugin_refused",
                f"{where}: plugin {name!r} is not one of MuJoCo's own ({FIRST_PARTY_PLUGIN}*): a plugin is "
                "native code from a shared library, so only MuJoCo's first-party plugins are accepted",
            )


# ---------------------------------------------------------------------------- MuJoCo's messages
def _elements_of(data: bytes) -> list[tuple[str, dict[str, str], int]]:
    """(tag, attributes, line) of every element of an XML file; empty when it is not XML."""
    found: list[tuple[str, dict[str, str], int]] = []
    parser = expat.ParserCreate()

    def start(tag: str, attrs: dict[str, str]) -> None:
        found.append((tag, attrs, parser.CurrentLineNumber))

    parser.StartElementHandler = start
    try:
        parser.Parse(data, True)
    except expat.ExpatError:
        return []
    return found


def locate(message: str, xml_files: list[str], files: dict[str, bytes]) -> str:
    """Where MuJoCo's message points: ``file, line N``. MuJoCo names the element and a line, but not
    the file, and gives line 0 inside included files; the element is looked up in the files."""
    tag = re.search(r"Element '([^']+)'", message)
    name = re.search(r"Element name '([^']*)'", message)
    attr = re.search(r"attribute: '([^']+)'", message)
    line = re.search(r"line (\d+)", message)
    n = int(line.group(1)) if line else 0
    candidates = []
    if tag or (name and name.group(1)):
        for path in xml_files:
            for el_tag, attrs, el_line in _elements_of(files[path]):
                if tag and el_tag != tag.group(1):
                    continue
                if name and name.group(1) and attrs.get("name") != name.group(1):
                    continue
                if attr and attr.group(1) not in attrs:
                    continue
                candidates.append((path, el_line))
    if n and (xml_files[0], n) in candidates:
        return f"{xml_files[0]}, line {n}"
    exact = [c for c in candidates if c[1] == n] or candidates
    if exact:
        path, ln = exact[0]
        return f"{path}, line {ln}"
    return xml_files[0] + (f", line {n}" if n else "")


_FILE_MESSAGE = re.compile(
    r"(?:Error opening file|Empty file|[Cc]ould not open file|Could not read file|file not found)\s*'([^']*)'"
)


def _unreadable_file(message: str, files: dict[str, bytes]) -> SourceError | None:
    """A message about a file MuJoCo could not read: the same words whether or not the file exists on
    the server (the sandbox reads none of them, but MuJoCo's words differ: "Empty file", "Error opening
    file")."""
    m = _FILE_MESSAGE.search(message)
    if m is None:
        return None
    name = m.group(1)
    rel = name.replace("\\", "/")
    tag = re.search(r"Element '([^']+)'", message)
    what = f"<{tag.group(1)}> file {name!r}" if tag else f"file {name!r}"
    if rel.startswith("/") or re.match(r"^[A-Za-z]:", rel) or posixpath.normpath(rel).startswith(".."):
        return SourceError(
            "outside_model",
            f"{what} is outside the model's folder: only the model's own files are read; give paths "
            "relative to the model's folder (neuro train --mjcf FOLDER --entry path/to/model.xml)",
        )
    return SourceError("missing_file", f"{what} is missing: it is not among the model's files")


def _compile_error(exc: Exception, xml_files: list[str], files: dict[str, bytes]) -> SourceError:
    message = str(exc)
    unreadable = _unreadable_file(message, files)
    if unreadable is not None:
        return unreadable
    tag = re.search(r"Element '([^']+)'", message)
    text = re.sub(r"Element (name )?'[^']*'(, id \d+)?, line \d+", "", message)
    text = " ".join(text.replace("XML Error:", "").replace("Error:", "").split())
    where = locate(message, xml_files, files) + (f" (<{tag.group(1)}>)" if tag else "")
    return SourceError("compile_error", f"MuJoCo cannot load the model: {where}: {text}")


# ---------------------------------------------------------------------------- assets
def _mesh_vertices(data: bytes, ext: str) -> int:
    """A mesh file's vertex count, read cheaply from the file (before MuJoCo parses it)."""
    if ext == ".obj":
        return sum(1 for line in data.splitlines() if line[:2] in (b"v ", b"v\t"))
    if ext == ".stl":  # STL repeats shared vertices per triangle: a closed mesh has about F/2 of its own
        if len(data) >= 84:
            (triangles,) = struct.unpack_from("<I", data, 80)
            if len(data) == 84 + 50 * triangles:  # binary STL
                return triangles // 2
        return data.count(b"vertex") // 6  # ASCII STL: three "vertex" lines per facet
    if ext == ".msh" and len(data) >= 16:
        return int(struct.unpack_from("<i", data, 0)[0])
    return 0


@dataclass
class _Collector:
    files: dict[str, bytes]
    base: str  # the entry's folder inside the source
    strip: bool
    limits: Limits
    assets: dict[str, Asset] = field(default_factory=dict)

    def take(self, kind: AssetKind, owner: str, folder: str, file: str) -> str:
        """One asset file, found among the source's files as MuJoCo finds it (relative to the entry's
        folder, through ``folder``); returns its content-addressed name."""
        what = f"{kind} {owner!r} file {file!r}"
        name = PurePosixPath(file.replace("\\", "/")).name if self.strip else file
        key = _lookup(self.files, posixpath.join(self.base, folder), name) or _lookup(
            self.files, self.base, name
        )
        if key is None:
            found = _unreadable_file(f"Error opening file '{posixpath.join(folder, name)}'", self.files)
            assert found is not None
            raise SourceError(found.kind, str(found).replace(f"file {posixpath.join(folder, name)!r}", what))
        data = self.files[key]
        ext = PurePosixPath(key).suffix.lower()
        if kind == "mesh" and ext in MESH_TYPES:
            n = _mesh_vertices(data, ext)
            if n > self.limits.max_mesh_vertices:
                raise SourceError(
                    "mesh_too_large",
                    f"{what} has {n:,} vertices; a mesh may have {self.limits.max_mesh_vertices:,} "
                    "(simplify it, e.g. decimate it in Blender or MeshLab)",
                )
        sha = hashlib.sha256(data).hexdigest()
        source = key[len(self.base) + 1 :] if self.base and key.startswith(self.base + "/") else key
        self.assets.setdefault(sha + ext, Asset(sha + ext, sha, kind, source, data))
        return sha + ext


def _bundle_assets(spec: mujoco.MjSpec, sf: SourceFiles, entry: str, limits: Limits) -> dict[str, Asset]:
    """Point every asset of the spec at its content-addressed name (in place); the assets found."""
    col = _Collector(sf.files, posixpath.dirname(entry), bool(spec.strippath), limits)
    meshdir, texturedir = spec.meshdir or "", spec.texturedir or ""
    kinds: tuple[tuple[AssetKind, list[Any], str], ...] = (
        ("mesh", spec.meshes, meshdir),  # height fields and skins are found through meshdir too
        ("hfield", spec.hfields, meshdir),
        ("skin", spec.skins, meshdir),
        ("texture", spec.textures, texturedir),
    )
    for kind, elements, folder in kinds:
        for el in elements:
            if el.file:
                el.file = col.take(kind, el.name, folder, el.file)
    for tex in spec.textures:
        faces = list(tex.cubefiles)
        if any(faces):
            tex.cubefiles = [col.take("texture", tex.name, texturedir, f) if f else "" for f in faces]
    spec.meshdir = ""
    spec.texturedir = ""
    return col.assets


def _check_timestep(m: mujoco.MjModel, limits: Limits) -> None:
    dt = float(m.opt.timestep)
    if not dt > 0.0 or dt != dt or dt == float("inf"):
        raise SourceError("bad_timestep", f"<option timestep> is {dt:g} s: it must be a positive number")
    if dt < limits.min_timestep:
        raise SourceError(
            "bad_timestep",
            f"<option timestep> is {dt:g} s, below the floor of {limits.min_timestep:g} s (MIN_TIMESTEP): "
            "a second of motion would take over "
            f"{round(1.0 / limits.min_timestep):,} MuJoCo steps; use a timestep of at least that",
        )


def _vfs(files: dict[str, bytes]) -> mujoco.MjVfs:
    vfs = mujoco.MjVfs()
    for name, data in files.items():
        vfs[name] = data
    return vfs


def bundle_files(sf: SourceFiles, limits: Limits) -> tuple[Bundle, mujoco.MjModel]:
    """The bundle of a source's files and its compiled model (see the module's text). Call it where
    MuJoCo can open nothing but ``sf.files`` (``sandbox``)."""
    files = sf.files
    entry = _find_entry(sf)
    for name, data in files.items():
        if name.lower().endswith(".xml") and len(data) > limits.max_xml_bytes:
            raise SourceError(
                "file_too_large",
                f"{name} is {len(data):,} bytes; an MJCF file may have {limits.max_xml_bytes:,}",
            )
    first = _parse(files, entry)
    if first.tag != "mujoco":
        raise SourceError(
            "not_xml", f"{entry} is XML but not an MJCF: its root element is <{first.tag}>, not <mujoco>"
        )
    xml_files = _xml_files(entry, files)
    try:
        spec = mujoco.MjSpec.from_file(entry, vfs=_vfs(files))
    except Exception as exc:  # MuJoCo raises ValueError with its parser's message
        raise _compile_error(exc, xml_files, files) from exc
    for p in spec.plugins:
        _check_plugins(ET.Element("plugin", {"plugin": p.plugin_name or FIRST_PARTY_PLUGIN}), entry)
    assets = _bundle_assets(spec, sf, entry, limits)
    vfs = {a.name: a.data for a in assets.values()}
    spec.assets = vfs  # what compiling and writing the MJCF back read (the spec's own file system)
    try:
        xml = spec.to_xml()
        m = mujoco.MjModel.from_xml_string(xml, vfs or None)
    except Exception as exc:
        raise _compile_error(exc, xml_files, files) from exc
    _check_timestep(m, limits)
    if m.nmesh and int(m.mesh_vertnum.max()) > limits.max_mesh_vertices:
        big = int(m.mesh_vertnum.argmax())
        raise SourceError(
            "mesh_too_large",
            f"mesh {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_MESH, big)!r} has {int(m.mesh_vertnum[big]):,} "
            f"vertices; a mesh may have {limits.max_mesh_vertices:,}",
        )
    given = (first.get("model") or "").strip() or None
    bundle = Bundle(xml=xml, assets=tuple(assets.values()), entry=entry, files=tuple(xml_files), name=given)
    return bundle, m
