import jax

# float64 available for the tests that ask for it (float32 stays the default
# for arrays the tests create with an explicit dtype); strict promotion catches
# silent float32/float64 mixing.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


import gc  # noqa: E402
import os  # noqa: E402

# the nhsde command turns JAX's persistent compilation cache on in ~/.cache: tests leave the user's cache alone
# (the cache's own tests point it at a temporary folder)
os.environ["NHSDE_COMPILATION_CACHE"] = "off"

import equinox as eqx  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop compiled programs after each test module so one long session does not accumulate them."""
    yield
    jax.clear_caches()
    eqx.clear_caches()
    gc.collect()


@pytest.hookimpl(optionalhook=True)  # runs with -p no:xdist too
def pytest_xdist_auto_num_workers(config):
    """``-n auto`` (pyproject's addopts): one worker per available core, at most 4 (a worker peaks near 4 GB)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(cores, 4))
