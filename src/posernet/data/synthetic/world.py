"""One simulated scene with its sequences, and the lazily evaluated images and image pairs.

:class:`SceneWorld` is the simulator's working object: it builds the scene and its sequences
from the seed, then simulates an image (visible keypoints, detector output, keypoint noise) or an
image pair (keypoint matches, box matches, both 5-point estimates) on demand and caches it.
Every image and pair draws from its own named random stream, so results do not depend on the
order in which graphs ask for them.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ...frontend.assembly import PairResult
from ...frontend.boxmatch import (
    box_centres,
    boxes_contain,
    keypoints_in_matched_boxes,
    match_boxes,
)
from ...frontend.relpose import five_point
from .camera import intrinsics
from .config import DatasetOptions
from .detections import Detections, detect
from .matching import match_keypoints, reassign_wrong
from .scenes import Scene, build_scene
from .seeding import make_rng, stream_seed
from .trajectories import FramePool, Sequence, frame_pools, make_sequences
from .visibility import observe

__all__ = ["Frame", "PairResult", "SceneWorld"]


@dataclass
class Frame:
    """One simulated image.

    ``kp_ids (V,)`` detected keypoints (sorted), ``kp_uv (V, 2)`` their noisy pixels,
    ``kp_uv_true (V, 2)`` the exact projections; ``det`` the detector output.
    """

    fid: int
    w2c: np.ndarray
    centre: np.ndarray
    kp_ids: np.ndarray
    kp_uv: np.ndarray
    kp_uv_true: np.ndarray
    det: Detections


class SceneWorld:
    """Scene, sequences, frame pools and caches for one scene under one master seed."""

    def __init__(
        self, options: DatasetOptions, scene: str, seed: int = 0, max_cached_frames: int = 4000
    ) -> None:
        self.options = options
        self.seed = int(seed)
        self.scene_name = scene
        self.scene: Scene = build_scene(scene, make_rng(seed, scene, "layout"), options.keypoints)
        self.sequences: list[Sequence] = make_sequences(
            self.scene, options.sequences, make_rng(seed, scene, "trajectories")
        )
        self.w2c = np.concatenate([s.w2c for s in self.sequences])
        self.centres = np.concatenate([s.centres for s in self.sequences])
        self.frame_sequence = np.concatenate(
            [np.full(s.w2c.shape[0], s.index) for s in self.sequences]
        )
        self.pools: dict[str, FramePool] = frame_pools(
            self.sequences, options.sequences.val_fraction
        )
        cam = options.camera
        self.K = intrinsics(cam.focal, cam.width, cam.height)
        self._frames: OrderedDict[int, Frame] = OrderedDict()
        self._pairs: dict[tuple[int, int], PairResult] = {}
        self._max_frames = max_cached_frames

    @property
    def num_frames(self) -> int:
        return int(self.w2c.shape[0])

    # ------------------------------------------------------------------ images

    def frame(self, fid: int) -> Frame:
        """The simulated image ``fid`` (cached, LRU)."""
        fid = int(fid)
        hit = self._frames.get(fid)
        if hit is not None:
            self._frames.move_to_end(fid)
            return hit
        f = self._simulate_frame(fid)
        self._frames[fid] = f
        if len(self._frames) > self._max_frames:
            self._frames.popitem(last=False)
        return f

    def _simulate_frame(self, fid: int) -> Frame:
        o = self.options
        cam, kpo = o.camera, o.keypoints
        rng = make_rng(self.seed, self.scene_name, "frame", fid)
        w2c = self.w2c[fid]
        view = observe(self.scene, w2c, self.K, cam.width, cam.height, cam.near, cam.far, cam.k1)
        det = detect(view, o.detector, cam.width, cam.height, rng)
        n = view.kp_ids.size
        # repeatability falls for foreshortened texture
        p = kpo.detect_prob * np.clip(view.kp_cos / 0.5, 0.0, 1.0)
        keep = rng.random(n) < p
        noise = rng.normal(0.0, kpo.pixel_noise, size=(n, 2))
        uv_true = view.kp_uv[keep]
        return Frame(
            fid=fid,
            w2c=w2c,
            centre=self.centres[fid],
            kp_ids=view.kp_ids[keep],
            kp_uv=uv_true + noise[keep],
            kp_uv_true=uv_true,
            det=det,
        )

    # ------------------------------------------------------------------ pairs

    def pair(self, i: int, j: int) -> PairResult:
        """The evaluated pair of frames ``i, j`` (stored once as ``min -> max``, cached)."""
        a, b = (int(i), int(j)) if i < j else (int(j), int(i))
        if a == b:
            raise ValueError(f"a pair needs two different frames, got {a} twice")
        key = (a, b)
        hit = self._pairs.get(key)
        if hit is None:
            hit = self._evaluate_pair(a, b)
            self._pairs[key] = hit
        return hit

    def _evaluate_pair(self, a: int, b: int) -> PairResult:
        o = self.options
        fa, fb = self.frame(a), self.frame(b)
        rng = make_rng(self.seed, self.scene_name, "pair", a, b)
        sc = self.scene
        m = match_keypoints(
            sc.kp_xyz,
            sc.kp_owner,
            sc.kp_twin,
            fa.kp_ids,
            fa.kp_uv,
            fa.centre,
            fb.kp_ids,
            fb.kp_uv,
            fb.centre,
            o.keypoints,
            rng,
        )
        none = np.zeros(0, np.int64)
        if m.uv_a.shape[0] < o.matching.min_keypoints:  # cannot match a single box pair
            return PairResult(a, b, none, none, np.zeros(0, bool), 0, 0, None, None, "unmatched")
        # not one-to-one: the simulated detector gives no nested duplicates, and the datasets
        # (and results/) were made this way
        ia, ib, _ = match_boxes(
            m.uv_a,
            m.uv_b,
            fa.det.boxes,
            fb.det.boxes,
            o.matching.min_keypoints,
            o.matching.min_span,
            one_to_one=False,
        )
        ia, ib, wrong = reassign_wrong(
            ia, ib, fb.det.boxes.shape[0], o.matching.wrong_match_rate, rng
        )
        if ia.size < o.matching.min_boxes:
            return PairResult(a, b, ia, ib, wrong, 0, 0, None, None, "unmatched")
        # KP input: the matched keypoints inside the ROIs (paper, Sec. 3.1): inside a matched
        # box pair ("matched"; with kp_boxes, only the pairs sharing the most matches: matches
        # concentrate on the most textured region), or inside any box of each image ("boxes")
        if o.matching.kp_source == "matched":
            inside = keypoints_in_matched_boxes(
                m.uv_a, m.uv_b, fa.det.boxes, fb.det.boxes, ia, ib, o.matching.kp_boxes
            )
        else:
            inside = (
                boxes_contain(fa.det.boxes, m.uv_a).any(1)
                & boxes_contain(fb.det.boxes, m.uv_b).any(1)
            )
        p1, p2 = m.uv_a[inside], m.uv_b[inside]
        # BB input: centres of the matched boxes
        ca, cb = box_centres(fa.det.boxes[ia]), box_centres(fb.det.boxes[ib])
        cv_seed = int(stream_seed(self.seed, self.scene_name, "ransac", a, b).generate_state(1)[0])
        q = o.pose
        kp = five_point(
            p1, p2, self.K, q.kp_threshold, q.ransac_prob, q.max_iters, cv_seed, q.method
        )
        bb = five_point(
            ca, cb, self.K, q.bb_threshold, q.ransac_prob, q.max_iters, cv_seed, q.method
        )
        status = (
            "edge"
            if kp is not None and bb is not None
            else ("kp_failed" if kp is None else "bb_failed")
        )
        return PairResult(
            a, b, ia, ib, wrong, int(p1.shape[0]), int(m.outlier[inside].sum()), kp, bb, status
        )
