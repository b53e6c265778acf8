"""The dashboard with API keys on (``API_KEYS``), end to end in headless Chromium
(``tests/e2e/api_key.mjs``) against the whole stack: without a key the pages say that one is needed and
where to enter it; with the key entered, models, a live Playground session (REST and websocket) and a
controller job followed over its event stream all work; forgotten, the key is asked for again."""

from __future__ import annotations

import shutil
from collections.abc import Iterator

import pytest

from services.stack import Stack
from tests.e2e.harness import ROOT, missing, run_phase, running_stack

SCRIPT = ROOT / "tests" / "e2e" / "api_key.mjs"
KEY = "e2e-key-7f3a"

pytestmark = pytest.mark.skipif(missing() is not None, reason=missing() or "")


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    registry = tmp_path_factory.mktemp("registry")
    shutil.copytree(ROOT / "artifacts" / "pendulum-active", registry / "pendulum-active")
    env = {"API_KEYS": f"{KEY},another-key", "API_KEY_SECRET": "e2e-secret"}
    with running_stack(tmp_path_factory.mktemp("stack-logs"), artifacts_dir=registry, env=env) as s:
        yield s


def test_the_dashboard_works_with_a_key_and_asks_for_one_without(stack: Stack) -> None:
    r = run_phase(stack, SCRIPT, "api-key", 300, API_KEY=KEY)
    assert r["session_t"][1] > r["session_t"][0]
