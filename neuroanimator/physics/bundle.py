"""A model as users ship it -> a self-contained ``Bundle``: one MJCF and the asset files it uses.

A source is an MJCF file, a folder that holds the model, or a ``.zip`` / ``.tar.gz`` / ``.tgz`` of
such a folder (an archive's files are extracted into a temporary folder first, under the caps of
``Limits``, checked while extracting). In a folder or an archive the entry XML is named by ``entry``
(its path inside, or a file name found once), or found as the only MJCF that no other includes.

The entry's ``<include>`` files and its assets (meshes: STL, OBJ, MSH; textures, cube-map faces
included; height fields; skins) are found the way MuJoCo finds them: includes relative to the entry's
folder, assets relative to it through the compiler's ``meshdir`` / ``texturedir`` (``assetdir`` sets
both). Each must lie inside the model's folder (the entry's folder for a plain file), so a model never
reads files beside it. What the model declares is kept; other files of the folder are not.

The bundle's MJCF names each asset by its content, ``<sha256><extension>``, and has no directories and
no includes (MuJoCo writes the parsed model back as one MJCF: ``MjSpec.to_xml``); with the assets as a
MuJoCo virtual file system it compiles with nothing else. A model that refers to no other file is kept
as written. Every problem is a ``SourceError`` whose ``kind`` says which (for a service to map to a
status) and whose message names the file: not XML, MuJoCo's compile error (with the file and line), a
missing include or asset, an unsafe or oversized archive, a mesh over the vertex cap, or a plugin that
is not one of MuJoCo's own (plugins are native code in shared libraries).
"""

from __future__ import annotations

import hashlib
import os
import re
import stat
import struct
import tarfile
import tempfile
import xml.etree.ElementTree as ET
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import IO, Any, Literal
from xml.parsers import expat

import mujoco

from neuroanimator.physics.model import ModelError

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
]
AssetKind = Literal["mesh", "texture", "hfield", "skin"]
ARCHIVE_SUFFIXES = (".zip", ".tar.gz", ".tgz")
MESH_TYPES = (".stl", ".obj", ".msh")
FIRST_PARTY_PLUGIN = "mujoco."  # MuJoCo's own plugins: mujoco.elasticity.cable, mujoco.pid, ...
_MiB = 1 << 20


class SourceError(ModelError):
    """A model source that cannot become a bundle; ``kind`` says which problem, the message names it."""

    def __init__(self, kind: SourceProblem, message: str) -> None:
        super().__init__(message)
        self.kind: SourceProblem = kind


@dataclass(frozen=True)
class Limits:
    """Caps on what a source may hold: an archive's files are counted and measured while extracting
    (its headers are not trusted), against the archive's own size for the compression ratio."""

    max_bytes: int = 256 * _MiB  # everything extracted from an archive
    max_files: int = 5000  # files in an archive
    max_ratio: float = 100.0  # extracted bytes per archive byte ...
    ratio_from: int = 4 * _MiB  # ... checked once this much is extracted (small text compresses well)
    max_file_bytes: int = 64 * _MiB  # one XML or asset file
    max_mesh_vertices: int = 200_000  # one mesh


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

    def vfs(self) -> dict[str, bytes]:
        """The assets as MuJoCo's virtual file system: ``MjModel.from_xml_string(xml, vfs)``."""
        return {a.name: a.data for a in self.assets}


# ---------------------------------------------------------------------------- archives
def _archive_kind(path: Path) -> str | None:
    name = path.name.lower()
    if name.endswith(".zip"):
        return "zip"
    if name.endswith((".tar.gz", ".tgz")):
        return "tar"
    return None


