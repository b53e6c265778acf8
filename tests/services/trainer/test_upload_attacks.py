"""The upload probe as tests: what an attacker (key B) and a careless user send to ``POST /trainings``.

Another tenant's stored model is a real folder in the test's registry; the server's own files are real.
Every case is a 4xx naming the problem, with no server path in it, nothing kept and nothing claimed;
per-key limits hold under concurrent uploads (a real uvicorn server, ten threads). The costly cases
(a 60 MB XML, a 30,000-body replicate, /healthz while they are checked) are in
``bench/upload_probe.py``."""

from __future__ import annotations

import io
import tarfile
import threading
import zipfile
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from neuroanimator.sim import sandbox
from tests.services.trainer.trn import KEYS, TINY, TINYBOT, Trainer, auth, serve, upload, zipped

pytestmark = pytest.mark.skipif(not sandbox.available(), reason="this kernel has no Linux Landlock")

SECRET = """<mujoco model="secret-a"><worldbody><body name="stolen_body"><joint name="stolen_joint"
type="hinge"/><geom size=".1"/></body></worldbody><actuator><motor name="stolen_motor"
joint="stolen_joint" ctrlrange="-7 7"/></actuator></mujoco>"""
DECOY = """<mujoco model="decoy"><worldbody><body><joint name="h" type="hinge"/><geom size=".1"/></body>
</worldbody><actuator><motor joint="h" ctrlrange="-1 1"/></actuator></mujoco>"""


def doctype_include(target: str) -> bytes:
    return (
        '<!DOCTYPE x [<!ENTITY a ">\n'
        f"<mujoco model='s'><include file='{target}'/></mujoco>\n"
        '<!-- ">]>\n' + DECOY + "\n<!-- -->\n"
    ).encode()


def flexcomp(target: str) -> bytes:
    return DECOY.replace(
        "<worldbody>", f'<worldbody><flexcomp name="f" type="mesh" dim="2" file="{target}"/>', 1
    ).encode()


@pytest.fixture(name="trn", scope="module")
def trn_fixture(redis_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Trainer]:
    t = Trainer(redis_url, tmp_path_factory.mktemp("trainer"), MAX_TRAININGS_PER_KEY="2", **KEYS)
    secret = t.data / "secret-a" / "v1"  # key A's stored model, as the registry keeps it
    secret.mkdir(parents=True)
    (secret / "model.xml").write_text(SECRET)
    try:
        yield t
    finally:
        t.close()


@pytest.fixture(name="api", scope="module")
def api_fixture(trn: Trainer) -> TestClient:
    return trn.client()


def refused(
    api: TestClient,
    trn: Trainer,
    filename: str,
    data: bytes,
    echo: str = "",
    status: int = 422,
    **fields: str,
) -> Any:
    """The refusal of an upload by key B; ``echo``: a path the upload names (its own words may come back)."""
    before = trn.models()
    r = upload(api, filename, data, key="key-b", **{**TINY, **fields})
    assert r.status_code == status, r.text
    text = r.text.replace(echo, "") if echo else r.text
    assert str(trn.tmp) not in text and "/tmp" not in text, r.text  # no server path
    assert "stolen" not in r.text
    assert trn.models() == before
    uploads = trn.settings().uploads()
    kept = {p.name for p in uploads.iterdir()} if uploads.exists() else set()
    queued = {
        t["id"]
        for key in ("key-a", "key-b")
        for t in api.get("/trainings", headers=auth(key)).json()["trainings"]
    }
    assert kept <= queued  # only accepted uploads are kept
    return r.json()


@pytest.mark.parametrize("payload", [doctype_include, flexcomp], ids=["doctype-include", "flexcomp"])
def test_key_b_cannot_read_key_as_model_nor_the_servers_files(
    api: TestClient, trn: Trainer, payload: Any
) -> None:
    secret = str(trn.data / "secret-a" / "v1" / "model.xml")
    bodies = [
        refused(api, trn, "steal.xml", payload(target), echo=target, name="stolen-by-b")
        for target in (secret, "/etc/hostname", "/etc/no-such-file", "../../../../../../../../etc/hostname")
    ]
    assert {b["error"] for b in bodies} <= {"outside_model", "missing_file"}, bodies
    # the same words whether the file exists or not: nothing tells which files the server has
    assert bodies[1]["message"].replace("/etc/hostname", "X") == bodies[2]["message"].replace(
        "/etc/no-such-file", "X"
    )
    assert upload(api, "ok.xml", DECOY.encode(), key="key-a", **TINY).status_code == 202  # A unharmed


