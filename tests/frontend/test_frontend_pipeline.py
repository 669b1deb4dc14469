"""The image front end: worker threads change nothing, the cache resumes what a run did."""

from __future__ import annotations

import logging
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from posernet.data.render import render_intrinsics, render_sevenscenes
from posernet.frontend.boxmatch import BoxMatchRules
from posernet.frontend.features import SiftMatcher
from posernet.frontend.images import records_for_images
from posernet.frontend.pipeline import ImageFrontend
from posernet.frontend.proposals import SelectiveSearch
from posernet.frontend.results import ImageFeatures
from posernet.frontend.verify import VerifyRules

N = 6
PAIRS = [(a, b) for a in range(N) for b in range(a + 1, N)]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("render")
    seq = render_sevenscenes(root, "chess", seed=4, train_sequences=0, test_sequences=1,
                             frames_per_sequence=N, width=320, height=240, focal=292.5,
                             progress=False)
    assert [f"{v:g}" for v in render_intrinsics(seq)] == ["292.5", "292.5", "160", "120"]
    return next(p for p in seq.rglob("seq-*") if p.is_dir())


def _frontend(folder: Path, **kw) -> ImageFrontend:
    intr = "292.5,292.5,160,120"
    records = records_for_images(folder, intr, "*.color.png", "none")
    kw.setdefault("verify", VerifyRules())
    return ImageFrontend(records, SelectiveSearch(resize=160), SiftMatcher(),
                         edge_rule="verified", **kw)


def _outcome(fe: ImageFrontend) -> list[tuple]:
    out = []
    for a, b in PAIRS:
        p = fe.pair(a, b)
        kp = None if p.kp is None else np.round(np.concatenate([p.kp[0].ravel(),
                                                                p.kp[1].ravel()]), 9)
        inl = None if p.inliers is None else p.inliers.tolist()
        out.append((a, b, p.status, p.reason, p.box_a.tolist(), p.box_b.tolist(),
                    None if kp is None else kp.tolist(), inl))
    return out


def _counts(fe: ImageFrontend) -> tuple:
    s = fe.summary
    return dict(s.pairs), dict(s.rejected), s.rotation_only


@pytest.fixture(scope="module")
def reference(scene):
    fe = _frontend(scene)
    fe.evaluate_pairs(PAIRS, progress=False)
    assert fe.summary.pairs["edge"] >= 5  # the scene is usable
    return _outcome(fe), _counts(fe)


def test_worker_threads_change_nothing(scene, reference) -> None:
    fe = _frontend(scene, workers=2)
    fe.evaluate_pairs(PAIRS, progress=False)
    assert _outcome(fe) == reference[0]
    assert _counts(fe) == reference[1]


class _Interrupt:
    """A matcher that stops the run (like Ctrl-C) after ``n`` matches."""

    def __init__(self, n: int) -> None:
        self.inner, self.left = SiftMatcher(), n
        self.name, self.kind = "sift", "rootsift"

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def extract(self, image):
        return self.inner.extract(image)

    def match(self, a, b):
        if self.left == 0:
            raise KeyboardInterrupt
        self.left -= 1
        return self.inner.match(a, b)


def test_interrupted_run_resumes_from_the_cache(scene, reference, tmp_path) -> None:
    cache = tmp_path / "cache"
    fe = _frontend(scene, cache=cache)
    fe.matcher = _Interrupt(5)  # same options (the cache key is taken at construction)
    with pytest.raises(KeyboardInterrupt):
        fe.evaluate_pairs(PAIRS, progress=False)
    again = _frontend(scene, cache=cache)
    again.evaluate_pairs(PAIRS, progress=False)
    assert again.summary.reused == {"images": N, "pairs": 5}
    assert _outcome(again) == reference[0] and _counts(again) == reference[1]
    # a third run reuses everything, matches included (for pictures)
    third = _frontend(scene, cache=cache)
    third.evaluate_pairs(PAIRS, progress=False)
    assert third.summary.reused == {"images": N, "pairs": len(PAIRS)}
    assert _outcome(third) == reference[0] and _counts(third) == reference[1]
    assert set(third.matches) == set(PAIRS)
    # the keypoint colours (for the exports) come back from the cache too
    for i in range(N):
        got, made = third.features(i), fe.features(i)
        assert got.colours is not None and got.colours.shape == (len(got), 3)
        np.testing.assert_array_equal(got.colours, made.colours)
    assert "reused from the cache: 6 images, 15 pairs" in "\n".join(third.summary.lines())


