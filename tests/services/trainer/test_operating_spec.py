"""An upload's operating spec (docs/operating-spec.md) through ``POST /trainings``: the form field
``operating_spec`` (JSON) and ``keyframe``, else an ``operating.json`` at the top of the archive.

A spec that is not JSON, not an operating spec, or does not fit the model (an actuator, joint or
keyframe it lacks, a range outside its ``ctrlrange``) is refused at once with 422 naming the field,
and nothing is written; a good one is queued with the training, handed to ``neuro train --spec``, and
the trained emulator's manifest, the training's notes and the emulator service's ``GET /models/{model}``
say which operating point it was trained around. Models: Menagerie's Skydio X2 (tests/data/skydio_x2:
keyframe ``hover``, actuators thrust1..thrust4 over 0..13) and the project's tinybot."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from neuroanimator import cli
from neuroanimator.artifacts import registry
from neuroanimator.core.operating_spec import OperatingSpec
from services.emulator.app import create_app as emulator_app
from services.emulator.settings import Settings as EmulatorSettings
from services.trainer import run
from services.trainer.spec import ChildSpec, TrainingSpec
from services.trainer.store import TrainingStore
from tests.services.trainer.trn import ROOT, TINY, TINYBOT, Trainer, ended, tarred, upload, zipped

X2 = ROOT / "tests" / "data" / "skydio_x2"
HOVER_SPEC = {"keyframe": "hover", "controls": {"thrust1": {"range": [2.0, 5.0]}}, "held_share": 0.3}


@pytest.fixture(name="trn", scope="module")
def trn_fixture(redis_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Trainer]:
    t = Trainer(redis_url, tmp_path_factory.mktemp("trainer"), JOB_TIMEOUT_S="120")
    try:
        yield t
    finally:
        t.close()


@pytest.fixture(name="api", scope="module")
def api_fixture(trn: Trainer) -> TestClient:
    return trn.client()


@pytest.fixture(name="x2_zip", scope="module")
def x2_zip_fixture() -> bytes:
    return zipped(X2, top="skydio_x2")


def nothing_kept(api: TestClient, trn: Trainer) -> None:
    assert trn.models() == []  # no model folder claimed
    uploads = trn.settings().uploads()
    assert not uploads.exists() or not any(uploads.iterdir())  # the upload is not kept
    assert [t for t in api.get("/trainings").json()["trainings"] if t["status"] == "queued"] == []


def refused(api: TestClient, trn: Trainer, name: str, data: bytes, **fields: str) -> dict[str, Any]:
    """Upload; a 422 ``invalid_operating_spec`` answered at once, nothing kept; the error body."""
    t0 = time.monotonic()
    r = upload(api, name, data, **{**TINY, **fields})
    assert r.status_code == 422, r.text
    assert time.monotonic() - t0 < 5.0
    body: dict[str, Any] = r.json()
    assert body["error"] == "invalid_operating_spec", body
    nothing_kept(api, trn)
    return body


def test_an_unknown_actuator_is_refused_naming_it(api: TestClient, trn: Trainer, x2_zip: bytes) -> None:
    spec = {"controls": {"thrust9": {"centre": 3.25, "spread": 1.0}}}
    body = refused(api, trn, "x2.zip", x2_zip, operating_spec=json.dumps(spec))
    assert body["field"] == "operating_spec.controls.thrust9"
    assert "no actuator 'thrust9'" in body["message"] and "'thrust1'" in body["message"]  # the known ones


def test_a_spec_that_does_not_fit_the_model_is_refused(api: TestClient, trn: Trainer, x2_zip: bytes) -> None:
    outside = {"controls": {"thrust2": {"range": [0, 20]}}}
    body = refused(api, trn, "x2.zip", x2_zip, operating_spec=json.dumps(outside))
    assert body["field"] == "operating_spec.controls.thrust2" and "ctrlrange [0, 13]" in body["message"]
    body = refused(api, trn, "x2.zip", x2_zip, operating_spec=json.dumps({"keyframe": "cruise"}))
    assert body["field"] == "operating_spec.keyframe" and "'hover'" in body["message"]
    body = refused(api, trn, "x2.zip", x2_zip, keyframe="cruise")  # the form's own field
    assert body["field"] == "keyframe" and "no keyframe 'cruise'" in body["message"]
    joints = {"start": {"joints": {"elbow": 0.1}}}
    body = refused(api, trn, "x2.zip", x2_zip, operating_spec=json.dumps(joints))
    assert body["field"] == "operating_spec.start.joints.elbow"


def test_a_spec_that_is_not_one_is_refused_before_the_model_is_read(
    api: TestClient, trn: Trainer, x2_zip: bytes
) -> None:
    body = refused(api, trn, "x2.zip", x2_zip, operating_spec='{"controls": {')
    assert body["field"] == "operating_spec" and body["message"].startswith("operating_spec is not JSON")
    body = refused(api, trn, "x2.zip", x2_zip, operating_spec="[1, 2]")
    assert body["field"] == "operating_spec"
    backwards = {"controls": {"thrust1": {"range": [5, 2]}}}
    body = refused(api, trn, "x2.zip", x2_zip, operating_spec=json.dumps(backwards))
    assert body["field"] == "operating_spec.controls.thrust1" and "low above high" in body["message"]
    body = refused(api, trn, "x2.zip", x2_zip, operating_spec=json.dumps({"held_share": 2}))
    assert body["field"] == "operating_spec.held_share"
    body = refused(api, trn, "x2.zip", x2_zip, operating_spec=json.dumps({"thrust": 1}))
    assert body["field"] == "operating_spec.thrust" and "Extra inputs" in body["message"]


def _queued(trn: Trainer, api: TestClient, r: Any) -> TrainingSpec:
    """The queued training's spec (the training is then cancelled: no worker runs here)."""
    assert r.status_code == 202, r.text
    tid = r.json()["id"]
    store = TrainingStore(trn.r, trn.settings())
    rec = store.record(tid)
    assert rec is not None
    assert api.delete(f"/trainings/{tid}").status_code == 202
    return TrainingSpec.model_validate_json(rec.spec)


