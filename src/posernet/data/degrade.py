"""Camera degradations of rendered frames: what makes a photo harder than a clean render.

The renderer (:mod:`posernet.data.render`) draws ideal pinhole images. Real handheld frames
(a Kinect in 7-Scenes, a phone) differ in ways that change what the image front end finds:
exposure and white balance drift between frames, vignetting, uncorrected radial lens
distortion, defocus and motion blur, sensor noise (shot + read) and compression. A
:class:`Degradation` draws one such camera per scene (distortion) and one state per frame
(exposure, blur, noise) from its ranges and applies it to a frame: colour image, depth and the
object-id map move together under the lens warp, so boxes and depth stay consistent with the
pixels. Every draw comes from the generator it is given, so a seed reproduces a render.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np

__all__ = ["Degradation"]


@dataclass(frozen=True)
class Degradation:
    """Ranges of the per-scene and per-frame degradations (each drawn uniformly).

    Attributes:
        k1: radial distortion ``(lo, hi)`` of the scene's lens, ``x_d = x (1 + k1 r^2)`` in
            normalised coordinates; not recorded in the intrinsics, as with the uncorrected
            Kinect frames of 7-Scenes.
        exposure: log2 exposure change per frame ``(lo, hi)`` (0: as rendered).
        white_balance: largest per-channel gain change per frame (0.05: +-5 %).
        vignetting: brightness lost at the image corner ``(lo, hi)`` (0.3: 30 % darker).
        defocus: Gaussian blur sigma in pixels per frame ``(lo, hi)``.
        motion_blur: linear motion blur length in pixels per frame ``(lo, hi)``, random
            direction.
        shot_noise: shot-noise scale (std at full white, intensity 0-1) ``(lo, hi)``.
        read_noise: read-noise std (intensity 0-1) ``(lo, hi)``.
        jpeg_quality: JPEG quality per frame ``(lo, hi)``; 100 or more: no compression.
    """

    k1: tuple[float, float] = (0.0, 0.2)
    exposure: tuple[float, float] = (-0.7, 0.5)
    white_balance: float = 0.05
    vignetting: tuple[float, float] = (0.1, 0.4)
    defocus: tuple[float, float] = (0.0, 1.2)
    motion_blur: tuple[float, float] = (0.0, 6.0)
    shot_noise: tuple[float, float] = (0.01, 0.04)
    read_noise: tuple[float, float] = (0.002, 0.01)
    jpeg_quality: tuple[float, float] = (70.0, 95.0)

    def __post_init__(self) -> None:
        for name in ("k1", "exposure", "vignetting", "defocus", "motion_blur", "shot_noise",
                     "read_noise", "jpeg_quality"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
                raise ValueError(f"Degradation.{name}: need a finite range lo <= hi, got "
                                 f"{(lo, hi)}")
        for name in ("vignetting", "defocus", "motion_blur", "shot_noise", "read_noise"):
            if getattr(self, name)[0] < 0:
                raise ValueError(f"Degradation.{name}: must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.white_balance < 1:
            raise ValueError(f"Degradation.white_balance: must be in [0, 1), got "
                             f"{self.white_balance}")
        if self.vignetting[1] >= 1:
            raise ValueError(f"Degradation.vignetting: must be < 1, got {self.vignetting}")
        if self.jpeg_quality[0] < 1:
            raise ValueError(f"Degradation.jpeg_quality: must be >= 1, got {self.jpeg_quality}")

    @classmethod
    def none(cls) -> Degradation:
        """No degradation at all (a clean render through the same code path)."""
        return cls((0, 0), (0, 0), 0.0, (0, 0), (0, 0), (0, 0), (0, 0), (0, 0), (100, 100))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def draw_lens(self, rng: np.random.Generator) -> float:
        """The scene's radial distortion ``k1``."""
        return float(rng.uniform(*self.k1))

    def apply(self, rgb: np.ndarray, depth: np.ndarray, ids: np.ndarray, K: np.ndarray,
              k1: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                            dict[str, float]]:
        """Degrade one frame.

        Args:
            rgb: ``(H, W, 3)`` uint8; depth: ``(H, W)`` float (metres, inf = no hit);
            ids: ``(H, W)`` int object ids (-1: none); K: ``(3, 3)`` intrinsics of the render;
            k1: the scene's lens (:meth:`draw_lens`); rng: this frame's generator.
        Returns:
            ``(rgb, depth, ids, record)``: the degraded frame (same shapes and dtypes) and the
            values drawn for it.
        """
        h, w = rgb.shape[:2]
        rec: dict[str, float] = {"k1": k1}
        if k1 != 0.0:
            map_x, map_y = _distortion_maps(K, k1, w, h)
            rgb = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
            depth = cv2.remap(depth.astype(np.float32), map_x, map_y, cv2.INTER_NEAREST,
                              borderMode=cv2.BORDER_REPLICATE).astype(depth.dtype)
            ids = cv2.remap(ids.astype(np.float32), map_x, map_y, cv2.INTER_NEAREST,
                            borderMode=cv2.BORDER_REPLICATE).astype(ids.dtype)
        img = rgb.astype(np.float32) / 255.0
        img = img ** 2.2  # to linear light: exposure, vignetting and noise act there
        ev = float(rng.uniform(*self.exposure))
        gains = 1 + rng.uniform(-self.white_balance, self.white_balance, 3)
        img *= (2.0 ** ev) * gains.astype(np.float32)
        v = float(rng.uniform(*self.vignetting))
        if v > 0:
            yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
            r2 = ((xx - K[0, 2]) ** 2 + (yy - K[1, 2]) ** 2) / (K[0, 2] ** 2 + K[1, 2] ** 2)
            img *= (1 - v * np.clip(r2, 0, 1))[..., None]
        sigma = float(rng.uniform(*self.defocus))
        if sigma > 0.05:
            img = cv2.GaussianBlur(img, (0, 0), sigma)
        length = float(rng.uniform(*self.motion_blur))
        if length >= 1.0:
            img = cv2.filter2D(img, -1, _line_kernel(length, float(rng.uniform(0, np.pi))))
        shot, read = float(rng.uniform(*self.shot_noise)), float(rng.uniform(*self.read_noise))
        if shot > 0 or read > 0:
            std = np.sqrt(shot ** 2 * np.clip(img, 0, None) + read ** 2)
            img = img + std * rng.standard_normal(img.shape).astype(np.float32)
        img = np.clip(img, 0, 1) ** (1 / 2.2)
        out = np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)
        quality = round(float(rng.uniform(*self.jpeg_quality)))
        if quality < 100:
            ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, quality])
            if ok:
                out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        rec.update(exposure=ev, vignetting=v, defocus=sigma, motion_blur=length,
                   shot_noise=shot, read_noise=read, jpeg_quality=float(quality))
        return out, depth, ids, rec


def _distortion_maps(K: np.ndarray, k1: float, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the distorted image, where to read the pinhole render: invert
    ``x_d = x (1 + k1 r^2)`` by a few fixed-point steps (converges for the small k1 used)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    xd, yd = (xx - cx) / fx, (yy - cy) / fy
    x, y = xd.copy(), yd.copy()
    for _ in range(8):
        f = 1 + k1 * (x * x + y * y)
        x, y = xd / f, yd / f
    return (x * fx + cx).astype(np.float32), (y * fy + cy).astype(np.float32)


def _line_kernel(length: float, angle: float) -> np.ndarray:
    """A normalised line of ``length`` pixels at ``angle`` (motion blur)."""
    size = int(np.ceil(length)) | 1
    k = np.zeros((size, size), np.float32)
    c = size // 2
    d = np.array([np.cos(angle), np.sin(angle)])
    for s in np.linspace(-length / 2, length / 2, max(2, int(length * 2))):
        x, y = np.rint(c + s * d).astype(int)
        k[y, x] = 1.0
    return k / k.sum()