def _member_path(name: str, archive: str) -> PurePosixPath | None:
    """The relative path an archive member extracts to; None for the archive's folder entries."""
    if "\\" in name or "\x00" in name:
        raise SourceError("unsafe_archive", f"{archive}: entry {name!r} has a backslash or NUL in its name")
    p = PurePosixPath(name)
    if p.is_absolute() or re.match(r"^[A-Za-z]:", name):
        raise SourceError("unsafe_archive", f"{archive}: entry {name!r} is an absolute path")
    if ".." in p.parts:
        raise SourceError("unsafe_archive", f"{archive}: entry {name!r} climbs out of the archive ('..')")
    parts = [s for s in p.parts if s not in ("", ".")]
    return PurePosixPath(*parts) if parts else None


class _Extractor:
    """Writes members under ``dest`` while counting files and bytes against ``Limits``."""

    def __init__(self, dest: Path, archive: Path, limits: Limits) -> None:
        self.dest = dest
        self.name = archive.name
        self.size = max(1, archive.stat().st_size)
        self.limits = limits
        self.files = 0
        self.bytes = 0

    def add(self, rel: PurePosixPath, stream: IO[bytes], declared: int) -> None:
        lim = self.limits
        self.files += 1
        if self.files > lim.max_files:
            raise SourceError("archive_too_large", f"{self.name}: more than {lim.max_files} files")
        if declared > lim.max_file_bytes:
            raise SourceError(
                "file_too_large",
                f"{self.name}: {rel} is {declared:,} bytes; one file may have {lim.max_file_bytes:,}",
            )
        target = self.dest.joinpath(*rel.parts)
        if target.exists():
            raise SourceError("unsafe_archive", f"{self.name}: {rel} appears twice")
        target.parent.mkdir(parents=True, exist_ok=True)
        written = 0
        with target.open("wb") as out:
            while chunk := stream.read(1 << 16):
                written += len(chunk)
                self.bytes += len(chunk)
                if written > lim.max_file_bytes:
                    raise SourceError(
                        "file_too_large",
                        f"{self.name}: {rel} is over {lim.max_file_bytes:,} bytes once extracted",
                    )
                if self.bytes > lim.max_bytes:
                    raise SourceError(
                        "archive_too_large",
                        f"{self.name}: more than {lim.max_bytes:,} bytes once extracted",
                    )
                if self.bytes > lim.ratio_from and self.bytes > lim.max_ratio * self.size:
                    raise SourceError(
                        "archive_too_large",
                        f"{self.name}: extracts to over {lim.max_ratio:g} times its own size "
                        f"({self.size:,} bytes); refused as a compression bomb",
                    )
                out.write(chunk)


def extract(archive: Path, dest: Path, limits: Limits) -> None:
    """Extract a .zip or .tar.gz into ``dest``: plain files and folders only (no links, devices,
    absolute paths or ``..``), within ``limits``. Raises ``SourceError``; ``dest`` may then hold part."""
    ex = _Extractor(dest, archive, limits)
    if _archive_kind(archive) == "zip":
        try:
            with zipfile.ZipFile(archive) as zf:
                for info in zf.infolist():
                    rel = _member_path(info.filename, archive.name)
                    mode = info.external_attr >> 16
                    if stat.S_ISLNK(mode):
                        raise SourceError(
                            "unsafe_archive", f"{archive.name}: entry {info.filename!r} is a link"
                        )
                    if rel is None or info.is_dir():
                        continue
                    with zf.open(info) as stream:
                        ex.add(rel, stream, info.file_size)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, NotImplementedError, EOFError) as exc:
            raise SourceError(
                "unsafe_archive", f"{archive.name}: not a readable zip archive ({exc})"
            ) from exc
        return
    try:
        with tarfile.open(archive, mode="r|gz") as tf:
            for member in tf:
                rel = _member_path(member.name, archive.name)
                if member.isdir():
                    continue
                if not member.isfile():
                    what = "a link" if member.issym() or member.islnk() else "not a plain file"
                    raise SourceError("unsafe_archive", f"{archive.name}: entry {member.name!r} is {what}")
                if rel is None:
                    continue
                content = tf.extractfile(member)
                if content is not None:
                    ex.add(rel, content, member.size)
    except (tarfile.TarError, EOFError, OSError) as exc:
        raise SourceError(
            "unsafe_archive", f"{archive.name}: not a readable .tar.gz archive ({exc})"
        ) from exc


