"""Pieces every ``posernet-*`` command shares: one-line user errors, thread count, logging."""

from __future__ import annotations

import re
import sys

__all__ = ["quiet_lightning", "quote_list_args", "report_error", "set_threads", "user_errors"]


def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions caused by the user's inputs: reported in one line, no traceback."""
    from hydra.errors import InstantiationException
    from omegaconf.errors import MissingMandatoryValue

    from ..graph import GraphValidationError
    from ..nn.model import CheckpointError

    return (FileNotFoundError, NotADirectoryError, GraphValidationError, CheckpointError,
            MissingMandatoryValue, InstantiationException)


def report_error(prog: str, exc: BaseException) -> None:
    """Print ``prog: error: message`` to stderr (for a failed instantiation: its root cause)."""
    from hydra.errors import InstantiationException

    while isinstance(exc, InstantiationException) and exc.__cause__ is not None:
        exc = exc.__cause__
    print(f"{prog}: error: {exc}", file=sys.stderr)


def quiet_lightning() -> None:
    """Avoid doubled log lines and known-harmless warnings under Hydra's logging setup.

    ``import lightning`` always adds its own console handler; when Hydra has configured the
    root logger the same messages would be printed twice, so that handler is dropped.
    """
    import logging
    import warnings

    if logging.getLogger().hasHandlers():
        lg = logging.getLogger("lightning")
        for h in list(lg.handlers):
            if type(h) is logging.StreamHandler:
                lg.removeHandler(h)
    warnings.filterwarnings("ignore", message=r".*overridden `transfer_batch_to_device`.*")
    warnings.filterwarnings("ignore", message=r".*treespec, LeafSpec.*")


def set_threads(n: int | None) -> None:
    """``torch.set_num_threads(n)`` when ``n`` is set (tiny graphs run fastest on one thread)."""
    if n:
        import torch

        torch.set_num_threads(int(n))


def quote_list_args(argv: list[str], keys: tuple[str, ...]) -> list[str]:
    """``key=a,b,c`` for ``key`` in ``keys`` would read as a Hydra sweep: pass it as one quoted
    string instead (``intrinsics=585,585,320,240`` is what users type)."""
    pattern = re.compile(rf"^({'|'.join(map(re.escape, keys))})=([^'\"\[].*,.*)$")
    return [pattern.sub(r"\1='\2'", a) for a in argv]
