"""``python -m posernet.experiments --scale quick|medium|paper --out DIR [--only table1,loo]``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from .runner import EXPERIMENTS, SCALES, parse_only, run_experiments

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m posernet.experiments",
        description="Run the PoserNet paper's experiments and write paper-layout tables "
                    "(DIR/<experiment>/table.md|.csv) and DIR/summary.md with wall times.")
    p.add_argument("--scale", choices=list(SCALES), default="quick",
                   help="quick: tiny synthetic data, 1-2 epochs (minutes on a CPU); "
                        "medium: the 'paper' preset with a tenth of its small graphs, the "
                        "paper's seeds and epochs (about an hour on 2 cores); "
                        "paper: the 'paper' preset, 3 seeds, the paper's epochs")
    p.add_argument("--out", required=True,
                   help="output folder (reruns reuse its data/models; several processes may "
                        "run different --only subsets into one folder at once)")
    p.add_argument("--only", default=None,
                   help=f"comma-separated subset of: {','.join(EXPERIMENTS)} (default: all)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (1 is fastest for small graphs; 0: torch default)")
    p.add_argument("--workers", type=int, default=2,
                   help="processes generating the synthetic dataset (first run only)")
    p.add_argument("--jobs", type=int, default=1,
                   help="train the models the experiments need first, this many processes at "
                        "a time (several can share one GPU); 1: train each when first needed")
    p.add_argument("--train-only", action="store_true",
                   help="stop after training the models (evaluate later, e.g. elsewhere)")
    p.add_argument("--data", default=None,
                   help="an existing dataset directory (posernet-make-data) instead of "
                        "generating the scale's dataset into OUT/data")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status (1 when an experiment failed or bad arguments)."""
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        names = parse_only(args.only)
    except ValueError as exc:
        parser.error(str(exc))
    try:
        status = run_experiments(args.scale, args.out, only=names, device=args.device,
                                 num_threads=args.threads or None, workers=args.workers,
                                 jobs=args.jobs, train_only=args.train_only, data=args.data)
    except (ValueError, FileNotFoundError) as exc:
        print(f"posernet.experiments: error: {exc}", file=sys.stderr)
        return 1
    return 0 if all(s["ok"] for s in status.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