# ---------------------------------------------------------------------------- XML files
def _parse(path: Path, root: Path) -> ET.Element:
    rel = _rel(path, root)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SourceError("missing_file", f"cannot read {rel}: {exc.strerror}") from exc
    try:
        return ET.fromstring(data)
    except ET.ParseError as exc:  # its message ends with the line and column
        raise SourceError("not_xml", f"{rel} is not XML: {exc}") from exc


def _rel(path: Path, root: Path) -> str:
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return str(path)


def _inside(path: Path, root: Path, what: str) -> Path:
    """``path`` made absolute and real; ``SourceError`` when it leaves ``root``."""
    real = Path(os.path.realpath(path))
    if real != root and root not in real.parents:
        raise SourceError(
            "outside_model",
            f"{what} is outside the model's folder {str(root)!r}; give the folder that holds the model "
            "and all its files (neuro train --mjcf FOLDER --entry path/to/model.xml)",
        )
    return real


def _xml_files(entry: Path, root: Path) -> list[Path]:
    """The entry and every file it includes (recursively), each parsed once; includes are relative to
    the entry's folder, as MuJoCo reads them."""
    first = _parse(entry, root)
    if first.tag != "mujoco":
        raise SourceError(
            "not_xml",
            f"{_rel(entry, root)} is XML but not an MJCF: its root element is <{first.tag}>, not <mujoco>",
        )
    files, queue, seen = [entry], [(entry, first)], {entry}
    while queue:
        path, tree = queue.pop(0)
        _check_plugins(tree, _rel(path, root))
        # <include file> and a sub-model <asset><model file>: MJCF files MuJoCo reads while parsing
        referenced = [("include", el) for el in tree.iter("include")]
        referenced += [("model", el) for asset in tree.iter("asset") for el in asset.iter("model")]
        for tag, inc in referenced:
            name = inc.get("file", "")
            what = f"{tag} {name!r} (in {_rel(path, root)})"
            if not name or os.path.isabs(name):
                raise SourceError("outside_model", f"{what}: give a path relative to the model's folder")
            target = _inside(entry.parent / name, root, what)
            if not target.is_file():
                raise SourceError("missing_file", f"{what} is missing: no file {_rel(target, root)}")
            if target not in seen:
                seen.add(target)
                files.append(target)
                queue.append((target, _parse(target, root)))
    return files


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
def _elements_of(path: Path) -> list[tuple[str, dict[str, str], int]]:
    """(tag, attributes, line) of every element of an XML file; empty when it is not XML."""
    found: list[tuple[str, dict[str, str], int]] = []
    parser = expat.ParserCreate()

    def start(tag: str, attrs: dict[str, str]) -> None:
        found.append((tag, attrs, parser.CurrentLineNumber))

    parser.StartElementHandler = start
    try:
        parser.Parse(path.read_bytes(), True)
    except (expat.ExpatError, OSError):
        return []
    return found


def _elements(files: list[Path]) -> Iterator[tuple[Path, str, dict[str, str], int]]:
    """(file, tag, attributes, line) of every element of these XML files."""
    for path in files:
        for tag, attrs, line in _elements_of(path):
            yield path, tag, attrs, line


def locate(message: str, files: list[Path], root: Path) -> str:
    """Where MuJoCo's message points: ``file, line N``. MuJoCo names the element and a line, but not
    the file, and gives line 0 inside included files; the element is looked up in the files."""
    tag = re.search(r"Element '([^']+)'", message)
    name = re.search(r"Element name '([^']*)'", message)
    attr = re.search(r"attribute: '([^']+)'", message)
    line = re.search(r"line (\d+)", message)
    n = int(line.group(1)) if line else 0
    candidates = []
    for path, el_tag, attrs, el_line in _elements(files):
        if tag and el_tag != tag.group(1):
            continue
        if name and name.group(1) and attrs.get("name") != name.group(1):
            continue
        if attr and attr.group(1) not in attrs:
            continue
        if not (tag or (name and name.group(1))):
            continue
        candidates.append((path, el_line))
    if n and any(p == files[0] and ln == n for p, ln in candidates):
        return f"{_rel(files[0], root)}, line {n}"
    exact = [c for c in candidates if c[1] == n] or candidates
    if exact:
        path, ln = exact[0]
        return f"{_rel(path, root)}, line {ln}"
    return _rel(files[0], root) + (f", line {n}" if n else "")


