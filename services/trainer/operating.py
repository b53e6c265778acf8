"""An upload's operating spec (``neuroanimator.core.operating_spec``, docs/operating-spec.md): the form
field ``operating_spec`` (JSON text), else an ``operating.json`` in the uploaded archive.

``parse`` reads the text into an ``OperatingSpec``, or ``SpecProblem`` naming the field where it is
wrong (``operating_spec.controls.thrust1.range``). ``in_archive`` finds the archive's ``operating.json``:
beside the entry the form names, else at the archive's top, else in its one top folder (an archive of
a model folder). It reads an archive that the model's check has already read under the service's caps,
and takes the file only when it is small (``MAX_SPEC_BYTES``).

Whether a spec fits the model (its actuators, joints, keyframes and control ranges) is
``sim.operating``'s to say, when the model is loaded with it (``validation.check_model``).
"""

from __future__ import annotations

import posixpath
import tarfile
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from pydantic import ValidationError

from neuroanimator.core.operating_spec import OperatingSpec

FORM_FIELD = "operating_spec"
SPEC_FILE = "operating.json"
MAX_SPEC_BYTES = 16_384
"""The largest operating spec taken from an archive (the form's field is capped alike)."""
MAX_SHOWN = 120


class SpecProblem(Exception):
    """A spec that is not JSON or not an operating spec: ``field`` names where (dotted, under the form
    field or the file), the message says what is wrong."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= MAX_SHOWN else text[: MAX_SHOWN - 3] + "..."


def parse(text: str, where: str = FORM_FIELD) -> OperatingSpec:
    """The operating spec in ``text`` (JSON); ``SpecProblem`` naming ``where`` and the field inside."""
    try:
        return OperatingSpec.model_validate_json(text)
    except ValidationError as exc:
        errors = exc.errors()
        first = errors[0]
        if first["type"] == "json_invalid":
            why = (first.get("ctx") or {}).get("error", "a syntax error")
            raise SpecProblem(where, f"{where} is not JSON: {why}") from exc
        loc = ".".join(str(x) for x in first["loc"])
        field = f"{where}.{loc}" if loc else where
        more = f" (and {len(errors) - 1} more problems)" if len(errors) > 1 else ""
        got = "" if first["type"] == "missing" else f"; got {_shown(first.get('input'))}"
        why = str(first["msg"]).removeprefix("Value error, ")
        raise SpecProblem(field, f"{field}: {why}{got}{more}") from exc


def canonical(spec: OperatingSpec) -> str:
    """The spec as the queued training keeps it (and hands to ``neuro train --spec``)."""
    return spec.model_dump_json(exclude_defaults=True)


@dataclass(frozen=True)
class Found:
    """An ``operating.json`` of an archive: its path inside it and its text."""

    path: str
    text: str


def _candidates(names: list[str], entry: str | None) -> list[str]:
    """Where an archive's spec may be, first first: beside the named entry, at the top, in the one top
    folder."""
    out = []
    if entry:
        folder = posixpath.dirname(posixpath.normpath(entry.replace("\\", "/").lstrip("/")))
        out.append(posixpath.join(folder, SPEC_FILE) if folder not in ("", ".") else SPEC_FILE)
    out.append(SPEC_FILE)
    tops = {PurePosixPath(n).parts[0] for n in names if PurePosixPath(n).parts}
    if len(tops) == 1:
        out.append(f"{next(iter(tops))}/{SPEC_FILE}")
    return list(dict.fromkeys(out))


def _member(name: str) -> str:
    return posixpath.normpath(name.replace("\\", "/").lstrip("/")).removeprefix("./")


class TooLarge(SpecProblem):
    """An archive's spec past ``MAX_SPEC_BYTES``."""


def in_archive(path: Path, entry: str | None) -> Found | None:
    """The archive's ``operating.json`` (see the module's text), or None (a plain MJCF upload too);
    ``TooLarge`` when it is larger than ``MAX_SPEC_BYTES``."""
    lower = path.name.lower()
    texts: dict[str, bytes] = {}
    names: list[str] = []
    if lower.endswith(".zip"):
        with zipfile.ZipFile(path) as zf:
            infos = [i for i in zf.infolist() if not i.is_dir()]
            names = [_member(i.filename) for i in infos]
            wanted = set(_candidates(names, entry))
            for info, name in zip(infos, names, strict=True):
                if name in wanted:
                    with zf.open(info) as f:
                        texts[name] = f.read(MAX_SPEC_BYTES + 1)
    elif lower.endswith((".tar.gz", ".tgz")):
        with tarfile.open(path, mode="r|gz") as tf:
            for member in tf:
                if not member.isfile():
                    continue
                name = _member(member.name)
                names.append(name)
                if PurePosixPath(name).name == SPEC_FILE and len(PurePosixPath(name).parts) <= 8:
                    content = tf.extractfile(member)
                    if content is not None:
                        texts[name] = content.read(MAX_SPEC_BYTES + 1)
    else:
        return None
    for name in _candidates(names, entry):
        if name in texts:
            data = texts[name]
            if len(data) > MAX_SPEC_BYTES:
                raise TooLarge(
                    "file",
                    f"{name} in {path.name} is larger than {MAX_SPEC_BYTES:,} bytes: not an operating spec",
                )
            return Found(name, data.decode("utf-8", errors="replace"))
    return None
