"""Motion averaging: absolute camera poses from relative poses, behind one small interface.

>>> from posernet.sync import get_backend
>>> backend = get_backend("eig_se3", scale="unit")          # doctest: +SKIP
>>> poses = backend.solve(batch, edge_pose)                  # [N, 4, 4] world-to-camera

Backends (``available_backends()``):

* ``eig_se3`` -- spectral SE(3) synchronisation (Arrigoni, Rossi, Fusiello 2016) with IRLS,
  batched over many graphs (:mod:`posernet.sync.eig_se3`);
* ``rotation_translation`` -- robust spectral rotation averaging + geodesic refinement, then
  translation averaging (scale-free from directions by default)
  (:mod:`posernet.sync.rotation_translation`);
* ``gtsam`` -- Shonan averaging + gtsam's TranslationRecovery (optional extra
  ``posernet[gtsam]``; listed only when gtsam imports) (:mod:`posernet.sync.gtsam_backend`).
* ``learned`` -- a trained MultiReg-style message-passing network (``ckpt_path=`` a checkpoint
  of ``posernet-train model=learned_sync``) (:mod:`posernet.sync.learned`; imported on first
  use, as is ``posernet.sync.LearnedSync``).

Hydra: ``posernet/conf/sync/<name>.yaml`` holds ``_target_`` (the backend class, or a factory
returning a backend), a ``name`` label and the backend's options; the commands build it
(:func:`posernet.cli.build.backend_from_config`, through ``_target_``), so a backend written
outside this package is chosen from a config like a built-in one (``_target_:
mypkg.MyBackend`` plus its options; a :class:`SyncBackend` subclass). ``sync=none``
(``_target_: posernet.sync.no_backend``) means no motion averaging. From Python, construct a
backend class or call :func:`get_backend`.

Modules: :mod:`~posernet.sync.backend` (interface, result, input checks, scale policy),
:mod:`~posernet.sync.components` (connected components), :mod:`~posernet.sync.padding` (the
padded per-component layout), :mod:`~posernet.sync.robust` (IRLS weights),
:mod:`~posernet.sync.spectral` (spectral rotation synchronisation shared by the backends),
:mod:`~posernet.sync.translation` (robust scale-free position solvers and the edge pruning of
``rotation_translation``),
:mod:`~posernet.sync.differentiable` (a differentiable spectral synchronisation and the aligned
absolute-pose loss, for end-to-end training), :mod:`~posernet.sync.learned` (the learned
synchronisation backend, imported on first use).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .backend import SCALE_POLICIES, SyncBackend, SyncResult
from .differentiable import aligned_pose_loss, differentiable_sync
from .eig_se3 import EigSE3
from .rotation_translation import RotationTranslation

__all__ = [
    "SCALE_POLICIES",
    "EigSE3",
    "LearnedSync",
    "RotationTranslation",
    "SyncBackend",
    "SyncResult",
    "aligned_pose_loss",
    "available_backends",
    "differentiable_sync",
    "get_backend",
    "no_backend",
    "register_backend",
]

_REGISTRY: dict[str, Callable[..., SyncBackend]] = {}
_OPTIONAL: dict[str, str] = {"gtsam": "pip install 'posernet[gtsam]' (or pip install gtsam)"}


def register_backend(name: str, factory: Callable[..., SyncBackend] | None = None):
    """Register a backend class/factory under ``name``; usable as a decorator."""
    if not isinstance(name, str) or not name or name == "none":
        raise ValueError(f"invalid backend name {name!r}")

    def deco(f: Callable[..., SyncBackend]) -> Callable[..., SyncBackend]:
        _REGISTRY[name] = f
        return f

    return deco(factory) if factory is not None else deco


def _gtsam_available() -> bool:
    try:
        import gtsam  # noqa: F401
    except ImportError:
        return False
    return True


def available_backends() -> list[str]:
    """Names of the backends that can be constructed here (gtsam only when installed)."""
    names = set(_REGISTRY)
    if _gtsam_available():
        names.add("gtsam")
    return sorted(names)


def get_backend(name: str, **options: Any) -> SyncBackend:
    """Construct backend ``name`` with ``options``; ``ValueError`` listing the available
    backends for an unknown name, or the valid options for an unknown option."""
    if name == "gtsam" and "gtsam" not in _REGISTRY:
        if not _gtsam_available():
            raise ValueError(f"sync backend 'gtsam' needs the optional dependency gtsam: "
                             f"{_OPTIONAL['gtsam']}; available backends: {available_backends()}")
        from .gtsam_backend import GtsamBackend

        _REGISTRY["gtsam"] = GtsamBackend
    if name not in _REGISTRY:
        hint = " ('none' means no motion averaging: use no backend)" \
            if name == "none" else ""
        raise ValueError(f"unknown sync backend {name!r}{hint}; available backends: "
                         f"{available_backends()}")
    return _REGISTRY[name](**options)


def no_backend(**_: Any) -> None:
    """The ``sync=none`` choice (``_target_`` of ``posernet/conf/sync/none.yaml``): no motion
    averaging, so there is no backend."""
    return None


register_backend("eig_se3", EigSE3)
register_backend("rotation_translation", RotationTranslation)


def _learned(**options: Any) -> SyncBackend:
    """Factory of the ``learned`` backend: imports :mod:`posernet.sync.learned` on first use."""
    from .learned import LearnedSync

    return LearnedSync(**options)


register_backend("learned", _learned)


def __getattr__(name: str) -> Any:
    # ``posernet.sync.LearnedSync`` (the _target_ of conf/sync/learned.yaml) without importing
    # the learned backend with the package.
    if name == "LearnedSync":
        from .learned import LearnedSync

        return LearnedSync
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
