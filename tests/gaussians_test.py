"""Tests for quaternions, covariances and SH evaluation."""

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

import physsplat_jax as ps
from physsplat_jax import gaussians as G
from physsplat_jax import test_util


def _brute_rotmat(q):
  # Rotation of v by q: q v q* via explicit quaternion products (NumPy).
  q = np.asarray(q, np.float64)
  q = q / np.linalg.norm(q)
  w, x, y, z = q

  def mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([
      aw * bw - ax * bx - ay * by - az * bz,
      aw * bx + ax * bw + ay * bz - az * by,
      aw * by - ax * bz + ay * bw + az * bx,
      aw * bz + ax * by - ay * bx + az * bw,
    ])

  cols = []
  for e in np.eye(3):
    v = mul(mul(q, np.r_[0.0, e]), np.array([w, -x, -y, -z]))
    cols.append(v[1:])
  return np.stack(cols, axis=1)


class GaussiansTest(absltest.TestCase):

  def test_covariance_matches_brute_force(self):
    with jax.enable_x64(True):
      rng = np.random.default_rng(0)
      q = rng.normal(size=(20, 4))
      ls = rng.uniform(-3, 0, size=(20, 3))
      cov = np.asarray(G.covariance(jnp.asarray(ls), jnp.asarray(q)))
      for i in range(20):
        R = _brute_rotmat(q[i])
        S = np.diag(np.exp(ls[i]))
        np.testing.assert_allclose(cov[i], R @ S @ S.T @ R.T, rtol=1e-12,
                                   atol=1e-15)

  def test_rotmat_quat_round_trip(self):
    with jax.enable_x64(True):
      rng = np.random.default_rng(1)
      q = rng.normal(size=(100, 4))
      R = G.quat_to_rotmat(jnp.asarray(q))
      q2 = G.rotmat_to_quat(R)
      np.testing.assert_allclose(G.quat_to_rotmat(q2), R, atol=1e-12)
      self.assertTrue(np.all(np.asarray(q2[:, 0]) >= 0))

  def test_decompose_covariance_inverts(self):
    with jax.enable_x64(True):
      rng = np.random.default_rng(2)
      A = rng.normal(size=(50, 3, 3))
      cov = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(3)
      ls, q = G.decompose_covariance(jnp.asarray(cov))
      np.testing.assert_allclose(G.covariance(ls, q), cov, rtol=1e-9,
                                 atol=1e-12)
      R = G.quat_to_rotmat(q)
      np.testing.assert_allclose(np.linalg.det(np.asarray(R)), 1.0, atol=1e-12)

  def test_sh_degree0_is_dc_colour(self):
    g = test_util.random_gaussians(jax.random.PRNGKey(0), 7, sh_degree=2)
    dirs = jax.random.normal(jax.random.PRNGKey(1), (7, 3))
    rgb = G.eval_sh(g.sh, dirs, degree=0)
    np.testing.assert_allclose(rgb, jnp.maximum(g.rgb_dc, 0), atol=1e-6)

  def test_sh_degree_above_the_coefficients_is_refused(self):
    # The einsum broadcast the size-1 SH axis: wrong colours, no error.
    g = test_util.random_gaussians(jax.random.PRNGKey(0), 3, sh_degree=0)
    dirs = jnp.ones((3, 3))
    with self.assertRaisesRegex(ps.types.DataError,
                                r'degree 3 asked of SH coefficients of '
                                r'degree 0 \(1 per channel\)'):
      G.eval_sh(g.sh, dirs, degree=3)

  def test_sh_basis_orthonormal(self):
    # Monte-Carlo orthonormality of the real SH basis on the sphere
    # (each basis has norm 1/(4 pi) ... times 4 pi).
    with jax.enable_x64(True):
      d = jax.random.normal(jax.random.PRNGKey(3), (400_000, 3),
                            dtype=jnp.float64)
      d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
      B = G.sh_basis(3, d)
      gram = 4 * np.pi * np.asarray(B.T @ B) / d.shape[0]
      np.testing.assert_allclose(gram, np.eye(16), atol=0.02)

  def test_sh_basis_is_inria_real_sh(self):
    """Against an independent construction: real SH from SciPy's complex
    ones (which carry the Condon-Shortley phase), sqrt(2) Im Y_l^|m| for
    m < 0 and sqrt(2) Re Y_l^m for m > 0, ordered m = -l..l. That is the
    3DGS (INRIA ``eval_sh``) convention: e.g. basis 1 is -C1 y. Orthonor-
    mality alone would pass any sign flip or order swap within a band."""
    from scipy import special

    rng = np.random.default_rng(4)
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    theta, phi = np.arccos(d[:, 2]), np.arctan2(d[:, 1], d[:, 0])

    def complex_sh(l, m):  # noqa: E741
      if hasattr(special, 'sph_harm_y'):  # SciPy >= 1.15
        return special.sph_harm_y(l, m, theta, phi)
      return special.sph_harm(m, l, phi, theta)

    want = []
    for l in range(4):  # noqa: E741
      for m in range(-l, l + 1):
        Y = complex_sh(l, abs(m))
        want.append(np.sqrt(2) * Y.imag if m < 0 else
                    np.sqrt(2) * Y.real if m > 0 else Y.real)
    with jax.enable_x64(True):
      got = np.asarray(G.sh_basis(3, jnp.asarray(d)))
    np.testing.assert_allclose(got, np.stack(want, -1), atol=1e-12)
    np.testing.assert_allclose(got[:, 1], -G.SH_C1 * d[:, 1], atol=1e-12)

  def test_subset_and_concatenate(self):
    g = test_util.random_gaussians(jax.random.PRNGKey(0), 10, sh_degree=1)
    mask = np.arange(10) % 3 == 0
    s = g.subset(mask)
    self.assertEqual(s.num, 4)
    np.testing.assert_array_equal(s.means, g.means[mask])
    c = ps.concatenate_gaussians([s, g.subset(~mask)])
    self.assertEqual(c.num, 10)
    with self.assertRaisesRegex(ValueError, 'expected'):
      g.subset(np.ones(3, bool))

  def test_camera_project_principal_point(self):
    cam = ps.make_camera(np.eye(4), 100.0, 100.0, 64, 48)
    uv, z = cam.project(jnp.array([[0.0, 0.0, 2.0], [0.2, -0.1, 2.0]]))
    np.testing.assert_allclose(uv[0], [32.0, 24.0])
    np.testing.assert_allclose(uv[1], [42.0, 19.0], rtol=1e-6)
    np.testing.assert_allclose(cam.position, 0.0)


if __name__ == '__main__':
  absltest.main()
