"""Tests for physsplat_jax.sampling.filling: interior filling of shells."""

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from absl.testing import absltest
from scipy import spatial

from physsplat_jax import gaussians as gs
from physsplat_jax.sampling import filling
from physsplat_jax.types import Gaussians

_fill = jax.jit(filling.fill_gaussians,
                static_argnames=('max_particles', 'config'))
_CFG = filling.FillConfig(grid_res=32)
VOLUME_RTOL = 0.1  # enclosed volume of a closed shell vs the true one


def _shell(n=4000, radius=1.0, seed=0, log_scale=-3.5, open_top=False):
  """Flat Gaussians tangent to a sphere shell."""
  rng = np.random.default_rng(seed)
  v = rng.normal(size=(n, 3))
  v /= np.linalg.norm(v, axis=1, keepdims=True)
  if open_top:
    v = v[v[:, 2] < 0.3]
    n = len(v)
  means = radius * v
  # Rotation taking e3 to the normal: the third (thin) axis is the normal.
  z = np.array([0.0, 0.0, 1.0])
  axis = np.cross(z, v)
  s = np.linalg.norm(axis, axis=1, keepdims=True)
  c = v[:, 2:3]
  half = 0.5 * np.arctan2(s, c)
  ax = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), [1.0, 0, 0])
  quats = np.c_[np.cos(half), np.sin(half) * ax]
  ls = np.tile([log_scale, log_scale, log_scale - 2.0], (n, 1))
  f = lambda a: jnp.asarray(a, jnp.float32)
  return Gaussians(
    means=f(means), log_scales=f(ls), quats=f(quats),
    opacity_logits=f(np.full(n, 3.0)), sh=jnp.zeros((n, 1, 3)))


def _run(g, key=jax.random.PRNGKey(0), max_particles=40000, config=_CFG):
  return _fill(key, g.means, g.log_scales, g.quats, g.opacities,
               max_particles=max_particles, config=config)