def test_cache_follows_options_and_image_content(scene, tmp_path, caplog) -> None:
    cache = tmp_path / "cache"
    _frontend(scene, cache=cache).evaluate_pairs(PAIRS, progress=False)
    first = {p.name for p in cache.iterdir()}
    # another verification option: a new cache folder; the stale one is removed
    fe = _frontend(scene, cache=cache, verify=VerifyRules(min_inliers=20))
    fe.evaluate_pairs(PAIRS, progress=False)
    assert not fe.summary.reused
    assert len({p.name for p in cache.iterdir()} - first) == 1 and len(list(cache.iterdir())) == 1
    # an image whose content changed is recomputed, with every pair it is in
    copy = tmp_path / "seq"
    shutil.copytree(scene, copy)
    base = _frontend(copy, cache=tmp_path / "c2")
    base.evaluate_pairs(PAIRS, progress=False)
    img = sorted(copy.glob("*.color.png"))[2]
    cv2.imwrite(str(img), cv2.flip(cv2.imread(str(img)), 1))
    fe = _frontend(copy, cache=tmp_path / "c2")
    fe.evaluate_pairs(PAIRS, progress=False)
    assert fe.summary.reused == {"images": N - 1, "pairs": len(PAIRS) - (N - 1)}
    # a damaged entry is a miss: recomputed, with one warning naming the file
    entry = sorted((fe.cache.folder / "pairs").glob("*.npz"))[0]
    entry.write_bytes(entry.read_bytes()[:40])
    with caplog.at_level(logging.WARNING, logger="posernet.frontend"):
        fe = _frontend(copy, cache=tmp_path / "c2")
        fe.evaluate_pairs(PAIRS, progress=False)
    assert fe.summary.reused["pairs"] == len(PAIRS) - 1
    assert any(entry.name in r.getMessage() for r in caplog.records)


def test_cache_that_cannot_be_written_is_turned_off(scene, tmp_path, caplog) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with caplog.at_level(logging.WARNING, logger="posernet.frontend"):
        fe = _frontend(scene, cache=blocker / "cache")
        fe.evaluate_pairs(PAIRS[:3], progress=False)
    assert fe.cache is not None and not fe.cache.enabled
    assert any("cache" in r.getMessage() for r in caplog.records)
    assert fe.summary.pairs  # the run went on without it


def test_working_resolution_maps_keypoints_back(scene, tmp_path) -> None:
    img = cv2.imread(str(sorted(scene.glob("*.color.png"))[0]))
    big = tmp_path / "big"
    big.mkdir()
    cv2.imwrite(str(big / "frame.color.png"),
                cv2.resize(img, (1280, 960), interpolation=cv2.INTER_CUBIC))

    def keypoints(max_image_size: int | None) -> ImageFeatures:
        records = records_for_images(big, "1170,1170,640,480", "*.color.png", "none")
        return ImageFrontend(records, None, SiftMatcher(), edge_rule="verified",
                             max_image_size=max_image_size).extract(progress=False)[0]

    small = SiftMatcher().extract(img)  # what the 1280x960 copy shrunk to 320x240 looks like
    mapped = keypoints(320)
    assert mapped.size == (1280, 960)
    assert len(mapped.keypoints) == pytest.approx(len(small), rel=0.2)
    # keypoints sit where the small image's do, in full-resolution pixels
    d = np.linalg.norm(mapped.keypoints[:, None] - ((small.uv + 0.5) * 4 - 0.5)[None], axis=2)
    assert np.median(d.min(1)) < 2.0
    full = keypoints(None)
    assert len(full.keypoints) > len(mapped.keypoints)  # full size: more (finer) keypoints
    with pytest.raises(ValueError, match="max_image_size"):
        _frontend(scene, max_image_size=8)


def test_without_boxes_a_rejected_pair_names_the_verification_rule(scene) -> None:
    """No stage uses boxes: a pair that fails verification says which rule, not "matched
    boxes"."""
    records = records_for_images(scene, "292.5,292.5,160,120", "*.color.png", "none")
    strict = VerifyRules(min_inlier_ratio=0.999)  # any outlier at all rejects the pair
    fe = ImageFrontend(records, None, SiftMatcher(), verify=strict, edge_rule="verified")
    fe.evaluate_pairs(PAIRS, progress=False)
    reasons = {fe.pair(a, b).reason for a, b in PAIRS if fe.pair(a, b).status != "edge"}
    assert "low_inlier_ratio" in reasons and "too_few_matched_boxes" not in reasons, reasons


