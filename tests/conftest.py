"""pytest configuration shared by all tests."""

import os
import pathlib

os.environ.setdefault('JAX_PLATFORMS', 'cpu')

# The tests run tiny problems, so on the CPU compiling dominates their time
# (thousands of programs). JAX's own test setting
# jax_disable_most_optimizations (XLA's backend at -O0 without LLVM's
# expensive passes) cuts the suite's CPU time by a quarter. XLA keeps IEEE
# semantics at any level (no fast math), but the unoptimised code rounds a
# few operations differently: five frames of tests/mpm_blocks.four_blocks
# agree with the default compile to float32 rounding (6e-8 m in x, 3e-5
# relative in C), not bitwise (-O1 is bitwise equal, but saves a third as
# much). Every bitwise check here compares two programs compiled alike, and
# the tolerances are far above that. The few tests whose loops
# run long unoptimised (a rigid-contact gradient: 12 s -> 74 s) are marked
# ``@pytest.mark.optimized`` and compile as usual. Set through the
# environment before JAX starts, so the tests' subprocesses inherit it;
# PHYSSPLAT_TEST_XLA_O2=1 keeps XLA's default everywhere.
if (os.environ['JAX_PLATFORMS'] == 'cpu'
    and not os.environ.get('PHYSSPLAT_TEST_XLA_O2')):
  os.environ.setdefault('JAX_DISABLE_MOST_OPTIMIZATIONS', '1')

import jax  # noqa: E402

import pytest  # noqa: E402

# Tests that need float64 use ``with jax.enable_x64(True):`` locally, so the
# f32 default of the library is what the rest of the suite exercises.


@pytest.fixture(autouse=True)
def _optimized_compiles(request):
  """XLA's usual optimisation inside tests marked ``optimized``."""
  if request.node.get_closest_marker('optimized') is None:
    yield
    return
  before = jax.config.read('jax_disable_most_optimizations')
  jax.config.update('jax_disable_most_optimizations', False)
  try:
    yield
  finally:
    jax.config.update('jax_disable_most_optimizations', before)


REPO = pathlib.Path(__file__).resolve().parents[1]
