"""The error JSON every service answers: ``{"error", "message", "field", "expected", "got"}``."""

from __future__ import annotations

import math

from fastapi import FastAPI
from fastapi.testclient import TestClient
from pydantic import BaseModel

from services.common.errors import ApiError, add_error_handlers, field_name, jsonable

KEYS = {"error", "message", "field", "expected", "got"}


class Item(BaseModel):
    controls: list[float]


class Body(BaseModel):
    items: list[Item]


def _app() -> FastAPI:
    app = FastAPI()
    add_error_handlers(app)

    @app.get("/missing")
    async def missing() -> None:
        raise ApiError(404, "unknown_session", "no session 'r0-x'")

    @app.post("/bad")
    async def bad() -> None:
        raise ApiError(422, "out_of_range", "controls[0] is not finite", field="controls[0]", got=math.nan)

    @app.post("/items")
    async def items(body: Body) -> int:
        return len(body.items)

    return app


def test_api_errors_keep_their_status_and_shape() -> None:
    client = TestClient(_app())
    r = client.get("/missing")
    assert r.status_code == 404
    assert r.json() == {
        "error": "unknown_session",
        "message": "no session 'r0-x'",
        "field": None,
        "expected": None,
        "got": None,
    }
    r = client.post("/bad")
    assert r.status_code == 422 and set(r.json()) == KEYS
    assert (r.json()["field"], r.json()["got"]) == ("controls[0]", "nan")


def test_validation_errors_name_the_field() -> None:
    r = TestClient(_app()).post("/items", json={"items": [{"controls": [1.0]}, {"controls": ["x"]}]})
    assert r.status_code == 422 and set(r.json()) == KEYS
    body = r.json()
    assert (body["error"], body["field"], body["got"]) == ("invalid_request", "items[1].controls[0]", "x")
    assert body["expected"] == "a valid number, unable to parse string as a number"
    assert body["message"].startswith("items[1].controls[0]: Input should be a valid number")


def test_values_json_can_carry() -> None:
    assert jsonable([math.inf, -math.inf, 1.5, None]) == ["inf", "-inf", 1.5, None]
    assert jsonable(list(range(20))) == [*range(16), "..."]
    assert jsonable({1: (2, 3)}) == {"1": [2, 3]}
    assert jsonable(object()).startswith("<object object")
    assert field_name(("body", "items", 2, "controls", 0)) == "items[2].controls[0]"
    assert field_name(("body",)) == "body"
