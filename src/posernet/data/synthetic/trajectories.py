"""Handheld camera sequences: smooth, slow motion at standing height, looking at the objects.

A sequence is a random walk of waypoints inside the scene's capture volume (7-Scenes extents),
each paired with a look-at target on an object ahead of the camera; a cubic spline through the
waypoints gives the smooth path and a little hand shake is added on top. Sequences are split into
train and test like 7-Scenes, and the tail of every training sequence is held out for
validation (so validation images are never test images).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from .camera import look_at
from .config import SequenceOptions
from .scenes import OBJECT, SCENE_PRESETS, Scene

__all__ = ["FramePool", "Sequence", "frame_pools", "make_sequences"]


@dataclass
class Sequence:
    """One recorded sequence: world-to-camera poses ``(F, 4, 4)`` and centres ``(F, 3)``."""

    index: int
    split: str  # "train" / "test" (7-Scenes split)
    w2c: np.ndarray
    centres: np.ndarray


@dataclass
class FramePool:
    """Frames of one split: global frame ids (into the scene's concatenated sequences)."""

    split: str
    frames: np.ndarray  # (F,) int64


def _smooth_noise(
    rng: np.random.Generator,
    t: np.ndarray,
    dims: int,
    amp: float,
    freqs: tuple[float, ...] = (0.7, 1.3, 2.9),
) -> np.ndarray:
    """Sum of sinusoids with random phases: band-limited jitter ``(len(t), dims)``."""
    out = np.zeros((t.size, dims))
    for f in freqs:
        phase = rng.uniform(0, 2 * np.pi, size=dims)
        out += np.sin(2 * np.pi * f * t[:, None] + phase) * amp / len(freqs) ** 0.5
    return out


def _targets_ahead(scene: Scene) -> np.ndarray:
    """Centres of the objects worth looking at: ahead of the camera volume."""
    ahead = (scene.centre[:, 1] > scene.capture_hi[1]) & (scene.kind == OBJECT)
    pts = scene.centre[ahead]
    return pts if len(pts) else scene.centre


def _one_sequence(
    scene: Scene, opts: SequenceOptions, frames: int, duration: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = scene.capture_lo, scene.capture_hi
    targets = _targets_ahead(scene)
    n_way = int(np.ceil(duration / opts.waypoint_s)) + 2
    step = opts.speed * opts.waypoint_s
    pos = np.empty((n_way, 3))
    look = np.empty((n_way, 3))
    pos[0] = rng.uniform(lo, hi)
    for k in range(n_way):
        if k:
            d = rng.normal(0, 1, 3) * np.array([1.0, 1.0, 0.3])
            p = pos[k - 1] + step * d / max(np.linalg.norm(d), 1e-9)
            # reflect at the volume's walls so the walk stays inside
            p = np.where(p < lo, 2 * lo - p, p)
            p = np.where(p > hi, 2 * hi - p, p)
            pos[k] = np.clip(p, lo, hi)
        for _try in range(20):
            tgt = targets[rng.integers(len(targets))] + rng.normal(0, 0.15, 3)
            if np.linalg.norm(tgt[:2] - pos[k, :2]) > 0.6:
                break
        else:  # everything is too close: look ahead along +y
            tgt = pos[k] + np.array([0.0, 1.5, -0.5])
        look[k] = tgt
    tk = np.linspace(0, duration, n_way)
    t = np.linspace(0, duration, frames)
    centres = np.clip(CubicSpline(tk, pos)(t), lo, hi)
    tgts = CubicSpline(tk, look)(t)
    centres = centres + _smooth_noise(rng, t, 3, opts.shake_m)
    # gaze jitter: move the look-at point by the hand-shake angle at the target distance
    dist = np.linalg.norm(tgts - centres, axis=1, keepdims=True)
    tgts = tgts + _smooth_noise(rng, t, 3, np.deg2rad(opts.shake_deg)) * dist
    # keep the gaze away from the vertical (look_at is undefined there)
    flat = np.linalg.norm(tgts[:, :2] - centres[:, :2], axis=1) < 0.3
    if flat.any():
        tgts[flat, 1] = centres[flat, 1] + 0.3
    roll = _smooth_noise(rng, t, 1, np.deg2rad(3.0), freqs=(0.11, 0.23))[:, 0]
    return look_at(centres, tgts, roll), centres


def make_sequences(scene: Scene, opts: SequenceOptions, rng: np.random.Generator) -> list[Sequence]:
    """All sequences of a scene (train ones first), with the 7-Scenes sequence counts."""
    pre = SCENE_PRESETS[scene.name]
    counts = {"train": pre.train_sequences, "test": pre.test_sequences}
    if opts.max_sequences is not None:
        counts = {k: min(v, opts.max_sequences) for k, v in counts.items()}
    frames = max(round(opts.frames_per_sequence * pre.length), 2)
    duration = opts.duration_s * pre.length
    seqs: list[Sequence] = []
    for split in ("train", "test"):
        for _ in range(counts[split]):
            w2c, c = _one_sequence(scene, opts, frames, duration, rng)
            seqs.append(Sequence(index=len(seqs), split=split, w2c=w2c, centres=c))
    return seqs


def frame_pools(sequences: list[Sequence], val_fraction: float) -> dict[str, FramePool]:
    """Frame ids per split: train (heads of training sequences), val (their tails), test."""
    pools: dict[str, list[np.ndarray]] = {"train": [], "val": [], "test": []}
    start = 0
    for s in sequences:
        n = s.w2c.shape[0]
        ids = np.arange(start, start + n)
        if s.split == "test":
            pools["test"].append(ids)
        else:
            n_val = round(n * val_fraction)
            pools["train"].append(ids[: n - n_val])
            pools["val"].append(ids[n - n_val :])
        start += n
    return {
        k: FramePool(k, np.concatenate(v) if v else np.zeros(0, np.int64)) for k, v in pools.items()
    }
