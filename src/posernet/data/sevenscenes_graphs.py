"""The paper's graph datasets from real images in the 7-Scenes layout, through the front end.

What ``posernet-make-data source=sevenscenes root=DIR`` runs. Per scene:

* frames: every ``frame_step``-th frame of each sequence (7-Scenes records 1000 frames at 30 Hz;
  neighbouring frames are near-duplicates), split into train (the head of every training
  sequence), val (its tail, ``val_fraction``, like the synthetic generator) and test (the test
  sequences); ``max_frames`` optionally thins each split's pool evenly. Intrinsics default to the
  Kinect's f = 585, c = (320, 240); ground truth comes from the ``pose.txt`` files.
* small graphs (paper: 8 images): grown connected with
  :func:`~posernet.frontend.assembly.grow_connected`, candidates within ``window`` pool frames of
  a chosen one with probability ``locality``; large graphs (paper: 125 images): a random set of
  frames, no connectivity constraint (the paper accepts them as they are).

Every graph draws from its own random stream ``(seed, scene, split, size, index)`` and every
image pair's RANSAC from ``(seed, pair)`` (:func:`~posernet.frontend.pipeline.pair_seed`), so a
chunk (one ``<size>/<split>/<scene>.pt`` file) gives the same graphs whatever ran before it.
Directory layout, manifest, resume and JSON export are the dataset writer's, shared with the
synthetic generator (:mod:`posernet.data.writer`). Chunk files hold graphs and deterministic counts
only; wall times go to the manifest's ``frontend`` entry and the printed summary.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..frontend.assembly import grow_connected, is_connected
from ..frontend.images import ImageRecord
from ..frontend.pipeline import FrontendSummary, ImageFrontend
from ..graph import ViewGraph
from .layout import LARGE_SCENES, SIZES, SPLITS
from .synthetic.chunks import Chunk, add_graph_stats, empty_stats
from .synthetic.config import ConfigError, GraphCounts
from .synthetic.sampling import SamplingError
from .synthetic.seeding import make_rng
from .synthetic.summary import format_summary
from .writer import (
    check_run_options,
    finish_dataset,
    make_spec,
    prepare_output,
    resumed_chunks,
    save_chunk,
)

__all__ = [
    "FORMAT",
    "FRONTEND_GROUPS",
    "SOURCE",
    "FrontendStages",
    "ScenePools",
    "SevenScenesOptions",
    "build_chunk",
    "generate_sevenscenes",
    "make_frontend",
    "plan_sevenscenes_chunks",
    "resolve_intrinsics",
    "scene_pools",
    "sevenscenes_options",
]

SOURCE = "sevenscenes"
FORMAT = "posernet-sevenscenes-dataset"
VERSION = 1
#: the front-end stages the builder makes, each a Hydra config group of ``make_data``
FRONTEND_GROUPS: tuple[str, ...] = ("proposals", "matcher", "box_matching", "relpose")


def frontend_defaults() -> dict[str, dict[str, Any]]:
    """The default ``_target_`` config of each front-end stage, read from the shipped configs:
    the option ``make_data.yaml``'s defaults list picks in each group."""
    from omegaconf import OmegaConf

    from ..conf import config_root

    root = config_root()
    picks: dict[str, str] = {}
    for entry in OmegaConf.create(root.joinpath("make_data.yaml").read_text()).defaults:
        if OmegaConf.is_dict(entry):
            picks.update({str(k): str(v) for k, v in entry.items()})
    return {g: OmegaConf.to_container(OmegaConf.create(
                root.joinpath(g, f"{picks[g]}.yaml").read_text()), resolve=True)
            for g in FRONTEND_GROUPS}


