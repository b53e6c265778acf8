"""``POST /step``: one super-step of many sessions (game servers), as JSON or binary.

``Content-Type: application/json`` (the default): a ``BatchStepRequest``; sessions of any models.
``Content-Type: application/octet-stream``: the binary layout of ``proto/frames.md`` (little-endian
float32, every session of one (model, version)); the answer is binary too. Errors are JSON in both.

The endpoint reads the body itself (FastAPI would parse every body as JSON). Binary requests are
normally answered before routing by ``services/emulator/fastpath.py`` (the same ``binary_step``,
without FastAPI's per-request cost); the route documents both forms in the OpenAPI document.
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np
from fastapi import APIRouter, Request, Response
from pydantic import ValidationError

from neuroanimator.emulator_schemas import BatchStepRequest, BatchStepResponse, ErrorBody
from services.common.errors import ApiError, from_validation
from services.emulator import binary
from services.emulator.batcher import ROW_DIVERGED, ROW_GONE
from services.emulator.deps import EngineDep
from services.emulator.engine import Engine

router = APIRouter(tags=["step"])
OCTET = "application/octet-stream"


def _inline(schema: dict[str, Any]) -> dict[str, Any]:
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

    result: dict[str, Any] = sub(schema)
    return result


_BINARY_DOC = "little-endian float32 layout of proto/frames.md (all sessions of one model/version)"
_OPENAPI: dict[str, Any] = {
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


@router.post(
    "/step",
    response_model=BatchStepResponse,
    responses={413: {"model": ErrorBody}, 415: {"model": ErrorBody}, 422: {"model": ErrorBody}},
    openapi_extra=_OPENAPI,
)
async def batch_step(request: Request, engine: EngineDep) -> Response:
    body = await request.body()
    ctype = request.headers.get("content-type", "application/json").split(";")[0].strip().lower()
    if ctype == OCTET:  # normally answered before routing, by services/emulator/fastpath.py
        return Response(await binary_step(engine, body), media_type=OCTET)
    if ctype != "application/json" and not ctype.endswith("+json"):
        raise ApiError(
            415,
            "unsupported_media_type",
            f"POST /step takes application/json or {OCTET}, got {ctype!r}",
            field="content-type",
            expected=["application/json", OCTET],
            got=ctype,
        )
    try:
        raw = json.loads(body)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ApiError(422, "malformed_json", f"the body is not JSON: {exc}", field="body") from exc
    try:
        req = BatchStepRequest.model_validate(raw)
    except ValidationError as exc:
        raise from_validation([dict(e) for e in exc.errors()]) from exc
    out = await engine.batch_step(req)
    return Response(out.model_dump_json(), media_type="application/json")


async def binary_step(engine: Engine, body: bytes) -> bytes:
    """Parse, validate (the whole request fails on a problem and steps nothing), step every known
    session in ONE batcher entry, and encode the answer. The sessions are resolved, checked, locked
    and stepped as arrays (``SessionStore.resolve_block``, ``StatePool``): no per-session Python."""
    parsed = binary.parse_batch_request(body, engine.settings.max_batch)
    n = parsed.count
    res = engine.store.resolve_block(parsed.id_block, parsed.width)
    emu, pool = res.emu, res.pool
    if emu is None or pool is None:  # no known session: nothing to step, every status says so
        if parsed.row_width() is None and n:
            raise ApiError(
                422,
                "wrong_length",
                f"binary body is {len(body)} bytes, which fits no whole number of float32 per session "
                f"for the {n} sessions the header announces",
                field="body",
                got=len(body),
            )
        return binary.encode_batch_response(
            np.full(n, binary.UNKNOWN, np.uint8), np.zeros((n, 0), np.float32)
        )
    nu, nf = emu.num_controls, emu.num_forces
    rows = parsed.rows(nu + nf, f"model {emu.model!r} ({nu} controls, {nf} forces)")
    # the common case in two comparisons: every input in range (NaN fails them too, and is then named)
    if (rows >= emu.input_low).all() and (rows <= emu.input_high).all():
        inputs, status = rows, np.zeros(n, np.uint8)
    else:
        binary.check_rows(rows, nu, parsed)
        clipped = ((rows < emu.input_low) | (rows > emu.input_high)).any(axis=1)
        inputs = np.clip(rows, emu.input_low, emu.input_high).astype(np.float32)
        status = np.where(clipped, binary.CLIPPED, binary.OK).astype(np.uint8)

    slots, known = res.slots, res.known
    states = np.full((n, emu.state_size), np.nan, np.float32)
    status[~known] = binary.UNKNOWN
    safe = np.where(known, slots, 0)
    diverged = known & pool.diverged[safe]
    status[diverged] = binary.DIVERGED
    states[diverged] = pool.states[slots[diverged]]
    # Sessions no other request is stepping are locked now (no await in between) and stepped as one
    # entry; one another request is stepping is stepped after it, one by one, holding only its lock.
    runnable = known & ~diverged
    busy = runnable & pool.busy[safe]
    free = np.flatnonzero(runnable & ~busy)
    batcher = engine.batcher(emu)
    t0 = time.perf_counter()
    if free.size:
        everyone = free.size == n  # the usual request: every session known, none busy or diverged
        mine = slots if everyone else slots[free]
        gens = pool.gen[mine]
        mine_in = inputs if everyone else inputs[free]
        pool.lock_rows(mine)
        try:
            new, rowst = await batcher.step_many(pool, mine, gens, mine_in[:, :nu], mine_in[:, nu:])
        finally:
            pool.unlock_rows(mine, gens)
        if everyone:
            states = new
        else:
            states[free] = new
        status[free[rowst == ROW_DIVERGED]] = binary.DIVERGED
        status[free[rowst == ROW_GONE]] = binary.UNKNOWN
    for i in np.flatnonzero(busy).tolist():
        one = pool.owner[int(slots[i])]
        if one is None or pool.gen[slots[i]] != res.gens[i]:
            status[i] = binary.UNKNOWN
            continue
        try:
            async with one.lock:
                states[i] = await batcher.step(one, inputs[i, :nu], inputs[i, nu:])
        except ApiError as exc:
            status[i] = binary.DIVERGED if exc.body.error == "diverged" else binary.UNKNOWN
            if one.alive:
                states[i] = one.state
    engine.metrics.latency(emu.model, "rest-binary").observe(time.perf_counter() - t0)
    return binary.encode_batch_response(status, states)
