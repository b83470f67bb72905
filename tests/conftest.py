import pathlib

import jax
import pytest


# Identification needs float64; the library never sets it, the tests do.
jax.config.update("jax_enable_x64", True)

ISDB = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "isdb"


@pytest.fixture(scope="session")
def isdb():
    if not (ISDB / "CHEM23.csv").exists():
        pytest.skip("ISDB data folder ../shared/data/isdb is absent")
    return ISDB
