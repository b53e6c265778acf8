"""The public zoo: every model of dm_control's suite, as the installed package ships it, trained with
``neuro train --mjcf`` and evaluated; plus the catalog's committed emulators. Fetches nothing.

    python bench/zoo.py [--models cartpole,acrobot] [--no-catalog] [--quick] [--out DIR] [--json]

Each suite model is trained exactly as a user would (``neuro train --mjcf PATH --json``; the super-step
is chosen by the trainer), in its own process, then evaluated against MuJoCo (physical errors at 5 and
20 s). The swimmer and the LQR model are built by their own functions (they are made, not shipped as
finished files). One row per model: accepted or refused (with the reason), state size, super-step and
why, training seconds, one-step error, linear baseline, physical errors, and whether it meets the bar:
without contact, one-step ≤ 0.01 and ≥ 5× below linear at n = 50; with contact, ≤ 0.01 at the chosen n
(≥ 10). ``--quick`` trains with tiny budgets (a smoke test of the pipeline, not a measurement).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

log = logging.getLogger("zoo")

TARGET = 0.01
LINEAR_GAIN = 5.0
QUICK = ["--examples", "400", "--epochs", "3", "--hidden", "16", "--rollout-steps", "0", "--force"]
MADE = ("swimmer", "lqr")  # built by their own functions


@dataclass
class ZooRow:
    model: str
    source: str  # "dm_control" or "catalog"
    accepted: bool
    emulator: str | None = None  # its name in the registry (the MJCF's model attribute, made a name)
    reason: str = ""  # why refused, or why this super-step
    state_size: int | None = None
    substeps: int | None = None
    contact: bool | None = None
    train_s: float | None = None
    one_step: float | None = None
    linear: float | None = None
    root_m_5s: float | None = None
    root_m_20s: float | None = None
    attitude_deg_5s: float | None = None
    attitude_deg_20s: float | None = None
    joint_rad_5s: float | None = None
    joint_rad_20s: float | None = None
    joint_m_5s: float | None = None
    joint_m_20s: float | None = None
    finite: bool | None = None  # every evaluated rollout stayed finite
    meets_bar: bool | None = None


def suite_dir() -> Path:
    from dm_control import suite

    return Path(suite.__file__).parent


def suite_models(only: set[str] | None, workdir: Path) -> dict[str, Path]:
    """Name -> entry MJCF of every suite model (the shipped files, or the made ones written beside a copy
    of the suite's ``common/`` folder so that their includes resolve)."""
    import shutil

    from dm_control.suite import lqr, swimmer

    here = suite_dir()
    models = {p.stem: p for p in sorted(here.glob("*.xml")) if p.stem not in MADE}
    made_dir = workdir / "made"
    shutil.copytree(here / "common", made_dir / "common", dirs_exist_ok=True)
    makers = {
        "swimmer": lambda: swimmer.get_model_and_assets(6)[0],
        "lqr": lambda: lqr.get_model_and_assets(2, 1, __import__("numpy").random.RandomState(0))[0],
    }
    for name, make in makers.items():
        if only is None or name in only:
            path = made_dir / f"{name}.xml"
            xml = make()
            path.write_bytes(xml if isinstance(xml, bytes) else xml.encode())
            models[name] = path
    return {k: v for k, v in sorted(models.items()) if only is None or k in only}


def _last_json(text: str) -> dict[str, Any] | None:
    for line in reversed(text.strip().splitlines()):
        if line.startswith("{"):
            try:
                parsed: dict[str, Any] = json.loads(line)
                return parsed
            except json.JSONDecodeError:
                return None
    return None


def _error_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if " ERROR " in ln or "Error" in ln]
    line = lines[-1] if lines else (text.strip().splitlines() or ["no output"])[-1]
    return line.split(": ", 1)[-1] if " ERROR " in line else line


def _physical(row: ZooRow, root: Path, name: str, trials: int) -> None:
    from neuroanimator.artifacts import registry
    from neuroanimator.evaluation import evaluate as evaluation

    path = registry.resolve(root, name)
    manifest = registry.read_manifest(path)
    model = registry.load_physical_model(path, manifest)
    steps = round(20.0 / model.dt) + manifest.substeps
    curve, phys = evaluation.rollout_errors(path, model, manifest.substeps, trials=trials, steps=steps)
    row.finite = all(math.isfinite(e) and e < 1e5 for e in curve.error)
    for quantity, short in (
        ("root_position_m", "root_m"),
        ("attitude_deg", "attitude_deg"),
        ("joint_angle_rad", "joint_rad"),
        ("joint_position_m", "joint_m"),
    ):
        for t in (5, 20):
            at = phys.at(quantity, float(t))
            if at is not None:
                setattr(row, f"{short}_{t}s", at.mean)


def bar(row: ZooRow) -> bool:
    if row.one_step is None or row.linear is None or row.substeps is None:
        return False
    if row.contact:
        return row.one_step <= TARGET and row.substeps >= 10
    from neuroanimator.training.super_step import ACCEPT_ERROR

    # an emulator under the absolute floor (an exact one of a linear system) has no baseline to beat
    beats_linear = row.linear >= LINEAR_GAIN * row.one_step or row.one_step <= ACCEPT_ERROR
    return row.one_step <= TARGET and beats_linear and row.substeps == 50


