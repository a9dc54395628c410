"""Where the experiments read real data.

A data set's folder comes from the script's argument when one is given;
otherwise from the `EQSMOOTH_DATA` environment variable (the folder that holds
`pendulum/`, `kitti_poses/`, `cascaded_tanks/`, ...); otherwise from
`../shared/data` beside this checkout, where the project's development set-up
keeps it. The experiments run from a checkout only (they are not part of the
installed package), so the last default may follow this file's location.
"""

import os
from pathlib import Path


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
