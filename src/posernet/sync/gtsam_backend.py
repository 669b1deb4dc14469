"""gtsam reference backend: Shonan rotation averaging + TranslationRecovery (optional extra).

Install with ``pip install 'posernet[gtsam]'``. This is the external reference implementation
the batched backends are compared against; it runs one component at a time in gtsam's C++
(a Python loop over components, which is fine for a reference, not for a hot path).

Conventions (checked numerically in the tests): ``BinaryMeasurementRot3(i, j, R)`` measures
``wR_i^T wR_j`` with camera-to-world ``wR``; in our terms (world-to-camera ``R``, edge
``i -> j`` with ``R_ij = R_j R_i^T``) that is ``R_i R_j^T = R_ij^T``. ``BinaryMeasurementUnit3(i,
j, d)`` measures the direction of ``c_j - c_i`` in the world frame, which our edge gives as
``-R_j^T t_ij`` (``t_ij = -R_j (c_j - c_i)``). Noise models are isotropic (Shonan requires it)
and keys are ``0..n-1`` per component.

Scale: ``free`` only -- TranslationRecovery uses unit directions; its gauge (first camera at
the origin, first baseline of length 1) is replaced by centroid 0, RMS radius 1. Evaluate with
a similarity alignment.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..options import option
from .backend import SyncBackend, SyncOptions, SyncResult, scale_option
from .components import Components
from .padding import assemble, build_padded, edge_rotations

try:  # optional dependency: the registry only offers this backend when it imports
    import gtsam
except ImportError:  # pragma: no cover - exercised only without gtsam
    gtsam = None

__all__ = ["GtsamBackend", "GtsamOptions"]


@dataclass(frozen=True)
class GtsamOptions(SyncOptions):
    """``rotation_sigma`` / ``direction_sigma``: isotropic noise of the rotation and direction
    measurements; ``p_min`` / ``p_max``: Shonan's Riemannian staircase; ``huber``: Shonan's
    robust (Huber) cost; ``lm_tol``: relative/absolute error tolerance of the LM solves;
    ``max_iterations``: LM iterations."""

    scale: str = scale_option("free")
    rotation_sigma: float = option(0.1, gt=0, help="isotropic noise of relative rotations (rad)")
    direction_sigma: float = option(0.01, gt=0, help="isotropic noise of translation directions")
    p_min: int = option(3, ge=3, help="Shonan Riemannian staircase: lowest level")
    p_max: int = option(10, ge=3, help="... highest level (>= p_min)")
    huber: bool = option(False, help="Shonan's robust (Huber) cost")
    lm_tol: float = option(1e-14, gt=0, help="relative/absolute error tolerance of the LM solves")
    max_iterations: int = option(1000, ge=1, help="LM iterations")

    def check(self) -> None:
        super().check()
        if self.p_max < self.p_min:
            raise ValueError(f"need 3 <= p_min <= p_max, got p_min={self.p_min}, "
                             f"p_max={self.p_max}")


class GtsamBackend(SyncBackend):
    """Shonan averaging (certifiable rotation averaging) + gtsam TranslationRecovery."""

    name = "gtsam"
    Options = GtsamOptions
    scales = ("free",)

    def __init__(self, **options: Any) -> None:
        if gtsam is None:
            raise ValueError("sync backend 'gtsam' needs gtsam: pip install 'posernet[gtsam]'")
        super().__init__(**options)

    def _lm(self) -> Any:
        p = gtsam.LevenbergMarquardtParams.CeresDefaults()
        p.setRelativeErrorTol(self.options.lm_tol)
        p.setAbsoluteErrorTol(self.options.lm_tol)
        p.setMaxIterations(self.options.max_iterations)
        return p

    def solve_component(self, n: int, src: np.ndarray, dst: np.ndarray, R_e: np.ndarray,
                        t_e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One connected component: local edges ``src -> dst`` with relative rotations
        ``R_e (m, 3, 3)`` and translations ``t_e (m, 3)`` -> world-to-camera ``(R (n, 3, 3),
        t (n, 3))`` (centroid 0, RMS camera distance 1)."""
        o: GtsamOptions = self.options  # type: ignore[assignment]
        rnoise = gtsam.noiseModel.Isotropic.Sigma(3, o.rotation_sigma)
        meas = [gtsam.BinaryMeasurementRot3(int(i), int(j), gtsam.Rot3(R.T), rnoise)
                for i, j, R in zip(src, dst, R_e, strict=True)]
        params = gtsam.ShonanAveragingParameters3(self._lm())
        params.setUseHuber(o.huber)
        shonan = gtsam.ShonanAveraging3(meas, params)
        try:
            values, _ = shonan.run(shonan.initializeRandomly(), o.p_min, o.p_max)
        except RuntimeError as exc:  # the staircase found no certified optimum up to p_max
            raise ValueError(f"gtsam Shonan averaging did not converge on a component of {n} "
                             f"cameras with p_max={o.p_max} ({exc}); raise sync.p_max or use "
                             "another backend") from exc
        R = np.stack([values.atRot3(k).matrix().T for k in range(n)])  # world-to-camera
        u = -np.einsum("mba,mb->ma", R[dst], t_e)  # world baselines c_j - c_i
        norm = np.linalg.norm(u, axis=1)
        dnoise = gtsam.noiseModel.Isotropic.Sigma(2, o.direction_sigma)
        dirs = [gtsam.BinaryMeasurementUnit3(int(i), int(j), gtsam.Unit3(v / nv), dnoise)
                for i, j, v, nv in zip(src, dst, u, norm, strict=True) if nv > 0]
        c = np.zeros((n, 3))
        if dirs:
            vals = gtsam.TranslationRecovery(self._lm()).run(dirs, 1.0)
            c = np.stack([vals.atPoint3(k) if vals.exists(k) else np.zeros(3)
                          for k in range(n)])
        c = c - c.mean(0)
        rms = np.sqrt((c * c).sum(1).mean())
        c = c / rms if rms > 0 else c
        return R, -np.einsum("nab,nb->na", R, c)

    def _solve(self, struct: dict[str, Any], edge_pose: Tensor, edge_pose_gt: Tensor | None,
               comps: Components) -> SyncResult:
        R_e = edge_rotations(edge_pose)
        prob = build_padded(struct["edge_index"], R_e, edge_pose[:, 4:], comps)
        G, n = prob.G, prob.n
        R = torch.eye(3, dtype=torch.float64).expand(G, n, 3, 3).clone()
        t = torch.zeros(G, n, 3, dtype=torch.float64)
        cpu = {k: getattr(prob, k).cpu() for k in ("src", "dst", "R", "t", "edge_mask", "count")}
        for g in range(G):  # reference implementation: one component at a time
            em = cpu["edge_mask"][g]
            k = int(cpu["count"][g])
            Rg, tg = self.solve_component(k, cpu["src"][g][em].numpy(),
                                          cpu["dst"][g][em].numpy(),
                                          cpu["R"][g][em].numpy(), cpu["t"][g][em].numpy())
            R[g, :k], t[g, :k] = torch.from_numpy(Rg), torch.from_numpy(tg)
        dev = prob.R.device
        ones = prob.edge_mask.to(torch.float64)
        it = torch.ones(G, dtype=torch.long, device=dev)
        conv = torch.ones(G, dtype=torch.bool, device=dev)
        poses, solved, w, itg, cvg = assemble(struct, comps, prob, R.to(dev), t.to(dev), ones,
                                              it, conv, edge_pose.dtype, dev)
        return SyncResult(poses=poses, component=comps.comp, solved=solved, edge_weight=w,
                          iterations=itg, converged=cvg, scale=self.options.scale,
                          metric=False, backend=self.name)
