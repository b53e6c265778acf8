"""A training's progress comes from the budget that binds: when the time cap will end the training loop
long before its epochs do, the percent and the detail follow the time, not "epoch N of at most 300"."""

from __future__ import annotations

import io
import json
from collections.abc import Iterator

import pytest

from services.trainer import run


@pytest.fixture(name="channel")
def channel_fixture() -> Iterator[tuple[run.Channel, io.StringIO]]:
    out = io.StringIO()
    channel = run.Channel(out)
    channel.stage = "train"
    channel.phase = "training"
    run.CHANNEL = channel
    try:
        yield channel, out
    finally:
        run.CHANNEL = None


def test_the_time_cap_drives_the_percent_when_it_binds(channel: tuple[run.Channel, io.StringIO]) -> None:
    c, out = channel
    bar = run.Bar(total=300, desc="training")
    bar.started -= 60.0  # a minute into the loop, at epoch 3, with 60 s of the cap left: half done
    bar.n = 3
    bar.set_postfix(val="1e-3", left="60s")
    lo, hi = run.SHARES["training"]
    half = lo + (hi - lo) * run.EPOCHS_SHARE * 0.5
    assert c.percent == pytest.approx(half, abs=0.5)
    assert "60 s of the training's time cap left" in c.detail and "of at most" not in c.detail
    bar.close()  # a closing bar reports at once (between reports, at most one every REPORT_EVERY_S)
    assert json.loads(out.getvalue().splitlines()[-1])["percent"] == pytest.approx(half, abs=0.5)


def test_epochs_drive_it_when_they_bind(channel: tuple[run.Channel, io.StringIO]) -> None:
    c, _ = channel
    bar = run.Bar(total=10, desc="training")
    bar.n = 8
    bar.set_postfix(val="1e-3", left="500s")
    assert c.detail == "epoch 8 of at most 10"


def test_sampling_names_the_budget_asked_for_then_the_held_out_set(
    channel: tuple[run.Channel, io.StringIO],
) -> None:
    c, _ = channel
    c.phase = "sampling"
    c.sampling_total = 20_000 + run.TEST_EXAMPLES
    bar = run.Bar(total=20_000, desc="sampling")
    bar.update(20_000)
    assert c.detail == "sampling: 20,000 of 20,000 training examples"
    bar.update(1_000)
    assert c.detail == f"sampling the held-out set: 1,000 of {run.TEST_EXAMPLES:,} examples"
