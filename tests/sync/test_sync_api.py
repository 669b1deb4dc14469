"""The sync package's interface: registry, options, configs, descriptions."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from posernet.cli import CONFIG_DIR
from posernet.cli.build import backend_from_config
from posernet.options import ConfigValueError
from posernet.sync import (
    SCALE_POLICIES,
    EigSE3,
    RotationTranslation,
    SyncBackend,
    SyncResult,
    available_backends,
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
    with pytest.raises(ValueError, match="means no motion averaging"):
        get_backend("none")


def test_unknown_or_bad_options_are_named():
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['max_iter'\].*max_iters"):
        get_backend("eig_se3", max_iter=3)
    # each option's rule is declared on its field (posernet.options)
    with pytest.raises(ConfigValueError, match=r"^EigSE3Options.scale: 'metres' is not one of "
                                               r"unit, given, oracle, free$"):
        get_backend("eig_se3", scale="metres")
    with pytest.raises(ValueError, match=r"max_iters: 2.5 is not an integer >= 1"):
        get_backend("eig_se3", max_iters=2.5)
    with pytest.raises(ValueError, match=r"tol: -1.0 is not a number > 0"):
        get_backend("rotation_translation", tol=-1.0)
    with pytest.raises(ValueError, match="solver: 'magic' is not one of auto, dense, krylov"):
        get_backend("eig_se3", solver="magic")
    with pytest.raises(ValueError, match="disconnected: 'ignore' is not one of"):
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
            if k not in ("name", "_target_"):
                assert getattr(be.options, k) == v


def test_config_needs_a_name():
    with pytest.raises(ValueError, match="'name'"):
        backend_from_config({"scale": "unit"})


def test_every_config_file_has_a_target():
    for path in sorted(CONF.glob("*.yaml")):
        assert OmegaConf.load(path).get("_target_"), path.name


def test_old_name_style_configs_still_work():
    be = backend_from_config({"name": "eig_se3", "scale": "given", "max_iters": 7})
    assert isinstance(be, EigSE3) and be.options.max_iters == 7 and be.scale == "given"
    assert backend_from_config({"name": "none"}) is None
    assert backend_from_config({"_target_": "posernet.sync.no_backend", "name": "none"}) is None


def test_target_configs_report_bad_options_and_targets():
    with pytest.raises(ValueError, match="scale='free' is not supported"):
        backend_from_config({"_target_": "posernet.sync.EigSE3", "name": "eig_se3",
                             "scale": "free"})
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['max_iter'\]"):
        backend_from_config({"_target_": "posernet.sync.EigSE3", "max_iter": 3})
    with pytest.raises(ValueError, match="cannot build _target_ 'posernet.sync.Nope'"):
        backend_from_config({"_target_": "posernet.sync.Nope"})
    with pytest.raises(ValueError, match="not a posernet.sync.SyncBackend"):
        backend_from_config({"_target_": "builtins.dict", "a": 1})


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


class _OutsideBackend(SyncBackend):
    """A backend written outside the package: every camera at the identity; it counts its
    calls (enough to see that a config selected it and the pipeline used it)."""

    name = "outside"
    calls = 0

    def _solve(self, struct, edge_pose, edge_pose_gt, comps):
        type(self).calls += 1
        n = struct["num_nodes"]
        return SyncResult(
            poses=torch.eye(4, dtype=edge_pose.dtype).expand(n, 4, 4).clone(),
            component=comps.comp, solved=torch.ones(n, dtype=torch.bool),
            edge_weight=torch.ones(edge_pose.shape[0], dtype=edge_pose.dtype),
            iterations=torch.ones(struct["num_graphs"], dtype=torch.long),
            converged=torch.ones(struct["num_graphs"], dtype=torch.bool),
            scale=self.scale, metric=self.metric, backend=self.name)


def test_backend_defined_outside_the_package_is_chosen_by_target():
    from posernet.refinement import refine_graphs
    from posernet.testing import random_view_graph

    cfg = OmegaConf.create({"_target_": f"{__name__}._OutsideBackend", "name": "outside",
                            "scale": "given"})
    be = backend_from_config(cfg)
    assert isinstance(be, _OutsideBackend) and be.scale == "given"
    gen = torch.Generator().manual_seed(0)
    gs = [random_view_graph(num_nodes=5, extra_edges=2, generator=gen, name=f"o{i}")
          for i in range(3)]
    before = _OutsideBackend.calls
    res = refine_graphs(None, gs, backend=be, batch_size=2, progress=False)
    assert _OutsideBackend.calls - before == 2  # two batches, the initial stage only
    assert res.backend["backend"] == "outside" and res.backend["scale"] == "given"
    for g, poses in zip(gs, res.absolute["initial"], strict=True):
        assert torch.equal(poses, torch.eye(4, dtype=poses.dtype).expand(g.num_nodes, 4, 4))
