"""The one place where the emulator's domain errors (``errors.py``) become what a client receives.

HTTP: ``STATUS`` gives each kind its status code; the body is an ``ErrorBody``. Websockets: a
``WsError`` text message with the same fields (and the ``seq`` of the message it answers); an error
that ends the connection closes it with ``4000 + status`` (4404 for an unknown session, 4422 for a bad
query). A pydantic ``ValidationError`` of a request or message becomes ``BadInput`` here too.
"""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from pydantic import ValidationError

from neuroanimator.contracts.emulator import ErrorBody, WsError
from services.common.errors import add_error_handlers, from_validation, jsonable
from services.emulator.errors import (
    BadInput,
    ClientDisconnected,
    Diverged,
    EmulatorError,
    PolicyMismatch,
    QuotaExceeded,
    StepFailed,
    TooLarge,
    UnknownModel,
    UnknownPolicy,
    UnknownSession,
    UnsupportedMediaType,
    WrongMode,
)

STATUS: dict[type[EmulatorError], int] = {
    ClientDisconnected: 400,
    UnknownSession: 404,
    UnknownModel: 404,
    UnknownPolicy: 404,
    Diverged: 409,
    PolicyMismatch: 409,
    WrongMode: 409,
    TooLarge: 413,
    UnsupportedMediaType: 415,
    BadInput: 422,
    QuotaExceeded: 429,
    StepFailed: 500,
}


def status_of(exc: EmulatorError) -> int:
    """The HTTP status of an error (500 for a kind without one)."""
    for kind in type(exc).__mro__:
        status = STATUS.get(kind)
        if status is not None:
            return status
    return 500


def error_body(exc: EmulatorError) -> ErrorBody:
    return ErrorBody(
        error=exc.code,
        message=exc.message,
        field=exc.field,
        expected=jsonable(exc.expected),
        got=jsonable(exc.got),
    )


def http_json(exc: EmulatorError) -> tuple[int, bytes]:
    """Status and JSON body, for routes served as plain ASGI."""
    return status_of(exc), error_body(exc).model_dump_json().encode()


async def _http_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, EmulatorError)
    return JSONResponse(error_body(exc).model_dump(), status_code=status_of(exc))


def add_http_handlers(app: FastAPI) -> None:
    """Answer domain errors, ``ApiError`` (API keys) and request validation errors as ``ErrorBody``."""
    add_error_handlers(app)
    app.add_exception_handler(EmulatorError, _http_handler)


def ws_error(exc: EmulatorError, seq: int | None = None) -> str:
    """The websocket error message answering a message (``seq`` echoed)."""
    return WsError(**error_body(exc).model_dump(), seq=seq).model_dump_json()


def ws_close_code(exc: EmulatorError) -> int:
    """The close code of a websocket that this error ends."""
    return 4000 + status_of(exc)


def invalid(exc: ValidationError) -> BadInput:
    """The first problem pydantic found, naming the field, the expected and the got."""
    body = from_validation([dict(e) for e in exc.errors()]).body
    return BadInput(body.message, code=body.error, field=body.field, expected=body.expected, got=body.got)
