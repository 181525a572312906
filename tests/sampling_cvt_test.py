"""Tests for physsplat_jax.sampling.centroidal (PGAS allocation + Lloyd)."""

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from scipy import spatial

from physsplat_jax import sampling
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.types import Gaussians

# Volumes are sums of the same float64 numbers in another grouping.
VOLUME_RTOL = 1e-12


def _sphere(n, seed=0):
  rng = np.random.default_rng(seed)
  v = rng.normal(size=(n, 3))
  return v / np.linalg.norm(v, axis=1, keepdims=True)


class AllocateTest(absltest.TestCase):

  def test_proportional_within_bounds(self):
    n = sampling.allocate(100, demand=[3.0, 1.0, 1.0], floor=[0, 0, 0],
                          cap=[1000, 1000, 1000])
    self.assertEqual(n.sum(), 100)
    np.testing.assert_allclose(n, [60, 20, 20], atol=1)

  def test_floor_cap_and_shortfall(self):
    # Object 1's share (10) is under its floor (30); object 0 is capped.
    n = sampling.allocate(100, demand=[8.0, 1.0, 1.0], floor=[0, 30, 0],
                          cap=[50, 1000, 1000])
    self.assertEqual(n.sum(), 100)
    self.assertEqual(n[0], 50)
    self.assertGreaterEqual(n[1], 30)
    # Floors over the budget shrink in proportion.
    n = sampling.allocate(10, demand=[1.0, 1.0], floor=[20, 20],
                          cap=[100, 100])
    np.testing.assert_array_equal(n, [5, 5])
    # A budget over the candidates keeps them all.
    n = sampling.allocate(500, demand=[1.0, 1.0], floor=[0, 0], cap=[7, 9])
    np.testing.assert_array_equal(n, [7, 9])


class WeightedLloydTest(absltest.TestCase):

  def test_energy_decreases_and_follows_the_weight(self):
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (4000, 3))
    w = np.where(x[:, 0] < 0.5, 8.0, 1.0)
    init = x[rng.choice(len(x), 60, replace=False)]
    c, e = sampling.weighted_lloyd(x, w, init, iters=15, tol=0.0)
    self.assertTrue(np.all(np.diff(e) <= 1e-12 * e[0]), e)
    self.assertLess(e[-1], 0.8 * e[0])
    # Weight 8 on the left half: density ratio 8^(3/5) ~ 3.5 for many
    # points, ~2 for 60 (the walls of the cube).
    left = np.sum(c[:, 0] < 0.5)
    self.assertGreater(left, 1.6 * (60 - left))


class SelectCVTTest(absltest.TestCase):

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    pts = np.concatenate([_sphere(600), _sphere(600, seed=1) + [3.0, 0, 0]])
    n = len(pts)
    g = Gaussians(
      means=jnp.asarray(pts, jnp.float32),
      log_scales=jnp.full((n, 3), -3.0), quats=jnp.tile(
        jnp.array([1.0, 0, 0, 0]), (n, 1)),
      opacity_logits=jnp.full((n,), 3.0), sh=jnp.zeros((n, 1, 3)))
    ids = np.r_[np.zeros(600), np.ones(600)].astype(np.int32)
    cls.cand = sampling.make_candidates(
      jax.random.PRNGKey(0), g, ids,
      fill_config=sampling.FillConfig(grid_res=12))
    cls.cfg = sampling.PGASConfig(base_radius=0.5)
    cls.E = {0: 1e5, 1: 5e6}  # soft, stiff: same shape and size

  def _select(self, budget, key=1, **cvt):
    return sampling.select_drivers(
      jax.random.PRNGKey(key), self.cand, 'pgas-cvt', E=self.E,
      config=self.cfg, budget=budget, cvt=sampling.CVTConfig(**cvt))

  def test_count_mass_and_softness(self):
    d = self._select(150)
    self.assertLen(d.x, 150)
    for o in (0, 1):
      np.testing.assert_allclose(
        d.volume[d.object_ids == o].sum(),
        self.cand.volume[self.cand.object_ids == o].sum(), rtol=VOLUME_RTOL)
    self.assertTrue(np.all(d.volume > 0))
    v = [self.cand.volume[self.cand.object_ids == o].sum() for o in (0, 1)]
    per_vol = [np.sum(d.object_ids == o) / v[o] for o in (0, 1)]
    self.assertGreater(per_vol[0], 1.5 * per_vol[1])

  def test_deterministic_and_budget_over_candidates(self):
    a, b = self._select(120, key=3), self._select(120, key=3)
    np.testing.assert_array_equal(a.x, b.x)
    m = len(self.cand.x)
    d = self._select(m + 10)
    self.assertLen(d.x, m)
    np.testing.assert_array_equal(np.sort(d.candidate_index), np.arange(m))

  def test_lloyd_lowers_the_energy_of_the_poisson_start(self):
    # Same key, same allocation and Poisson start; Lloyd steps only lower
    # the weighted quantisation energy of each object.
    d0 = self._select(100, lloyd_iters=0)
    d1 = self._select(100)
    self.assertTrue(np.all(d0.candidate_index >= 0))
    np.testing.assert_array_equal(d0.object_ids, d1.object_ids)
    n, _ = sampling.target_density(
      self.cand, np.where(self.cand.object_ids == 0, 1e5, 5e6), self.cfg)
    w = n ** (5.0 / 3.0)
    for o in (0, 1):
      c = self.cand.object_ids == o

      def energy(d):
        dist, _ = spatial.cKDTree(d.x[d.object_ids == o]).query(
          self.cand.x[c])
        return np.sum(w[c] * dist**2)  # noqa: B023

      self.assertLess(energy(d1), 0.9 * energy(d0))

  def test_thin_parts_count_as_dense(self):
    rng = np.random.default_rng(0)
    block = rng.uniform(0, 1, (8000, 3))
    plate = rng.uniform(0, 1, (2000, 3)) * [1, 1, 0.05] + [1.0, 0, 0.5]
    x = np.concatenate([block, plate])
    phi = sampling.fill_fraction(x, np.zeros(len(x), int), voxel=0.1)
    inner = np.all((block > 0.3) & (block < 0.7), axis=1)
    self.assertGreater(phi[:8000][inner].min(), 0.99)
    self.assertLess(np.median(phi[8000:]), 0.45)

  def test_bad_input(self):
    with self.assertRaisesRegex(PhysSplatError, 'density_power'):
      sampling.CVTConfig(density_power=-1.0)
    with self.assertRaisesRegex(PhysSplatError, 'weights'):
      sampling.CVTConfig(weights='mass')
    with self.assertRaisesRegex(PhysSplatError, 'budget'):
      sampling.select_drivers(jax.random.PRNGKey(0), self.cand, 'pgas-cvt',
                              E=self.E, config=self.cfg)


if __name__ == '__main__':
  absltest.main()
