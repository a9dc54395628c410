"""Command-line pieces that the experiments' example scripts share."""

import argparse
from pathlib import Path


def experiment_parser(
    doc: str, *, quick: str, out: str, folds: str
) -> argparse.ArgumentParser:
    """A parser described by `doc`'s first line, with the options every
    experiment script has: `--quick` (help `quick`), `--out` (default `out`)
    and `--folds` (help `folds`)."""
    p = argparse.ArgumentParser(
        description=doc.split("\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--quick", action="store_true", help=quick)
    p.add_argument("--out", type=Path, default=Path(out))
    p.add_argument("--folds", type=int, nargs="+", help=folds)
    return p
