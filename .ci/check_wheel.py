"""Release checks for CI (issue 54): what the built distributions contain, and
the README's Python snippets run against an installed eqsmooth.

    python .ci/check_wheel.py WHEEL [SDIST]   # contents of the wheel (and sdist)
    python .ci/check_wheel.py --readme README.md   # run its ```python blocks

The wheel must be the library alone: `eqsmooth/` and its `.dist-info/`, with
`py.typed`, and no module that finds data beside its own file or runs git (both
belong to the experiments, which run from a checkout). The sdist must carry
the experiments and tests for a source build, but not `results/`. Exits
non-zero with every problem listed.
"""

import re
import sys
import tarfile
import zipfile
from pathlib import Path


# Source text that means "data next to this file" or "ask git": fine in the
# experiments, wrong in an installed library.
_DATA_PATH = re.compile(r"Path\(__file__\)|dirname\(__file__\)|shared/data")
_GIT = re.compile(r"""["']git["']""")


def check_wheel(wheel: Path) -> tuple[list[str], str]:
    """Problems with `wheel`'s contents, and a summary of what was checked."""
    name, version = wheel.name.split("-")[:2]
    allowed = (f"{name}/", f"{name}-{version}.dist-info/")
    problems = []
    with zipfile.ZipFile(wheel) as zf:
        entries = zf.namelist()
        outside = [e for e in entries if not e.startswith(allowed)]
        if outside:
            problems.append(
                f"{len(outside)} entries outside {' and '.join(allowed)}, "
                f"e.g. {', '.join(outside[:5])}"
            )
        if f"{name}/py.typed" not in entries:
            problems.append(f"{name}/py.typed is missing")
        sources = [e for e in entries if e.endswith(".py")]
        for entry in sources:
            text = zf.read(entry).decode()
            if m := _DATA_PATH.search(text):
                problems.append(f"{entry} finds data by file path ({m.group()!r})")
            if "subprocess" in text and _GIT.search(text):
                problems.append(f"{entry} runs git (subprocess and 'git')")
    summary = (
        f"wheel {wheel.name}: {len(entries)} entries under {' and '.join(allowed)}, "
        f"py.typed present, {len(sources)} .py files without __file__ data paths "
        "or git"
    )
    return problems, summary


def check_sdist(sdist: Path) -> tuple[list[str], str]:
    """Problems with `sdist`'s contents, and a summary of what was checked."""
    with tarfile.open(sdist) as tf:
        # Entries are "eqsmooth-0.2.0/<path>"; drop that first component.
        paths = [n.partition("/")[2] for n in tf.getnames()]
    problems = []
    for wanted in ("experiments/", "tests/", "pyproject.toml"):
        if not any(p == wanted or p.startswith(wanted) for p in paths):
            problems.append(f"sdist lacks {wanted}")
    for unwanted in ("results/", ".venv/", ".ci-venv/"):
        found = [p for p in paths if p.startswith(unwanted)]
        if found:
            problems.append(
                f"sdist holds {len(found)} entries under {unwanted}, e.g. {found[0]}"
            )
    summary = (
        f"sdist {sdist.name}: {len(paths)} entries, experiments/ tests/ "
        "pyproject.toml present, no results/"
    )
    return problems, summary


def run_readme(readme: Path) -> str:
    """Run each ```python block of `readme` in its own namespace (as
    tests/test_readme.py extracts them); a summary."""
    blocks = re.findall(r"```python\n(.*?)```", readme.read_text(), re.S)
    if not blocks:
        raise SystemExit(f"no ```python blocks in {readme}")
    for i, block in enumerate(blocks):
        exec(compile(block, f"{readme.name}:block{i}", "exec"), {})
    import eqsmooth

    return f"README: {len(blocks)} python blocks ran against {eqsmooth.__file__}"


def main(argv: list[str]) -> int:
    if len(argv) == 2 and argv[0] == "--readme":
        print(run_readme(Path(argv[1])))
        return 0
    if not 1 <= len(argv) <= 2 or argv[0].startswith("-"):
        print(__doc__, file=sys.stderr)
        return 2
    problems, summary = check_wheel(Path(argv[0]))
    summaries = [summary]
    if len(argv) == 2:
        sdist_problems, summary = check_sdist(Path(argv[1]))
        problems += sdist_problems
        summaries.append(summary)
    if problems:
        print("release check FAILED:", *problems, sep="\n  ", file=sys.stderr)
        return 1
    print("; ".join(summaries))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
