"""MuJoCo sees only the upload (``neuroanimator.sim.sandbox``): models that try to read other files, by
every element that reads one, are refused alike whether the file exists or not, and never read it; a
stored MJCF is compiled the same way; the caps stop costly models in seconds.

The attacks are real files written by the test (a "secret" model beside the upload, and the server's
own /etc/hostname), not mocks."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import mujoco
import pytest

from neuroanimator.sim import landlock, sandbox
from neuroanimator.sim.bundle import Limits, SourceError
from neuroanimator.sim.sandbox import load_bundle

pytestmark = pytest.mark.skipif(not sandbox.available(), reason="this kernel has no Linux Landlock")

SECRET = """<mujoco model="secret-a"><worldbody><body name="stolen_body"><joint name="stolen_joint"
type="hinge"/><geom size=".1" rgba="0.1 0.2 0.3 1"/></body></worldbody>
<actuator><motor name="stolen_motor" joint="stolen_joint" ctrlrange="-7 7"/></actuator></mujoco>"""
DECOY = """<mujoco model="decoy"><worldbody><body><joint name="h" type="hinge"/><geom size=".1"/></body>
</worldbody><actuator><motor joint="h" ctrlrange="-1 1"/></actuator></mujoco>"""
OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


def doctype_include(target: str) -> str:
    """The first probe's payload: an <include> that expat reads as an entity's value and MuJoCo's
    parser as an element (it ends the DOCTYPE at the first '>')."""
    return (
        '<!DOCTYPE x [<!ENTITY a ">\n'
        f"<mujoco model='s'><include file='{target}'/></mujoco>\n"
        '<!-- ">]>\n' + DECOY + "\n<!-- -->\n"
    )


def flexcomp(target: str) -> str:
    """The second probe's payload: a flexcomp whose mesh file lies outside the upload."""
    return (
        '<mujoco model="flex"><worldbody><flexcomp name="f" type="mesh" dim="2" '
        f'file="{target}"/>'
        '<body><joint name="h" type="hinge"/><geom size=".1"/></body></worldbody>'
        '<actuator><motor joint="h" ctrlrange="-1 1"/></actuator></mujoco>'
    )


def asset_paths(target: str) -> str:
    """A payload of our own: the same file through a mesh's absolute meshdir, a height field, a texture,
    a skin and a sub-model, each in turn."""
    return DECOY.replace("<worldbody>", f'<asset><mesh name="m" file="{target}"/></asset><worldbody>')


@pytest.fixture(name="secret")
def secret_fixture(tmp_path: Path) -> Path:
    """Another tenant's stored model, and a mesh of theirs."""
    folder = tmp_path / "artifacts" / "secret-a" / "v1"
    folder.mkdir(parents=True)
    (folder / "model.xml").write_text(SECRET)
    (folder / "mesh.obj").write_bytes(OBJ)
    return folder


def refusal(tmp_path: Path, name: str, xml: str) -> SourceError:
    upload = tmp_path / "uploads" / name
    upload.mkdir(parents=True)
    (upload / "upload.xml").write_text(xml)
    with pytest.raises(SourceError) as info:
        load_bundle(upload / "upload.xml")
    return info.value


def same_words(a: SourceError, b: SourceError, name_a: str, name_b: str) -> None:
    """Two refusals that say the same apart from the file's name: nothing tells which file exists."""
    assert a.kind == b.kind, (a, b)
    assert str(a).replace(name_a, "X") == str(b).replace(name_b, "X"), (str(a), str(b))


@pytest.mark.parametrize(
    "payload", [doctype_include, flexcomp, asset_paths], ids=["doctype-include", "flexcomp", "mesh-file"]
)
def test_files_outside_the_upload_are_never_read(
    tmp_path: Path, secret: Path, payload: Callable[[str], str]
) -> None:
    make = payload
    real = str(secret / ("model.xml" if make is doctype_include else "mesh.obj"))
    missing = str(secret / "nothing-here.obj")
    a = refusal(tmp_path, "a", make(real))
    b = refusal(tmp_path, "b", make(missing))
    assert "stolen" not in str(a) and "secret-a" not in str(a).replace(real, "")
    assert a.kind in ("outside_model", "missing_file"), str(a)
    same_words(a, b, real, missing)
    rel = "../" * 8 + real.lstrip("/")  # the same file by a relative path that climbs out
    c = refusal(tmp_path, "c", make(rel))
    assert c.kind == a.kind and "stolen" not in str(c)


@pytest.mark.parametrize("target", ["/etc/hostname", "/proc/self/environ", "/etc/no-such-file"])
def test_the_servers_files_read_as_missing_alike(tmp_path: Path, target: str) -> None:
    err = refusal(tmp_path, "x", doctype_include(target))
    assert str(err) == str(refusal(tmp_path, "y", doctype_include("/nope/x.xml"))).replace(
        "/nope/x.xml", target
    )


