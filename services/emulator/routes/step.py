"""``POST /step``: one super-step of many sessions (game servers), as JSON or binary.

``Content-Type: application/json`` (the default): a ``BatchStepRequest``; sessions of any models.
``Content-Type: application/octet-stream``: the binary layout of ``proto/frames.md`` (little-endian
float32, every session of one (model, version)); the answer is binary too. Errors are JSON in both.

The endpoint reads the body itself (FastAPI would parse every body as JSON). Binary requests are
normally answered before routing by ``services/emulator/fastpath.py`` (the same ``binary_step``,
without FastAPI's per-request cost); the route documents both forms in the OpenAPI document. Both
are thin transports over the stepping core (``stepping.py``).
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, Request, Response
from pydantic import ValidationError

from neuroanimator.contracts.emulator import BatchStepRequest, BatchStepResponse, BatchStepResult, ErrorBody
from services.common.errors import json_error
from services.common.openapi import OpenApiDoc
from services.emulator.binary import MEDIA_TYPE as OCTET
from services.emulator.deps import ServiceDep
from services.emulator.error_mapping import error_body, invalid
from services.emulator.errors import BadInput, EmulatorError, TooLarge, UnsupportedMediaType
from services.emulator.fastpath import binary_step
from services.emulator.settings import Settings

router = APIRouter(tags=["step"])


def _inline(schema: OpenApiDoc) -> OpenApiDoc:
    """A pydantic JSON Schema with its ``$defs`` substituted in place (for ``openapi_extra``)."""
    defs = schema.pop("$defs", {})

    def sub(node: Any) -> Any:
        if isinstance(node, dict):
            ref = node.get("$ref")
            if isinstance(ref, str) and ref.startswith("#/$defs/"):
                return sub(defs[ref.removeprefix("#/$defs/")])
            return {k: sub(v) for k, v in node.items()}
        if isinstance(node, list):
            return [sub(v) for v in node]
        return node

    result: OpenApiDoc = sub(schema)
    return result


_BINARY_DOC = "little-endian float32 layout of proto/frames.md (all sessions of one model/version)"
_OPENAPI: OpenApiDoc = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {"schema": _inline(BatchStepRequest.model_json_schema())},
            OCTET: {"schema": {"type": "string", "format": "binary", "description": _BINARY_DOC}},
        },
    },
    "responses": {
        "200": {
            "content": {OCTET: {"schema": {"type": "string", "format": "binary", "description": _BINARY_DOC}}}
        }
    },
}


def json_batch_too_large(limit: int) -> str:
    return (
        f"a JSON batch may have at most {limit:,} bytes (MAX_JSON_BODY_BYTES); send large batches in the "
        f"binary form ({OCTET})"
    )


def _refuse_large_json(body: bytes, settings: Settings) -> None:
    """``TooLarge`` for a JSON batch over ``MAX_JSON_BODY_BYTES`` or with more items than ``MAX_BATCH``,
    before it is parsed: parsing and validating 300,000 items takes seconds of CPU, counting their
    ``"session"`` keys a millisecond (an over-count only refuses a body no client sends). Large batches
    belong to the binary form."""
    limit = settings.max_json_body_bytes
    if len(body) > limit:  # normally refused by its Content-Length before it is read (app.py)
        raise TooLarge(
            json_batch_too_large(limit),
            code="body_too_large",
            field="body",
            expected=f"<= {limit}",
            got=len(body),
        )
    items = body.count(b'"session"')
    if items > settings.max_batch:
        raise TooLarge(
            f"a batch may hold at most {settings.max_batch} items (MAX_BATCH), got about {items}",
            field="items",
            expected=f"<= {settings.max_batch}",
            got=items,
        )


@router.post(
    "/step",
    response_model=BatchStepResponse,
    responses={413: {"model": ErrorBody}, 415: {"model": ErrorBody}, 422: {"model": ErrorBody}},
    openapi_extra=_OPENAPI,
)
async def batch_step(request: Request, service: ServiceDep) -> Response:
    """One super-step of many sessions in one request: JSON (sessions of any models, a result per item)
    or binary (proto/frames.md: sessions of one model version, a status byte and a state per session)."""
    body = await request.body()
    ctype = request.headers.get("content-type", "application/json").split(";")[0].strip().lower()
    if ctype == OCTET:  # normally answered before routing, by services/emulator/fastpath.py
        return Response(await binary_step(service, body), media_type=OCTET)
    if ctype != "application/json" and not ctype.endswith("+json"):
        raise UnsupportedMediaType(
            f"POST /step takes application/json or {OCTET}, got {ctype!r}",
            field="content-type",
            expected=["application/json", OCTET],
            got=ctype,
        )
    _refuse_large_json(body, service.settings)
    try:
        raw = json.loads(body)
    except (ValueError, RecursionError) as exc:  # syntax, encoding, a huge integer, too deep
        raise BadInput(
            f"the body is not JSON: {json_error(exc)}", code="malformed_json", field="body"
        ) from exc
    try:
        req = BatchStepRequest.model_validate(raw)
    except ValidationError as exc:
        raise invalid(exc) from exc
    outcomes = await service.stepper.step_items(req.items)
    results = []
    for it, out in zip(req.items, outcomes, strict=True):
        if isinstance(out, EmulatorError):
            results.append(BatchStepResult(session=it.session, error=error_body(out)))
            continue
        inputs, sess = out.inputs, out.session
        results.append(
            BatchStepResult(
                session=it.session,
                state=out.states[-1].tolist(),
                t=out.session.t,
                clipped=inputs.clipped,
                clipped_controls=inputs.clipped_controls,
                clipped_forces=inputs.clipped_forces,
                outside_envelope=bool(out.outside),
                outside_groups=out.outside,
                controls=None if out.controls is None else out.controls[-1].tolist(),
                goal=None if sess.policy is None else sess.goal.tolist(),
                goal_outside=[] if sess.policy is None else sess.policy.goal_outside(sess.goal),
            )
        )
    return Response(BatchStepResponse(results=results).model_dump_json(), media_type="application/json")
