"""A seeded fuzz of what users upload: archives with flipped, cut and inserted bytes, and MJCFs with
spans cut, repeated and spliced with hostile pieces (includes of the server's files, DOCTYPEs, file
attributes that climb out). Each either becomes a bundle or is a ``SourceError`` naming the problem:
never another exception, never a server path, never a hang past the caps. The seeds are fixed, so a
failure reproduces."""

from __future__ import annotations

import gzip
import io
import random
import tarfile
import zipfile
from pathlib import Path

import pytest

from neuroanimator.sim import sandbox
from neuroanimator.sim.bundle import Limits, SourceError, extract
from neuroanimator.sim.sandbox import load_bundle

ROOT = Path(__file__).resolve().parents[2]
TINYBOT = ROOT / "tests" / "data" / "tinybot"
HOSTILE = [
    b"<include file='/etc/hostname'/>",
    b"<include file='../../../../etc/passwd'/>",
    b"<!DOCTYPE x [<!ENTITY a \"<include file='/etc/hostname'/>\">]>",
    b'<flexcomp name="f" type="mesh" dim="2" file="/etc/hostname"/>',
    b'<compiler meshdir="/etc" assetdir="/"/>',
    b'<mesh name="z" file="/proc/self/environ"/>',
    b'<texture name="t" type="2d" file="../../x.png"/>',
    b'<hfield name="h" file="/etc/hostname"/>',
    b"<replicate count='3'>",
    b"</replicate>",
    b"&a;",
    b"\x00\xff",
    b"<mujoco>",
    b"</mujoco>",
]


def _archive(kind: str) -> bytes:
    """The tinybot folder archived with fixed times and owners: the same bytes in every clone, so
    that the seeded mutations are the same everywhere."""
    files = [
        (f"tinybot/{p.relative_to(TINYBOT).as_posix()}", p.read_bytes())
        for p in sorted(TINYBOT.rglob("*"))
        if p.is_file()
    ]
    buf = io.BytesIO()
    if kind == "zip":
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
            for name, data in files:
                zf.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data)
    else:
        with gzip.GzipFile(fileobj=buf, mode="wb", mtime=0) as gz, tarfile.open(fileobj=gz, mode="w") as tf:
            for name, data in files:
                info = tarfile.TarInfo(name)
                info.size, info.mtime, info.mode = len(data), 0, 0o644
                tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def _mutate(data: bytes, rng: random.Random) -> bytes:
    out = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        what = rng.random()
        at = rng.randrange(len(out)) if out else 0
        if what < 0.4 and out:
            out[at] ^= 1 << rng.randrange(8)
        elif what < 0.6:
            del out[at : at + rng.randint(1, 64)]
        elif what < 0.8:
            out[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        else:
            out[at:at] = out[at : at + rng.randint(1, 128)]
    return bytes(out)


@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_mutated_archives_extract_or_are_refused(tmp_path: Path, kind: str) -> None:
    rng = random.Random(f"archive-{kind}")
    base = _archive(kind)
    limits = Limits(max_bytes=1 << 20, max_files=50)
    extracted = 0
    for i in range(300):
        path = tmp_path / f"m{i}.{kind}"
        path.write_bytes(_mutate(base, rng))
        try:
            files = extract(path, limits)
        except SourceError as exc:
            assert str(tmp_path) not in str(exc), str(exc)
            continue
        extracted += 1
        assert all(not n.startswith("/") and ".." not in n.split("/") for n in files)
    assert extracted < 300  # the mutations do break archives (and some survive: deflate's slack)


@pytest.mark.skipif(not sandbox.available(), reason="this kernel has no Linux Landlock")
def test_mutated_mjcfs_bundle_or_are_refused(tmp_path: Path) -> None:
    rng = random.Random("mjcf")
    robot = (TINYBOT / "robot.xml").read_bytes()
    outcomes: dict[str, int] = {}
    for i in range(24):
        folder = tmp_path / f"m{i}"
        (folder / "parts").mkdir(parents=True)
        (folder / "assets").mkdir()
        for p in ("parts/arm.xml", "assets/knob.obj", "assets/checker.png"):
            (folder / p).write_bytes((TINYBOT / p).read_bytes())
        xml = bytearray(robot)
        for _ in range(rng.randint(1, 3)):
            at = rng.randrange(len(xml))
            if rng.random() < 0.6:
                xml[at:at] = rng.choice(HOSTILE)
            else:
                del xml[at : at + rng.randint(1, 40)]
        (folder / "robot.xml").write_bytes(bytes(xml))
        try:
            b = load_bundle(folder, "robot.xml", Limits(compile_seconds=20.0))
        except SourceError as exc:
            assert str(tmp_path) not in str(exc), str(exc)
            assert "root:" not in str(exc)  # nothing of /etc/passwd
            outcomes[exc.kind] = outcomes.get(exc.kind, 0) + 1
            continue
        outcomes["bundled"] = outcomes.get("bundled", 0) + 1
        assert "<include" not in b.xml and "/etc" not in b.xml
    assert sum(outcomes.values()) == 24 and len(outcomes) >= 2, outcomes