def test_a_good_spec_is_queued_and_reaches_neuro_train(
    api: TestClient, trn: Trainer, x2_zip: bytes, tmp_path: Path
) -> None:
    r = upload(api, "x2.zip", x2_zip, operating_spec=json.dumps(HOVER_SPEC), **TINY)
    message = r.json()["message"]
    assert "operating point from keyframe: keyframe 'hover', as asked" in message
    assert message.endswith(
        "with the operating spec of the form field operating_spec; queued to train a new model"
    )
    queued = _queued(trn, api, r)
    assert OperatingSpec.model_validate_json(queued.operating_spec or "") == OperatingSpec(**HOVER_SPEC)
    nothing_kept(api, trn)  # cancelled: its upload removed and its name given back

    # the training's process writes it into its staging folder and names it to neuro train
    child = ChildSpec(
        **queued.model_dump(exclude={"keyframe"}),
        keyframe="hover",
        staging=str(tmp_path),
        limits={},
        time_limit_s=60,
        eval_trials=1,
        eval_seconds=1,
    )
    run.write_spec(child, tmp_path)
    argv = run.train_argv(child, tmp_path)
    assert argv[argv.index("--spec") + 1] == str(tmp_path / run.SPEC_FILE)
    assert argv[argv.index("--keyframe") + 1] == "hover"
    args = cli.build_parser().parse_args(argv)
    assert cli.read_operating_spec(args.spec) == OperatingSpec(**HOVER_SPEC)
    plain = run.train_argv(child.model_copy(update={"operating_spec": None, "keyframe": None}), tmp_path)
    assert "--spec" not in plain and "--keyframe" not in plain


