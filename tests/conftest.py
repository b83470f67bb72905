import pathlib

from jaxstiction._cli import _lean_compiler


# The command line's compiler flag (XLA's older CPU fusion code generator: under half
# the compile memory, and faster, which is most of this suite's time). Importing the
# package creates no JAX backend, so it still takes effect here.
_lean_compiler()

import jax  # noqa: E402
import pytest  # noqa: E402


# Identification needs float64; the library never sets it, the tests do.
jax.config.update("jax_enable_x64", True)

ISDB = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "isdb"


@pytest.fixture(scope="session")
def isdb():
    if not (ISDB / "CHEM23.csv").exists():
        pytest.skip("ISDB data folder ../shared/data/isdb is absent")
    return ISDB
