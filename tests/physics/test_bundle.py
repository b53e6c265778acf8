"""Models as shipped (``neuroanimator.sim.bundle``): an MJCF with includes and assets, a model folder,
a .zip or .tar.gz of one, dm_control's suite XMLs; and every kind of bad input, refused with a message
that names the problem."""

from __future__ import annotations

import importlib.util
import io
import shutil
import tarfile
import warnings
import zipfile
from pathlib import Path

import mujoco
import pytest

from neuroanimator.sim.bundle import Limits, SourceError
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.sandbox import load_bundle

ROOT = Path(__file__).resolve().parents[2]
TINYBOT = ROOT / "tests" / "data" / "tinybot"


def copy_tinybot(tmp: Path) -> Path:
    dest = tmp / "tinybot"
    shutil.copytree(TINYBOT, dest)
    return dest


def zip_folder(folder: Path, archive: Path, prefix: str = "tinybot/") -> Path:
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                zf.write(p, prefix + p.relative_to(folder).as_posix())
    return archive


def tar_folder(folder: Path, archive: Path) -> Path:
    with tarfile.open(archive, "w:gz") as tf:
        tf.add(folder, arcname="tinybot")
    return archive


# ---------------------------------------------------------------------------- what loads
def test_a_folder_with_an_include_a_mesh_and_a_texture(tmp_path: Path) -> None:
    b = load_bundle(TINYBOT)
    assert b.entry == "robot.xml" and b.files == ("robot.xml", "parts/arm.xml")
    kinds = sorted((a.kind, a.source) for a in b.assets)
    assert kinds == [("mesh", "assets/knob.obj"), ("texture", "assets/checker.png")]  # not unused.obj
    for a in b.assets:
        assert a.name.startswith(a.sha256) and a.name in b.xml
    assert "<include" not in b.xml and "assetdir" not in b.xml and "meshdir" not in b.xml
    m = mujoco.MjModel.from_xml_string(b.xml, b.vfs())
    assert (m.nmesh, m.ntex, int(m.mesh_vertnum[0])) == (1, 1, 8)


def test_the_entry_file_a_zip_and_a_tar_gz_give_the_same_bundle(tmp_path: Path) -> None:
    folder = load_bundle(TINYBOT)
    for source, entry in (
        (TINYBOT / "robot.xml", None),
        (zip_folder(TINYBOT, tmp_path / "tinybot.zip"), None),
        (tar_folder(TINYBOT, tmp_path / "tinybot.tar.gz"), "robot.xml"),
        (zip_folder(TINYBOT, tmp_path / "named.zip"), "tinybot/robot.xml"),
    ):
        b = load_bundle(source, entry)
        assert b.xml == folder.xml and b.vfs() == folder.vfs(), source


def test_a_self_contained_mjcf_becomes_mujocos_own_and_the_same_model(arm_path: Path) -> None:
    """Never kept as written: what is stored is what MuJoCo parsed (no DOCTYPE, comments or includes)."""
    b = load_bundle(arm_path)
    assert b.assets == () and "<!--" not in b.xml
    ours = mujoco.MjModel.from_xml_string(b.xml)
    theirs = mujoco.MjModel.from_xml_path(str(arm_path))
    assert (ours.nq, ours.nv, ours.nu, ours.nbody) == (theirs.nq, theirs.nv, theirs.nu, theirs.nbody)
    assert ours.body_mass.tolist() == theirs.body_mass.tolist() and ours.opt.timestep == theirs.opt.timestep


def test_load_mjcf_builds_the_model_from_the_bundle(tmp_path: Path) -> None:
    model = load_mjcf(zip_folder(TINYBOT, tmp_path / "tinybot.zip"))
    assert model.name == "tinybot" and model.control_names == ["motor"]
    assert sorted(model.assets) == sorted(load_bundle(TINYBOT).vfs())
    assert model.mj_model.nmesh == 1


@pytest.mark.parametrize(
    "name", ["walker", "fish", "cheetah", "finger", "ball_in_cup", "hopper", "humanoid", "pendulum"]
)
def test_dm_control_suite_xmls_load_as_shipped(name: str) -> None:
    """They include ./common/materials.xml, skybox.xml and visual.xml."""
    spec = importlib.util.find_spec("dm_control")
    if spec is None or spec.origin is None:
        pytest.skip("dm_control is not installed (make install installs the dev dependencies)")
    suite = Path(spec.origin).parent / "suite"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # some use compiler attributes MuJoCo deprecates
        model = load_mjcf(suite / f"{name}.xml")
    assert "<include" not in model.xml and model.num_controls >= 1
    assert "/" not in model.name and " " not in model.name  # a folder name: "planar walker" -> planar-walker


# ---------------------------------------------------------------------------- what is refused
def refused(kind: str, source: Path, entry: str | None = None, limits: Limits | None = None) -> str:
    with pytest.raises(SourceError) as info:
        load_bundle(source, entry, limits)
    assert info.value.kind == kind, str(info.value)
    return str(info.value)