def test_the_archives_operating_json(api: TestClient, trn: Trainer) -> None:
    bad = {"controls": {"thrust9": {"centre": 3.0}}}
    data = zipped(X2, top="skydio_x2", extra={"skydio_x2/operating.json": json.dumps(bad).encode()})
    body = refused(api, trn, "x2.zip", data)
    assert body["field"] == "file"
    assert "skydio_x2/operating.json in x2.zip" in body["message"] and "controls.thrust9" in body["message"]
    body = refused(api, trn, "x2.zip", zipped(X2, top="skydio_x2", extra={"operating.json": b"{oops"}))
    assert "operating.json is not JSON" in body["message"]

    # at the top of a .tar.gz of the model's files
    files = {p.relative_to(X2).as_posix(): p.read_bytes() for p in X2.rglob("*") if p.is_file()}
    files["operating.json"] = json.dumps(HOVER_SPEC).encode()
    r = upload(api, "x2.tar.gz", tarred(files), **TINY)
    assert "with the operating spec of operating.json in x2.tar.gz" in r.json()["message"], r.text
    assert OperatingSpec.model_validate_json(_queued(trn, api, r).operating_spec or "") == OperatingSpec(
        **HOVER_SPEC
    )
    # the form's spec comes first: the archive's is not read
    r = upload(api, "x2.zip", data, operating_spec=json.dumps({"control_spread": 0.2}), **TINY)
    assert "with the operating spec of the form field operating_spec" in r.json()["message"], r.text
    assert _queued(trn, api, r).operating_spec == '{"control_spread":0.2}'
    nothing_kept(api, trn)


TINY_SPEC = {"controls": {"motor": {"centre": 0.2, "spread": 0.3}}, "held_share": 0.25, "run_s": 4.0}


def test_trained_around_the_spec_and_reported(trn: Trainer, api: TestClient) -> None:
    """A tiny training with a spec: the notes say which operating point and why, the manifest keeps the
    record, the emulator service reports it."""
    trn.worker()
    r = upload(api, "tinybot.zip", zipped(TINYBOT), operating_spec=json.dumps(TINY_SPEC), **TINY)
    assert r.status_code == 202, r.text
    done = ended(api, r.json()["id"])
    assert done["status"] == "succeeded", (done, trn.logs())
    notes = done["result"]["notes"]
    point = [n for n in notes if n.startswith("operating point from ")]
    assert len(point) == 1, notes
    manifest = registry.read_manifest(trn.data / "tinybot" / done["result"]["version"])
    record = manifest.spec.operating
    assert record is not None and record.spec == OperatingSpec(**TINY_SPEC)
    assert point[0] == record.describe() and record.held_share == 0.25

    emulator = TestClient(
        emulator_app(
            EmulatorSettings(
                data_dir=trn.data,
                artifacts_dir=trn.defaults,
                redis_url="",
                api_keys="",
                api_key_secret="test-secret",
                registry_poll_s=0.1,
            )
        )
    )
    with emulator:
        detail = emulator.get("/models/tinybot").json()
    assert detail["operating"] == record.model_dump(mode="json")
    assert detail["operating"]["spec"]["controls"] == {"motor": {"centre": 0.2, "spread": 0.3, "range": None}}


def test_a_catalog_model_has_no_operating_record(tmp_path: Path) -> None:
    shutil.copytree(ROOT / "artifacts" / "pendulum-passive", tmp_path / "pendulum-passive")
    settings = EmulatorSettings(
        artifacts_dir=tmp_path, data_dir=tmp_path / "data", redis_url="", api_keys="", registry_poll_s=0.0
    )
    with TestClient(emulator_app(settings)) as client:
        detail = client.get("/models/pendulum-passive")
        assert detail.status_code == 200, detail.text
        assert "operating" in detail.json() and detail.json()["operating"] is None
