"""Seven indoor scenes named after 7-Scenes: rooms with furniture and tens of cuboid objects.

Each preset gives a room, the volume the handheld camera moves in (the extents 7-Scenes reports
for its scenes), how much furniture and how many objects of which size, and the number of train
and test sequences of the real dataset. :func:`build_scene` turns a preset into geometry:
cuboids (centre, half extents, yaw) and textured keypoints on their surfaces, on the floor and on
the walls.

World frame: x across the room, y into the room (the cameras mostly look along +y), z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import rotation_z
from .config import KeypointOptions

__all__ = ["SCENE_PRESETS", "Scene", "ScenePreset", "build_scene"]

FURNITURE, OBJECT, STEP = 0, 1, 2


@dataclass(frozen=True)
class ScenePreset:
    """Layout parameters of one scene (sizes in metres).

    The camera moves in the ``capture`` volume (the extents 7-Scenes reports for the scene) and
    looks at the content zone ``focus`` (width, depth) ahead of it, where the furniture and most
    objects stand, like the desk, kitchen counter or staircase a 7-Scenes sequence films.
    """

    name: str
    capture: tuple[float, float, float]  # extents of the camera-centre volume (x, y, z)
    focus: tuple[float, float]  # width (x) and depth (y) of the content zone
    height: float  # room height
    tables: int
    shelves: int
    objects: int
    object_size: tuple[float, float]  # min / max edge length of objects
    texture: float  # keypoint density multiplier (stairs: plain surfaces)
    train_sequences: int
    test_sequences: int
    length: float = 1.0  # sequence length relative to 1000 frames (stairs: 500)
    steps: int = 0  # a staircase of this many steps

    @property
    def room(self) -> tuple[float, float, float]:
        """Room size: camera volume, a gap, the content zone and space for wall shelves."""
        W = max(self.capture[0], self.focus[0]) + 1.2
        D = _NEAR_GAP + self.capture[1] + _FOCUS_GAP + self.focus[1] + 0.6
        return (W, D, self.height)


_NEAR_GAP, _FOCUS_GAP = 0.45, 0.5  # wall to camera volume, camera volume to content zone

# Sequence counts follow 7-Scenes' train/test split; capture volumes its published extents.
SCENE_PRESETS: dict[str, ScenePreset] = {
    "chess": ScenePreset("chess", (3.0, 2.0, 1.0), (2.6, 1.6), 2.6, 2, 2, 32,
                         (0.08, 0.45), 1.0, 4, 2),
    "fire": ScenePreset("fire", (2.5, 1.0, 1.0), (2.4, 1.4), 2.6, 1, 2, 34,
                        (0.1, 0.5), 1.2, 2, 2),
    "heads": ScenePreset("heads", (2.0, 0.5, 1.0), (1.8, 1.0), 2.5, 2, 1, 30,
                         (0.08, 0.35), 1.8, 1, 1),
    "office": ScenePreset("office", (2.5, 2.0, 1.5), (3.0, 2.0), 2.7, 3, 3, 42,
                          (0.08, 0.5), 1.0, 6, 4),
    "pumpkin": ScenePreset("pumpkin", (2.5, 2.0, 1.0), (2.6, 1.8), 2.7, 2, 2, 30,
                           (0.1, 0.55), 0.9, 4, 2),
    "redkitchen": ScenePreset("redkitchen", (4.0, 3.0, 1.5), (4.4, 1.8), 2.7, 3, 4, 56,
                              (0.08, 0.5), 1.0, 7, 5),
    "stairs": ScenePreset("stairs", (2.5, 2.0, 1.5), (2.0, 2.8), 3.5, 0, 1, 16,
                          (0.15, 0.6), 0.6, 4, 2, length=0.5, steps=10),
}  # fmt: skip


@dataclass
class Scene:
    """Scene geometry. Cuboids ``(O, ...)``; keypoints ``(P, ...)`` with their owner cuboid."""

    name: str
    room: np.ndarray  # (3,)
    capture_lo: np.ndarray  # (3,) corner of the camera-centre volume
    capture_hi: np.ndarray  # (3,)
    centre: np.ndarray  # (O, 3)
    half: np.ndarray  # (O, 3) half extents in the cuboid frame
    yaw: np.ndarray  # (O,) rotation about z
    kind: np.ndarray  # (O,) FURNITURE / OBJECT / STEP
    kp_xyz: np.ndarray  # (P, 3)
    kp_normal: np.ndarray  # (P, 3) outward surface normal
    kp_owner: np.ndarray  # (P,) cuboid index, -1 for floor and walls
    kp_twin: np.ndarray  # (P,) same-looking keypoint on the twin object, -1 if none
    twin_of: np.ndarray  # (O,) original of a copied object, -1 for originals

    @property
    def num_objects(self) -> int:
        return int(self.centre.shape[0])

    @property
    def rotation(self) -> np.ndarray:
        """Cuboid-to-world rotations ``(O, 3, 3)``."""
        return rotation_z(self.yaw)


# --------------------------------------------------------------------------- placement


def _footprint(centre: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    """Axis-aligned 2D bounds ``[x1, y1, x2, y2]`` of a yawed box footprint."""
    c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
    ex = c * half[0] + s * half[1]
    ey = s * half[0] + c * half[1]
    return np.array([centre[0] - ex, centre[1] - ey, centre[0] + ex, centre[1] + ey])


def _overlaps(fp: np.ndarray, others: list[np.ndarray], gap: float) -> bool:
    for o in others:
        if fp[0] < o[2] + gap and o[0] < fp[2] + gap and fp[1] < o[3] + gap and o[1] < fp[3] + gap:
            return True
    return False


class _Builder:
    """Collects cuboids; keeps footprints per support surface to avoid interpenetration."""

    def __init__(self) -> None:
        self.centre: list[np.ndarray] = []
        self.half: list[np.ndarray] = []
        self.yaw: list[float] = []
        self.kind: list[int] = []
        self.twin_of: list[int] = []

    def add(
        self, centre: np.ndarray, half: np.ndarray, yaw: float, kind: int, twin_of: int = -1
    ) -> int:
        self.centre.append(np.asarray(centre, float))
        self.half.append(np.asarray(half, float))
        self.yaw.append(float(yaw))
        self.kind.append(kind)
        self.twin_of.append(twin_of)
        return len(self.centre) - 1


def _inside(fp: np.ndarray, W: float, D: float) -> bool:
    return fp[0] >= 0 and fp[1] >= 0 and fp[2] <= W and fp[3] <= D


def _place_furniture(
    pre: ScenePreset,
    rng: np.random.Generator,
    b: _Builder,
    keepout: np.ndarray,
    focus: np.ndarray,
    floor_fps: list[np.ndarray],
) -> list[int]:
    """Tables in the content zone, shelves against the walls around it; returns the supports."""
    W, D, _ = pre.room
    supports: list[int] = []
    for kind_name, count in (("table", pre.tables), ("shelf", pre.shelves)):
        for _ in range(count):
            for _try in range(300):
                if kind_name == "table":
                    half = np.array(
                        [rng.uniform(0.4, 0.8), rng.uniform(0.3, 0.45), rng.uniform(0.36, 0.39)]
                    )
                    yaw = rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.05)
                    xy = rng.uniform(focus[:2], focus[2:])
                else:
                    half = np.array(
                        [rng.uniform(0.3, 0.6), rng.uniform(0.17, 0.25), rng.uniform(0.4, 0.95)]
                    )
                    wall = rng.integers(3)  # back wall (far y), left or right wall
                    if wall == 0:
                        yaw = 0.0
                        xy = np.array([rng.uniform(focus[0], focus[2]), D - half[1]])
                    else:
                        yaw = np.pi / 2
                        x = half[1] if wall == 1 else W - half[1]
                        xy = np.array([x, rng.uniform(focus[1], D - half[0])])
                centre = np.array([xy[0], xy[1], half[2]])
                fp = _footprint(centre, half, yaw)
                if not _inside(fp, W, D):
                    continue
                if _overlaps(fp, [keepout], 0.25) or _overlaps(fp, floor_fps, 0.1):
                    continue
                floor_fps.append(fp)
                supports.append(b.add(centre, half, yaw, FURNITURE))
                break
    return supports


def _place_steps(pre: ScenePreset, b: _Builder, focus: np.ndarray) -> None:
    """A straight staircase rising along +y through the content zone (stacked solid blocks)."""
    W, D, _ = pre.room
    rise, width = 0.18, 1.1
    run = (D - focus[1]) / pre.steps
    for k in range(pre.steps):
        h = (k + 1) * rise
        b.add(
            np.array([W / 2, focus[1] + (k + 0.5) * run, h / 2]),
            np.array([width / 2, run / 2, h / 2]),
            0.0,
            STEP,
        )


def _place_objects(
    pre: ScenePreset,
    rng: np.random.Generator,
    b: _Builder,
    supports: list[int],
    keepout: np.ndarray,
    focus: np.ndarray,
    floor_fps: list[np.ndarray],
    twin_fraction: float,
) -> None:
    """Objects on tables, shelves and steps, and on the floor of the content zone.

    A ``twin_fraction`` of the objects are copies of an earlier object (same size and texture),
    the repeated structures that make keypoint matchers confuse objects.
    """
    W, D, _ = pre.room
    lo, hi = pre.object_size
    on_support: dict[int, list[np.ndarray]] = {s: [] for s in supports}
    for _ in range(pre.objects):
        originals = [
            i
            for i, (k, t) in enumerate(zip(b.kind, b.twin_of, strict=True))
            if k == OBJECT and t < 0
        ]
        twin = (
            int(originals[rng.integers(len(originals))])
            if originals and rng.random() < twin_fraction
            else -1
        )
        for _try in range(100):
            dims = np.exp(rng.uniform(np.log(lo), np.log(hi), size=3))
            half = dims / 2 if twin < 0 else b.half[twin]
            yaw = rng.uniform(-np.pi, np.pi)
            use_support = supports and rng.random() < 0.7
            if use_support:
                s = supports[int(rng.integers(len(supports)))]
                sc, sh, syaw = b.centre[s], b.half[s], b.yaw[s]
                local = rng.uniform(-sh[:2] + 0.03, sh[:2] - 0.03)
                xy = sc[:2] + rotation_z(np.array(syaw))[:2, :2] @ local
                centre = np.array([xy[0], xy[1], sc[2] + sh[2] + half[2]])
                fp = _footprint(centre, half, yaw)
                top = _footprint(sc, sh, syaw)
                # centre of mass on the support; no overlap with other objects on it
                if _overlaps(fp, on_support[s], 0.01) or not (
                    top[0] <= xy[0] <= top[2] and top[1] <= xy[1] <= top[3]
                ):
                    continue
                on_support[s].append(fp)
            else:
                xy = rng.uniform(focus[:2] - 0.3, focus[2:] + 0.3)
                centre = np.array([xy[0], xy[1], half[2]])
                fp = _footprint(centre, half, yaw)
                if not _inside(fp, W, D):
                    continue
                if _overlaps(fp, [keepout], 0.3) or _overlaps(fp, floor_fps, 0.02):
                    continue
                floor_fps.append(fp)
            b.add(centre, half, yaw, OBJECT, twin)
            break


# --------------------------------------------------------------------------- keypoints


def _face_points(
    half: np.ndarray, density: float, cap: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Random points on the 5 visible faces (not the bottom) of one cuboid, in its frame.

    ``half (3,)``, ``density`` per m^2 -> local points and normals ``(P, 3)``.
    """
    # faces: (axis, sign); the bottom face (z, -1) rests on a support
    faces = [(0, -1), (0, 1), (1, -1), (1, 1), (2, 1)]
    areas = np.array([4 * half[(a + 1) % 3] * half[(a + 2) % 3] for a, _ in faces])
    counts = rng.poisson(areas * density)
    counts = np.floor(counts * min(1.0, cap / max(counts.sum(), 1))).astype(np.int64)
    axis = np.repeat([a for a, _ in faces], counts)
    sign = np.repeat([float(s) for _, s in faces], counts)
    u = rng.uniform(-1, 1, size=(axis.size, 3))
    rows = np.arange(axis.size)
    u[rows, axis] = sign
    normal = np.zeros((axis.size, 3))
    normal[rows, axis] = sign
    return u * half, normal


