"""Plots: rolling mean and PNG output."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from posernet.plots import plot_cameras, plot_sorted_errors, rolling_mean
from posernet.testing import random_absolute_poses


def test_rolling_mean_matches_direct_window():
    x = np.arange(10, dtype=float) ** 2
    r = rolling_mean(x, 3)
    assert r.shape == x.shape
    assert r[5] == pytest.approx((16 + 25 + 36) / 3)
    assert r[0] == pytest.approx((0 + 1 + 4) / 3)  # window shifted inside at the ends
    assert np.allclose(rolling_mean(x, 1), x)
    assert np.allclose(rolling_mean(x, 100), np.full(10, x.mean()))


def test_sorted_error_plot_writes_png(tmp_path):
    rng = np.random.default_rng(0)
    refined = rng.uniform(0, 20, 200)
    path = plot_sorted_errors(
        tmp_path / "errors.png",
        {"rotation": {"initial": refined * 3, "refined": refined},
         "translation direction": {"initial": refined + 40, "refined": refined + 5}},
        window=50,
    )
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="no curve 'refined'"):
        plot_sorted_errors(tmp_path / "x.png", {"rot": {"initial": refined}})
    assert not (tmp_path / "x.png").exists()


def test_camera_plot_writes_png(tmp_path):
    T = random_absolute_poses(8, torch.Generator().manual_seed(0))
    path = plot_cameras(tmp_path / "cams.png", {"ground truth": T, "refined": T}, title="g0")
    assert path.stat().st_size > 1000


def test_camera_plot_links_estimates_to_ground_truth_and_names_stages(tmp_path, monkeypatch):

    import posernet.plots as plots

    seen = {}

    def keep(fig, path):  # look at the figure instead of only the file
        ax = fig.axes[0]
        seen["labels"] = [t.get_text() for t in ax.get_legend().get_texts()]
        seen["lines"] = len(ax.lines)
        seen["xlabel"] = ax.get_xlabel()
        return original(fig, path)

    original = plots._save
    monkeypatch.setattr(plots, "_save", keep)
    T = random_absolute_poses(6, torch.Generator().manual_seed(1))
    plot_cameras(tmp_path / "a.png", {"ground truth": T, "initial+ba": T}, links="initial+ba")
    assert seen["labels"] == ["ground truth", "motion averaging + bundle adjustment",
                              "estimate to ground truth"]
    assert seen["lines"] == 6 and seen["xlabel"] == "x (m)"
    plot_cameras(tmp_path / "b.png", {"initial+ba": T}, units="scale-free")
    assert seen["lines"] == 0 and seen["xlabel"] == "x (scale-free)"
