"""The sync package's interface: registry, options, configs, descriptions."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from posernet.cli import CONFIG_DIR
from posernet.sync import (
    SCALE_POLICIES,
    EigSE3,
    RotationTranslation,
    available_backends,
    backend_from_config,
    get_backend,
    register_backend,
)

CONF = Path(CONFIG_DIR) / "sync"


def test_registry_lists_builtin_backends():
    names = available_backends()
    assert {"eig_se3", "rotation_translation"} <= set(names)
    assert isinstance(get_backend("eig_se3"), EigSE3)
    assert isinstance(get_backend("rotation_translation"), RotationTranslation)


def test_unknown_backend_lists_available_ones():
    with pytest.raises(ValueError, match=r"unknown sync backend 'nope'.*eig_se3"):
        get_backend("nope")
    with pytest.raises(ValueError, match="backend_from_config"):
        get_backend("none")


def test_unknown_or_bad_options_are_named():
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['max_iter'\].*max_iters"):
        get_backend("eig_se3", max_iter=3)
    with pytest.raises(ValueError, match="scale='metres'"):
        get_backend("eig_se3", scale="metres")
    with pytest.raises(ValueError, match="max_iters must be an integer"):
        get_backend("eig_se3", max_iters=2.5)
    with pytest.raises(ValueError, match="tol must be a positive number"):
        get_backend("rotation_translation", tol=-1.0)
    with pytest.raises(ValueError, match="solver="):
        get_backend("eig_se3", solver="magic")
    with pytest.raises(ValueError, match="disconnected="):
        get_backend("eig_se3", disconnected="ignore")


def test_describe_and_repr_state_the_scale_policy():
    be = get_backend("eig_se3", scale="oracle")
    d = be.describe()
    assert d["backend"] == "eig_se3" and d["scale"] == "oracle"
    assert "ORACLE" in d["scale_label"]
    assert "scale='oracle'" in repr(be)
    assert be.metric
    assert not get_backend("eig_se3", scale="unit").metric
    rt = get_backend("rotation_translation")
    assert rt.scale == "free" and "scale-free" in rt.describe()["scale_label"]
    assert set(SCALE_POLICIES) == {"unit", "given", "oracle", "free"}


@pytest.mark.parametrize("name", ["none", "eig_se3", "rotation_translation", "gtsam"])
def test_config_files_build_their_backend(name):
    cfg = OmegaConf.load(CONF / f"{name}.yaml")
    assert cfg.name == name
    if name == "gtsam" and "gtsam" not in available_backends():
        with pytest.raises(ValueError, match="pip install"):
            backend_from_config(cfg)
        return
    be = backend_from_config(cfg)
    if name == "none":
        assert be is None
    else:
        assert be.name == name
        # Every option in the file is a real option with the value given.
        for k, v in cfg.items():
            if k != "name":
                assert getattr(be.options, k) == v


def test_config_needs_a_name():
    with pytest.raises(ValueError, match="'name'"):
        backend_from_config({"scale": "unit"})


def test_register_custom_backend():
    class Mine(EigSE3):
        name = "mine"

    from posernet.sync import _REGISTRY

    register_backend("mine", Mine)
    try:
        assert "mine" in available_backends()
        assert isinstance(get_backend("mine", scale="given"), Mine)
        with pytest.raises(ValueError):
            register_backend("none", Mine)
    finally:
        _REGISTRY.pop("mine", None)
