"""Schemathesis over the three services' OpenAPI documents, against the real processes (uvicorn, the
committed artifacts (the trainer: a registry of its own), the session's Redis): every generated
request, valid or not, must be answered without a 5xx and with a body that conforms to the document
(``not_a_server_error``, ``response_schema_conformance``).

The suite runs ``FUZZ_EXAMPLES`` examples per operation (default 8: 353 emulator, 562 controller and
242 trainer cases, about half a minute); ``python bench/fuzz_openapi.py`` runs the same tests with more
(1,000+ cases per service) and records the counts. ``FUZZ_REPORT=<file>`` writes what was run: cases and status codes by service.
"""

from __future__ import annotations

import json
import os
import sys
import uuid
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import redis
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import response_schema_conformance

ROOT = Path(__file__).resolve().parents[2]
sys.path.append(str(ROOT / "bench"))  # its _server (bench/ is no package)
from _server import serve  # noqa: E402

EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "8"))


def no_server_error(ctx: Any, response: Any, case: Any) -> bool | None:
    """``not_a_server_error``, but for the documented 503 of ``/readyz``: these deployments run no
    worker, and a queue with no worker is not ready (its body is checked against the schema still)."""
    if case.path == "/readyz" and response.status_code == 503:
        return None
    result: bool | None = not_a_server_error(ctx, response, case)
    return result


CHECKS = [no_server_error, response_schema_conformance]
SEEN: dict[str, Counter[int]] = {"emulator": Counter(), "controller": Counter(), "trainer": Counter()}


@pytest.fixture(scope="module", autouse=True)
def _report() -> Iterator[None]:
    yield
    if os.environ.get("FUZZ_REPORT"):
        out = {
            name: {"cases": sum(c.values()), "status": {str(k): v for k, v in sorted(c.items())}}
            for name, c in SEEN.items()
        }
        Path(os.environ["FUZZ_REPORT"]).write_text(json.dumps(out, indent=2) + "\n")


@pytest.fixture(scope="module")
def emulator_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    with serve(str(ROOT / "artifacts"), "services.emulator", MAX_SESSIONS_PER_KEY="1000000") as (url, _pid):
        yield url


@pytest.fixture(scope="module")
def controller_url(redis_url: str) -> Iterator[str]:
    tag = uuid.uuid4().hex[:10]
    prefix, queue = f"test-fuzz:{tag}", f"test-fuzz-{tag}"
    env = {"REDIS_URL": redis_url, "REDIS_PREFIX": prefix, "QUEUE_NAME": queue, "MAX_QUEUE": "1000000"}
    try:
        with serve(str(ROOT / "artifacts"), "services.controller", ready="/healthz", **env) as (url, _pid):
            yield url
    finally:  # no worker ever takes the queued jobs: remove them with their records
        _drop(redis_url, prefix, queue)


def _drop(redis_url: str, prefix: str, queue: str) -> None:
    """Remove a deployment's records and queued deliveries (no worker ever takes them)."""
    client = redis.Redis.from_url(redis_url)
    keys = list(client.scan_iter(match=f"{prefix}:*", count=1000))
    jobs = {k.decode().rsplit(":", 1)[1] for k in keys if b":job:" in k}
    keys += [f"rq:job:{j}-1".encode() for j in jobs]
    keys += list(client.scan_iter(match=f"rq:*{queue}", count=1000))
    for i in range(0, len(keys), 1000):
        client.delete(*keys[i : i + 1000])
    client.close()


@pytest.fixture(scope="module")
def trainer_url(redis_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    tag = uuid.uuid4().hex[:10]
    prefix, queue = f"test-fuzz-trainer:{tag}", f"test-fuzz-trainer-{tag}"
    env = {"REDIS_URL": redis_url, "REDIS_PREFIX": prefix, "QUEUE_NAME": queue, "MAX_QUEUE": "1000000"}
    env |= {"MAX_TRAININGS_PER_KEY": "1000000"}
    try:
        with serve(str(tmp_path_factory.mktemp("registry")), "services.trainer", ready="/healthz", **env) as (
            url,
            _pid,
        ):
            yield url
    finally:
        _drop(redis_url, prefix, queue)


@pytest.fixture
def trainer_schema(trainer_url: str) -> Any:
    return schemathesis.openapi.from_url(f"{trainer_url}/openapi.json")


@pytest.fixture
def emulator_schema(emulator_url: str) -> Any:
    return schemathesis.openapi.from_url(f"{emulator_url}/openapi.json")


@pytest.fixture
def controller_schema(controller_url: str) -> Any:
    return schemathesis.openapi.from_url(f"{controller_url}/openapi.json")


emulator = schemathesis.pytest.from_fixture("emulator_schema")
controller = schemathesis.pytest.from_fixture("controller_schema")
trainer = schemathesis.pytest.from_fixture("trainer_schema")
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=os.environ.get("FUZZ_RANDOM") is None,  # the suite's cases are the same every run
    suppress_health_check=list(HealthCheck),
    database=None,
)


@emulator.parametrize()
@FUZZ
def test_emulator_api(case: Any) -> None:
    response = case.call_and_validate(checks=CHECKS, timeout=30)
    SEEN["emulator"][response.status_code] += 1


@controller.parametrize()
@FUZZ
def test_controller_api(case: Any) -> None:
    response = case.call_and_validate(checks=CHECKS, timeout=30)
    SEEN["controller"][response.status_code] += 1


@trainer.parametrize()
@FUZZ
def test_trainer_api(case: Any) -> None:
    response = case.call_and_validate(checks=CHECKS, timeout=30)
    SEEN["trainer"][response.status_code] += 1
