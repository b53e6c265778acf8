"""The stack's ports: ``free_port`` picks ports that an outgoing connection cannot be given before a
service binds them, and a service that finds its port taken all the same ends the start with a
``PortTakenError`` (so a caller on free ports can pick new ones), not a bare ``StackError``."""

from __future__ import annotations

import random
import socket
import subprocess
from pathlib import Path

import pytest

from services.stack import PortTakenError, Service, Stack, StackConfig, _ephemeral_range, free_port


def test_free_ports_are_bindable_distinct_and_below_the_ephemeral_range() -> None:
    low, _ = _ephemeral_range()
    ports = [free_port(rng=random.Random(0)) for _ in range(40)]  # the same draws: must still differ
    assert len(set(ports)) == len(ports)
    if low > 20000:
        assert max(ports) < low
    for port in ports:
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))


def test_a_port_taken_after_the_check_is_reported_as_taken(tmp_path: Path, redis_url: str) -> None:
    holder = socket.socket()  # bound, not listening: the stack's own check sees the port free
    holder.bind(("127.0.0.1", free_port()))
    taken = holder.getsockname()[1]
    stack = Stack(
        StackConfig(
            emulator_port=taken,
            web_port=free_port(),
            controller=False,
            trainer=False,
            train_missing=False,
            log_dir=tmp_path,
            redis_url=redis_url,
            namespace="test-ports",
            ready_timeout_s=60,
        )
    )
    launched: list[subprocess.Popen[bytes]] = []
    launch = stack._launch

    def remember(svc: Service) -> None:
        launch(svc)
        assert svc.proc is not None
        launched.append(svc.proc)

    stack._launch = remember  # type: ignore[method-assign]
    try:
        with pytest.raises(PortTakenError, match="emulator exited"):
            stack.start()
    finally:
        holder.close()
    assert [p.poll() is not None for p in launched] == [True, True]  # the web server was stopped too
