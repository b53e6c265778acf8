"""PyTorch's intra-op thread count for the length of one training or optimisation, then restored.

The worker runs jobs one after another in one process: a job's thread count must not leak into the
next one's (nor into the caller's, for a library call)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run the ``with`` block with ``max(1, threads)`` PyTorch threads, the previous count restored."""
    previous = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        yield
    finally:
        torch.set_num_threads(previous)
