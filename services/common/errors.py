"""``ApiError``: every error a service answers, as an HTTP status plus an ``ErrorBody``.

The JSON of an error is ``ErrorBody``'s: ``{"error", "message", "field", "expected", "got"}``, the last
three set for bad input. ``add_error_handlers(app)`` answers ``ApiError`` and FastAPI's request
validation errors in that form.
"""

from __future__ import annotations

import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from neuroanimator.emulator_schemas import ErrorBody


class ApiError(Exception):
    """An error with its HTTP status and body; raised anywhere, answered by ``api_error_handler``."""

    def __init__(
        self,
        status: int,
        error: str,
        message: str,
        *,
        field: str | None = None,
        expected: Any = None,
        got: Any = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.body = ErrorBody(
            error=error, message=message, field=field, expected=jsonable(expected), got=jsonable(got)
        )


def jsonable(value: Any) -> Any:
    """Values JSON can carry: non-finite floats become strings ("nan", "inf"), long inputs are cut."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, (list, tuple)):
        items = [jsonable(v) for v in value[:16]]
        return [*items, "..."] if len(value) > 16 else items
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in list(value.items())[:16]}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)[:200]


def field_name(loc: tuple[Any, ...]) -> str:
    """('body', 'items', 2, 'controls', 0) -> 'items[2].controls[0]'."""
    out = ""
    for part in loc:
        if part == "body" and not out:
            continue
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out or "body"


def from_validation(errors: list[dict[str, Any]]) -> ApiError:
    """The first pydantic error as a 422 naming the field, what was expected and what was got."""
    if not errors:
        return ApiError(422, "invalid_request", "the request is invalid")
    err = errors[0]
    if err.get("type") == "json_invalid":
        # pydantic puts the character offset of a syntax error where a field's path would be
        loc = tuple(err.get("loc", ()))
        at = loc[-1] if loc and isinstance(loc[-1], int) else None
        why = str((err.get("ctx") or {}).get("error", "JSON decode error"))
        where = f" at character {at}" if at is not None else ""
        return ApiError(
            422,
            "invalid_request",
            f"the body is not valid JSON{where}: {why}",
            field="body",
            expected="a JSON document",
            got=f"a syntax error{where}",
        )
    name = field_name(tuple(err.get("loc", ())))
    msg = str(err.get("msg", "invalid value"))
    more = f" (and {len(errors) - 1} more problems)" if len(errors) > 1 else ""
    return ApiError(
        422,
        "invalid_request",
        f"{name}: {msg}; got {jsonable(err.get('input'))!r}{more}",
        field=name,
        expected=msg.removeprefix("Input should be ").removeprefix("Field "),
        got=err.get("input"),
    )


async def api_error_handler(request: Request, exc: Exception) -> JSONResponse:
    """An ``ApiError`` as its status and body."""
    assert isinstance(exc, ApiError)
    return JSONResponse(exc.body.model_dump(), status_code=exc.status)


async def validation_error_handler(request: Request, exc: Exception) -> JSONResponse:
    """A request FastAPI could not validate as a 422 naming the first bad field (``from_validation``)."""
    assert isinstance(exc, RequestValidationError)
    err = from_validation(list(exc.errors()))
    return JSONResponse(err.body.model_dump(), status_code=err.status)


def add_error_handlers(app: FastAPI) -> None:
    """Answer ``ApiError`` and request validation errors with ``ErrorBody`` JSON."""
    app.add_exception_handler(ApiError, api_error_handler)
    app.add_exception_handler(RequestValidationError, validation_error_handler)
