"""Tests for physsplat_jax.mpm.linalg: 3x3 SoA algebra, polar, SVD VJPs."""

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized
from jax.test_util import check_grads

from physsplat_jax.mpm import linalg as la

_ATOL = 1e-10


def _soa(F):
  return la.to_mat(jnp.moveaxis(jnp.asarray(F), (-2, -1), (0, 1)))


def _aos(m):
  return jnp.moveaxis(la.from_mat(m), (0, 1), (-2, -1))


def _random_F(n, seed=0, amp=0.3):
  rng = np.random.default_rng(seed)
  F = np.eye(3) + amp * rng.normal(size=(n, 3, 3))
  F[np.linalg.det(F) < 0] *= -1.0
  return F


# F = I, a repeated pair, a uniform stretch and random matrices.
_CASES = (
  ('identity', np.repeat(np.eye(3)[None], 2, 0)),
  ('repeated', np.repeat(np.diag([1.1, 1.1, 0.9])[None], 2, 0)),
  ('uniform', np.repeat(1.05 * np.eye(3)[None], 2, 0)),
  ('random', _random_F(4)),
)


def _hencky_return(s, p):
  """A von Mises-like return map plus Hencky stress (tests only)."""
  mu, lam = p
  e = tuple(jnp.log(jnp.maximum(x, 1e-2)) for x in s)
  tr = e[0] + e[1] + e[2]
  eh = tuple(x - tr / 3 for x in e)
  n = jnp.sqrt(eh[0] ** 2 + eh[1] ** 2 + eh[2] ** 2 + 1e-300)
  dg = n - 0.01
  pl = dg > 0
  en = tuple(jnp.where(pl, x - dg / n * y, x) for x, y in zip(e, eh))
  h = tuple(jnp.exp(x) for x in en)
  k = tuple(2 * mu * x + lam * (en[0] + en[1] + en[2]) for x in en)
  return h, k, {'dg': jnp.where(pl, dg, 0.0)}


class AlgebraTest(absltest.TestCase):

  def test_products_match_numpy(self):
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(2, 5, 3, 3))
    A, B = _soa(a), _soa(b)
    np.testing.assert_allclose(_aos(la.matmul(A, B)), a @ b, atol=1e-5)
    np.testing.assert_allclose(_aos(la.matmul_t(A, B)),
                               a @ np.swapaxes(b, 1, 2), atol=1e-5)
    np.testing.assert_allclose(_aos(la.t_matmul(A, B)),
                               np.swapaxes(a, 1, 2) @ b, atol=1e-5)
    np.testing.assert_allclose(la.det(A), np.linalg.det(a), rtol=1e-4)
    np.testing.assert_allclose(
      _aos(la.cofactor(A)),
      np.linalg.det(a)[:, None, None] * np.swapaxes(np.linalg.inv(a), 1, 2),
      rtol=1e-3, atol=1e-5)


class PolarTest(parameterized.TestCase):

  @parameterized.named_parameters(*_CASES)
  def test_forward(self, F):
    with jax.enable_x64(True):
      R = np.asarray(la.polar(F))
      np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R,
                                 np.broadcast_to(np.eye(3), R.shape),
                                 atol=_ATOL)
      np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=_ATOL)
      S = np.swapaxes(R, 1, 2) @ F
      np.testing.assert_allclose(S, np.swapaxes(S, 1, 2), atol=_ATOL)
      self.assertGreater(np.linalg.eigvalsh(S).min(), 0)

  @parameterized.named_parameters(*_CASES)
  def test_derivatives_match_finite_differences(self, F):
    # Forward (jvp) and reverse mode (its transpose), at F = I too.
    with jax.enable_x64(True):
      check_grads(la.polar, (jnp.asarray(F),), 1, modes=('fwd', 'rev'),
                  eps=1e-6)

  def test_grad_finite_at_identity_in_float32(self):
    g = jax.grad(lambda F: jnp.sum(la.polar(F) * jnp.arange(9.).reshape(
      3, 3)))(jnp.eye(3)[None])
    self.assertTrue(np.all(np.isfinite(g)))


