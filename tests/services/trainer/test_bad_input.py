"""Bad uploads through ``POST /trainings``: each answered at once with a 4xx naming the problem, and
nothing written (no upload kept, no model folder, nothing queued). Trainings that fail later (a model
that diverges, or samples too slowly) are in test_e2e.py."""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.services.trainer.trn import TINY, TINYBOT, Trainer, tarred, upload, zipped

ROBOT = (TINYBOT / "robot.xml").read_text()
ARM = (TINYBOT / "parts" / "arm.xml").read_text()


@pytest.fixture(name="trn", scope="module")
def trn_fixture(redis_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Trainer]:
    t = Trainer(redis_url, tmp_path_factory.mktemp("trainer"), MAX_UPLOAD_BYTES="200000")
    try:
        yield t
    finally:
        t.close()


@pytest.fixture(name="api", scope="module")
def api_fixture(trn: Trainer) -> TestClient:
    return trn.client()


def folder_with(tmp: Path, robot: str = ROBOT, arm: str = ARM) -> Path:
    folder = tmp / "tinybot"
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(TINYBOT, folder)
    (folder / "robot.xml").write_text(robot)
    (folder / "parts" / "arm.xml").write_text(arm)
    return folder


def refused(
    api: TestClient, trn: Trainer, status: int, error: str, filename: str, data: bytes, **fields: str
) -> Any:
    """Upload; check the answer's status and error code, and that nothing was kept; the error body."""
    before = trn.models()
    t0 = time.monotonic()
    r = upload(api, filename, data, **{**TINY, **fields})
    took = time.monotonic() - t0
    assert r.status_code == status, r.text
    body = r.json()
    assert body["error"] == error, body
    assert took < 3.0, took  # answered at once (about 0.1 s here; 3 s is a loaded machine's margin)
    assert trn.models() == before  # no model folder claimed
    uploads = trn.settings().uploads()
    assert not uploads.exists() or not any(uploads.iterdir())  # the upload is not kept
    queued = [t for t in api.get("/trainings").json()["trainings"] if t["status"] == "queued"]
    assert queued == []  # nothing queued
    return body


def test_not_xml(api: TestClient, trn: Trainer) -> None:
    body = refused(api, trn, 422, "not_xml", "model.xml", b"this is not xml <")
    assert "model.xml is not XML" in body["message"] and body["field"] == "file"
    body = refused(api, trn, 422, "not_xml", "model.xml", b"<robot/>")
    assert "root element is <robot>" in body["message"]


def test_a_compile_error_names_the_file_and_line(api: TestClient, trn: Trainer, tmp_path: Path) -> None:
    folder = folder_with(tmp_path, arm=ARM.replace('type="hinge"', 'type="hinje"'))
    body = refused(api, trn, 422, "compile_error", "tinybot.zip", zipped(folder))
    assert "MuJoCo cannot load the model" in body["message"]
    assert "parts/arm.xml, line 3" in body["message"] and "hinje" in body["message"]


def test_a_missing_include_is_named(api: TestClient, trn: Trainer) -> None:
    body = refused(api, trn, 422, "missing_file", "robot.xml", ROBOT.encode())  # the XML alone
    assert "parts/arm.xml" in body["message"] and "missing" in body["message"]


def test_a_missing_asset_is_named(api: TestClient, trn: Trainer, tmp_path: Path) -> None:
    folder = folder_with(tmp_path)
    (folder / "assets" / "knob.obj").unlink()
    body = refused(
        api,
        trn,
        422,
        "missing_file",
        "tinybot.tar.gz",
        tarred(
            {
                f"tinybot/{p.relative_to(folder).as_posix()}": p.read_bytes()
                for p in folder.rglob("*")
                if p.is_file()
            }
        ),
    )
    assert "knob.obj" in body["message"]


@pytest.mark.parametrize(
    ("members", "links", "words"),
    [
        ({"../evil.xml": b"<mujoco/>"}, {}, "climbs out"),
        ({"/etc/model.xml": b"<mujoco/>"}, {}, "absolute path"),
        ({"m/model.xml": b"<mujoco/>"}, {"m/link.xml": "/etc/passwd"}, "is a link"),
    ],
)
def test_unsafe_archive_entries(
    api: TestClient, trn: Trainer, members: dict[str, bytes], links: dict[str, str], words: str
) -> None:
    body = refused(api, trn, 422, "unsafe_archive", "model.tar.gz", tarred(members, links))
    assert words in body["message"]


def test_archive_bombs_are_refused_while_extracting(api: TestClient, trn: Trainer, tmp_path: Path) -> None:
    # 16 MiB of zeros in a zip of a few kB: past the first 4 MiB, over 100 times the archive's size
    bomb = zipped(folder_with(tmp_path), extra={"tinybot/zeros.bin": bytes(16 << 20)})
    assert len(bomb) < 100_000
    body = refused(api, trn, 413, "archive_too_large", "tinybot.zip", bomb)
    assert "compression bomb" in body["message"]
    many = zipped(folder_with(tmp_path), extra={f"tinybot/f{i}.txt": b"x" for i in range(10)})
    capped = trn.client(max_archive_files=8)
    r = upload(capped, "tinybot.zip", many, **TINY)
    assert r.status_code == 413 and "more than 8 files" in r.json()["message"], r.text


