import os
import pathlib


# As the command line does (see `jaxstiction._cli._lean_compiler`): XLA's older CPU
# fusion code generator compiles in under half the memory and faster, which is most
# of this suite's time. Set before JAX creates its backend.
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    import jaxlib

    if jaxlib.__version__.startswith("0.10."):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()

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
