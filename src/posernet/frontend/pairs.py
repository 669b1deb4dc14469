"""Image-pair selection for structure from motion: which of the N(N-1)/2 pairs of N images to match.

Three modes (:class:`PairOptions` ``mode``), and ``auto``: exhaustive up to ``auto_max``
images, retrieval beyond:

* ``exhaustive``: every pair. Right for tens of images; quadratic beyond.
* ``sequential``: ordered captures (video, walk-throughs): each image with the next ``window``
  images in file order, plus ``loop_k`` loop closures per image: its most similar images by
  global descriptor that lie outside its window (revisits the window alone would never pair).
* ``retrieval``: unordered collections: the union of every image's ``k`` nearest images by
  cosine similarity of global descriptors, then a cheap connectivity repair that links the
  resulting components through their most similar cross-component pairs.

Global descriptor (:func:`global_descriptors`): VLAD (Jegou et al. 2010) over each image's own
local descriptors, with intra-normalisation (Arandjelovic & Zisserman 2013), signed square root
and L2 normalisation. The codebook is learned per run by k-means on a sample of the run's
descriptors: no pretrained retrieval network or vocabulary can be downloaded at run time, and
RootSIFT VLAD is a standard, cheap global descriptor that needs nothing but the descriptors the
matcher already extracted (it works the same on 64-D XFeat descriptors).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..options import check_options, option
from .features import Features, descriptor_array

__all__ = ["PAIR_MODES", "PairOptions", "PairSelection", "global_descriptors", "select_pairs"]

log = logging.getLogger("posernet.frontend")

PAIR_MODES = ("auto", "exhaustive", "sequential", "retrieval")

_ROWS = 1024  # query images per similarity block: memory stays at _ROWS x N floats
_CHUNK = 1 << 16  # local descriptors per assignment batch
_LLOYD_ITERS = 15


@dataclass
class PairOptions:
    """How :func:`select_pairs` chooses pairs.

    Attributes:
        mode: ``"exhaustive"``, ``"sequential"``, ``"retrieval"`` or ``"auto"`` (exhaustive
            for at most ``auto_max`` images, else retrieval).
        window: sequential: each image is paired with the next ``window`` images (file order).
        loop_k: sequential: plus this many loop-closure neighbours per image (0 = off).
        k: retrieval: nearest images per image by global descriptor.
        words: retrieval / loop closures: visual words of the per-run VLAD codebook.
        sample: descriptors sampled (over all images) to learn the codebook.
        seed: seed of the sampling and of the k-means++ seeding.
        auto_max: the largest image count ``auto`` matches exhaustively.
        repair_links: retrieval: pairs added between two components the k nearest
            neighbours left apart (several, so that averaging can fix their relative scale).
    """

    mode: str = option("exhaustive", choices=PAIR_MODES,
                       help="which pairs are matched; auto: exhaustive up to auto_max images, "
                            "else retrieval")
    window: int = option(5, ge=1, help="sequential: the next images in file order")
    loop_k: int = option(3, ge=0, help="sequential: loop-closure candidates per image")
    k: int = option(20, ge=1, help="retrieval: nearest images per image")
    words: int = option(64, ge=1, help="visual words of the per-run VLAD codebook")
    sample: int = option(20000, ge=1, help="descriptors sampled to learn it")
    seed: int = option(0, ge=0, help="seed of the sampling and of the k-means++ seeding")
    auto_max: int = option(40, ge=1, help="the largest image count auto matches exhaustively")
    repair_links: int = option(5, ge=1, help="retrieval: pairs added between two components "
                               "the k nearest neighbours left apart")

    def resolved(self, n: int) -> str:
        """The mode used for ``n`` images (``auto`` resolved)."""
        if self.mode != "auto":
            return self.mode
        return "exhaustive" if n <= self.auto_max else "retrieval"

    def __post_init__(self) -> None:
        check_options(self)
        for f in fields(self):  # numpy integers as plain ones (cache keys, JSON)
            if f.type == "int":
                setattr(self, f.name, int(getattr(self, f.name)))


@dataclass
class PairSelection:
    """The chosen pairs and the connectivity of the graph they form over all n images.

    Attributes:
        pairs: sorted, unique ``(a, b)`` image indices with ``a < b``.
        mode: the requested mode (also when retrieval fell back to all pairs).
        components: connected components of the pair graph over all n images.
        largest: images in the largest component.
        isolated: images in no pair.
        seconds: time spent selecting (global descriptors and search).
    """

    pairs: list[tuple[int, int]]
    mode: str
    components: int
    largest: int
    isolated: list[int]
    seconds: float

    def lines(self) -> list[str]:
        """Human-readable summary (one line: mode, pairs, connectivity, time)."""
        iso = (f", isolated images {', '.join(map(str, self.isolated))}" if self.isolated
               else "")
        return [f"pair selection: {self.mode}, {len(self.pairs)} pairs; {self.components} "
                f"connected component(s), the largest {self.largest} images{iso} "
                f"({self.seconds:.2f} s)"]

    def as_dict(self) -> dict:
        """JSON-ready dictionary (plain ints, floats and lists)."""
        return {
            "mode": self.mode,
            "n_pairs": len(self.pairs),
            "pairs": [[int(a), int(b)] for a, b in self.pairs],
            "components": int(self.components),
            "largest": int(self.largest),
            "isolated": [int(i) for i in self.isolated],
            "seconds": float(self.seconds),
        }


# --------------------------------------------------------------------------- descriptors


def _as_numpy(desc: Any) -> np.ndarray:
    """(K, D) float32 numpy descriptors from a numpy array or a (possibly GPU) torch tensor."""
    if desc is None:
        return np.zeros((0, 0), np.float32)
    if isinstance(desc, np.ndarray):
        arr = desc.astype(np.float32, copy=False)
    else:
        arr = torch.as_tensor(desc).detach().float().cpu().numpy()
    if arr.ndim == 2:
        return arr
    if arr.size == 0:
        return arr.reshape(0, 0)
    raise ValueError(f"descriptors must be a (K, D) array, got shape {tuple(arr.shape)}")


def _check_kinds(features: Sequence[Features]) -> None:
    if not features:
        return
    first = features[0].extra.get("kind")
    for i, f in enumerate(features):
        kind = f.extra.get("kind")
        if kind != first:
            raise ValueError(
                f"features of mixed kinds: image 0 has {first!r} features, image {i} has "
                f"{kind!r} features (extract all images with one matcher)"
            )


def _desc_shape(desc: Any) -> tuple[int, int]:
    """``(K, D)`` of a descriptor array or tensor (None or empty: ``(0, 0)``)."""
    shape = () if desc is None else tuple(desc.shape)
    if len(shape) == 2:
        return int(shape[0]), int(shape[1])
    if desc is None or int(np.prod(shape)) == 0:
        return 0, 0
    raise ValueError(f"descriptors must be a (K, D) array, got shape {shape}")


class _Descriptors:
    """Per-image ``(K_i, D)`` float32 descriptors, formed when an image's are read (SIFT
    features keep their bytes: converting every image at once would hold a float32 copy of
    all of them). ``counts (N,)`` rows per image, ``dim`` D (0 when no image has any)."""

    def __init__(self, features: Sequence[Features]) -> None:
        self._features = list(features)
        shapes = [_desc_shape(f.desc) for f in self._features]
        self.counts = np.array([sh[0] for sh in shapes], np.int64)
        dims = {sh[1] for sh in shapes if sh[0] > 0}
        if len(dims) > 1:
            raise ValueError(f"descriptors of different lengths: {sorted(dims)}")
        self.dim = dims.pop() if dims else max((sh[1] for sh in shapes), default=0)

    def __len__(self) -> int:
        return len(self._features)

    def __getitem__(self, i: int) -> np.ndarray:
        f = self._features[i]
        return descriptor_array(f) if isinstance(f.desc, np.ndarray) else _as_numpy(f.desc)


def _assign(x: np.ndarray, centres: np.ndarray, centre_sq: np.ndarray) -> np.ndarray:
    """(S,) index of the nearest centre for each row of x (S, D); ||x||^2 is constant per row."""
    return np.argmin(centre_sq[None, :] - 2.0 * (x @ centres.T), axis=1)


def _segment_sum(index: np.ndarray, x: np.ndarray, n: int) -> np.ndarray:
    """(n, D) sums of the rows of x (S, D) grouped by index (S,) in [0, n); sort + reduceat is
    batched and, unlike scattered float adds, independent of thread scheduling."""
    out = np.zeros((n, x.shape[1]), x.dtype)
    if index.size == 0:
        return out
    order = np.argsort(index, kind="stable")
    idx = index[order]
    starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
    out[idx[starts]] = np.add.reduceat(x[order], starts, axis=0)
    return out


def _kmeans(x: np.ndarray, words: int, rng: np.random.Generator) -> np.ndarray:
    """(W, D) centres of x (S, D), W = min(words, S): k-means++ seeding, then Lloyd iterations.

    float64 throughout: the sample is small and exact ties stay reproducible. An empty cluster
    keeps its previous centre (only happens with duplicated points).
    """
    x = x.astype(np.float64)
    s = x.shape[0]
    words = min(words, s)
    centres = np.empty((words, x.shape[1]))
    centres[0] = x[rng.integers(s)]
    d2 = ((x - centres[0]) ** 2).sum(1)
    for j in range(1, words):
        cum = np.cumsum(d2)
        if cum[-1] > 0:  # D^2 sampling
            pick = int(np.searchsorted(cum, rng.random() * cum[-1], side="right"))
        else:  # fewer distinct points than words
            pick = int(rng.integers(s))
        centres[j] = x[min(pick, s - 1)]
        d2 = np.minimum(d2, ((x - centres[j]) ** 2).sum(1))
    labels = None
    for _ in range(_LLOYD_ITERS):
        new = _assign(x, centres, (centres**2).sum(1))
        if labels is not None and np.array_equal(new, labels):
            break
        labels = new
        counts = np.bincount(labels, minlength=words)
        sums = _segment_sum(labels, x, words)
        filled = counts > 0
        centres[filled] = sums[filled] / counts[filled, None]
    return centres


def _sample(descs: _Descriptors, sample: int, rng: np.random.Generator) -> np.ndarray:
    """Up to ``sample`` descriptors drawn uniformly without replacement over all images."""
    counts = descs.counts
    offsets = np.r_[0, np.cumsum(counts)]
    total = int(offsets[-1])
    picks = np.sort(rng.choice(total, size=min(sample, total), replace=False))
    owner = np.searchsorted(offsets, picks, side="right") - 1
    bounds = np.searchsorted(owner, np.arange(len(descs) + 1))
    parts = [
        descs[i][picks[bounds[i] : bounds[i + 1]] - offsets[i]]
        for i in range(len(descs))
        if bounds[i + 1] > bounds[i]
    ]
    return np.concatenate(parts)


def _image_groups(counts: np.ndarray, chunk: int) -> Iterator[tuple[int, int]]:
    """Consecutive image ranges [start, stop) holding about ``chunk`` descriptors each."""
    start, acc = 0, 0
    for i, c in enumerate(counts):
        acc += int(c)
        if acc >= chunk:
            yield start, i + 1
            start, acc = i + 1, 0
    if start < len(counts):
        yield start, len(counts)


def _normalise_rows(x: np.ndarray, axis: int) -> np.ndarray:
    norm = np.linalg.norm(x, axis=axis, keepdims=True)
    return np.divide(x, norm, out=np.zeros_like(x), where=norm > 0)


def global_descriptors(
    features: Sequence[Features], words: int = 64, sample: int = 20000, seed: int = 0
) -> np.ndarray:
    """(N, W*D) float32 L2-normalised VLAD global descriptors of N images.

    The codebook (W = ``words`` visual words, fewer when fewer descriptors are sampled) is
    learned per run by k-means (k-means++ seeding with ``numpy.random.default_rng(seed)``, Lloyd
    iterations) on ``sample`` descriptors drawn uniformly over all images. Each image's
    residuals to its descriptors' nearest words are summed per word, intra-normalised (each
    word's block to unit L2 norm), power-normalised (signed square root) and L2-normalised.
    An image with no keypoints gets a zero row. Deterministic for a fixed seed.

    Args:
        features: N images' :class:`Features` of one kind; ``desc`` (K, D) numpy or torch.
        words, sample, seed: codebook size, codebook sample size, random seed.
    """
    return _vlad(_Descriptors(features), words, sample, seed)


def _vlad(descs: _Descriptors, words: int, sample: int, seed: int) -> np.ndarray:
    n, dim = len(descs), descs.dim
    counts = descs.counts
    if counts.sum() == 0:
        return np.zeros((n, words * dim), np.float32)
    rng = np.random.default_rng(seed)
    centres = _kmeans(_sample(descs, sample, rng), words, rng).astype(np.float32)
    w = centres.shape[0]
    centre_sq = (centres**2).sum(1)
    vlad = np.zeros((n, w, dim), np.float32)
    for start, stop in _image_groups(counts, _CHUNK):
        if counts[start:stop].sum() == 0:
            continue
        x = np.concatenate([descs[i] for i in range(start, stop) if counts[i] > 0])
        owner = np.repeat(np.arange(stop - start), counts[start:stop])
        label = _assign(x, centres, centre_sq)
        # residuals first, then sum: avoids sum(x) - count * centre cancelling in float32
        sums = _segment_sum(owner * w + label, x - centres[label], (stop - start) * w)
        vlad[start:stop] = sums.reshape(stop - start, w, dim)
    vlad = _normalise_rows(vlad, axis=2)  # intra-normalisation: bursty words do not dominate
    vlad = np.sign(vlad) * np.sqrt(np.abs(vlad))
    return _normalise_rows(vlad.reshape(n, w * dim), axis=1)


# --------------------------------------------------------------------------- pair search


def _row_blocks(rows: np.ndarray) -> Iterator[np.ndarray]:
    for s in range(0, rows.size, _ROWS):
        yield rows[s : s + _ROWS]


def _top(sim: np.ndarray, k: int) -> np.ndarray:
    """(B, k) column indices of each row's k largest entries (1 <= k <= columns)."""
    return np.argpartition(-sim, k - 1, axis=1)[:, :k]


