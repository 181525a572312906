"""Finite, correct gradients for every material and ground mode (issue 17).

Every constitutive model (and rigid bodies), every ground mode, from rest
(``F = I``: repeated singular values, zero deviatoric strain, grid nodes at
rest on the collider), through ``pipeline.simulate`` and the deformation of
the Gaussians, against central finite differences in float64. Plus the
float32 hazards at scale: a grid node with a tiny mass (the NaN that the
fixed-corotated benchmark block hit at 50k+ particles), an empty point-force
selection, and the README example.

Compile cost dominates; each test compiles one ``value_and_grad`` and
evaluates it three times (at the point and at +-eps along a direction).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl.testing import absltest

from physsplat_jax import mpm
from physsplat_jax import pipeline as pl
from physsplat_jax.types import Gaussians
from physsplat_jax.types import ObjectInfo
from physsplat_jax.types import Scene

_EPS = 1e-5    # central-difference step (float64, relative direction)
_FD_RTOL = 1e-4
_F32_RTOL = 1e-3  # float32 AD vs float64 AD

# Models per scene, grouped so that each ground mode sees SVD and non-SVD
# models and every model appears once (fewer, smaller compiles).
# Cohesionless sand at rest sits on the apex of its Drucker-Prager cone,
# where the return map has no derivative (AD takes the elastic side): from
# exact rest, as soon as anything deforms it (the ground, or a neighbour
# through the shared grid), central differences straddle the apex and
# differ from AD by 0.1-16% (measured), and so do its neighbours'. Sand is
# therefore checked for finite gradients from rest (``test_sand_...``);
# tests/mpm_grad_test.py checks it against FD away from the apex.
_GROUPS = {
  'slip': ('fixed_corotated', 'snow', 'von_mises', 'rigid'),
  'sticky': ('neo_hookean', 'stvk', 'plasticine', 'rigid'),
  'none': ('foam', 'bingham', 'newtonian'),
}


def _scene(models, n=40, half=0.02, gap=0.001, seed=0):
  """One cube per model on a 2 x 2 block, resting (1 mm gap) on a table."""
  rng = np.random.default_rng(seed)
  parts, ids, objs = [], [], []
  for k, m in enumerate(models):
    c = np.array([0.06 * (k % 2), 0.06 * (k // 2), gap + half])
    parts.append(rng.uniform(c - half, c + half, (n, 3)))
    ids.append(np.full(n, k, np.int32))
    objs.append(ObjectInfo(m))
  parts.append(rng.uniform([-0.04, -0.04, -0.02], [0.1, 0.1, 0.0], (n, 3)))
  ids.append(np.full(n, len(models), np.int32))
  objs.append(ObjectInfo('table', fixed=True))
  m = np.concatenate(parts)
  K = len(m)
  g = Gaussians(
    means=jnp.asarray(m, jnp.float32),
    log_scales=jnp.full((K, 3), np.log(0.004), jnp.float32),
    quats=jnp.tile(jnp.array([1.0, 0, 0, 0], jnp.float32), (K, 1)),
    opacity_logits=jnp.full((K,), 2.0, jnp.float32),
    sh=jnp.zeros((K, 1, 3), jnp.float32))
  return Scene(gaussians=g, object_ids=jnp.asarray(np.concatenate(ids)),
               objects=tuple(objs), up_axis='z', meters_per_unit=1.0,
               name='grad')


def _check_directional(test, fn, params, seed=0, fields=None):
  """AD vs central FD along a random direction of every float leaf, and of
  each of ``fields`` (Params field names) alone: a field whose share of
  the total is small would otherwise pass with its own gradient wrong.

  ``fn`` is a jitted ``value_and_grad``; returns the gradient.
  """
  rng = np.random.default_rng(seed)
  d = jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape), a.dtype),
                   params)
  _, g = fn(params)
  for leaf in jax.tree.leaves(g):
    test.assertTrue(np.all(np.isfinite(np.asarray(leaf))))

  def along(direction):
    ad = sum(float(jnp.sum(a * b)) for a, b in
             zip(jax.tree.leaves(g), jax.tree.leaves(direction)))
    fp, _ = fn(jax.tree.map(lambda a, b: a + _EPS * b, params, direction))
    fm, _ = fn(jax.tree.map(lambda a, b: a - _EPS * b, params, direction))
    return ad, float(fp - fm) / (2 * _EPS)

  ad, fd = along(d)
  test.assertGreater(abs(ad), 1e-8)  # the direction really matters
  np.testing.assert_allclose(ad, fd, rtol=_FD_RTOL)
  zero = jax.tree.map(jnp.zeros_like, d)
  for field in fields or ():
    ad, fd = along(zero.replace(**{field: getattr(d, field)}))
    test.assertGreater(abs(ad), 1e-10, msg=field)  # it matters at all
    np.testing.assert_allclose(ad, fd, rtol=_FD_RTOL, err_msg=field)
  return g


def _from_rest(models, ground):
  """(value_and_grad, params, loss) of a weighted final-frame loss."""
  mats = [pl.ObjectMaterial(m, 2e4, 0.3, 1000.0, rigid=(m == 'rigid'))
          for m in models]
  mats.append(pl.ObjectMaterial('rigid', 1e10, 0.3, 700.0, rigid=True))
  cfg = pl.PipelineConfig(
    grid_res=16, num_frames=2, fps=120.0, substeps_per_frame=None,
    sampling='kmeans', max_particles=30 * len(models),
    particles_per_cell=2.0, use_mpdp=False, render='none', margin=1.0,
    fill=False, ground=ground)
  prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), _scene(models), mats, cfg)
  prep = prep.astype(jnp.float64)
  params = pl.init_params(prep, cfg)  # float64, as prep
  rng = np.random.default_rng(1)
  shape = prep.rest_means.shape
  wm = jnp.asarray(rng.normal(size=shape))
  wc = jnp.asarray(rng.normal(size=shape + (3,)))
  wr = jnp.asarray(rng.normal(size=shape + (3,)))

  def loss(p):
    t = pl.simulate(p, prep, cfg)
    # Means, covariances F Sigma F^T (/ Sigma's scale) and polar rotations
    # of F: the deformation of the Gaussians is in the loop.
    return (jnp.sum(wm * t.means[-1])
            + 1e-2 * jnp.sum(wc * t.covariances[-1]) / 0.004 ** 2
            + 1e-2 * jnp.sum(wr * t.rotations[-1]))

  return jax.jit(jax.value_and_grad(loss)), params, loss


class PipelineFromRestTest(absltest.TestCase):
  """Each model's object starts at rest (F = I) touching the ground.

  The margin keeps the objects off the domain box: its one-sided constraint
  (zero any outward node velocity) has a kink at v = 0, which central
  differences straddle from rest (measured 4% off with margin 0.3) while AD
  takes one side.
  """

  def _check(self, ground, velocity=None):
    models = _GROUPS[ground]
    with jax.enable_x64(True):
      fn, params, loss = _from_rest(models, ground)
      self.assertFalse(np.any(np.asarray(params.velocity)))  # from rest
      if velocity is not None:  # F = I still, moving
        params = params.replace(velocity=jnp.asarray(velocity, jnp.float64))
      g = _check_directional(self, fn, params,
                             fields=('log_scale', 'velocity'))
      # Forward mode (the custom JVPs as written; reverse mode is their
      # transpose) along another direction: against the gradient.
      rng = np.random.default_rng(7)
      d = jax.tree.map(
        lambda a: jnp.asarray(rng.normal(size=a.shape), a.dtype), params)
      _, fwd = jax.jit(lambda p, d: jax.jvp(loss, (p,), (d,)))(params, d)
      rev = sum(float(jnp.sum(a * b)) for a, b in
                zip(jax.tree.leaves(g), jax.tree.leaves(d)))
      np.testing.assert_allclose(float(fwd), rev, rtol=1e-9)
      # Every object's velocity gradient is non-zero (no silent zero), and
      # every deformable object's stiffness matters.
      self.assertTrue(np.all(np.any(np.asarray(g.velocity) != 0, axis=1)))
      deformable = np.array([m != 'rigid' for m in models])
      self.assertTrue(np.all(np.asarray(g.log_scale)[deformable, 0] != 0))

  # Each pipeline case compiles a value_and_grad of simulate (~40-80 s on
  # the shared 2-core VM): slow, as the default run's budget is ~20 s each.
  @pytest.mark.slow
  def test_slip_ground_matches_fd_x64(self):
    self._check('slip')

  @pytest.mark.slow
  def test_sticky_ground_matches_fd_x64(self):
    self._check('sticky')

  @pytest.mark.slow
  def test_no_ground_matches_fd_x64(self):
    # Without a ground the cubes only fall, undeformed: their materials
    # would not matter. Thrown at one another (from F = I) they collide.
    self._check('none', velocity=[[1.5, 1.5, 0.0], [-1.5, 0.0, 0.0],
                                  [0.0, -1.5, 0.0]])

  @pytest.mark.slow
  def test_sand_from_rest_is_finite_x64(self):
    with jax.enable_x64(True):
      fn, params, _ = _from_rest(('drucker_prager',), 'slip')
      _, g = fn(params)
      for leaf in jax.tree.leaves(g):
        self.assertTrue(np.all(np.isfinite(np.asarray(leaf))))
      self.assertTrue(np.all(np.asarray(g.velocity) != 0))


class Float32HazardTest(absltest.TestCase):

  def test_tiny_node_mass_float32_matches_float64(self):
    """A node reached only at the edge of the B-spline support.

    Two particles whose fractional positions are ``0.5 + 2e-4`` along x and
    y give far nodes a mass ~1e-22 kg; JAX's rule for ``1 / m`` multiplied
    by ``m^-2`` (inf in float32) and the density gradient was NaN.
    """
    grid = mpm.GridSpec(res=16, size=1.0)
    f = np.array([0.5 + 2e-4, 0.5 + 2e-4, 1.0])
    x0 = (np.array([6, 6, 6]) + f) * grid.dx
    x0 = np.stack([x0, x0 + [0.0, 0.0, 0.25 * grid.dx]])
    n = len(x0)
    v0 = np.array([[0.1, 0.2, 0.3], [0.3, -0.1, 0.2]])

    def grads(dtype):
      cfg = mpm.SimConfig(grid=grid, dt=1e-4, substeps_per_frame=2,
                          models=('fixed_corotated',), dtype=dtype,
                          gravity=(0.0, 0.0, 0.0))

      def loss(v, rho):
        mat = mpm.make_materials(['fixed_corotated'] * n,
                                 jnp.full((n,), 1e4, dtype),
                                 jnp.full((n,), 0.3, dtype), rho,
                                 config_models=cfg.models, dtype=dtype)
        s = mpm.init_state(jnp.asarray(x0, dtype), v, 1e-9, mat, cfg)
        _, xs, Fs = mpm.rollout(s, mat, None, cfg, 1)
        return jnp.sum(xs[-1] ** 2) + jnp.sum(Fs[-1])

      args = (jnp.asarray(v0, dtype), jnp.full((n,), 1000.0, dtype))
      return jax.jit(jax.grad(loss, argnums=(0, 1)))(*args)

    g32 = grads('float32')
    for a in g32:
      self.assertTrue(np.all(np.isfinite(np.asarray(a))))
    with jax.enable_x64(True):
      g64 = grads('float64')
    for a, b in zip(g32, g64):
      np.testing.assert_allclose(np.asarray(a, np.float64),
                                 np.asarray(b), rtol=_F32_RTOL,
                                 atol=_F32_RTOL * float(np.max(np.abs(b))))

  def test_empty_point_force_selection_x64(self):
    """A point force that selects no particle (total mass 0)."""
    with jax.enable_x64(True):
      grid = mpm.GridSpec(res=12, size=1.0)
      sp = grid.dx / 2
      i = np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing='ij'), -1)
      x0 = np.array([0.45, 0.45, 0.5]) + (i.reshape(-1, 3) + 0.5) * sp
      n = len(x0)
      # Non-uniform velocities: the block deforms, so rho matters.
      v0 = np.random.default_rng(1).normal(size=(n, 3))
      cfg = mpm.SimConfig(
        grid=grid, dt=1e-3, substeps_per_frame=2, dtype='float64',
        boundary_conditions=(mpm.PointForce(
          point=(0.1, 0.1, 0.1), radius=0.01, force=(1.0, 0.0, 0.0),
          end_time=1.0, per_particle=False),))

      def loss(rho):
        mat = mpm.make_materials(['fixed_corotated'] * n,
                                 jnp.full((n,), 1e3), jnp.full((n,), 0.3),
                                 rho, dtype=jnp.float64)
        s = mpm.init_state(x0, v0, sp ** 3, mat, cfg)
        _, xs, Fs = mpm.rollout(s, mat, None, cfg, 1)
        return jnp.sum(Fs[-1] ** 2) + jnp.sum(xs[-1, :, 2])

      rho = jnp.linspace(900.0, 1100.0, n)
      fn = jax.jit(jax.value_and_grad(loss))
      _, g = fn(rho)
      self.assertTrue(np.all(np.isfinite(np.asarray(g))))
      d = jnp.asarray(np.random.default_rng(0).normal(size=n))
      h = 1e-3
      fd = (fn(rho + h * d)[0] - fn(rho - h * d)[0]) / (2 * h)
      np.testing.assert_allclose(float(jnp.sum(g * d)), float(fd),
                                 rtol=_FD_RTOL)


class RigidContactGradientTest(absltest.TestCase):

  @pytest.mark.optimized  # its loops run 6x longer unoptimised
  def test_rigid_projection_with_planes_matches_fd_x64(self):
    """Bodies in and out of contact, sticky and slip planes, free particles.

    Empty contact sets and a body at rest on a sticky plane (no sliding
    direction) once made the per-body sums' backward pass NaN (0 * inf),
    with the right forward values.
    """
    from physsplat_jax.mpm import rigid
    with jax.enable_x64(True):
      rng = np.random.default_rng(3)
      # Body 0 just below z = 0.3 (in contact), body 1 high up (no
      # contact), body 2 fixed, then free particles (the dump segment).
      x0 = np.concatenate([
        np.array([0.5, 0.5, 0.305]) + 0.02 * rng.uniform(-1, 1, (8, 3)),
        np.array([0.3, 0.6, 0.7]) + 0.02 * rng.uniform(-1, 1, (8, 3)),
        np.array([0.7, 0.3, 0.6]) + 0.02 * rng.uniform(-1, 1, (4, 3)),
        rng.uniform(0.4, 0.6, (5, 3))])
      body = np.array([0] * 8 + [1] * 8 + [2] * 4 + [-1] * 5)
      n = len(x0)
      mass = jnp.asarray(rng.uniform(0.5, 1.5, n))
      planes = [((0.0, 0.0, 0.3), (0.0, 0.0, 1.0), np.inf, 'sticky',
                 jnp.asarray(True), 0.005),
                ((0.0, 0.0, 0.3), (0.0, 0.0, 1.0), 0.3, 'separate',
                 jnp.asarray(True), 0.005)]
      F = tuple(tuple(jnp.full((n,), float(i == j)) for j in range(3))
                for i in range(3))
      # Cotangents of the size a long rollout builds up.
      w = jnp.asarray(100.0 * rng.normal(size=(n, 3)))

      def loss(v):
        _, x, vn, C, Fr = rigid.project(
          3, (False, False, True), 0.02, 1e-3, jnp.asarray(body), mass,
          tuple(jnp.asarray(x0[:, d]) for d in range(3)),
          tuple(v[:, d] for d in range(3)), F, planes=planes)
        return (jnp.sum(jnp.stack(x, -1) * w) + jnp.sum(jnp.stack(vn, -1))
                + sum(jnp.sum(c) for row in C for c in row)
                + sum(jnp.sum(f ** 2) for row in Fr for f in row))

      # Body 0 falls onto the planes, body 1 rests (no sliding).
      v = np.zeros((n, 3))
      v[:8] = [0.1, 0.0, -1.0]
      v[16:] = rng.normal(size=(n - 16, 3))
      v = jnp.asarray(v)
      fn = jax.jit(jax.value_and_grad(loss))
      _, g = fn(v)
      self.assertTrue(np.all(np.isfinite(np.asarray(g))))
      d = jnp.asarray(rng.normal(size=(n, 3)))
      h = 1e-6
      fd = (fn(v + h * d)[0] - fn(v - h * d)[0]) / (2 * h)
      np.testing.assert_allclose(float(jnp.sum(g * d)), float(fd),
                                 rtol=_FD_RTOL)


@pytest.mark.slow
class ReadmeExampleTest(absltest.TestCase):

  def test_readme_example_gradients_are_finite(self):
    """README: grad of the mean final height wrt init_params (tabletop)."""
    import physsplat_jax as ps

    scene = ps.load_scene('tabletop')
    materials = ps.perceive_scene(scene)
    config = ps.PipelineConfig(
      num_frames=1, fps=600.0, grid_res=16, max_particles=150,
      render='none',
      initial_velocity=(('rubber ball', (0.5, 0.0, 1.0)),))
    prepared, _ = ps.prepare_scene(jax.random.PRNGKey(0), scene, materials,
                                    config)
    params = ps.init_params(prepared, config)

    def loss(p):
      return ps.simulate(p, prepared, config).means[-1, :, 2].mean()

    g = jax.jit(jax.grad(loss))(params)
    for leaf in jax.tree.leaves(g):
      self.assertTrue(np.all(np.isfinite(np.asarray(leaf))))
    # The jelly cube's velocity gradient (the NaN of issue 17) is non-zero.
    j = prepared.spec.object_names.index('jelly cube')
    self.assertNotEqual(float(np.asarray(g.velocity)[j, 2]), 0.0)


@pytest.mark.slow
class ScaleTest(absltest.TestCase):

  def test_benchmark_block_50k_float32_gradient_is_finite(self):
    """experiments/benchmark_mpm.py's fixed-corotated block, 50k x 200."""
    from experiments import benchmark_mpm as bench

    n, steps = 50_000, 200
    cfg = bench.make_config(steps).replace(remat_frames=True)
    x = bench.make_block(n)

    def loss(E):
      mat = mpm.make_materials('fixed_corotated', E, bench.NU, bench.RHO,
                               num=n)
      s = mpm.init_state(x, (0.0, 0.0, -2.0), (bench.GRID.dx / 2) ** 3, mat,
                         cfg)
      s = mpm.make_frame(cfg)(s, mat, None)
      return jnp.mean(s.x[:, 2])

    v, g = jax.jit(jax.value_and_grad(loss))(jnp.float32(bench.E))
    self.assertTrue(np.isfinite(float(v)))
    self.assertTrue(np.isfinite(float(g)))
    self.assertNotEqual(float(g), 0.0)


if __name__ == '__main__':
  absltest.main()
