"""Every body of the emulator service is bounded before it is read: the JSON and the binary ``POST /step``,
the pose endpoint and the session endpoints; JSON that is not UTF-8 or nests too deep is the project's
400, never a parser's recursion (500) or FastAPI's own ``{"detail": ...}``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

KEYS = {"error", "message", "field", "expected", "got"}
JSON = {"content-type": "application/json"}


def _error(r: Any, status: int, error: str) -> None:
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == KEYS
    assert body["error"] == error, body


@pytest.mark.parametrize(
    "path", ["/step", "/sessions", "/models/pendulum-active/poses", "/sessions/r0-x/step"]
)
def test_deep_json_and_non_utf8_are_400_on_every_endpoint(client: Any, path: str) -> None:
    _error(client.post(path, content=b"[" * 1000, headers=JSON), 400, "too_deep")
    _error(client.post(path, content=b'{"model": "\xff"}', headers=JSON), 400, "invalid_encoding")


@pytest.mark.parametrize(
    "path", ["/step", "/sessions", "/models/pendulum-active/poses", "/sessions/r0-x/step"]
)
def test_a_number_too_long_to_read_is_named(client: Any, path: str) -> None:
    """Python reads integers of at most 4,300 digits: a longer one is the project's error naming it
    (POST /step parses its body itself: once a 500)."""
    body = b'{"items": [{"session": "x", "controls": [1' + b"0" * 5000 + b"]}]}"
    r = client.post(path, content=body, headers=JSON)
    assert r.status_code in (400, 422), r.text
    _error(r, r.status_code, "malformed_json")
    assert "more digits than can be read" in r.json()["message"] and r.json()["field"] == "body"


def test_two_content_types_are_refused(client: Any) -> None:
    """Checked by one header, parsed by another: a deep JSON body behind a second, non-JSON type once
    reached POST /step's parser (500)."""
    for types in (("application/json", "text/plain"), ("application/octet-stream", "application/json")):
        r = client.post("/step", content=b"[" * 5000, headers=[("content-type", t) for t in types])
        _error(r, 400, "bad_request")
        assert r.json()["field"] == "content-type"


def test_bodies_are_capped_per_endpoint(make_client: Callable[..., Any]) -> None:
    client = make_client(max_body_bytes=200_000, small_body_bytes=2048)
    big = b'{"items": [' + b" " * 300_000 + b"]}"
    _error(client.post("/step", content=big, headers=JSON), 413, "body_too_large")
    _error(
        client.post("/step", content=big, headers={"content-type": "application/octet-stream"}),
        413,
        "body_too_large",
    )
    _error(client.post("/models/pendulum-active/poses", content=big, headers=JSON), 413, "body_too_large")
    small = b'{"model": "pendulum-active"' + b" " * 3000 + b"}"
    _error(client.post("/sessions", content=small, headers=JSON), 413, "body_too_large")
    # below the caps, the same endpoints work
    r = client.post("/sessions", json={"model": "pendulum-active"})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    r = client.post("/step", json={"items": [{"session": sid, "controls": [0.0, 0.0, 0.0]}]})
    assert r.status_code == 200, r.text


def test_unknown_paths_and_methods_are_the_projects_json(client: Any) -> None:
    _error(client.get("/no-such-thing"), 404, "not_found")
    _error(client.put("/step", json={}), 405, "method_not_allowed")


def test_an_oversized_json_batch_is_refused_before_it_is_parsed(client: Any) -> None:
    """200,000 items in 6 MB (such a body once took 3.5 s of CPU to refuse): refused by size; 5,000 small items under the
    size limit: refused by their count, before parsing (the binary form takes large batches)."""
    item = b'{"session":"s","controls":[0]},'
    huge = b'{"items":[' + item * 200_000 + b'{"session":"s","controls":[0]}]}'
    r = client.post("/step", content=huge, headers=JSON)
    _error(r, 413, "body_too_large")
    assert "MAX_JSON_BODY_BYTES" in r.json()["message"] and "binary" in r.json()["message"]
    many = b'{"items":[' + item * 5000 + b'{"session":"s","controls":[0]}]}'
    r = client.post("/step", content=many, headers=JSON)
    _error(r, 413, "batch_too_large")
    assert "MAX_BATCH" in r.json()["message"] and r.json()["got"] == 5001