class SvdTest(parameterized.TestCase):

  @parameterized.named_parameters(*_CASES)
  def test_forward_rotations(self, F):
    with jax.enable_x64(True):
      U, s, V = la.svd(jnp.asarray(F))
      np.testing.assert_allclose(
        np.einsum('nij,nj,nkj->nik', U, s, V), F, atol=_ATOL)
      np.testing.assert_allclose(np.linalg.det(U), 1.0, atol=_ATOL)
      np.testing.assert_allclose(np.linalg.det(V), 1.0, atol=_ATOL)

  def test_svd_forward_reflection(self):
    with jax.enable_x64(True):
      F = np.diag([1.2, 0.9, -0.8])[None]
      U, s, V = la.svd(jnp.asarray(F))
      self.assertLess(float(s[0, 2]), 0)
      np.testing.assert_allclose(np.linalg.det(U), 1.0, atol=_ATOL)

  @parameterized.parameters('float32', 'float64')
  def test_svd_mat_matches_lapack(self, dtype):
    """Structure-of-arrays SVD (polar + Jacobi) against jnp.linalg.svd."""
    rng = np.random.default_rng(5)
    q = np.linalg.qr(rng.normal(size=(50, 3, 3)))[0]
    q[np.linalg.det(q) < 0] *= -1.0
    F = np.concatenate([
      rng.normal(size=(200, 3, 3)),                    # det F of both signs
      q @ np.diag([1.5, 1.5, 0.5]) @ np.swapaxes(q, 1, 2),  # repeated pair
      q,                                               # pure rotations
      np.diag([1.0, 1.0, -1.0])[None],                 # reflection
      np.eye(3)[None]])
    tol = 1e-5 if dtype == 'float32' else 1e-12
    with jax.enable_x64(dtype == 'float64'):
      U, s, V = jax.jit(la.svd_mat)(_soa(F.astype(dtype)))
      U, V = np.asarray(_aos(U)), np.asarray(_aos(V))
      s = np.stack(s, -1)
      _, s_ref, _ = la.svd(jnp.asarray(F, dtype))
    np.testing.assert_allclose(np.einsum('nij,nj,nkj->nik', U, s, V), F,
                               atol=tol * np.abs(F).max() * 10)
    np.testing.assert_allclose(np.linalg.det(U), 1.0, atol=tol * 10)
    np.testing.assert_allclose(np.linalg.det(V), 1.0, atol=tol * 10)
    np.testing.assert_allclose(s, np.asarray(s_ref), atol=tol * 10)
    # Descending |s|; the last carries the sign of det F.
    self.assertTrue(np.all(np.abs(s[:, :2]) >= np.abs(s[:, 1:]) - tol))
    np.testing.assert_array_equal(s[:, 2] < 0, np.linalg.det(F) < 0)

  def test_svd_derivatives_distinct_values(self):
    with jax.enable_x64(True):
      f = lambda F: la.svd(F)[1]  # noqa: E731
      check_grads(f, (jnp.asarray(_random_F(3, seed=2)),), 1,
                  modes=('fwd', 'rev'), eps=1e-6)
      g = lambda F: jnp.einsum(  # noqa: E731
        'nij,nkj->nik', la.svd(F)[0], la.svd(F)[2])
      check_grads(g, (jnp.asarray(_random_F(3, seed=3)),), 1,
                  modes=('fwd', 'rev'), eps=1e-6)

  def test_svd_derivatives_finite_at_identity(self):
    g = jax.grad(lambda F: jnp.sum(la.svd(F)[0] * la.svd(F)[1][..., None, :]))
    self.assertTrue(np.all(np.isfinite(g(jnp.eye(3)[None]))))
    # The tangents of U and V stay tangent to the rotations (U^T dU skew)
    # where singular values repeat exactly, and ds is diag(U^T dF V).
    rng = np.random.default_rng(6)
    for F in (np.eye(3)[None], np.diag([1.2, 1.2, 0.8])[None],
              _random_F(2, seed=7)):
      dF = jnp.asarray(rng.normal(size=F.shape), jnp.float32)
      (U, _, V), (dU, ds, dV) = jax.jvp(la.svd, (jnp.asarray(F, jnp.float32),),
                                        (dF,))
      for Q, dQ in ((U, dU), (V, dV)):
        K = np.swapaxes(np.asarray(Q), 1, 2) @ np.asarray(dQ)
        self.assertTrue(np.all(np.isfinite(K)))
        np.testing.assert_allclose(K, -np.swapaxes(K, 1, 2), atol=1e-3 *
                                   max(1.0, np.abs(K).max()))
      P = np.swapaxes(np.asarray(U), 1, 2) @ np.asarray(dF) @ np.asarray(V)
      np.testing.assert_allclose(ds, np.diagonal(P, 0, 1, 2), atol=1e-5)

  @parameterized.named_parameters(*_CASES)
  def test_spectral_map_derivatives(self, F):
    """Return map + Hencky stress: exact derivatives in forward and reverse
    mode, also at F = I."""
    apply = la.make_spectral_map(_hencky_return)

    def f(F, mu, lam):
      Fh, Tk, aux = apply(_soa(F), (mu, lam))
      return _aos(Fh), _aos(Tk), aux['dg']

    with jax.enable_x64(True):
      n = F.shape[0]
      args = (jnp.asarray(F), jnp.full((n,), 2.0), jnp.full((n,), 3.0))
      check_grads(f, args, 1, modes=('fwd', 'rev'), eps=1e-6)

  def test_second_derivatives_where_singular_values_differ(self):
    """jax.hessian of the polar factor (also at F = I) and of a spectral
    map (its rule evaluates svd_mat, whose own derivative is a custom JVP:
    the Jacobi sweeps' gave NaN) against central differences of the
    gradient, float64."""
    apply = la.make_spectral_map(_hencky_return)
    rng = np.random.default_rng(8)
    w = rng.normal(size=(3, 3))

    def spectral(F):
      Fh, Tk, aux = apply(_soa(F), (jnp.full((1,), 2.0), jnp.full((1,), 3.0)))
      return (jnp.sum(w * _aos(Fh)[0]) + jnp.sum(w.T * _aos(Tk)[0])
              + jnp.sum(aux['dg']))

    def polar(F):
      return jnp.sum(w * la.polar(F)[0])

    with jax.enable_x64(True):
      for fn, F in ((polar, np.eye(3)), (polar, _random_F(1, seed=9)[0]),
                    (spectral, np.eye(3) + 0.05 * rng.normal(size=(3, 3)))):
        F = jnp.asarray(F)[None]
        H = jax.hessian(fn)(F)
        d = jnp.asarray(rng.normal(size=F.shape))
        g = jax.grad(fn)
        fd = (g(F + 1e-6 * d) - g(F - 1e-6 * d)) / 2e-6
        np.testing.assert_allclose(
          jnp.einsum('aijbkl,bkl->aij', H, d), fd,
          atol=1e-6 * max(1.0, float(jnp.abs(fd).max())))

  def test_spectral_map_forward(self):
    with jax.enable_x64(True):
      F = _random_F(3, seed=4)
      apply = la.make_spectral_map(
        lambda s, p: (s, tuple(jnp.log(x) for x in s), {}))
      Fh, Tk, _ = apply(_soa(F), ())
      np.testing.assert_allclose(_aos(Fh), F, atol=_ATOL)
      # U diag(log s) U^T = log(F F^T) / 2.
      w, Q = np.linalg.eigh(F @ np.swapaxes(F, 1, 2))
      ref = np.einsum('nij,nj,nkj->nik', Q, 0.5 * np.log(w), Q)
      np.testing.assert_allclose(_aos(Tk), ref, atol=1e-8)


if __name__ == '__main__':
  absltest.main()
