"""The upload probe's costly cases, against a real trainer API and emulator service on this machine.

    python bench/upload_probe.py [--redis-url URL] [--repeats 20] [--ws-seconds 10] [--json]

Starts the trainer API (no worker: accepted trainings stay queued; per-key limits raised so that every
upload is checked) and the emulator service on the committed artifacts, then measures:

- how each costly upload is answered, and in how long: a 60 MB XML in a zip of under 1 MB, a
  531-byte ``<replicate>`` of 30,000 bodies, a .tar.gz of a million folder entries, the DOCTYPE
  include of another tenant's model and a flexcomp of the server's file;
- the check of valid uploads of 10, 100 and 1,000 bodies (``--repeats`` each): p50 and p99 seconds;
- ``/healthz`` of the trainer API every 50 ms throughout (from a process of its own): its largest and
  p99 latency;
- the trainer API's resident memory before and after everything;
- an 8 MB JSON batch of 300,000 items to the emulator's ``POST /step``: how long its refusal takes;
- websocket steps on the emulator (``bench/ws_load.py``, 20 clients) alone and while the costly
  uploads run: p99 latency both times.

A table, and with ``--json`` one JSON object as the last line.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
import uuid
import zipfile
from pathlib import Path
from typing import Any

import httpx
import redis
from _server import REPO, rss_bytes, serve

DECOY = (
    '<mujoco model="decoy"><worldbody><body><joint name="h" type="hinge"/><geom size=".1"/></body>'
    '</worldbody><actuator><motor joint="h" ctrlrange="-1 1"/></actuator></mujoco>'
)


def bodies(n: int) -> bytes:
    """A valid model of ``n`` bodies, each on a hinge of its own, one motor."""
    parts = "".join(
        f'<body name="b{i}" pos="{i * 0.3:.1f} 0 0"><joint name="j{i}" type="hinge" damping="0.1"/>'
        f'<geom type="capsule" size=".05 .1"/></body>'
        for i in range(n)
    )
    return (
        f'<mujoco model="chain{n}"><option timestep="0.005"/><worldbody>{parts}</worldbody>'
        '<actuator><motor joint="j0" ctrlrange="-1 1"/></actuator></mujoco>'
    ).encode()


def big_xml_zip() -> bytes:
    """A zip of about 1 MB holding a 60 MB MJCF (many small bodies, each named)."""
    buf = io.BytesIO()
    with (
        zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf,
        zf.open("m/model.xml", "w") as out,
    ):
        out.write(b'<mujoco model="big"><worldbody>')
        written, i = 0, 0
        while written < 60 << 20:
            chunk = b"".join(
                b'<body name="b%d"><joint type="hinge"/><geom size=".1"/></body>' % k
                for k in range(i, i + 10_000)
            )
            out.write(chunk)
            written, i = written + len(chunk), i + 10_000
        out.write(b"</worldbody></mujoco>")
    return buf.getvalue()


def replicate() -> bytes:
    return (
        DECOY.replace("<body>", '<replicate count="30000" offset="0.1 0 0"><body>', 1)
        .replace("</body>", "</body></replicate>", 1)
        .encode()
    )


def million_folders() -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=9) as tf:
        info = tarfile.TarInfo("d")
        info.type = tarfile.DIRTYPE
        for i in range(1_000_000):
            info.name = f"d{i}"
            tf.addfile(info)
    return buf.getvalue()


def doctype(target: str) -> bytes:
    return (
        f"<!DOCTYPE x [<!ENTITY a \">\n<mujoco model='s'><include file='{target}'/></mujoco>\n<!-- \">]>\n"
        + DECOY
        + "\n<!-- -->\n"
    ).encode()


_POLL = """
import json, select, sys, time
import httpx
lat = []
with httpx.Client(timeout=30) as c:
    while not select.select([sys.stdin], [], [], 0.05)[0]:
        t0 = time.perf_counter()
        try:
            c.get(sys.argv[1] + "/healthz")
        except httpx.HTTPError:
            pass
        lat.append(time.perf_counter() - t0)