def _object_points(
    centre: np.ndarray,
    half: np.ndarray,
    yaw: np.ndarray,
    density: np.ndarray,
    twin_of: np.ndarray,
    cap: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, ...]:
    """Keypoints of all cuboids: points, normals, owners ``(P,)`` and twin keypoints ``(P,)``.

    A twin copies its original's texture (same local points), and the two keypoint sets point
    at each other through ``twin`` (-1 for keypoints without a twin).
    """
    R = rotation_z(yaw)
    local: list[tuple[np.ndarray, np.ndarray]] = []
    start = [0]
    for i in range(centre.shape[0]):
        local.append(
            local[twin_of[i]]
            if twin_of[i] >= 0
            else _face_points(half[i], float(density[i]), cap, rng)
        )
        start.append(start[-1] + local[-1][0].shape[0])
    P = start[-1]
    if P == 0:
        z = np.zeros((0, 3))
        return z, z.copy(), np.zeros(0, np.int64), np.zeros(0, np.int64)
    pts = np.concatenate([p @ R[i].T + centre[i] for i, (p, _) in enumerate(local)])
    nrm = np.concatenate([n @ R[i].T for i, (_, n) in enumerate(local)])
    own = np.repeat(np.arange(centre.shape[0]), np.diff(start))
    twin = np.full(P, -1, np.int64)
    for i, j in enumerate(twin_of):
        if j >= 0:
            twin[start[i] : start[i + 1]] = np.arange(start[j], start[j + 1])
            twin[start[j] : start[j + 1]] = np.arange(start[i], start[i + 1])
    return pts, nrm, own, twin


