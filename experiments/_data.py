"""Where the experiments read real data.

A data set's folder comes from the script's argument when one is given;
otherwise from the `EQSMOOTH_DATA` environment variable (the folder that holds
`pendulum/`, `kitti_poses/`, `cascaded_tanks/`, ...); otherwise from
`../shared/data` beside this checkout, where the project's development set-up
keeps it. The experiments run from a checkout only (they are not part of the
installed package), so the last default may follow this file's location.
"""

import os
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np


ENV = "EQSMOOTH_DATA"


def data_root() -> Path:
    """The folder holding the real data sets: `$EQSMOOTH_DATA`, or
    `../shared/data` beside the checkout."""
    if os.environ.get(ENV):
        return Path(os.environ[ENV]).expanduser()
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


def require(path: Path, what: str, source: str, option: str) -> Path:
    """`path`, or a `FileNotFoundError` that names it, says where `what`
    comes from (`source`) and how to point the script at it (`option`)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(
            f"{what} not found at {path}. It comes from {source}. Pass {option} "
            f"PATH, or set {ENV} to the folder that holds the data sets "
            "(see shared/data/README.md in the development set-up)."
        )
    return path


def load_cache(
    path: Path,
    keys: tuple[str, ...],
    check: Callable[[dict[str, np.ndarray]], None] | None = None,
) -> dict[str, np.ndarray] | None:
    """The arrays `keys` of the `.npz` cache at `path`, or None when there is
    none. A damaged cache (cut short by a kill, missing a key, or failing
    `check`, which raises a `ValueError` when the arrays are not what the
    file's name or the run promises) is only a cache: it is reported with its
    path and rebuilt, never a crash and never used."""
    if not path.exists():
        return None
    try:
        # Our own file handle: np.load leaves its own open when the zip is bad.
        with open(path, "rb") as fh, np.load(fh) as z:
            out = {k: z[k] for k in keys}
        if check is not None:
            check(out)
        return out
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as err:
        warnings.warn(
            f"{path}: damaged cache file ({type(err).__name__}: {err}); it is "
            "rebuilt (delete the file to silence this)",
            stacklevel=2,
        )
        return None


def leading_axes(shapes: dict[str, tuple[int, ...]]):
    """A `load_cache` check: array `k` must start with the axes `shapes[k]`."""

    def check(out: dict[str, np.ndarray]) -> None:
        for k, want in shapes.items():
            if out[k].shape[: len(want)] != want:
                raise ValueError(
                    f"{k} has shape {out[k].shape}, expected leading axes {want}"
                )

    return check
