"""pytest configuration shared by all tests."""

import atexit
import os
import pathlib
import shutil
import tempfile

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
#
# With jaxlib 0.10, XLA:CPU's older element-wise emitters
# (--xla_cpu_use_fusion_emitters=false) compile the solver's frame a third
# faster again (the four-block frame 5.4-5.7 s against 8.7-8.9 s at -O0 on
# the 2-core VM; the suite a third shorter). Their code runs about half as
# fast, so the package never sets it for its users (docs/benchmarks.md);
# the tests' problems are small enough that compiling still dominates.
# They round a few elements of two differently shaped programs differently:
# checks across programs go through tests/codegen.py. jaxlib 0.12 has
# removed the flag (an unknown flag in XLA_FLAGS aborts the process), so it
# is added only for the jaxlib versions listed.
_LEGACY_EMITTERS_JAXLIB = ('0.10.2',)


def _test_xla_cpu_flags():
  if (os.environ['JAX_PLATFORMS'] != 'cpu'
      or os.environ.get('PHYSSPLAT_TEST_XLA_O2')):
    return
  os.environ.setdefault('JAX_DISABLE_MOST_OPTIMIZATIONS', '1')
  import jaxlib  # noqa: PLC0415 - its version only; no backend starts
  import codegen  # noqa: PLC0415 - the flag; reads XLA_FLAGS as it stands
  flags = os.environ.get('XLA_FLAGS', '')
  name = codegen.FLAG.split('=')[0]
  if (str(getattr(jaxlib, '__version__', '')) in _LEGACY_EMITTERS_JAXLIB
      and name not in flags):
    os.environ['XLA_FLAGS'] = f'{flags} {codegen.FLAG}'.strip()


_test_xla_cpu_flags()

import jax  # noqa: E402

import pytest  # noqa: E402

# physsplat_jax.compile_cache.ENV (not imported here: the xdist controller
# would load the whole package for one name; outputs_test checks they agree)
CACHE_ENV = 'PHYSSPLAT_JAX_CACHE'
OWN_CACHE = 'PHYSSPLAT_TESTS_OWN_CACHE'  # the folder, where the suite made it


def _session_cache_folder():
  """A compilation cache folder of the suite's own, for its scripts.

  The experiment scripts the tests run turn JAX's persistent compilation
  cache on in the user's cache folder by default (~/.cache/physsplat_jax,
  with the stored programs and scenes beside it): the suite's runs wrote
  there and could load what a demo or a benchmark had left, so that a
  fresh machine's suite ran colder than a used one's. They share one
  empty folder instead, removed at the end by the process that made it
  (the xdist workers and the scripts inherit it through the
  environment). A PHYSSPLAT_JAX_CACHE set by the caller wins."""
  if CACHE_ENV in os.environ:
    return
  folder = tempfile.mkdtemp(prefix='physsplat_tests_cache_')
  os.environ[CACHE_ENV] = os.environ[OWN_CACHE] = folder
  atexit.register(shutil.rmtree, folder, ignore_errors=True)


_session_cache_folder()

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
