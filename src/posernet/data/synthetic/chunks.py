"""Units of work: the graphs of one (size, split, scene), simulated in memory.

A chunk is independent of every other chunk: it rebuilds its scene from the seed and draws each
graph from its own random stream ``(seed, scene, split, size, graph index)``. Chunks can thus
run in any order, in any process, and give bit-identical graphs.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

from ...graph import ViewGraph
from ..layout import SIZES, SPLITS
from .config import ConfigError, DatasetOptions, resolve_options
from .sampling import GraphStats, build_view_graph, sample_large, sample_small
from .seeding import make_rng
from .world import SceneWorld

__all__ = ["ERROR_KEYS", "Chunk", "add_graph_stats", "empty_stats", "merge_stats", "plan_chunks",
           "simulate_chunk", "simulate_graphs", "split_chunk"]

ERROR_KEYS = ("kp_rot", "kp_tdir", "bb_rot", "bb_tdir")


@dataclass(frozen=True)
class Chunk:
    """The ``count`` graphs of ``graph_size`` images of one scene, split and size."""

    size: str
    split: str
    scene: str
    count: int
    graph_size: int

    @property
    def relpath(self) -> str:
        """Where the chunk lives in a dataset directory."""
        return f"{self.size}/{self.split}/{self.scene}.pt"

    @property
    def cost(self) -> float:
        """Rough relative run time (pairs evaluated), for scheduling big chunks first."""
        return self.count * self.graph_size * (self.graph_size - 1) / 2


def plan_chunks(options: DatasetOptions) -> list[Chunk]:
    """Every non-empty chunk of the dataset, in a fixed order (size, split, scene)."""
    out = []
    for size in SIZES:
        counts = getattr(options, size)
        for split in SPLITS:
            n = getattr(counts, split)
            if n <= 0:
                continue
            for scene in options.scenes_for(size):
                out.append(Chunk(size, split, scene, n, counts.graph_size))
    return out


def empty_stats() -> dict[str, Any]:
    """Statistics of a chunk with no graph yet (counters, per-graph ``errors`` lists)."""
    return {
        "graphs": 0, "nodes": 0, "edges": 0, "detections": 0, "matched_pairs": 0,
        "pairs_checked": 0, "image_pairs_matched": 0, "dropped_kp": 0, "dropped_bb": 0,
        "wrong_box_matches": 0, "kp_correspondences": 0, "kp_outliers": 0,
        "errors": {k: [] for k in ERROR_KEYS},
    }  # fmt: skip


def add_graph_stats(stats: dict[str, Any], g: ViewGraph, s: GraphStats) -> None:
    """Count graph ``g`` and its pair book-keeping ``s`` into chunk ``stats`` (in place)."""
    stats["graphs"] += 1
    stats["nodes"] += g.num_nodes
    stats["edges"] += g.num_edges
    stats["detections"] += g.num_dets
    stats["matched_pairs"] += g.num_pairs
    stats["pairs_checked"] += s.pairs_checked
    stats["image_pairs_matched"] += s.matched
    stats["dropped_kp"] += s.dropped_kp
    stats["dropped_bb"] += s.dropped_bb
    stats["wrong_box_matches"] += s.wrong_box_matches
    stats["kp_correspondences"] += s.kp_correspondences
    stats["kp_outliers"] += s.kp_outliers
    for k in ERROR_KEYS:
        # graphs without edges (possible for large graphs only) have nothing to measure
        stats["errors"][k].append(s.errors.get(k, float("nan")))


def simulate_chunk(
    options: DatasetOptions,
    chunk: Chunk,
    seed: int,
    progress: Callable[[int], None] | None = None,
    world: SceneWorld | None = None,
    graphs_range: range | None = None,
) -> tuple[list[ViewGraph], dict[str, Any]]:
    """Simulate the chunk's graphs; returns them (float32) and their statistics.

    ``progress(k)`` is called after every ``k`` finished graphs. Graph ``i`` is named
    ``<scene>-<size>-<split>-<i:05d>``. ``graphs_range`` simulates only those graph indices
    (a part of the chunk, for parallel workers); each graph has its own random stream, so the
    parts joined by :func:`merge_stats` and concatenation equal the whole chunk bit for bit.
    """
    world = world or SceneWorld(options, chunk.scene, seed)
    seq = options.sequences
    window = round(options.sampling.window_s * seq.frames_per_sequence / seq.duration_s)
    graphs: list[ViewGraph] = []
    stats = empty_stats()
    indices = range(chunk.count) if graphs_range is None else graphs_range
    if indices.start < 0 or indices.stop > chunk.count:
        raise ValueError(f"graphs_range {indices} is outside the chunk's "
                         f"{chunk.count} graphs")
    for i in indices:
        rng = make_rng(seed, chunk.scene, chunk.split, chunk.size, "graph", i)
        if chunk.size == "small":
            nodes = sample_small(
                world, chunk.split, chunk.graph_size, rng, options.sampling.locality, window
            )
            # growth order would make node 0 the seed image and edges point "forward": shuffle
            nodes = [nodes[k] for k in rng.permutation(len(nodes))]
        else:
            nodes = sample_large(world, chunk.split, chunk.graph_size, rng)
        meta = {
            "name": f"{chunk.scene}-{chunk.size}-{chunk.split}-{i:05d}",
            "scene": chunk.scene,
            "split": chunk.split,
            "size": chunk.size,
            "source": "posernet-synthetic",
            "seed": int(seed),
        }
        g, s = build_view_graph(world, nodes, meta)
        graphs.append(g)
        add_graph_stats(stats, g, s)
        if progress is not None:
            progress(1)
    stats["scene_frames"] = int(world.num_frames)
    stats["pool_frames"] = int(world.pools[chunk.split].frames.size)
    return graphs, stats


def merge_stats(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Statistics of a chunk from those of its consecutive parts (counts summed, per-graph
    errors concatenated in order, per-scene constants taken from the first part)."""
    if not parts:
        raise ValueError("merge_stats: no parts")
    out = dict(parts[0], errors={k: list(v) for k, v in parts[0]["errors"].items()})
    for st in parts[1:]:
        for k, v in st.items():
            if k == "errors":
                for e, vals in v.items():
                    out["errors"][e] += vals
            elif k not in ("scene_frames", "pool_frames"):
                out[k] += v
    return out