class FillingTest(absltest.TestCase):

  def test_sphere_shell_interior(self):
    g = _shell()
    res = _run(g)
    self.assertFalse(bool(res.overflow))
    p = np.asarray(res.points)[np.asarray(res.valid)]
    r = np.linalg.norm(p, axis=1)
    dx = float(res.dx)
    # Everything inside the sphere up to the cell the surface cuts (the
    # flood-fill interior excludes the occupied shell), filled up to about
    # a shell thickness (~2 cells).
    self.assertLess(r.max(), 1.0 + dx)
    self.assertGreater(r.max(), 1.0 - 3 * dx)
    vol = len(p) * dx**3
    want = 4 / 3 * np.pi * (1.0 - dx) ** 3  # about a cell of shell inside
    self.assertLess(abs(vol - want) / want, 0.15)
    # Roughly uniform: octants within 10 % of each other.
    octant = (p[:, 0] > 0) * 4 + (p[:, 1] > 0) * 2 + (p[:, 2] > 0)
    counts = np.bincount(octant, minlength=8)
    self.assertLess(counts.max() / counts.min(), 1.1)
    # Radial uniformity: the fraction within r < 0.5 matches the volume.
    frac = np.mean(r < 0.5) / np.mean(r < 0.8)
    self.assertAlmostEqual(frac, (0.5 / 0.8) ** 3, delta=0.03)

  def test_open_shell_is_not_filled(self):
    g = _shell(open_top=True)
    closed = _run(_shell())
    self.assertGreater(int(closed.count), 1000)
    # The flood fill reaches every cell of the open bowl.
    self.assertEqual(int(_run(g).count), 0)
    # PhysGaussian's 6 axis rays: cells right under the curved rim see the
    # wall along all 6 axes, so a few percent remain.
    rays = filling.fill_gaussians_host(
      None, g.means, g.log_scales, g.quats, g.opacities, 40000,
      dataclasses.replace(_CFG, inside_test='rays'))
    self.assertGreater(int(rays.count), 0)
    self.assertLess(int(rays.count), 0.05 * int(closed.count))

  def test_closed_shell_with_a_hole_fills_to_its_volume(self):
    # A cap of half-angle ~7 degrees (0.12 of the radius, ~1.5 cells at
    # grid 32) removed: the closing shuts it, so the interior fills and the
    # enclosed volume matches the sphere's.
    g = _shell(n=4000)
    v = np.asarray(g.means)
    keep = np.nonzero(v[:, 0] < 0.993)[0]
    g = g.subset(keep)
    ids = np.zeros(len(keep), np.int32)
    pts, _, info = filling.fill_objects(None, g, ids, config=_CFG,
                                        return_info=True)
    want = 4.0 / 3.0 * np.pi
    self.assertLess(abs(info[0]['volume'] - want) / want, VOLUME_RTOL)
    fill_vol = len(pts) * info[0]['dx'] ** 3
    self.assertGreater(fill_vol, 0.6 * want)  # interior filled, not shell
    # Without the closing the flood gets in through the hole.
    cfg0 = dataclasses.replace(_CFG, closing_cells=0)
    pts0, _ = filling.fill_objects(None, g, ids, config=cfg0)
    self.assertLess(len(pts0), 0.05 * len(pts))

  def test_parallel_plates_are_not_filled_between(self):
    # Two square plates 0.5 apart (6 cells at grid 32), open at the sides:
    # an open structure, the gap is wider than the closing.
    rng = np.random.default_rng(0)
    n = 3000
    xy = rng.uniform(-1.0, 1.0, (2 * n, 2))
    z = np.r_[np.full(n, -0.25), np.full(n, 0.25)]
    f = lambda a: jnp.asarray(a, jnp.float32)
    g = Gaussians(
      means=f(np.c_[xy, z]), log_scales=f(np.tile([-3.5, -3.5, -5.5],
                                                  (2 * n, 1))),
      quats=f(np.tile([1.0, 0, 0, 0], (2 * n, 1))),
      opacity_logits=f(np.full(2 * n, 3.0)), sh=jnp.zeros((2 * n, 1, 3)))
    ids = np.zeros(2 * n, np.int32)
    pts, _, info = filling.fill_objects(None, g, ids, config=_CFG,
                                        return_info=True)
    self.assertEqual(len(pts), 0)
    # Nothing enclosed; the sheet estimate is two plates of area 4 and
    # thickness 2 sqrt(3) exp(-5.5).
    want = 2 * 4.0 * 2 * np.sqrt(3) * np.exp(-5.5)
    self.assertLess(info[0]['volume'], 0.1 * 4.0 * 0.5)
    self.assertAlmostEqual(info[0]['sheet_volume'], want, delta=0.2 * want)

  def test_deterministic_and_jittered(self):
    g = _shell(n=2000)
    cfg = filling.FillConfig(grid_res=16, particles_per_cell=2)
    a = _run(g, jax.random.PRNGKey(1), 8000, cfg)
    b = _run(g, jax.random.PRNGKey(1), 8000, cfg)
    c = _run(g, jax.random.PRNGKey(2), 8000, cfg)
    np.testing.assert_array_equal(a.points, b.points)
    self.assertFalse(np.array_equal(np.asarray(a.points),
                                    np.asarray(c.points)))
    self.assertEqual(int(a.count), 2 * int(np.sum(a.inside)))
    centres = filling.fill_gaussians(None, g.means, g.log_scales, g.quats,
                                     g.opacities, 4000,
                                     filling.FillConfig(grid_res=16))
    self.assertEqual(int(centres.count), int(np.sum(a.inside)))

  def test_pathological_covariances_stay_bounded(self):
    g = _shell(n=4000)
    rng = np.random.default_rng(1)
    ls = np.asarray(g.log_scales).copy()
    bad = rng.choice(4000, 400, replace=False)
    ls[bad[:100]] = 80.0        # exp overflows to inf
    ls[bad[100:200]] = 30.0     # radius 1e13
    ls[bad[200:300]] = -80.0    # zero scale
    ls[bad[300:]] = np.nan
    q = np.asarray(g.quats).copy()
    q[bad[300:350]] = 0.0       # zero quaternion
    g = g.replace(log_scales=jnp.asarray(ls, jnp.float32),
                  quats=jnp.asarray(q, jnp.float32))
    t0 = time.perf_counter()
    res = _run(g)
    res.points.block_until_ready()
    elapsed = time.perf_counter() - t0
    self.assertLess(elapsed, 60.0)  # includes compile; ~1 s warm
    p = np.asarray(res.points)[np.asarray(res.valid)]
    self.assertTrue(np.all(np.isfinite(p)))
    self.assertGreater(len(p), 1000)
    self.assertLess(np.linalg.norm(p, axis=1).max(), 1.0)

  def test_overflow_and_errors(self):
    g = _shell(n=2000)
    res = _run(g, max_particles=100)
    self.assertTrue(bool(res.overflow))
    self.assertEqual(int(np.sum(res.valid)), 100)
    ids = np.zeros(2000, np.int32)
    with self.assertRaisesRegex(ValueError, 'max_particles_per_object'):
      filling.fill_objects(None, g, ids, max_particles_per_object=10,
                           config=filling.FillConfig(grid_res=16))
    bad = g.replace(means=g.means.at[0, 0].set(jnp.nan))
    with self.assertRaisesRegex(ValueError, 'non-finite means'):
      filling.fill_objects(None, bad, ids,
                           config=filling.FillConfig(grid_res=16))
    with self.assertRaisesRegex(ValueError, 'grid_res'):
      filling.FillConfig(grid_res=1024)
    # The margins left no cell (ZeroDivisionError in the fill).
    with self.assertRaisesRegex(ValueError, r'grid_res=8: .* margin_cells'):
      filling.FillConfig(grid_res=8)

  def test_fill_objects_two_spheres(self):
    a = _shell(n=2000)
    b = _shell(n=2000, radius=0.5, seed=1)
    b = b.replace(means=b.means + jnp.array([3.0, 0, 0]))
    from physsplat_jax.types import concatenate_gaussians
    g = concatenate_gaussians([a, b])
    ids = np.r_[np.zeros(2000), np.ones(2000)].astype(np.int32)
    cfg = filling.FillConfig(grid_res=16)
    pts, obj = filling.fill_objects(jax.random.PRNGKey(0), g, ids,
                                    config=cfg)
    self.assertEqual(set(np.unique(obj)), {0, 1})
    self.assertTrue(np.all(np.linalg.norm(pts[obj == 0], axis=1) < 1.0))
    c = pts[obj == 1] - np.array([3.0, 0, 0])
    self.assertTrue(np.all(np.linalg.norm(c, axis=1) < 0.5))
    pts2, _ = filling.fill_objects(jax.random.PRNGKey(0), g, ids, config=cfg)
    np.testing.assert_array_equal(pts, pts2)

  def test_fill_mesh(self):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    pts = filling.fill_mesh(mesh, 0.1)
    self.assertTrue(np.all(np.linalg.norm(pts, axis=1) < 1.0))
    vol = len(pts) * 0.1**3
    self.assertAlmostEqual(vol, mesh.volume, delta=0.1 * mesh.volume)
    box = trimesh.creation.box()
    box.faces = box.faces[:-2]
    with self.assertRaisesRegex(ValueError, 'watertight'):
      filling.fill_mesh(box, 0.1)

  def test_host_twin_matches_jit(self):
    # The NumPy filler (fill_objects' default) computes the same grid,
    # occupancy and interior as the jitted one (float64 vs float32: a cell
    # exactly on the threshold may differ).
    g = _shell(n=4000)
    a = _run(g)
    b = filling.fill_gaussians_host(
      jax.random.PRNGKey(0), g.means, g.log_scales, g.quats, g.opacities,
      40000, _CFG)
    self.assertAlmostEqual(float(a.dx), float(b.dx), places=6)
    np.testing.assert_allclose(np.asarray(a.origin), b.origin, atol=1e-6)
    occ_diff = np.sum(np.asarray(a.occupied) != b.occupied)
    self.assertLessEqual(occ_diff, 0.001 * b.occupied.size)
    in_diff = np.sum(np.asarray(a.inside) != b.inside)
    self.assertLessEqual(in_diff, 0.001 * b.inside.size)
    self.assertEqual(int(b.count), int(np.sum(b.inside)))
    self.assertEqual(len(b.points), int(b.count))
    # Every host point lies in an interior cell.
    ijk = np.floor((b.points - b.origin) / b.dx).astype(int)
    self.assertTrue(np.all(b.inside[ijk[:, 0], ijk[:, 1], ijk[:, 2]]))
    # Deterministic for a key, jittered differently for another.
    c = filling.fill_gaussians_host(
      jax.random.PRNGKey(0), g.means, g.log_scales, g.quats, g.opacities,
      40000, _CFG)
    np.testing.assert_array_equal(b.points, c.points)
    d = filling.fill_gaussians_host(
      jax.random.PRNGKey(5), g.means, g.log_scales, g.quats, g.opacities,
      40000, _CFG)
    self.assertFalse(np.array_equal(b.points, d.points))
    occ = np.array(a.occupied)
    np.testing.assert_array_equal(filling.interior_cells_host(occ, 5),
                                  np.asarray(filling.interior_cells(occ, 5)))
    occ[::3, 5, ::2] = False  # holes of every size
    np.testing.assert_array_equal(
      filling.enclosed_cells_host(occ, 2),
      np.asarray(jax.jit(filling.enclosed_cells, static_argnums=1)(occ, 2)))

  def test_host_grid_matches_jit_at_the_faces(self):
    # The host splat (a matrix product of the quadratic forms, no per-cell
    # test for windows inside the grid) against the jitted one, with
    # Gaussians whose windows cross the grid's faces and some outside it.
    rng = np.random.default_rng(3)
    cfg = filling.FillConfig(grid_res=12, margin_cells=2, footprint=3,
                             max_sigma_cells=3.0)
    n = 300
    origin, dx = np.array([0.1, -0.2, 0.05]), 0.1
    means = origin + rng.uniform(-0.3, 1.5, (n, 3))  # the grid: [0, 1.2)
    ls = np.log(rng.uniform(0.02, 0.4, (n, 3)))
    q = rng.normal(size=(n, 4))
    op = rng.uniform(0.0, 1.0, n)
    d_host, occ_host = filling.occupancy_grid_host(means, ls, q, op, origin,
                                                   dx, cfg)
    d_jit, occ_jit = jax.jit(filling.occupancy_grid, static_argnums=6)(
      jnp.asarray(means, jnp.float32), jnp.asarray(ls, jnp.float32),
      jnp.asarray(q, jnp.float32), jnp.asarray(op, jnp.float32),
      jnp.asarray(origin, jnp.float32), jnp.float32(dx), cfg)
    self.assertGreater(d_host[0].sum() + d_host[-1].sum(), 1.0)  # faces hit
    np.testing.assert_allclose(d_host, np.asarray(d_jit), rtol=2e-4,
                               atol=2e-5)
    np.testing.assert_array_equal(occ_host, np.asarray(occ_jit))

  def test_host_pathological_covariances_and_speed(self):
    g = _shell(n=20000)
    rng = np.random.default_rng(1)
    ls = np.asarray(g.log_scales).copy()
    bad = rng.choice(20000, 2000, replace=False)
    ls[bad[:500]] = 80.0
    ls[bad[500:1000]] = 30.0
    ls[bad[1000:1500]] = -80.0
    ls[bad[1500:]] = np.nan
    q = np.asarray(g.quats).copy()
    q[bad[:300]] = 0.0
    g = g.replace(log_scales=jnp.asarray(ls, jnp.float32),
                  quats=jnp.asarray(q, jnp.float32))
    t0 = time.perf_counter()
    pts, _ = filling.fill_objects(jax.random.PRNGKey(0), g,
                                  np.zeros(20000, np.int32), config=_CFG)
    elapsed = time.perf_counter() - t0
    self.assertLess(elapsed, 20.0)  # ~0.3 s on a quiet core; no compile
    self.assertTrue(np.all(np.isfinite(pts)))
    self.assertGreater(len(pts), 1000)
    self.assertLess(np.linalg.norm(pts, axis=1).max(), 1.0)

  def test_interior_cells_on_a_box(self):
    occ = np.zeros((10, 10, 10), bool)
    occ[2:8, 2:8, 2] = occ[2:8, 2:8, 7] = True
    occ[2:8, 2, 2:8] = occ[2:8, 7, 2:8] = True
    occ[2, 2:8, 2:8] = occ[7, 2:8, 2:8] = True
    inside = np.asarray(filling.interior_cells(jnp.asarray(occ)))
    want = np.zeros_like(occ)
    want[3:7, 3:7, 3:7] = True
    np.testing.assert_array_equal(inside, want)
    occ[4, 4, 7] = False  # a hole in the lid
    inside5 = np.asarray(filling.interior_cells(jnp.asarray(occ), 5))
    self.assertTrue(inside5[4, 4, 5])
    inside6 = np.asarray(filling.interior_cells(jnp.asarray(occ), 6))
    self.assertFalse(inside6[4, 4, 5])


