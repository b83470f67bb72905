import atexit
import os
import pathlib
import shutil
import tempfile

from jaxstiction._cli import _lean_compiler


# The command line's compiler flag (XLA's older CPU fusion code generator: under half
# the compile memory, and faster, which is most of this suite's time). Importing the
# package creates no JAX backend, so it still takes effect here.
_lean_compiler()

import jax  # noqa: E402
import pytest  # noqa: E402


# The command-line tests run `python -m jaxstiction`, which keeps compiled programs
# in a persistent cache (by default in the user's ~/.cache). The suite gives them a
# cache of its own, removed when the run ends, so it neither writes to the user's
# folder nor passes only because an earlier run left programs there; this is also
# what a fresh machine (CI) sees. Set JAXSTICTION_CACHE yourself to reuse a cache.
if "JAXSTICTION_CACHE" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="jaxstiction-test-cache-")
    os.environ["JAXSTICTION_CACHE"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)

# Identification needs float64; the library never sets it, the tests do.
jax.config.update("jax_enable_x64", True)

ISDB = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "isdb"


@pytest.fixture(scope="session")
def isdb():
    if not (ISDB / "CHEM23.csv").exists():
        pytest.skip("ISDB data folder ../shared/data/isdb is absent")
    return ISDB
