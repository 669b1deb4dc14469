"""Offline renderer: synthetic scenes written in the exact 7-Scenes dataset layout.

The geometry is the simulator's (:func:`posernet.data.synthetic.scenes.build_scene`: a closed
room and tens of cuboids). Images are ray cast in pure numpy, vectorised over pixels: every
pixel ray is intersected with the room box and with each cuboid (restricted to the cuboid's
projected screen rectangle), the nearest hit wins. Surfaces carry procedural textures defined in
their own face coordinates (so they are consistent across views), shaded by a ceiling point
light, a fill light and ambient light (Lambertian, no shadows).

Output, for ``ROOT/<scene>``::

    TrainSplit.txt, TestSplit.txt          "sequence1", ... (sequence N -> folder seq-0N)
    seq-01/frame-000000.color.png          8-bit RGB
    seq-01/frame-000000.depth.png          uint16 millimetres, 65535 = invalid
    seq-01/frame-000000.pose.txt           4x4 camera-to-world
    objects.json                           ground-truth boxes (``posernet-boxes`` format)
    render.json                            render settings (size, intrinsics, seed, frames)

Camera convention: world-to-camera ``x_cam = R X + t``, OpenCV axes (x right, y down, z
forward); pose.txt stores the inverse (camera-to-world), like 7-Scenes.
"""

from __future__ import annotations

import colorsys
import json
import os
import re
import string
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.interpolate import CubicSpline
from tqdm.auto import tqdm

from posernet.io import atomic_path, atomic_write_json, atomic_write_text

from ..frontend.proposals import BOXES_FORMAT, BOXES_VERSION
from .degrade import Degradation
from .synthetic.camera import cuboid_corners, look_at
from .synthetic.scenes import FURNITURE, OBJECT, SCENE_PRESETS, STEP, Scene, build_scene
from .synthetic.seeding import make_rng

__all__ = [
    "RENDER_FORMAT",
    "RenderedView",
    "Renderer",
    "make_trajectory",
    "object_ring_scene",
    "read_render_info",
    "render_intrinsics",
    "render_object_ring",
    "render_sevenscenes",
]

RENDER_FORMAT = "posernet-render"
DEPTH_INVALID = 65535  # 7-Scenes marks missing depth with 65535
_NEAR = 1e-3  # hits closer than this (m) are ignored
_MIN_PX_640 = 200  # an object needs this many visible pixels at 640x480 to get a box

# Texture resolution in metres per texel, and the largest texture side.
_OBJ_TEXEL, _OBJ_MAX = 0.0025, 512
_ROOM_TEXEL, _ROOM_MAX = 0.008, 1024

# Face f = 2 * axis + (sign > 0). Texture coordinates on a face seen from outside:
# (u axis, u sign, v axis, v sign); u runs to the viewer's right, v downwards on side faces,
# so marks are upright and not mirrored. u = u_sign * p[u_axis] + h[u_axis] (same for v).
_FACE_UV = np.array(
    [
        [1, -1, 2, -1],  # -x
        [1, 1, 2, -1],  # +x
        [0, 1, 2, -1],  # -y
        [0, -1, 2, -1],  # +y
        [0, 1, 1, 1],  # -z (bottom)
        [0, 1, 1, -1],  # +z (top)
    ]
)


# --------------------------------------------------------------------------- textures


def _noise(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> np.ndarray:
    """Smooth value noise ``(h, w)`` float32, unit std, feature size ``cell`` texels."""
    h, w = shape
    gh, gw = max(int(np.ceil(h / cell)) + 2, 2), max(int(np.ceil(w / cell)) + 2, 2)
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    out = cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
    return out / max(float(out.std()), 1e-6)


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0), 1), min(max(v, 0), 1)), np.float32)


def _tex_size(extent: float, texel: float, cap: int) -> int:
    return int(np.clip(round(extent / texel), 4, cap))


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _c(colour: np.ndarray, gain: float = 1.0) -> tuple[int, ...]:
    """An RGB colour in [0, 1] as the 0-255 tuple cv2's drawing functions take."""
    return tuple(int(np.clip(round(float(x) * gain * 255), 0, 255)) for x in colour)


@dataclass(frozen=True)
class _Palette:
    """Colours of one object: base, alternate, accent and ink ``(3,)`` RGB in [0, 1]."""

    base: np.ndarray
    alt: np.ndarray
    accent: np.ndarray
    ink: np.ndarray


def _radii(
    rng: np.random.Generator, ppm: float, a: tuple[float, float], b: tuple[float, float]
) -> tuple[int, int]:
    """Random ellipse half axes in texels, drawn in metres from the ranges ``a`` and ``b``."""
    return (max(1, int(rng.uniform(*a) * ppm)), max(1, int(rng.uniform(*b) * ppm)))


def _object_palette(hue: float, rng: np.random.Generator) -> _Palette:
    s, v = rng.uniform(0.5, 0.9), rng.uniform(0.5, 0.92)
    ink_v = 0.12 if v > 0.55 else 0.95
    return _Palette(
        base=_hsv(hue, s, v),
        alt=_hsv(hue + rng.uniform(-0.06, 0.06), s * rng.uniform(0.5, 1.0), v * 0.75),
        accent=_hsv(hue + rng.uniform(0.3, 0.7), rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0)),
        ink=_hsv(hue + rng.uniform(-0.1, 0.1), 0.3, ink_v),
    )


