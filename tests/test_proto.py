"""``proto/`` (JSON Schemas of the wire models and the OpenAPI document) matches the code."""

from __future__ import annotations

from services.emulator import export_proto


def test_proto_is_up_to_date() -> None:
    bad = export_proto.drift()
    assert not bad, f"proto/ drifted from the code; run {export_proto.COMMAND}. Differing files: {bad}"


def test_proto_lists_every_wire_model() -> None:
    names = set(export_proto.wire_schemas())
    assert {
        "BatchStepRequest",
        "ClientMessage",
        "ServerMessage",
        "WsStart",
        "WsStarted",
        "ErrorBody",
    } <= names
    paths = export_proto.openapi()["paths"]
    body = paths["/step"]["post"]["requestBody"]["content"]
    assert {"application/json", "application/octet-stream"} <= set(body)
