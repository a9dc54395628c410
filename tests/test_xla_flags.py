import functools
import os
import subprocess
import sys

import pytest

import eqsmooth._xla_flags as xla_flags
from eqsmooth._xla_flags import set_xla_cpu_flags


FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"
FAST = "--xla_cpu_use_fusion_emitters"


@functools.cache
def _known(flag: str) -> bool:
    return xla_flags._known_to_xla(f"{flag}=false") is None


def _require(*flags: str) -> None:
    """Skip where this jaxlib's XLA lacks a flag: XLA renames and retires its
    flags between releases, and the function then leaves them out (tested
    below with a flag no XLA knows)."""
    for flag in flags:
        if not _known(flag):
            pytest.skip(f"this jaxlib's XLA does not know {flag}")


def test_flag_added_to_existing_flags(monkeypatch):
    _require(FLAG)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    set_xla_cpu_flags()
    flags = os.environ["XLA_FLAGS"].split()
    assert flags == ["--xla_cpu_multi_thread_eigen=false", f"{FLAG}=false"]


def test_flag_added_when_unset(monkeypatch):
    _require(FLAG)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert set_xla_cpu_flags() == f"{FLAG}=false"
    assert os.environ["XLA_FLAGS"] == f"{FLAG}=false"


def test_user_setting_kept(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", f"{FLAG}=true")
    set_xla_cpu_flags()
    assert os.environ["XLA_FLAGS"] == f"{FLAG}=true"


def test_import_leaves_xla_flags_alone():
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    code = "import os, eqsmooth; print(repr(os.environ.get('XLA_FLAGS')))"
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "None"


def test_fast_compile_flag_added_when_xla_knows_it(monkeypatch):
    _require(FLAG, FAST)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    # Both flags, in order (one probe of the backend); a second call adds
    # nothing and starts no probe.
    flags = set_xla_cpu_flags(fast_compile=True)
    assert flags.split() == [f"{FLAG}=false", f"{FAST}=false"]
    monkeypatch.setattr(xla_flags, "_known_to_xla", None)  # not called again
    assert set_xla_cpu_flags(fast_compile=True) == flags


def test_flag_unknown_to_xla_is_not_added(monkeypatch):
    # XLA aborts a process whose XLA_FLAGS names a flag it does not know: the
    # probe subprocess fails and the flag is left out.
    monkeypatch.setattr(xla_flags, "FAST_COMPILE_FLAG", "--xla_cpu_no_such_flag=1")
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    with pytest.warns(UserWarning, match="xla_cpu_no_such_flag"):
        flags = set_xla_cpu_flags(serial_scheduler=False, fast_compile=True)
    assert flags == "--xla_cpu_multi_thread_eigen=false"
    assert os.environ["XLA_FLAGS"] == flags


def test_every_flag_is_probed(monkeypatch):
    _require(FAST)
    # XLA renames and retires flags between jaxlib releases; a flag the
    # running jaxlib lacks would abort the process at JAX's first
    # computation, so the scheduler flag is probed like the other.
    monkeypatch.setattr(xla_flags, "SCHEDULER_FLAG", "--xla_cpu_no_such_flag=1")
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    with pytest.warns(UserWarning, match="xla_cpu_no_such_flag"):
        flags = set_xla_cpu_flags(fast_compile=True)
    assert flags.split() == [f"{FAST}=false"]


def test_quiet_route_leaves_an_unknown_flag_out_without_a_warning(monkeypatch):
    _require(FAST)
    # `enable_compilation_cache` adds the flags this way: the cache works the
    # same without them, so nothing is said.
    import warnings

    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        flags = xla_flags.add_xla_flags(
            ["--xla_cpu_no_such_flag=1", f"{FAST}=false"], warn=False
        )
    assert flags.split() == ["--xla_cpu_multi_thread_eigen=false", f"{FAST}=false"]
