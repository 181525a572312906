"""Tests for physsplat_jax.mpdp.knn: the O(N k) grid search against the
O(N^2) brute force, and the MPDP field under both searches."""

import functools
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

import codegen
from physsplat_jax.mpdp import knn
from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp import pretrained

_N = 400                # points per test cloud (one compile per k)
_FIELD_RTOL = 1e-6      # same neighbours -> same field up to f32 rounding


def _cloud(kind: str, seed: int = 0) -> np.ndarray:
  """(_N, 3) float32 clouds that stress the cell grid."""
  rng = np.random.default_rng(seed)
  n = _N
  if kind == 'cube':
    x = rng.uniform(-1, 1, (n, 3))
  elif kind == 'lattice':  # exact distance ties everywhere
    a = np.linspace(-1.0, 1.0, 7)
    x = np.stack(np.meshgrid(a, a, a, indexing='ij'), -1).reshape(-1, 3)
    x = np.concatenate([x, rng.uniform(-1, 1, (n - len(x), 3))])
  elif kind == 'plate':
    x = rng.uniform(-1, 1, (n, 3)) * [1.0, 1.0, 0.01]
  elif kind == 'shell':
    x = rng.normal(size=(n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
  elif kind == 'rod':
    x = np.c_[rng.uniform(-1, 1, n), 1e-3 * rng.normal(size=(n, 2))]
  elif kind == 'two_densities':  # half the points 1000x denser
    x = rng.uniform(-1, 1, (n, 3))
    x[: n // 2] *= 0.1
  elif kind == 'duplicates':
    x = rng.uniform(-1, 1, (n, 3))
    x[n // 4: n // 2] = x[: n // 4]
  else:
    raise ValueError(kind)
  return x.astype(np.float32)


def _mask(seed: int = 1) -> np.ndarray:
  return np.random.default_rng(seed).uniform(size=_N) > 0.2


@functools.partial(jax.jit, static_argnums=(2,))
def _brute(x, mask, k):
  return knn.knn_brute(x, mask, k)


@functools.partial(jax.jit, static_argnums=(2, 3))
def _grid(x, mask, k, options=()):
  return knn.knn_grid(x, mask, k, **dict(options))


def _d2(x, idx):
  return np.sum((x[idx] - x[:, None, :]) ** 2, axis=-1)


class KnnTest(parameterized.TestCase):

  @parameterized.product(
    kind=['cube', 'lattice', 'plate', 'shell', 'rod', 'two_densities',
          'duplicates'],
    k=[4, 8])
  def test_grid_equals_brute_force(self, kind, k):
    x, mask = _cloud(kind), _mask()
    # Invalid rows hold junk far away: they must never be neighbours.
    x[~mask] += 1e3
    ref = np.asarray(_brute(x, mask, k))
    res = _grid(x, mask, k)
    got = np.asarray(res.index)
    self.assertTrue(np.all(mask[got[mask]]))
    # Same distances (the neighbour sets up to ties) ...
    np.testing.assert_array_equal(_d2(x, got)[mask], _d2(x, ref)[mask])
    # ... and, with ties broken by index in both, the same indices.
    np.testing.assert_array_equal(got[mask], ref[mask])
    self_rows = np.broadcast_to(np.nonzero(~mask)[0][:, None],
                                got[~mask].shape)
    np.testing.assert_array_equal(got[~mask], self_rows)

  @parameterized.named_parameters(
    # Cells far too small: rows climb the coarser levels or fall back.
    ('tiny_cells', (('cell', 1e-5), ('coarser_levels', 2))),
    # Cells far too large: every block is truncated.
    ('huge_cells', (('cell', 10.0),)),
    # A small budget truncates blocks; few retries.
    ('small_budget', (('budget', 16), ('retry_budget', 24),
                      ('max_retries', 1))),
  )
  def test_forced_repairs_stay_exact(self, options):
    x, mask = _cloud('two_densities'), _mask()
    ref = np.asarray(_brute(x, mask, 8))
    res = _grid(x, mask, 8, options)
    self.assertGreater(int(res.num_repaired), 0)
    self.assertGreater(int(res.num_brute), 0)  # the fallback ran
    np.testing.assert_array_equal(np.asarray(res.index)[mask], ref[mask])

  def test_few_valid_points_point_to_self(self):
    x = _cloud('cube')
    mask = np.zeros(_N, bool)
    mask[[3, 50, 200]] = True
    ref = np.asarray(_brute(x, mask, 8))
    got = np.asarray(_grid(x, mask, 8).index)
    np.testing.assert_array_equal(got[mask], ref[mask])
    self.assertTrue(np.all(got[3, 3:] == 3))  # 3 valid: the rest is self

  def test_no_valid_point(self):
    got = np.asarray(_grid(_cloud('cube'), np.zeros(_N, bool), 8).index)
    np.testing.assert_array_equal(got, np.repeat(np.arange(_N)[:, None], 8, 1))

  def test_fused_inputs(self):
    # Points computed inside the same jit (as in the network): XLA may
    # round a fused value differently per consumer; the cell list must
    # stay consistent. The minimum point sits exactly on a cell face.
    x, mask = PretrainedFieldTest.objects()
    for b in range(2):
      p, res = jax.jit(lambda x, m: (
        lambda p: (p, knn.knn_grid(p, m, 8)))(
          model_lib.normalize_points(x, m)))(x[b], mask[b])
      ref = np.asarray(_brute(np.asarray(p), mask[b], 8))
      np.testing.assert_array_equal(np.asarray(res.index)[mask[b]],
                                    ref[mask[b]])

  def test_brute_in_blocks_is_the_sorted_distances(self):
    """Over several row blocks (the last one partial), with masked points
    and exact ties: every row is numpy's stable sort of its valid
    distances, ties by lower index; a row with fewer valid points than k
    points to itself there."""
    n = 2 * knn.BRUTE_BLOCK + 37
    rng = np.random.default_rng(7)
    a = np.linspace(-1.0, 1.0, 9)
    lattice = np.stack(np.meshgrid(a, a, a, indexing='ij'), -1).reshape(-1, 3)
    x = np.concatenate([lattice, rng.uniform(-1, 1, (n - len(lattice), 3))])
    x = x.astype(np.float32)
    mask = rng.uniform(size=n) > 0.3
    got = np.asarray(_brute(jnp.asarray(x), jnp.asarray(mask), 6))
    d2 = np.sum((x[:, None, :] - x[None, :, :]) ** 2, axis=-1)
    d2[:, ~mask] = np.inf
    want = np.argsort(d2, axis=1, kind='stable')[:, :6]
    want = np.where(np.isfinite(np.take_along_axis(d2, want, 1)), want,
                    np.arange(n)[:, None])
    np.testing.assert_array_equal(got, want)
    few = np.zeros(n, bool)
    few[[3, 900]] = True
    got = np.asarray(_brute(jnp.asarray(x), jnp.asarray(few), 4))
    np.testing.assert_array_equal(got[3], [3, 900, 3, 3])

  @parameterized.parameters('lattice', 'duplicates', 'two_densities')
  def test_lattice_coordinates_give_exact_distances(self, kind):
    """Integer points: both searches rank numpy's exact int64 squared
    distances (as float32, ties by lower index), and the lattice spans
    [0, LATTICE_STEPS] on the largest extent of the valid points."""
    x, mask = _cloud(kind), _mask()
    x[~mask] += 1e3  # junk outside: not part of the lattice's bounds
    q = np.asarray(jax.jit(knn.lattice_coordinates)(x, mask))
    self.assertEqual(q.dtype, np.int32)
    np.testing.assert_array_equal(q[~mask], 0)
    np.testing.assert_array_equal(q[mask].min(0), 0)
    self.assertEqual(int((q[mask].max(0) - q[mask].min(0)).max()),
                     knn.LATTICE_STEPS)
    qi = q.astype(np.int64)
    d2 = np.sum((qi[:, None, :] - qi[None, :, :]) ** 2, -1).astype(np.float32)
    d2[:, ~mask] = np.inf
    want = np.argsort(d2, axis=1, kind='stable')[:, :8]
    got = np.asarray(_brute(q, mask, 8))
    np.testing.assert_array_equal(got[mask], want[mask])
    res = _grid(q, mask, 8)
    np.testing.assert_array_equal(np.asarray(res.index)[mask], want[mask])

  def test_auto_uses_grid_above_threshold(self):
    n = knn.BRUTE_MAX_POINTS + 500
    rng = np.random.default_rng(4)
    x = jnp.asarray(rng.uniform(-1, 1, (n, 3)), jnp.float32)
    mask = jnp.asarray(rng.uniform(size=n) > 0.1)
    jaxpr = str(jax.make_jaxpr(
      lambda x, m: knn.knn_indices(x, m, 8, 'auto'))(x, mask))
    self.assertIn('while', jaxpr)  # the grid path, not one top_k
    got = jax.jit(lambda x, m: knn.knn_indices(x, m, 8, 'auto'))(x, mask)
    ref = _brute(x, mask, 8)
    np.testing.assert_array_equal(np.asarray(got)[np.asarray(mask)],
                                  np.asarray(ref)[np.asarray(mask)])
    with self.assertRaisesRegex(ValueError, 'knn method'):
      knn.knn_indices(x, mask, 8, 'kdtree')


class PretrainedFieldTest(absltest.TestCase):
  """The shipped weights give the same field with either search."""

  @staticmethod
  def objects():
    """A cube and a thin plate (300 and 260 points) padded to 384 rows of
    junk, interleaved; (2, 384, 3) points and (2, 384) masks."""
    rng = np.random.default_rng(7)
    n_pad = 384
    cube = rng.uniform(-0.05, 0.05, (300, 3))
    plate = rng.uniform(-1, 1, (260, 3)) * [0.2, 0.1, 0.004]
    pts = np.zeros((2, n_pad, 3), np.float32)
    mask = np.zeros((2, n_pad), bool)
    for b, o in enumerate((cube, plate)):
      pts[b, :len(o)] = o + [0.3, -0.1, 0.02]
      mask[b, :len(o)] = True
      pts[b, len(o):] = rng.uniform(-5, 5, (n_pad - len(o), 3))  # junk
    # Shuffle so the padding is interleaved with the valid points.
    perm = rng.permutation(n_pad)
    return pts[:, perm], mask[:, perm]

  def test_field_matches_brute_force(self):
    params = pretrained.load_pretrained()
    pts, mask = self.objects()
    means = jnp.stack([
      model_lib.encode_means(2e5, 0.3, 800.0, 'fixed_corotated'),
      model_lib.encode_means(5e6, 0.35, 1200.0, 'neo_hookean')])
    old = jax.jit(model_lib.make_predict(knn_method='brute'))
    new = jax.jit(model_lib.make_predict(knn_method='grid'))
    f_old = np.asarray(old(params, pts, means, mask))
    f_new = np.asarray(new(params, pts, means, mask))
    self.assertGreater(f_old[mask][:, 0].std(), 0.01)  # not trivially 1
    np.testing.assert_allclose(f_new[mask], f_old[mask], rtol=_FIELD_RTOL)
    np.testing.assert_array_equal(f_new[~mask], 1.0)
    # Unbatched as well, and the neighbour sets behind it.
    f1 = np.asarray(new(params, pts[1], means[1], mask[1]))
    np.testing.assert_allclose(f1[mask[1]], f_old[1][mask[1]],
                               rtol=_FIELD_RTOL)
    p = model_lib.normalize_points(jnp.asarray(pts[0]), jnp.asarray(mask[0]))
    np.testing.assert_array_equal(
      np.asarray(knn.knn_grid(p, mask[0], 8).index)[mask[0]],
      np.asarray(knn.knn_brute(p, mask[0], 8))[mask[0]])

  def test_neighbours_do_not_depend_on_the_normalisation_rounding(self):
    """A lattice block has exact ties at every neighbour shell. Another
    backend or JAX version rounds the normalised points differently (a
    reduction in another order: an ulp or two); searched on those floats,
    equidistant neighbours swap and a whole object's field moved by 10 %
    between JAX 0.10 and 0.12. Searched on the raw points' integer
    lattice, the field moves by float noise only."""
    a = np.arange(9, dtype=np.float32)
    g = np.stack(np.meshgrid(a, a, a, indexing='ij'), -1).reshape(-1, 3)
    pts = (g * np.float32(0.0371) + np.float32(0.3)).astype(np.float32)
    mask = np.ones(len(pts), bool)
    rng = np.random.default_rng(3)
    ulps = rng.integers(-2, 3, pts.shape).astype(np.float32)
    normalize = model_lib.normalize_points

    def rounded_otherwise(points, m):
      p = normalize(points, m)
      return p + ulps * jnp.abs(p) * np.float32(2.0**-24)

    p0 = normalize(jnp.asarray(pts), jnp.asarray(mask))
    p1 = rounded_otherwise(jnp.asarray(pts), jnp.asarray(mask))
    swapped = (np.sort(np.asarray(_brute(p0, mask, 8)), 1)
               != np.sort(np.asarray(_brute(p1, mask, 8)), 1)).any(1)
    self.assertGreater(swapped.sum(), 10)  # the hazard is real here
    params = pretrained.load_pretrained()
    means = model_lib.encode_means(2e5, 0.3, 800.0, 'fixed_corotated')
    f0 = np.asarray(jax.jit(model_lib.make_predict())(params, pts, means))
    with mock.patch.object(model_lib, 'normalize_points', rounded_otherwise):
      f1 = np.asarray(jax.jit(model_lib.make_predict())(params, pts, means))
    self.assertGreater(f0[:, 0].std(), 0.01)  # not trivially 1
    np.testing.assert_allclose(f1, f0, rtol=1e-5)

  def test_gradient_matches_brute_force(self):
    params = pretrained.load_pretrained()
    pts, mask = self.objects()
    means = model_lib.encode_means(2e5, 0.3, 800.0, 'fixed_corotated')

    def loss(p, method):
      f = model_lib.make_predict(knn_method=method)(p, pts[0], means,
                                                    mask[0])
      return jnp.sum(jnp.where(mask[0][:, None], jnp.log(f) ** 2, 0.0))

    g_old = jax.jit(jax.grad(functools.partial(loss, method='brute')))(params)
    g_new = jax.jit(jax.grad(functools.partial(loss, method='grid')))(params)
    for a, b in zip(jax.tree.leaves(g_new), jax.tree.leaves(g_old)):
      self.assertTrue(np.all(np.isfinite(np.asarray(a))))
      codegen.allclose_across_programs(a, b, 1e-5, 1e-7,
                                       legacy_scale=1e-6)


if __name__ == '__main__':
  absltest.main()
