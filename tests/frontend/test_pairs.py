"""Image-pair selection (posernet.frontend.pairs): exhaustive, sequential, retrieval."""

from __future__ import annotations

import json
from itertools import combinations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.frontend.features import Features
from posernet.frontend.pairs import (
    PAIR_MODES,
    PairOptions,
    PairSelection,
    global_descriptors,
    select_pairs,
)


def _unit(rng: np.random.Generator, m: int, d: int = 128) -> np.ndarray:
    """RootSIFT-like rows: non-negative, unit L2 norm."""
    x = np.abs(rng.standard_normal((m, d)))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _feat(desc: np.ndarray, kind: str = "rootsift") -> Features:
    desc = np.asarray(desc, np.float32)
    return Features(uv=np.zeros((len(desc), 2)), desc=desc, size=(640, 480), extra={"kind": kind})


def _noisy(rng: np.random.Generator, x: np.ndarray, sigma: float = 0.02) -> np.ndarray:
    x = np.abs(x + sigma * rng.standard_normal(x.shape))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _places(n_places: int = 3, per: int = 6, k: int = 300, seed: int = 0):
    """Images of ``n_places`` places, interleaved in file order (image i shows place i % P):
    each image sees 80% of its place's descriptors plus noise; places share none."""
    rng = np.random.default_rng(seed)
    bases = [_unit(rng, k) for _ in range(n_places)]
    feats, place = [], []
    for i in range(n_places * per):
        p = i % n_places
        seen = rng.choice(k, int(0.8 * k), replace=False)
        feats.append(_feat(_noisy(rng, bases[p][seen])))
        place.append(p)
    return feats, np.array(place)


def _trajectory(n: int = 12, step: int = 60, k: int = 300, loop: bool = True, seed: int = 0):
    """A walk: image i sees descriptors [i * step, i * step + k) of one long pool, so neighbours
    overlap; with ``loop`` the last image also sees half of image 0's (it came back)."""
    rng = np.random.default_rng(seed)
    pool = _unit(rng, n * step + k)
    feats = []
    for i in range(n):
        x = pool[i * step : i * step + k].copy()
        if loop and i == n - 1:
            x[: k // 2] = pool[: k // 2]
        feats.append(_feat(_noisy(rng, x)))
    return feats


def _empty() -> Features:
    return _feat(np.zeros((0, 128), np.float32))


def _check_pairs(sel: PairSelection, n: int) -> None:
    assert sel.pairs == sorted(set(sel.pairs))
    assert all(isinstance(a, int) and isinstance(b, int) for a, b in sel.pairs)
    assert all(0 <= a < b < n for a, b in sel.pairs)


# ----------------------------------------------------------------------------- options


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("mode", "vocab_tree"),
        ("repair_links", 0),
        ("window", 0),
        ("k", 0),
        ("loop_k", -1),
        ("words", 0),
        ("sample", 0),
        ("seed", -1),
        ("k", 2.5),
        ("window", True),
    ],
)
def test_options_validation_names_the_field(field, value):
    with pytest.raises(ValueError, match=rf"^PairOptions\.{field}: {value!r} is not "):
        PairOptions(**{field: value})


def test_options_defaults_are_valid():
    opts = PairOptions()
    assert opts.mode in PAIR_MODES
    assert PairOptions(mode="sequential", loop_k=0).loop_k == 0


# ----------------------------------------------------------------------------- exhaustive


def test_exhaustive_all_pairs_in_order():
    feats = [_feat(_unit(np.random.default_rng(i), 5)) for i in range(6)]
    sel = select_pairs(feats)
    assert sel.mode == "exhaustive"
    assert sel.pairs == list(combinations(range(6), 2))
    assert len(sel.pairs) == 15
    assert (sel.components, sel.largest, sel.isolated) == (1, 6, [])


# ----------------------------------------------------------------------------- sequential


def test_sequential_window_and_clipping():
    feats = [_feat(_unit(np.random.default_rng(i), 5)) for i in range(7)]
    sel = select_pairs(feats, PairOptions(mode="sequential", window=2, loop_k=0))
    assert sel.pairs == [(i, j) for i in range(7) for j in range(i + 1, min(7, i + 3))]
    assert [p for p in sel.pairs if 6 in p] == [(4, 6), (5, 6)]  # clipped at the end
    assert sel.components == 1
    # a window past the end is every pair
    big = select_pairs(feats, PairOptions(mode="sequential", window=10, loop_k=3))
    assert big.pairs == list(combinations(range(7), 2))