# Enclosed volume vs the true mesh volume of the built-in scenes' closed
# objects at fill grid 64 (measured -5 to -10 %, docs/sampling.md).
BUILTIN_VOLUME_RTOL = 0.15


@pytest.mark.slow
class BuiltinSceneVolumeTest(absltest.TestCase):
  """Volumes of the built-in scenes' objects (scene builds take seconds)."""

  def _info(self, name):
    from physsplat_jax import scenes  # noqa: PLC0415
    sc = scenes.load_scene(name)
    oid = np.asarray(sc.object_ids)
    _, _, info = filling.fill_objects(
      None, sc.gaussians, oid, config=filling.FillConfig(grid_res=64),
      return_info=True)
    return sc, oid, {sc.object_names[o]: v for o, v in info.items()}

  def test_tabletop_closed_objects(self):
    from physsplat_jax.scenes import tabletop as tt  # noqa: PLC0415
    _, _, info = self._info('tabletop')
    rng = np.random.default_rng(
      np.random.default_rng(0).integers(1 << 62, size=8)[4])
    true = {'jelly cube': tt.JELLY_EDGE ** 3,
            'rubber ball': trimesh.creation.icosphere(
              4, tt.BALL_RADIUS).volume,
            'metal can': trimesh.creation.cylinder(
              tt.CAN_RADIUS, tt.CAN_HEIGHT, sections=48).volume,
            'sand pile': tt._sand_mesh(rng).volume}
    for name, want in true.items():
      got = info[name]['volume']
      self.assertLess(abs(got - want) / want, BUILTIN_VOLUME_RTOL,
                      f'{name}: {got:.3e} vs {want:.3e}')

  def test_ficus_foliage_is_not_filled_solid(self):
    sc, oid, info = self._info('ficus')
    leaves = np.asarray(sc.gaussians.means)[
      oid == sc.object_names.index('leaves')]
    crown = spatial.ConvexHull(leaves).volume
    # The 6-ray fill gave the leaves 11 % of the crown's convex volume at
    # grid 64 (45 % at grid 24); the flood fill 5 %, about their sheet
    # volume (area times thickness).
    v = max(info['leaves']['volume'], info['leaves']['sheet_volume'])
    self.assertLess(v, 0.08 * crown)
    self.assertLess(info['leaves']['volume'],
                    2.0 * info['leaves']['sheet_volume'])
    # The stem (tapered tubes, ~1.4e-4 m^3) had no interior cells and fell
    # back to its convex hull; now its enclosed volume is 2 % of that.
    stem = np.asarray(sc.gaussians.means)[oid == sc.object_names.index(
      'stem')]
    self.assertLess(info['stem']['volume'],
                    0.05 * spatial.ConvexHull(stem).volume)

if __name__ == '__main__':
  absltest.main()