def _zip(members: list[tuple[str, bytes]], encrypted: bool = False) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members:
            zf.writestr(zipfile.ZipInfo(name), data)
    out = bytearray(buf.getvalue())
    if encrypted:  # the "encrypted" bit in the local and the central header (zipfile writes none)
        out[out.index(b"PK\x03\x04") + 6] |= 0x1
        out[out.index(b"PK\x01\x02") + 8] |= 0x1
    return bytes(out)


def _corrupt_deflate() -> bytes:
    data = _zip([("m/model.xml", DECOY.encode() * 50)])
    at = len(data) // 3  # the middle of the deflate stream
    return data[:at] + bytes(b ^ 0x5A for b in data[at : at + 40]) + data[at + 40 :]


def _million_folders(n: int) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for i in range(n):
            info = tarfile.TarInfo(f"d{i}")
            info.type = tarfile.DIRTYPE
            tf.addfile(info)
    return buf.getvalue()


@pytest.mark.parametrize(
    ("filename", "make", "error", "words"),
    [
        (
            "ab.zip",
            lambda: _zip([("m/a", b"x"), ("m/a/b", b"y")]),
            "unsafe_archive",
            "both a file and a folder",
        ),
        (
            "long.zip",
            lambda: _zip([("m/" + "n" * 300 + ".xml", DECOY.encode())]),
            "unsafe_archive",
            "255 bytes",
        ),
        ("deep.zip", lambda: _zip([("m/" + "d/" * 3000 + "x.xml", b"x")]), "unsafe_archive", "1024 bytes"),
        ("bad.zip", _corrupt_deflate, "unsafe_archive", "not a readable zip"),
        (
            "enc.zip",
            lambda: _zip([("m/model.xml", DECOY.encode())], encrypted=True),
            "unsafe_archive",
            "encrypted",
        ),
        ("dirs.tar.gz", lambda: _million_folders(6000), "archive_too_large", "files and folders"),
        (
            "long-name.xml",
            lambda: DECOY.replace('model="decoy"', f'model="{"x" * 300}"').encode(),
            "entry",
            "64",
        ),
        (
            "t0.xml",
            lambda: DECOY.replace("<worldbody>", '<option timestep="0"/><worldbody>').encode(),
            "bad_timestep",
            "positive",
        ),
        (
            "tneg.xml",
            lambda: DECOY.replace("<worldbody>", '<option timestep="-0.01"/><worldbody>').encode(),
            "bad_timestep",
            "positive",
        ),
        (
            "tiny.xml",
            lambda: DECOY.replace("<worldbody>", '<option timestep="1e-12"/><worldbody>').encode(),
            "bad_timestep",
            "MIN_TIMESTEP",
        ),
    ],
)
def test_archive_and_mjcf_faults_are_4xx_naming_the_problem(
    api: TestClient, trn: Trainer, filename: str, make: Any, error: str, words: str
) -> None:
    status = 413 if error in ("archive_too_large", "file_too_large") else 422
    body = refused(api, trn, filename, make(), status=status)
    assert body["error"] == error and words in body["message"], body


def test_ten_concurrent_uploads_against_a_limit_of_two_give_two_202s(
    redis_url: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    trn = Trainer(redis_url, tmp_path_factory.mktemp("trainer"), MAX_TRAININGS_PER_KEY="2", **KEYS)
    data = zipped(TINYBOT)
    with serve(trn.app(max_models_per_key=10, max_validations=10)) as base:
        answers: list[int] = []

        def one(i: int) -> None:
            with httpx.Client(base_url=base, timeout=120) as c:
                r = c.post(
                    "/trainings",
                    files={"file": ("tinybot.zip", data)},
                    data={**TINY, "name": f"conc-{i}"},
                    headers=auth("key-a"),
                )
                answers.append(r.status_code)

        threads = [threading.Thread(target=one, args=(i,)) for i in range(10)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    try:
        assert sorted(answers) == [202, 202] + [429] * 8, answers
        assert len(trn.models()) == 2, trn.models()
    finally:
        trn.close()


def test_a_refused_upload_gives_its_place_back(api: TestClient, trn: Trainer) -> None:
    for _ in range(4):  # more refusals than places: each gave its place back
        refused(
            api, trn, "t0.xml", DECOY.replace("<worldbody>", '<option timestep="0"/><worldbody>').encode()
        )
    r = upload(api, "tinybot.zip", zipped(TINYBOT), key="key-b", name="b-model", **TINY)
    assert r.status_code == 202, r.text
