"""The API without workers: bad input (422 naming the field), a full queue and a Redis that is down
(503 with a message), API keys (a key sees only its own jobs), CORS, /readyz and /metrics."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import Any

import pytest

from tests.services.controller.ctl import QUICK, Controller, ctl_fixture  # noqa: F401


def _closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = int(s.getsockname()[1])
    s.close()  # nothing listens there now
    return port


BAD: list[tuple[dict[str, Any], str, str]] = [
    ({"task": "pendulum-fly"}, "task", "unknown task"),
    ({"model": "pendulum-huge"}, "model", "unknown model"),
    ({}, "task", "expected a task or a model"),
    ({"task": "pendulum-swing", "target_state": [1, 0, 0]}, "target_state", "6"),
    ({"task": "pendulum-swing", "target_state": [1, 0, 0, 0, 0, "x"]}, "target_state[5]", "number"),
    ({"task": "pendulum-swing", "horizon": -5}, "horizon", "greater than or equal to 1"),
    ({"task": "pendulum-swing", "horizon": 100_000}, "horizon", "1000"),
    (
        {"task": "pendulum-swing", "optimizer": {"max_iterations": 0}},
        "optimizer.max_iterations",
        "greater than or equal to 1",
    ),
    ({"task": "pendulum-swing", "optimizer": {"max_iterations": 10**7}}, "optimizer.max_iterations", "10000"),
    (
        {"task": "pendulum-swing", "optimizer": {"learning_rate": -1}},
        "optimizer.learning_rate",
        "greater than 0",
    ),
    ({"task": "pendulum-swing", "optimizer": {"learning_rate": 1e6}}, "optimizer.learning_rate", "100"),
    ({"task": "pendulum-swing", "optimizer": {"momentum": 1.5}}, "optimizer.momentum", "less than 1"),
    ({"task": "pendulum-swing", "mu_u": -1}, "mu_u", "greater than or equal to 0"),
    ({"task": "pendulum-swing", "model": "truck"}, "model", "pendulum-active"),
    ({"task": "pendulum-swing", "terms": [{"term": "no-such-term"}]}, "terms[0]", "no-such-term"),
    ({"task": "pendulum-swing", "wings": 2}, "wings", "xtra"),
    # numbers are strict: a boolean or a string is not a number, whatever it would convert to
    ({"task": "pendulum-swing", "horizon": True}, "horizon", "valid integer"),
    ({"task": "pendulum-swing", "horizon": "40"}, "horizon", "valid integer"),
    ({"task": "pendulum-swing", "horizon": 40.5}, "horizon", "valid integer"),
    ({"task": "pendulum-swing", "substeps": "50"}, "substeps", "valid integer"),
    ({"task": "pendulum-swing", "mu_u": "0.1"}, "mu_u", "valid number"),
    ({"task": "pendulum-swing", "mu_s": False}, "mu_s", "valid number"),
    (
        {"task": "pendulum-swing", "optimizer": {"max_iterations": "5"}},
        "optimizer.max_iterations",
        "valid integer",
    ),
    ({"task": "pendulum-swing", "optimizer": {"starts": True}}, "optimizer.starts", "valid integer"),
    ({"task": "pendulum-swing", "optimizer": {"line_search": "yes"}}, "optimizer.line_search", "boolean"),
    ({"task": "pendulum-swing", "optimizer": {"stop_on_success": 1}}, "optimizer.stop_on_success", "boolean"),
    (
        {"task": "pendulum-swing", "optimizer": {"starts": 0}},
        "optimizer.starts",
        "greater than or equal to 1",
    ),
]


@pytest.mark.parametrize(("body", "field", "text"), BAD, ids=[f"{b[1]}-{i}" for i, b in enumerate(BAD)])
def test_bad_input_is_422_naming_the_field(
    ctl: Controller, body: dict[str, Any], field: str, text: str
) -> None:
    # Redis is not needed to refuse bad input: this app's Redis is a closed port.
    api = ctl.client(redis_url=f"redis://127.0.0.1:{_closed_port()}/0")
    r = api.post("/jobs", json=body)
    assert r.status_code == 422, r.text
    err = r.json()
    assert err["field"].startswith(field), err
    assert text.lower() in err["message"].lower(), err


def test_an_unknown_task_lists_the_known_ones_as_expected(ctl: Controller) -> None:
    api = ctl.client(redis_url=f"redis://127.0.0.1:{_closed_port()}/0")
    err = api.post("/jobs", json={"task": "pendulum-fly"}).json()
    tasks = {t["name"] for t in api.get("/tasks").json()["tasks"]}
    assert isinstance(err["expected"], list) and set(err["expected"]) == tasks, err
    assert err["got"] == "pendulum-fly"


def test_non_finite_numbers_are_refused(ctl: Controller) -> None:
    api = ctl.client()
    for raw, field in (
        ('{"task": "pendulum-swing", "target_state": [NaN, 0, 0, 0, 0, 0]}', "target_state[0]"),
        ('{"task": "pendulum-swing", "initial_state": [0, 0, 0, 0, 0, Infinity]}', "initial_state[5]"),
        ('{"task": "pendulum-swing", "optimizer": {"learning_rate": NaN}}', "optimizer.learning_rate"),
    ):
        r = api.post("/jobs", content=raw, headers={"content-type": "application/json"})
        assert r.status_code == 422 and r.json()["field"] == field, r.text
        assert "finite" in r.json()["message"]


def test_a_json_syntax_error_names_its_position_not_a_field(ctl: Controller) -> None:
    api = ctl.client()
    raw = '{"task": "pendulum-swing",, "horizon": 4}'
    r = api.post("/jobs", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    err = r.json()
    assert err["error"] == "invalid_request" and err["field"] == "body", err
    assert "not valid JSON at character 26" in err["message"], err


def test_redis_down_is_503_with_a_message_that_does_not_say_where_redis_is(ctl: Controller) -> None:
    port = _closed_port()
    api = ctl.client(redis_url=f"redis://127.0.0.1:{port}/0", redis_timeout_s=0.5)
    for method, path, body in (
        ("POST", "/jobs", QUICK),
        ("GET", "/jobs/abc", None),
        ("GET", "/jobs", None),
        ("DELETE", "/jobs/abc", None),
        ("GET", "/jobs/abc/events", None),
    ):
        r = api.request(method, path, json=body)
        assert r.status_code == 503, (path, r.text)
        assert r.json()["error"] == "redis_unavailable", r.text
        assert str(port) not in r.text and "127.0.0.1" not in r.text
    ready = api.get("/readyz")
    assert ready.status_code == 503 and ready.json()["status"] == "redis unavailable"
    assert str(port) not in ready.text and "127.0.0.1" not in ready.text
    assert api.get("/healthz").json() == {"status": "ok"}
    assert api.get("/tasks").status_code == 200  # needs no Redis
    assert "controller_redis_up 0.0" in api.get("/metrics").text


def test_full_queue_is_503(ctl: Controller) -> None:
    api = ctl.client(max_queue=2)
    assert [api.post("/jobs", json=QUICK).status_code for _ in range(2)] == [202, 202]
    r = api.post("/jobs", json=QUICK)
    assert r.status_code == 503 and r.json()["error"] == "queue_full"
    assert "MAX_QUEUE=2" in r.json()["message"]
    assert (r.json()["field"], r.json()["expected"], r.json()["got"]) == ("MAX_QUEUE", "<= 2", 3)
    text = api.get("/metrics").text
    assert "controller_queue_depth 2.0" in text
    assert 'controller_jobs_rejected_total{reason="queue_full"} 1.0' in text
    assert "controller_jobs_submitted_total 2.0" in text


def test_unknown_job_is_404(ctl: Controller) -> None:
    api = ctl.client()
    for method, path in (("GET", "/jobs/nope"), ("GET", "/jobs/nope/result"), ("DELETE", "/jobs/nope")):
        r = api.request(method, path)
        assert r.status_code == 404 and r.json()["field"] == "id"
    assert api.get("/jobs/nope/events").status_code == 404


def test_api_keys_isolate_jobs(ctl: Controller) -> None:
    api = ctl.client(api_keys="key-a,key-b")
    a = {"Authorization": "Bearer key-a"}
    b = {"X-API-Key": "key-b"}
    assert api.post("/jobs", json=QUICK).status_code == 401
    assert api.post("/jobs", json=QUICK, headers={"X-API-Key": "wrong"}).status_code == 401
    assert api.get("/healthz").status_code == 200 and api.get("/metrics").status_code == 200
    job_id = api.post("/jobs", json=QUICK, headers=a).json()["id"]
    assert api.get(f"/jobs/{job_id}", headers=a).status_code == 200
    for method, path in (("GET", ""), ("GET", "/result"), ("DELETE", ""), ("GET", "/events")):
        assert api.request(method, f"/jobs/{job_id}{path}", headers=b).status_code == 404
    assert api.get("/jobs", headers=b).json() == {"jobs": []}
    assert [j["id"] for j in api.get("/jobs", headers=a).json()["jobs"]] == [job_id]
    # the same idempotency key under two keys makes two jobs
    ka = api.post("/jobs", json={**QUICK, "idempotency_key": "k"}, headers=a).json()["id"]
    kb = api.post("/jobs", json={**QUICK, "idempotency_key": "k"}, headers=b).json()["id"]
    assert ka != kb
    # EventSource cannot send headers: the event stream takes ?api_key= (the job is cancelled, so it ends)
    api.delete(f"/jobs/{job_id}", headers=a)
    r = api.get(f"/jobs/{job_id}/events?api_key=key-a")
    assert r.status_code == 200 and "event: end" in r.text
    assert api.get(f"/jobs/{job_id}/events?api_key=key-b").status_code == 404


def test_cors_preflight_and_headers(ctl: Controller) -> None:
    api = ctl.client(api_keys="key-a", cors_origins="http://localhost:5173")
    pre = api.options(
        "/jobs",
        headers={
            "Origin": "http://localhost:5173",
            "Access-Control-Request-Method": "POST",
            "Access-Control-Request-Headers": "authorization,content-type",
        },
    )
    assert pre.status_code == 200
    assert pre.headers["access-control-allow-origin"] == "http://localhost:5173"
    r = api.get("/tasks", headers={"Origin": "http://localhost:5173", "X-API-Key": "key-a"})
    assert r.headers["access-control-allow-origin"] == "http://localhost:5173"
    other = api.get("/tasks", headers={"Origin": "http://evil.example", "X-API-Key": "key-a"})
    assert "access-control-allow-origin" not in other.headers


def test_readyz_and_metrics(ctl: Controller, tmp_path: Path) -> None:
    api = ctl.client()
    ready = api.get("/readyz")  # no worker started: not ready, and it says why
    assert ready.status_code == 503, ready.text
    body = ready.json()
    assert body["status"] == "no workers" and "pendulum-active" in body["models"] and body["workers"] == 0
    text = api.get("/metrics").text
    for name in (
        "controller_redis_up 1.0",
        "controller_queue_depth 0.0",
        "controller_jobs_running 0.0",
        "controller_workers 0.0",
        'controller_jobs_finished_total{status="succeeded"}',
        'controller_job_duration_seconds_bucket{le="+Inf"}',
        "controller_job_iterations_count",
    ):
        assert name in text, name
    empty = ctl.client(artifacts_dir=tmp_path / "nothing")
    r = empty.get("/readyz")
    assert r.status_code == 503 and r.json()["status"] == "no artifacts", r.text
    assert "ARTIFACTS_DIR" in r.json()["message"] and str(tmp_path) not in r.text  # no path to anybody
