"""Tests for physsplat_jax.deform: exactness under affine motions, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized
from jax import test_util as jtu

from physsplat_jax import deform
from physsplat_jax import gaussians as gs
from physsplat_jax import test_util

_F32_TOL = 2e-4
_F64_TOL = 1e-9


def _random_rotation(rng):
  q = rng.normal(size=4)
  return np.asarray(gs.quat_to_rotmat(jnp.asarray(q / np.linalg.norm(q))))


def _scene(seed=0, num_g=200, num_d=60, dtype=jnp.float32):
  g = test_util.random_gaussians(jax.random.PRNGKey(seed), num_g, dtype=dtype)
  rng = np.random.default_rng(seed)
  drivers = rng.uniform(-1.1, 1.1, size=(num_d, 3))
  return g, drivers


class DeformTest(parameterized.TestCase):

  @parameterized.named_parameters(
    ('_fit', False), ('_interpolated_F', True))
  def test_rigid_motion_is_exact(self, use_F):
    g, drivers = _scene()
    bind = deform.make_binding(g.means, drivers, k=8)
    rng = np.random.default_rng(1)
    R = _random_rotation(rng)
    t = rng.normal(size=3)
    x = jnp.asarray(drivers @ R.T + t, jnp.float32)
    F = jnp.broadcast_to(jnp.asarray(R, jnp.float32), (len(drivers), 3, 3))
    means, covs, rots = deform.deform(bind, g, x, F if use_F else None)
    want_means = np.asarray(g.means) @ R.T + t
    want_covs = R @ np.asarray(g.covariances) @ R.T
    np.testing.assert_allclose(means, want_means, atol=_F32_TOL)
    np.testing.assert_allclose(covs, want_covs, atol=_F32_TOL * 1e-2)
    np.testing.assert_allclose(rots, np.broadcast_to(R, rots.shape),
                               atol=_F32_TOL)

  def test_uniform_stretch_is_exact(self):
    g, drivers = _scene(seed=2)
    bind = deform.make_binding(g.means, drivers, k=10)
    A = np.diag([1.5, 0.7, 1.2])
    t = np.array([0.1, -0.2, 0.3])
    x = jnp.asarray(drivers @ A.T + t, jnp.float32)
    means, covs, rots = deform.deform(bind, (g.means, g.covariances), x)
    np.testing.assert_allclose(means, np.asarray(g.means) @ A.T + t,
                               atol=_F32_TOL)
    np.testing.assert_allclose(covs, A @ np.asarray(g.covariances) @ A.T,
                               atol=1e-6)
    # A pure stretch has no rotation.
    np.testing.assert_allclose(rots, np.broadcast_to(np.eye(3), rots.shape),
                               atol=_F32_TOL)

  def test_general_affine_exact_in_f64(self):
    with jax.enable_x64(True):
      g, drivers = _scene(seed=3, dtype=jnp.float64)
      bind = deform.make_binding(g.means, drivers, k=6)
      rng = np.random.default_rng(3)
      A = np.eye(3) + 0.3 * rng.normal(size=(3, 3))
      x = jnp.asarray(drivers @ A.T)
      means, covs, rots = deform.deform(bind, g, x)
      np.testing.assert_allclose(means, np.asarray(g.means) @ A.T,
                                 atol=_F64_TOL)
      np.testing.assert_allclose(covs, A @ np.asarray(g.covariances) @ A.T,
                                 atol=_F64_TOL)
      u, _, vt = np.linalg.svd(A)
      np.testing.assert_allclose(rots[0], u @ vt, atol=1e-8)

  def test_nonaffine_motion_is_local(self):
    # A bend: Gaussians follow nearby drivers, error shrinks with density.
    g, _ = _scene(seed=4, num_g=300)
    errs = []
    for n in (100, 800):
      drivers = np.random.default_rng(n).uniform(-1.1, 1.1, size=(n, 3))
      bind = deform.make_binding(g.means, drivers, k=8)
      warp = lambda p: p + 0.2 * np.sin(2 * p[:, [1, 2, 0]])
      means, _, _ = deform.deform(bind, g, jnp.asarray(warp(drivers),
                                                       jnp.float32))
      errs.append(np.abs(np.asarray(means) - warp(np.asarray(g.means))).max())
    self.assertLess(errs[1], errs[0])
    self.assertLess(errs[1], 0.05)

  @parameterized.named_parameters(('_fit', False), ('_interpolated_F', True))
  def test_gradients_match_finite_differences(self, use_F):
    with jax.enable_x64(True):
      g, drivers = _scene(seed=5, num_g=6, num_d=12, dtype=jnp.float64)
      bind = deform.make_binding(g.means, drivers, k=5)
      rng = np.random.default_rng(5)
      x = jnp.asarray(drivers + 0.05 * rng.normal(size=drivers.shape))
      F = jnp.asarray(np.eye(3) + 0.1 * rng.normal(size=(12, 3, 3)))
      covs0 = g.covariances

      def f(x, F):
        m, c, r = deform.deform(bind, (g.means, covs0), x,
                                F if use_F else None)
        return jnp.sum(jnp.sin(m)) + jnp.sum(c * 7.0) + jnp.sum(r ** 3)

      jtu.check_grads(f, (x, F), order=1, modes=('rev',), atol=1e-6,
                      rtol=1e-6, eps=1e-5)
      gx = jax.grad(f)(x, F)
      test_util.assert_tree_all_finite(gx)
      self.assertGreater(float(jnp.abs(gx).max()), 0.0)

  def test_polar_gradient_finite_at_identity(self):
    with jax.enable_x64(True):
      f = lambda F: jnp.sum(deform.polar_rotation(F) * jnp.arange(9.0).reshape(
        3, 3))
      grad = jax.grad(f)(jnp.eye(3))
      test_util.assert_tree_all_finite(grad)
      jtu.check_grads(f, (jnp.eye(3),), order=1, modes=('rev',), eps=1e-5)

  def test_jit_and_deform_gaussians(self):
    g, drivers = _scene(seed=6)
    bind = deform.make_binding(g.means, drivers, k=8)
    x = jnp.asarray(drivers, jnp.float32)
    means, covs, _ = jax.jit(deform.deform)(bind, g, x)
    np.testing.assert_allclose(means, g.means, atol=_F32_TOL)
    out = deform.deform_gaussians(bind, g, x)
    np.testing.assert_allclose(out.covariances, g.covariances, atol=1e-6)

  def test_deform_gaussians_turns_view_dependent_colour(self):
    """A rigidly rotated object seen from d looks as the rest one seen from
    R^T d (the SH were kept in world axes: 0.76 colour error at 90 deg)."""
    _, drivers = _scene(seed=8)
    g = test_util.random_gaussians(jax.random.PRNGKey(8), 200, sh_degree=2)
    bind = deform.make_binding(g.means, drivers, k=8)
    R = _random_rotation(np.random.default_rng(3))
    x = jnp.asarray(drivers @ R.T, jnp.float32)
    out = deform.deform_gaussians(bind, g, x)
    self.assertGreater(g.sh_degree, 0)
    d = np.random.default_rng(4).normal(size=(len(g.means), 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = gs.eval_sh(out.sh, jnp.asarray(d, jnp.float32))
    want = gs.eval_sh(g.sh, jnp.asarray(d @ R, jnp.float32))
    np.testing.assert_allclose(got, want, atol=1e-4)
    kept = deform.deform_gaussians(bind, g, x, rotate_colors=False)
    np.testing.assert_array_equal(kept.sh, g.sh)

  def test_per_object_binding(self):
    g, drivers = _scene(seed=7)
    go = (np.asarray(g.means)[:, 0] > 0).astype(int)
    do = (drivers[:, 0] > 0).astype(int)
    bind = deform.make_binding(g.means, drivers, k=6, gauss_object_ids=go,
                               driver_object_ids=do)
    np.testing.assert_array_equal(do[np.asarray(bind.index)],
                                  np.broadcast_to(go[:, None], (len(go), 6)))
    # Move only object 1's drivers: object 0's Gaussians stay put.
    x = drivers + np.where(do[:, None] == 1, [0.5, 0, 0], 0.0)
    means, _, _ = deform.deform(bind, g, jnp.asarray(x, jnp.float32))
    np.testing.assert_allclose(np.asarray(means)[go == 0],
                               np.asarray(g.means)[go == 0], atol=_F32_TOL)
    np.testing.assert_allclose(np.asarray(means)[go == 1],
                               np.asarray(g.means)[go == 1] + [0.5, 0, 0],
                               atol=_F32_TOL)
    with self.assertRaisesRegex(ValueError, 'fewer than k'):
      deform.make_binding(g.means, drivers, k=6, gauss_object_ids=go,
                          driver_object_ids=np.r_[do[:-55], [1] * 55])

  def test_bad_input_errors(self):
    g, drivers = _scene()
    with self.assertRaisesRegex(ValueError, 'at least 4 driving'):
      deform.make_binding(g.means, drivers[:3])
    with self.assertRaisesRegex(ValueError, r'expected \(N, 3\)'):
      deform.make_binding(g.means, drivers[:, :2])
    bind = deform.make_binding(g.means[:10], drivers)
    with self.assertRaisesRegex(ValueError, 'binding was made for 10'):
      deform.deform(bind, g, jnp.asarray(drivers))


def _degenerate_scene():
  """Drivers on a plate (coplanar), a line (collinear) and a cube lattice.

  Returns (gauss_means, gauss_ids, drivers, driver_ids): plate Gaussians in
  z = 0, line Gaussians near the line, cube Gaussians on its z = 0 face
  (whose 8 nearest drivers all lie in that face) and inside it.
  """
  rng = np.random.default_rng(3)
  t = np.linspace(0.0, 1.0, 6)
  plate = np.stack(np.meshgrid(t, t, [0.0], indexing='ij'), -1).reshape(-1, 3)
  s = np.linspace(0.0, 1.0, 11)
  line = np.stack([s, 0 * s + 3.0, 0 * s + 3.0], -1)
  cube = np.stack(np.meshgrid(t, t, t, indexing='ij'), -1).reshape(-1, 3)
  cube = cube + [5.0, 0.0, 0.0]
  g_plate = np.c_[rng.uniform(0.1, 0.9, (40, 2)), np.zeros(40)]
  g_line = np.c_[rng.uniform(0.1, 0.9, 10), 3.0 + rng.normal(0, 0.01, (10, 2))]
  g_face = np.c_[5.0 + rng.uniform(0.05, 0.95, (40, 2)), np.zeros(40)]
  g_in = 5.0 * np.eye(3)[0] + rng.uniform(0.3, 0.7, (20, 3))
  means = np.r_[g_plate, g_line, g_face, g_in]
  gids = np.r_[[0] * 40, [1] * 10, [2] * 60]
  drivers = np.r_[plate, line, cube]
  dids = np.r_[[0] * len(plate), [1] * len(line), [2] * len(cube)]
  return means, gids, drivers, dids


class DegenerateDriversTest(absltest.TestCase):
  """Coplanar / collinear drivers: F = I at rest, rotations followed."""

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    means, gids, drivers, dids = _degenerate_scene()
    cls.means, cls.gids, cls.drivers = means, gids, drivers
    cls.bind = deform.make_binding(
      means.astype(np.float32), drivers.astype(np.float32), k=8,
      gauss_object_ids=gids, driver_object_ids=dids)
    cls.fn = staticmethod(jax.jit(deform.local_deformation))

  def test_every_rank_is_exercised(self):
    rank = np.asarray(self.bind.rank)
    np.testing.assert_array_equal(rank[:40], 2)  # plate
    np.testing.assert_array_equal(rank[40:50], 1)  # line
    np.testing.assert_array_equal(rank[50:90], 2)  # cube face
    np.testing.assert_array_equal(rank[90:], 3)  # cube interior

  def test_rest_is_identity(self):
    x = jnp.asarray(self.drivers, jnp.float32)
    means, F = self.fn(self.bind, x)
    np.testing.assert_allclose(
      F, np.broadcast_to(np.eye(3), F.shape), atol=1e-5)
    np.testing.assert_allclose(means, self.means, atol=1e-6)

  def test_rigid_motion_rotates_degenerate_directions(self):
    R = _random_rotation(np.random.default_rng(7))
    tr = np.array([0.3, -1.0, 2.0])
    x = jnp.asarray(self.drivers @ R.T + tr, jnp.float32)
    means, F = self.fn(self.bind, x)
    F = np.asarray(F)
    # Planes and volumes: exactly the rotation, normals included.
    sel = np.asarray(self.bind.rank) >= 2
    np.testing.assert_allclose(F[sel], np.broadcast_to(R, F[sel].shape),
                               atol=_F32_TOL)
    np.testing.assert_allclose(np.asarray(means)[sel],
                               self.means[sel] @ R.T + tr, atol=_F32_TOL)
    rots = deform.polar_rotation(jnp.asarray(F[sel]))
    np.testing.assert_allclose(rots, np.broadcast_to(R, rots.shape),
                               atol=_F32_TOL)
    # Line: the twist about the line is unobservable; F is the rotation
    # that turns the line as R does (and no stretch).
    line = F[40:50]
    np.testing.assert_allclose(line @ [1.0, 0, 0],
                               np.broadcast_to(R[:, 0], (10, 3)),
                               atol=_F32_TOL)
    np.testing.assert_allclose(line @ np.swapaxes(line, -1, -2),
                               np.broadcast_to(np.eye(3), line.shape),
                               atol=_F32_TOL)
    np.testing.assert_allclose(np.linalg.det(line), 1.0, atol=_F32_TOL)

  def test_affine_motion_spanned_directions_and_covariance(self):
    A = np.array([[1.2, 0.1, -0.05], [0.0, 0.9, 0.2], [0.1, 0.0, 1.1]])
    x = jnp.asarray(self.drivers @ A.T, jnp.float32)
    _, F = self.fn(self.bind, x)
    F = np.asarray(F)
    # Plate (in xy): F = A on x and y; the normal is the unit normal of the
    # deformed plate.
    plate = self.gids == 0
    np.testing.assert_allclose(F[plate][:, :, :2],
                               np.broadcast_to(A[:, :2], (40, 3, 2)),
                               atol=_F32_TOL)
    n = np.cross(A[:, 0], A[:, 1])
    np.testing.assert_allclose(F[plate][:, :, 2],
                               np.broadcast_to(n / np.linalg.norm(n),
                                               (40, 3)), atol=_F32_TOL)
    # Cube interior (full rank): F = A, so the covariance is A Sigma A^T.
    face = (self.gids == 2) & (np.asarray(self.bind.rank) == 3)
    self.assertEqual(face.sum(), 20)
    np.testing.assert_allclose(F[face], np.broadcast_to(A, F[face].shape),
                               atol=_F32_TOL)
    rng = np.random.default_rng(1)
    L = rng.normal(size=(110, 3, 3)) * 0.01
    covs0 = L @ np.swapaxes(L, -1, -2)
    _, covs, _ = deform.deform(
      self.bind, (jnp.asarray(self.means, jnp.float32),
                  jnp.asarray(covs0, jnp.float32)), x)
    np.testing.assert_allclose(covs[face], A @ covs0[face] @ A.T,
                               atol=1e-7, rtol=1e-3)

  def test_gradients_match_finite_differences_with_degenerate_drivers(self):
    with jax.enable_x64(True):
      means, gids, drivers, dids = _degenerate_scene()
      bind = deform.make_binding(means, drivers, k=8, dtype=np.float64,
                                 gauss_object_ids=gids,
                                 driver_object_ids=dids)
      self.assertEqual(set(np.asarray(bind.rank).tolist()), {1, 2, 3})
      rng = np.random.default_rng(2)
      x = jnp.asarray(drivers + 0.02 * rng.normal(size=drivers.shape))
      covs0 = jnp.broadcast_to(jnp.diag(jnp.array([1e-3, 2e-3, 1e-5])),
                               (len(means), 3, 3))

      def f(x):
        m, c, r = deform.deform(bind, (jnp.asarray(means), covs0), x)
        return (jnp.sum(jnp.sin(m)) + jnp.sum(c * 300.0)
                + jnp.sum(r ** 3))

      jtu.check_grads(f, (x,), order=1, modes=('rev',), atol=1e-6,
                      rtol=1e-6, eps=1e-5)
      g = jax.grad(f)(x)
      test_util.assert_tree_all_finite(g)
      self.assertGreater(float(jnp.abs(g).max()), 0.0)

if __name__ == '__main__':
  absltest.main()