def _compile_error(exc: Exception, files: list[Path], root: Path) -> SourceError:
    message = str(exc)
    tag = re.search(r"Element '([^']+)'", message)
    text = re.sub(r"Element (name )?'[^']*'(, id \d+)?, line \d+", "", message)
    text = " ".join(text.replace("XML Error:", "").replace("Error:", "").split())
    where = locate(message, files, root) + (f" (<{tag.group(1)}>)" if tag else "")
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


def _asset_path(base: Path, folder: str, file: str, strip: bool) -> str:
    """The file MuJoCo opens for an asset: relative to the model file's folder, through ``folder``."""
    if strip:
        file = PurePosixPath(file.replace("\\", "/")).name
    if os.path.isabs(file):
        return file
    if folder and os.path.isabs(folder):
        return os.path.join(folder, file)
    return os.path.join(str(base), folder, file)


@dataclass
class _Collector:
    root: Path
    base: Path
    strip: bool
    limits: Limits
    assets: dict[str, Asset] = field(default_factory=dict)

    def take(self, kind: AssetKind, owner: str, folder: str, file: str) -> str:
        """Read one asset file; returns its content-addressed name."""
        what = f"{kind} {owner!r} file {file!r}"
        path = Path(_asset_path(self.base, folder, file, self.strip))
        real = _inside(path, self.root, what)
        if not real.is_file():
            raise SourceError("missing_file", f"{what} is missing: no file {_rel(real, self.root)}")
        size = real.stat().st_size
        if size > self.limits.max_file_bytes:
            raise SourceError(
                "file_too_large",
                f"{what} is {size:,} bytes; one file may have {self.limits.max_file_bytes:,}",
            )
        data = real.read_bytes()
        ext = real.suffix.lower()
        if kind == "mesh" and ext in MESH_TYPES:
            n = _mesh_vertices(data, ext)
            if n > self.limits.max_mesh_vertices:
                raise SourceError(
                    "mesh_too_large",
                    f"{what} has {n:,} vertices; a mesh may have {self.limits.max_mesh_vertices:,} "
                    "(simplify it, e.g. decimate it in Blender or MeshLab)",
                )
        sha = hashlib.sha256(data).hexdigest()
        name = sha + ext
        source = _rel(real, self.base) if self.base in real.parents else _rel(real, self.root)
        self.assets.setdefault(name, Asset(name, sha, kind, source, data))
        return name


def _bundle_assets(spec: mujoco.MjSpec, root: Path, entry: Path, limits: Limits) -> dict[str, Asset]:
    """Point every asset of the spec at its content-addressed name (in place); the assets read."""
    col = _Collector(root, Path(os.path.realpath(entry.parent)), bool(spec.strippath), limits)
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


# ---------------------------------------------------------------------------- sources
def _mjcf_files(root: Path) -> list[Path]:
    out = []
    for p in sorted(root.rglob("*.xml")):
        try:
            with p.open("rb") as fh:
                head = fh.read(4096)
        except OSError:
            continue
        if b"<mujoco" in head:
            out.append(p)
    return out


