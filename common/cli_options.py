"""The command-line options several ``needletrack`` commands share, each declared once:
``--quiet`` (``add_quiet``), the learned detector's weights (``add_weights``: ``--weights``, or
``--model`` where a command has always called it so), a dataset folder with ground truth and
one a command loops over (``add_dataset``), and the ``X,Y,Z`` value type (``vector3``). Imports
nothing of ``common``."""
from __future__ import annotations

import argparse

def add_quiet(p: argparse.ArgumentParser) -> None:
    """``--quiet``: no progress bars (``args.quiet``; a function's ``progress=not args.quiet``)."""
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def add_weights(p: argparse.ArgumentParser, flag: str = "--weights", learned_only: bool = False) -> None:
    """``--weights FILE`` (or ``flag``): the learned detector's weights; None (the default): the
    shipped model, which the detector's backends load for None."""
    p.add_argument(flag, dest=flag.lstrip("-").replace("-", "_"), default=None, metavar="FILE",
                   help=("learned only: " if learned_only else "")
                   + "the detector's weights file (default: the shipped model, common.detector.weights.DEFAULT_WEIGHTS)")


def add_dataset(p: argparse.ArgumentParser, looped: bool = False, what: str = "") -> None:
    """``--dataset DIR``: a folder with ground truth (required), or with ``looped`` one the command
    replays over and over (default ``data/test``, else ``data/bench`` generated once:
    ``common.evaluation.graph_speed.ensure_dataset``). ``what``: the words before the default."""
    if looped:
        p.add_argument("--dataset", metavar="DIR",
                       help=f"{what or 'dataset folder to loop over'} (default data/test, else data/bench)")
    else:
        p.add_argument("--dataset", metavar="DIR", required=True,
                       help=f"{what or 'dataset folder'} with ground truth (docs/dataset.md)")


def vector3(text: str) -> list:
    """An ``X,Y,Z`` option value: three numbers, not all zero (argparse's error otherwise)."""
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 3 or not any(v):
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z not all zero, got {text!r}")
    return v
