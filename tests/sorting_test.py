"""Tests for physsplat_jax/sorting.py: the CUB-friendly sorts.

On the CPU the orders must equal NumPy's stable argsort. For a GPU the
lowered programs are checked for the form XLA's SortRewriter sends to CUB's
radix sort (unsigned keys, an int32 payload, a plain less-than), since
compiling without a GPU skips that rewrite.
"""

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from physsplat_jax import cameras
from physsplat_jax import mpm
from physsplat_jax import sorting
from physsplat_jax import test_util
from physsplat_jax.mpm import solver
from physsplat_jax.render import raster
from physsplat_jax.types import make_camera


def _sorts(stablehlo: str) -> list[tuple[str, str]]:
  """(first operand's element type, comparator body) of every sort."""
  out = []
  for m in re.finditer(
      r'"stablehlo\.sort"\([^)]*\).*?\^bb0\(%\w+: tensor<(\w+)>(.*?)\}\) :',
      stablehlo, re.S):
    out.append((m.group(1), m.group(2)))
  return out


def _is_radix_form(key_type: str, body: str) -> bool:
  compares = re.findall(r'stablehlo\.compare\s+(\w+),', body)
  ops = re.findall(r'= (?:stablehlo|chlo)\.(\w+)', body)
  return (key_type.startswith('ui') and compares == ['LT']
          and ops == ['compare'])


class SortingTest(absltest.TestCase):

  def test_orders_equal_numpy_stable_argsort(self):
    rng = np.random.default_rng(0)
    ints = rng.integers(0, 50, size=3000).astype(np.int32)  # many ties
    floats = rng.uniform(0.1, 5.0, size=3000).astype(np.float32)
    floats[::7] = np.inf  # culled Gaussians
    floats[::11] = floats[5]  # ties
    for name, keys in (('int32', ints), ('float32', floats)):
      with self.subTest(name):
        np.testing.assert_array_equal(
          np.asarray(jax.jit(sorting.argsort)(jnp.asarray(keys))),
          np.argsort(keys, kind='stable'))
    with jax.enable_x64(True):
      d = rng.uniform(0.1, 5.0, size=500)
      np.testing.assert_array_equal(
        np.asarray(sorting.argsort(jnp.asarray(d))),
        np.argsort(d, kind='stable'))
    # Negative floats and -0 share +0's key (first), NaN goes after +inf.
    odd = jnp.asarray([2.0, np.nan, -1.0, np.inf, -0.0, 0.5], jnp.float32)
    np.testing.assert_array_equal(np.asarray(sorting.argsort(odd)),
                                  [2, 4, 5, 0, 3, 1])
    k, v = sorting.sort_pairs(jnp.asarray(ints), jnp.arange(3000) * 2)
    order = np.argsort(ints, kind='stable')
    self.assertEqual(k.dtype, jnp.int32)
    np.testing.assert_array_equal(np.asarray(k), ints[order])
    np.testing.assert_array_equal(np.asarray(v), 2 * order)
    perm = jnp.asarray(rng.permutation(1000).astype(np.int32))
    np.testing.assert_array_equal(
      np.asarray(sorting.inverse_permutation(perm)), np.argsort(perm))

  def test_render_sorts_are_radix_pairs_on_a_gpu(self):
    g = test_util.random_gaussians(jax.random.PRNGKey(0), 50)
    vm = cameras.look_at(np.asarray((0.0, -3.5, 1.0)), np.zeros(3))
    cam = make_camera(vm, 60.0, 60.0, 64, 48)
    text = jax.jit(lambda g, c: raster.render(
      g, c, config=raster.RenderConfig(backend='jax'))).trace(
        g, cam).lower(lowering_platforms=('cuda',)).as_text()
    sorts = _sorts(text)
    self.assertLen(sorts, 2)  # depth order, then the slots by sub-tile
    for key_type, body in sorts:
      self.assertTrue(_is_radix_form(key_type, body), (key_type, body))
    # What it replaced: jnp.argsort of floats (NumPy order: NaN and -0
    # handling in the comparator) is not that form.
    old = jax.jit(jnp.argsort).trace(jnp.ones(8)).lower(
      lowering_platforms=('cuda',)).as_text()
    self.assertFalse(any(_is_radix_form(*s) for s in _sorts(old)))

  def test_mpm_orders_particles_by_model_then_cell(self):
    grid = mpm.GridSpec(res=16, size=1.0)
    n = 400
    rng = np.random.default_rng(1)
    x = rng.uniform(0.2, 0.7, (n, 3))
    models = ('fixed_corotated', 'neo_hookean', 'drucker_prager')
    names = [models[i] for i in rng.integers(0, 3, n)]
    mat = mpm.make_materials(names, 2e4, 0.3, 1000.0, config_models=models)
    counts = tuple(names.count(m) for m in models)
    for grouped in (False, True):
      with self.subTest(grouped=grouped):
        config = mpm.SimConfig(grid=grid, dt=1e-3, models=models,
                               model_counts=counts if grouped else None)
        state = mpm.init_state(x, (0, 0, 0), 1e-3, mat, config)
        s2, m2, inv = jax.jit(functools.partial(solver._order, config))(
          state, mat)
        cell = np.asarray(solver._cell_key(grid, state.x))
        mid = np.asarray(mat.model_id)
        want = (np.lexsort((cell, mid)) if grouped
                else np.argsort(cell, kind='stable'))
        np.testing.assert_array_equal(np.asarray(s2.x),
                                      np.asarray(state.x)[want])
        np.testing.assert_array_equal(np.asarray(m2.model_id), mid[want])
        np.testing.assert_array_equal(np.asarray(inv), np.argsort(want))
    # The key is one unsigned array sorted with an int32 payload.
    text = jax.jit(functools.partial(solver._order, config)).trace(
      state, mat).lower(lowering_platforms=('cuda',)).as_text()
    sorts = _sorts(text)
    self.assertLen(sorts, 1)
    self.assertTrue(_is_radix_form(*sorts[0]), sorts[0])


if __name__ == '__main__':
  absltest.main()
