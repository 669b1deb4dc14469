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

Hydra: ``posernet/conf/sync/<name>.yaml`` holds ``name`` plus the backend's options;
:func:`backend_from_config` turns such a mapping into a backend (``None`` for ``name: none``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .base import SCALE_POLICIES, SyncBackend, SyncResult, as_mapping
from .eig_se3 import EigSE3
from .rotation_translation import RotationTranslation

__all__ = [
    "SCALE_POLICIES",
    "EigSE3",
    "RotationTranslation",
    "SyncBackend",
    "SyncResult",
    "available_backends",
    "backend_from_config",
    "get_backend",
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
        hint = " ('none' means no motion averaging: use backend_from_config)" \
            if name == "none" else ""
        raise ValueError(f"unknown sync backend {name!r}{hint}; available backends: "
                         f"{available_backends()}")
    return _REGISTRY[name](**options)


def backend_from_config(cfg: Any) -> SyncBackend | None:
    """Backend from a ``posernet/conf/sync/*.yaml`` mapping (``name`` + options); ``None`` for
    ``name: none`` (no motion averaging)."""
    d = dict(as_mapping(cfg))
    if "name" not in d:
        raise ValueError(f"sync config needs a 'name' field (one of {available_backends()} or "
                         f"'none'); got keys {sorted(d)}")
    name = d.pop("name")
    if name in (None, "none"):
        return None
    return get_backend(str(name), **d)


register_backend("eig_se3", EigSE3)
register_backend("rotation_translation", RotationTranslation)