def test_a_flexcomp_mesh_inside_the_upload_still_loads(tmp_path: Path) -> None:
    folder = tmp_path / "flexmodel"
    folder.mkdir()
    (folder / "model.xml").write_text(flexcomp("cloth.obj"))
    (folder / "cloth.obj").write_bytes(OBJ)
    b = load_bundle(folder)
    assert "<include" not in b.xml
    assert mujoco.MjModel.from_xml_string(b.xml, b.vfs()).nflex == 1


def test_a_stored_mjcf_compiles_only_with_its_assets(tmp_path: Path, secret: Path) -> None:
    """A stored MJCF that names another file (written by hand, or by a MuJoCo that keeps a reference)
    cannot read it at load time either."""
    hostile = DECOY.replace("<worldbody>", f"<include file='{secret / 'model.xml'}'/><worldbody>", 1)
    with pytest.raises(Exception, match=r"opening file|Error") as info:
        sandbox.compile_xml(hostile, {})
    assert "stolen" not in str(info.value)
    m = sandbox.compile_xml(DECOY, {})
    assert (m.nv, m.nu) == (1, 1)
    assert sandbox.compile_xml(DECOY, {}) is not m  # a fresh model from the cache each time


def test_the_child_can_open_no_path(tmp_path: Path) -> None:
    """Landlock itself: after ``deny_all`` a process can read, list or write nothing, even /tmp."""
    probe = tmp_path / "probe.txt"
    probe.write_text("x")
    code = (
        "from neuroanimator.sim import landlock; import os, sys\n"
        "landlock.deny_all()\n"
        "bad = []\n"
        f"for f in (lambda: open({str(probe)!r}).read(), lambda: os.listdir('/'), "
        f"lambda: open({str(tmp_path / 'new.txt')!r}, 'w')):\n"
        "    try: f(); bad.append(1)\n"
        "    except PermissionError: pass\n"
        "sys.exit(len(bad))\n"
    )
    root = Path(__file__).resolve().parents[2]
    assert subprocess.run([sys.executable, "-c", code], cwd=root, timeout=60).returncode == 0
    assert landlock.abi_version() >= 1


def test_a_child_starved_of_cpu_is_not_called_costly() -> None:
    """A child killed at the wall-clock deadline before it used its CPU cap (a busy machine: it runs at
    the lowest priority) is told apart from one that used the cap up: try again, not "too big"."""
    with pytest.raises(SourceError, match="machine is busy") as busy:
        sandbox._no_reply(-signal.SIGKILL, Limits(compile_seconds=10.0), waited_out=True)
    assert "35 s" in str(busy.value) and "COMPILE_SECONDS" not in str(busy.value)
    with pytest.raises(SourceError, match="COMPILE_SECONDS"):
        sandbox._no_reply(-signal.SIGXCPU, Limits(compile_seconds=10.0), waited_out=False)


def test_costly_models_are_stopped_by_the_caps(tmp_path: Path) -> None:
    """A replicate of thousands of bodies (MuJoCo's parser takes minutes) stops at the time cap; an XML
    over the size cap is refused before MuJoCo reads it."""
    replicate = DECOY.replace("<body>", '<replicate count="30000" offset="0.1 0 0"><body>', 1).replace(
        "</body>", "</body></replicate>", 1
    )
    (tmp_path / "rep.xml").write_text(replicate)
    t0 = time.monotonic()
    with pytest.raises(SourceError) as info:
        load_bundle(tmp_path / "rep.xml", limits=Limits(compile_seconds=3.0))
    assert info.value.kind == "too_costly" and "COMPILE_SECONDS" in str(info.value)
    assert time.monotonic() - t0 < 10.0
    big = tmp_path / "big.zip"
    with zipfile.ZipFile(big, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("m/model.xml", DECOY.replace("<worldbody>", "<worldbody>" + " " * (9 << 20), 1))
    with pytest.raises(SourceError) as info:
        load_bundle(big, limits=Limits(max_ratio=1e6))
    assert info.value.kind == "file_too_large" and "m/model.xml" in str(info.value)


@pytest.mark.parametrize(("timestep", "words"), [("0", "positive"), ("-0.01", "positive"), ("1e-8", "floor")])
def test_degenerate_timesteps(tmp_path: Path, timestep: str, words: str) -> None:
    err = refusal(tmp_path, "t", DECOY.replace("<worldbody>", f'<option timestep="{timestep}"/><worldbody>'))
    assert err.kind == "bad_timestep" and words in str(err), str(err)
