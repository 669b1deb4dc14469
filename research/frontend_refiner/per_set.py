"""Per real set, the paper's protocol: absolute rotation after ``rotation_translation`` (the
default averaging; uniform and confidence-weighted start) of KP and BB input, refined by the
shipped front-end checkpoint or not (median over the set's test graphs).

``python research/frontend_refiner/per_set.py /tmp/realdata_redkitchen /tmp/realdata_fountain
/tmp/realdata_herzjesu`` (the data: ``README.md``, "Real test sets")."""

from __future__ import annotations

import glob
import sys

import torch

from posernet.checkpoints import resolve_checkpoint
from posernet.evaluation import evaluate_result
from posernet.graph import load_graphs
from posernet.guard import load_refiner
from posernet.refinement import refine_graphs
from posernet.sync import get_backend


def main(folders: list[str]) -> None:
    torch.set_num_threads(2)
    model, _ = load_refiner(resolve_checkpoint("shipped:posernet_frontend_kp.ckpt"))
    for d in folders:
        graphs = [g for f in sorted(glob.glob(f"{d}/small/test/*.pt")) for g in load_graphs(f)]
        for inp in ("bb", "kp"):
            inputs = [g.with_estimate(inp) for g in graphs]
            for weighted in (False, True):
                res = refine_graphs(model, inputs, backend=get_backend("rotation_translation"),
                                    progress=False, weighted=weighted)
                absolute = evaluate_result(res)["absolute"]
                a0, a1 = absolute["initial"]["rot"].median, absolute["refined"]["rot"].median
                weights = "confidence" if weighted else "uniform"
                print(f"{d.split('_')[-1]:12s} {inp} {weights:10s} graphs {len(inputs)}: "
                      f"{a0:.2f} -> {a1:.2f}  ratio {a1 / a0:.2f}")


if __name__ == "__main__":
    main(sys.argv[1:])
