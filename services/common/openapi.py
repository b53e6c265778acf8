"""``document_errors(app)``: every error a service can answer, in its OpenAPI document.

Some errors come from outside the routes and so are not in the responses FastAPI derives from them:
the body limits (``limits.py``: 413, and 400 for a JSON body that is not UTF-8 or nests too deep), the
API-key check (``auth.py``: 401), and per service errors of every route (the controller's 503 while
Redis is down). FastAPI also documents its own validation error (``HTTPValidationError``) where the
services answer ``ErrorBody``. This rewrites the generated document once, when it is first asked for:
each operation gets those responses, typed as ``ErrorBody``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from fastapi import FastAPI
from prometheus_client import CONTENT_TYPE_LATEST

from neuroanimator.contracts.emulator import ErrorBody
from services.common.auth import OPEN_PATHS

ERROR_REF = {"$ref": "#/components/schemas/ErrorBody"}
BODY_ERRORS = {
    "400": "the body cannot be read: JSON that is not UTF-8, nests arrays and objects too deep or has a "
    "number too long to read, or a request with more than one Content-Type",
    "413": "the body is larger than this endpoint takes (refused before it is read)",
}
AUTH_ERROR = {"401": "no API key, or one that is not valid (when the service has API_KEYS)"}
VALIDATION = "the request is not valid: the field, what was expected and what was got"
OPS_STATUS = {
    "type": "object",
    "properties": {"status": {"type": "string"}, "message": {"type": "string"}},
    "required": ["status"],
    "additionalProperties": True,
}
"""The JSON of ``/healthz`` and ``/readyz`` answers (``status``, and why when not ready)."""
METRICS_TYPE: str = CONTENT_TYPE_LATEST
"""The media type of ``/metrics``: Prometheus's text exposition format."""


OpenApiDoc = dict[str, Any]
"""An OpenAPI document or JSON Schema, or a part of one (a response, a schema): free-form JSON."""
Responses = dict[int | str, OpenApiDoc]
"""What FastAPI's ``responses=`` takes: an OpenAPI response object per status code."""


def error_response(description: str) -> OpenApiDoc:
    return {"description": description, "content": {"application/json": {"schema": ERROR_REF}}}


def readiness_responses(not_ready: str) -> Responses:
    """The documented answers of a ``/readyz``: 200 ready, 503 with the reason."""
    return {
        200: {"description": "ready", "content": {"application/json": {"schema": OPS_STATUS}}},
        503: {"description": not_ready, "content": {"application/json": {"schema": OPS_STATUS}}},
    }


METRICS_RESPONSES: Responses = {
    200: {
        "description": "Prometheus metrics in the text exposition format",
        "content": {METRICS_TYPE: {"schema": {"type": "string"}}},
    }
}


def _add(responses: OpenApiDoc, codes: Mapping[str, str]) -> None:
    for code, description in codes.items():
        responses.setdefault(code, error_response(description))


def _uses_validation_error(response: Mapping[str, Any]) -> bool:
    schema = response.get("content", {}).get("application/json", {}).get("schema", {})
    return bool(schema.get("$ref", "").endswith("/HTTPValidationError"))


def add_errors(
    schema: OpenApiDoc, everywhere: Mapping[str, str] = {}, open_paths: frozenset[str] = OPEN_PATHS
) -> OpenApiDoc:
    """``schema`` (an OpenAPI document) with the errors of the module's text on every operation;
    ``everywhere`` adds (status, description) to every operation but the open ones."""
    for path, operations in schema.get("paths", {}).items():
        for op in operations.values():
            responses = op.setdefault("responses", {})
            if "422" in responses and _uses_validation_error(responses["422"]):
                responses["422"] = error_response(VALIDATION)
            if "requestBody" in op:
                _add(responses, BODY_ERRORS)
            if path not in open_paths:
                _add(responses, AUTH_ERROR)
                _add(responses, everywhere)
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components.setdefault(
        "ErrorBody", ErrorBody.model_json_schema(ref_template="#/components/schemas/{model}")
    )
    text = str(schema["paths"])
    for unused in ("HTTPValidationError", "ValidationError"):
        if f"/{unused}'" not in text and unused in components:
            still = any(f"/{unused}'" in str(v) for k, v in components.items() if k != unused)
            if not still:
                del components[unused]
    return schema


def document_errors(app: FastAPI, everywhere: Mapping[str, str] = {}) -> None:
    """Make ``app.openapi()`` return its document with ``add_errors`` applied (once, then cached)."""
    generate: Callable[[], OpenApiDoc] = app.openapi

    def openapi() -> OpenApiDoc:
        if app.openapi_schema is None:
            app.openapi_schema = add_errors(generate(), everywhere)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