def split_chunk(chunk: Chunk, parts: int) -> list[range]:
    """``parts`` consecutive, near-equal ranges of the chunk's graph indices (fewer when the
    chunk has fewer graphs)."""
    k = max(1, min(int(parts), chunk.count))
    bounds = [chunk.count * j // k for j in range(k + 1)]
    return [range(a, b) for a, b in pairwise(bounds) if b > a]


def simulate_graphs(
    options: DatasetOptions | str | Mapping[str, Any] = "tiny",
    scene: str = "chess",
    split: str = "train",
    size: str = "small",
    count: int | None = None,
    seed: int = 0,
) -> list[ViewGraph]:
    """In-memory graphs of one scene, split and size (no files), e.g. for tests and notebooks.

    ``options``: preset name, mapping or :class:`DatasetOptions`; ``count`` defaults to the
    preset's number for that split and size (at least 1).
    """
    opts = resolve_options(options)
    if size not in SIZES:
        raise ConfigError(f"size must be one of {list(SIZES)}, got {size!r}")
    if split not in SPLITS:
        raise ConfigError(f"split must be one of {list(SPLITS)}, got {split!r}")
    if scene not in opts.scenes:
        raise ConfigError(f"scene {scene!r} is not in dataset.scenes {opts.scenes}")
    counts = getattr(opts, size)
    n = max(getattr(counts, split), 1) if count is None else int(count)
    if n < 0:
        raise ConfigError(f"count must be >= 0, got {n}")
    graphs, _ = simulate_chunk(opts, Chunk(size, split, scene, n, counts.graph_size), seed)
    return graphs
