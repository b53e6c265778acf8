"""The Policies page end to end, in headless Chromium (``tests/e2e/policies.mjs``) against the stack
(``services.stack``: emulator, controller API and worker, the dashboard's server, a real Redis) over a
registry of the lander's committed emulators alone, with a data directory of its own:

- a lander-landing policy trained through the dashboard with 15 s of budget and no refinement: its
  iterations, loss curve, success on MuJoCo and MuJoCo steps live, then the stored policy's metrics;
- "Drive it": a session driven by the policy beside its MuJoCo ghost; the pad dragged in the view goes
  over the websocket as the goal, the replies echo it and the lander moves; a goal typed outside the
  trained range is flagged; a kick goes on in a new session of the same policy and goal;
- the runner's committed running policy driven from the page's address: its speed command set with a
  slider (no marker: a command is no place), sent and echoed; the runner runs at it; a speed outside
  the trained range is flagged.

``E2E_UPDATE_DOCS=1`` copies the drive view and the training panel into ``docs/``.
"""

from __future__ import annotations

import json
import os
import shutil
import urllib.request
from collections.abc import Iterator

import pytest

from services.stack import Stack
from tests.e2e.harness import ROOT, missing, run_phase, running_stack, update_docs

SCRIPT = ROOT / "tests" / "e2e" / "policies.mjs"
DOC_SHOTS = {"policies.png": "policies.png", "policies-train.png": "policies-train.png"}
RUNNER_SHOTS = {"policies-runner.png": "policies-runner.png"}

pytestmark = pytest.mark.skipif(missing() is not None, reason=missing() or "")


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    registry = tmp_path_factory.mktemp("registry")
    shutil.copytree(ROOT / "artifacts" / "lander", registry / "lander")
    data = tmp_path_factory.mktemp("data")
    with running_stack(
        tmp_path_factory.mktemp("stack-logs"), artifacts_dir=registry, data_dir=data, trainer=False
    ) as s:
        yield s


def test_train_a_lander_policy_and_drive_it(stack: Stack) -> None:
    r = run_phase(stack, SCRIPT, "policies", 150)
    model, name, version = r["policy"].split("/")
    # the policy the page showed is the one stored, and the controller lists it
    assert (stack.config.data_dir / "policies" / model / name / version / "policy.json").is_file()
    with urllib.request.urlopen(f"{stack.urls['controller']}/policies?model=lander", timeout=10) as resp:
        listed = json.loads(resp.read())["policies"]
    assert [(p["name"], p["version"]) for p in listed] == [(name, version)]
    assert r["moved_m"] > 0.05 and 1 <= r["goal_messages"] <= 20
    print(f"policy trained in the browser in {r['training_s']} s; the phase took {r['wall_s']} s")
    if os.environ.get("E2E_UPDATE_DOCS") == "1":
        update_docs(DOC_SHOTS)


@pytest.fixture(scope="module")
def runner_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    """The stack over the runner's committed emulator and its committed running policy."""
    registry = tmp_path_factory.mktemp("runner-registry")
    shutil.copytree(ROOT / "artifacts" / "runner", registry / "runner")
    shutil.copytree(ROOT / "artifacts" / "policies" / "runner", registry / "policies" / "runner")
    with running_stack(
        tmp_path_factory.mktemp("runner-logs"),
        artifacts_dir=registry,
        data_dir=tmp_path_factory.mktemp("runner-data"),
        trainer=False,
    ) as s:
        yield s


def test_drive_the_runner_at_a_commanded_speed(runner_stack: Stack) -> None:
    r = run_phase(runner_stack, SCRIPT, "runner", 90)
    assert r["speed"] > 1.0
    if os.environ.get("E2E_UPDATE_DOCS") == "1":
        update_docs(RUNNER_SHOTS)
