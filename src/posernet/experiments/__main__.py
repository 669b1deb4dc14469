"""``python -m posernet.experiments --scale quick|medium|paper --out DIR [--only table1,loo]``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from .models import EXPERIMENTS, parse_only, scale_names

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m posernet.experiments",
        description="Run the PoserNet paper's experiments: generate the scale's dataset, train "
                    "the models with posernet-train Hydra multiruns (into DIR/models), then "
                    "write paper-layout tables (DIR/<experiment>/table.md|.csv) and "
                    "DIR/summary.md.")
    p.add_argument("--scale", choices=scale_names(), default="quick",
                   help="conf/scale/<name>.yaml. quick: tiny synthetic data, 1-2 epochs "
                        "(minutes on a CPU); medium: the 'paper' preset with a tenth of its "
                        "small graphs, the paper's seeds and epochs (about an hour on 2 cores); "
                        "paper: the 'paper' preset, 3 seeds, the paper's epochs")
    p.add_argument("--out", required=True,
                   help="output folder (a rerun reuses its data and finished models, and "
                        "resumes interrupted ones)")
    p.add_argument("--only", default=None,
                   help=f"comma-separated subset of: {','.join(EXPERIMENTS)} (default: all)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads per training job (1 is fastest for small graphs; "
                        "0: torch default)")
    p.add_argument("--workers", type=int, default=2,
                   help="processes generating the synthetic dataset (first run only)")
    p.add_argument("--jobs", type=int, default=1,
                   help="training jobs at a time (the joblib launcher's n_jobs; several can "
                        "share one GPU)")
    p.add_argument("--launcher", default=None,
                   choices=["basic", "joblib", "submitit_local", "submitit_slurm"],
                   help="Hydra launcher plugin of the training multiruns (default: joblib when "
                        "--jobs > 1 and installed, else basic)")
    p.add_argument("--hydra", action="append", default=[], metavar="OVERRIDE",
                   help="extra override of every training multirun, e.g. "
                        "hydra.launcher.partition=gpu (repeat)")
    p.add_argument("--train-only", action="store_true",
                   help="stop after training the models (collect the tables later)")
    p.add_argument("--collect-only", action="store_true",
                   help="train nothing: tables from the models in DIR/models (trained "
                        "elsewhere, e.g. on a cluster)")
    p.add_argument("--data", default=None,
                   help="an existing dataset directory (posernet-make-data) instead of "
                        "generating the scale's dataset into OUT/data")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status (1 when an experiment failed or bad arguments)."""
    from .collect import run_experiments

    parser = _parser()
    args = parser.parse_args(argv)
    try:
        names = parse_only(args.only)
    except ValueError as exc:
        parser.error(str(exc))
    try:
        status = run_experiments(args.scale, args.out, only=names, device=args.device,
                                 num_threads=args.threads or None, workers=args.workers,
                                 jobs=args.jobs, launcher=args.launcher, hydra=args.hydra,
                                 train_only=args.train_only, collect_only=args.collect_only,
                                 data=args.data)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"posernet.experiments: error: {exc}", file=sys.stderr)
        return 1
    return 0 if all(s["ok"] for s in status.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
