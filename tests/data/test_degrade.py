"""Camera degradations of rendered frames: consistency of pixels, depth and ids; determinism."""

from __future__ import annotations

import json

import numpy as np
import pytest

from posernet.data.degrade import Degradation
from posernet.data.synthetic.seeding import make_rng

K = np.array([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])


def _frame() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    rgb = rng.integers(40, 200, (120, 160, 3), dtype=np.uint8)
    depth = np.full((120, 160), 2.0)
    ids = -np.ones((120, 160), np.int32)
    ids[20:30, 130:150] = 7  # an object near the corner, where distortion moves it most
    rgb[20:30, 130:150] = 255
    return rgb, depth, ids


def test_no_degradation_keeps_the_frame() -> None:
    rgb, depth, ids = _frame()
    out, d, i, rec = Degradation.none().apply(rgb, depth, ids, K, 0.0, make_rng(0, "t"))
    assert np.abs(out.astype(int) - rgb).max() <= 1  # gamma round trip only
    assert np.array_equal(d, depth) and np.array_equal(i, ids)
    assert rec["jpeg_quality"] == 100 and rec["motion_blur"] == 0


def test_lens_moves_pixels_ids_and_depth_together() -> None:
    rgb, depth, ids = _frame()
    clean = Degradation.none()
    out, _, moved, _ = clean.apply(rgb, depth, ids, K, 0.3, make_rng(0, "t"))
    ys, xs = np.nonzero(moved == 7)
    # k1 > 0 (x_d = x (1 + k1 r^2)) pushes content away from the centre
    assert xs.mean() > 140 and ys.mean() < 24.5
    bright = out[..., 0] >= 250
    overlap = (bright & (moved == 7)).sum() / max((moved == 7).sum(), 1)
    assert overlap > 0.8  # the white patch is where its ids are


def test_degradation_is_seeded_and_changes_the_image() -> None:
    rgb, depth, ids = _frame()
    deg = Degradation()
    a = deg.apply(rgb, depth, ids, K, 0.1, make_rng(3, "f"))
    b = deg.apply(rgb, depth, ids, K, 0.1, make_rng(3, "f"))
    c = deg.apply(rgb, depth, ids, K, 0.1, make_rng(4, "f"))
    assert np.array_equal(a[0], b[0]) and a[3] == b[3]
    assert not np.array_equal(a[0], c[0])
    assert np.abs(a[0].astype(int) - rgb).mean() > 2


@pytest.mark.parametrize("kwargs,message", [
    ({"k1": (0.2, 0.1)}, "k1"), ({"vignetting": (0.0, 1.0)}, "vignetting"),
    ({"defocus": (-1.0, 1.0)}, "defocus"), ({"white_balance": 1.0}, "white_balance"),
    ({"jpeg_quality": (0.0, 50.0)}, "jpeg_quality"),
])
def test_bad_ranges_are_named(kwargs, message) -> None:
    with pytest.raises(ValueError, match=message):
        Degradation(**kwargs)


def test_render_records_the_degradation(tmp_path) -> None:
    from posernet.data.render import render_sevenscenes

    folder = render_sevenscenes(tmp_path, "chess", seed=1, train_sequences=1,
                                test_sequences=0, frames_per_sequence=2, width=160,
                                height=120, focal=146.25, progress=False,
                                degrade=Degradation())
    info = json.loads((folder / "render.json").read_text())
    deg = info["degradation"]
    assert 0.0 <= deg["k1"] <= 0.2 and len(deg["frames"]) == 2
    assert info["intrinsics"] == [146.25, 146.25, 80.0, 60.0]  # the pinhole's: uncorrected
    clean = render_sevenscenes(tmp_path, "chess", seed=1, train_sequences=1, test_sequences=0,
                               frames_per_sequence=2, width=160, height=120, focal=146.25,
                               progress=False, name="clean")
    assert "degradation" not in json.loads((clean / "render.json").read_text())
    a = (folder / "seq-01" / "frame-000001.color.png").read_bytes()
    assert a != (clean / "seq-01" / "frame-000001.color.png").read_bytes()
