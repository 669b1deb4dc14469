"""Suite-wide settings.

Tiny graphs are dominated by per-op overhead: one torch thread is much faster than two on a
2-core machine (no oversubscription with pytest's own process or a second job).
"""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """One torch thread for every test module, restored afterwards (a test may change it):
    tiny tensors are dominated by per-op overhead, and OpenMP threads oversubscribe the
    2-core CI box (small batched linear algebra 10-50x slower)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
