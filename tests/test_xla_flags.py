import os

from eqsmooth._xla_flags import apply_default_xla_flags


FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"


def test_flag_added_to_existing_flags(monkeypatch):
    monkeypatch.delenv("EQSMOOTH_KEEP_XLA_FLAGS", raising=False)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false")
    apply_default_xla_flags()
    flags = os.environ["XLA_FLAGS"].split()
    assert flags == ["--xla_cpu_multi_thread_eigen=false", f"{FLAG}=false"]


def test_flag_added_when_unset(monkeypatch):
    monkeypatch.delenv("EQSMOOTH_KEEP_XLA_FLAGS", raising=False)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    apply_default_xla_flags()
    assert os.environ["XLA_FLAGS"] == f"{FLAG}=false"


def test_user_setting_kept(monkeypatch):
    monkeypatch.delenv("EQSMOOTH_KEEP_XLA_FLAGS", raising=False)
    monkeypatch.setenv("XLA_FLAGS", f"{FLAG}=true")
    apply_default_xla_flags()
    assert os.environ["XLA_FLAGS"] == f"{FLAG}=true"


def test_opt_out(monkeypatch):
    monkeypatch.setenv("EQSMOOTH_KEEP_XLA_FLAGS", "1")
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    apply_default_xla_flags()
    assert "XLA_FLAGS" not in os.environ
