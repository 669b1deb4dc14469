"""Names shared by every dataset folder and its readers and writers, defined once.

A dataset folder holds ``manifest.json`` (written last: its presence means "complete"),
``.make_data.json`` (what is being generated, for resume) and one graph file per
``<size>/<split>/<scene>.pt``.
"""

from __future__ import annotations

__all__ = ["JOB_FILE", "LARGE_SCENES", "MANIFEST", "SCENES", "SIZES", "SPLITS"]

#: graph sizes (the paper's small 8-image graphs and its large ones)
SIZES: tuple[str, ...] = ("small", "large")
#: dataset splits
SPLITS: tuple[str, ...] = ("train", "val", "test")
#: the seven 7-Scenes scenes
SCENES: tuple[str, ...] = ("chess", "fire", "heads", "office", "pumpkin", "redkitchen",
                           "stairs")
#: the five scenes of the paper's large graphs
LARGE_SCENES: tuple[str, ...] = ("chess", "fire", "heads", "office", "pumpkin")
MANIFEST = "manifest.json"
JOB_FILE = ".make_data.json"
