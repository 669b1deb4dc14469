"""Library objects built from command configs: the one place a ``_target_`` config meets
Hydra's ``instantiate`` for them (the library takes built objects)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..data.sevenscenes_graphs import FrontendStages

__all__ = ["backend_from_config", "check_sync_config", "frontend_stages"]


def backend_from_config(cfg: Any) -> Any:
    """The :class:`posernet.sync.SyncBackend` of a ``posernet/conf/sync/*.yaml`` mapping;
    ``None`` for ``sync=none`` (no motion averaging).

    With ``_target_`` the backend is built by Hydra's ``instantiate`` from that class or factory
    and the other keys (its options; a ``name`` key is only a label and is not passed on), so
    any importable :class:`SyncBackend` can be chosen; without it, ``name`` picks a registered
    backend (:func:`get_backend`) and ``name: none`` means no motion averaging. Bad options
    raise the backend's own ``ValueError``.
    """
    from ..sync import available_backends, get_backend
    from ..sync.backend import as_mapping

    d = dict(as_mapping(cfg))
    if "_target_" in d:
        return _instantiate_backend(d)
    if "name" not in d:
        raise ValueError(f"sync config needs a '_target_' (a backend class) or a 'name' field "
                         f"(one of {available_backends()} or 'none'); got keys {sorted(d)}")
    name = d.pop("name")
    if name in (None, "none"):
        return None
    return get_backend(str(name), **d)


def check_sync_config(sync: Mapping[str, Any]) -> None:
    """Build the backend of a ``sync`` config (plain values) before any work, so that its own
    checks across options (the scale policies it supports, gtsam installed) run then;
    :class:`~posernet.options.ConfigValueError` ``sync=<name>: <reason>``."""
    from ..options import ConfigValueError

    if sync.get("name") == "none" or (sync.get("name") is None and sync.get("_target_") is None):
        return
    try:
        backend_from_config(sync)
    except ValueError as exc:
        label = sync.get("name") or sync.get("_target_")
        first = next((ln.strip() for ln in str(exc).splitlines() if ln.strip()),
                     type(exc).__name__)
        raise ConfigValueError(f"sync={label}: {first}") from None


def _instantiate_backend(d: dict[str, Any]) -> Any:
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    from ..sync import SyncBackend

    target = d.get("_target_")
    if not isinstance(target, str) or not target:
        raise ValueError(f"sync config: _target_ must be the dotted path of a backend class or "
                         f"factory, got {target!r}")
    d.pop("name", None)
    try:
        backend = instantiate(d, _convert_="all")
    except InstantiationException as exc:
        if isinstance(exc.__cause__, ValueError):  # the backend's own message (bad option)
            raise exc.__cause__ from None
        first = next((ln.strip() for ln in str(exc).splitlines() if ln.strip()), "")
        raise ValueError(f"sync config: cannot build _target_ {target!r}: {first}") from exc
    if backend is not None and not isinstance(backend, SyncBackend):
        raise ValueError(f"sync config: _target_ {target!r} gave a {type(backend).__name__}, "
                         "not a posernet.sync.SyncBackend")
    return backend


def frontend_stages(configs: Mapping[str, Any] | None = None) -> FrontendStages:
    """The 7-Scenes graph builder's front-end stages from ``_target_`` configs of
    ``proposals``, ``matcher``, ``box_matching`` and ``relpose`` (missing ones: the shipped
    defaults, :func:`posernet.data.sevenscenes_graphs.frontend_defaults`)."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from ..data.sevenscenes_graphs import FrontendStages, frontend_defaults

    cfgs: dict[str, Any] = {}
    for k, default in frontend_defaults().items():
        c = (configs or {}).get(k)
        c = default if c is None else c
        cfgs[k] = OmegaConf.to_container(c, resolve=True) if OmegaConf.is_config(c) else dict(c)
    return FrontendStages({k: instantiate(c) for k, c in cfgs.items()}, cfgs)
