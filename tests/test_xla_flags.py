import os
import subprocess
import sys

import pytest

import eqsmooth._xla_flags as xla_flags
from eqsmooth._xla_flags import set_xla_cpu_flags


FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"
FAST = "--xla_cpu_use_fusion_emitters"


def test_flag_added_to_existing_flags(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    set_xla_cpu_flags()
    flags = os.environ["XLA_FLAGS"].split()
    assert flags == ["--xla_cpu_multi_thread_eigen=false", f"{FLAG}=false"]


def test_flag_added_when_unset(monkeypatch):
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
    monkeypatch.setattr(xla_flags, "_FAST_COMPILE_FLAG", "--xla_cpu_no_such_flag=1")
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    with pytest.warns(UserWarning, match="xla_cpu_no_such_flag"):
        flags = set_xla_cpu_flags(serial_scheduler=False, fast_compile=True)
    assert flags == "--xla_cpu_multi_thread_eigen=false"
    assert os.environ["XLA_FLAGS"] == flags