def _furniture_palette(rng: np.random.Generator) -> _Palette:
    if rng.random() < 0.6:  # wood
        hue, s, v = rng.uniform(0.05, 0.1), rng.uniform(0.35, 0.6), rng.uniform(0.35, 0.65)
    else:  # painted
        hue, s, v = rng.uniform(0, 1), rng.uniform(0.05, 0.3), rng.uniform(0.3, 0.8)
    return _Palette(
        base=_hsv(hue, s, v),
        alt=_hsv(hue, s * 0.9, v * 0.8),
        accent=_hsv(hue, s, v * 0.55),
        ink=_hsv(hue, s * 0.5, v * 0.4),
    )


def _draw_text(
    img: np.ndarray, rng: np.random.Generator, colour: np.ndarray, letter_px: float, lines: int
) -> None:
    """Lines of random capitals (or word blocks where letters would be too small)."""
    h, w = img.shape[:2]
    col = _c(colour)
    for _ in range(lines):
        x = int(rng.uniform(0, 0.4) * w)
        y = int(rng.uniform(letter_px, max(h - 2, letter_px + 1)))
        n = int(rng.integers(3, 12))
        if letter_px >= 6:
            scale = letter_px / 22.0  # HERSHEY_SIMPLEX capitals are ~22 px high at scale 1
            text = "".join(rng.choice(list(string.ascii_uppercase + string.digits + " "), n))
            thick = max(1, round(scale * 2.2))
            cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, col, thick, cv2.LINE_AA)
        else:  # "words": short dark blocks on a line
            hgt = max(1, round(letter_px * 0.8))
            for _w in range(n):
                wl = max(1, round(letter_px * rng.uniform(1.0, 4.0)))
                cv2.rectangle(img, (x, y - hgt), (x + wl, y), col, -1)
                x += wl + max(1, round(letter_px * 0.8))


