"""Compare two runs of one benchmark: after / before ratios per configuration.

Records are matched by their `config`; the table gives both medians, the
ratio (after / before: < 1 is faster after), the same for `compile_s` and
for any other timing both records have, and each run's load average.

    python benchmarks/before_after.py results/chain_issue13_before.json \\
        results/chain_issue13_after.json
"""

import argparse
import json
from pathlib import Path


TIMINGS = ("median_s", "compile_s", "solve_ms_per_step", "solve_compile_s")


def _records(path: Path):
    data = json.loads(path.read_text())
    return data.get("machine", {}), data["records"]


def _key(rec) -> str:
    return json.dumps(rec.get("config", {}), sort_keys=True)


def _fmt(x) -> str:
    return "" if x is None else f"{x:.4g}"


def compare(before: Path, after: Path) -> str:
    mb, rb = _records(before)
    ma, ra = _records(after)
    by_key = {_key(r): r for r in rb}
    lines = [
        f"before: git {mb.get('eqsmooth_git', mb.get('git'))}, load average at "
        f"write {mb.get('load_average')}, XLA_FLAGS "
        f"{mb.get('env', {}).get('XLA_FLAGS', '(unset)')}",
        f"after: git {ma.get('eqsmooth_git', ma.get('git'))}, load average at "
        f"write {ma.get('load_average')}, XLA_FLAGS "
        f"{ma.get('env', {}).get('XLA_FLAGS', '(unset)')}",
        "",
        "| config | timing | before | after | after / before |",
        "|---|---|---|---|---|",
    ]
    for rec in ra:
        ref = by_key.get(_key(rec))
        if ref is None:
            continue
        cfg = ", ".join(f"{k}={v}" for k, v in rec.get("config", {}).items())
        for t in TIMINGS:
            b, a = ref.get(t), rec.get(t)
            if isinstance(b, (int, float)) and isinstance(a, (int, float)) and b:
                lines.append(f"| {cfg} | {t} | {_fmt(b)} | {_fmt(a)} | {a / b:.3f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    args = parser.parse_args(argv)
    print(compare(args.before, args.after))


if __name__ == "__main__":
    main()