def test_sequential_loop_closure():
    n = 12
    feats = _trajectory(n, loop=True)
    with_loops = select_pairs(feats, PairOptions(mode="sequential", window=2, loop_k=1))
    without = select_pairs(feats, PairOptions(mode="sequential", window=2, loop_k=0))
    assert (0, n - 1) in with_loops.pairs
    assert (0, n - 1) not in without.pairs
    assert set(without.pairs) < set(with_loops.pairs)
    # every image gets at most loop_k closures of its own, all outside its window
    extra = set(with_loops.pairs) - set(without.pairs)
    assert all(b - a > 2 for a, b in extra)
    assert len(extra) <= n
    _check_pairs(with_loops, n)


# ----------------------------------------------------------------------------- retrieval


def test_global_descriptors_find_the_place():
    feats, place = _places()
    g = global_descriptors(feats, words=32, seed=0)
    sim = g @ g.T
    np.fill_diagonal(sim, -np.inf)
    nn = np.argsort(-sim, axis=1)[:, :3]
    assert (place[nn] == place[:, None]).all()


def test_retrieval_neighbours_and_connectivity_repair():
    feats, place = _places()  # 3 places x 6 images, no descriptor shared across places
    sel = select_pairs(feats, PairOptions(mode="retrieval", k=3, words=32, repair_links=1))
    _check_pairs(sel, len(feats))
    assert sel.mode == "retrieval"
    # the 3-NN graph is 3 components (one per place); the repair joins them with exactly 2 links
    cross = [(a, b) for a, b in sel.pairs if place[a] != place[b]]
    assert len(cross) == 3 - 1
    # by default each join is 5 pairs to 5 different images (so averaging can fix the scale
    # between the two blocks), the first of them the single best link
    many = select_pairs(feats, PairOptions(mode="retrieval", k=3, words=32))
    cross5 = [(a, b) for a, b in many.pairs if place[a] != place[b]]
    assert len(cross5) == 2 * 5 and set(cross) <= set(cross5) and many.components == 1
    for pa, pb in ((0, 1), (0, 2), (1, 2)):
        join = [p for p in cross5 if {place[p[0]], place[p[1]]} == {pa, pb}]
        if join:
            side = [{x for p in join for x in p if place[x] == q} for q in (pa, pb)]
            assert len(set(join)) == 5 and max(map(len, side)) == 5
    assert (sel.components, sel.largest, sel.isolated) == (1, 18, [])
    # the rest is exactly the union of every image's 3 nearest neighbours
    g = global_descriptors(feats, words=32)
    sim = g @ g.T
    np.fill_diagonal(sim, -np.inf)
    knn = {tuple(sorted((i, int(j)))) for i in range(18) for j in np.argsort(-sim[i])[:3]}
    assert set(sel.pairs) - set(cross) == knn


def test_retrieval_repair_takes_the_most_similar_link():
    """Image 7 (place 1) also sees part of place 2: the repair joins places 1 and 2 through it."""
    rng = np.random.default_rng(1)
    bases = [_unit(rng, 300) for _ in range(3)]
    feats, place = [], np.arange(15) % 3
    for i in range(15):
        x = bases[place[i]][rng.choice(300, 240, replace=False)]
        if i == 7:
            x = np.vstack([x[:160], bases[2][:120]])
        feats.append(_feat(_noisy(rng, x)))
    sel = select_pairs(feats, PairOptions(mode="retrieval", k=3, words=32, repair_links=1))
    cross = [(a, b) for a, b in sel.pairs if place[a] != place[b]]
    assert len(cross) == 2 and sel.components == 1
    assert any(7 in pair and 2 in place[list(pair)] for pair in cross)


def test_retrieval_small_n_is_exhaustive():
    feats, _ = _places(n_places=2, per=2, k=40)
    sel = select_pairs(feats, PairOptions(mode="retrieval", k=3))
    assert sel.pairs == list(combinations(range(4), 2))
    assert sel.mode == "retrieval"


def test_retrieval_pairs_images_without_keypoints():
    feats, _ = _places(n_places=2, per=4, k=60)
    feats[0] = _empty()
    feats[4] = _empty()
    feats[7] = _feat(np.zeros((0, 128)))
    sel = select_pairs(feats, PairOptions(mode="retrieval", k=2, words=8))
    _check_pairs(sel, 8)
    assert sel.isolated == []
    assert (0, 1) in sel.pairs and (3, 4) in sel.pairs and (4, 5) in sel.pairs
    assert (6, 7) in sel.pairs
    assert sel.components == 1


