"""The paper's own numbers (ECCV 2022 main text and supplementary), printed beside ours.

Each full row is ``(percent below 3, 5, 10, 30, 45 deg, median)`` per metric group; rows with a
standard deviation over seeds carry a second tuple. Absolute translations use the metre
thresholds 0.05, 0.1, 0.25, 0.5, 0.75. Only medians are published for the depth ablation and the
leave-one-scene-out test.
"""

from __future__ import annotations

from ..metrics import ANGLE_THRESHOLDS_DEG, METRE_THRESHOLDS, ThresholdRow
from ..report import TableRow

__all__ = [
    "DEPTH_MEDIANS",
    "LOO_MEDIANS",
    "TABLE1",
    "TABLE2",
    "TABLE3_EIG",
    "TABLE3_MULTIREG",
    "paper_row",
]

Six = tuple[float, float, float, float, float, float]
# (group key -> (mean values, std values or None))
Cells = dict[str, tuple[Six, Six | None]]

_Z: Six = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

#: Table 1 (7-Scenes, small test graphs): ``{(input, stage): cells}``.
TABLE1: dict[tuple[str, str], Cells] = {
    ("BB", "Initial"): {"rot": ((0.00, 0.00, 0.00, 0.16, 1.44, 96.48), None),
                        "tdir": ((0.00, 0.00, 0.00, 0.00, 0.00, 89.30), None)},
    ("BB", "PoserNet"): {"rot": ((0.00, 0.00, 0.74, 88.18, 99.02, 20.39),
                                 (0.00, 0.00, 0.14, 0.28, 0.02, 0.20)),
                         "tdir": ((0.00, 0.00, 0.00, 7.92, 45.63, 46.60),
                                  (0.00, 0.00, 0.00, 0.25, 0.43, 0.14))},
    ("KP", "Initial"): {"rot": ((0.74, 4.01, 11.16, 41.46, 62.53, 36.26), None),
                        "tdir": ((0.00, 0.03, 0.10, 1.37, 5.49, 87.23), None)},
    ("KP", "PoserNet"): {"rot": ((1.13, 17.24, 78.19, 98.78, 99.86, 7.31),
                                 (0.11, 0.86, 1.36, 0.02, 0.01, 0.11)),
                         "tdir": ((0.01, 1.42, 27.67, 80.07, 90.01, 14.54),
                                  (0.01, 0.28, 0.70, 0.31, 0.68, 0.14))},
}

#: Table 2 (KP): ``{(train, test): cells}``; train ``Raw`` is the initial estimate.
TABLE2: dict[tuple[str, str], Cells] = {
    ("Raw", "Small"): TABLE1[("KP", "Initial")],
    ("Small", "Small"): TABLE1[("KP", "PoserNet")],
    ("Large", "Small"): {"rot": ((0.00, 0.04, 13.26, 96.98, 99.61, 13.97),
                                 (0.00, 0.03, 5.55, 0.37, 0.09, 0.94)),
                         "tdir": ((0.00, 0.00, 0.11, 57.19, 81.26, 27.56),
                                  (0.00, 0.00, 0.10, 5.72, 1.16, 2.02))},
    ("Raw", "Large"): {"rot": ((0.00, 0.00, 0.00, 20.00, 60.00, 37.70), None),
                       "tdir": ((0.00, 0.00, 0.00, 0.00, 0.00, 79.60), None)},
    ("Small", "Large"): {"rot": ((0.00, 0.00, 80.0, 100.00, 100.00, 6.85),
                                 (0.00, 0.00, 0.00, 0.00, 0.00, 0.11)),
                         "tdir": ((0.00, 0.00, 20.00, 100.00, 100.00, 12.62),
                                  (0.00, 0.00, 0.00, 0.00, 0.00, 0.48))},
    ("Large", "Large"): {"rot": ((0.00, 0.00, 13.33, 100.00, 100.00, 12.11),
                                 (0.00, 0.00, 9.43, 0.00, 0.00, 1.10)),
                        "tdir": ((0.00, 0.00, 0.00, 100.00, 100.00, 21.58),
                                 (0.00, 0.00, 0.00, 0.00, 0.00, 1.36))},
}