def test_stages_hand_on_typed_snapshots(scene) -> None:
    """extract -> select_pairs -> match -> view_graph: typed results that stay as they were
    when the front end later forgets its pairs, and the graph of the front end's own
    assembly."""
    import dataclasses

    from posernet.frontend.results import FrontendResult, ImageFeatures, MatchResult

    fe = _frontend(scene)
    feats = fe.extract(progress=False)
    assert len(feats) == N and all(isinstance(f, ImageFeatures) for f in feats)
    assert all(f.keypoints.shape[1] == 2 and f.size == (320, 240) for f in feats)
    sel = fe.select_pairs()
    assert sel.pairs == PAIRS
    matches = fe.match(sel.pairs, progress=False)
    assert isinstance(matches, MatchResult) and list(matches.pairs) == PAIRS
    view = fe.view_graph(sel, matches, meta={"name": "seq"})
    assert isinstance(view, FrontendResult)
    graph, _ = fe.graph(range(N), pairs=sel.pairs)
    assert view.graph.edge_index.tolist() == graph.edge_index.tolist()
    with pytest.raises(dataclasses.FrozenInstanceError):
        view.matches.pairs[(0, 1)].geometry.status = "edge"  # type: ignore[misc]
    before = [(p.geometry.status, p.geometry.num_inliers) for p in matches.pairs.values()]
    counts = dict(view.summary.pairs)
    fe.forget_pairs()
    assert not fe.summary.pairs and dict(view.summary.pairs) == counts
    assert [(p.geometry.status, p.geometry.num_inliers)
            for p in matches.pairs.values()] == before
    for p in matches.pairs.values():  # the drawn matches are the verified ones
        v, inl = p.verified(), p.geometry.inliers
        assert v is not None and len(v) == (len(p.matches) if inl is None else len(inl))


def test_boxes_leave_the_verified_keypoint_geometry_alone(scene, reference) -> None:
    """With every verified pair an edge, a pair's KP pose, status and tracks come from all its
    keypoint matches, as without boxes: the paper's fit on in-box keypoints alone can be a
    small subset (on a few far-apart photos, poses 10-50 deg off that the tracks then kept)."""
    records = records_for_images(scene, "292.5,292.5,160,120", "*.color.png", "none")
    plain = ImageFrontend(records, None, SiftMatcher(), verify=VerifyRules(),
                          edge_rule="verified")
    plain.evaluate_pairs(PAIRS, progress=False)
    boxed = [(a, b, st, why, kp, inl) for a, b, st, why, _, _, kp, inl in reference[0]]
    bare = [(a, b, st, why, kp, inl) for a, b, st, why, _, _, kp, inl in _outcome(plain)]
    assert boxed == bare
    # the comparison covers edges that share enough matched boxes for the paper's rule
    enough = BoxMatchRules().min_boxes
    assert any(st == "edge" and len(ba) >= enough for _, _, st, _, ba, *_ in reference[0])


def test_released_descriptors_keep_evaluated_pairs_and_refuse_new_matching(scene) -> None:
    fe = _frontend(scene)
    done = PAIRS[:3]
    fe.evaluate_pairs(done, progress=False)
    before = [fe.pair(a, b) for a, b in done]
    fe.release_descriptors()
    assert all(fe.image(i).features.desc is None for i in range(N))
    assert [fe.pair(a, b) for a, b in done] == before  # evaluated pairs stay
    assert len(fe.features(0).keypoints) == len(fe.image(0).features.uv) > 0  # keypoints stay
    a, b = PAIRS[-1]
    name = f"pair ({fe.records[a].key}, {fe.records[b].key})"
    with pytest.raises(RuntimeError, match=re.escape(name) + ".*released"):
        fe.pair(a, b)
    with pytest.raises(RuntimeError, match="selecting pairs.*released"):
        fe.select_pairs()


def test_a_front_end_with_other_intrinsics_verifies_its_pairs_again(scene, tmp_path) -> None:
    """``with_intrinsics``: the same images, options and cache folder with new intrinsics;
    the images' features carry over, the pairs are verified again under the new K."""
    records = records_for_images(scene, "300,300,160,120", "*.color.png", "none")
    for r in records:
        r.intrinsics_source = "prior"  # guessed: the matches are remembered for a second pass
    calls = []

    class Counting(SiftMatcher):
        def match(self, a, b):
            calls.append(1)
            return super().match(a, b)

    fe = ImageFrontend(records, None, Counting(), edge_rule="verified", seed=3,
                       cache=tmp_path / "cache")
    fe.evaluate_pairs([(0, 1)], progress=False)
    assert len(calls) == 1
    K = np.stack([r.K for r in fe.records])
    K[:, :2, :2] *= 1.5
    other = fe.with_intrinsics(K)
    assert [r.key for r in other.records] == [r.key for r in fe.records]
    np.testing.assert_allclose(other.records[0].K[0, 0], 450.0)
    assert fe.records[0].K[0, 0] == 300.0  # the first front end keeps its own
    assert other.cache is not None and other.cache.root == fe.cache.root
    assert other.seed == 3 and other.image(0).features is fe.image(0).features
    a, b = 0, 1
    assert fe._pair_key(a, b) != other._pair_key(a, b)  # its pairs are not the cached ones
    other.evaluate_pairs([(0, 1)], progress=False)  # verified again, not matched again
    assert len(calls) == 1 and other.summary.pairs.get("edge", 0) == fe.summary.pairs["edge"]
    with pytest.raises(ValueError, match=r"with_intrinsics: K must be finite"):
        fe.with_intrinsics(K[:1])
    K[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"with_intrinsics: K must be finite"):
        fe.with_intrinsics(K)