def _object_face_texture(
    pal: _Palette, size_m: tuple[float, float], rng: np.random.Generator, furniture: bool
) -> np.ndarray:
    """Texture ``(nv, nu, 3)`` uint8 of a ``size_m = (u, v)`` metre face of a cuboid."""
    nu, nv = (_tex_size(s, _OBJ_TEXEL, _OBJ_MAX) for s in size_m)
    ppm = np.array([nu / size_m[0], nv / size_m[1]]).mean()  # texels per metre
    shape = (nv, nu)
    if furniture:  # wood grain: noise stretched along u, a few darker streaks
        g = _noise(rng, (nv, max(nu // 8, 2)), 0.01 * ppm)
        g = cv2.resize(g, (nu, nv), interpolation=cv2.INTER_LINEAR)
        mix = 0.5 + 0.25 * g + 0.1 * _noise(rng, shape, 0.05 * ppm)
        img = pal.base * (1 - mix[..., None]) + pal.alt * mix[..., None]
        img *= (1 + 0.05 * _noise(rng, shape, 0.004 * ppm))[..., None]
        img = _to_u8(img)
        for _ in range(rng.poisson(3 * size_m[0] * size_m[1]) + 1):  # knots / stains
            c = (int(rng.uniform(0, nu)), int(rng.uniform(0, nv)))
            r = _radii(rng, ppm, (0.01, 0.04), (0.004, 0.01))
            cv2.ellipse(img, c, r, 0, 0, 360, _c(pal.accent), -1, cv2.LINE_AA)
        return img
    # soft patches of base / alternate colour, brightness noise at three scales
    mix = np.clip(0.5 + 0.6 * _noise(rng, shape, 0.05 * ppm), 0, 1)[..., None]
    img = pal.base * (1 - mix) + pal.alt * mix
    bright = 1 + 0.08 * _noise(rng, shape, 0.015 * ppm) + 0.04 * _noise(rng, shape, 0.004 * ppm)
    img = _to_u8(img * bright[..., None])
    colours = [pal.accent, pal.ink, pal.alt * 0.6, np.ones(3, np.float32) * 0.95]
    if rng.random() < 0.5:  # stripes across the face
        for _ in range(int(rng.integers(1, 4))):
            wpx = max(1, int(rng.uniform(0.005, 0.03) * ppm))
            col = _c(colours[int(rng.integers(len(colours)))])
            if rng.random() < 0.5:
                y = int(rng.uniform(0, nv))
                cv2.rectangle(img, (0, y), (nu, y + wpx), col, -1)
            else:
                x = int(rng.uniform(0, nu))
                cv2.rectangle(img, (x, 0), (x + wpx, nv), col, -1)
    area = size_m[0] * size_m[1]
    for _ in range(int(rng.poisson(area * 150)) + 2):  # blobs and rectangles
        col = _c(colours[int(rng.integers(len(colours)))])
        c = (int(rng.uniform(0, nu)), int(rng.uniform(0, nv)))
        r = _radii(rng, ppm, (0.004, 0.025), (0.004, 0.025))
        if rng.random() < 0.6:
            ang = float(rng.uniform(0, 180))
            cv2.ellipse(img, c, r, ang, 0, 360, col, -1, cv2.LINE_AA)
        else:
            cv2.rectangle(img, (c[0] - r[0], c[1] - r[1]), (c[0] + r[0], c[1] + r[1]), col, -1)
    letter_px = rng.uniform(0.008, 0.02) * ppm
    lines = int(np.clip(size_m[1] / (rng.uniform(0.008, 0.02) * 4), 1, 12))
    _draw_text(img, rng, pal.ink, letter_px, lines)
    return img


def _room_texture(
    kind: str, size_m: tuple[float, float], colour: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Low-contrast texture ``(nv, nu, 3)`` uint8 of a wall, the floor or the ceiling."""
    nu, nv = (_tex_size(s, _ROOM_TEXEL, _ROOM_MAX) for s in size_m)
    ppm = np.array([nu / size_m[0], nv / size_m[1]]).mean()
    shape = (nv, nu)
    if kind == "floor":  # planks along v (into the room), each with its own tone and grain
        plank = max(2, int(rng.uniform(0.12, 0.2) * ppm))
        cols = np.arange(nu) // plank
        tone = 1 + 0.09 * rng.standard_normal(cols.max() + 1).astype(np.float32)
        grain = _noise(rng, (max(nv // 10, 2), nu), 0.006 * ppm)
        grain = cv2.resize(grain, (nu, nv), interpolation=cv2.INTER_LINEAR)
        bright = tone[cols][None, :] * (1 + 0.05 * grain + 0.04 * _noise(rng, shape, 0.3 * ppm))
        bright[:, (np.arange(nu) % plank) == 0] *= 0.75  # seams
        img = colour * bright[..., None]
        # plank ends at random places
        for p in range(cols.max() + 1):
            for y in rng.uniform(0, nv, size=2).astype(int):
                img[y : y + 1, p * plank : (p + 1) * plank] *= 0.8
    else:
        amp = 0.02 if kind == "ceiling" else 0.045
        bright = 1 + amp * (
            _noise(rng, shape, 0.4 * ppm)
            + 0.8 * _noise(rng, shape, 0.08 * ppm)
            + 0.6 * _noise(rng, shape, 0.02 * ppm)
        )
        img = _to_u8(colour * bright[..., None])
        if kind == "wall":
            for _ in range(int(rng.poisson(4 * size_m[0] * size_m[1]))):  # faint marks
                c = (int(rng.uniform(0, nu)), int(rng.uniform(0, nv)))
                r = _radii(rng, ppm, (0.01, 0.05), (0.005, 0.03))
                f = rng.uniform(0.85, 1.1)
                ang = float(rng.uniform(0, 180))
                cv2.ellipse(img, c, r, ang, 0, 360, _c(colour, f), -1, cv2.LINE_AA)
            board = max(1, int(0.08 * ppm))  # skirting board along the bottom
            img[nv - board :] = _c(colour, 0.55)
        return img
    return _to_u8(img)


class _Textures:
    """Lazily generated textures of every face; each from its own seeded stream."""

    def __init__(self, scene: Scene, seed: int, textured_every: int = 1,
                 plain: frozenset[int] = frozenset()) -> None:
        self.scene, self.seed, self.textured_every = scene, seed, textured_every
        self.plain = plain  # cuboids drawn in one colour whatever textured_every says
        O = scene.num_objects
        rng = make_rng(seed, scene.name, "render", "palettes")
        hue0 = rng.uniform()
        self.palettes: list[_Palette] = []
        for i in range(O):
            if scene.kind[i] == OBJECT:  # golden-ratio hues: neighbours in index differ most
                self.palettes.append(_object_palette(hue0 + 0.618034 * i, rng))
            else:
                self.palettes.append(_furniture_palette(rng))
        self.wall = _hsv(rng.uniform(0, 1), rng.uniform(0.04, 0.14), rng.uniform(0.72, 0.85))
        self.floor = _hsv(rng.uniform(0.04, 0.12), rng.uniform(0.15, 0.4), rng.uniform(0.35, 0.55))
        self.ceiling = _hsv(0.1, 0.03, 0.9)
        self._cache: dict[tuple[int, int], np.ndarray] = {}

    def face(self, box: int, face: int, half: np.ndarray) -> np.ndarray:
        """Texture of ``face`` of cuboid ``box`` (``box == O`` is the room, seen from inside)."""
        key = (box, face)
        if key not in self._cache:
            ua, _, va, _ = _FACE_UV[face]
            size = (2 * float(half[ua]), 2 * float(half[va]))
            rng = make_rng(self.seed, self.scene.name, "render", "texture", box, face)
            plain = box in self.plain or (self.textured_every > 1 and (
                box == self.scene.num_objects or box % self.textured_every))
            if plain:  # low-texture scene: one colour, a 1 % brightness drift
                base = (self.wall if face < 4 else self.floor if face == 5 else self.ceiling) \
                    if box == self.scene.num_objects else self.palettes[box].base
                room = box == self.scene.num_objects
                texel, cap = (_ROOM_TEXEL, _ROOM_MAX) if room else (_OBJ_TEXEL, _OBJ_MAX)
                nu, nv = (_tex_size(s, texel, cap) for s in size)
                drift = 1 + 0.01 * _noise(rng, (nv, nu), 20.0)
                self._cache[key] = _to_u8(base * drift[..., None])
            elif box == self.scene.num_objects:
                kind = "floor" if face == 5 else "ceiling" if face == 4 else "wall"
                colour = {"floor": self.floor, "ceiling": self.ceiling}.get(kind, self.wall)
                self._cache[key] = _room_texture(kind, size, colour, rng)
            else:
                furn = self.scene.kind[box] in (FURNITURE, STEP)
                self._cache[key] = _object_face_texture(self.palettes[box], size, rng, furn)
        return self._cache[key]


def _bilinear(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Sample ``tex (h, w, 3)`` at texel coordinates ``x, y (N,)`` (clamped) -> ``(N, 3)``."""
    h, w = tex.shape[:2]
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0 = np.minimum(x.astype(np.int32), w - 2) if w > 1 else np.zeros(x.shape, np.int32)
    y0 = np.minimum(y.astype(np.int32), h - 2) if h > 1 else np.zeros(y.shape, np.int32)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    t = tex.astype(np.float32)
    top = t[y0, x0] * (1 - fx) + t[y0, x1] * fx
    bot = t[y1, x0] * (1 - fx) + t[y1, x1] * fx
    return (top * (1 - fy) + bot * fy) * np.float32(1 / 255)


# --------------------------------------------------------------------------- ray casting


@dataclass
class RenderedView:
    """One rendered frame: ``rgb (H, W, 3)`` uint8, ``depth (H, W)`` float32 z-depth in metres
    (inf where nothing was hit), ``object_id (H, W)`` int32 cuboid index, -1 for the room."""

    rgb: np.ndarray
    depth: np.ndarray
    object_id: np.ndarray


def _grid_dirs(width: int, height: int, K: np.ndarray) -> np.ndarray:
    """Camera-frame ray directions ``(H, W, 3)`` float32 with z = 1 (so ray t = z-depth)."""
    u = (np.arange(width) - K[0, 2]) / K[0, 0]
    v = (np.arange(height) - K[1, 2]) / K[1, 1]
    d = np.empty((height, width, 3), np.float32)
    d[..., 0] = u[None, :]
    d[..., 1] = v[:, None]
    d[..., 2] = 1.0
    return d


class Renderer:
    """Ray caster of one scene at one image size.

    ``supersample`` s > 1 averages s x s colour samples per pixel (anti-aliasing); depth and
    object ids always come from the pixel centres. Principal point: the image centre
    (``(320, 240)`` at 640x480, as 7-Scenes).
    """

    def __init__(
        self,
        scene: Scene,
        seed: int = 0,
        width: int = 640,
        height: int = 480,
        focal: float = 585.0,
        supersample: int = 1,
        textured_every: int = 1,
        plain: frozenset[int] = frozenset(),
    ) -> None:
        self.scene, self.width, self.height = scene, int(width), int(height)
        self.focal, self.supersample = float(focal), int(supersample)
        self.K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
        s = self.supersample
        # Sub-sample j of pixel u sits at u + (j + 0.5) / s - 0.5: the grid's own intrinsics.
        off = (s - 1) / 2
        self.K_ss = np.array(
            [[s * focal, 0, s * width / 2 + off], [0, s * focal, s * height / 2 + off], [0, 0, 1]]
        )
        self._dirs = _grid_dirs(width, height, self.K)
        self._dirs_ss = self._dirs if s == 1 else _grid_dirs(s * width, s * height, self.K_ss)
        # Boxes: the cuboids, then the room (index O) as a box seen from inside.
        O = scene.num_objects
        room = np.asarray(scene.room, float)
        self.centre = np.vstack([scene.centre, room / 2])
        self.half = np.vstack([scene.half, room / 2])
        self.R = np.concatenate([scene.rotation, np.eye(3)[None]])
        self.corners = cuboid_corners(scene.centre, scene.half, scene.rotation)  # (O, 8, 3)
        self.textures = _Textures(scene, seed, int(textured_every), frozenset(plain))
        self.num_objects = O
        # Lights: a ceiling lamp above the content and a fill light from behind the cameras.
        ahead = scene.kind == OBJECT
        focus = scene.centre[ahead].mean(0) if ahead.any() else room / 2
        self.lamp = np.array([focus[0], focus[1] - 0.5, room[2] - 0.05], np.float32)
        fill = np.array([0.35, -1.0, 0.7])
        self.fill = (fill / np.linalg.norm(fill)).astype(np.float32)

    # -- geometry

    def _cast(
        self, dirs: np.ndarray, K: np.ndarray, R: np.ndarray, C: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest hits of the rays ``dirs (h, w, 3)`` from centre ``C``: ``t (h, w)``,
        ``box (h, w)`` int16 (O = room) and ``room_face (h, w)`` int8."""
        h, w = dirs.shape[:2]
        Rf = R.astype(np.float32)
        dw = dirs @ Rf  # world directions: d_w = R^T d_c
        room = self.half[-1] * 2
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = np.where(dw > 0, room.astype(np.float32), np.float32(0))
            ta = (bound - C.astype(np.float32)) / dw
        ta = np.where(np.isfinite(ta) & (ta > 0), ta, np.inf)
        axis = ta.argmin(-1)
        t = np.take_along_axis(ta, axis[..., None], -1)[..., 0]
        room_face = (2 * axis + (np.take_along_axis(dw, axis[..., None], -1)[..., 0] > 0)).astype(
            np.int8
        )
        box = np.full((h, w), self.num_objects, np.int16)
        # cuboids: a slab test inside each one's projected rectangle
        zc = (self.corners - C) @ R.T  # (O, 8, 3) camera frame
        for i in range(self.num_objects):
            z = zc[i, :, 2]
            if (z <= _NEAR).all():
                continue
            if (z > 0.05).all():
                uv = zc[i, :, :2] / z[:, None] * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]]
                x0, y0 = np.floor(uv.min(0)).astype(int) - 1
                x1, y1 = np.ceil(uv.max(0)).astype(int) + 2
                x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
                if x0 >= x1 or y0 >= y1:
                    continue
            else:  # straddles the camera plane: test every pixel
                x0, y0, x1, y1 = 0, 0, w, h
            Ri = self.R[i]
            M = (R @ Ri).astype(np.float32)  # d_local = Ri^T R^T d_c
            o = (Ri.T @ (C - self.centre[i])).astype(np.float32)
            hf = self.half[i].astype(np.float32)
            dl = dirs[y0:y1, x0:x1] @ M
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / dl
                t1 = (-hf - o) * inv
                t2 = (hf - o) * inv
            tn = np.minimum(t1, t2).max(-1)
            tf = np.maximum(t1, t2).min(-1)
            tsub = t[y0:y1, x0:x1]
            hit = (tn <= tf) & (tn > _NEAR) & (tn < tsub)
            tsub[hit] = tn[hit]
            box[y0:y1, x0:x1][hit] = i
        return t, box, room_face

    # -- appearance

    def _shade(
        self,
        dirs: np.ndarray,
        R: np.ndarray,
        C: np.ndarray,
        t: np.ndarray,
        box: np.ndarray,
        room_face: np.ndarray,
    ) -> np.ndarray:
        """Colours ``(h, w, 3)`` float32 in [0, 1] of the hits."""
        h, w = t.shape
        N = h * w
        dw = (dirs @ R.astype(np.float32)).reshape(N, 3)
        X = C.astype(np.float32) + dw * t.reshape(N, 1)  # world hit points
        key = box.reshape(N)
        rface = room_face.reshape(N)
        colour = np.empty((N, 3), np.float32)
        normal = np.empty((N, 3), np.float32)
        order = np.argsort(key, kind="stable")  # int16 keys: radix sort
        counts = np.bincount(key, minlength=self.num_objects + 1)
        starts = np.concatenate([[0], np.cumsum(counts)])
        O = self.num_objects
        for b in np.flatnonzero(counts):
            idx = order[starts[b] : starts[b + 1]]
            Rb, hb = self.R[b].astype(np.float32), self.half[b].astype(np.float32)
            p = (X[idx] - self.centre[b].astype(np.float32)) @ Rb  # local: Rb^T (X - c)
            if b == O:
                face = rface[idx].astype(np.int64)
                tex_face = face ^ 1  # seen from inside: the opposite face's orientation
            else:
                a = np.abs(p / hb).argmax(-1)
                face = 2 * a + (np.take_along_axis(p, a[:, None], -1)[:, 0] > 0)
                tex_face = face
            for f in np.unique(face):
                sel = face == f
                pi = p[sel]
                tf = int(tex_face[sel][0])
                ua, us, va, vs = _FACE_UV[tf]
                tex = self.textures.face(int(b), tf, self.half[b])
                u = us * pi[:, ua] + hb[ua]
                v = vs * pi[:, va] + hb[va]
                nv, nu = tex.shape[:2]
                colour[idx[sel]] = _bilinear(
                    tex, u * (nu / (2 * hb[ua])) - 0.5, v * (nv / (2 * hb[va])) - 0.5
                )
                axis, sgn = int(f) // 2, 1.0 if int(f) % 2 else -1.0
                n = Rb[:, axis] * sgn * (-1.0 if b == O else 1.0)  # the room's normals point in
                normal[idx[sel]] = n
        # Lambertian: ceiling lamp with a soft falloff, fill light, ambient
        L = self.lamp - X
        dist = np.linalg.norm(L, axis=1)
        lamp = np.clip((normal * L).sum(1) / np.maximum(dist, 1e-6), 0, None)
        lamp = lamp / (1 + (dist / 3.5) ** 2)
        fill = np.clip(normal @ self.fill, 0, None)
        shade = 0.32 + 0.75 * lamp + 0.3 * fill
        return (colour * shade[:, None]).reshape(h, w, 3)

    def render(self, w2c: np.ndarray) -> RenderedView:
        """Render the camera with world-to-camera pose ``w2c (4, 4)``."""
        w2c = np.asarray(w2c, float)
        R, tvec = w2c[:3, :3], w2c[:3, 3]
        C = -R.T @ tvec
        t, box, rface = self._cast(self._dirs, self.K, R, C)
        s = self.supersample
        if s == 1:
            col = self._shade(self._dirs, R, C, t, box, rface)
        else:
            ts, bs, rs = self._cast(self._dirs_ss, self.K_ss, R, C)
            col = self._shade(self._dirs_ss, R, C, ts, bs, rs)
            col = col.reshape(self.height, s, self.width, s, 3).mean((1, 3))
        ids = box.astype(np.int32)
        ids[ids == self.num_objects] = -1
        return RenderedView(rgb=_to_u8(col), depth=t, object_id=ids)


# --------------------------------------------------------------------------- trajectories


def _wiggle(rng: np.random.Generator, n: int, dims: int, amp: float, period: float) -> np.ndarray:
    """Smooth jitter ``(n, dims)``: two sinusoids per dimension with random phases."""
    x = np.arange(n)[:, None]
    out = np.zeros((n, dims))
    for k in (1.0, 2.3):
        ph = rng.uniform(0, 2 * np.pi, dims)
        out += np.sin(2 * np.pi * x * k / period + ph) * amp / np.sqrt(2)
    return out


def make_trajectory(
    scene: Scene,
    frames: int,
    rng: np.random.Generator,
    step: float = 0.12,
    frames_per_waypoint: int = 5,
) -> np.ndarray:
    """Handheld sweep of ``frames`` world-to-camera poses ``(F, 4, 4)`` with strong overlap.

    The camera walks through the scene's capture volume (about ``step`` metres per frame) and
    keeps looking at a gaze point that drifts slowly over the objects ahead, so consecutive
    frames are ~10-15 cm and a few degrees apart and all frames see the content zone.
    """
    lo, hi = scene.capture_lo, scene.capture_hi
    ahead = (scene.kind == OBJECT) & (scene.centre[:, 1] > hi[1])
    objs = scene.centre[ahead] if ahead.any() else scene.centre
    t_lo, t_hi = objs.min(0), objs.max(0)
    n_way = max(2, int(np.ceil((frames - 1) / frames_per_waypoint)) + 1)
    pos = np.empty((n_way, 3))
    tgt = np.empty((n_way, 3))
    margin = 0.1 * (hi - lo)
    pos[0] = rng.uniform(lo + margin, hi - margin)
    tgt[0] = objs[rng.integers(len(objs))]
    for k in range(1, n_way):
        d = rng.normal(0, 1, 3) * np.array([1.0, 0.6, 0.25])
        p = pos[k - 1] + step * frames_per_waypoint * d / max(np.linalg.norm(d), 1e-9)
        p = np.where(p < lo, 2 * lo - p, p)  # reflect at the volume's faces
        pos[k] = np.clip(np.where(p > hi, 2 * hi - p, p), lo, hi)
        cand = tgt[k - 1] + rng.normal(0, 0.25, 3) * np.array([1.0, 1.0, 0.3])
        nearest = objs[np.argmin(np.linalg.norm(objs - cand, axis=1))]
        tgt[k] = np.clip(0.5 * cand + 0.5 * nearest, t_lo, t_hi)  # stay on the content
    # Spline through the waypoints, sampled at equal arc length so the speed is uniform.
    knots = np.arange(n_way, dtype=float)
    dense = np.linspace(0, n_way - 1, 64 * n_way)
    if n_way >= 3:
        path, gaze = CubicSpline(knots, pos)(dense), CubicSpline(knots, tgt)(dense)
    else:
        a = (dense / (n_way - 1))[:, None]
        path, gaze = pos[0] * (1 - a) + pos[1] * a, tgt[0] * (1 - a) + tgt[1] * a
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    at = np.linspace(0, min(arc[-1], step * (frames - 1)), frames)
    centres = np.stack([np.interp(at, arc, path[:, j]) for j in range(3)], 1)
    targets = np.stack([np.interp(at, arc, gaze[:, j]) for j in range(3)], 1)
    centres = np.clip(centres, lo, hi) + _wiggle(rng, frames, 3, 0.004, 17.0)
    # keep the gaze well away from vertical
    centres[:, 1] = np.minimum(centres[:, 1], targets[:, 1] - 0.7)
    dist = np.linalg.norm(targets - centres, axis=1, keepdims=True)
    targets = targets + _wiggle(rng, frames, 3, np.deg2rad(0.4), 13.0) * dist
    roll = _wiggle(rng, frames, 1, np.deg2rad(2.5), 29.0)[:, 0]
    return look_at(centres, targets, roll)


# --------------------------------------------------------------------------- writing


def _write_png(path: Path, img: np.ndarray) -> None:
    """Atomic ``cv2.imwrite`` (the temporary name keeps the .png extension cv2 needs)."""
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise OSError(f"cv2.imwrite failed to write {path}")


def _pose_text(T: np.ndarray) -> str:
    return "".join(" ".join(f"{x: .12e}" for x in row) + "\n" for row in T)


def _invert_rigid(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def _depth_mm(depth: np.ndarray) -> np.ndarray:
    """Metres ``(H, W)`` -> uint16 millimetres, 65535 where invalid (none hit, out of range)."""
    mm = np.round(np.where(np.isfinite(depth), depth, 0) * 1000.0)
    bad = ~np.isfinite(depth) | (mm <= 0) | (mm >= DEPTH_INVALID)
    return np.where(bad, DEPTH_INVALID, mm).astype(np.uint16)


def _boxes(ids: np.ndarray, min_px: int) -> tuple[list[list[int]], list[int]]:
    """Boxes ``[x1, y1, x2, y2]`` (x2, y2 exclusive) of object ids with >= ``min_px`` pixels."""
    boxes, oids = [], []
    ys, xs = np.nonzero(ids >= 0)
    if ys.size == 0:
        return boxes, oids
    v = ids[ys, xs]
    order = np.argsort(v, kind="stable")
    v, ys, xs = v[order], ys[order], xs[order]
    uniq, start, count = np.unique(v, return_index=True, return_counts=True)
    for o, a, n in zip(uniq, start, count, strict=True):
        if n < min_px:
            continue
        yy, xx = ys[a : a + n], xs[a : a + n]
        boxes.append([int(xx.min()), int(yy.min()), int(xx.max()) + 1, int(yy.max()) + 1])
        oids.append(int(o))
    return boxes, oids


def _boxes_json(images: dict[str, dict[str, list]]) -> str:
    """``objects.json`` text: one line per image (readable, diff-friendly, still plain JSON)."""
    head = json.dumps({"format": BOXES_FORMAT, "version": BOXES_VERSION})[:-1]
    rows = ",\n".join(f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in images.items())
    return f'{head}, "images": {{\n{rows}\n}}}}\n'


_OURS = re.compile(r"^frame-\d+\.(color\.png|depth\.png|pose\.txt)$")


def _clear_scene(folder: Path) -> None:
    """Remove what a previous render wrote (and nothing else) before overwriting: the frames
    of the folder itself (:func:`render_object_ring`) and of its ``seq-*`` folders."""
    for name in ("TrainSplit.txt", "TestSplit.txt", "objects.json", "render.json"):
        (folder / name).unlink(missing_ok=True)
    for f in folder.iterdir():
        if f.is_file() and _OURS.match(f.name):
            f.unlink()
    for seq in folder.glob("seq-*"):
        if seq.is_dir():
            for f in seq.iterdir():
                if _OURS.match(f.name):
                    f.unlink()
            if not any(seq.iterdir()):
                seq.rmdir()


def _render_folder(folder: Path, overwrite: bool) -> Path:
    """``folder``, made; one that holds files only with ``overwrite`` (a previous render's
    files are removed then, nothing else)."""
    if folder.exists() and not folder.is_dir():
        raise FileExistsError(f"{folder} exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"scene folder {folder} is not empty; pass overwrite=True to render over it"
            )
        _clear_scene(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _check_int(name: str, v: object, lo: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    return int(v)


def render_sevenscenes(
    root: str | os.PathLike[str],
    scene: str = "chess",
    seed: int = 0,
    train_sequences: int = 1,
    test_sequences: int = 1,
    frames_per_sequence: int = 16,
    width: int = 640,
    height: int = 480,
    focal: float = 585.0,
    overwrite: bool = False,
    progress: bool = True,
    *,
    name: str | None = None,
    supersample: int = 1,
    min_visible_px: int | None = None,
    degrade: Degradation | None = None,
    textured_every: int = 1,
) -> Path:
    """Render one scene into ``ROOT/<scene>`` in the 7-Scenes layout; returns the scene folder.

    ``scene`` is a preset of :data:`SCENE_PRESETS` (geometry identical to the simulator's with
    the same ``seed``); ``name`` renames the folder. Train sequences are numbered first
    (``seq-01`` ...), then test ones. Boxes in ``objects.json`` cover every cuboid with at least
    ``min_visible_px`` visible pixels (default: 200 at 640x480, scaled with the image area).
    ``degrade``: camera degradations (:class:`~posernet.data.degrade.Degradation`: an
    uncorrected lens per scene; exposure, vignetting, blur, noise and JPEG per frame) applied
    to each frame, depth and boxes warped with the pixels; what was drawn goes to
    ``render.json``. ``textured_every`` k > 1 renders a low-texture scene: plain walls, floor
    and ceiling, and only every k-th object keeps its texture (the others one colour with a
    1 % brightness drift). Same arguments give byte-identical files.
    """
    if scene not in SCENE_PRESETS:
        raise ValueError(f"unknown scene {scene!r}; choose from {sorted(SCENE_PRESETS)}")
    train_sequences = _check_int("train_sequences", train_sequences, 0)
    test_sequences = _check_int("test_sequences", test_sequences, 0)
    if train_sequences + test_sequences == 0:
        raise ValueError("render at least one sequence (train_sequences + test_sequences >= 1)")
    if train_sequences + test_sequences > 99:
        raise ValueError("at most 99 sequences (folders seq-01 .. seq-99)")
    frames_per_sequence = _check_int("frames_per_sequence", frames_per_sequence, 1)
    width, height = _check_int("width", width, 16), _check_int("height", height, 16)
    supersample = _check_int("supersample", supersample, 1)
    textured_every = _check_int("textured_every", textured_every, 1)
    seed = _check_int("seed", seed, 0)
    if not (np.isfinite(focal) and focal > 0):
        raise ValueError(f"focal must be a positive number, got {focal!r}")
    if min_visible_px is None:
        min_visible_px = max(8, round(_MIN_PX_640 * width * height / (640 * 480)))
    folder = _render_folder(Path(root) / (name or scene), overwrite)

    geometry = build_scene(scene, make_rng(seed, scene, "layout"))
    renderer = Renderer(geometry, seed, width, height, float(focal), supersample,
                        textured_every)
    lens = None if degrade is None else degrade.draw_lens(make_rng(seed, scene, "lens"))
    drawn: dict[str, dict[str, float]] = {}
    splits = ["train"] * train_sequences + ["test"] * test_sequences
    images: dict[str, dict[str, list]] = {}
    sequences: dict[str, dict[str, object]] = {}
    bar = tqdm(
        total=len(splits) * frames_per_sequence, desc=f"render {folder.name}", disable=not progress
    )
    for n, split in enumerate(splits, start=1):
        seq = f"seq-{n:02d}"
        (folder / seq).mkdir(exist_ok=True)
        w2c = make_trajectory(geometry, frames_per_sequence, make_rng(seed, scene, "render", n))
        for k in range(frames_per_sequence):
            view = renderer.render(w2c[k])
            rgb, depth, object_id = view.rgb, view.depth, view.object_id
            if degrade is not None and lens is not None:
                rgb, depth, object_id, rec = degrade.apply(
                    rgb, depth, object_id, renderer.K, lens, make_rng(seed, scene, "degrade",
                                                                       n, k))
                drawn[f"{seq}/frame-{k:06d}"] = rec
            stem = folder / seq / f"frame-{k:06d}"
            _write_png(stem.with_name(stem.name + ".color.png"), rgb[..., ::-1])
            _write_png(stem.with_name(stem.name + ".depth.png"), _depth_mm(depth))
            pose = _pose_text(_invert_rigid(w2c[k]))
            atomic_write_text(stem.with_name(stem.name + ".pose.txt"), pose)
            boxes, oids = _boxes(object_id, min_visible_px)
            images[f"{seq}/frame-{k:06d}.color.png"] = {
                "boxes": boxes,
                "scores": [1.0] * len(boxes),
                "object_ids": oids,
            }
            bar.update()
        sequences[seq] = {"split": split, "frames": frames_per_sequence}
    bar.close()
    for split, fname in (("train", "TrainSplit.txt"), ("test", "TestSplit.txt")):
        nums = [n for n, s in enumerate(splits, start=1) if s == split]
        atomic_write_text(folder / fname, "".join(f"sequence{n}\n" for n in nums))
    atomic_write_text(folder / "objects.json", _boxes_json(images))
    cx, cy = width / 2, height / 2
    info = {
        "format": RENDER_FORMAT,
        "version": 1,
        "scene": scene,
        "seed": seed,
        "width": width,
        "height": height,
        "focal": float(focal),
        "principal_point": [cx, cy],
        "intrinsics": [float(focal), float(focal), cx, cy],
        "supersample": supersample,
        "textured_every": textured_every,
        "frames_per_sequence": frames_per_sequence,
        "num_frames": len(splits) * frames_per_sequence,
        "train_sequences": train_sequences,
        "test_sequences": test_sequences,
        "sequences": sequences,
        "depth_scale": 1000.0,
        "depth_invalid": DEPTH_INVALID,
        "min_visible_px": int(min_visible_px),
        "pose": "camera-to-world",
    }
    if degrade is not None:  # the intrinsics above stay the pinhole's: the lens is uncorrected
        info["degradation"] = {"ranges": degrade.to_dict(), "k1": lens, "frames": drawn}
    atomic_write_json(folder / "render.json", info)
    return folder


def object_ring_scene(seed: int = 0, background: bool = True) -> Scene:
    """A plain cabinet-like object (a cuboid with a smaller one on top and a drawer front) in
    the middle of a 6 x 6 x 2.7 m room, for :func:`render_object_ring`. ``background``: 14
    textured boxes and furniture along the walls (the room's walls, floor and ceiling are
    textured then too); without, the room is bare."""
    rng = make_rng(seed, "object_ring", "layout")
    room = np.array([6.0, 6.0, 2.7])
    centre = [[3.0, 3.0, 0.45], [3.05, 2.98, 0.99], [3.0, 2.73, 0.3]]
    half = [[0.32, 0.26, 0.45], [0.16, 0.12, 0.09], [0.28, 0.02, 0.12]]
    kind = [FURNITURE, OBJECT, FURNITURE]
    yaw = [0.0, 0.3, 0.0]
    if background:
        for k in range(14):
            side = k % 4  # along each wall in turn
            along = rng.uniform(0.6, 5.4)
            h = rng.uniform([0.15, 0.1, 0.2], [0.5, 0.35, 0.9])
            gap = h[1] + rng.uniform(0.05, 0.3)
            x, y = [(along, gap), (6 - gap, along), (along, 6 - gap), (gap, along)][side]
            centre.append([x, y, h[2]])
            half.append(h.tolist())
            kind.append(FURNITURE if h[2] > 0.5 else OBJECT)
            yaw.append(side * np.pi / 2 + rng.normal(0, 0.1))
    O = len(centre)
    none3, none = np.zeros((0, 3)), np.zeros(0, np.int64)
    return Scene("object_ring", room, np.array([1.0, 1.0, 0.5]), np.array([5.0, 5.0, 1.8]),
                 np.array(centre), np.array(half), np.array(yaw), np.array(kind), none3, none3,
                 none, none, np.full(O, -1))


def render_object_ring(
    root: str | os.PathLike[str],
    frames: int = 24,
    radius: float = 1.5,
    camera_height: float = 1.25,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    focal: float = 585.0,
    background: bool = True,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Render a textureless object from all round: ``frames`` views on a ring of ``radius``
    metres at ``camera_height`` around the plain object of :func:`object_ring_scene`, evenly
    spaced in angle (a little jitter in position and gaze), every one looking at it. Writes
    ``frame-<k>.color.png`` and ``frame-<k>.pose.txt`` (camera-to-world) into ``root`` with
    ``render.json``; returns ``root``. The object is drawn in one colour per cuboid (a 1 %
    brightness drift); ``background``: the room and the boxes along its walls are textured
    (a plain object in an ordinary room), else the room is plain and bare."""
    frames = _check_int("frames", frames, 2)
    width, height = _check_int("width", width, 16), _check_int("height", height, 16)
    seed = _check_int("seed", seed, 0)
    for name, v in (("radius", radius), ("camera_height", camera_height), ("focal", focal)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive number, got {v!r}")
    folder = _render_folder(Path(root), overwrite)
    scene = object_ring_scene(seed, background)
    plain = frozenset(range(3)) if background else frozenset(range(scene.num_objects))
    renderer = Renderer(scene, seed, width, height, float(focal), 1,
                        1 if background else 2, plain)
    rng = make_rng(seed, "object_ring", "cameras")
    angle = 2 * np.pi * np.arange(frames) / frames + rng.normal(0, np.radians(1.0), frames)
    r = radius + rng.normal(0, 0.03, frames)
    centres = np.stack([3.0 + r * np.cos(angle), 3.0 + r * np.sin(angle),
                        camera_height + rng.normal(0, 0.03, frames)], axis=1)
    targets = np.array([3.0, 3.0, 0.55]) + rng.normal(0, 0.03, (frames, 3))
    w2c = look_at(centres, targets, rng.normal(0, np.radians(2.0), frames))
    for k in tqdm(range(frames), desc=f"render {folder.name}", disable=not progress):
        view = renderer.render(w2c[k])
        stem = folder / f"frame-{k:06d}"
        _write_png(stem.with_name(stem.name + ".color.png"), view.rgb[..., ::-1])
        atomic_write_text(stem.with_name(stem.name + ".pose.txt"),
                          _pose_text(_invert_rigid(w2c[k])))
    atomic_write_json(folder / "render.json", {
        "format": RENDER_FORMAT, "version": 1, "scene": "object_ring", "seed": seed,
        "width": width, "height": height, "focal": float(focal),
        "principal_point": [width / 2, height / 2],
        "intrinsics": [float(focal), float(focal), width / 2, height / 2],
        "frames": frames, "radius": float(radius), "camera_height": float(camera_height),
        "background": bool(background), "pose": "camera-to-world"})
    return folder


def read_render_info(scene_dir: str | os.PathLike[str]) -> dict:
    """The ``render.json`` a :func:`render_sevenscenes` call wrote into ``scene_dir``."""
    path = Path(scene_dir) / "render.json"
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"cannot read render settings {path}: {e}") from None
    if not isinstance(info, dict) or info.get("format") != RENDER_FORMAT:
        raise ValueError(f"{path} is not a {RENDER_FORMAT} file")
    return info


def render_intrinsics(scene_dir: str | os.PathLike[str]) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` a rendered scene was made with (for ``SevenScenesScene``)."""
    fx, fy, cx, cy = read_render_info(scene_dir)["intrinsics"]
    return float(fx), float(fy), float(cx), float(cy)