def _find_entry(root: Path, entry: str | None, source: str) -> Path:
    files = _mjcf_files(root)
    listed = ", ".join(_rel(p, root) for p in files[:10]) or "none"
    if entry is not None:
        rel = PurePosixPath(entry.replace("\\", "/"))
        if rel.is_absolute() or ".." in rel.parts:
            raise SourceError("entry", f"the entry {entry!r} must be a path inside {source}")
        exact = root.joinpath(*rel.parts)
        if exact.is_file():
            return exact
        named = [p for p in files if p.name == rel.name]
        if len(named) == 1:
            return named[0]
        raise SourceError(
            "entry",
            f"{source} has no MJCF {entry!r}"
            + (" (several by that name)" if named else f"; its MJCF files: {listed}"),
        )
    included = set()
    for p in files:
        try:
            tree = ET.parse(p).getroot()
        except ET.ParseError:
            continue
        for inc in tree.iter("include"):
            included.add(os.path.realpath(p.parent / inc.get("file", "")))
    tops = [p for p in files if os.path.realpath(p) not in included]
    if len(tops) == 1:
        return tops[0]
    if not tops:
        raise SourceError("entry", f"{source} holds no MJCF file (an XML whose root element is <mujoco>)")
    raise SourceError("entry", f"{source} holds several MJCF files ({listed}): name the entry (--entry FILE)")


def load_source(path: str | Path, entry: str | None = None, limits: Limits | None = None) -> Bundle:
    """The bundle of an MJCF file, a model folder or an archive of one (see the module docstring)."""
    limits = limits or Limits()
    src = Path(path)
    if not src.exists():
        raise SourceError("not_found", f"{str(src)!r} does not exist")
    if src.is_dir():
        root = Path(os.path.realpath(src))
        return _bundle(_find_entry(root, entry, f"folder {src.name!r}"), root, limits)
    if _archive_kind(src) is not None:
        with tempfile.TemporaryDirectory(prefix="neuro-model-") as tmp:
            dest = Path(os.path.realpath(tmp))
            extract(src, dest, limits)
            return _bundle(_find_entry(dest, entry, f"archive {src.name!r}"), dest, limits)
    if entry is not None:
        raise SourceError(
            "entry", f"--entry names a file inside a folder or an archive; {src.name!r} is a file"
        )
    size = src.stat().st_size
    if size > limits.max_file_bytes:
        raise SourceError(
            "file_too_large", f"{src.name} is {size:,} bytes; one file may have {limits.max_file_bytes:,}"
        )
    real = Path(os.path.realpath(src))
    return _bundle(real, real.parent, limits)


def _bundle(entry: Path, root: Path, limits: Limits) -> Bundle:
    files = _xml_files(entry, root)
    rels = tuple(_rel(p, root) for p in files)
    try:
        spec = mujoco.MjSpec.from_file(str(entry))
    except Exception as exc:  # MuJoCo raises ValueError with its parser's message
        raise _compile_error(exc, files, root) from exc
    has_files = any(m.file for m in spec.meshes) or any(h.file for h in spec.hfields)
    has_files = has_files or any(s.file for s in spec.skins)
    has_files = has_files or any(t.file or any(t.cubefiles) for t in spec.textures)
    if len(files) == 1 and not has_files:
        xml = entry.read_text()  # self-contained: kept as written
        assets: dict[str, Asset] = {}
    else:
        assets = _bundle_assets(spec, root, entry, limits)
        spec.assets = {a.name: a.data for a in assets.values()}
        try:
            xml = spec.to_xml()
        except Exception as exc:
            raise _compile_error(exc, files, root) from exc
    try:
        m = mujoco.MjModel.from_xml_string(xml, {a.name: a.data for a in assets.values()} or None)
    except Exception as exc:
        raise _compile_error(exc, files, root) from exc
    if m.nmesh and int(m.mesh_vertnum.max()) > limits.max_mesh_vertices:
        big = int(m.mesh_vertnum.argmax())
        raise SourceError(
            "mesh_too_large",
            f"mesh {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_MESH, big)!r} has {int(m.mesh_vertnum[big]):,} "
            f"vertices; a mesh may have {limits.max_mesh_vertices:,}",
        )
    return Bundle(xml=xml, assets=tuple(assets.values()), entry=rels[0], files=rels)
