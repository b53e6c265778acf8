"""The README's API examples run as written against real services: the emulator over the committed
defaults, the controller's API with one worker on the session's Redis. The ``curl`` lines are read
from the README and sent as they say (method, headers, body; the placeholders ``r0-XXXXXXXXXXXXX``
and ``<id>`` replaced by what the calls before them answered), and the websocket client is run as
printed: after its lock-step hover and its real-time steps the lander is still up (a client that
says nothing after ``start`` keeps the last step's controls).
"""

from __future__ import annotations

import asyncio
import re
import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from neuroanimator.artifacts import registry
from services.emulator.app import create_app as emulator_app
from services.emulator.settings import Settings as EmulatorSettings
from tests.helpers import uvicorn_serving
from tests.services.controller.ctl import Controller

README = Path(__file__).resolve().parents[1] / "README.md"
SESSION = "r0-XXXXXXXXXXXXX"


def code_blocks(lang: str) -> list[str]:
    """The README's fenced code blocks in ``lang``, in order."""
    return re.findall(rf"^```{lang}\n(.*?)^```", README.read_text(), flags=re.S | re.M)


def the_block(lang: str, holding: str) -> str:
    found = [b for b in code_blocks(lang) if holding in b]
    assert len(found) == 1, f"one {lang} block of the README holds {holding!r}"
    return found[0]


def curl_commands(block: str) -> list[list[str]]:
    """Each ``curl`` command of a shell block as its words (continued lines joined, comments dropped)."""
    text = re.sub(r"\\\n\s*", " ", block)
    lines = (line.split(" #")[0].strip() for line in text.splitlines())
    return [shlex.split(line) for line in lines if line.startswith("curl ")]


def request(words: list[str], urls: dict[str, str]) -> tuple[str, str, dict[str, str], str | None]:
    """(method, url, headers, body) of a curl command; ``localhost:<port>`` goes to the test's server."""
    method, headers, body, url = "GET", {}, None, ""
    it = iter(words[1:])
    for w in it:
        if w == "-X":
            method = next(it)
        elif w == "-H":
            name, value = next(it).split(":", 1)
            headers[name.strip()] = value.strip()
        elif w == "-d":
            body = next(it)
            method = "POST" if method == "GET" else method
        elif w == "-N":
            continue
        else:
            assert not w.startswith("-"), f"a curl option this test does not read: {w}"
            url = w
    host, _, path = url.partition("/")
    return method, f"{urls[host]}/{path}", headers, body


@pytest.fixture(scope="module")
def services(redis_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    """The emulator (real time 20x faster than the model's Δt) and the controller API with a worker."""
    emulator = emulator_app(
        EmulatorSettings(
            artifacts_dir=registry.DEFAULTS_DIR,
            data_dir=tmp_path_factory.mktemp("data"),
            redis_url="",
            api_keys="",
            ws_realtime_scale=0.05,
        )
    )
    ctl = Controller(redis_url, tmp_path_factory.mktemp("controller"))
    ctl.worker()
    try:
        with uvicorn_serving(emulator) as e_port, uvicorn_serving(ctl.app()) as c_port:
            yield {
                "localhost:8000": f"http://127.0.0.1:{e_port}",
                "localhost:8001": f"http://127.0.0.1:{c_port}",
            }
    finally:
        ctl.close()


def test_the_api_at_a_glance(services: dict[str, str]) -> None:
    commands = curl_commands(the_block("bash", "curl localhost:8000/models"))
    assert len(commands) >= 7
    found: dict[str, str] = {}
    answers: dict[str, Any] = {}
    with httpx.Client(timeout=120) as http:
        for words in commands:
            method, url, headers, body = request(words, services)
            url = url.replace(SESSION, found.get("session", SESSION)).replace(
                "<id>", found.get("job", "<id>")
            )
            r = http.request(method, url, headers=headers, content=body)
            assert r.status_code < 400, (" ".join(words), r.status_code, r.text)
            if url.endswith("/sessions"):
                found["session"] = r.json()["id"]
            elif url.endswith("/jobs"):
                found["job"] = r.json()["id"]
            answers[url.rsplit("/", 1)[-1]] = r
    stepped = answers["step"].json()
    assert len(stepped["states"]) == 3 and stepped["states"][-1][2] > 9.0  # hovering, as the text says
    assert "event: end" in answers["events"].text  # the stream ran to the job's end
    assert answers["result"].json()["task"] == "truck-parking"


def test_the_websocket_client_keeps_the_lander_up(services: dict[str, str]) -> None:
    emulator = services["localhost:8000"]
    r = httpx.post(f"{emulator}/sessions", json={"model": "lander", "state": [0, 0, 10, 1] + [0] * 9})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    code = the_block("python", "websockets.connect")
    code = code.replace("ws://127.0.0.1:8000", emulator.replace("http://", "ws://"))
    code = code.replace(f'asyncio.run(main("{SESSION}"))', "")
    scope: dict[str, Any] = {}
    exec(compile(code, str(README), "exec"), scope)  # the README's client, as printed
    asyncio.run(scope["main"](sid))
    state = httpx.get(f"{emulator}/sessions/{sid}").json()["state"]
    assert state[2] > 8.0, f"the lander fell to z = {state[2]:.1f} m during the example"


def test_the_policy_example_lands_on_the_pad(services: dict[str, str]) -> None:
    """The README's policy session, as written, on the committed lander-landing policy: after its 80
    super-steps (20 s) the lander is down on the pad it was given, as the task judges a landing."""
    commands = curl_commands(the_block("bash", '"policy"'))
    assert len(commands) == 2
    with httpx.Client(timeout=120) as http:
        method, url, headers, body = request(commands[0], services)
        r = http.request(method, url, headers=headers, content=body)
        assert r.status_code == 201, r.text
        method, url, headers, body = request(commands[1], services)
        r = http.request(method, url.replace(SESSION, r.json()["id"]), headers=headers, content=body)
        assert r.status_code == 200, r.text
    final = r.json()["states"][-1]
    assert abs(final[0] - 5) < 1 and abs(final[1] + 3) < 1 and abs(final[2]) < 1, final[:3]
    assert -1.0 <= final[9] <= 0.0  # coming down softly
