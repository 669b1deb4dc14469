"""The fast robust dense IRLS (:mod:`posernet.sync.filtered`) computes what the
eigh-per-iteration loop it replaced computed, to float round-off.

Pinned three ways: against that loop, kept here as the slow reference (:func:`eigh_irls`, the
code of ``rotation_irls`` before the filter), component by component and through both
backends; against numbers the old code printed for a fixed seeded batch (``OLD_*``); and its
parts against their textbook counterparts (``eigh`` subspaces, ``project_to_so3``,
Gram-Schmidt, ``rotation_residuals``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers import F64, make_graph, rel_to_first

import posernet.sync.filtered as filtered
import posernet.sync.irls as irls
from posernet.geometry import axis_angle_to_rotation_matrix, project_to_so3
from posernet.graph import GraphBatch
from posernet.sync import get_backend
from posernet.sync.components import connected_components
from posernet.sync.irls import rotation_irls
from posernet.sync.padding import PaddedProblem, build_padded, edge_rotations
from posernet.sync.robust import mad_cauchy_weights
from posernet.sync.spectral import (
    RotationSolution,
    _orthonormal_columns,
    batched_eigh,
    degrees,
    dense_N,
    rotation_residuals,
    rotations_from_eigvecs,
    start_weights,
    top3_dense,
)

# --------------------------------------------------------------------------- the reference


def eigh_irls(prob: PaddedProblem, max_iters: int = 50, tol: float = 1e-5, theta: float = 2.0,
              w0: torch.Tensor | None = None, prior: bool = False,
              sizes: list | None = None) -> RotationSolution:
    """The robust dense ``rotation_irls`` before the filter: one batched ``eigh`` of every
    still-iterating component per iteration (the batch re-selected, trimmed, each time).
    ``sizes``: if a list, gets the padded size of each component's last solve ``[G]``."""
    G, n, dev, dt = prob.G, prob.n, prob.R.device, prob.R.dtype
    w_edge, w_diag = start_weights(prob, w0)
    w_prior = w_edge.clone() if prior and w0 is not None else None
    R = torch.eye(3, dtype=dt, device=dev).expand(G, n, 3, 3).clone()
    V3 = torch.zeros(G, 3 * n, 3, dtype=dt, device=dev)
    Rh = torch.zeros_like(V3)
    used_edge, used_diag = w_edge.clone(), w_diag.clone()
    iters = torch.zeros(G, dtype=torch.long)
    last_n = torch.zeros(G, dtype=torch.long)
    converged = torch.zeros(G, dtype=torch.bool)
    active = torch.ones(G, dtype=torch.bool)
    for k in range(1, max_iters + 1):
        idx = active.nonzero().squeeze(1)
        sub = prob.select(idx) if idx.numel() < G else prob
        ns, ms = sub.n, sub.m
        we, wd = w_edge[idx, :ms], w_diag[idx]
        s = degrees(sub, we, wd).rsqrt()
        V3s = top3_dense(dense_N(sub, we, wd, s))
        Rs, Rhs = rotations_from_eigvecs(V3s, s, sub.node_mask)
        R[idx, :ns], V3[idx, :3 * ns], Rh[idx, :3 * ns] = Rs, V3s, Rhs
        used_edge[idx, :ms], used_diag[idx] = we, wd
        iters[idx], last_n[idx] = k, ns
        w_new = mad_cauchy_weights(rotation_residuals(sub, Rs), sub.edge_mask, theta)
        if w_prior is not None:
            w_new = w_new * w_prior[idx, :ms]
        wd_new = w_new.amax(dim=1)
        cnt = sub.count.to(dt)
        num = (2 * ((we - w_new) ** 2).sum(1) + cnt * (wd - wd_new) ** 2).sqrt()
        den = (2 * (w_new ** 2).sum(1) + cnt * wd_new ** 2).sqrt() * cnt
        w_edge[idx, :ms], w_diag[idx] = w_new, wd_new
        stop = num / den.clamp_min(1e-300) <= tol
        converged[idx[stop]] = True
        active[idx[stop]] = False
        if not bool(active.any()):
            break
    if sizes is not None:
        sizes.extend(last_n.tolist())
    return RotationSolution(R=R, V3=V3, Rh=Rh, w_edge=used_edge, w_diag=used_diag,
                            iterations=iters, converged=converged,
                            eig_converged=torch.ones(G, dtype=torch.bool))


