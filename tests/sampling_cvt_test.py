"""Tests for physsplat_jax.sampling.centroidal (PGAS allocation + Lloyd)."""

import jax
import numpy as np
from absl.testing import absltest
from scipy import spatial

from physsplat_jax import sampling
from physsplat_jax.errors import PhysSplatError

# Volumes are sums of the same float64 numbers in another grouping.
VOLUME_RTOL = 1e-12



def _block_and_plate(h, gap):
  """Cell centres (side ``h``) of a unit cube and of a unit square plate
  one cell thick at ``z = 0.5``, shifted by ``gap`` along x."""
  g = np.arange(0, 1, h) + h / 2
  block = np.stack(np.meshgrid(g, g, g), -1).reshape(-1, 3)
  plate = np.stack(np.meshgrid(g + gap, g, [0.5]), -1).reshape(-1, 3)
  return block, plate

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
    n = sampling.allocate(10, demand=[1.0, 1.0, 1.0], floor=[20, 20, 20],
                          cap=[100, 100, 100])
    np.testing.assert_array_equal(np.sort(n), [3, 3, 4])
    # ... but not below min_count (8 drivers per object to bind to).
    n = sampling.allocate(20, demand=[1.0, 1.0, 1.0], floor=[90, 10, 10],
                          cap=[100, 100, 100], min_count=8)
    np.testing.assert_array_equal(n, [8, 8, 8])
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
    # Two lattice balls of radius 1 (cheaper than make_candidates): the
    # outer layer stands for the Gaussians, the rest for the fill.
    h = 0.15
    g = np.arange(-1, 1 + 1e-9, h)
    p = np.stack(np.meshgrid(g, g, g), -1).reshape(-1, 3)
    p = p[np.linalg.norm(p, axis=1) <= 1.0]
    x = np.concatenate([p, p + [3.0, 0, 0]])
    m = len(x)
    surf = np.tile(np.linalg.norm(p, axis=1) > 1.0 - h, 2)
    cls.cand = sampling.Candidates(
      x=x, is_surface=surf,
      object_ids=np.repeat([0, 1], len(p)).astype(np.int32),
      covariances=np.tile(np.diag([1e-3, 1e-3, 1e-4]), (m, 1, 1)),
      volume=np.full(m, h**3), gaussian_index=np.full(m, -1, np.int32))
    cls.cfg = sampling.PGASConfig(base_radius=0.5)
    cls.E = {0: 1e5, 1: 5e6}  # soft, stiff: same shape and size

  def _select(self, budget, key=1, **cvt):
    return sampling.select_drivers(
      jax.random.PRNGKey(key), self.cand, 'pgas-cvt', E=self.E,
      config=self.cfg, budget=budget, cvt=sampling.CVTConfig(**cvt))

  def test_count_mass_and_softness(self):
    # The paper's physics density (off by default, see docs/sampling.md).
    d = self._select(150, density_power=1.0)
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
    kw = dict(density_power=1.0, placement_power=5.0 / 3.0)
    d0 = self._select(100, lloyd_iters=0, **kw)
    d1 = self._select(100, **kw)
    self.assertTrue(np.all(d0.candidate_index >= 0))
    np.testing.assert_array_equal(d0.object_ids, d1.object_ids)
    n, _ = sampling.target_density(
      self.cand, np.where(self.cand.object_ids == 0, 1e5, 5e6), self.cfg,
      sampling.CVTConfig(**kw))
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

  def test_thin_part_gets_more_drivers_per_volume(self):
    # A 1 m block and a 1 x 1 x 0.05 m plate beside it, one material: the
    # default allocation gives the plate more drivers per volume (K-means
    # would split by candidate count, i.e. by volume here).
    h = 0.05
    block, plate = _block_and_plate(h, 1.0)
    x = np.concatenate([block, plate])
    m = len(x)
    cand = sampling.Candidates(
      x=x, is_surface=np.ones(m, bool),
      object_ids=np.r_[np.zeros(len(block)), np.ones(len(plate))].astype(
        np.int32), covariances=np.zeros((m, 3, 3)),
      volume=np.full(m, h**3), gaussian_index=np.full(m, -1, np.int32))
    d = sampling.select_drivers(
      jax.random.PRNGKey(0), cand, 'pgas-cvt', E={0: 1e5, 1: 1e5},
      config=sampling.PGASConfig(base_radius=0.1), budget=300,
      cvt=sampling.CVTConfig(floor=0.0))
    n = [np.sum(d.object_ids == o) for o in (0, 1)]
    v = [np.sum(cand.volume[cand.object_ids == o]) for o in (0, 1)]
    self.assertGreater(n[1] / v[1], 2.0 * n[0] / v[0], n)
    np.testing.assert_allclose(d.volume.sum(), m * h**3, rtol=VOLUME_RTOL)

  def test_volume_fraction_bulk_and_plate(self):
    # A solid 1 m block of 0.05 m cells and a 0.05 m plate, voxels 0.1 m,
    # window 5 voxels: ~1 deep in the block, ~t / (5 voxel) = 0.1 across
    # the plate (the occupancy measure says ~0.2 for any thickness).
    h = 0.05
    block, plate = _block_and_plate(h, 2.0)
    x = np.concatenate([block, plate])
    ob = np.r_[np.zeros(len(block)), np.ones(len(plate))].astype(int)
    psi = sampling.volume_fraction(x, ob, np.full(len(x), h**3), voxel=0.1)
    inner = np.all((block > 0.3) & (block < 0.7), axis=1)
    np.testing.assert_allclose(psi[:len(block)][inner], 1.0, rtol=1e-9)
    mid = np.all(np.abs(plate[:, :2] - [2.5, 0.5]) < 0.2, axis=1)
    np.testing.assert_allclose(psi[len(block):][mid], 0.1, rtol=1e-9)

  def test_twigs_under_a_crown_get_the_count_split(self):
    # The ficus in small: a twig (a line, object 0) under a crown of
    # stacked thin leaves (object 1). Both are thin by material, so the
    # default rule gives both the same factor and the split is K-means'
    # (by candidates). Counted by occupied voxels (the old rule) the crown
    # fills its voxels like a bulk and the twig got ~2.5x its share.
    twig = np.c_[np.zeros((2, 501)).T, np.linspace(0, 1, 501)]
    g = np.linspace(-0.4, 0.4, 21)
    crown = np.stack(np.meshgrid(g, g, 1.2 + 0.04 * np.arange(12)),
                     -1).reshape(-1, 3)
    x = np.concatenate([twig, crown])
    m = len(x)
    vol = np.r_[np.full(len(twig), np.pi * 0.005**2 * 0.002),  # 1 cm twig
                np.full(len(crown), 0.04**2 * 0.002)]  # 2 mm leaves
    cand = sampling.Candidates(
      x=x, is_surface=np.ones(m, bool),
      object_ids=np.r_[np.zeros(len(twig)), np.ones(len(crown))].astype(
        np.int32), covariances=np.zeros((m, 3, 3)), volume=vol,
      gaussian_index=np.full(m, -1, np.int32))
    budget = 400
    share = len(twig) / m  # K-means' split: 0.086

    def twig_count(**kw):
      d = sampling.select_drivers(
        jax.random.PRNGKey(0), cand, 'pgas-cvt', E={0: 3e5, 1: 1e5},
        config=sampling.PGASConfig(base_radius=0.1), budget=budget,
        cvt=sampling.CVTConfig(lloyd_iters=0, **kw))
      return np.sum(d.object_ids == 0)

    self.assertAlmostEqual(twig_count(), share * budget, delta=1.0)
    self.assertGreater(twig_count(thinness='occupancy', geom_ref=0.6,
                                   geom_max=3.0),
                       2.0 * share * budget)

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
