"""Hand-made bodies that once answered 500, or were accepted and then failed in every run of the worker:
each is now answered 4xx in the service's JSON error form, naming the problem, within 100 ms."""

from __future__ import annotations

import time

import pytest

from tests.services.controller.ctl import Controller, ctl_fixture  # noqa: F401

ZEROS = "0" * 330  # JSON's 1 followed by 330 zeros: an integer no float can hold
JSON = {"content-type": "application/json"}

CASES: list[tuple[bytes, int, str]] = [
    (
        b'{"task":"truck-parking","success":[{"check":"abs","variables":["heading"],"max":1,"target":["a"]}]}',
        422,
        "success[0].target[0]",
    ),
    (
        b'{"task":"truck-parking","success":[{"check":"abs","variables":["heading"],"max":1'
        + ZEROS.encode()
        + b"}]}",
        422,
        "success[0].max",
    ),
    (
        b'{"task":"truck-parking","terms":[{"term":"control_effort","weight":1' + ZEROS.encode() + b"}]}",
        422,
        "terms[0].weight",
    ),
    (
        b'{"task":"truck-parking","terms":[{"term":"path_target","waypoints":'
        b'[{"time":1e308,"target":[0,0,0,0,0,0]}]}]}',
        422,
        "terms[0].waypoints[0].time",
    ),
    (
        b'{"task":"truck-parking","success":[{"check":"abs","variables":["heading"],"max":1,"target":[[1,2]]}]}',
        422,
        "success[0].target[0]",
    ),
    (
        b'{"task":"truck-parking","terms":[{"term":"forward_distance","direction":[1e308,1e308]}]}',
        422,
        "terms[0].direction[0]",
    ),
    (b'{"task":"truck-parking","initial_state":[1e308,1e308,0,0,0,0]}', 422, "initial_state[0]"),
    (
        b'{"task":"truck-parking","terms":[{"term":"path_target","waypoints":['
        + b",".join([b'{"step":1,"target":[0,0,0,0,0,0]}'] * 2000)
        + b"]}]}",
        422,
        "terms[0].waypoints",
    ),
    (b'{"task":"truck-parking","initial_state":[' + b",".join([b"0"] * 5000) + b"]}", 422, "initial_state"),
    (b"[" * 1000, 400, "body"),
    (b'{"task":' + b'{"a":' * 200 + b"1" + b"}" * 201, 400, "body"),
    (b'{"task":"\xff\xfe"}', 400, "body"),
    (b'{"task":"truck-parking"', 422, "body"),
    (b'{"task":"truck-parking","horizon":1' + b"0" * 5000 + b"}", 400, "body"),  # no int that long is read
]


@pytest.mark.parametrize(("body", "status", "field"), CASES, ids=[f"case{i}" for i in range(len(CASES))])
def test_hostile_job_bodies_are_refused_naming_the_field(
    ctl: Controller, body: bytes, status: int, field: str
) -> None:
    client = ctl.client()
    client.post("/jobs", content=b"{}", headers=JSON)  # warm: the first call loads the task registry
    took = []
    for _ in range(3):  # the quickest of three: the machine's other load is not the service's time
        t0 = time.perf_counter()
        r = client.post("/jobs", content=body, headers=JSON)
        took.append(time.perf_counter() - t0)
    assert r.status_code == status, r.text
    err = r.json()
    assert set(err) == {"error", "message", "field", "expected", "got"}
    assert err["field"] == field, err
    assert len(r.content) < 2000, "an error quotes a huge input cut short"
    assert min(took) < 0.1, f"answered in {min(took) * 1000:.0f} ms"
    assert ctl.r.llen(f"rq:queue:{ctl.env['QUEUE_NAME']}") == 0, "nothing was queued"