@dataclass
class SevenScenesOptions:
    """Everything that defines a 7-Scenes graph dataset besides the seed and the front end."""

    root: str | None = None  # folder holding the scene folders (chess/, fire/, ...)
    scenes: list[str] | None = None  # None: every scene folder found under root
    intrinsics: Any = None  # None: f = 585, c = (320, 240); "fx,fy,cx,cy", a list or a file
    frame_step: int = 10  # every n-th frame of a sequence
    max_frames: int | None = None  # cap on each split's frames per scene (evenly thinned)
    val_fraction: float = 0.2  # tail of every training sequence kept for validation
    locality: float = 0.8  # chance a small-graph candidate is near a chosen frame
    window: int = 15  # "near": within this many pool frames (after frame_step) of one
    small: GraphCounts = field(default_factory=GraphCounts)
    large: GraphCounts = field(
        default_factory=lambda: GraphCounts(graph_size=125, train=1, val=0, test=1,
                                            scenes=list(LARGE_SCENES)))
    kp_top_pairs: int = 0  # KP input from the N box pairs sharing most matches (0: all)
    # "boxes" (the paper's: an edge needs box_matching.min_boxes matched boxes) or "verified"
    # (posernet-reconstruct's: every pair with verified two-view geometry, boxes or not)
    edge_rule: str = "boxes"
    max_tries_per_node: int = 100  # rejected candidates in a row before a restart
    restarts: int = 10  # attempts at one small graph before giving up
    workers: int = 1  # threads for per-image stages (read, proposals, features)
    name: str = SOURCE

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def scenes_for(self, size: str, available: Sequence[str]) -> list[str]:
        """Scenes of ``available`` that get graphs of ``size``."""
        counts: GraphCounts = getattr(self, size)
        if counts.scenes is None:
            return list(available)
        return [s for s in available if s in counts.scenes]


def _fail(path: str, msg: str) -> None:
    raise ConfigError(f"invalid option sevenscenes.{path}: {msg}")


def _int(path: str, v: Any, lo: int, none_ok: bool = False) -> None:
    if v is None and none_ok:
        return
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        _fail(path, f"must be an integer >= {lo}, got {v!r}")


def _float(path: str, v: Any, lo: float, hi: float) -> None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
            or not lo <= v <= hi:
        _fail(path, f"must be a number in [{lo}, {hi}], got {v!r}")


def _scene_list(path: str, v: Any) -> list[str] | None:
    """``None``, a list of names or a ``"chess,fire"`` string -> list of names."""
    if v is None:
        return None
    if isinstance(v, str):
        v = [s.strip() for s in v.strip("[]").split(",") if s.strip()]
    if not isinstance(v, list | tuple) or not all(isinstance(s, str) and s for s in v):
        _fail(path, f"must be a list of scene names, got {v!r}")
    if not v:
        _fail(path, "must name at least one scene")
    if len(set(v)) != len(v):
        _fail(path, f"lists a scene twice: {list(v)}")
    return list(v)