def _knn_pairs(g: np.ndarray, valid: np.ndarray, k: int) -> set[tuple[int, int]]:
    """Union of the k-nearest-neighbour pairs among the images ``valid`` (indices into g)."""
    m = valid.size
    kk = min(k, m - 1)
    pairs: set[tuple[int, int]] = set()
    if kk < 1:
        return pairs
    gv = g[valid]
    for block in _row_blocks(np.arange(m)):
        sim = gv[block] @ gv.T
        sim[np.arange(block.size), block] = -np.inf  # not its own neighbour
        nn = _top(sim, kk)
        a = np.repeat(valid[block], kk)
        c = valid[nn.ravel()]
        pairs.update(zip(np.minimum(a, c).tolist(), np.maximum(a, c).tolist(), strict=True))
    return pairs


def _loop_pairs(g: np.ndarray, valid: np.ndarray, window: int, loop_k: int) -> set[tuple[int, int]]:
    """Each valid image's ``loop_k`` most similar valid images farther than ``window`` in file
    order (fewer when fewer lie outside its window)."""
    pairs: set[tuple[int, int]] = set()
    gv = g[valid]
    for block in _row_blocks(np.arange(valid.size)):
        sim = g[valid[block]] @ gv.T
        near = np.abs(valid[block][:, None] - valid[None, :]) <= window
        sim[near] = -np.inf
        nn = _top(sim, min(loop_k, valid.size))
        keep = np.isfinite(np.take_along_axis(sim, nn, axis=1))  # -inf: inside the window
        a = np.broadcast_to(valid[block][:, None], nn.shape)[keep]
        c = valid[nn[keep]]
        pairs.update(zip(np.minimum(a, c).tolist(), np.maximum(a, c).tolist(), strict=True))
    return pairs


