"""Write the wire contract into ``proto/``: JSON Schemas of the models in ``neuroanimator.contracts.emulator``
(``proto/schemas/<Name>.json``) and the emulator service's OpenAPI document
(``proto/emulator.openapi.json``); the controller service's models (``neuroanimator.contracts.controller``,
``proto/schemas/controller/<Name>.json``) and OpenAPI document (``proto/controller.openapi.json``); the
evaluation and benchmark results the dashboard shows (``neuroanimator.core.results``,
``proto/schemas/results/<Name>.json``); the trainer service's models (``neuroanimator.contracts.trainer``,
``proto/schemas/trainer/<Name>.json``) and OpenAPI document (``proto/trainer.openapi.json``).
``proto/frames.md`` (the binary layouts) is written by hand.

    python -m services.export_proto            # (re)write proto/
    python -m services.export_proto --check    # exit 1 and list the files that drifted

The OpenAPI documents come from each service's ``create_app(...)`` over an empty artifact folder, so
no artifacts, Redis or API keys are needed. This module sits beside the services, not in one: it is
the only place that imports both.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import logging
import sys
import tempfile
from pathlib import Path
from typing import Any

from pydantic import BaseModel, TypeAdapter

from neuroanimator.contracts import controller as controller_schemas
from neuroanimator.contracts import emulator as emulator_schemas
from neuroanimator.contracts import trainer as trainer_schemas
from neuroanimator.core import results
from services.common.openapi import OpenApiDoc

log = logging.getLogger(__name__)
ROOT = Path(__file__).resolve().parents[1] / "proto"
COMMAND = "python -m services.export_proto  (or: make proto)"
UNIONS = ("ClientMessage", "ServerMessage")
CONTROLLER = "schemas/controller"  # the controller's schemas, beside (not among) the emulator's
RESULTS = "schemas/results"  # evaluation and benchmark results (served by the dashboard's server)
TRAINER = "schemas/trainer"  # the trainer's schemas


def _dump(obj: Any) -> str:
    return json.dumps(obj, indent=2, ensure_ascii=False) + "\n"


def wire_schemas() -> dict[str, OpenApiDoc]:
    """Every pydantic model defined in ``neuroanimator.contracts.emulator`` or listed in its
    ``WIRE_MODELS_FROM_ELSEWHERE``, plus the websocket message unions."""
    out: dict[str, OpenApiDoc] = {}
    for name, obj in vars(emulator_schemas).items():
        ours = (
            inspect.isclass(obj) and obj.__module__ == emulator_schemas.__name__ and not name.startswith("_")
        )
        if ours and issubclass(obj, BaseModel):
            out[name] = obj.model_json_schema()
    for model in emulator_schemas.WIRE_MODELS_FROM_ELSEWHERE:
        out[model.__name__] = model.model_json_schema()
    for name in UNIONS:
        schema = TypeAdapter(getattr(emulator_schemas, name)).json_schema()
        schema.setdefault("title", name)
        out[name] = schema
    return dict(sorted(out.items()))


def controller_wire_schemas() -> dict[str, OpenApiDoc]:
    """Every pydantic model defined in ``neuroanimator.contracts.controller``."""
    return _module_schemas(controller_schemas)


def trainer_wire_schemas() -> dict[str, OpenApiDoc]:
    """Every pydantic model defined in ``neuroanimator.contracts.trainer``."""
    return _module_schemas(trainer_schemas)


def results_wire_schemas() -> dict[str, OpenApiDoc]:
    """Every pydantic model defined in ``neuroanimator.core.results``."""
    return _module_schemas(results)


def _module_schemas(mod: Any) -> dict[str, OpenApiDoc]:
    return {
        name: obj.model_json_schema()
        for name, obj in sorted(vars(mod).items())
        if inspect.isclass(obj)
        and obj.__module__ == mod.__name__
        and not name.startswith("_")
        and issubclass(obj, BaseModel)
    }


def _job_service_openapi(service: str) -> OpenApiDoc:
    """A job service's document (``controller`` or ``trainer``); its Redis is not contacted, since
    connections are lazy."""
    app_module = importlib.import_module(f"services.{service}.app")
    settings_module = importlib.import_module(f"services.{service}.settings")
    with tempfile.TemporaryDirectory() as empty:
        settings = settings_module.Settings(
            artifacts_dir=Path(empty), api_keys="", cors_origins="", redis_url="redis://127.0.0.1:1/0"
        )
        doc: OpenApiDoc = app_module.create_app(settings).openapi()
    return doc


def controller_openapi() -> OpenApiDoc:
    """The controller API's document."""
    return _job_service_openapi("controller")


def trainer_openapi() -> OpenApiDoc:
    """The trainer API's document."""
    return _job_service_openapi("trainer")


def emulator_openapi() -> OpenApiDoc:
    """The emulator service's document (no Redis: persistence off)."""
    from services.emulator.app import create_app
    from services.emulator.settings import Settings

    with tempfile.TemporaryDirectory() as empty:
        settings = Settings(artifacts_dir=Path(empty), api_keys="", redis_url="")
        doc: OpenApiDoc = create_app(settings).openapi()
    return doc


def render() -> dict[str, str]:
    """The generated files of ``proto/``, by path relative to it."""
    files = {f"schemas/{name}.json": _dump(s) for name, s in wire_schemas().items()}
    files["emulator.openapi.json"] = _dump(emulator_openapi())
    files |= {f"{CONTROLLER}/{name}.json": _dump(s) for name, s in controller_wire_schemas().items()}
    files |= {f"{RESULTS}/{name}.json": _dump(s) for name, s in results_wire_schemas().items()}
    files["controller.openapi.json"] = _dump(controller_openapi())
    files |= {f"{TRAINER}/{name}.json": _dump(s) for name, s in trainer_wire_schemas().items()}
    files["trainer.openapi.json"] = _dump(trainer_openapi())
    return files


def _schema_files(root: Path) -> list[str]:
    """The schema files now in ``root`` (both folders), relative to it."""
    return [
        f"{d}/{p.name}"
        for d in ("schemas", CONTROLLER, RESULTS, TRAINER)
        for p in sorted((root / d).glob("*.json"))
    ]


def drift(root: Path = ROOT) -> list[str]:
    """Generated files that differ from (or are missing in) ``root``, and stale schema files."""
    want = render()
    bad = [p for p, text in want.items() if not (root / p).is_file() or (root / p).read_text() != text]
    stale = sorted(p for p in _schema_files(root) if p not in want)
    return sorted(bad) + stale


def write(root: Path = ROOT) -> list[str]:
    """(Re)write every generated file; returns the paths that changed."""
    changed = drift(root)
    files = render()
    (root / CONTROLLER).mkdir(parents=True, exist_ok=True)
    (root / RESULTS).mkdir(parents=True, exist_ok=True)
    (root / TRAINER).mkdir(parents=True, exist_ok=True)
    for p in _schema_files(root):
        if p not in files:
            (root / p).unlink()
    for path, text in files.items():
        target = root / path
        if not target.is_file() or target.read_text() != text:
            target.write_text(text)
    return changed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=ROOT, help="the proto folder (default: the repository's)")
    p.add_argument("--check", action="store_true", help="write nothing; exit 1 if proto/ drifted")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.check:
        bad = drift(args.out)
        for path in bad:
            log.error("drifted: %s", path)
        if bad:
            log.error("proto/ drifted from the code; run %s", COMMAND)
        return 1 if bad else 0
    changed = write(args.out)
    log.info("proto/: %d files updated%s", len(changed), "".join(f"\n  {c}" for c in changed))
    return 0


if __name__ == "__main__":
    sys.exit(main())
