"""Tests for the MLS-MPM transfers and time stepping (physsplat_jax.mpm)."""

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from physsplat_jax import mpm
from physsplat_jax.mpm import linalg as la
from physsplat_jax.mpm import transfer

_TOL64 = 1e-10


def _block(n_side, lo, spacing, jitter=0.0, seed=0):
  """A cubic block of n_side^3 particles, lower corner ``lo``."""
  i = np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing='ij'), -1)
  x = np.asarray(lo) + (i.reshape(-1, 3) + 0.5) * spacing
  if jitter:
    x += jitter * spacing * np.random.default_rng(seed).uniform(
      -0.5, 0.5, x.shape)
  return x


class TransferTest(absltest.TestCase):

  def test_weights_partition_unity_and_linear_reproduction(self):
    with jax.enable_x64(True):
      grid = mpm.GridSpec(res=16, size=1.0, lower=(0.5, -1.0, 0.0))
      rng = np.random.default_rng(0)
      x = np.asarray(grid.lower) + 0.1 + 0.8 * rng.random((50, 3))
      st = transfer.Stencil(grid, tuple(jnp.asarray(x.T)))
      np.testing.assert_allclose(jnp.sum(st.W, (0, 1, 2)), 1.0,
                                 atol=_TOL64)
      # sum_i w_ip x_i = x_p for quadratic B-splines.
      idx = np.asarray(st.indices()).reshape(27, -1)
      node = np.stack(np.unravel_index(idx, (16,) * 3), -1) * grid.dx
      node = node + np.asarray(grid.lower)
      xr = np.einsum('kn,knd->nd', np.asarray(st.W).reshape(27, -1), node)
      np.testing.assert_allclose(xr, x, atol=_TOL64)

  def test_g2p_reproduces_affine_velocity_field(self):
    """Quadratic B-splines: v_p = v(x_p) and C_p = grad v for affine v."""
    with jax.enable_x64(True):
      grid = mpm.GridSpec(res=16, size=1.0, lower=(0.5, -1.0, 0.0))
      rng = np.random.default_rng(2)
      x = np.asarray(grid.lower) + 0.2 + 0.6 * rng.random((40, 3))
      a, B = rng.normal(size=3), rng.normal(size=(3, 3))
      node = np.stack(np.meshgrid(*[np.arange(16)] * 3, indexing='ij'), -1)
      vel = a + (node * grid.dx + np.asarray(grid.lower)) @ B.T
      st = transfer.Stencil(grid, tuple(jnp.asarray(x.T)))
      gv = tuple(jnp.asarray(vel[..., d]) for d in range(3))
      # Both forms of the window sum (the CPU's product, the GPU's sum;
      # tests/gpu_program_test.py checks which platform gets which).
      for form in ('auto', 'dot', 'sum'):
        v, C = transfer.g2p(grid, st, gv, form=form)
        np.testing.assert_allclose(np.stack(v, -1), a + x @ B.T,
                                   atol=1e-12, err_msg=form)
        np.testing.assert_allclose(np.asarray(C).transpose(2, 0, 1),
                                   np.broadcast_to(B, (40, 3, 3)),
                                   atol=1e-11, err_msg=form)

  def test_materialize_is_the_identity_for_values_gradients_and_vmap(self):
    a = jnp.asarray([[1.0, jnp.nan], [-2.0, 3.0]])
    for b in (a, a.at[0, 0].set(jnp.nan)):  # either branch of the cond
      np.testing.assert_array_equal(jax.jit(transfer.materialize)(b), b)
    x = jnp.arange(6.0).reshape(2, 3)
    g = jax.grad(lambda y: jnp.sum(transfer.materialize(y) ** 2))(x)
    np.testing.assert_allclose(g, 2.0 * x)
    np.testing.assert_array_equal(jax.vmap(transfer.materialize)(x), x)

  def test_p2g_derivatives_are_the_window_sums(self):
    # transfer._p2g_window's CPU reverse pass (batched products) against
    # XLA's own transpose of the same scatter, its tangent against XLA's,
    # and the (co)tangent of F/C materialized is the identity's.
    with jax.enable_x64(True):
      rng = np.random.default_rng(3)
      n, G, C = 40, 10, 8
      W = jnp.asarray(rng.uniform(size=(n, 3, 3, 3)))
      parts = [jnp.asarray(rng.normal(size=(n, 1, 1, 1, C)))
               for _ in range(4)]
      base = jnp.asarray(rng.integers(0, G - 3, size=(n, 3)), jnp.int32)
      g = jnp.asarray(rng.normal(size=(G, G, G, C)))
      out, ours = jax.vjp(
        lambda *a: transfer._p2g_window(G, *a, base), W, *parts)
      ref, xla = jax.vjp(
        lambda *a: transfer._p2g_window_sum(G, *a, base), W, *parts)
      np.testing.assert_array_equal(out, ref)
      for a, b in zip(ours(g), xla(g)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
      # Forward mode: its tangent (products) is XLA's jvp of the sum.
      tangents = [jnp.asarray(rng.normal(size=a.shape)) for a in [W] + parts]
      _, t_ours = jax.jvp(lambda *a: transfer._p2g_window(G, *a, base),
                          [W] + parts, tangents)
      _, t_xla = jax.jvp(lambda *a: transfer._p2g_window_sum(G, *a, base),
                         [W] + parts, tangents)
      np.testing.assert_allclose(t_ours, t_xla, rtol=1e-12, atol=1e-12)
      x = jnp.asarray(rng.normal(size=(5,)))
      np.testing.assert_array_equal(
        jax.grad(lambda y: jnp.sum(jnp.sin(
          transfer.materialize_cotangent(y))))(x), jnp.cos(x))
      np.testing.assert_array_equal(
        jax.jvp(lambda y: jnp.sin(transfer.materialize_cotangent(y)),
                (x,), (jnp.ones_like(x),))[1], jnp.cos(x))

  def test_p2g_g2p_conserve_mass_and_momentum(self):
    with jax.enable_x64(True):
      grid = mpm.GridSpec(res=16, size=1.0)
      rng = np.random.default_rng(1)
      n = 64
      x = tuple(jnp.asarray(0.3 + 0.4 * rng.random((3, n))))
      v = tuple(jnp.asarray(rng.normal(size=(3, n))))
      m = jnp.asarray(rng.uniform(0.5, 2.0, n))
      # Any affine matrix (APIC C and stress): adds no net momentum.
      A = la.to_mat(jnp.asarray(rng.normal(size=(3, 3, n))))
      st = transfer.Stencil(grid, x)
      g = transfer.p2g(grid, st, v, m, A).reshape(-1, 4).T
      np.testing.assert_allclose(jnp.sum(g[0]), jnp.sum(m), rtol=_TOL64)
      p = np.array([float(jnp.sum(m * v[d])) for d in range(3)])
      np.testing.assert_allclose(jnp.sum(g[1:], 1), p, atol=_TOL64)
      has = g[0] > 0
      gv = tuple(jnp.where(has, g[d + 1] / jnp.where(has, g[0], 1), 0)
                 for d in range(3))
      v2, _ = transfer.g2p(grid, st, gv)
      p2 = np.array([float(jnp.sum(m * v2[d])) for d in range(3)])
      np.testing.assert_allclose(p2, p, atol=1e-9)


class StepTest(absltest.TestCase):

  def test_free_fall_matches_discrete_kinematics(self):
    """x(t) = x0 + v0 t + g t^2 / 2 + g t dt / 2 (symplectic Euler)."""
    with jax.enable_x64(True):
      grid = mpm.GridSpec(res=16, size=1.0)
      g = (0.5, -1.0, -9.8)
      dt, sub, frames = 1e-3, 10, 3
      cfg = mpm.SimConfig(grid=grid, dt=dt, substeps_per_frame=sub,
                          gravity=g, dtype='float64')
      x0 = _block(4, (0.4, 0.4, 0.5), grid.dx / 2)
      v0 = np.array([0.3, 0.0, 1.0])
      mat = mpm.make_materials('fixed_corotated', 1e4, 0.3, 1000.,
                               num=len(x0), dtype=jnp.float64)
      s = mpm.init_state(x0, v0, (grid.dx / 2) ** 3, mat, cfg)
      _, xs, Fs = jax.jit(mpm.rollout, static_argnums=(3, 4))(
        s, mat, None, cfg, frames)
      self.assertEqual(xs.shape, (frames + 1, len(x0), 3))
      for f in range(frames + 1):
        t = f * sub * dt
        ref = x0 + v0 * t + np.asarray(g) * (0.5 * t * t + 0.5 * t * dt)
        np.testing.assert_allclose(xs[f], ref, atol=1e-12,
                                   err_msg=f'frame {f}')
      # Uniform motion: no deformation.
      np.testing.assert_allclose(Fs[-1], np.broadcast_to(np.eye(3),
                                                         Fs[-1].shape),
                                 atol=1e-12)

  def test_momentum_conserved_without_gravity_and_walls(self):
    with jax.enable_x64(True):
      grid = mpm.GridSpec(res=16, size=1.0)
      cfg = mpm.SimConfig(grid=grid, dt=2e-4, substeps_per_frame=8,
                          gravity=(0, 0, 0), dtype='float64')
      x0 = _block(5, (0.35, 0.35, 0.35), grid.dx / 2, jitter=0.5)
      rng = np.random.default_rng(2)
      v0 = 0.3 * rng.normal(size=x0.shape)   # deforms the block: stress
      mat = mpm.make_materials('fixed_corotated', 2e4, 0.3, 1000.,
                               num=len(x0), dtype=jnp.float64)
      s = mpm.init_state(x0, v0, (grid.dx / 2) ** 3, mat, cfg)
      s1 = jax.jit(mpm.make_frame(cfg))(s, mat, None)
      p0 = np.sum(s.mass[:, None] * s.v, 0)
      p1 = np.sum(s1.mass[:, None] * s1.v, 0)
      np.testing.assert_allclose(p1, p0, atol=_TOL64)
      # The block did deform, so stress acted.
      self.assertGreater(float(jnp.abs(s1.F - jnp.eye(3)).max()), 1e-4)

  def test_frame_equals_its_substeps_and_keeps_the_state_time(self):
    """make_frame derives each substep's time from its step instead of
    carrying it; it equals make_substep applied substep by substep, from a
    state whose time is not step * dt (a plane switched on at that time),
    and ends at step * dt."""
    with jax.enable_x64(True):
      grid = mpm.GridSpec(res=16, size=1.0)
      dt = 1e-3
      cfg = mpm.SimConfig(
        grid=grid, dt=dt, substeps_per_frame=6, dtype='float64',
        boundary_conditions=(mpm.SurfaceCollider(
          point=(0, 0, 0.45), surface='sticky', start_time=0.4,
          end_time=0.4025),))
      x0 = _block(3, (0.4, 0.4, 0.44), grid.dx / 2)
      mat = mpm.make_materials('fixed_corotated', 1e4, 0.3, 1000.,
                               num=len(x0), dtype=jnp.float64)
      s = mpm.init_state(x0, (0.2, 0.0, -0.5), (grid.dx / 2) ** 3, mat, cfg)
      s = s.replace(t=jnp.asarray(0.4), step=jnp.asarray(3, jnp.int32))
      forces = mpm.make_forces(cfg)
      one = jax.jit(mpm.make_substep(cfg))
      ref = s
      for _ in range(cfg.substeps_per_frame):
        ref = one(ref, mat, forces)
      got = jax.jit(mpm.make_frame(cfg))(s, mat, forces)
      for name in ('x', 'v', 'F', 'C', 't', 'step'):
        np.testing.assert_allclose(getattr(got, name), getattr(ref, name),
                                   rtol=1e-12, atol=1e-12, err_msg=name)
      self.assertEqual(int(got.step), 9)
      self.assertEqual(float(got.t), 9 * dt)
      # The plane was on in the first substep only (t = 0.4; the next
      # substeps run at 0.004-0.008 s): it stopped the block there.
      free = jax.jit(mpm.make_frame(cfg))(s.replace(t=jnp.asarray(0.0)), mat,
                                          forces)
      self.assertGreater(float(jnp.abs(free.x - got.x).max()), 1e-6)

  def test_eager_rollout_and_substep_check_their_inputs(self):
    """Concrete bad inputs get mpm.run's messages (rollout returned NaN, or
    ran with nu = 0.5); traced ones are not read."""
    cfg = mpm.SimConfig(grid=mpm.GridSpec(res=8, size=1.0), dt=1e-3,
                        substeps_per_frame=1)
    x = _block(2, (0.45, 0.45, 0.45), 0.02)
    mat = mpm.make_materials('fixed_corotated', 1e4, 0.3, 1000.0, num=8)
    s = mpm.init_state(x, np.zeros(3), 1e-5, mat, cfg)
    v = np.zeros((8, 3))
    v[4, 1] = np.nan
    cases = (
      (s, mat.replace(nu=mat.nu.at[2].set(0.5)),
       r'nu outside \(-1, 0\.5\) for 1 of 8 particles \(2\)'),
      (s, mat.replace(E=mat.E.at[1].set(jnp.nan)),
       r'material field E is not finite for 1 of 8 particles \(1\)'),
      (s, mat.replace(E=0.0 * mat.E), 'E <= 0 for 8 of 8 particles'),
      (s, mat.replace(rho=mat.rho.at[0].set(0.0)),
       r'rho <= 0 for 1 of 8 particles \(0\)'),
      (mpm.init_state(x, v, 1e-5, mat, cfg), mat,
       r'the initial state has non-finite v for 1 of 8 particles \(4\)'))
    substep_fn = mpm.make_substep(cfg)
    for state, m, want in cases:
      with self.subTest(want):
        with self.assertRaisesRegex(mpm.MPMInputError, '^mpm: ' + want):
          mpm.rollout(state, m, None, cfg, 1)
        with self.assertRaisesRegex(mpm.MPMInputError, want):
          substep_fn(state, m)
        # Under tracing nothing is read (no error, no concretization).
        out = jax.eval_shape(lambda a, b: mpm.rollout(a, b, None, cfg, 1)[1],
                             state, m)
        self.assertEqual(out.shape, (2, 8, 3))
        # mpm.run's own check says 'mpm.run:'; check=False skips it.
        with self.assertRaisesRegex(mpm.MPMInputError, '^mpm.run: ' + want):
          mpm.FrameLoop(state, m, None, cfg, 1)
        mpm.FrameLoop(state, m, None, cfg, 1, check=False)


if __name__ == '__main__':
  absltest.main()
