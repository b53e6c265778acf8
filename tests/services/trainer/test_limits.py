"""Per-key limits and names with API keys on (no worker: trainings stay queued): concurrent trainings,
stored models and bytes each answered 429 naming the limit; a name is its uploader's (another key gets
409, the uploader a new version); the ``/models`` list and usage of each key; keys off: one pool."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.services.trainer.trn import KEYS, TINY, TINYBOT, Trainer, auth, upload, zipped

ZIP = zipped(TINYBOT)


@pytest.fixture(name="trn")
def trn_fixture(redis_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Trainer]:
    t = Trainer(redis_url, tmp_path_factory.mktemp("trainer"), MAX_TRAININGS_PER_KEY="2", **KEYS)
    try:
        yield t
    finally:
        t.close()


def test_concurrent_trainings_and_names(trn: Trainer) -> None:
    api = trn.client()
    assert api.post("/trainings", files={"file": ("m.zip", ZIP)}).status_code == 401  # keys on
    first = upload(api, "tinybot.zip", ZIP, key="key-a", **TINY)
    assert first.status_code == 202 and not first.json()["new_version"], first.text
    again = upload(api, "tinybot.zip", ZIP, key="key-a", **TINY)
    assert again.status_code == 202 and again.json()["new_version"], again.text
    assert "new version of your model 'tinybot'" in again.json()["message"]
    third = upload(api, "tinybot.zip", ZIP, key="key-a", **TINY)
    assert third.status_code == 429, third.text
    body = third.json()
    assert (body["error"], body["field"], body["got"]) == ("limit_exceeded", "MAX_TRAININGS_PER_KEY", 2)
    assert "MAX_TRAININGS_PER_KEY=2" in body["message"]
    taken = upload(api, "tinybot.zip", ZIP, key="key-b", **TINY)  # key-b: its own count, not this name
    assert taken.status_code == 409 and taken.json()["error"] == "name_taken", taken.text
    assert "is not available" in taken.json()["message"]  # the same words as for the catalog's names
    other = upload(api, "tinybot.zip", ZIP, key="key-b", name="bbot", **TINY)
    assert other.status_code == 202 and other.json()["model"] == "bbot", other.text

    mine = api.get("/models", headers=auth("key-a")).json()
    assert [m["model"] for m in mine["models"]] == ["tinybot"] and mine["models"][0]["versions"] == []
    assert (mine["usage"]["trainings"], mine["usage"]["models"]) == (2, 1)
    everything = api.get("/models", headers=auth("key-op")).json()["models"]
    assert {m["model"] for m in everything} == {"tinybot", "bbot"}
    assert len({m["owner"] for m in everything}) == 2

    # a cancelled queued training frees its place; the name stays while another training holds it
    assert api.delete(f"/trainings/{first.json()['id']}", headers=auth("key-a")).status_code == 202
    assert (trn.data / "tinybot").is_dir()
    assert upload(api, "tinybot.zip", ZIP, key="key-a", **TINY).status_code == 202


def test_stored_models_and_bytes(trn: Trainer) -> None:
    api = trn.client(max_models_per_key=2, max_trainings_per_key=10)
    for name in ("one", "two"):
        assert upload(api, "tinybot.zip", ZIP, key="key-a", name=name, **TINY).status_code == 202
    assert upload(api, "tinybot.zip", ZIP, key="key-a", name="one", **TINY).status_code == 202  # a version
    three = upload(api, "tinybot.zip", ZIP, key="key-a", name="three", **TINY)
    assert three.status_code == 429 and three.json()["field"] == "MAX_MODELS_PER_KEY", three.text
    assert "DELETE /models/{name}" in three.json()["message"]
    assert api.delete("/models/two", headers=auth("key-b")).status_code == 404  # not key-b's
    assert api.delete("/models/two", headers=auth("key-a")).status_code == 200  # its uploader's, unpublished
    assert upload(api, "tinybot.zip", ZIP, key="key-a", name="three", **TINY).status_code == 202

    small = trn.client(max_bytes_per_key=1024)
    r = upload(small, "tinybot.zip", ZIP, key="key-b", name="big", **TINY)
    assert r.status_code == 429 and r.json()["field"] == "MAX_BYTES_PER_KEY", r.text
    assert not (trn.data / "big").exists()


def test_a_full_queue_is_503_naming_the_limit(trn: Trainer) -> None:
    api = trn.client(max_queue=1, max_trainings_per_key=10)
    assert upload(api, "tinybot.zip", ZIP, key="key-a", name="one", **TINY).status_code == 202
    r = upload(api, "tinybot.zip", ZIP, key="key-a", name="two", **TINY)
    assert r.status_code == 503, r.text
    body = r.json()
    assert (body["error"], body["field"], body["expected"], body["got"]) == (
        "queue_full",
        "MAX_QUEUE",
        "<= 1",
        2,
    )
    assert not (trn.data / "two").exists()  # the name is given back, nothing kept of the upload


def test_keys_off_share_one_pool_of_trainings(
    redis_url: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    t = Trainer(
        redis_url, tmp_path_factory.mktemp("trainer"), MAX_TRAININGS_PER_KEY="1", MAX_MODELS_PER_KEY="1"
    )
    try:
        api = t.client()
        assert upload(api, "tinybot.zip", ZIP, **TINY).status_code == 202
        r = upload(api, "tinybot.zip", ZIP, name="other", **TINY)
        assert r.status_code == 429 and "there are 1 trainings queued" in r.json()["message"], r.text
        listed = api.get("/models").json()["models"]
        assert [(m["model"], m["owner"]) for m in listed] == [("tinybot", "public")]
    finally:
        t.close()