def test_not_xml(tmp_path: Path) -> None:
    (tmp_path / "m.xml").write_text("<mujoco><worldbody>")
    assert "m.xml is not XML" in refused("not_xml", tmp_path / "m.xml")
    (tmp_path / "n.xml").write_text("<html><body/></html>")
    assert "<html>" in refused("not_xml", tmp_path / "n.xml")


def test_a_compile_error_names_the_included_file_and_line(tmp_path: Path) -> None:
    folder = copy_tinybot(tmp_path)
    arm = folder / "parts" / "arm.xml"
    arm.write_text(arm.read_text().replace('name="rod"', 'name="rod" bogus="1"'))
    msg = refused("compile_error", folder)
    assert "parts/arm.xml, line 4" in msg and "bogus" in msg


def test_a_missing_include_or_asset_is_named(tmp_path: Path) -> None:
    folder = copy_tinybot(tmp_path)
    (folder / "assets" / "knob.obj").unlink()
    assert "knob.obj" in refused("missing_file", folder)
    (folder / "parts" / "arm.xml").unlink()
    assert "parts/arm.xml" in refused("missing_file", folder)


def test_files_outside_the_model_folder_are_refused(tmp_path: Path) -> None:
    folder = copy_tinybot(tmp_path)
    (tmp_path / "secret.obj").write_bytes((folder / "assets" / "knob.obj").read_bytes())
    xml = folder / "robot.xml"
    xml.write_text(xml.read_text().replace('file="knob.obj"', 'file="../../secret.obj"'))
    assert "outside the model's folder" in refused("outside_model", folder)


def test_plugins_other_than_mujocos_own_are_refused(tmp_path: Path) -> None:
    folder = copy_tinybot(tmp_path)
    xml = folder / "robot.xml"
    xml.write_text(
        xml.read_text().replace(
            "<asset>", '<extension><plugin plugin="acme.thrusters"/></extension>\n  <asset>'
        )
    )
    assert "acme.thrusters" in refused("plugin_refused", folder)


def test_a_mesh_over_the_vertex_cap(tmp_path: Path) -> None:
    assert "8 vertices" in refused("mesh_too_large", TINYBOT, limits=Limits(max_mesh_vertices=7))


def test_the_entry_must_be_found(tmp_path: Path) -> None:
    folder = copy_tinybot(tmp_path)
    shutil.copy(folder / "robot.xml", folder / "robot2.xml")
    assert "--entry" in refused("entry", folder)
    assert load_bundle(folder, "robot2.xml").entry == "robot2.xml"
    assert "no MJCF" in refused("entry", folder, "nothere.xml")


def zip_with(tmp: Path, members: dict[str, bytes], links: tuple[str, ...] = ()) -> Path:
    archive = tmp / "model.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            info = zipfile.ZipInfo(name)
            if name in links:
                info.external_attr = 0o120777 << 16  # a symbolic link
            zf.writestr(info, data)
    return archive


def test_archive_entries_that_climb_out_are_absolute_or_links(tmp_path: Path) -> None:
    xml = (TINYBOT / "robot.xml").read_bytes()
    assert "'..'" in refused("unsafe_archive", zip_with(tmp_path, {"m/robot.xml": xml, "../evil.xml": b"x"}))
    assert "absolute" in refused("unsafe_archive", zip_with(tmp_path, {"/etc/evil.xml": b"x"}))
    assert "link" in refused(
        "unsafe_archive", zip_with(tmp_path, {"m/robot.xml": xml, "m/l": b"/etc/passwd"}, ("m/l",))
    )
    archive = tmp_path / "link.tar.gz"
    with tarfile.open(archive, "w:gz") as tf:
        info = tarfile.TarInfo("m/passwd.obj")
        info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
        tf.addfile(info)
    assert "link" in refused("unsafe_archive", archive)
    archive = tmp_path / "climb.tar.gz"
    with tarfile.open(archive, "w:gz") as tf:
        info = tarfile.TarInfo("../../evil.xml")
        info.size = 1
        tf.addfile(info, io.BytesIO(b"x"))
    assert "'..'" in refused("unsafe_archive", archive)


def test_archive_bombs_are_stopped_while_extracting(tmp_path: Path) -> None:
    """A zip of 64 MiB of zeros is 64 kB: refused by its ratio after a few MiB, not after 64."""
    archive = tmp_path / "bomb.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf, zf.open("m/big.obj", "w") as out:
        for _ in range(64):
            out.write(bytes(1 << 20))
    assert archive.stat().st_size < 1 << 20
    assert "compression bomb" in refused("archive_too_large", archive)
    assert "bytes once extracted" in refused(
        "archive_too_large", archive, limits=Limits(max_bytes=1 << 20, max_file_bytes=1 << 30)
    )
    many = zip_with(tmp_path, {f"m/{i}.txt": b"x" for i in range(20)})
    assert "more than 10 files" in refused("archive_too_large", many, limits=Limits(max_files=10))


def test_a_file_over_the_per_file_cap(tmp_path: Path) -> None:
    archive = tmp_path / "big.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("m/a.obj", bytes(3 << 20))
    assert "one such file may have" in refused(
        "file_too_large", archive, limits=Limits(max_file_bytes=1 << 20)
    )