def _graph_components(n: int, pairs: Sequence[tuple[int, int]] | set) -> tuple[int, np.ndarray]:
    if pairs:
        ab = np.array(sorted(pairs), np.int64)
        adj = coo_matrix((np.ones(len(ab)), (ab[:, 0], ab[:, 1])), shape=(n, n)).tocsr()
    else:
        adj = coo_matrix((n, n)).tocsr()
    count, labels = connected_components(adj, directed=False)
    return int(count), labels


def _repair(
    n: int, pairs: set[tuple[int, int]], g: np.ndarray, valid: np.ndarray, links: int = 5
) -> list[tuple[int, int]]:
    """Cross-component links that connect the graph of ``pairs`` over the images ``valid``.

    Kruskal's maximum spanning tree over the components, two components scored by their most
    similar pair (one similarity pass per component, then union-find); each join adds the
    ``links`` most similar pairs between the two (distinct images of the other component):
    blocks joined by a single pair could slide and scale against each other in translation
    averaging, which needs several non-parallel directions between them.

    The sign of the similarity is not a stop: with a codebook learned on the run's own
    descriptors, each word's residuals sum to about zero over the run, so images of unrelated
    places score below zero (about -0.25 for 3 synthetic places of 6 images) and a
    positive-only rule would leave such components apart. A few extra pairs per component are
    cheap, and two-view verification rejects them if the places really are unrelated.
    """
    _, labels = _graph_components(n, pairs)
    vlab = labels[valid]
    comps = np.unique(vlab)
    if comps.size < 2:
        return []
    gv = g[valid]
    groups: list[tuple[float, int, int, list[tuple[int, int]]]] = []
    for comp in comps[:-1]:
        rows = valid[vlab == comp]
        cols = np.flatnonzero(vlab > comp)  # each pair of components once
        best = np.full(cols.size, -np.inf, np.float32)
        arg = np.zeros(cols.size, np.int64)
        targets = gv[cols].T
        for block in _row_blocks(rows):
            sim = g[block] @ targets
            j = sim.argmax(axis=0)
            v = sim[j, np.arange(cols.size)]
            better = v > best
            best[better], arg[better] = v[better], block[j[better]]
        # per other component: its images sorted by their best similarity, the top `links`
        order = np.lexsort((-best, vlab[cols]))
        lab = vlab[cols][order]
        starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
        for st, en in zip(starts, np.r_[starts[1:], order.size], strict=True):
            top = order[st:min(en, st + links)]
            group = []
            for c in top:
                a, b = int(arg[c]), int(valid[cols[c]])
                group.append((min(a, b), max(a, b)))
            groups.append((float(best[top[0]]), int(comp), int(lab[st]), group))
    groups.sort(key=lambda e: (-e[0], e[3][0]))
    parent = {int(c): int(c) for c in comps}

    def root(c: int) -> int:
        while parent[c] != c:
            parent[c] = parent[parent[c]]
            c = parent[c]
        return c

    added: list[tuple[int, int]] = []
    joins = 0
    for _, ca, cb, group in groups:
        ra, rb = root(ca), root(cb)
        if ra != rb:
            parent[ra] = rb
            added.extend(group)
            joins += 1
            if joins == comps.size - 1:
                break
    return added


