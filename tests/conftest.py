"""Suite-wide settings.

Tiny graphs are dominated by per-op overhead: one torch thread is much faster than two on a
2-core machine (no oversubscription with pytest's own process or a second job).
"""

from __future__ import annotations

import torch

torch.set_num_threads(1)
