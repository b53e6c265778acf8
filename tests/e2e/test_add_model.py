"""The "Add a model" flow end to end, in headless Chromium (``tests/e2e/add_model.mjs``) against the
whole stack (``services.stack``: emulator, controller, trainer and their workers, the dashboard's
server, a real Redis) over an artifact registry of this module's own, holding one catalog emulator to
begin with:

- the project's small model folder (tests/data/tinybot: an include, an OBJ mesh in assets/, a
  texture), zipped here, is uploaded on the Models page with a tiny budget; its progress shows live to
  the result, and "Drive it" opens the Playground driving it, its knob drawn from the OBJ;
- bad models are refused at once in plain words: an actuator without a ctrlrange, an MJCF uploaded
  without the file it includes, a file that is no model; and an operating spec naming an actuator the
  model does not have, beside the spec's box.

``E2E_UPDATE_DOCS=1`` copies the Models page with the panel into ``docs/models-add-model.png``.
"""

from __future__ import annotations

import os
import shutil
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from neuroanimator.artifacts import registry
from services.stack import Stack
from tests.e2e.harness import ROOT, missing, run_phase, running_stack, update_docs

SCRIPT = ROOT / "tests" / "e2e" / "add_model.mjs"
TINYBOT = ROOT / "tests" / "data" / "tinybot"
NO_CTRLRANGE = """<mujoco model="noctrl">
  <worldbody>
    <body name="slider"><joint name="x" type="slide"/><geom type="box" size="0.1 0.1 0.1"/></body>
  </worldbody>
  <actuator><motor name="push" joint="x"/></actuator>
</mujoco>
"""
SLIDER = NO_CTRLRANGE.replace('"noctrl"', '"slider"').replace('joint="x"/>', 'joint="x" ctrlrange="-1 1"/>')

pytestmark = pytest.mark.skipif(missing() is not None, reason=missing() or "")


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """A stack whose committed defaults are pendulum-passive alone (so the Playground has a model to
    choose before the new one), with an empty data directory of its own; trainings as small as they come
    (2 evaluation rollouts of 2 s)."""
    defaults = tmp_path_factory.mktemp("registry")
    shutil.copytree(ROOT / "artifacts" / "pendulum-passive", defaults / "pendulum-passive")
    env = {"EVAL_TRIALS": "2", "EVAL_SECONDS": "2", "REGISTRY_POLL_S": "0.5", "JOB_TIMEOUT_S": "240"}
    data = tmp_path_factory.mktemp("data")
    logs = tmp_path_factory.mktemp("stack-logs")
    with running_stack(logs, artifacts_dir=defaults, data_dir=data, env=env) as s:
        yield s


def _zipped(folder: Path, archive: Path) -> Path:
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                zf.write(p, f"{folder.name}/{p.relative_to(folder).as_posix()}")
    return archive


def test_add_a_model_train_it_and_drive_it(stack: Stack, tmp_path: Path) -> None:
    model_zip = _zipped(TINYBOT, tmp_path / "tinybot.zip")
    r = run_phase(stack, SCRIPT, "add-model", 360, MODEL_ZIP=str(model_zip))
    assert r["phases"][-1] == "done" and r["one_step_rel_error"] > 0
    # the upload and its training are in the data directory; the committed defaults are as they were
    c = stack.config
    assert sorted(p.name for p in c.artifacts_dir.iterdir()) == ["pendulum-passive"]
    assert (c.data_dir / "tinybot" / registry.LATEST).is_file()
    assert registry.list_models(c.artifacts_dir) == ["pendulum-passive"]
    print(f"upload to drive in the browser: training {r['training_s']} s, phase {r['wall_s']} s in all")
    if os.environ.get("E2E_UPDATE_DOCS") == "1":
        update_docs({"models-add-model.png": "models-add-model.png"})


def test_bad_models_are_refused_in_plain_words(stack: Stack, tmp_path: Path) -> None:
    no_range = tmp_path / "noctrl.xml"
    no_range.write_text(NO_CTRLRANGE)
    slider = tmp_path / "slider.xml"
    slider.write_text(SLIDER)
    r = run_phase(
        stack,
        SCRIPT,
        "add-model-refused",
        120,
        NO_CTRLRANGE_XML=str(no_range),
        LONE_XML=str(TINYBOT / "robot.xml"),  # without parts/arm.xml, which it includes
        SPEC_XML=str(slider),
    )
    assert len(r["refusals"]) == 3
    assert "no actuator 'thrust9'" in r["spec_refusal"]
    assert not (stack.config.data_dir / "slider").exists()  # nothing kept of it