def test_an_upload_over_the_cap_is_refused_before_it_is_read(api: TestClient, trn: Trainer) -> None:
    big = bytes(300_000)  # MAX_UPLOAD_BYTES is 200,000 here
    body = refused(api, trn, 413, "body_too_large", "model.zip", big)
    assert "200000 bytes" in body["message"]
    read = 0

    def chunks() -> Iterator[bytes]:  # no Content-Length: counted as it streams, refused past the cap
        nonlocal read
        head = b'--b\r\nContent-Disposition: form-data; name="file"; filename="m.zip"\r\n\r\n'
        yield head
        for _ in range(100):
            read += 65_536
            yield bytes(65_536)

    r = api.post("/trainings", content=chunks(), headers={"Content-Type": "multipart/form-data; boundary=b"})
    assert r.status_code == 413 and r.json()["error"] == "body_too_large", r.text


def test_a_mesh_over_the_vertex_cap(trn: Trainer) -> None:
    capped = trn.client(max_mesh_vertices=7)
    r = upload(capped, "tinybot.zip", zipped(TINYBOT), **TINY)
    assert r.status_code == 422 and r.json()["error"] == "mesh_too_large", r.text
    assert "8 vertices" in r.json()["message"]


def test_plugins_other_than_mujocos_own(api: TestClient, trn: Trainer, tmp_path: Path) -> None:
    robot = ROBOT.replace("<asset>", '<extension><plugin plugin="acme.thrusters"/></extension>\n  <asset>')
    body = refused(api, trn, 422, "plugin_refused", "tinybot.zip", zipped(folder_with(tmp_path, robot=robot)))
    assert "acme.thrusters" in body["message"] and "first-party" in body["message"]


NO_JOINTS = '<mujoco><worldbody><body><geom type="box" size=".1 .1 .1"/></body></worldbody></mujoco>'
NO_ACTUATORS = '<mujoco><worldbody><body><joint type="hinge"/><geom size=".1"/></body></worldbody></mujoco>'
NO_RANGE = """<mujoco><compiler autolimits="true"/><worldbody><body><joint name="j" type="hinge"/>
<geom size=".1"/></body></worldbody><actuator><motor name="ok" joint="j" ctrlrange="-1 1"/>
<motor name="free" joint="j"/></actuator></mujoco>"""


@pytest.mark.parametrize(
    ("xml", "error", "words"),
    [
        (NO_JOINTS, "no_joints", "no joints"),
        (NO_ACTUATORS, "no_actuators", "no actuators"),
        (NO_RANGE, "no_ctrlrange", "actuator 'free' has no ctrlrange"),
    ],
)
def test_models_an_emulator_cannot_be_made_of(
    api: TestClient, trn: Trainer, xml: str, error: str, words: str
) -> None:
    body = refused(api, trn, 422, error, "model.xml", xml.encode())
    assert words in body["message"]


@pytest.mark.parametrize("where", ["data", "defaults"])
def test_names_of_models_that_were_not_uploaded_are_taken(api: TestClient, trn: Trainer, where: str) -> None:
    # one trained on the server (no owner file), or a committed default's: neither is an upload's to take
    taken = (trn.data if where == "data" else trn.defaults) / "tinybot"
    taken.mkdir()
    try:
        body = refused(api, trn, 409, "name_taken", "tinybot.zip", zipped(TINYBOT))
        assert "is not available" in body["message"] and body["field"] == "name"
        assert not (trn.data / "tinybot" / "owner.json").exists()  # nothing claimed beside the default
    finally:
        taken.rmdir()


def test_the_policy_registrys_name_is_no_models(api: TestClient, trn: Trainer) -> None:
    # a model named so would hold every policy beside it, and its owner's delete would remove them
    body = refused(api, trn, 409, "name_taken", "tinybot.zip", zipped(TINYBOT), name="policies")
    assert "policy registry" in body["message"] and body["field"] == "name", body
    assert not (trn.data / "policies").exists()


def test_what_is_not_a_model_upload(api: TestClient, trn: Trainer) -> None:
    body = refused(api, trn, 415, "unsupported_file", "model.rar", b"Rar!")
    assert ".zip" in body["message"]
    r = api.post("/trainings", json={"file": "x"})
    assert r.status_code == 415 and r.json()["error"] == "unsupported_media_type", r.text
    r = api.post("/trainings", files={"other": ("a.xml", b"<mujoco/>")})
    assert r.status_code == 422 and r.json()["field"] == "file", r.text
    body = refused(api, trn, 422, "invalid_request", "tinybot.zip", zipped(TINYBOT), super_step="0")
    assert body["field"] == "super_step"
    body = refused(api, trn, 422, "invalid_request", "tinybot.zip", zipped(TINYBOT), examples="10")
    assert body["field"] == "examples"
    body = refused(api, trn, 422, "invalid_request", "tinybot.zip", zipped(TINYBOT), colour="red")
    assert body["field"] == "colour"


def test_a_good_upload_is_queued_and_cancelled(api: TestClient, trn: Trainer) -> None:
    t0 = time.monotonic()
    r = upload(api, "tinybot.zip", zipped(TINYBOT), **TINY)
    assert r.status_code == 202, r.text
    assert time.monotonic() - t0 < 3.0
    got = r.json()
    assert (got["status"], got["phase"], got["model"], got["new_version"]) == (
        "queued",
        "queued",
        "tinybot",
        False,
    )
    assert r.headers["location"] == f"/trainings/{got['id']}"
    status = api.get(f"/trainings/{got['id']}").json()
    assert (status["super_step"], status["examples"], status["percent"]) == (10, 200, 0.0)
    assert (trn.data / "tinybot" / "owner.json").is_file()  # the name is claimed
    r = api.delete(f"/trainings/{got['id']}")
    assert r.status_code == 202 and r.json()["status"] == "cancelled", r.text
    assert not (trn.data / "tinybot").exists()  # given back: nothing was trained under it
    assert not any(trn.settings().uploads().iterdir())
    assert api.delete(f"/trainings/{got['id']}").status_code == 409