def sevenscenes_options(options: SevenScenesOptions | Mapping[str, Any]) -> SevenScenesOptions:
    """Validated options from a mapping (e.g. the ``sevenscenes`` config node) or options;
    :class:`ConfigError` naming the field otherwise."""
    from omegaconf import OmegaConf

    if OmegaConf.is_config(options):
        options = OmegaConf.to_container(options, resolve=True)  # type: ignore[assignment]
    if isinstance(options, SevenScenesOptions):
        d = options.to_dict()
    elif isinstance(options, Mapping):
        d = dict(options)
    else:
        raise ConfigError(f"sevenscenes options must be a mapping, got {type(options).__name__}")
    known = {f.name for f in dataclasses.fields(SevenScenesOptions)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ConfigError(f"unknown sevenscenes option(s) {unknown}; known: {sorted(known)}")
    counts = {}
    for size in SIZES:
        c = d.get(size)
        base = dataclasses.asdict(getattr(SevenScenesOptions(), size))
        if c is not None:
            if not isinstance(c, Mapping) or set(c) - set(base):
                _fail(size, f"must be a mapping with keys {sorted(base)}, got {c!r}")
            base.update(c)
        counts[size] = GraphCounts(**base)
    o = SevenScenesOptions(**{**d, **counts})
    if o.root is None or (isinstance(o.root, str) and not o.root.strip()):
        raise ConfigError("source=sevenscenes needs root=DIR, the folder holding the 7-Scenes "
                          "scene folders (chess/, fire/, ...)")
    o.root = str(o.root)
    o.scenes = _scene_list("scenes", o.scenes)
    _int("frame_step", o.frame_step, 1)
    _int("max_frames", o.max_frames, 2, none_ok=True)
    _float("val_fraction", o.val_fraction, 0.0, 0.9)
    _float("locality", o.locality, 0.0, 1.0)
    _int("window", o.window, 0)
    _int("kp_top_pairs", o.kp_top_pairs, 0)
    if o.edge_rule not in ("boxes", "verified"):
        _fail("edge_rule", f"must be 'boxes' or 'verified', got {o.edge_rule!r}")
    _int("max_tries_per_node", o.max_tries_per_node, 1)
    _int("restarts", o.restarts, 1)
    _int("workers", o.workers, 1)
    if not isinstance(o.name, str) or not o.name:
        _fail("name", "must be a non-empty string")
    for size in SIZES:
        c: GraphCounts = getattr(o, size)
        _int(f"{size}.graph_size", c.graph_size, 2)
        for split in SPLITS:
            _int(f"{size}.{split}", getattr(c, split), 0)
        c.scenes = _scene_list(f"{size}.scenes", c.scenes)
    if o.small.graph_size > 64:
        _fail("small.graph_size", f"small graphs are grown connected; use at most 64 images "
                                  f"(got {o.small.graph_size}); use sevenscenes.large for big ones")
    return o


# --------------------------------------------------------------------------- frames


@dataclass
class ScenePools:
    """The frames of one scene that graphs may use, as front-end records.

    ``records`` are ordered split by split (train, val, test), sequence by sequence, in time
    order, so neighbouring ids of one ``sequence`` code are neighbouring frames; ``pools[split]``
    the record ids of each split ``(P,)``; ``num_frames`` frames in the scene's sequences.
    """

    scene: str
    records: list[ImageRecord]
    sequence: np.ndarray  # (R,) int: one code per (split, sequence)
    pools: dict[str, np.ndarray]
    num_frames: int


def _thin(frames: list[Any], cap: int | None) -> list[Any]:
    """At most ``cap`` frames, evenly spread (first and last kept)."""
    if cap is None or len(frames) <= cap:
        return frames
    keep = np.unique(np.linspace(0, len(frames) - 1, cap).round().astype(int))
    return [frames[k] for k in keep]


def resolve_intrinsics(spec: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(K (3, 3), dist (D,) or None)`` from the ``intrinsics`` option: ``None`` (the 7-Scenes
    Kinect, K left to the reader), ``"fx,fy,cx,cy"``, 4 numbers, a 3x3 matrix, or a JSON / text
    file (:func:`~posernet.frontend.images.parse_intrinsics`, one entry for all images)."""
    from omegaconf import OmegaConf

    from ..frontend.images import parse_intrinsics

    if spec is None:
        return None, None
    if OmegaConf.is_config(spec):
        spec = OmegaConf.to_container(spec, resolve=True)
    if isinstance(spec, Mapping) and "images" in spec:
        raise ConfigError("intrinsics: 7-Scenes graphs use one camera for every image; give "
                          "fx,fy,cx,cy, a 3x3 matrix or a file with one entry")
    K, dist = parse_intrinsics(spec, ["*"])[0]
    return K, dist


def scene_pools(scene: Any, opts: SevenScenesOptions, dist: np.ndarray | None = None
                ) -> ScenePools:
    """Records and per-split pools of a :class:`~posernet.data.sevenscenes.SevenScenesScene`
    (reads every kept frame's pose file; errors name the file). ``dist``: lens distortion of
    every image (OpenCV order) or ``None``."""
    K = np.asarray(scene.K(), dtype=np.float64)
    parts: dict[str, list[list[Any]]] = {s: [] for s in SPLITS}
    total = 0
    for split in ("train", "test"):
        by_seq: dict[Any, list[Any]] = {}
        for f in scene.frames(split):
            by_seq.setdefault(f.sequence, []).append(f)
        for seq in by_seq.values():
            total += len(seq)
            seq = sorted(seq, key=lambda f: f.index)[:: opts.frame_step]
            if split == "test":
                parts["test"].append(seq)
                continue
            n_val = round(len(seq) * opts.val_fraction)
            parts["train"].append(seq[: len(seq) - n_val])
            parts["val"].append(seq[len(seq) - n_val :])
    records: list[ImageRecord] = []
    codes: list[int] = []
    pools: dict[str, np.ndarray] = {}
    code = 0
    for split in SPLITS:
        flat = [(k, f) for k, seq in enumerate(parts[split]) for f in seq]
        flat = _thin(flat, opts.max_frames)
        start = len(records)
        for k, f in flat:
            records.append(ImageRecord(path=Path(f.color), key=str(f.key), K=K.copy(),
                                       dist=None if dist is None else dist.copy(),
                                       c2w=np.asarray(scene.camera_to_world(f), np.float64)))
            codes.append(code + k)
        code += len(parts[split])
        pools[split] = np.arange(start, len(records), dtype=np.int64)
    return ScenePools(str(scene.name), records, np.asarray(codes, np.int64), pools, total)


def plan_sevenscenes_chunks(opts: SevenScenesOptions, scenes: Sequence[str]) -> list[Chunk]:
    """Every non-empty chunk, in a fixed order (size, split, scene)."""
    out = []
    for size in SIZES:
        counts: GraphCounts = getattr(opts, size)
        for split in SPLITS:
            n = getattr(counts, split)
            if n > 0:
                out += [Chunk(size, split, s, n, counts.graph_size)
                        for s in opts.scenes_for(size, scenes)]
    return out


def _check_pool(chunk: Chunk, pools: ScenePools, opts: SevenScenesOptions) -> None:
    have = pools.pools[chunk.split].size
    if have >= chunk.graph_size:
        return
    why = {"val": f"raise sevenscenes.val_fraction (now {opts.val_fraction}), ",
           "train": "", "test": ""}[chunk.split]
    cap = f" and sevenscenes.max_frames={opts.max_frames}" if opts.max_frames else ""
    raise SamplingError(
        f"scene {chunk.scene!r} split {chunk.split!r} has {have} images (frame_step="
        f"{opts.frame_step}{cap}), fewer than the {chunk.graph_size} a {chunk.size} graph needs; "
        f"{why}lower frame_step or sevenscenes.{chunk.size}.graph_size, or set "
        f"sevenscenes.{chunk.size}.{chunk.split}=0"
    )


# --------------------------------------------------------------------------- front end


def make_frontend(pools: ScenePools, parts: Mapping[str, Any], seed: int, opts: SevenScenesOptions
                  ) -> ImageFrontend:
    """The front end over a scene's records; ``parts`` holds built stages (``proposals``,
    ``matcher``, ``box_matching``, ``relpose``)."""
    return ImageFrontend(pools.records, parts["proposals"], parts["matcher"],
                         rules=parts["box_matching"], pose=parts["relpose"],
                         kp_top_pairs=opts.kp_top_pairs, seed=seed, workers=opts.workers,
                         edge_rule=opts.edge_rule,
                         keep_matches=False)  # thousands of pairs: keep only their results


class _Tracker:
    """Feeds a chunk's images and pairs to the front end with progress bars, and counts what
    the chunk used (whether computed now or cached by an earlier chunk of the scene)."""

    def __init__(self, fe: ImageFrontend, done_images: set[int], progress: bool,
                 desc: str) -> None:
        from tqdm.auto import tqdm

        self.fe, self.done = fe, done_images
        self.images: set[int] = set()
        self.pairs: dict[tuple[int, int], str] = {}
        self.computed_pairs = 0
        kw = {"disable": not progress, "leave": False, "dynamic_ncols": True}
        self.img_bar = tqdm(desc=f"{desc} images", unit="img", position=1, **kw)
        self.pair_bar = tqdm(desc=f"{desc} pairs", unit="pair", position=2, **kw)

    def prepare(self, ids: Sequence[int], block: int, bulk: bool = False) -> None:
        """Per-image stages for ``ids`` (threads inside each block of ``block`` images);
        ``bulk``: these are all the chunk's images (the bar gets a total)."""
        ids = [int(i) for i in ids]
        self.images.update(ids)
        todo = [i for i in dict.fromkeys(ids) if i not in self.done]
        if bulk:
            self.img_bar.reset(total=len(todo))
        for k in range(0, len(todo), block):
            part = todo[k : k + block]
            self.fe.prepare(part, progress=False)
            self.done.update(part)
            self.img_bar.update(len(part))

    def pair(self, u: int, v: int) -> bool:
        """Whether images ``u, v`` are joined by an edge (evaluated once)."""
        key = (u, v) if u < v else (v, u)
        status = self.pairs.get(key)
        if status is None:
            self.prepare(key, block=2)
            n0 = sum(self.fe.summary.pairs.values())
            r = self.fe.two_view(*key)
            computed = sum(self.fe.summary.pairs.values()) > n0
            self.computed_pairs += computed
            status = self.pairs[key] = r.status
            self.pair_bar.update(1)
        return status == "edge"

    def close(self) -> None:
        self.img_bar.close()
        self.pair_bar.close()


def _small_nodes(tr: _Tracker, pools: ScenePools, chunk: Chunk, rng: np.random.Generator,
                 opts: SevenScenesOptions) -> list[int]:
    """Record ids of small graph ``rng``: grown connected, then shuffled."""
    nodes = grow_connected(pools.pools[chunk.split], chunk.graph_size, tr.pair, rng,
                           max_tries=opts.max_tries_per_node, restarts=opts.restarts,
                           locality=opts.locality, window=opts.window, sequence=pools.sequence)
    if nodes is None:
        edges = sum(s == "edge" for s in tr.pairs.values())
        raise SamplingError(
            f"scene {chunk.scene!r} split {chunk.split!r}: could not grow a connected "
            f"{chunk.graph_size}-image graph ({len(tr.pairs)} image pairs checked, {edges} "
            f"edges among them): too few image pairs share enough matched boxes; lower "
            f"sevenscenes.small.graph_size or box_matching.min_boxes, raise "
            f"sevenscenes.locality or lower frame_step (closer frames overlap more), or set "
            f"sevenscenes.small.{chunk.split}=0"
        )
    # growth order would make node 0 the seed image and edges point "forward": shuffle
    return [nodes[k] for k in rng.permutation(len(nodes))]


def build_chunk(
    fe: ImageFrontend,
    pools: ScenePools,
    chunk: Chunk,
    opts: SevenScenesOptions,
    seed: int,
    done_images: set[int] | None = None,
    progress: bool = False,
    on_graph: Callable[[int], None] | None = None,
) -> tuple[list[ViewGraph], dict[str, Any]]:
    """The chunk's graphs and statistics (the synthetic ``simulate_chunk`` format plus
    ``frontend`` counts over the images and pairs the chunk used, and ``timing``: work done and
    wall seconds per stage in this call, which depend on what earlier chunks cached).

    ``done_images``: ids ``fe`` already prepared (shared across the chunks of a scene).
    ``on_graph(1)`` after every finished graph.
    """
    done = set() if done_images is None else done_images
    _check_pool(chunk, pools, opts)
    pool = pools.pools[chunk.split]
    desc = f"{chunk.scene} {chunk.size} {chunk.split}"
    sec0 = Counter(fe.summary.seconds)
    tr = _Tracker(fe, done, progress, desc)
    n_done0 = len(done)
    graphs: list[ViewGraph] = []
    stats = empty_stats()
    block = max(4, 4 * opts.workers)
    try:
        if chunk.size == "small":
            # touching most of the pool anyway: prepare it up front, in threads
            if chunk.count * chunk.graph_size >= pool.size:
                tr.prepare(pool.tolist(), block, bulk=True)
            plans = None
        else:
            plans = [[int(v) for v in make_rng(seed, chunk.scene, chunk.split, chunk.size,
                                               "graph", i).choice(pool, chunk.graph_size,
                                                                  replace=False)]
                     for i in range(chunk.count)]
            tr.prepare(sorted({v for p in plans for v in p}), block, bulk=True)
            tr.pair_bar.reset(total=len({(min(a, b), max(a, b)) for p in plans
                                         for k, a in enumerate(p) for b in p[k + 1:]}))
        for i in range(chunk.count):
            if plans is None:
                rng = make_rng(seed, chunk.scene, chunk.split, chunk.size, "graph", i)
                nodes = _small_nodes(tr, pools, chunk, rng, opts)
            else:
                nodes = plans[i]
            for k, a in enumerate(nodes):  # every pair through the tracker (bars, counts)
                for b in nodes[k + 1 :]:
                    tr.pair(a, b)
            meta = {
                "name": f"{chunk.scene}-{chunk.size}-{chunk.split}-{i:05d}",
                "scene": chunk.scene,
                "split": chunk.split,
                "size": chunk.size,
                "source": SOURCE,
                "seed": int(seed),
                "camera_ids": [pools.records[v].key for v in nodes],
            }
            g, s = fe.graph(nodes, meta)
            if chunk.size == "small" and not is_connected(len(nodes), g.edge_index.numpy()):
                raise SamplingError(f"graph {meta['name']!r} is not connected")  # cannot happen
            graphs.append(g)
            add_graph_stats(stats, g, s)
            if on_graph is not None:
                on_graph(1)
    finally:
        tr.close()
    used_pairs = Counter(tr.pairs.values())
    stats["scene_frames"] = int(pools.num_frames)
    stats["pool_frames"] = int(pool.size)
    stats["frontend"] = {
        "images": len(tr.images),
        "images_without_boxes": sum(int(len(fe.features(i).boxes) == 0) for i in tr.images),
        "pairs": len(tr.pairs),
        "pair_status": {k: int(used_pairs[k]) for k in sorted(used_pairs)},
    }
    secs = Counter(fe.summary.seconds)
    secs.subtract(sec0)
    stats["timing"] = {
        "images_computed": len(done) - n_done0,
        "pairs_computed": tr.computed_pairs,
        "seconds": {k: float(v) for k, v in sorted(secs.items()) if v > 0},
    }
    return graphs, stats


@dataclass(frozen=True)
class FrontendStages:
    """The front-end stages the builder runs, built (``proposals``, ``matcher``,
    ``box_matching``, ``relpose``: see :data:`FRONTEND_GROUPS`), with the plain configs they
    were built from (recorded in the manifest; a resumed run must match them).
    :func:`posernet.cli.build.frontend_stages` builds them from Hydra ``_target_`` configs."""

    built: Mapping[str, Any]
    configs: Mapping[str, Mapping[str, Any]]


# --------------------------------------------------------------------------- public


def generate_sevenscenes(
    options: SevenScenesOptions | Mapping[str, Any],
    out_dir: str | Path,
    *,
    frontend: FrontendStages,
    seed: int = 0,
    overwrite: bool = False,
    resume: bool = False,
    export_json_files: bool = False,
    progress: bool = True,
    echo: Callable[[str], None] | None = print,
) -> dict[str, Any]:
    """Write a graph dataset of a 7-Scenes-layout folder into ``out_dir``; returns the manifest.

    ``frontend``: the built stages and their configs (:class:`FrontendStages`).
    Same layout, manifest, overwrite / resume rules and ``export_json`` as the synthetic
    :func:`~posernet.data.synthetic.generate_dataset`. Everything a user can get wrong (options,
    the root folder, intrinsics, a scene) fails before anything is written.
    """
    from tqdm.auto import tqdm

    from .sevenscenes import open_sevenscenes

    opts = sevenscenes_options(options)
    check_run_options(seed, opts.workers, overwrite, resume)
    K, dist = resolve_intrinsics(opts.intrinsics)
    scenes = open_sevenscenes(opts.root, opts.scenes, K)
    names = [str(s.name) for s in scenes]
    chunks = plan_sevenscenes_chunks(opts, names)
    if not chunks:
        raise ConfigError("invalid sevenscenes options: every graph count (sevenscenes.small.* "
                          "and sevenscenes.large.* for the chosen scenes) is 0, nothing to make")
    pools = {s.name: scene_pools(s, opts, dist) for s in scenes
             if any(c.scene == s.name for c in chunks)}
    for c in chunks:
        _check_pool(c, pools[c.scene], opts)
    parts, part_cfgs = dict(frontend.built), dict(frontend.configs)
    config = opts.to_dict()
    config.pop("workers")  # threads do not change the output
    config.pop("intrinsics")  # by value below: "585,585,320,240" and a file may be the same
    config.update(root=str(Path(opts.root).resolve()), scenes=names,
                  camera={"K": scenes[0].K().tolist(),
                          "dist": None if dist is None else dist.tolist()},
                  frontend={**part_cfgs, "matcher_built": repr(parts["matcher"])})
    spec = make_spec(opts.name, seed, config, fmt=FORMAT, version=VERSION)
    root = Path(out_dir)
    prepare_output(root, spec, overwrite, resume, prefix="sevenscenes")

    t0 = time.perf_counter()
    results, todo = resumed_chunks(root, chunks, spec, resume)
    run = FrontendSummary()  # the front end's work in this run (resumed chunks: none)
    bar = tqdm(total=sum(c.count for c in todo), unit="graph", desc="make-data",
               disable=not progress or not todo, dynamic_ncols=True, position=0)
    try:
        for name in names:  # scene by scene: the front end's cache serves all its chunks
            mine = [c for c in todo if c.scene == name]
            if not mine:
                continue
            fe = make_frontend(pools[name], parts, seed, opts)
            done: set[int] = set()
            for c in mine:
                graphs, stats = build_chunk(fe, pools[name], c, opts, seed, done, progress,
                                            bar.update)
                stats.pop("timing")  # files hold reproducible numbers only
                save_chunk(root, c, graphs, stats, spec["spec_hash"])
                results[c.relpath] = stats
            run.images += len(done)
            run.images_without_boxes += fe.summary.images_without_boxes
            run.pairs.update(fe.summary.pairs)
            run.seconds.update(fe.summary.seconds)
            del fe  # features of every image: free them before the next scene
    finally:
        bar.close()
    elapsed = time.perf_counter() - t0
    manifest = finish_dataset(root, spec, chunks, results, export_json_files,
                              extra={"source": SOURCE, "frontend": run.to_dict()})
    if echo is not None:
        lines = format_summary(dict(manifest, root=str(root))).split("\n")
        lines[0] = (f"posernet 7-Scenes graph dataset {opts.name!r} from {opts.root} (seed {seed}) "
                    f"at {root}")
        echo("\n".join(lines))
        echo("front end (this run): " + "\n  ".join(run.lines()))
        echo(f"generated {sum(c.count for c in todo)} graphs in {elapsed:.1f} s "
             f"({len(todo)} of {len(chunks)} files, {opts.workers} image threads)")
    return manifest
