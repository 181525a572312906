"""Gradients of MPM rollouts against central finite differences (float64)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl.testing import absltest

import mpm_blocks
from physsplat_jax import mpm
from physsplat_jax.mpm import linalg as la

_EPS = 1e-5
_RTOL = 1e-4


def _scene():
  grid = mpm.GridSpec(res=12, size=1.0)
  sp = grid.dx / 2
  i = np.stack(np.meshgrid(*[np.arange(3)] * 3, indexing='ij'), -1)
  x0 = np.array([0.4, 0.42, 0.3]) + (i.reshape(-1, 3) + 0.5) * sp
  # Jitter so that no symmetry hides a wrong gradient.
  x0 += 0.1 * sp * np.random.default_rng(0).uniform(-1, 1, x0.shape)
  return grid, x0, sp ** 3


def _directional(f, args, grads, argnum, seed):
  """(AD, central FD) derivatives of scalar f along a random direction in
  argument ``argnum`` only, scaled to that argument's size (E ~ 3e4 Pa and
  v0 ~ 1 m/s in one direction would leave E's share of the derivative
  below the tolerance)."""
  rng = np.random.default_rng(seed)
  a = args[argnum]
  scale = max(float(jnp.abs(a).max()), 1e-3)
  d = jnp.asarray(rng.normal(size=np.shape(a))) * scale
  ad = float(jnp.sum(grads[argnum] * d))

  def step(s):
    return args[:argnum] + (a + s * _EPS * d,) + args[argnum + 1:]

  fd = (f(*step(1.0)) - f(*step(-1.0))) / (2 * _EPS)
  return ad, float(fd)


class GradTest(absltest.TestCase):

  @pytest.mark.optimized  # its loops run 6x longer unoptimised
  def test_rollout_grads_match_finite_differences(self):
    """d loss / d (E, nu, rho, v0, impulse force) on a 2 x 4-substep rollout.

    Four models share the block (fixed corotated through the polar VJP,
    StVK, snow and sand through the spectral-map VJP); one compile.
    """
    with jax.enable_x64(True):
      grid, x0, vol = _scene()
      n = len(x0)
      models = ('fixed_corotated', 'stvk', 'snow', 'drucker_prager')
      names = [models[i % 4] for i in range(n)]
      cfg = mpm.SimConfig(
        grid=grid, dt=1e-3, substeps_per_frame=4, models=models,
        dtype='float64',
        boundary_conditions=(
          mpm.SurfaceCollider(point=(0, 0, 0.31), surface='slip',
                              friction=0.3),
          mpm.ParticleImpulse(force=(0.0, 0.0, 0.0), num_dt=3)),
      )
      w = jnp.asarray(np.random.default_rng(1).normal(size=(3, n, 3)))

      def loss(E, nu, rho, v0, force):
        # Per-particle E, nu, rho (the MPDP field); force of the impulse.
        mat = mpm.make_materials(names, E, nu, rho, config_models=models,
                                 dtype=jnp.float64, theta_c=0.01)
        s = mpm.init_state(x0, v0, vol, mat, cfg)
        forces = mpm.Forces(values=(jnp.zeros(0), force))
        _, xs, Fs = mpm.rollout(s, mat, forces, cfg, 2)
        return jnp.sum(w * xs) + jnp.sum(Fs[-1] ** 2)

      # A non-uniform v0 so that no particle sits at F = I after a substep:
      # cohesionless sand's return map is not differentiable there (the apex
      # of its cone), so finite differences and AD need not agree.
      v0 = jnp.tile(jnp.asarray([[0.3, -0.2, -1.5]]), (n, 1)) + 0.1 * (
        jnp.asarray(np.random.default_rng(5).normal(size=(n, 3))))
      # Strongly typed, as the perturbed copies in _directional are (with
      # weakly typed E, nu, rho each check compiled the loss again), and
      # the differences taken with the gradient's own program: one
      # compile, not six (55 s at -O2 on a 2-core CPU).
      f64 = jnp.float64
      args = (jnp.full((n,), 3e4, f64), jnp.full((n,), 0.3, f64),
              jnp.full((n,), 800.0, f64), v0, jnp.asarray([1e-3, 0.0, 2e-3]))
      value_and_grad = jax.jit(jax.value_and_grad(
        loss, argnums=tuple(range(len(args)))))
      g = value_and_grad(*args)[1]
      labels = ('E', 'nu', 'rho', 'v0', 'force')
      for i, name in enumerate(labels):  # one check per argument
        ad, fd = _directional(lambda *a: value_and_grad(*a)[0], args, g, i,
                              seed=i)
        np.testing.assert_allclose(ad, fd, rtol=_RTOL, err_msg=name)
      # Each parameter really matters (no silently zero gradient).
      for name, gi in zip(labels, g):
        self.assertGreater(float(jnp.abs(gi).max()), 0.0, msg=name)
        self.assertTrue(bool(jnp.all(jnp.isfinite(gi))), msg=name)


class ConstitutiveHessianTest(absltest.TestCase):

  def test_spectral_functions_have_second_derivatives_at_rest(self):
    """jax.hessian of each SVD model's map on the singular values at rest.

    At F = I the deviatoric strain is 0: the floored norm of the von Mises
    family (and of sand's strain) had an overflowing second derivative
    there, and foam's and Bingham's unused quotient 0 * inf: NaN for five
    of the seven models before. Its Jacobian is what the spectral map's
    rule differentiates (jax.hessian through the update).
    """
    with jax.enable_x64(True):
      for m in mpm.constitutive.SVD_MODELS:
        mat = mpm.make_materials(m, 2e4, 0.3, 1000.0, num=2,
                                 dtype=jnp.float64)
        p = mpm.constitutive.spectral_params(
          (m,), (m,), None, mat, *mat.lame(), jnp.ones(2), jnp.zeros(2),
          1e-4)

        def g(s, p, m=m):
          h, k, aux = mpm.constitutive._SPECTRAL[m](tuple(s), p)
          return (sum(jnp.sum(x) for x in h)
                  + 1e-4 * sum(jnp.sum(x) for x in k)
                  + sum(jnp.sum(x) for x in jax.tree.leaves(aux)))

        # Exactly at rest, and two singular values 1e-12 apart.
        s0 = jnp.stack([jnp.ones(2), jnp.array([1.0, 1.0 + 1e-12]),
                        jnp.ones(2)])
        H = jax.hessian(g, argnums=(0, 1))(s0, p)
        for leaf in jax.tree.leaves(H):
          self.assertTrue(np.all(np.isfinite(np.asarray(leaf))), msg=m)

  @pytest.mark.slow  # a Hessian compile per model: ~60 s in all
  def test_second_derivatives_of_every_svd_model_match_fd(self):
    """jax.hessian (forward over reverse) of each SVD model's update.

    Two particles: F = I (finite) and 0.96 I + 0.05 noise (compressed,
    distinct singular values, plastic for the plastic models), where the
    Hessian in F and E must match central differences of the gradient.
    """
    rng = np.random.default_rng(3)
    F0 = np.stack([np.eye(3),
                   0.96 * np.eye(3) + 0.05 * rng.normal(size=(3, 3))], -1)
    w = rng.normal(size=(2, 3, 3, 2))
    with jax.enable_x64(True):
      for m in mpm.constitutive.SVD_MODELS:

        def f(F, E, m=m):
          mat = mpm.make_materials(m, E, 0.3, 1000.0, dtype=jnp.float64)
          z = la.to_mat(jnp.zeros_like(F))
          Fe, Jp, ep, tau = mpm.constitutive.constitutive_update(
            (m,), None, la.to_mat(F), z, jnp.ones(2), jnp.zeros(2), mat,
            1e-4)
          return (jnp.sum(w[0] * la.from_mat(Fe))
                  + 1e-4 * jnp.sum(w[1] * la.from_mat(tau))
                  + jnp.sum(Jp) + jnp.sum(ep))

        args = (jnp.asarray(F0), jnp.full((2,), 2e4))
        H = jax.jit(jax.hessian(f, argnums=(0, 1)))(*args)
        for leaf in jax.tree.leaves(H):
          self.assertTrue(np.all(np.isfinite(np.asarray(leaf))), msg=m)
        dF = np.zeros_like(F0)
        dF[..., 1] = rng.normal(size=(3, 3))
        dE = np.array([0.0, 2e3])
        g = jax.jit(jax.grad(f, argnums=(0, 1)))
        e = 1e-6
        gp = g(args[0] + e * dF, args[1] + e * dE)
        gm = g(args[0] - e * dF, args[1] - e * dE)
        for a in range(2):
          fd = (gp[a] - gm[a]) / (2 * e)
          ad = (jnp.tensordot(H[a][0], dF, dF.ndim)
                + jnp.tensordot(H[a][1], dE, 1))
          scale = float(jnp.abs(fd).max())
          self.assertGreater(scale, 0.0, msg=m)
          np.testing.assert_allclose(ad, fd, atol=1e-5 * scale, err_msg=m)

  @pytest.mark.slow  # the second-order program: ~100 s to compile at -O0
  def test_rollout_hessian_reverse_over_forward_matches_fd(self):
    """The README's route to second derivatives through a rollout:
    jacrev(jacfwd) of a 27-particle block of StVK, snow and plasticine
    from rest on a sticky plane (F = I: repeated singular values), in
    (log E, nu), against central differences of the gradient (float64).
    jax.hessian's order is NaN here (docs/mpm.md: lax.scan's hoisting
    drops the custom JVPs)."""
    with jax.enable_x64(True):
      grid, x0, vol = _scene()
      n = len(x0)
      models = ('stvk', 'snow', 'plasticine')
      names = [models[i % 3] for i in range(n)]
      cfg = mpm.SimConfig(
        grid=grid, dt=1e-3, substeps_per_frame=4, models=models,
        dtype='float64', boundary_conditions=(
          mpm.SurfaceCollider(point=(0, 0, 0.3), surface='sticky'),))

      def loss(q):
        mat = mpm.make_materials(
          names, jnp.exp(q[0]) * jnp.ones(n), q[1] * jnp.ones(n),
          jnp.full((n,), 800.0), config_models=models, dtype=jnp.float64)
        s = mpm.init_state(x0, jnp.zeros((n, 3)), vol, mat, cfg)
        _, xs, Fs = mpm.rollout(s, mat, mpm.make_forces(cfg), cfg, 2)
        return jnp.sum(xs[-1][:, 2]) + jnp.sum(Fs[-1] ** 2)

      q = jnp.array([np.log(3e4), 0.3])
      H = np.asarray(jax.jit(jax.jacrev(jax.jacfwd(loss)))(q))
      g = jax.jit(jax.grad(loss))
      step = (1e-4, 1e-5)
      fd = np.stack([(g(q.at[k].add(step[k])) - g(q.at[k].add(-step[k])))
                     / (2 * step[k]) for k in range(2)])
      scale = float(np.abs(fd).max())
      self.assertGreater(float(np.abs(fd[0, 0])), 1e-4 * scale)
      np.testing.assert_allclose(H, fd, atol=1e-6 * scale)
      np.testing.assert_allclose(H, H.T, atol=1e-9 * scale)


class VmapGradTest(absltest.TestCase):

  def test_grad_of_a_vmapped_frame(self):
    """jax.grad through jax.vmap of a frame (a batch of scenes, as the
    batch and particle-sharded MPDP gradients take it): the tangent that
    the constitutive update materializes became a select under vmap, with
    stop_gradient on it, and the reverse pass raised (no transpose)."""
    s, mat, forces, cfg = mpm_blocks.one_block()
    frame = mpm.make_frame(cfg)

    def loss(scale):
      m = mat.replace(E=mat.E * scale)
      return jnp.sum(frame(s, m, forces).x * jnp.arange(3.0))

    scales = jnp.array([1.0, 1.5])
    batched = jax.jit(jax.grad(lambda e: jnp.sum(jax.vmap(loss)(e))))(scales)
    each = jnp.stack([jax.jit(jax.grad(loss))(e) for e in scales])
    self.assertTrue(np.all(np.asarray(each) != 0))
    np.testing.assert_allclose(batched, each, rtol=1e-5)


if __name__ == '__main__':
  absltest.main()
