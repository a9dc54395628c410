"""Where does the test suite compile? A pytest plugin and its summary.

Every XLA compilation (JAX's `backend_compile_duration` event, with the
lowering just before it) is charged to the running test and to the innermost
two stack frames inside this repository (eqsmooth, tests, examples). Each
worker writes `PREFIX.<worker>.json`; `summarize` adds them up.

```bash
PYTHONPATH=benchmarks COMPILE_SITES_OUT=/tmp/sites \\
    python -m pytest -q -p no:cacheprovider -p pytest_compile_sites
python benchmarks/pytest_compile_sites.py /tmp/sites \\
    --json benchmarks/results/compile_sites.json
```

A "small" program is one that took under 80 ms to lower and compile: almost
always one JAX operation run op by op outside `jit` (`jit(multiply)`,
`jit(broadcast_in_dim)`, ...), which costs 20-30 ms of lowering and
compilation the first time a process meets its shapes.
"""

import argparse
import collections
import glob
import json
import os
import pathlib
import traceback


ROOT = str(pathlib.Path(__file__).resolve().parents[1]) + os.sep
SMALL_S = 0.08

_current = {"test": None, "lowering": 0.0}
_sites: dict = collections.defaultdict(lambda: [0, 0.0])


def _listener(event: str, duration: float, **kwargs) -> None:
    if event.endswith("jaxpr_to_mlir_module_duration"):
        _current["lowering"] = duration
        return
    if not event.endswith("backend_compile_duration"):
        return
    frames = []
    for frame in reversed(traceback.extract_stack()):
        if frame.filename.startswith(ROOT) and "site-packages" not in frame.filename:
            path = frame.filename[len(ROOT) :]
            if path != "benchmarks/pytest_compile_sites.py":
                frames.append(f"{path}:{frame.lineno}:{frame.name}")
        if len(frames) == 2:
            break
    key = (
        kwargs.get("fun_name", "?"),
        " <- ".join(frames),
        _current["test"] or "<outside a test>",
    )
    _sites[key][0] += 1
    _sites[key][1] += duration + _current["lowering"]
    _current["lowering"] = 0.0


# ---------------------------------------------------------------------------
# pytest hooks (active when loaded with `-p pytest_compile_sites`)


def pytest_configure(config) -> None:
    from jax import monitoring

    monitoring.register_event_duration_secs_listener(_listener)


def pytest_runtest_protocol(item, nextitem) -> None:
    _current["test"] = item.nodeid


def pytest_runtest_logfinish(nodeid, location) -> None:
    _current["test"] = None


def pytest_sessionfinish(session) -> None:
    prefix = os.environ.get("COMPILE_SITES_OUT")
    if not prefix:
        return
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    rows = [[*key, count, secs] for key, (count, secs) in _sites.items()]
    pathlib.Path(f"{prefix}.{worker}.json").write_text(json.dumps(rows))


# ---------------------------------------------------------------------------
# Summary


def summarize(prefix: str, top: int = 25) -> dict:
    rows = []
    for path in sorted(glob.glob(f"{prefix}.*.json")):
        rows += json.loads(pathlib.Path(path).read_text())
    if not rows:
        raise SystemExit(f"no {prefix}.*.json files: run pytest with the plugin first")
    small = [r for r in rows if r[4] / r[3] < SMALL_S]
    by_test: dict = collections.defaultdict(lambda: [0, 0.0])
    by_area: dict = collections.defaultdict(lambda: [0, 0.0])
    for _, frames, test, count, secs in small:
        by_test[test][0] += count
        by_test[test][1] += secs
        first = frames.split(" <- ")[0].split(":")[0]
        parts = first.split("/")
        area = "/".join(parts[:2]) if parts[0] == "eqsmooth" else parts[0]
        by_area[area][0] += count
        by_area[area][1] += secs
    out = {
        "programs": sum(r[3] for r in rows),
        "lower_and_compile_s": sum(r[4] for r in rows),
        "small_programs": sum(r[3] for r in small),
        "small_lower_and_compile_s": sum(r[4] for r in small),
        "small_by_area": dict(sorted(by_area.items(), key=lambda kv: -kv[1][1])),
        "small_by_test": dict(sorted(by_test.items(), key=lambda kv: -kv[1][1])[:top]),
    }
    print(
        f"{out['programs']} programs compiled, {out['lower_and_compile_s']:.0f} s "
        f"lowering + XLA; {out['small_programs']} small ones (< {SMALL_S * 1e3:.0f} "
        f"ms each), {out['small_lower_and_compile_s']:.0f} s"
    )
    print("small programs by the innermost repository frame:")
    for area, (count, secs) in out["small_by_area"].items():
        print(f"  {secs:7.1f} s {count:6d}  {area}")
    print(f"small programs by test (top {top}):")
    for test, (count, secs) in out["small_by_test"].items():
        print(f"  {secs:7.1f} s {count:6d}  {test}")
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("prefix", help="the COMPILE_SITES_OUT prefix of a run")
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--json", help="also write the summary here")
    args = parser.parse_args(argv)
    out = summarize(args.prefix, args.top)
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
