"""Assertion helpers shared by the test modules (pytest puts this folder on sys.path)."""

from __future__ import annotations

import pytest

from hdrplenoxels.core.errors import InputError


def raises_naming(name: str, fn, *args, contains: tuple[str, ...] = ()) -> InputError:
    """Call fn(*args); it must raise a one-line InputError that names `name` and holds every `contains`."""
    with pytest.raises(InputError) as info:
        fn(*args)
    msg = str(info.value)
    assert name in msg and "\n" not in msg, msg
    for c in contains:
        assert c in msg, msg
    return info.value
