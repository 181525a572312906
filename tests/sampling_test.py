"""Tests for physsplat_jax.sampling: Poisson disk, PGAS radii, K-means."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl.testing import absltest
from absl.testing import parameterized
from scipy import spatial

from physsplat_jax import sampling
from physsplat_jax.sampling import curvature
from physsplat_jax.sampling import pgas
from physsplat_jax.sampling import poisson

_poisson = jax.jit(
  poisson.poisson_disk,
  static_argnames=('max_samples', 'max_per_cell', 'max_neighbors',
                   'max_rounds', 'thin', 'num_levels'))


def _cloud(n=3000, seed=0):
  rng = np.random.default_rng(seed)
  pts = rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)
  r = np.where(pts[:, 0] < 0.5, 0.06, 0.12).astype(np.float32)
  return pts, r


def _sequential_greedy(pts, r, prio):
  keep = np.zeros(len(pts), bool)
  for i in np.argsort(-prio, kind='stable'):
    kp = np.nonzero(keep)[0]
    d = np.linalg.norm(pts[kp] - pts[i], axis=1)
    if not np.any(d < np.minimum(r[kp], r[i])):
      keep[i] = True
  return keep


def _sphere(n, radius=1.0, seed=0):
  rng = np.random.default_rng(seed)
  v = rng.normal(size=(n, 3))
  return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


class PoissonTest(parameterized.TestCase):

  @pytest.mark.optimized  # its sampling loops: 11 s -> 8 s
  def test_separation_and_coverage(self):
    pts, r = _cloud()
    res = _poisson(jax.random.PRNGKey(0), jnp.asarray(pts), jnp.asarray(r),
                   max_samples=3000)
    self.assertFalse(bool(res.overflow))
    keep = np.asarray(res.keep)
    kp, kr = pts[keep], r[keep]
    self.assertEqual(int(res.count), keep.sum())
    d = spatial.distance.cdist(kp, kp)
    np.fill_diagonal(d, np.inf)
    # "min" convention: kept pairs are at least min(r_i, r_j) apart.
    self.assertTrue(np.all(d >= np.minimum(kr[:, None], kr[None, :])))
    # Every input point has a kept point within 2 r (thinned candidates).
    dist, _ = spatial.cKDTree(kp).query(pts)
    self.assertTrue(np.all(dist < 2 * r))
    # Without thinning: within r.
    res2 = _poisson(jax.random.PRNGKey(0), jnp.asarray(pts), jnp.asarray(r),
                    max_samples=3000, thin=False, max_per_cell=128)
    self.assertFalse(bool(res2.overflow))
    dist, _ = spatial.cKDTree(pts[np.asarray(res2.keep)]).query(pts)
    self.assertTrue(np.all(dist < r))
    # The compacted outputs agree with the mask.
    v = np.asarray(res.valid)
    np.testing.assert_array_equal(np.sort(np.asarray(res.index)[v]),
                                  np.nonzero(keep)[0])
    np.testing.assert_allclose(np.asarray(res.points)[v],
                               pts[np.asarray(res.index)[v]])

  def test_matches_sequential_greedy(self):
    pts, r = _cloud(n=400, seed=1)
    prio = np.random.default_rng(2).permutation(400).astype(np.float32)
    res = _poisson(None, jnp.asarray(pts), jnp.asarray(r), max_samples=400,
                   priority=jnp.asarray(prio), thin=False)
    np.testing.assert_array_equal(np.asarray(res.keep),
                                  _sequential_greedy(pts, r, prio))

  def test_deterministic_for_a_key(self):
    pts, r = _cloud(n=1000)
    a = _poisson(jax.random.PRNGKey(3), pts, r, max_samples=1000)
    b = _poisson(jax.random.PRNGKey(3), pts, r, max_samples=1000)
    c = _poisson(jax.random.PRNGKey(4), pts, r, max_samples=1000)
    np.testing.assert_array_equal(a.index, b.index)
    np.testing.assert_array_equal(a.keep, b.keep)
    self.assertFalse(np.array_equal(np.asarray(a.keep), np.asarray(c.keep)))

  def test_capacity_overflow(self):
    pts, r = _cloud(n=1000)
    full = _poisson(jax.random.PRNGKey(0), pts, r, max_samples=1000)
    n = int(full.count)
    small = _poisson(jax.random.PRNGKey(0), pts, r, max_samples=n - 10)
    self.assertTrue(bool(small.overflow))
    self.assertEqual(int(small.overflow_code), 1)
    self.assertEqual(int(np.sum(small.valid)), n - 10)
    # The first n - 10 are the highest-priority kept points.
    np.testing.assert_array_equal(small.index, full.index[: n - 10])
    with self.assertRaisesRegex(ValueError, 'raise max_samples'):
      sampling.check_overflow(small)
    crowded = _poisson(jax.random.PRNGKey(0), pts, r, max_samples=1000,
                       max_per_cell=2)
    self.assertTrue(int(crowded.overflow_code) & 2)
    with self.assertRaisesRegex(ValueError, 'max_per_cell'):
      sampling.check_overflow(crowded)
    sampling.check_overflow(full)  # no error

  def test_valid_mask_excludes_points(self):
    pts, r = _cloud(n=800)
    valid = pts[:, 1] < 0.5
    res = _poisson(jax.random.PRNGKey(0), pts, r, max_samples=800,
                   valid=jnp.asarray(valid))
    self.assertFalse(np.any(np.asarray(res.keep) & ~valid))
    dist, _ = spatial.cKDTree(pts[np.asarray(res.keep)]).query(pts[valid])
    self.assertTrue(np.all(dist < 2 * r[valid]))


def _radius_field(pts, kind):
  if kind == 'two_levels':
    return np.where(pts[:, 0] < 0.5, 0.06, 0.12).astype(np.float32)
  if kind == 'continuous_5x':  # PGAS-like: r / 5 .. r
    return (0.024 + 0.096 * pts[:, 1]).astype(np.float32)
  return np.full(len(pts), 0.08, np.float32)


class HostPoissonTest(parameterized.TestCase):

  @parameterized.named_parameters(
    ('_two_levels_thin', 'two_levels', True),
    ('_continuous_thin', 'continuous_5x', True),
    ('_uniform_thin', 'uniform', True),
    ('_continuous_nothin', 'continuous_5x', False))
  def test_host_equals_jit(self, kind, thin):
    # Same key -> same priorities -> the identical kept set, in the same
    # priority order, from the NumPy/SciPy and the jittable paths.
    pts, _ = _cloud(n=2500, seed=3)
    r = _radius_field(pts, kind)
    valid = np.random.default_rng(4).uniform(size=len(pts)) > 0.1
    key = jax.random.PRNGKey(7)
    a = _poisson(key, pts, r, max_samples=2500, valid=valid, thin=thin,
                 max_per_cell=64 if thin else 128)
    b = poisson.poisson_disk_host(key, pts, r, max_samples=2500, valid=valid,
                                  thin=thin)
    self.assertFalse(bool(a.overflow))
    self.assertEqual(int(b.overflow_code), 0)
    np.testing.assert_array_equal(np.asarray(a.keep), b.keep)
    np.testing.assert_array_equal(np.asarray(a.index), b.index)
    np.testing.assert_array_equal(np.asarray(a.valid), b.valid)

  def test_host_matches_sequential_greedy(self):
    pts, r = _cloud(n=600, seed=5)
    r = _radius_field(pts, 'continuous_5x')
    prio = np.random.default_rng(6).permutation(600).astype(np.float32)
    res = poisson.poisson_disk_host(None, pts, r, priority=prio, thin=False)
    np.testing.assert_array_equal(res.keep, _sequential_greedy(pts, r, prio))
    self.assertEqual(len(res.index), int(res.count))

  def test_host_properties_on_a_dense_cloud(self):
    # 40k points, radii varying 5x: separation (min convention), coverage
    # within 2 r, and the thinning bound of 64 representatives per cell.
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.0, 1.0, (40000, 3)).astype(np.float32)
    r = (0.02 + 0.08 * pts[:, 2]).astype(np.float32)
    res = poisson.poisson_disk_host(jax.random.PRNGKey(0), pts, r)
    keep = res.keep
    kp, kr = pts[keep], r[keep]
    tree = spatial.cKDTree(kp)
    pairs = tree.query_pairs(float(kr.max()), output_type='ndarray')
    d = np.linalg.norm(kp[pairs[:, 0]] - kp[pairs[:, 1]], axis=1)
    self.assertTrue(np.all(d >= np.minimum(kr[pairs[:, 0]],
                                           kr[pairs[:, 1]])))
    dist, _ = tree.query(pts)
    self.assertTrue(np.all(dist < 2 * r))
    prio = np.asarray(jax.random.uniform(jax.random.PRNGKey(0), (40000,)))
    rank = np.argsort(np.argsort(-prio, kind='stable'))
    rep, too_wide = poisson.thin_candidates_host(pts, r, rank,
                                                 np.ones(40000, bool))
    self.assertFalse(too_wide)
    lvl, h, _ = poisson.radius_levels(r, np.ones(40000, bool), 3)
    cell = np.floor((pts - pts.min(0)) / h[lvl][:, None]).astype(np.int64)
    _, per_cell = np.unique(np.c_[lvl, cell][rep], axis=0, return_counts=True)
    self.assertLessEqual(per_cell.max(), poisson.MAX_PER_CELL)
    self.assertGreater(per_cell.max(), 8)  # the bound is exercised

  def test_radius_levels_are_exact(self):
    half_up = np.nextafter(np.float32(0.5), np.float32(1.0))
    r = np.array([1.0, 0.5, half_up, 0.25, 0.1, 0.01], np.float32)
    lvl, h, r_max = poisson.radius_levels(r, np.ones(6, bool), 3)
    np.testing.assert_array_equal(lvl, [0, 1, 0, 2, 2, 2])
    np.testing.assert_array_equal(h, np.float32([1.0, 0.5, 0.25]))
    lvl_j, _, _ = poisson.radius_levels(jnp.asarray(r), jnp.ones(6, bool), 3)
    np.testing.assert_array_equal(lvl_j, lvl)

  def test_host_bad_radii_and_overflow(self):
    pts, r = _cloud(n=500)
    r = r.copy()
    r[:10] = 0.0
    r[10:20] = np.nan
    res = poisson.poisson_disk_host(jax.random.PRNGKey(0), pts, r)
    self.assertFalse(np.any(res.keep[:20]))
    small = poisson.poisson_disk_host(jax.random.PRNGKey(0), pts, r,
                                      max_samples=5)
    self.assertEqual(int(small.overflow_code), 1)
    np.testing.assert_array_equal(small.index, res.index[:5])
    # Radii spanning 2^14: the voxel refinement of the last level runs out.
    r2 = np.full(500, 1.0, np.float32)
    r2[0] = 1e-5
    wide = poisson.poisson_disk_host(jax.random.PRNGKey(0), pts, r2)
    self.assertTrue(int(wide.overflow_code) & 16)
    with self.assertRaisesRegex(ValueError, 'num_levels'):
      sampling.check_overflow(wide)
    with self.assertRaisesRegex(ValueError, 'PRNG key'):
      poisson.poisson_disk_host(None, pts, r)

  def test_budget_search_is_short(self):
    # The secant search needs a handful of evaluations, not ~12 bisections.
    rng = np.random.default_rng(1)
    pts = rng.uniform(0.0, 1.0, (30000, 3)).astype(np.float32)
    r = (0.02 + 0.08 * pts[:, 2]).astype(np.float32)
    fn = poisson.make_poisson_host(jax.random.PRNGKey(0), pts)
    calls = []

    def sample_fn(rad):
      res = fn(np.asarray(rad), 3000)
      calls.append(int(res.count))
      return res

    mult, res = pgas.scale_for_budget(sample_fn, r, 3000, rtol=0.02)
    self.assertLessEqual(int(res.count), 3000)
    self.assertGreaterEqual(int(res.count), 0.98 * 3000)
    self.assertLessEqual(len(calls), 6, calls)
    np.testing.assert_array_equal(res.keep, fn(r * mult, 3000).keep)


class PGASTest(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    self.pts = _sphere(1500).astype(np.float32)
    self.cfg = pgas.PGASConfig(base_radius=0.3)

  def _count(self, E, K_hat):
    r = pgas.adaptive_radius(np.full(len(self.pts), E),
                             np.full(len(self.pts), K_hat), self.cfg)
    res = _poisson(jax.random.PRNGKey(0), self.pts, r.astype(np.float32),
                   max_samples=1500)
    self.assertFalse(bool(res.overflow))
    return int(res.count)

  @pytest.mark.optimized  # its sampling loops: 7 s -> 4.6 s
  def test_count_grows_as_stiffness_falls(self):
    counts = [self._count(E, 3.0) for E in (1e7, 1e6, 2e5, 5e4)]
    self.assertTrue(all(a < b for a, b in zip(counts, counts[1:])), counts)

  def test_count_grows_with_curvature(self):
    counts = [self._count(1e6, k) for k in (1.0, 3.0, 10.0)]
    self.assertTrue(all(a < b for a, b in zip(counts, counts[1:])), counts)

  def test_radius_formula(self):
    cfg = self.cfg
    r = pgas.adaptive_radius(np.array([1e7, 1e6, 1e6, 1e2]),
                             np.array([1.0, 1.0, 10.0, 1.0]), cfg)
    # E_hat=1: k sqrt(1) r > r -> capped at r; E_hat=0.1, K_hat=1: r;
    # E_hat=0.1, K_hat=10: sqrt(10) sqrt(0.01) r; tiny E: floor.
    np.testing.assert_allclose(
      r, [0.3, 0.3, 0.3 * np.sqrt(10) * 0.1, 0.3 * cfg.min_radius_frac],
      rtol=1e-12)
    rj = pgas.adaptive_radius(jnp.asarray([1e6]), jnp.asarray([10.0]), cfg)
    self.assertIsInstance(rj, jax.Array)

  def test_local_curvature_flat_vs_curved(self):
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    small = 0.1 * _sphere(600, seed=1) + np.array([3.0, 0, 0])
    k_plane = curvature.local_curvature(plane, k=16)
    k_ball = curvature.local_curvature(small, k=16)
    self.assertLess(k_plane.max(), 1e-10)
    self.assertGreater(np.median(k_ball), 1e-3)
    # Per-Gaussian measure: flat disc 0, isotropic 1/3.
    kg = curvature.gaussian_curvature(
      np.stack([np.diag([1.0, 1.0, 0.0]), np.eye(3)]))
    np.testing.assert_allclose(kg, [0.0, 1.0 / 3.0], atol=1e-12)

  def test_pgas_curvature_densifies_curved_regions(self):
    # A flat plate with a small ball on it: more drivers per Gaussian on the
    # ball (local curvature) at the same E.
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)]
    ball = 0.15 * _sphere(600, seed=2) + np.array([0.0, 0.0, 0.4])
    pts = np.concatenate([plane, ball]).astype(np.float32)
    covs = np.broadcast_to(np.diag([1e-4, 1e-4, 1e-6]), (len(pts), 3, 3))
    cfg = pgas.PGASConfig(base_radius=0.25)
    k_hat, info = pgas.pgas_curvature(pts, np.ones(len(pts), bool),
                                      np.zeros(len(pts), int), covs, cfg)
    self.assertGreater(np.median(k_hat[3000:]), np.median(k_hat[:3000]))
    r = pgas.adaptive_radius(np.full(len(pts), 1e5), k_hat, cfg)
    res = _poisson(jax.random.PRNGKey(1), pts, r.astype(np.float32),
                   max_samples=len(pts))
    self.assertFalse(bool(res.overflow))
    keep = np.asarray(res.keep)
    # Drivers per unit area (plane 2x2, ball 4 pi 0.15^2).
    per_area_ball = keep[3000:].sum() / (4 * np.pi * 0.15**2)
    per_area_plane = keep[:3000].sum() / 4.0
    self.assertGreater(per_area_ball, 1.5 * per_area_plane)
    self.assertIn(0, info['k_obj'])

  def test_flat_scene_noise_stays_flat(self):
    # The local range is stretched over [v_min, v_max]; with nothing curved
    # in the scene it was the noise's (K_hat 1.07-3.37 on this plate).
    rng = np.random.default_rng(0)
    plate = np.c_[rng.uniform(-1, 1, (2000, 2)),
                  1e-7 * rng.normal(size=2000)]
    covs = np.broadcast_to(np.diag([1e-4, 1e-4, 0.0]), (2000, 3, 3))
    k_hat, _ = pgas.pgas_curvature(plate, np.ones(2000, bool),
                                   np.zeros(2000, int), covs, self.cfg)
    np.testing.assert_allclose(k_hat, 1.0, atol=1e-3)

  def test_interior_points_use_object_curvature(self):
    pts = np.concatenate([_sphere(500), 0.3 * _sphere(50, seed=3)])
    surf = np.arange(550) < 500
    covs = np.broadcast_to(np.eye(3) * 1e-4, (550, 3, 3))
    k_hat, info = pgas.pgas_curvature(pts, surf, np.zeros(550, int), covs,
                                      self.cfg)
    # Isotropic Gaussians: K_g = 1/3 -> K_hat_obj = v_max.
    self.assertAlmostEqual(info['k_obj'][0], 10.0)
    np.testing.assert_allclose(k_hat[500:], 10.0)

  def test_scale_for_budget(self):
    pts = _sphere(1000, seed=4).astype(np.float32)
    r = pgas.adaptive_radius(np.full(1000, 1e6), np.full(1000, 3.0),
                             self.cfg)
    fn = lambda rad: _poisson(jax.random.PRNGKey(0), pts, rad,
                              max_samples=1000, max_per_cell=64,
                              max_neighbors=128)
    mult, res = pgas.scale_for_budget(fn, r, 100, lo=0.2, hi=5.0, iters=10)
    self.assertLessEqual(int(res.count), 100)
    self.assertGreater(int(res.count), 85)
    self.assertGreater(mult, 0)

  def test_bad_config(self):
    with self.assertRaisesRegex(ValueError, 'base_radius'):
      pgas.PGASConfig(base_radius=0.0)
    with self.assertRaisesRegex(ValueError, 'v_min'):
      pgas.PGASConfig(base_radius=1.0, v_min=0.5)


class DrivingTest(parameterized.TestCase):

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    from physsplat_jax.types import Gaussians
    pts = np.concatenate([_sphere(600), _sphere(600, seed=1) + [3.0, 0, 0]])
    n = len(pts)
    g = Gaussians(
      means=jnp.asarray(pts, jnp.float32),
      log_scales=jnp.full((n, 3), -3.0), quats=jnp.tile(
        jnp.array([1.0, 0, 0, 0]), (n, 1)),
      opacity_logits=jnp.full((n,), 3.0), sh=jnp.zeros((n, 1, 3)))
    cls.ids = np.r_[np.zeros(600), np.ones(600)].astype(np.int32)
    cls.cand = sampling.make_candidates(
      jax.random.PRNGKey(0), g, cls.ids,
      fill_config=sampling.FillConfig(grid_res=16))

  def test_thin_solid_and_degenerate_objects_get_a_volume(self):
    from physsplat_jax.types import Gaussians
    rng = np.random.default_rng(3)

    def gaussians(pts, log_scales):
      n = len(pts)
      return Gaussians(
        means=jnp.asarray(pts, jnp.float32),
        log_scales=jnp.asarray(log_scales, jnp.float32),
        quats=jnp.tile(jnp.array([1.0, 0, 0, 0]), (n, 1)),
        opacity_logits=jnp.full((n,), 3.0), sh=jnp.zeros((n, 1, 3)))

    # A bar 0.5 x 0.05 x 0.05 sampled through its volume with round
    # Gaussians (the MPDP cantilever): the fill band covers it and the
    # surface level set encloses nothing, so the hull must stand in.
    half = np.array([0.25, 0.025, 0.025])
    bar = rng.uniform(-half, half, (96, 3))
    g = gaussians(bar, np.full((96, 3), np.log(0.02)))
    c = sampling.make_candidates(jax.random.PRNGKey(0), g,
                                 np.zeros(96, np.int32),
                                 fill_config=sampling.FillConfig(grid_res=16))
    np.testing.assert_allclose(c.volume.sum(), spatial.ConvexHull(
      c.x).volume, rtol=1e-9)
    self.assertGreater(c.volume.sum(), 0.5 * 0.5 * 0.05 * 0.05)
    # Coplanar centres without fill: flat Gaussians are read as a sheet,
    # round ones are an error that names the object.
    sheet = np.c_[rng.uniform(-1, 1, (200, 2)), np.zeros(200)]
    flat = gaussians(sheet, np.tile(np.log([0.1, 0.1, 0.005]), (200, 1)))
    c = sampling.make_candidates(jax.random.PRNGKey(0), flat,
                                 np.full(200, 2, np.int32), fill=False)
    self.assertTrue(np.all(c.volume > 0))
    # Area 4 times thickness 2 sqrt(3) sigma; the k-NN area estimate of 200
    # random centres runs ~20 % high (the square's edge), hence 0.25.
    np.testing.assert_allclose(c.volume.sum(), 4.0 * 2 * np.sqrt(3) * 0.005,
                               rtol=0.25)
    with self.assertRaisesRegex(ValueError, 'object 2 has zero volume'):
      sampling.make_candidates(
        jax.random.PRNGKey(0), gaussians(sheet, np.full((200, 3), -3.0)),
        np.full(200, 2, np.int32), fill=False)

  def test_candidates(self):
    c = self.cand
    self.assertEqual(int(c.is_surface.sum()), 1200)
    self.assertGreater(int((~c.is_surface).sum()), 100)
    per_obj = [c.volume[c.object_ids == o].sum() for o in (0, 1)]
    np.testing.assert_allclose(per_obj, 4 / 3 * np.pi, rtol=0.15)
    # Uniform density: a fill point owns one fill cell (dx^3), the Gaussian
    # centres of an object share the rest of its enclosed volume equally.
    for o in (0, 1):
      fill = c.volume[(c.object_ids == o) & ~c.is_surface]
      surf = c.volume[(c.object_ids == o) & c.is_surface]
      np.testing.assert_allclose(fill, fill[0], rtol=1e-12)
      np.testing.assert_allclose(surf, surf[0], rtol=1e-12)
      dx = fill[0] ** (1.0 / 3.0)
      self.assertAlmostEqual(dx, 2.0 / (16 - 8), delta=0.02)  # ext / inner

  @parameterized.named_parameters(('_pgas', 'pgas'), ('_uniform', 'uniform'))
  def test_budget_search(self, method):
    cfg = pgas.PGASConfig(base_radius=0.6)
    d = sampling.select_drivers(
      jax.random.PRNGKey(1), self.cand, method, E={0: 1e5, 1: 5e6},
      config=cfg, budget=150, lloyd_steps=0)
    self.assertLessEqual(len(d.x), 150)
    self.assertGreaterEqual(len(d.x), 0.98 * 150)
    np.testing.assert_allclose(d.volume.sum(), self.cand.volume.sum(),
                               rtol=1e-9)
    # The drivers are a Poisson-disk sample at the scaled radii.
    dd = spatial.distance.cdist(d.x, d.x)
    np.fill_diagonal(dd, np.inf)
    self.assertTrue(np.all(dd >= np.minimum.outer(d.radius, d.radius)
                           * (1 - 1e-6)))
    # The jittable backend keeps the same drivers.
    dj = sampling.select_drivers(
      jax.random.PRNGKey(1), self.cand, method, E={0: 1e5, 1: 5e6},
      config=cfg, budget=150, backend='jax', lloyd_steps=0)
    np.testing.assert_array_equal(np.sort(d.candidate_index),
                                  np.sort(dj.candidate_index))

  def test_pgas_budget_keeps_the_base_radius_first(self):
    # A tight budget: the cap-first search keeps the stiff object at the
    # base resolution and takes the soft object's extra drivers away; one
    # factor on every radius starves the stiff object instead.
    cfg = pgas.PGASConfig(base_radius=0.5)
    E = {0: 1e5, 1: 5e6}
    key = jax.random.PRNGKey(2)
    cap = sampling.select_drivers(key, self.cand, 'pgas', E=E, config=cfg,
                                  budget=120)
    one = sampling.select_drivers(key, self.cand, 'pgas', E=E, config=cfg,
                                  budget=120, pgas_cap_first=False)
    n_cap = [np.sum(cap.object_ids == o) for o in (0, 1)]
    n_one = [np.sum(one.object_ids == o) for o in (0, 1)]
    self.assertGreater(n_cap[1], 1.5 * n_one[1], (n_cap, n_one))
    self.assertGreater(n_cap[0], n_cap[1])  # still more on the soft one
    self.assertLessEqual(cap.radius.max(), cfg.base_radius * (1 + 1e-6))

  def test_capped_family(self):
    r = np.array([0.1, 0.2, 0.5])
    fn = pgas.capped_family(r, 0.5)
    np.testing.assert_allclose(fn(0.5), 0.5 * r)
    np.testing.assert_allclose(fn(1.0), r)
    np.testing.assert_allclose(fn(2.0), [0.2, 0.4, 0.5])  # capped
    np.testing.assert_allclose(fn(10.0), [1.0, 1.0, 1.0])  # uniform beyond
    ts = np.geomspace(0.1, 50, 200)
    rs = np.stack([fn(t) for t in ts])
    self.assertTrue(np.all(np.diff(rs, axis=0) >= -1e-15))

  def test_lloyd_step_centres_the_drivers(self):
    cfg = pgas.PGASConfig(base_radius=0.6)
    kw = dict(E={0: 1e5, 1: 5e6}, config=cfg, budget=100)
    d0 = sampling.select_drivers(jax.random.PRNGKey(1), self.cand, 'uniform',
                                 lloyd_steps=0, **kw)
    d1 = sampling.select_drivers(jax.random.PRNGKey(1), self.cand, 'uniform',
                                 lloyd_steps=1, **kw)
    np.testing.assert_array_equal(d0.candidate_index, d1.candidate_index)
    np.testing.assert_array_equal(d0.x, self.cand.x[d0.candidate_index])
    self.assertFalse(np.allclose(d0.x, d1.x))

    def quantisation(d):  # volume-weighted squared distance to the driver
      err = 0.0
      for o in (0, 1):
        c = self.cand.object_ids == o
        dist, _ = spatial.cKDTree(d.x[d.object_ids == o]).query(
          self.cand.x[c])
        err += np.sum(self.cand.volume[c] * dist**2)
      return err

    self.assertLess(quantisation(d1), 0.9 * quantisation(d0))
    np.testing.assert_allclose(d1.volume.sum(), self.cand.volume.sum(),
                               rtol=1e-9)

  @parameterized.named_parameters(
    ('_pgas', 'pgas'), ('_uniform', 'uniform'), ('_kmeans', 'kmeans'))
  def test_budget_and_volume(self, method):
    # Radius-driven for the Poisson methods (the budget bisection is
    # tested in PGASTest.test_scale_for_budget), budget-driven for K-means.
    cfg = pgas.PGASConfig(base_radius=0.6)
    d = sampling.select_drivers(
      jax.random.PRNGKey(1), self.cand, method, E={0: 1e5, 1: 5e6},
      config=cfg, budget=100 if method == 'kmeans' else None)
    self.assertGreater(len(d.x), 40)
    self.assertLess(len(d.x), 600)
    np.testing.assert_allclose(d.volume.sum(), self.cand.volume.sum(),
                               rtol=1e-9)
    n_soft = np.sum(d.object_ids == 0)
    n_stiff = np.sum(d.object_ids == 1)
    if method == 'pgas':  # the soft object gets more drivers
      self.assertGreater(n_soft, 1.5 * n_stiff)
    else:  # same shape and size: about the same number
      self.assertLess(abs(n_soft - n_stiff), 0.25 * (n_soft + n_stiff))

  def test_kmeans_keeps_exactly_the_budget(self):
    # Split by candidate count with largest-remainder rounding: an object of
    # 2 candidates gets 2 drivers (not 4, two of them duplicates of volume
    # 0) and three equal objects share the other 98 as 33/33/32 (rounding
    # each share gave 4 + 3 x 33 = 103).
    rng = np.random.default_rng(0)
    sizes = (300, 300, 300, 2)
    x = np.concatenate([rng.uniform(size=(s, 3)) + 3.0 * i
                        for i, s in enumerate(sizes)])
    ob = np.concatenate([np.full(s, i, np.int32)
                         for i, s in enumerate(sizes)])
    m = len(x)
    cand = sampling.Candidates(
      x=x, is_surface=np.ones(m, bool), object_ids=ob,
      covariances=np.zeros((m, 3, 3)), volume=np.full(m, 1.0 / m),
      gaussian_index=np.arange(m, dtype=np.int32))
    d = sampling.select_drivers(jax.random.PRNGKey(0), cand, 'kmeans',
                                budget=100, kmeans_iters=2)
    self.assertEqual(len(d.x), 100)
    self.assertEqual(sorted(np.bincount(d.object_ids)[:3]), [32, 33, 33])
    self.assertEqual(np.sum(d.object_ids == 3), 2)
    self.assertTrue(np.all(d.volume > 0))
    np.testing.assert_allclose(d.volume.sum(), 1.0, rtol=1e-9)


class KMeansTest(parameterized.TestCase):

  @parameterized.named_parameters(('_pp', 'kmeans++'), ('_random', 'random'))
  def test_recovers_separated_blobs(self, init):
    rng = np.random.default_rng(0)
    centres = np.array([[0, 0, 0], [5, 0, 0], [0, 5, 0], [0, 0, 5.0]])
    pts = (centres[:, None] + 0.1 * rng.normal(size=(4, 250, 3))).reshape(
      -1, 3).astype(np.float32)
    fn = jax.jit(functools.partial(sampling.kmeans, num_clusters=4,
                                   num_iters=10, init=init))
    res = fn(jax.random.PRNGKey(1), jnp.asarray(pts))
    got = np.asarray(res.centers)
    d = spatial.distance.cdist(centres, got)
    if init == 'kmeans++':  # D^2 seeding finds all four blobs
      self.assertLess(d.min(1).max(), 0.05)
      np.testing.assert_array_equal(np.sort(res.counts), [250] * 4)
    self.assertEqual(int(np.sum(res.counts)), 1000)
    # Lloyd never increases the inertia.
    res0 = sampling.kmeans(jax.random.PRNGKey(1), jnp.asarray(pts), 4,
                           num_iters=0, init=init)
    self.assertLessEqual(float(res.inertia), float(res0.inertia) + 1e-3)

  def test_valid_mask_and_determinism(self):
    rng = np.random.default_rng(1)
    pts = jnp.asarray(rng.uniform(size=(500, 3)), jnp.float32)
    valid = jnp.arange(500) < 300
    a = sampling.kmeans(jax.random.PRNGKey(0), pts, 16, valid=valid)
    b = sampling.kmeans(jax.random.PRNGKey(0), pts, 16, valid=valid)
    np.testing.assert_array_equal(a.centers, b.centers)
    self.assertTrue(np.all(np.asarray(a.assign)[300:] == -1))
    self.assertEqual(int(a.counts.sum()), 300)
    self.assertTrue(np.all(np.asarray(a.centers)[:, None] != 0))
    with self.assertRaisesRegex(ValueError, 'init'):
      sampling.kmeans(jax.random.PRNGKey(0), pts, 4, init='bogus')


if __name__ == '__main__':
  absltest.main()
