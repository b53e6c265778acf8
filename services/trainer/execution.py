"""``perform(job_id, delivery)``: one run of a training, inside the training worker's forked job process.

The training itself runs in a child process (``python -m services.trainer.run``), at the worker's low
CPU priority (``WORKER_NICE``, set by the worker and inherited), so that it can be stopped at once,
whatever it is doing: this process reads its progress (JSON lines), writes it to Redis, and keeps the
job's lease (``Watch``). When the child has made the emulator (in a staging registry), this process
exports it into the artifact registry (``models.export``) and ends the training with its result.

How a run ends:
- the child's result, exported: succeeded;
- the child said why the training cannot succeed (a model that diverges, samples too slowly, misses
  the acceptance bar, ...): failed with that reason, not retried (it would fail the same way);
- cancelled by DELETE: the child is stopped; cancelled;
- past ``JOB_TIMEOUT_S``: the child is stopped; failed, naming the phase it was in;
- its worker is shutting down: the child is stopped; back on the queue, not counted as a failure;
- the child crashed (killed, out of memory) or this process raised: back on the queue while
  ``JOB_RETRIES`` allows, else failed.
A training that ends for good removes its upload and staging folder, and gives back a name whose
first training made nothing.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import IO

import redis

from neuroanimator.contracts.trainer import TrainingPhase, TrainingResult
from services.common.job_worker import Watch, connect_job
from services.common.jobs import FINAL
from services.trainer import models
from services.trainer.settings import Settings
from services.trainer.spec import (
    ChildMessage,
    ChildSpec,
    LossPair,
    TrainedEmulator,
    TrainingProgress,
    TrainingSpec,
)
from services.trainer.store import TrainingStore

log = logging.getLogger(__name__)
ROOT = Path(__file__).resolve().parents[2]
STOP_GRACE_S = 5.0
_settings: Settings | None = None


def configure(settings: Settings) -> None:
    """Set the settings of the trainings this process (and the job processes it forks) will run."""
    global _settings
    _settings = settings


def settings() -> Settings:
    return _settings if _settings is not None else Settings()


def _read_lines(stream: IO[bytes], out: queue.Queue[ChildMessage | None]) -> None:
    for raw in stream:
        try:
            out.put(ChildMessage.model_validate_json(raw))
        except ValueError:
            log.warning(
                "unreadable line from the training", extra={"line": raw[:200].decode(errors="replace")}
            )
    out.put(None)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    """Stop the training's process group: SIGTERM, then SIGKILL after ``STOP_GRACE_S``."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(STOP_GRACE_S)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


class Progress:
    """The training's last report, with the time left estimated from the percent."""

    def __init__(self, store: TrainingStore, job_id: str, attempt: int) -> None:
        self.store, self.job_id, self.attempt = store, job_id, attempt
        self.t0 = time.monotonic()
        self.phase = "validating"
        self.percent = 0.0

    def report(
        self, phase: TrainingPhase, percent: float, detail: str, losses: Sequence[LossPair] = ()
    ) -> None:
        self.phase, self.percent = phase, percent
        elapsed = time.monotonic() - self.t0
        eta = elapsed * (100.0 - percent) / percent if percent >= 3.0 else None
        p = TrainingProgress(
            phase=phase,
            percent=percent,
            detail=detail,
            elapsed_s=round(elapsed, 1),
            eta_s=None if eta is None else round(eta, 1),
        )
        try:
            self.store.progress(self.job_id, self.attempt, p, losses)
        except redis.RedisError as exc:  # progress is best effort; the result is what counts
            log.warning("progress not recorded", extra={"job": self.job_id, "error": str(exc)})


def perform(job_id: str, delivery: int) -> str:
    """Run delivery ``n`` of a training; returns how it ended (for RQ's log)."""
    s = settings()
    store = TrainingStore(connect_job(s), s)
    worker = os.environ.get("RQ_WORKER_ID", f"pid-{os.getpid()}")
    rec, why = store.start(job_id, delivery, worker, os.getpid())
    if rec is None:
        log.info("training not run", extra={"job": job_id, "delivery": delivery, "reason": why})
        ended = store.record(job_id)
        if ended is not None and ended.status in FINAL:  # cancelled before it started
            _cleanup(s, store, job_id, TrainingSpec.model_validate_json(ended.spec), ended.owner)
        return why
    spec = TrainingSpec.model_validate_json(rec.spec)
    owner = rec.owner
    progress = Progress(store, job_id, rec.attempt)
    watch = Watch(store, job_id, delivery, worker)
    watch.start()
    deadline = time.monotonic() + s.job_timeout_s
    staging = s.staging() / job_id
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    child = ChildSpec(
        **spec.model_dump(exclude={"source"}),
        source=str(s.uploads() / spec.source),
        staging=str(staging),
        limits=asdict(s.limits()),
        time_limit_s=s.job_timeout_s,
        eval_trials=s.eval_trials,
        eval_seconds=s.eval_seconds,
    )
    log.info("training started", extra={"job": job_id, "model": spec.model, "attempt": rec.attempt})
    progress.report("validating", 0.0, "starting")
    try:
        outcome, detail = _run_child(child, staging, watch, deadline, progress)
    except Exception as exc:
        watch.stop()
        state = store.requeue_or_fail(job_id, delivery, f"{type(exc).__name__}: {exc}", count_failure=True)
        log.exception("training raised", extra={"job": job_id, "outcome": state})
        if state in ("failed", "cancelled"):
            _cleanup(s, store, job_id, spec, owner)
        raise
    watch.stop()
    if watch.superseded:  # another run of this training took over (this worker had seemed dead)
        return "superseded"
    if isinstance(detail, TrainedEmulator):
        return _export(s, store, job_id, delivery, spec, owner, detail, progress)
    if outcome == "cancelled":
        state = store.requeue_or_fail(
            job_id, delivery, f"stopped in phase {progress.phase}", count_failure=False
        )
    elif outcome == "yield":
        state = store.requeue_or_fail(job_id, delivery, f"worker {worker} shut down", count_failure=False)
    elif outcome == "timeout":
        reason = (
            f"time limit of {s.job_timeout_s:g} s (JOB_TIMEOUT_S) reached in phase {progress.phase} "
            f"({progress.percent:.0f}%); try a smaller sample budget (examples) or fewer epochs"
        )
        state = "failed" if store.end(job_id, delivery, "failed", reason) else "stale"
    elif outcome == "failed":
        state = "failed" if store.end(job_id, delivery, "failed", str(detail)) else "stale"
    else:  # crashed
        state = store.requeue_or_fail(job_id, delivery, str(detail), count_failure=True)
    if state in ("failed", "cancelled"):
        _cleanup(s, store, job_id, spec, owner)
    else:
        shutil.rmtree(staging, ignore_errors=True)
    return state