def _room_points(
    room: np.ndarray, density: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Sparse texture on the floor and the four walls."""
    W, D, H = room
    planes = [  # (origin, u axis, v axis, extent u, extent v, normal)
        (np.array([0, 0, 0.0]), np.array([1, 0, 0.0]), np.array([0, 1, 0.0]), W, D, [0, 0, 1]),
        (np.array([0, 0, 0.0]), np.array([1, 0, 0.0]), np.array([0, 0, 1.0]), W, H, [0, 1, 0]),
        (np.array([0, D, 0.0]), np.array([1, 0, 0.0]), np.array([0, 0, 1.0]), W, H, [0, -1, 0]),
        (np.array([0, 0, 0.0]), np.array([0, 1, 0.0]), np.array([0, 0, 1.0]), D, H, [1, 0, 0]),
        (np.array([W, 0, 0.0]), np.array([0, 1, 0.0]), np.array([0, 0, 1.0]), D, H, [-1, 0, 0]),
    ]
    pts, nrm = [], []
    for o, u, v, eu, ev, n in planes:
        k = rng.poisson(density * eu * ev)
        a = rng.uniform(0, eu, size=(k, 1))
        c = rng.uniform(0, ev, size=(k, 1))
        pts.append(o + a * u + c * v)
        nrm.append(np.broadcast_to(np.asarray(n, float), (k, 3)))
    return np.concatenate(pts), np.concatenate(nrm)


# --------------------------------------------------------------------------- public


def build_scene(
    name: str, rng: np.random.Generator, keypoints: KeypointOptions | None = None
) -> Scene:
    """Geometry of the preset ``name`` drawn from ``rng`` (deterministic given the stream)."""
    if name not in SCENE_PRESETS:
        raise ValueError(f"unknown scene {name!r}; choose from {sorted(SCENE_PRESETS)}")
    kpo = keypoints or KeypointOptions()
    pre = SCENE_PRESETS[name]
    room = np.asarray(pre.room, float)
    cap = np.asarray(pre.capture, float)
    # Camera volume near the near wall, centred in x, at standing height; content zone ahead.
    cap_c = np.array([room[0] / 2, _NEAR_GAP + cap[1] / 2, 1.45])
    cap_lo, cap_hi = cap_c - cap / 2, cap_c + cap / 2
    cap_lo[2], cap_hi[2] = max(cap_lo[2], 0.8), min(cap_hi[2], room[2] - 0.3)
    keepout = np.array([cap_lo[0], cap_lo[1], cap_hi[0], cap_hi[1]])
    fy = cap_hi[1] + _FOCUS_GAP
    focus = np.array(
        [room[0] / 2 - pre.focus[0] / 2, fy, room[0] / 2 + pre.focus[0] / 2, fy + pre.focus[1]]
    )

    b = _Builder()
    floor_fps: list[np.ndarray] = []
    if pre.steps:
        _place_steps(pre, b, focus)
        floor_fps.extend(
            _footprint(c, h, y) for c, h, y in zip(b.centre, b.half, b.yaw, strict=True)
        )
    supports = _place_furniture(pre, rng, b, keepout, focus, floor_fps)
    if pre.steps:  # objects stand on the steps too
        supports = supports + [i for i, k in enumerate(b.kind) if k == STEP]
    _place_objects(pre, rng, b, supports, keepout, focus, floor_fps, kpo.twin_fraction)

    centre, half = np.stack(b.centre), np.stack(b.half)
    yaw, kind = np.asarray(b.yaw), np.asarray(b.kind, np.int64)
    twin_of = np.asarray(b.twin_of, np.int64)
    dens = np.where(kind == OBJECT, kpo.density, kpo.furniture_density) * pre.texture
    kp, kn, ko, kt = _object_points(centre, half, yaw, dens, twin_of, kpo.max_per_object, rng)
    rp, rn = _room_points(room, kpo.background_density * pre.texture, rng)
    return Scene(
        name=name,
        room=room,
        capture_lo=cap_lo,
        capture_hi=cap_hi,
        centre=centre,
        half=half,
        yaw=yaw,
        kind=kind,
        kp_xyz=np.concatenate((kp, rp)),
        kp_normal=np.concatenate((kn, rn)),
        kp_owner=np.concatenate((ko, np.full(len(rp), -1, np.int64))),
        kp_twin=np.concatenate((kt, np.full(len(rp), -1, np.int64))),
        twin_of=twin_of,
    )
