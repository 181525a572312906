"""pytest configuration shared by all tests."""

import os
import pathlib

os.environ.setdefault('JAX_PLATFORMS', 'cpu')

# The tests run tiny problems, so on the CPU compiling dominates their time
# (thousands of programs). LLVM's -O1 without its expensive passes compiles
# about a quarter faster than XLA's default -O2 and computes the same
# values: XLA keeps IEEE semantics at any level (no fast math; five frames
# of tests/mpm_blocks.four_blocks come out bitwise equal), so every bitwise
# and tolerance check means what it did. -O0 would compile faster
# still, but some loops then run 20x slower (a rigid-contact gradient
# test: 7 s -> 67 s). Set before JAX starts its CPU client; subprocesses of
# the tests inherit it. PHYSSPLAT_TEST_XLA_O2=1 keeps XLA's default.
_FAST_COMPILE = ('--xla_backend_optimization_level=1 '
                 '--xla_llvm_disable_expensive_passes=true')
if (os.environ['JAX_PLATFORMS'] == 'cpu'
    and not os.environ.get('PHYSSPLAT_TEST_XLA_O2')
    and 'xla_backend_optimization_level' not in os.environ.get(
        'XLA_FLAGS', '')):
  os.environ['XLA_FLAGS'] = (
    os.environ.get('XLA_FLAGS', '') + ' ' + _FAST_COMPILE).strip()

import jax  # noqa: E402

# Tests that need float64 use ``with jax.enable_x64(True):`` locally, so the
# f32 default of the library is what the rest of the suite exercises.
del jax

REPO = pathlib.Path(__file__).resolve().parents[1]
