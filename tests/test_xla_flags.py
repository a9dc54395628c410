import os
import subprocess
import sys

from eqsmooth._xla_flags import set_xla_cpu_flags


FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"


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
