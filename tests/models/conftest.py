"""Model tests run single-threaded: their tensors are tiny, and on a loaded 2-core machine intra-op
threading makes each small op wait on the other core (measured: 10x slower)."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
