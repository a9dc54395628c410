"""Shared helper of the hostile-input tests (tests/test_hostile_*.py)."""

import contextlib

import pytest


@contextlib.contextmanager
def raises(exc_type, *fragments):
    """Expect exactly `exc_type` (not a subclass) whose message contains every
    fragment: the factor, field, shape, file:line or argument at fault."""
    with pytest.raises(BaseException) as info:
        yield info
    err = info.value
    assert type(err) is exc_type, (
        f"expected {exc_type.__name__}, got {type(err)!r}: {err}"
    )
    text = str(err)
    for fragment in fragments:
        assert fragment in text, f"{fragment!r} not in the message: {text}"
