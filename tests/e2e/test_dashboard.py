"""The dashboard end to end, in headless Chromium: the stack (``services.stack``) is started here on
free ports with a Redis found or started as ``make up`` does, then ``tests/e2e/dashboard.mjs`` drives
the browser phase by phase at 1280×800:

- Models: every model, the rollout curves of the versions the emulator serves with what their error
  means in words, the lander's errors in physical units, long tables folded, the page under 6000 px
  and no request for a result that does not exist;
- Playground: a live lander session that starts at hover thrust and stays where it starts, on screen
  with the ground and its pad below it, driven by the keyboard, the MuJoCo ghost and the gap to it
  (number and curve, in a small corner clear of the model), the frame rate, then driven out of its
  training envelope, which the page reports; then, without reloading, a
  pendulum-force session framed with its ground and driven through its force sliders; then the dolphin,
  drawn as a skin over its nodes and bent by its muscle sliders; then the runner, driven by its own
  running controller at the target speed its slider sets, beside its MuJoCo ghost;
- Controllers: a truck-parking job (goal dragged, objective curve live and falling), its outcome and
  verdict checked against the job's result check by check, the replay with model and goal on screen,
  the model drawn big enough to read, and the gap plotted; switching to lander-landing clears the job
  and frames the lander and its goal, and its job's outcome and replay are checked the same way (the
  emulated lander not tinted by the MuJoCo outline); dolphin-swim shows no goal, says its gradients
  went through the global network, is "done, no criterion" (not "succeeded"), and is replayed on both
  sides;
- with the worker stopped, the message that no worker is taking jobs.

Screenshots go to ``tests/e2e/screenshots/`` (ignored by git); ``E2E_UPDATE_DOCS=1`` copies those the
README shows into ``docs/`` (``DOC_SHOTS``).
"""

from __future__ import annotations

import json
import os
import urllib.request
from collections.abc import Iterator
from typing import Any

import pytest

from services.stack import Stack
from tests.e2e.harness import ROOT, missing, run_phase, running_stack, update_docs

SCRIPT = ROOT / "tests" / "e2e" / "dashboard.mjs"
# screenshot of a phase -> its name under docs/ (shown in the README)
DOC_SHOTS = {
    "models.png": "models.png",
    "playground.png": "playground.png",
    "playground-pendulum-force.png": "playground-pendulum-force.png",
    "playground-dolphin.png": "playground-dolphin.png",
    "playground-runner.png": "playground-runner.png",
    "controllers.png": "controllers.png",
    "controllers-lander.png": "controllers-lander.png",
    "replay.png": "replay.png",
    "replay-lander.png": "replay-lander.png",
    "replay-dolphin.png": "replay-dolphin.png",
}

pytestmark = pytest.mark.skipif(missing() is not None, reason=missing() or "")


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    with running_stack(tmp_path_factory.mktemp("stack-logs")) as s:
        yield s


def _phase(stack: Stack, phase: str, timeout: float, **env: str) -> dict[str, Any]:
    return run_phase(stack, SCRIPT, phase, timeout, **env)


def _truck_task(stack: Stack) -> str:
    with urllib.request.urlopen(f"{stack.urls['controller']}/tasks", timeout=10) as r:
        body = json.loads(r.read())
    tasks = body["tasks"] if isinstance(body, dict) else body
    names = [t["name"] for t in tasks if t.get("model") == "truck"]
    assert names, f"no truck task in {tasks}"
    return str(names[0])


def test_models_page(stack: Stack) -> None:
    r = _phase(stack, "models", 120)
    assert r["models"] >= 5


def test_playground_drives_a_lander_then_a_pendulum(stack: Stack) -> None:
    r = _phase(stack, "playground", 300)
    assert r["changed_cells"] > 20
    print(
        "dashboard fps with a live lander session and its ghost (headless Chromium, software WebGL): "
        f"{r['fps']} at resolution scale {r['resolution_scale']}"
    )


def test_controller_job_and_replay(stack: Stack) -> None:
    r = _phase(stack, "controllers", 420, TRUCK_TASK=_truck_task(stack))
    assert r["objective_last"] < r["objective_first"]
    if os.environ.get("E2E_UPDATE_DOCS") == "1":
        update_docs(DOC_SHOTS)


def test_stopped_worker_is_reported(stack: Stack) -> None:
    task = _truck_task(stack)
    stack.stop_service("worker")
    r = _phase(stack, "worker-down", 120, TRUCK_TASK=task)
    assert "worker" in r["message"]