#: Table 3, EIG-SE3 rows (absolute poses): ``{(stage, input): cells}``, groups rot / trans.
TABLE3_EIG: dict[tuple[str, str], Cells] = {
    ("Initial", "BB"): {"rot": ((0.00, 0.00, 0.09, 2.46, 7.84, 78.46), None),
                        "trans": ((0.00, 0.00, 0.00, 0.57, 13.47, 0.65), None)},
    ("Initial", "KP"): {"rot": ((11.99, 23.87, 34.49, 57.59, 62.09, 25.37), None),
                        "trans": ((0.00, 0.06, 2.63, 31.39, 74.40, 0.61), None)},
    ("PoserNet", "BB"): {"rot": ((0.00, 0.09, 10.36, 88.00, 94.06, 15.80), None),
                         "trans": ((0.00, 0.00, 7.54, 46.80, 83.23, 0.52), None)},
    ("PoserNet", "KP"): {"rot": ((15.56, 48.36, 82.14, 93.14, 95.69, 5.10), None),
                         "trans": ((0.04, 1.94, 34.51, 76.43, 94.49, 0.32), None)},
}

#: Table 3, MultiReg (Yew & Lee 2021) on raw and PoserNet-refined input (mean and std over
#: three runs): ``{(stage, input): cells}``. The paper prints "8,10" for the BB raw 10-degree
#: cell; read as 8.10.
TABLE3_MULTIREG: dict[tuple[str, str], Cells] = {
    ("Initial", "BB"): {"rot": ((0.60, 2.10, 8.10, 47.60, 69.13, 31.37),
                                (0.00, 0.00, 0.10, 0.53, 0.47, 0.30)),
                        "trans": ((0.50, 1.47, 6.93, 23.03, 40.80, 0.89),
                                  (0.00, 0.06, 0.12, 0.70, 0.85, 0.01))},
    ("Initial", "KP"): {"rot": ((10.23, 24.23, 39.70, 67.97, 79.90, 15.69),
                                (0.12, 0.25, 0.40, 0.06, 0.00, 0.08)),
                        "trans": ((1.00, 3.77, 17.77, 40.30, 57.23, 0.64),
                                  (0.00, 0.06, 0.12, 0.17, 0.06, 0.01))},
    ("PoserNet", "BB"): {"rot": ((0.50, 1.60, 6.10, 41.03, 62.50, 35.60),
                                 (0.00, 0.00, 0.10, 0.42, 0.14, 0.33)),
                         "trans": ((0.60, 1.50, 6.53, 21.60, 39.33, 0.91),
                                   (0.00, 0.00, 0.06, 0.00, 0.06, 0.00))},
    ("PoserNet", "KP"): {"rot": ((0.50, 1.63, 6.20, 40.90, 62.60, 35.73),
                                 (0.00, 0.06, 0.10, 0.44, 0.53, 0.37)),
                         "trans": ((0.60, 1.50, 6.40, 21.43, 39.23, 0.91),
                                   (0.00, 0.00, 0.10, 0.12, 0.12, 0.00))},
}

#: Supplementary, GNN depth ablation (KP, medians in degrees): ``{depth: (rot, tdir)}``.
DEPTH_MEDIANS: dict[int, tuple[float, float]] = {2: (7.5, 14.7), 3: (7.6, 14.9),
                                                 4: (9.4, 16.1), 5: (11.2, 17.2)}

#: Supplementary, leave-one-scene-out (KP, medians in degrees): ``{scene: (rot, tdir)}``;
#: ``median`` is the median over the seven tests, ``all`` the model trained on every scene.
LOO_MEDIANS: dict[str, tuple[float, float]] = {
    "office": (5.05, 10.59), "pumpkin": (9.93, 13.05), "redkitchen": (7.33, 16.82),
    "stairs": (9.39, 18.07), "chess": (7.27, 21.03), "fire": (8.36, 11.15),
    "heads": (8.96, 47.54), "median": (8.04, 19.75), "all": (7.31, 14.54),
}


def paper_row(labels: tuple[str, ...], cells: Cells, count: int = 7000) -> TableRow:
    """A :class:`TableRow` holding the paper's numbers (``runs=3`` when it has a std).

    ``count``: test graphs behind the row (7000 small graphs, 5 large ones).
    """
    out: dict[str, ThresholdRow] = {}
    std: dict[str, ThresholdRow] = {}
    for key, (vals, sd) in cells.items():
        ths = METRE_THRESHOLDS if key == "trans" else ANGLE_THRESHOLDS_DEG
        out[key] = ThresholdRow(tuple(ths), tuple(vals[:5]), vals[5], count)
        s = sd if sd is not None else _Z
        std[key] = ThresholdRow(tuple(ths), tuple(s[:5]), s[5], count)
    has_std = any(sd is not None for _, sd in cells.values())
    return TableRow(labels, out, std if has_std else None, runs=3 if has_std else 1)