def _all_pairs(n: int) -> set[tuple[int, int]]:
    a, b = np.triu_indices(n, k=1)
    return set(zip(a.tolist(), b.tolist(), strict=True))


def select_pairs(features: Sequence[Features], options: PairOptions | None = None) -> PairSelection:
    """Choose the image pairs to match among N images (see the module docstring for the modes).

    * exhaustive: all N(N-1)/2 pairs.
    * sequential: (i, j) for 0 < j - i <= ``window``, plus each image's ``loop_k`` most similar
      images (VLAD cosine similarity) outside its window.
    * retrieval: union of each image's ``k`` nearest images by VLAD cosine similarity. If that
      graph has several components, a cheap connectivity repair adds the single most similar
      cross-component pair, again and again, until the images with keypoints are connected
      (whatever the similarity's sign; see ``_repair``). ``k >= N - 1`` gives all pairs.
      Images without keypoints take no part in the search and are paired with their
      neighbours in file order instead, so none is silently dropped.

    N < 2 gives no pairs. Deterministic for a fixed ``options.seed``; CPU only.

    Args:
        features: N images' :class:`Features`, all of one kind (``extra["kind"]``).
        options: :class:`PairOptions`; defaults to exhaustive.

    Raises:
        ValueError: features of mixed kinds or descriptor lengths.
    """
    opts = options if options is not None else PairOptions()
    t0 = time.perf_counter()
    features = list(features)
    _check_kinds(features)
    n = len(features)
    mode = opts.resolved(n)
    pairs: set[tuple[int, int]] = set()
    if n >= 2:
        if mode == "exhaustive" or (mode == "retrieval" and opts.k >= n - 1):
            pairs = _all_pairs(n)
        elif mode == "sequential":
            pairs = {(i, j) for i in range(n) for j in range(i + 1, min(n, i + opts.window + 1))}
            if opts.loop_k > 0 and opts.window < n - 1:  # else nothing lies outside a window
                descs = _Descriptors(features)
                valid = np.flatnonzero(descs.counts > 0)
                if valid.size >= 2:
                    g = _vlad(descs, opts.words, opts.sample, opts.seed)
                    pairs |= _loop_pairs(g, valid, opts.window, opts.loop_k)
        else:
            descs = _Descriptors(features)
            valid = np.flatnonzero(descs.counts > 0)
            if valid.size >= 2:
                g = _vlad(descs, opts.words, opts.sample, opts.seed)
                pairs = _knn_pairs(g, valid, opts.k)
                pairs.update(_repair(n, pairs, g, valid, opts.repair_links))
            for i in np.setdiff1d(np.arange(n), valid).tolist():  # no keypoints: file order
                pairs.update((j, j + 1) for j in (i - 1, i) if 0 <= j and j + 1 < n)
    ordered = sorted(pairs)
    count, labels = _graph_components(n, ordered)
    degree = np.zeros(n, np.int64)
    if ordered:
        np.add.at(degree, np.array(ordered).ravel(), 1)
    selection = PairSelection(
        pairs=ordered,
        mode=mode,
        components=count if n else 0,
        largest=int(np.bincount(labels).max()) if n else 0,
        isolated=np.flatnonzero(degree == 0).tolist(),
        seconds=time.perf_counter() - t0,
    )
    log.debug("pairs: %s", "; ".join(selection.lines()))
    return selection
