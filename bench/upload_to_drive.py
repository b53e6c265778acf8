"""Upload to first drive: how long a new model takes from its upload to its first emulated step.

    python bench/upload_to_drive.py                              # the default models, service defaults
    python bench/upload_to_drive.py --model path/to/model.zip --entry robot.xml --json

Starts, on a registry of its own, a trainer API with one training worker (``bench/_trainer.py``) and an
emulator service (which picks up new artifacts without a restart). Each model is uploaded through
``POST /trainings`` with the service's defaults (super-step ``auto``, the default sample budget) unless
``--examples`` / ``--super-step`` say otherwise; the benchmark records how long the upload's answer took
(validation), the seconds spent in each phase (the result's ``phase_seconds``), the training's own total,
and then how long until the emulator service lists the model and answers a session's first step: that
moment is "first drive", counted from the upload.

The default models: the project's small model folder (``tests/data/tinybot``: an include, an OBJ mesh
and a texture, zipped here) and dm_control's ``cartpole.xml`` as the installed package ships it (its
suite folder zipped with the includes it uses). Targets: first drive ≤ 5 minutes for a model of up to
10 degrees of freedom; validation ≤ 1 s. Meaningful on a quiet machine only (``uptime`` below 1.5;
``--force`` runs anyway). Redis: ``REDIS_URL``, else 127.0.0.1:6379.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any

import httpx
from _server import serve
from _trainer import Trainer, trainer

ROOT = Path(__file__).resolve().parents[1]
TINYBOT = ROOT / "tests" / "data" / "tinybot"
FINAL = ("succeeded", "failed", "cancelled")
PHASES = ("validating", "sampling", "training", "evaluating", "exporting")
log = logging.getLogger("upload_to_drive")


def zip_folder(folder: Path, out: Path, only: list[str] | None = None) -> Path:
    """``folder`` (or just the files named in ``only``, relative to it) as a zip archive at ``out``."""
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        files = [folder / f for f in only] if only else sorted(p for p in folder.rglob("*") if p.is_file())
        for f in files:
            z.write(f, f.relative_to(folder).as_posix())
    return out


def default_models(work: Path) -> list[tuple[str, Path, str]]:
    """(name, archive, entry XML) of the default models; dm_control's cartpole when it is installed."""
    models = [("tinybot", zip_folder(TINYBOT, work / "tinybot.zip"), "robot.xml")]
    try:
        from dm_control import suite
    except ImportError:
        log.warning("dm_control is not installed: its cartpole is left out")
        return models
    folder = Path(suite.__file__).parent
    used = ["cartpole.xml", "common/materials.xml", "common/skybox.xml", "common/visual.xml"]
    models.append(("cartpole", zip_folder(folder, work / "cartpole.zip", used), "cartpole.xml"))
    return models


def first_step(emulator: str, model: str, deadline: float) -> float:
    """Waits until the emulator service serves ``model``, then starts a session and steps it once;
    returns the time (``time.monotonic()``) the step's answer came."""
    while time.monotonic() < deadline:
        r = httpx.get(f"{emulator}/models/{model}", timeout=10)
        if r.status_code == 200:
            break
        time.sleep(0.2)
    else:
        raise SystemExit(f"the emulator service did not serve {model!r} in time")
    detail = r.json()
    session = httpx.post(f"{emulator}/sessions", json={"model": model}, timeout=10)
    session.raise_for_status()
    sid = session.json()["id"]
    controls = [0.0] * len(detail.get("controls", []))
    step = httpx.post(f"{emulator}/sessions/{sid}/step", json={"controls": controls}, timeout=10)
    step.raise_for_status()
    return time.monotonic()


def drive(
    t: Trainer, emulator: str, name: str, archive: Path, entry: str, fields: dict[str, str]
) -> dict[str, Any]:
    """Upload one model and follow it to its first step in the emulator service."""
    start = time.monotonic()
    answer, validation_s = t.upload(archive, name=name, entry=entry, **fields)
    tid = answer["id"]
    deadline = start + 1800
    last_phase = ""
    while (s := t.status(tid))["status"] not in FINAL:
        if s["phase"] != last_phase:
            last_phase = s["phase"]
            log.info("%s: %s (%.0f s)", name, last_phase, time.monotonic() - start)
        if time.monotonic() > deadline:
            raise SystemExit(f"{name}: the training did not end in 30 minutes")
        time.sleep(0.5)
    trained = time.monotonic()
    if s["status"] != "succeeded":
        return {"model": name, "status": s["status"], "error": s.get("error"), "validation_s": validation_s}
    served = first_step(emulator, s["model"], trained + 60)
    result = s["result"]
    return {
        "model": name,
        "status": s["status"],
        "validation_s": round(validation_s, 3),
        "phase_seconds": result.get("phase_seconds", {}),
        "substeps": result["substeps"],
        "examples": result.get("examples"),
        "one_step_rel_error": result.get("one_step_rel_error"),
        "linear_baseline_rel_error": result.get("linear_baseline_rel_error"),
        "training_s": round(trained - start, 1),
        "first_drive_s": round(served - start, 1),
        "notes": result.get("notes", []),
    }


def table(rows: list[dict[str, Any]]) -> str:
    seen = {p for r in rows for p in r.get("phase_seconds", {})}
    phases = [p for p in PHASES if p in seen] + sorted(seen - set(PHASES))
    head = ["model", "validation s", *[f"{p} s" for p in phases], "n", "one-step", "linear", "first drive s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        if r["status"] != "succeeded":
            lines.append(f"| {r['model']} | {r['validation_s']:.2f} | {r['status']}: {r.get('error')} |")
            continue
        cells = [r["model"], f"{r['validation_s']:.2f}"]
        cells += [f"{r['phase_seconds'].get(p, 0.0):.1f}" for p in phases]
        cells += [
            str(r["substeps"]),
            f"{r['one_step_rel_error']:.4f}",
            f"{r['linear_baseline_rel_error']:.4f}",
        ]
        cells.append(f"{r['first_drive_s']:.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", type=Path, help="an XML or an archive to upload instead of the default models")
    p.add_argument("--entry", help="the entry XML inside --model's archive")
    p.add_argument("--examples", type=int, help="the sample budget (default: the service's)")
    p.add_argument("--super-step", default="auto", help="n, or auto (the default)")
    p.add_argument("--epochs", type=int, help="most epochs of the one-step phase (default: the service's)")
    p.add_argument("--keep", action="store_true", help="keep an emulator that misses the acceptance bar")
    p.add_argument("--force", action="store_true", help="run even on a busy machine (numbers not comparable)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    load = os.getloadavg()[0]
    if load >= 1.5 and not args.force:
        print(f"the machine is busy (load {load:.2f}); run it when `uptime` says below 1.5 (or --force)")
        return 2
    redis_url = os.environ.get("REDIS_URL", "redis://127.0.0.1:6379/0")
    fields = {"super_step": args.super_step}
    if args.keep:
        fields["force"] = "true"
    for key in ("examples", "epochs"):
        if getattr(args, key):
            fields[key] = str(getattr(args, key))
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-upload-") as tmp:
        work = Path(tmp)
        models = [(args.model.stem, args.model, args.entry or "")] if args.model else default_models(work)
        with (
            trainer(redis_url, work) as t,
            serve(str(t.registry), ready="/healthz", REGISTRY_POLL_S="1") as (emulator, _pid),
        ):
            for name, archive, entry in models:
                rows.append(drive(t, emulator, name, archive, entry, fields))
                log.info("%s", json.dumps(rows[-1]))
    print(table(rows))
    if args.json:
        print(json.dumps({"models": rows, "load": load, "fields": fields}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