def train_suite_model(name: str, xml: Path, root: Path, quick: bool, timeout: float) -> ZooRow:
    cmd = [sys.executable, "-m", "neuroanimator.cli", "train", "--mjcf", str(xml), "--out", str(root)]
    cmd += ["--quiet", "--json", *(QUICK if quick else [])]
    t0 = time.perf_counter()
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return ZooRow(name, "dm_control", False, reason=f"training ran past {timeout:.0f} s")
    wall = time.perf_counter() - t0  # the whole command: loading, probes, sampling, training, export
    summary = _last_json(done.stdout)
    if summary is None or (done.returncode != 0 and summary.get("accepted") is not False):
        return ZooRow(name, "dm_control", False, reason=_error_line(done.stderr + done.stdout), train_s=wall)
    accepted = done.returncode == 0 and summary.get("accepted", True)
    return ZooRow(
        model=name,
        source="dm_control",
        accepted=accepted,
        emulator=summary["model"] if accepted else None,
        # a refusal's reason says what it missed (and what cut its data); an acceptance, its super-step
        reason=summary.get("substeps_reason", "") if accepted else summary.get("reason", ""),
        state_size=summary.get("state_size"),
        substeps=summary["substeps"],
        contact=summary.get("contact_fraction", 0.0) > 0,
        train_s=wall,
        one_step=summary["one_step_rel_error"],
        linear=summary["linear_baseline_rel_error"],
    )


def catalog_rows(artifacts: Path, trials: int) -> list[ZooRow]:
    """The catalog's committed emulators (the latest version of each), as trained for the catalog."""
    from neuroanimator import catalog
    from neuroanimator.artifacts import registry
    from neuroanimator.training.super_step import constraint_activity

    rows = []
    for name in catalog.CATALOG:
        try:
            path = registry.resolve(artifacts, name)
        except registry.ArtifactError as exc:
            rows.append(ZooRow(name, "catalog", False, reason=str(exc)))
            continue
        m = registry.read_manifest(path)
        activity = constraint_activity(catalog.get(name))
        row = ZooRow(
            model=name,
            source="catalog",
            accepted=True,
            emulator=name,
            reason=f"committed {m.version}",
            state_size=m.state_size,
            substeps=m.substeps,
            contact=activity.contact > 0,
            train_s=m.metrics.total_seconds,
            one_step=m.metrics.one_step_rel_error,
            linear=m.metrics.linear_baseline_rel_error,
        )
        _physical(row, artifacts, name, trials)
        rows.append(row)
    return rows


def _fmt(v: Any, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def print_table(rows: list[ZooRow]) -> None:
    print(
        "| model | source | accepted | S | n | contact | train s | one-step | linear | root m @5/20 s | attitude ° @5/20 s | joints rad @5/20 s | slides m @5/20 s | meets bar |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        acc = "yes" if r.accepted else f"no: {r.reason}"
        pair = lambda a, b, f: f"{_fmt(a, f)} / {_fmt(b, f)}"  # noqa: E731
        print(
            f"| {r.model} | {r.source} | {acc} | {_fmt(r.state_size, 'd')} | {_fmt(r.substeps, 'd')} | "
            f"{'-' if r.contact is None else ('yes' if r.contact else 'no')} | {_fmt(r.train_s, '.0f')} | "
            f"{_fmt(r.one_step, '.4f')} | {_fmt(r.linear, '.3f')} | {pair(r.root_m_5s, r.root_m_20s, '.3g')} | "
            f"{pair(r.attitude_deg_5s, r.attitude_deg_20s, '.3g')} | {pair(r.joint_rad_5s, r.joint_rad_20s, '.3g')} | "
            f"{pair(r.joint_m_5s, r.joint_m_20s, '.3g')} | "
            f"{'-' if r.meets_bar is None else ('yes' if r.meets_bar else 'no')} |"
        )
    print()
    for r in rows:
        if r.accepted and r.reason and r.source == "dm_control":
            print(f"- {r.model}: {r.reason}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", help="only these suite models, comma-separated (default: all)")
    p.add_argument("--no-catalog", action="store_true", help="leave out the catalog's committed emulators")
    p.add_argument("--artifacts", default="artifacts", help="the catalog's registry (default: artifacts/)")
    p.add_argument("--out", help="registry for the suite's emulators (default: a temporary folder)")
    p.add_argument("--quick", action="store_true", help="tiny budgets: a smoke test, not a measurement")
    p.add_argument("--trials", type=int, default=10, help="rollouts per model for the physical errors")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds allowed per training")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    order = args.models.split(",") if args.models else None
    only = set(order) if order else None
    with tempfile.TemporaryDirectory(prefix="zoo-") as tmp:
        root = Path(args.out) if args.out else Path(tmp) / "registry"
        rows: list[ZooRow] = []
        models = suite_models(only, Path(tmp))
        if order:  # in the order given: the first ones first on a long run
            models = {k: models[k] for k in order if k in models}
        for name, xml in tqdm(models.items(), desc="zoo", unit="model"):
            row = train_suite_model(name, xml, root, args.quick, args.timeout)
            if row.accepted:
                assert row.emulator is not None
                _physical(row, root, row.emulator, 3 if args.quick else args.trials)
                row.meets_bar = bar(row)
            log.info("%s: %s", name, "accepted" if row.accepted else f"refused: {row.reason}")
            log.info("row %s", json.dumps(asdict(row)))  # a partial run keeps what it measured
            rows.append(row)
        if not args.no_catalog:
            for row in catalog_rows(Path(args.artifacts), 3 if args.quick else args.trials):
                row.meets_bar = bar(row)
                rows.append(row)
    print_table(rows)
    if args.json:
        print(json.dumps({"rows": [asdict(r) for r in rows]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
