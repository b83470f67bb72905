import os
import pathlib

from jaxstiction.internal import cache_folder, lean_compiler, release_programs_near_map_limit, xla_cache


# The command line's compiler flag (XLA's older CPU fusion code generator: under half
# the compile memory, and faster, which is most of this suite's time). Importing the
# package creates no JAX backend, so it still takes effect here.
lean_compiler()

import jax  # noqa: E402
import pytest  # noqa: E402


# The command-line tests run `python -m jaxstiction`, which keeps compiled programs in
# a persistent cache. The suite gives them a cache folder of its own (beside the
# user's, not in it: the suite's programs never mix with the user's), kept between
# runs as the user's is: on a fresh machine the first run compiles everything, later
# runs load what did not change. The tests' own process compiles into the same
# folder (XLA's cache is keyed by the compiled program itself, so nothing stale is
# ever loaded). Set JAXSTICTION_CACHE to use another folder, or `off` to compile
# everything every time.
#
# Each pytest-xdist worker has a folder of its own: JAX reads and writes a cache
# folder's entries without a lock, and a worker once died of a segmentation fault
# deserialising an entry the other worker was still writing.
_cache = cache_folder("test-xla-" + os.environ.get("PYTEST_XDIST_WORKER", "main"))
os.environ.setdefault("JAXSTICTION_CACHE", _cache or "off")
if _cache is not None:
    xla_cache(_cache)

# Identification needs float64; the library never sets it, the tests do.
jax.config.update("jax_enable_x64", True)

ISDB = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "isdb"

# The test files, heaviest first (seconds of the default run's 60 slowest test phases,
# `-m "not slow"`, on a cold compilation cache in a fresh virtual environment with the
# ISDB folder present: 188, 139, 128, 102, 84, 81, 52, 35; the rest take under 10).
# With `--no-loadscope-reorder` (pyproject's addopts) xdist hands whole files to the
# two workers in collection order as each frees up, so this is a longest-first
# schedule (8 min 45 s of wall time, one run on a 2-core CPU).
_HEAVIEST_FIRST = ("test_screen.py", "test_estimate.py", "test_stages.py", "test_diagnose.py", "test_verdict.py",
                   "test_whatif.py", "test_relax.py", "test_simulate.py", "test_whatif_cli.py", "test_filters.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(_HEAVIEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file keeps its order


@pytest.fixture(scope="session")
def isdb():
    if not (ISDB / "CHEM23.csv").exists():
        pytest.skip("ISDB data folder ../shared/data/isdb is absent")
    return ISDB


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    """Every compiled XLA CPU program keeps its own memory maps, and a worker that runs
    many test files accumulates them: past the kernel's limit (`vm.max_map_count`,
    65530 by default) LLVM fails mid-compilation: a cold run of the suite lost one
    worker to a segmentation fault in compilation while the other, holding 42,000
    maps, hung. After each test the
    compiled programs are cleared when the process holds more than half the limit
    (`release_programs_near_map_limit`); the cost is recompiling what a later test
    uses again."""
    yield
    release_programs_near_map_limit()
