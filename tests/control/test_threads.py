"""A job's PyTorch thread count holds for the job alone: restored after it, even when it raised."""

from __future__ import annotations

import pytest
import torch

from neuroanimator.control.threads import torch_threads


def test_the_thread_count_is_set_for_the_block_and_restored_after_an_error() -> None:
    before = torch.get_num_threads()
    wanted = 1 if before != 1 else 2
    with pytest.raises(ValueError, match="a job that failed"), torch_threads(wanted):
        assert torch.get_num_threads() == wanted
        raise ValueError("a job that failed")
    assert torch.get_num_threads() == before


def test_a_count_below_one_runs_on_one_thread() -> None:
    with torch_threads(0):
        assert torch.get_num_threads() == 1
