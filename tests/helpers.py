"""What several test modules share besides fixtures: a user's MJCF file, the trained-artifact record,
running a benchmark script, the emulator service behind a test client, and a small regression problem
with an emulator of its shape.

Here rather than in ``conftest.py``, which pytest imports itself and tests should not import.
"""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np
import torch
import uvicorn
from fastapi import FastAPI

from neuroanimator.core.state import LayoutGroup
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.sim.model import PhysicalModel, derive_layout
from neuroanimator.training.metrics import TrainingMetrics
from neuroanimator.training.train import TrainResult

if TYPE_CHECKING:
    from fastapi.testclient import TestClient

    from services.emulator.service import EmulatorService

ROOT = Path(__file__).resolve().parents[1]

ARM_XML = """<mujoco model="myarm">
  <option timestep="0.005"/>
  <worldbody>
    <body name="upper" pos="0 0 1">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.5"/>
      <geom name="upper_geom" type="capsule" fromto="0 0 0 0.5 0 0" size="0.05" mass="1"/>
      <body name="lower" pos="0.5 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0" damping="0.5"/>
        <geom name="lower_geom" type="capsule" fromto="0 0 0 0.5 0 0" size="0.04" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="shoulder_motor" joint="shoulder" ctrlrange="-3 3"/>
    <motor name="elbow_motor" joint="elbow" ctrlrange="-1.5 2"/>
  </actuator>
</mujoco>
"""


RAIL_XML = """<mujoco model="rail">
  <option timestep="0.01"/>
  <worldbody>
    <body name="cart">
      <joint name="slider" type="slide" axis="1 0 0" limited="true" range="-0.5 0.5" solreflimit="0.02 1"/>
      <geom name="cart_geom" type="box" size="0.1 0.05 0.05" mass="1"/>
      <body name="pole">
        <joint name="hinge" type="hinge" axis="0 1 0" damping="0.01"/>
        <geom name="pole_geom" type="capsule" fromto="0 0 0 0 0 0.6" size="0.03" mass="0.2"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="push" joint="slider" gear="10" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""
"""A cart on a rail with hard ends (a limited slider) carrying a free pole: the cart hits its limits."""


@dataclass
class Trained:
    model: PhysicalModel
    result: TrainResult
    path: Path  # the saved version folder
    root: Path  # the artifact registry


def run_bench(*args: str, timeout: float = 300.0) -> tuple[list[str], dict[str, Any]]:
    """Run ``python <script> <args> --json`` from the repository root (e.g. ``bench/control.py``):
    its output lines, and the JSON object it prints last."""
    out = subprocess.run(
        [sys.executable, *args, "--json"],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
        timeout=timeout,
    ).stdout
    lines = out.strip().splitlines()
    return lines, json.loads(lines[-1])


def app_state(client: TestClient) -> Any:
    """The ``app.state`` of the FastAPI app behind a test client."""
    app = client.app
    assert isinstance(app, FastAPI)
    return app.state


def service_of(client: TestClient) -> EmulatorService:
    """The ``EmulatorService`` behind a test client of the emulator app."""
    service: EmulatorService = app_state(client).service
    return service


# Metrics for an artifact saved without training (its manifest needs them; their values do not matter)
METRICS: TrainingMetrics = {
    "weights": 1,
    "examples": 1,
    "test_examples": 1,
    "one_step_rel_error": 0.5,
    "linear_baseline_rel_error": 0.5,
    "validation_rel_error": 0.5,
    "data_seconds": 0.0,
    "train_seconds": 0.0,
    "total_seconds": 0.0,
}


def regression_problem(seed: int = 0) -> tuple[torch.Tensor, ...]:
    """A smooth map from 5 inputs to 6 outputs (the truck emulator's core shape): training x, y and
    validation x, y (the first 80 of 400 rows)."""
    gen = torch.Generator().manual_seed(seed)
    w = torch.randn(5, 6, generator=gen)
    x = torch.randn(400, 5, generator=gen)
    y = torch.tanh(x @ w)
    return x[80:], y[80:], x[:80], y[:80]


def truck_emulator() -> StructuredEmulator:
    """The truck's emulator with one hidden layer of 16, random weights from seed 0."""
    from neuroanimator import catalog
    from neuroanimator.training import train as training

    torch.manual_seed(0)
    return training.build_emulator(catalog.get("truck"), TrainConfig(hidden=(16,)))


@contextlib.contextmanager
def uvicorn_serving(app: Any) -> Iterator[int]:
    """The app under a real uvicorn on a free port (for concurrent clients and raw sockets); the port."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = int(sock.getsockname()[1])
    sock.close()
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not srv.started:
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.01)
    try:
        yield port
    finally:
        srv.should_exit = True
        thread.join(timeout=20)


def mjcf_model(xml: str) -> tuple[mujoco.MjModel, list[LayoutGroup]]:
    """A model from dm_control's suite (``walker.xml``) or from MJCF text, and its state's layout groups."""
    from dm_control import suite

    path = Path(suite.__file__).parent / xml
    m = (
        mujoco.MjModel.from_xml_path(str(path))
        if xml.endswith(".xml")
        else mujoco.MjModel.from_xml_string(xml)
    )
    lay = derive_layout(m)
    return m, [LayoutGroup(**g.model_dump(), offset=o) for g, o in zip(lay.groups, lay.offsets, strict=True)]


def mj_state(d: mujoco.MjData, layout: list[LayoutGroup]) -> np.ndarray:
    """MuJoCo's qpos and qvel as the emulator's state (S,) of ``layout``."""
    s = np.zeros(sum(g.size for g in layout))
    for g in layout:
        src = d.qpos if g.source == "qpos" else d.qvel
        s[g.offset : g.offset + g.size] = src[g.address : g.address + g.size]
    return s
