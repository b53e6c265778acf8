"""``ApiError``: every error a service answers, as an HTTP status plus an ``ErrorBody``.

The JSON of an error is ``ErrorBody``'s: ``{"error", "message", "field", "expected", "got"}``, the last
three set for bad input. ``add_error_handlers(app)`` answers in that form ``ApiError``, FastAPI's request
validation errors, Starlette's HTTP errors (an unknown path, a method the path does not take, a body
that could not be read) and, as 500 ``internal_error``, anything a route did not expect.
"""

from __future__ import annotations

import math
import sys
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException

from neuroanimator.contracts.emulator import ErrorBody

HTTP_ERRORS = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    413: "body_too_large",
    415: "unsupported_media_type",
}
"""The ``error`` of a Starlette ``HTTPException`` by status (one may name its own in ``exc.error``)."""


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


MAX_SHOWN = 200
"""The longest text of an input quoted back in an error (a string, or the digits of a huge integer)."""


def _cut(text: str) -> str:
    return text if len(text) <= MAX_SHOWN else f"{text[: MAX_SHOWN - 40]}... ({len(text)} characters)"


def jsonable(value: Any, depth: int = 0) -> Any:
    """Values JSON can carry: non-finite floats become strings ("nan", "inf"), long inputs are cut
    (strings, lists and objects, and integers beyond 64 bits: shown as text)."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 2**63:
        return _cut(str(value))
    if isinstance(value, str):
        return _cut(value)
    if isinstance(value, (list, tuple, dict)) and depth >= 8:
        return "..."
    if isinstance(value, (list, tuple)):
        items = [jsonable(v, depth + 1) for v in value[:16]]
        return [*items, "..."] if len(value) > 16 else items
    if isinstance(value, dict):
        return {_cut(str(k)): jsonable(v, depth + 1) for k, v in list(value.items())[:16]}
    if value is None or isinstance(value, (bool, int, float)):
        return value
    return _cut(repr(value))


PARSE_FAILED = "There was an error parsing the body"
"""FastAPI's 400 for a body its JSON parser raised on with anything but a syntax error (the cause is
the exception's ``__cause__``)."""


def json_error(exc: BaseException) -> str:
    """Why a text is not JSON that Python can read, in words for the client: the parser's own for a
    syntax error, and for what is not one (an integer of more than 4,300 digits: ``ValueError``;
    nesting past the recursion limit: ``RecursionError``) what the text has that cannot be read."""
    if isinstance(exc, RecursionError):
        return "it nests arrays and objects too deep"
    text = str(exc)
    if "integer string conversion" in text:
        return f"a number has more digits than can be read ({sys.get_int_max_str_digits()} at most)"
    return _cut(text)


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
        f"{name}: {_cut(msg)}; got {_cut(repr(jsonable(err.get('input'))))}{more}",
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


async def http_error_handler(request: Request, exc: Exception) -> JSONResponse:
    """Starlette's and FastAPI's own HTTP errors in the project's form, their headers kept."""
    assert isinstance(exc, HTTPException)
    error = getattr(exc, "error", None) or HTTP_ERRORS.get(exc.status_code, f"http_{exc.status_code}")
    detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    if exc.status_code == 404 and detail == "Not Found":
        detail = f"no such path: {request.url.path}"
    elif exc.status_code == 405:
        detail = f"{request.method} is not a method of {request.url.path}"
    elif exc.status_code == 400 and detail == PARSE_FAILED and exc.__cause__ is not None:
        error, detail = "malformed_json", f"the body cannot be read as JSON: {json_error(exc.__cause__)}"
    field = "body" if exc.status_code in (400, 413, 415) else None
    body = ErrorBody(error=error, message=detail, field=field)
    return JSONResponse(body.model_dump(), status_code=exc.status_code, headers=exc.headers)


async def internal_error_handler(request: Request, exc: Exception) -> JSONResponse:
    """An exception no route expected: 500 ``internal_error``; the server logs the traceback (Starlette
    raises the exception on after this answer)."""
    body = ErrorBody(
        error="internal_error",
        message=f"the service failed on this request ({type(exc).__name__}); it is logged",
    )
    return JSONResponse(body.model_dump(), status_code=500)


def add_error_handlers(app: FastAPI) -> None:
    """Answer ``ApiError``, request validation errors, HTTP errors and unexpected exceptions with
    ``ErrorBody`` JSON."""
    app.add_exception_handler(ApiError, api_error_handler)
    app.add_exception_handler(RequestValidationError, validation_error_handler)
    app.add_exception_handler(HTTPException, http_error_handler)
    app.add_exception_handler(Exception, internal_error_handler)
