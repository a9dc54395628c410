"""Which code produced a result: the commit, marked when the code differs."""

import functools
import subprocess
from pathlib import Path


@functools.cache
def git_hash() -> str:
    """The commit this process runs from, with `+dirty` when the package, the
    experiments or the example scripts have uncommitted changes (results
    written by a run do not count); "unknown" outside a git checkout.

    Read once per process: a commit made while a long run goes on does not
    describe the code that run executes.
    """
    here = Path(__file__).parent

    def git(*args):
        return subprocess.run(
            ["git", *args], capture_output=True, text=True, cwd=here, check=True
        ).stdout.strip()

    try:
        root = git("rev-parse", "--show-toplevel")
        dirty = git(
            "-C",
            root,
            "status",
            "--porcelain",
            "--",
            "eqsmooth",
            "experiments",
            "examples",
        )
        return git("rev-parse", "HEAD") + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