def problem(graphs: list) -> PaddedProblem:
    b = GraphBatch.from_graphs(graphs)
    comps = connected_components(b.edge_index, b.num_nodes, b.node_batch, b.num_graphs)
    return build_padded(b.edge_index, edge_rotations(b.edge_pose), b.edge_pose[:, 4:], comps)


def gauge_free(R: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``R_i R_0^T`` of every component's valid nodes ``[G, n, 3, 3]`` (identity on pads)."""
    out = R @ R[:, :1].mT
    eye = torch.eye(3, dtype=R.dtype)
    return torch.where(mask[..., None, None], out, eye)


def projector(V: torch.Tensor) -> torch.Tensor:
    """Orthogonal projector onto the span of the columns of ``V [G, M, k]``."""
    Q = torch.linalg.qr(V).Q
    return Q @ Q.mT


CASES = {
    # the paper's test graphs: 8 nodes, ~16 edges, noise and a few outliers
    "paper": [make_graph(8, 9, 600 + k, rot_noise_deg=3.0, trans_noise=0.03,
                         outlier_frac=0.1) for k in range(24)],
    # sizes 3..20 in one padded batch: the batch shrinks and is trimmed as components stop
    "mixed": [make_graph(n, e, 700 + n, rot_noise_deg=4.0, trans_noise=0.05, outlier_frac=0.15)
              for n, e in [(3, 1), (5, 4), (8, 8), (12, 20), (20, 60), (4, 2), (9, 12)]],
    # heavy outliers: the filter's test fails on some iterations (dense fallback)
    "outliers": [make_graph(10, 14, 800 + k, rot_noise_deg=6.0, trans_noise=0.1,
                            outlier_frac=0.4) for k in range(12)],
}


def roundoff(prob: PaddedProblem,
             ref: RotationSolution) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """How far the reference itself moves per component when its edge rotations move by
    round-off (1e-15): weights ``[G]`` and gauge-free rotations ``[G]`` (the scale "the same to
    float round-off" is measured on: an IRLS amplifies round-off, some components a lot), and
    whether the output kept its gauge ``[G]`` (the sign of an ``eigh`` eigenvector can flip
    under round-off)."""
    g = torch.Generator().manual_seed(0)
    R = project_to_so3(prob.R + 1e-15 * torch.randn(prob.R.shape, generator=g, dtype=F64))
    moved = eigh_irls(dataclasses.replace(prob, R=torch.where(prob.edge_mask[..., None, None],
                                                              R, prob.R)))
    dw = (moved.w_edge - ref.w_edge).abs().amax(1)
    dR = (gauge_free(moved.R, prob.node_mask) - gauge_free(ref.R, prob.node_mask)).abs()
    kept = (moved.R - ref.R).abs().flatten(1).amax(1) < 1e-8
    return dw, dR.flatten(1).amax(1), kept


@pytest.mark.parametrize("chunked", [False, True])
@pytest.mark.parametrize("case", sorted(CASES))
def test_dense_irls_matches_the_eigh_loop(case: str, chunked: bool,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    if chunked:  # a few components per chunk (one of the larger ones)
        monkeypatch.setattr(filtered, "_CHUNK", 3 * 24 * 24)
    prob = problem(CASES[case])
    ref = eigh_irls(prob)
    got = rotation_irls(prob, True, 50, 1e-5, 2.0, krylov=False)
    assert torch.equal(got.iterations, ref.iterations)
    assert torch.equal(got.converged, ref.converged)
    dw, dR, kept = roundoff(prob, ref)
    assert bool(((got.w_edge - ref.w_edge).abs().amax(1) <= 1e-11 + 20 * dw).all())
    assert bool(((got.w_diag - ref.w_diag).abs() <= 1e-11 + 20 * dw).all())
    diff = (gauge_free(got.R, prob.node_mask) - gauge_free(ref.R, prob.node_mask)).abs()
    assert bool((diff.flatten(1).amax(1) <= 1e-11 + 20 * dR).all())
    # the last solve's eigenvectors: the same span; mostly the same gauge (eigh's sign choice
    # flips under round-off for some components, the loop's own output too: ``kept``; the
    # bit-for-bit gauge given the same weights is tested below)
    tol = (1e-11 + 20 * dR)[:, None, None]
    assert bool(((projector(got.V3) - projector(ref.V3)).abs() <= tol).all())
    assert bool(((projector(got.Rh) - projector(ref.Rh)).abs() <= tol).all())
    same = (got.R - ref.R).abs().flatten(1).amax(1) < 1e-8
    assert 2 * int(same.sum()) >= prob.G and 2 * int(kept.sum()) >= prob.G


def test_last_solve_is_padded_like_the_eigh_loop(monkeypatch) -> None:
    """Each component's last eigen-solve has the size the loop gave it (the largest component
    still iterating then), so ``eigh`` sees the very same matrix."""
    prob = problem(CASES["mixed"])
    sizes: list = []
    eigh_irls(prob, sizes=sizes)
    seen: list = []
    real = filtered.top3_dense

    def spy(N: torch.Tensor) -> torch.Tensor:
        seen.append(N.shape[-1] // 3)
        return real(N)

    monkeypatch.setattr(filtered, "top3_dense", spy)
    sol = rotation_irls(prob, True, 50, 1e-5, 2.0, krylov=False)
    # the dense fallback inside the iterations pads to the batch; the last solves come last
    assert sorted(seen[-len(set(sizes)):]) == sorted(set(sizes))
    assert len(set(sizes)) > 1  # the case does exercise trimming
    # one iteration: the weights are the start weights, the output is the loop's, bit for bit
    one, ref = (rotation_irls(prob, True, 1, 1e-5, 2.0, krylov=False),
                eigh_irls(prob, max_iters=1))
    for a, b in ((one.R, ref.R), (one.V3, ref.V3), (one.Rh, ref.Rh)):
        assert torch.equal(a, b)
    assert sol.iterations.max() > 1


@pytest.mark.parametrize("prior", [False, True])
def test_weighted_start_matches_the_eigh_loop(prior: bool) -> None:
    prob = problem(CASES["paper"][:10])
    g = torch.Generator().manual_seed(5)
    w0 = torch.where(prob.edge_mask, 0.1 + torch.rand(prob.G, prob.m, generator=g,
                                                      dtype=F64), 0.0)
    ref = eigh_irls(prob, w0=w0, prior=prior)
    got = rotation_irls(prob, True, 50, 1e-5, 2.0, krylov=False, w0=w0, prior=prior)
    assert torch.equal(got.iterations, ref.iterations)
    torch.testing.assert_close(got.w_edge, ref.w_edge, atol=1e-9, rtol=0)
    torch.testing.assert_close(gauge_free(got.R, prob.node_mask),
                               gauge_free(ref.R, prob.node_mask), atol=1e-9, rtol=0)


@pytest.mark.parametrize("backend", ["eig_se3", "rotation_translation"])
def test_backends_match_the_eigh_loop(backend: str, monkeypatch) -> None:
    graphs = CASES["mixed"] + CASES["paper"][:6]
    b = GraphBatch.from_graphs(graphs)
    be = get_backend(backend, scale="given")
    got = be.solve_with_info(b)

    calls = []

    def slow(prob, w_edge, w_diag, max_iters, tol, theta, seed, w_prior):
        calls.append(prob.G)
        return eigh_irls(prob, max_iters, tol, theta, w0=w_edge,
                         prior=w_prior is not None)

    monkeypatch.setattr(irls, "dense_irls", slow)  # what the backends' rotation_irls runs
    ref = be.solve_with_info(b)
    assert calls  # the reference did run
    # the reference's own round-off scale: its poses for edge poses moved by 1e-15
    g = torch.Generator().manual_seed(0)
    moved = be.solve_with_info(b, b.edge_pose + 1e-15 * torch.randn(b.edge_pose.shape,
                                                                    generator=g, dtype=F64))
    assert torch.equal(got.iterations, ref.iterations)
    torch.testing.assert_close(got.edge_weight, ref.edge_weight, atol=1e-9, rtol=0)
    for k in range(b.num_graphs):
        sl = slice(int(b.ptr[k]), int(b.ptr[k + 1]))
        want = rel_to_first(ref.poses[sl])
        scale = np.abs(rel_to_first(moved.poses[sl]) - want).max()
        np.testing.assert_allclose(rel_to_first(got.poses[sl]), want, atol=1e-10 + 20 * scale,
                                   rtol=0)


# Printed by the code before the filter (eigh every iteration) for this batch:
OLD_SPECS = [(8, 8, 501), (8, 8, 502), (5, 4, 503), (12, 20, 504), (3, 1, 505), (20, 60, 506)]
OLD_ITERS = [48, 50, 20, 18, 2, 13]
OLD_WSUM = [9.184157322024, 8.040594157523, 5.789284852215, 18.44273541383, 0.0,
            48.949409396781]
OLD_W0 = [0.920476092661, 0.920489677916, 0.000182752228, 0.76697673014, 0.00018314996,
          0.922708786916, 0.589794970592, 0.676372248367, 0.715127196014, 0.582126038145,
          0.967894608246, 0.931544336424, 0.000181094115, 0.283286943379, 0.90681269692]
OLD_T0 = {  # graph 0, positions relative to camera 0 (gauge-free)
    "eig_se3": [[-2.261168200358, -0.325808215441, 1.691807889009],
                [-3.312689228729, -2.418817513068, 3.930047862713],
                [-2.903465294854, 2.155099285658, 1.095529951935],
                [-1.708333811109, 0.614125711534, -4.475087527581],
                [1.916679060179, -2.048925574588, -0.444200024728],
                [-1.397004482437, -1.770131812238, 2.525227138674],
                [4.769599446442, 5.42663986697, -0.280245981707]],
    "rotation_translation": [[-2.268296550174, -0.310843720902, 1.689058610231],
                             [-3.308608797217, -2.417367691521, 3.900735454876],
                             [-2.916461239444, 2.164701579008, 1.071612657615],
                             [-1.677217014503, 0.58679456036, -4.541584580103],
                             [1.912918404848, -2.047722033101, -0.459753536825],
                             [-1.394297560805, -1.770732078087, 2.486332803703],
                             [4.775042650437, 5.460847743814, -0.26037218518]],
}
OLD_TNORM = {
    "eig_se3": [12.237429837922, 16.944082342056, 8.470369129514, 13.478213790941,
                4.467925064854, 27.18053134366],
    "rotation_translation": [12.257214374896, 16.798498324328, 8.002575977662,
                             13.526615434436, 4.46183532329, 27.01842844677],
}


@pytest.mark.parametrize("backend", ["eig_se3", "rotation_translation"])
def test_numbers_of_the_code_before_the_filter(backend: str) -> None:
    graphs = [make_graph(n, e, s, rot_noise_deg=3.0, trans_noise=0.03, outlier_frac=0.15)
              for n, e, s in OLD_SPECS]
    b = GraphBatch.from_graphs(graphs)
    res = get_backend(backend, scale="given").solve_with_info(b)
    assert res.iterations.tolist() == OLD_ITERS
    eptr, ptr = b.edge_ptr.tolist(), b.ptr.tolist()
    w = res.edge_weight
    np.testing.assert_allclose([float(w[eptr[k]:eptr[k + 1]].sum()) for k in range(6)],
                               OLD_WSUM, atol=1e-9)
    np.testing.assert_allclose(w[eptr[0]:eptr[1]].numpy(), OLD_W0, atol=1e-9)
    rel = [torch.as_tensor(rel_to_first(res.poses[ptr[k]:ptr[k + 1]])) for k in range(6)]
    np.testing.assert_allclose(rel[0][1:, :3, 3].numpy(), OLD_T0[backend], atol=1e-9)
    np.testing.assert_allclose([float(r[:, :3, 3].norm()) for r in rel], OLD_TNORM[backend],
                               atol=1e-9)


# --------------------------------------------------------------------------- the parts


def spectrum_matrix(G: int, M: int, top: list, rest: tuple, seed: int,
                    pad: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric ``[G, M + pad, M + pad]`` with eigenvalues ``top`` and the rest uniform in
    ``rest`` (padded rows and columns 0), and its top-3 eigenvectors ``[G, M + pad, 3]``."""
    g = torch.Generator().manual_seed(seed)
    U = torch.linalg.qr(torch.randn(G, M, M, generator=g, dtype=F64)).Q
    lam = torch.empty(G, M, dtype=F64).uniform_(*rest, generator=g)
    lam[:, :3] = torch.tensor(top, dtype=F64)
    N = (U * lam[:, None]) @ U.mT
    N = torch.nn.functional.pad(N, (0, pad, 0, pad))
    return 0.5 * (N + N.mT), torch.nn.functional.pad(U[:, :, :3], (0, 0, 0, pad))


@pytest.mark.parametrize("start", ["random", "warm"])
def test_top3_filtered_spans_the_top_eigenvectors(start: str) -> None:
    N, V = spectrum_matrix(40, 24, [1.0, 0.9995, 0.999], (-0.95, 0.85), seed=1, pad=6)
    g = torch.Generator().manual_seed(2)
    if start == "random":
        Vt, first = torch.randn(40, 3, 30, generator=g, dtype=F64), 1
    else:  # a start 1e-2 off the subspace
        Vt = (V + 1e-2 * torch.randn(V.shape, generator=g, dtype=F64)).mT
        first = filtered._FIRST
    Qt, ok = filtered.top3_filtered(N, Vt, first=first)
    assert bool(ok.all())
    eye = torch.eye(3, dtype=F64).expand(40, 3, 3)
    torch.testing.assert_close(Qt @ Qt.mT, eye, atol=1e-14, rtol=0)
    torch.testing.assert_close(Qt.mT @ Qt, V @ V.mT, atol=1e-13, rtol=0)
    assert float(Qt[:, :, 24:].abs().max()) < 1e-14  # nothing on the padded rows


@pytest.mark.parametrize("top,rest", [([1.0, 0.999, 0.998], (-0.5, 0.995)),  # lambda_4 ~ 1
                                      ([1.0, 0.95, 0.8], (-0.5, 0.5))])  # lambda_3 < _HI
def test_top3_filtered_flags_what_it_cannot_solve(top: list, rest: tuple) -> None:
    N, _ = spectrum_matrix(16, 24, top, rest, seed=3)
    if rest[1] > 0.99:  # put the fourth eigenvalue right under the top three
        lam, U = torch.linalg.eigh(N)
        lam[:, -4] = 0.9975
        N = (U * lam[:, None]) @ U.mT
    Vt = torch.randn(16, 3, 24, generator=torch.Generator().manual_seed(4), dtype=F64)
    _, ok = filtered.top3_filtered(N, Vt, first=1)
    assert not bool(ok.any())


def test_orth_rows_is_gram_schmidt() -> None:
    g = torch.Generator().manual_seed(6)
    V = torch.randn(50, 3, 21, generator=g, dtype=F64)
    V[:, 2] += 1e3 * V[:, 0]  # ill-conditioned (~1e4)
    Q = filtered.orth_rows(V)
    ref = _orthonormal_columns(V.mT).mT
    torch.testing.assert_close(Q, ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(Q @ Q.mT, torch.eye(3, dtype=F64).expand(50, 3, 3), atol=1e-15,
                               rtol=0)


@pytest.mark.parametrize("threads", [1, 3])
def test_batched_eigh_is_eigh_bit_for_bit(threads: int, monkeypatch) -> None:
    """Split between threads or not, each matrix is solved alone: the very same output."""
    g = torch.Generator().manual_seed(11)
    A = torch.randn(200, 12, 12, generator=g, dtype=F64)
    A = A + A.mT
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    lam, vec = batched_eigh(A)
    ref = torch.linalg.eigh(A)
    assert torch.equal(lam, ref.eigenvalues) and torch.equal(vec, ref.eigenvectors)


def test_rotations_take_more_newton_steps_where_the_first_ones_fall_short() -> None:
    """Blocks far from a rotation fail the few-step polar test and are finished by the full
    iteration (or the SVD): every output is the nearest rotation."""
    g = torch.Generator().manual_seed(12)
    G, n = 6, 4
    R = axis_angle_to_rotation_matrix(torch.randn(G, n, 3, generator=g, dtype=F64))
    noise = torch.full((G, n, 1, 1), 0.002, dtype=F64)
    noise[:2] = 0.3  # two components far off: the first two steps do not reach round-off
    B = R + noise * torch.randn(G, n, 3, 3, generator=g, dtype=F64)
    # basis rows Qt[c, k, a n + j] = B_j[a, k]; s = 1
    Qt = B.permute(0, 3, 2, 1).reshape(G, 3, 3 * n)
    Qt = filtered.orth_rows(Qt, passes=2)
    mask = torch.ones(G, n, dtype=torch.bool)
    a = Qt.view(G, 3, 3, n).permute(2, 1, 0, 3).reshape(9, G * n)
    assert not bool(filtered.polar9(a, filtered._POLAR_FIRST)[1].all())  # the retry runs
    out = filtered._rotations(Qt, torch.ones(G, n, dtype=F64), mask)
    ref = project_to_so3(a.T.reshape(-1, 3, 3))
    torch.testing.assert_close(out.T.reshape(-1, 3, 3), ref, atol=1e-14, rtol=0)


def test_polar9_is_project_to_so3() -> None:
    g = torch.Generator().manual_seed(7)
    K = 400
    R = axis_angle_to_rotation_matrix(torch.randn(K, 3, generator=g, dtype=F64))
    A = (R + 0.05 * torch.randn(K, 3, 3, generator=g, dtype=F64)) * 0.4
    A[:20] = torch.randn(20, 3, 3, generator=g, dtype=F64)  # far from any rotation
    A[20:25] = -A[20:25]  # det < 0: no proper polar factor
    out, ok = filtered.polar9(A.reshape(K, 9).T.contiguous())
    ref = project_to_so3(A)
    assert not bool(ok[20:25].any()) and bool(ok[25:].all())
    torch.testing.assert_close(out.T.reshape(K, 3, 3)[ok], ref[ok], atol=1e-14, rtol=0)


def test_edge_residuals_are_rotation_residuals() -> None:
    prob = problem(CASES["mixed"])
    g = torch.Generator().manual_seed(8)
    R = axis_angle_to_rotation_matrix(torch.randn(prob.G, prob.n, 3, generator=g, dtype=F64))
    ref = rotation_residuals(prob, R)
    base = (torch.arange(prob.G) * prob.n)[:, None]
    got = filtered.edge_residuals(R.reshape(-1, 9).T, prob.R.reshape(-1, 9).T,
                                  (base + prob.src).flatten(), (base + prob.dst).flatten())
    got = torch.where(prob.edge_mask, got.view(prob.G, prob.m), 0.0)
    torch.testing.assert_close(got, ref, atol=1e-15, rtol=0)