print(json.dumps(lat))
"""


class Poller:
    """GET /healthz every 50 ms from a process of its own (so that this one's work does not delay
    the measurement); ``stop`` returns the latencies in seconds."""

    def __init__(self, url: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _POLL, url], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )

    def stop(self) -> list[float]:
        out, _ = self.proc.communicate("stop\n", timeout=60)
        latencies: list[float] = json.loads(out)
        return latencies


def quantile(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))] if s else float("nan")


def ws_p99(url: str, seconds: float) -> dict[str, Any]:
    out = subprocess.run(
        [
            sys.executable,
            str(REPO / "bench" / "ws_load.py"),
            "--url",
            url,
            "--clients",
            "20",
            "--rate",
            "20",
            "--duration",
            str(seconds),
            "--json",
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        check=True,
    )
    got: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return got


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--redis-url", default=os.environ.get("REDIS_URL", "redis://127.0.0.1:6379/0"))
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--ws-seconds", type=float, default=10.0)
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    tag = uuid.uuid4().hex[:8]
    env = {
        "REDIS_URL": args.redis_url,
        "REDIS_PREFIX": f"bench-probe:{tag}",
        "QUEUE_NAME": f"bench-probe-{tag}",
        "MAX_TRAININGS_PER_KEY": "10000",
        "MAX_MODELS_PER_KEY": "10000",
        "MAX_QUEUE": "10000",
    }
    registry = Path(tempfile.mkdtemp(prefix="bench-probe-"))
    secret = registry / "secret-a" / "v1"
    secret.mkdir(parents=True)
    (secret / "model.xml").write_text(DECOY.replace("decoy", "secret-a"))
    cases = {
        "60 MB XML in a zip": ("big.zip", big_xml_zip()),
        "replicate of 30,000 bodies": ("rep.xml", replicate()),
        "a million folder entries": ("dirs.tar.gz", million_folders()),
        "DOCTYPE include of another's model": ("steal.xml", doctype(str(secret / "model.xml"))),
        "flexcomp of /etc/hostname": (
            "flex.xml",
            DECOY.replace(
                "<worldbody>", '<worldbody><flexcomp name="f" type="mesh" dim="2" file="/etc/hostname"/>'
            ).encode(),
        ),
    }
    rows: list[dict[str, Any]] = []
    result: dict[str, Any] = {}
    with (
        serve(str(registry), "services.trainer", ready="/healthz", **env) as (trainer, pid),
        serve(str(REPO / "artifacts")) as (emulator, _epid),
    ):
        rss0 = rss_bytes(pid)
        poller = Poller(trainer)
        baseline = ws_p99(emulator, args.ws_seconds)
        during: dict[str, Any] = {}
        ws = threading.Thread(target=lambda: during.update(ws_p99(emulator, args.ws_seconds * 3)))
        ws.start()
        with httpx.Client(base_url=trainer, timeout=120) as c:
            for what, (name, data) in cases.items():
                t0 = time.perf_counter()
                r = c.post("/trainings", files={"file": (name, data)}, data={"name": f"p{len(rows)}"})
                rows.append(
                    {
                        "case": what,
                        "upload_bytes": len(data),
                        "status": r.status_code,
                        "error": r.json().get("error"),
                        "seconds": round(time.perf_counter() - t0, 3),
                    }
                )
            ws.join()
            checks: dict[str, list[float]] = {}
            for n in (10, 100, 1000):
                data = bodies(n)
                for i in range(args.repeats):
                    t0 = time.perf_counter()
                    r = c.post(
                        "/trainings", files={"file": (f"chain{n}.xml", data)}, data={"name": f"c{n}-{i}"}
                    )
                    assert r.status_code == 202, r.text
                    checks.setdefault(str(n), []).append(time.perf_counter() - t0)
        polls = poller.stop()
        rss1 = rss_bytes(pid)
        item = b'{"session":"s","controls":[0]},'
        huge = b'{"items":[' + item * 260_000 + b'{"session":"s","controls":[0]}]}'
        t0 = time.perf_counter()
        r = httpx.post(
            f"{emulator}/step", content=huge, headers={"content-type": "application/json"}, timeout=60
        )
        batch_s = time.perf_counter() - t0
        result = {
            "cases": rows,
            "check_seconds": {
                n: {"p50": round(statistics.median(v), 3), "p99": round(quantile(v, 0.99), 3)}
                for n, v in checks.items()
            },
            "healthz_max_ms": round(1000 * max(polls), 1),
            "healthz_p99_ms": round(1000 * quantile(polls, 0.99), 1),
            "healthz_polls": len(polls),
            "api_rss_mb_before": round(rss0 / 2**20, 1),
            "api_rss_mb_after": round(rss1 / 2**20, 1),
            "json_batch_bytes": len(huge),
            "json_batch_status": r.status_code,
            "json_batch_refused_ms": round(1000 * batch_s, 1),
            "ws_p99_ms_alone": baseline.get("p99_ms"),
            "ws_p99_ms_during_probe": during.get("p99_ms"),
        }
    conn = redis.Redis.from_url(args.redis_url)
    keys = [*conn.scan_iter(match=f"bench-probe:{tag}:*"), *conn.scan_iter(match=f"rq:*bench-probe-{tag}*")]
    if keys:
        conn.delete(*keys)
    print(f"{'case':38s} {'bytes':>11s} {'status':>6s} {'error':>18s} {'seconds':>8s}")
    for row in rows:
        print(
            f"{row['case']:38s} {row['upload_bytes']:>11,} {row['status']:>6} {row['error']!s:>18s} {row['seconds']:>8.2f}"
        )
    for n, q in result["check_seconds"].items():
        print(f"check of a valid {n:>4s}-body model: p50 {q['p50']:.2f} s, p99 {q['p99']:.2f} s")
    print(
        f"/healthz during the probe: max {result['healthz_max_ms']} ms, p99 {result['healthz_p99_ms']} ms "
        f"({result['healthz_polls']} polls)"
    )
    print(f"trainer API RSS: {result['api_rss_mb_before']} MB before, {result['api_rss_mb_after']} MB after")
    print(
        f"JSON batch of {len(huge):,} bytes to POST /step: {result['json_batch_status']} in "
        f"{result['json_batch_refused_ms']} ms"
    )
    print(
        f"websocket p99: {result['ws_p99_ms_alone']} ms alone, {result['ws_p99_ms_during_probe']} ms during the probe"
    )
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