def _run_child(
    child: ChildSpec, staging: Path, watch: Watch, deadline: float, progress: Progress
) -> tuple[str, TrainedEmulator | str | None]:
    """Run the training's process until it ends or must stop: (outcome, its result or reason)."""
    log_path = staging / "training.log"
    with log_path.open("wb") as log_file:
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.trainer.run"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=log_file,
            cwd=staging,  # MuJoCo writes MUJOCO_LOG.TXT into the working directory on warnings
            env={
                **os.environ,
                "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
            },
            # its own process group (stopped with everything it started) in the worker's session: a new
            # session would be a new scheduler autogroup, where the worker's lower priority no longer
            # counts against the services (Linux shares the CPU fairly between autogroups first)
            process_group=0,
        )
    assert proc.stdin is not None and proc.stdout is not None
    proc.stdin.write(child.model_dump_json().encode())
    proc.stdin.close()
    lines: queue.Queue[ChildMessage | None] = queue.Queue()
    reader = threading.Thread(target=_read_lines, args=(proc.stdout, lines), daemon=True)
    reader.start()
    result: TrainedEmulator | None = None
    error: str | None = None
    try:
        while True:
            if watch.stop_requested or time.monotonic() > deadline:
                _stop(proc)
                if watch.cancelled:
                    return "cancelled", None
                if watch.yielding or watch.superseded:
                    return "yield", None
                return "timeout", None
            try:
                msg = lines.get(timeout=0.25)
            except queue.Empty:
                continue
            if msg is None:
                break
            if msg.result is not None:
                result = msg.result
            elif msg.error is not None:
                error = msg.error
            elif msg.phase is not None:
                progress.report(msg.phase, msg.percent, msg.detail, msg.losses)
        rc = proc.wait()
    finally:
        if proc.poll() is None:
            _stop(proc)
    if rc == 0 and result is not None:
        return "result", result
    if error is not None:
        return "failed", error
    tail = log_path.read_text(errors="replace").strip().splitlines()[-3:]
    return "crashed", f"the training process ended with status {rc}: {' / '.join(tail)[-500:]}"


def _export(
    s: Settings,
    store: TrainingStore,
    job_id: str,
    delivery: int,
    spec: TrainingSpec,
    owner: str,
    trained: TrainedEmulator,
    progress: Progress,
) -> str:
    """Export the staged emulator into the artifact registry and end the training with its result."""
    progress.report("exporting", 95.0, "exporting into the artifact registry")
    t0 = time.monotonic()
    staging = s.staging() / job_id
    try:
        version = models.export(staging, s.data_dir, spec.model, owner)
    except models.ExportError as exc:
        store.end(job_id, delivery, "failed", str(exc))
        _cleanup(s, store, job_id, spec, owner)
        return "failed"
    seconds = {**trained.phase_seconds, "exporting": round(time.monotonic() - t0, 2)}
    result = TrainingResult(
        **trained.model_dump(exclude={"version", "phase_seconds"}),
        version=version,
        artifact=f"{spec.model}/{version}",
        phase_seconds=seconds,
    )
    done = store.end(job_id, delivery, "succeeded", None, result)
    _cleanup(s, store, job_id, spec, owner, release=False)
    return "succeeded" if done else "stale"


def _cleanup(
    s: Settings,
    store: TrainingStore,
    job_id: str,
    spec: TrainingSpec,
    owner: str,
    release: bool = True,
) -> None:
    """A training that ended for good: remove its upload and staging, give back an unused name."""
    shutil.rmtree(s.staging() / job_id, ignore_errors=True)
    shutil.rmtree(s.uploads() / job_id, ignore_errors=True)
    if release:
        with contextlib.suppress(OSError, redis.RedisError):
            if not store.active(owner, spec.model, but=job_id):
                models.release(s.data_dir, spec.model, owner)
