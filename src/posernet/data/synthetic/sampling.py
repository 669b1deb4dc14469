"""Sample view graphs from a simulated scene and assemble them as :class:`ViewGraph`.

* Small graphs (paper: 8 images) must form one connected view graph: images are added one at a
  time, each candidate kept only when it has an edge to an image already in the graph (the
  paper rejects graphs with isolated nodes or components; growing them connected is the same
  constraint without the waste).
* Large graphs (paper: 125 images) are a random set of images without that constraint.

An edge exists when two images share at least ``min_boxes`` matched boxes and both 5-point
estimates (KP and BB) succeeded; pairs that matched but lost an estimate are counted as dropped.
"""

from __future__ import annotations

import numpy as np

from ...frontend.assembly import GraphStats, assemble_view_graph, grow_connected, is_connected
from ...graph import ViewGraph
from .world import SceneWorld

__all__ = ["GraphStats", "SamplingError", "build_view_graph", "sample_large", "sample_small"]


class SamplingError(RuntimeError):
    """The scene cannot provide the requested graphs (too few images or connections)."""


def _pool_of(world: SceneWorld, split: str, need: int) -> np.ndarray:
    pool = world.pools[split].frames
    if pool.size < need:
        raise SamplingError(
            f"scene {world.scene_name!r} split {split!r} has {pool.size} images, fewer than the "
            f"{need} a graph needs; raise dataset.sequences.frames_per_sequence or lower the "
            f"graph size"
        )
    return pool


def sample_small(
    world: SceneWorld,
    split: str,
    n: int,
    rng: np.random.Generator,
    locality: float = 0.0,
    window: int = 0,
) -> list[int]:
    """Frame ids of one connected ``n``-image graph from the ``split`` pool.

    Candidates are uniform over the pool, or with probability ``locality`` within ``window``
    frames of an image already chosen (same sequence): short baselines, as when a handheld
    camera pans. Raises :class:`SamplingError` when the pool cannot give a connected graph.
    """
    pool = _pool_of(world, split, n)
    nodes = grow_connected(
        pool,
        n,
        lambda u, v: world.pair(u, v).is_edge,
        rng,
        max_tries=world.options.max_tries_per_node,
        locality=locality,
        window=window,
        sequence=world.frame_sequence,
    )
    if nodes is not None:
        return nodes
    raise SamplingError(
        f"could not grow a connected {n}-image graph in scene {world.scene_name!r} split "
        f"{split!r} ({world.options.max_tries_per_node} candidates per image, 20 restarts): "
        f"too few image pairs share {world.options.matching.min_boxes} matched boxes; lower "
        f"dataset.small.graph_size or dataset.matching.min_boxes, or raise "
        f"dataset.keypoints.density"
    )


def sample_large(world: SceneWorld, split: str, n: int, rng: np.random.Generator) -> list[int]:
    """Frame ids of ``n`` random images of the ``split`` pool (no connectivity constraint)."""
    pool = _pool_of(world, split, n)
    return [int(v) for v in rng.choice(pool, size=n, replace=False)]


def build_view_graph(
    world: SceneWorld, nodes: list[int], meta: dict
) -> tuple[ViewGraph, GraphStats]:
    """Evaluate every pair of ``nodes`` (frame ids) and assemble the graph (float32) with the
    front end's :func:`~posernet.frontend.assembly.assemble_view_graph`; returns it and its
    statistics."""
    cam = world.options.camera
    g, stats = assemble_view_graph(
        nodes,
        world.pair,
        [world.frame(f).det.boxes for f in nodes],
        world.K,
        np.array([float(cam.width), float(cam.height)]),
        cam.k1,
        world.w2c[nodes],
        meta,
    )
    g.meta["frames"] = ",".join(str(f) for f in nodes)
    if meta.get("size") == "small" and not is_connected(len(nodes), g.edge_index.numpy()):
        raise SamplingError(f"graph {meta.get('name')!r} is not connected")  # cannot happen
    return g, stats