def test_all_modes_with_empty_images_and_torch_descriptors():
    rng = np.random.default_rng(3)
    feats = [
        Features(
            uv=np.zeros((30, 2)),
            desc=torch.from_numpy(_unit(rng, 30, 64).astype(np.float32)),
            size=(640, 480),
            extra={"kind": "xfeat"},
        )
        for _ in range(9)
    ]
    feats[2] = Features(np.zeros((0, 2)), torch.zeros(0, 64), (640, 480), {"kind": "xfeat"})
    for mode in PAIR_MODES:
        sel = select_pairs(feats, PairOptions(mode=mode, k=2, window=1, loop_k=2, words=8))
        _check_pairs(sel, 9)
        assert sel.isolated == []


@pytest.mark.parametrize("mode", PAIR_MODES)
@pytest.mark.parametrize("n", [0, 1])
def test_fewer_than_two_images(mode, n):
    feats = [_feat(_unit(np.random.default_rng(0), 10))] * n
    sel = select_pairs(feats, PairOptions(mode=mode))
    assert sel.pairs == []
    assert sel.components == n and sel.largest == n
    assert sel.isolated == list(range(n))


def test_mixed_kinds_raise():
    rng = np.random.default_rng(0)
    feats = [_feat(_unit(rng, 10)), _feat(_unit(rng, 10), kind="sift")]
    with pytest.raises(ValueError, match=r"'rootsift'.*'sift'"):
        select_pairs(feats)


# ----------------------------------------------------------------------------- descriptors


def test_global_descriptors_unit_rows_zero_for_empty_and_deterministic():
    feats, _ = _places(n_places=2, per=3, k=50)
    feats.insert(2, _empty())
    g = global_descriptors(feats, words=16, sample=200, seed=7)
    assert g.shape == (7, 16 * 128) and g.dtype == np.float32
    norms = np.linalg.norm(g, axis=1)
    np.testing.assert_allclose(np.delete(norms, 2), 1.0, atol=1e-5)
    assert not g[2].any()
    np.testing.assert_array_equal(g, global_descriptors(feats, words=16, sample=200, seed=7))
    # fewer sampled descriptors than words: the codebook shrinks to what is there
    assert global_descriptors(feats, words=16, sample=5, seed=7).shape == (7, 5 * 128)


def test_selection_report_is_json_ready():
    feats = _trajectory(8, loop=False)
    sel = select_pairs(feats, PairOptions(mode="sequential", window=1, loop_k=1, words=8))
    d = sel.as_dict()
    assert json.loads(json.dumps(d)) == d
    assert d["n_pairs"] == len(sel.pairs) and d["mode"] == "sequential"
    text = "\n".join(sel.lines())
    assert f"sequential, {len(sel.pairs)} pairs; 1 connected component(s)" in text


@settings(max_examples=25, deadline=None)
@given(
    sizes=st.lists(st.integers(0, 12), min_size=0, max_size=14),
    mode=st.sampled_from(PAIR_MODES),
    k=st.integers(1, 5),
    window=st.integers(1, 4),
    loop_k=st.integers(0, 3),
    seed=st.integers(0, 3),
)
def test_pairs_are_unique_ordered_in_range(sizes, mode, k, window, loop_k, seed):
    rng = np.random.default_rng(seed)
    feats = [_feat(_unit(rng, m, 16)) for m in sizes]
    opts = PairOptions(mode=mode, k=k, window=window, loop_k=loop_k, words=4, seed=seed)
    sel = select_pairs(feats, opts)
    n = len(sizes)
    _check_pairs(sel, n)
    if n >= 2:
        assert sel.isolated == []  # every mode pairs every image with something
    again = select_pairs(feats, opts)
    assert again.pairs == sel.pairs


def test_auto_is_exhaustive_for_few_images_and_retrieval_beyond():
    opts = PairOptions(mode="auto", auto_max=5, k=2, words=8)
    assert opts.resolved(5) == "exhaustive" and opts.resolved(6) == "retrieval"
    rng = np.random.default_rng(0)
    few = [_feat(_unit(rng, 50)) for _ in range(5)]
    sel = select_pairs(few, opts)
    assert sel.mode == "exhaustive" and len(sel.pairs) == 10
    many = few + few[:3]
    sel = select_pairs(many, opts)
    assert sel.mode == "retrieval" and len(sel.pairs) < 28
    with pytest.raises(ValueError, match="auto_max"):
        PairOptions(auto_max=0)
