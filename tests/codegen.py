"""How the suite's CPU programs are compiled, for checks that compare two
different programs (no test here).

With jaxlib 0.10 the suite compiles with XLA:CPU's older element-wise
emitters (tests/conftest.py: compiling a third faster). Those round a few
elements of two differently shaped programs differently: a vmapped stress
kernel against one call per item, or F and C packed against separate,
differ by about 1 unit in the last place of the values' scale (more of an
element's own near zero, where it comes from cancellation); a one-device
shard_map against the plain rollout by a few 1e-5 of the values' scale
after two substeps. Checks across programs that hold bit for bit, or to
1e-6, with the emitters the package's users get keep that strictness
wherever those emitters compile (jaxlib 0.12, PHYSSPLAT_TEST_XLA_O2=1) and
allow that much under the older ones.
"""

import os

import numpy as np

# The setting (conftest.py adds it to XLA_FLAGS before JAX starts).
FLAG = '--xla_cpu_use_fusion_emitters=false'


def legacy_emitters():
  """Whether this process compiles with the older emitters."""
  return FLAG in os.environ.get('XLA_FLAGS', '')


def assert_same_bits(a, b, ulps=4):
  """``a == b`` bit for bit; under the older emitters within ``ulps``
  units in the last place of ``b``'s largest magnitude (an element near
  zero, computed by cancellation, carries its operands' rounding)."""
  a, b = np.asarray(a), np.asarray(b)
  if legacy_emitters() and np.issubdtype(b.dtype, np.floating) and b.size:
    atol = ulps * np.finfo(b.dtype).eps * float(np.max(np.abs(b)))
    np.testing.assert_allclose(a, b, rtol=0, atol=atol)
  else:
    np.testing.assert_array_equal(a, b)


def allclose_across_programs(actual, desired, rtol, atol, legacy_scale):
  """``assert_allclose(actual, desired)`` at ``rtol``/``atol``; under the
  older emitters the absolute tolerance is at least ``legacy_scale`` times
  ``desired``'s largest magnitude (values computed by cancellation carry
  their operands' rounding)."""
  desired = np.asarray(desired)
  if legacy_emitters() and desired.size:
    atol = max(atol, legacy_scale * float(np.max(np.abs(desired))))
  np.testing.assert_allclose(np.asarray(actual), desired, rtol=rtol,
                             atol=atol)
