"""``proto/`` (JSON Schemas of the wire models and the OpenAPI document) matches the code."""

from __future__ import annotations

from services import export_proto


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
    paths = export_proto.emulator_openapi()["paths"]
    body = paths["/step"]["post"]["requestBody"]["content"]
    assert {"application/json", "application/octet-stream"} <= set(body)


def test_proto_has_the_controller_contract() -> None:
    names = set(export_proto.controller_wire_schemas())
    assert {
        "JobCreate",
        "JobAccepted",
        "JobStatus",
        "JobResult",
        "TaskInfo",
        "ProgressEvent",
        "EndEvent",
    } <= names
    files = export_proto.render()
    assert "schemas/controller/JobCreate.json" in files and "controller.openapi.json" in files
    paths = export_proto.controller_openapi()["paths"]
    assert {"/jobs", "/jobs/{job_id}", "/jobs/{job_id}/result", "/jobs/{job_id}/events", "/tasks"} <= set(
        paths
    )
    assert "text/event-stream" in paths["/jobs/{job_id}/events"]["get"]["responses"]["200"]["content"]


def test_proto_has_the_results_contract() -> None:
    names = set(export_proto.results_wire_schemas())
    assert {"ModelEval", "ModelBench", "VersionEval", "VersionBench", "RolloutCurve"} <= names
    files = export_proto.render()
    assert "schemas/results/ModelEval.json" in files
    layout = export_proto.wire_schemas()["LayoutGroup"]
    assert "enum" in layout["properties"]["kind"]  # a closed set of kinds on the wire too


def test_proto_has_the_trainer_contract() -> None:
    names = set(export_proto.trainer_wire_schemas())
    assert {
        "TrainingUpload",
        "TrainingAccepted",
        "TrainingStatus",
        "TrainingResult",
        "StoredModelList",
    } <= names
    files = export_proto.render()
    assert "schemas/trainer/TrainingStatus.json" in files and "trainer.openapi.json" in files
    doc = export_proto.trainer_openapi()
    paths = doc["paths"]
    assert {"/trainings", "/trainings/{training_id}", "/trainings/{training_id}/events", "/models"} <= set(
        paths
    )
    post = paths["/trainings"]["post"]
    form = post["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert form["properties"]["file"]["format"] == "binary" and "super_step" in form["properties"]
    assert {"413", "415", "422", "429", "409"} <= set(post["responses"])


def test_ops_endpoints_are_documented_with_their_media_types() -> None:
    """``/metrics`` is Prometheus's text (never documented as JSON), ``/readyz`` JSON with its 503; and
    every error of every operation is the project's ``ErrorBody``, on all three services."""
    documents = {
        "emulator": export_proto.emulator_openapi(),
        "controller": export_proto.controller_openapi(),
        "trainer": export_proto.trainer_openapi(),
    }
    for name, doc in documents.items():
        metrics = doc["paths"]["/metrics"]["get"]["responses"]["200"]["content"]
        assert "application/json" not in metrics and any(t.startswith("text/plain") for t in metrics), name
        assert set(doc["paths"]["/readyz"]["get"]["responses"]) == {"200", "503"}, name
        for path, operations in doc["paths"].items():
            for method, op in operations.items():
                for code, response in op["responses"].items():
                    if code.startswith(("4", "5")) and path != "/readyz":
                        schema = response["content"]["application/json"]["schema"]
                        assert schema == {"$ref": "#/components/schemas/ErrorBody"}, (
                            name,
                            method,
                            path,
                            code,
                        )
