"""The library's sources pass the release check's source rules.

CI builds the wheel and refuses it when a library file finds data by its own
path (`Path(__file__)`, `shared/data`) or runs git (`.ci/check_wheel.py`).
This runs the same rules over the checkout's `eqsmooth/`, so a local `pytest`
catches what would otherwise fail only in CI's release step.
"""

import importlib.util
from pathlib import Path

import pytest


_ROOT = Path(__file__).resolve().parents[1]


def _check_wheel():
    path = _ROOT / ".ci" / "check_wheel.py"
    if not path.exists():
        pytest.skip(f"{path} is absent (not a development checkout)")
    spec = importlib.util.spec_from_file_location("_check_wheel", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_library_sources_pass_the_release_rules():
    rules = _check_wheel()
    sources = sorted((_ROOT / "eqsmooth").rglob("*.py"))
    assert len(sources) > 50
    problems = []
    for path in sources:
        text = path.read_text()
        name = path.relative_to(_ROOT)
        if m := rules._DATA_PATH.search(text):
            problems.append(f"{name} finds data by file path ({m.group()!r})")
        if "subprocess" in text and rules._GIT.search(text):
            problems.append(f"{name} runs git")
    assert not problems, problems


def test_the_rules_catch_a_file_path():
    rules = _check_wheel()
    assert rules._DATA_PATH.search("root = Path(__file__).parent")
    assert not rules._DATA_PATH.search('files("eqsmooth")')
