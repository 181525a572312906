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

      @jax.jit
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
      args = (jnp.full((n,), 3e4), jnp.full((n,), 0.3),
              jnp.full((n,), 800.0), v0, jnp.asarray([1e-3, 0.0, 2e-3]))
      g = jax.grad(loss, argnums=tuple(range(len(args))))(*args)
      labels = ('E', 'nu', 'rho', 'v0', 'force')
      for i, name in enumerate(labels):  # one check per argument
        ad, fd = _directional(loss, args, g, i, seed=i)
        np.testing.assert_allclose(ad, fd, rtol=_RTOL, err_msg=name)
      # Each parameter really matters (no silently zero gradient).
      for name, gi in zip(labels, g):
        self.assertGreater(float(jnp.abs(gi).max()), 0.0, msg=name)
        self.assertTrue(bool(jnp.all(jnp.isfinite(gi))), msg=name)


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
