"""The suite's own fixtures (tests/conftest.py) do what the suite relies on."""

import gc

import jax
import jax.numpy as jnp
import pytest

from conftest import mappings


@pytest.mark.skipif(mappings() == 0, reason="needs /proc/self/maps")
def test_clearing_the_jax_caches_releases_the_mappings_of_compiled_code():
    # On the CPU, where XLA's JIT maps the code of each compilation (a GPU's kernels live on the device).
    with jax.default_device(jax.devices("cpu")[0]):
        jax.jit(lambda x: jnp.cumsum(jnp.sin(x)))(jnp.ones(1)).block_until_ready()  # one-time setup mapped
        jax.clear_caches()
        gc.collect()
        before = mappings()
        for k in range(40):  # 40 distinct shapes: 40 compilations
            jax.jit(lambda x: jnp.cumsum(jnp.sin(x)))(jnp.ones(k + 1)).block_until_ready()
        compiled = mappings()
    jax.clear_caches()
    gc.collect()
    assert compiled - before > 40, "compiled code no longer maps regions: the fixture's threshold needs a new reason"
    assert mappings() - before < (compiled - before) / 2
