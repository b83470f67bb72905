"""Helpers shared by several test files."""

import subprocess
import sys

import pytest

from jaxstiction import LoopDataError


def raises_one_line(match, func, *args, **kwargs):
    """Call `func`; assert a one-line LoopDataError (a ValueError) matching `match`."""
    with pytest.raises(LoopDataError, match=match) as info:
        func(*args, **kwargs)
    msg = str(info.value)
    assert isinstance(info.value, ValueError)
    assert "\n" not in msg and "\r" not in msg
    return msg


def run(*args, timeout=900):
    return subprocess.run(
        [sys.executable, "-m", "jaxstiction", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
