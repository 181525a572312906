"""End-to-end tests of physsplat_jax.pipeline on tiny synthetic scenes.

Analytic checks through every stage (scene -> simulation frame -> MPM ->
deformed Gaussians -> scene frame): free fall of a body in a y-up scene in
centimetres, gradients of the final centre of mass with respect to the
initial velocity (exactly the elapsed time in free fall) and a finite
difference check in float64, colliders from fixed objects, one compilation
for two same-shape scenes, and the host loop's outputs.
"""

import dataclasses
import os
import tempfile
import threading
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from physsplat_jax import mpm
from physsplat_jax import io as ps_io
from physsplat_jax import pipeline as pl
from physsplat_jax.io import ply as ply_io
from physsplat_jax.io import spz as spz_io
from physsplat_jax.pipeline import host
from physsplat_jax.types import Gaussians
from physsplat_jax.types import ObjectInfo
from physsplat_jax.types import Scene

# Free fall: the centre of mass of the simulated Gaussians vs x0 + v0 t +
# g t^2 / 2, relative to the distance fallen (MPM integrates the grid
# velocity exactly for a body with no stress, up to float32 rounding).
_FREE_FALL_RTOL = 2e-3
_GRAD_RTOL = 1e-3


def _blob(rng, center, half, n):
  return rng.uniform(np.asarray(center) - half, np.asarray(center) + half,
                     size=(n, 3))


def _scene(up='z', units=1.0, with_table=True, seed=0, n=300):
  """A cube of Gaussians (object 0) above an optional fixed slab (1)."""
  rng = np.random.default_rng(seed)
  cube = _blob(rng, (0.0, 0.0, 0.05), 0.03, n)
  parts = [cube]
  ids = [np.zeros(n, np.int32)]
  objects = [ObjectInfo('cube', 'rubber')]
  if with_table:
    slab = _blob(rng, (0.0, 0.0, -0.01), np.array([0.12, 0.12, 0.01]), n)
    parts.append(slab)
    ids.append(np.ones(n, np.int32))
    objects.append(ObjectInfo('table', 'wood', fixed=True))
  m = np.concatenate(parts) / units  # metres -> scene units
  if up == 'y':  # scene (x, y, z) = metres (x, z, -y)
    m = np.stack([m[:, 0], m[:, 2], -m[:, 1]], 1)
  K = len(m)
  g = Gaussians(
    means=jnp.asarray(m, jnp.float32),
    log_scales=jnp.full((K, 3), np.log(0.004 / units), jnp.float32),
    quats=jnp.tile(jnp.array([1.0, 0, 0, 0], jnp.float32), (K, 1)),
    opacity_logits=jnp.full((K,), 2.0, jnp.float32),
    sh=jnp.zeros((K, 1, 3), jnp.float32))
  return Scene(gaussians=g, object_ids=jnp.asarray(np.concatenate(ids)),
               objects=tuple(objects), up_axis=up, meters_per_unit=units,
               name='tiny')


_RUBBER = pl.ObjectMaterial('fixed_corotated', 3e4, 0.3, 1000.0)
_WOOD = pl.ObjectMaterial('rigid', 1e10, 0.3, 700.0, rigid=True)


def _config(**kw):
  base = dict(grid_res=16, num_frames=3, fps=30.0, substeps_per_frame=None,
              sampling='kmeans', max_particles=200, particles_per_cell=2.0,
              use_mpdp=False, render='none', width=32, height=24,
              margin=1.5, fill=False)
  base.update(kw)
  return pl.PipelineConfig(**base)


class FrameTest(absltest.TestCase):

  def test_up_rotation_is_proper_and_maps_up_to_z(self):
    for axis in ('x', 'y', 'z', '-x', '-y', '-z'):
      u = np.zeros(3)
      u['xyz'.index(axis[-1])] = -1.0 if axis.startswith('-') else 1.0
      R = pl.up_rotation(u)
      np.testing.assert_allclose(R @ u, [0, 0, 1], atol=1e-12,
                                 err_msg=f'mismatch: {axis}')
      np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
      self.assertAlmostEqual(np.linalg.det(R), 1.0, places=12)

  def test_transform_gaussians_round_trip(self):
    scene = _scene(up='y', units=0.01, with_table=False)
    fr = pl.SimFrame(rotation=jnp.asarray(pl.up_rotation([0, 1, 0]),
                                          jnp.float32),
                     scale=jnp.asarray(0.01), shift=jnp.asarray([1., 2, 3]))
    g = scene.gaussians
    gs = pl.transform_gaussians(g, fr)
    np.testing.assert_allclose(fr.to_scene(gs.means), g.means, rtol=1e-5,
                               atol=1e-4)
    np.testing.assert_allclose(fr.covariance_to_scene(gs.covariances),
                               g.covariances, rtol=1e-4, atol=1e-12)


class PrepareTest(absltest.TestCase):

  def test_support_plane_and_counts(self):
    scene = _scene()
    prep, rep = pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER, _WOOD], _config())
    spec = prep.spec
    self.assertEqual(spec.object_names, ('cube',))
    self.assertEqual(rep.num_particles, prep.num_particles)
    self.assertLessEqual(prep.num_particles, 200)
    # The slab's top (z = 0 m) is the ground plane, shifted into the grid.
    ground_scene = spec.colliders.ground_z - float(prep.frame.shift[2])
    self.assertAlmostEqual(ground_scene, 0.0, delta=0.002)
    self.assertEqual(spec.colliders.anchors, ())
    # Drivers lie inside the grid with room for the boundary layer.
    x0 = np.asarray(prep.x0)
    self.assertTrue(np.all(x0 > 3 * spec.dx))
    self.assertTrue(np.all(x0 < spec.grid_size - 3 * spec.dx))

  def test_anchor_for_fixed_object_reaching_into_movables(self):
    # A fixed post through the cube becomes a sticky anchor box.
    rng = np.random.default_rng(3)
    scene = _scene(with_table=False)
    post = _blob(rng, (0.0, 0.0, 0.05), np.array([0.005, 0.005, 0.05]), 50)
    g = scene.gaussians
    K = len(post)
    g2 = Gaussians(
      means=jnp.concatenate([g.means, jnp.asarray(post, jnp.float32)]),
      log_scales=jnp.concatenate([g.log_scales, g.log_scales[:K]]),
      quats=jnp.concatenate([g.quats, g.quats[:K]]),
      opacity_logits=jnp.concatenate([g.opacity_logits,
                                      g.opacity_logits[:K]]),
      sh=jnp.concatenate([g.sh, g.sh[:K]]))
    ids = jnp.concatenate([scene.object_ids, jnp.ones(K, jnp.int32)])
    scene = scene.replace(gaussians=g2, object_ids=ids,
                          objects=scene.objects + (ObjectInfo(
                            'post', 'wood', fixed=True),))
    prep, rep = pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER, _WOOD], _config())
    self.assertLen(prep.spec.colliders.anchors, 1)
    self.assertTrue(any('anchor' in n for n in rep.colliders))

  def test_bad_inputs_raise_clear_errors(self):
    scene = _scene()
    with self.assertRaisesRegex(pl.PipelineError, 'one material per object'):
      pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER], _config())
    bad = pl.ObjectMaterial('fixed_corotated', 3e4, 0.7, 1000.0)
    with self.assertRaisesRegex(pl.PipelineError, r'nu=0\.7'):
      pl.prepare_scene(jax.random.PRNGKey(0), scene, [bad, _WOOD], _config())
    fixed_all = scene.replace(objects=(ObjectInfo('cube', fixed=True),
                                       scene.objects[1]))
    with self.assertRaisesRegex(pl.PipelineError, 'no movable object'):
      pl.prepare_scene(jax.random.PRNGKey(0), fixed_all, [_RUBBER, _WOOD], _config())
    with self.assertRaisesRegex(pl.PipelineError, 'grid_res'):
      _config(grid_res=4)
    with self.assertRaisesRegex(pl.PipelineError, 'no such movable object'):
      pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER, _WOOD], _config(
        initial_velocity=(('table', (0.0, 0.0, 1.0)),)))


  def test_movable_object_without_gaussians_is_refused(self):
    # An empty box, an all -1 mask or an ObjectInfo no Gaussian points to:
    # the object was dropped without a word (Params rows shifted).
    scene = _scene()
    ghost = scene.replace(objects=scene.objects + (ObjectInfo('ghost'),))
    with self.assertRaisesRegex(
        pl.PipelineError, r"movable object 'ghost' \(scene 'tiny'\) has no "
        'Gaussians; remove it and its material, mark it fixed, or fix its '
        'segmentation'):
      pl.prepare_scene(0, ghost, [_RUBBER, _WOOD, _RUBBER], _config())
    # An empty fixed object is harmless (nothing to collide with).
    prep, _ = pl.prepare_scene(
      0, scene.replace(objects=scene.objects + (ObjectInfo('shelf',
                                                           fixed=True),)),
      [_RUBBER, _WOOD, _WOOD], _config())
    self.assertEqual(prep.spec.object_names, ('cube',))

  def test_the_stress_kernel_check_starts_with_the_preparation(self):
    """On a GPU with constitutive_kernel='auto', preparing a scene starts
    the stress kernel's build check in the background; not with 'jax', and
    not off a GPU. (The GPU and the check are simulated.)"""
    from physsplat_jax.mpm import pallas_constitutive as pc
    from physsplat_jax.pipeline import prepare
    for backend, kernel, want in (('gpu', 'auto', True),
                                  ('gpu', 'jax', False),
                                  ('cpu', 'auto', False)):
      with self.subTest(backend=backend, kernel=kernel), \
          mock.patch.object(jax, 'default_backend', lambda b=backend: b), \
          mock.patch.object(pc, 'start_probe') as probe:
        got = prepare.start_kernel_check(
          _config(constitutive_kernel=kernel))
        self.assertEqual(got, want)
        self.assertEqual(probe.call_count, int(want))
    # prepare_scene calls it with its config.
    with mock.patch.object(prepare, 'start_kernel_check',
                           return_value=False) as check:
      cfg = _config()
      pl.prepare_scene(jax.random.PRNGKey(0), _scene(), [_RUBBER, _WOOD],
                       cfg)
      check.assert_called_once_with(cfg)


class SimulateTest(absltest.TestCase):

  def test_free_fall_through_every_frame_map(self):
    # A y-up scene in centimetres; no table, no ground: the cube falls
    # freely along -y in scene coordinates.
    scene = _scene(up='y', units=0.01, with_table=False)
    v0 = (0.1, 0.2, 0.0)  # m/s in scene axes (x, y-up, z)
    cfg = _config(ground='none', num_frames=3, margin=3.0,
                  initial_velocity=(('cube', v0),))
    prep, rep = pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER], cfg)
    params = pl.init_params(prep, cfg)
    traj = pl.simulate_jit(params, prep, cfg)
    t = np.arange(cfg.num_frames + 1) / cfg.fps
    dt = rep.time_step['dt_s']
    com = np.asarray(traj.means, np.float64).mean(1)  # scene units (cm)
    # Symplectic Euler (v then x) falls exactly g (t^2 + t dt) / 2.
    drop = 0.5 * 9.8 * (t**2 + t * dt)
    expect = com[0] + (np.outer(t, v0) - np.outer(drop, [0.0, 1.0, 0.0])
                       ) / 0.01
    np.testing.assert_allclose(com, expect, rtol=0,
                               atol=_FREE_FALL_RTOL * drop[-1] / 0.01,
                               err_msg='mismatch: centre of mass')
    self.assertTrue(np.all(np.isfinite(np.asarray(traj.covariances))))
    # A falling body with no stress keeps its shape: covariances unchanged.
    np.testing.assert_allclose(traj.covariances[-1], traj.covariances[0],
                               atol=1e-3 * float(np.max(np.abs(
                                 traj.covariances[0]))))

  def test_arguments_of_the_wrong_type_are_named(self):
    # Swapped or missing arguments: AttributeError: ... no attribute 'spec'.
    cfg = _config(num_frames=1)
    prep, _ = pl.prepare_scene(0, _scene(), [_RUBBER, _WOOD], cfg)
    params = pl.init_params(prep, cfg)
    for args, want in (
        ((prep, params), 'params must be a pipeline.Params, got '
         'PreparedScene; the arguments are \\(params, prepared, config\\)'),
        ((params, None), 'prepared must be a pipeline.PreparedScene, got '
         'NoneType')):
      for fn in (pl.simulate_jit, pl.simulate):
        with self.subTest(want=want, fn=fn.__name__), \
            self.assertRaisesRegex(pl.PipelineError, want):
          fn(*args, cfg)

  def test_params_that_do_not_fit_the_prepared_scene_are_named(self):
    cfg = _config(num_frames=1)
    prep, _ = pl.prepare_scene(0, _scene(), [_RUBBER, _WOOD], cfg)
    # A force the scene was not prepared with ran without it, silently,
    # with a zero gradient for it.
    pushed = dataclasses.replace(cfg, forces=(
      pl.ForceSpec('impulse', 'cube', vector=(0.0, 0.0, 2.0)),))
    with self.assertRaisesRegex(
        pl.PipelineError, r"config.forces are placed at \[\('cube', None\)"
        r"\] .* prepared with nothing; forces are placed by prepare_scene"):
      pl.simulate_jit(pl.init_params(prep, pushed), prep, pushed)
    # The same force with its point moved after preparing: the point was
    # silently the prepared one.
    prep2, _ = pl.prepare_scene(0, _scene(), [_RUBBER, _WOOD], pushed)
    moved = dataclasses.replace(pushed, forces=(dataclasses.replace(
      pushed.forces[0], point=(0.0, 0.0, 0.1)),))
    pl.simulate_jit(pl.init_params(prep2, pushed), prep2, pushed)
    with self.assertRaisesRegex(
        pl.PipelineError, r"placed at \[\('cube', \(0.0, 0.0, 0.1\)\)\]"
        r".* prepared with \[\('cube', None\)\]"):
      pl.simulate_jit(pl.init_params(prep2, moved), prep2, moved)
    params = pl.init_params(prep, cfg)
    # A list leaf: a TracerArrayConversionError deep inside before.
    with self.assertRaisesRegex(pl.PipelineError,
                                'Params.velocity is a list; give an array'):
      pl.simulate(params.replace(velocity=[[0.0, 0.0, 0.0]]), prep, cfg)
    # NumPy's float64 is float32 to JAX without x64 mode: accepted.
    pl.simulate_jit(params.replace(velocity=np.zeros((1, 3))), prep, cfg)
    with self.assertRaisesRegex(ValueError, "float64 needs JAX's x64 mode"):
      prep.astype(jnp.float64)
    with jax.enable_x64(True):
      # Float64: the scene cast, init_params following it; float32 params
      # with it crashed in the solver's loop (dynamic_update_slice).
      p64 = prep.astype(jnp.float64)
      self.assertEqual(p64.x0.dtype, jnp.float64)
      self.assertEqual(p64.driver_object.dtype, prep.driver_object.dtype)
      params64 = pl.init_params(p64, cfg)
      self.assertEqual(params64.velocity.dtype, jnp.float64)
      traj = pl.simulate_jit(params64, p64, cfg)
      self.assertEqual(traj.means.dtype, jnp.float64)
      ref = pl.simulate_jit(params, prep, cfg)
      np.testing.assert_allclose(traj.means, ref.means, atol=1e-5)
      with self.assertRaisesRegex(
          pl.PipelineError, 'Params.log_scale is float32 but the prepared '
          'scene is float64: cast both alike'):
        pl.simulate_jit(params, p64, cfg)

  def test_forward_mode_equals_reverse_mode(self):
    # jax.jvp was refused before (custom VJPs in the solver); now the
    # solver's rules are custom JVPs, transposed for the reverse pass. A
    # neo-Hookean cube (its stress through the SVD) resting on the rigid
    # slab from F = I: <grad, t> against the jvp along t, for the
    # velocities and stiffness scales at once.
    cfg = _config(num_frames=1, substeps_per_frame=40)
    nh = pl.ObjectMaterial('neo_hookean', 3e4, 0.3, 1000.0)
    prep, _ = pl.prepare_scene(0, _scene(), [nh, _WOOD], cfg)
    params = pl.init_params(prep, cfg)
    rng = np.random.default_rng(0)
    w = jnp.asarray(rng.normal(size=prep.rest_means.shape), jnp.float32)

    def f(v, s):
      p = params.replace(velocity=v, log_scale=s)
      return jnp.sum(w * pl.simulate(p, prep, cfg).means[-1])

    args = (params.velocity + 0.3, params.log_scale)
    t = tuple(jnp.asarray(rng.normal(size=a.shape), a.dtype) for a in args)
    _, fwd = jax.jit(lambda a, t: jax.jvp(f, a, t))(args, t)
    g = jax.jit(jax.grad(f, (0, 1)))(*args)
    rev = sum(float(jnp.vdot(a, b)) for a, b in zip(g, t))
    self.assertTrue(np.isfinite(float(fwd)))
    self.assertGreater(abs(rev), 1e-6)
    np.testing.assert_allclose(float(fwd), rev, rtol=1e-4)

  def test_forward_mode_through_the_images(self):
    # The JAX compositor of render='differentiable' works in forward mode
    # (its jvp is the reverse pass's transpose); render='fast', whose
    # compositor has no derivative, says what to use.
    cfg = _config(num_frames=1, substeps_per_frame=20,
                  render='differentiable')
    prep, _ = pl.prepare_scene(0, _scene(), [_RUBBER, _WOOD], cfg)
    params = pl.init_params(prep, cfg)
    w = jnp.asarray(np.random.default_rng(2).normal(
      size=(2, cfg.height, cfg.width, 3)), jnp.float32)

    def f(v, cfg=cfg):
      return jnp.sum(w * pl.simulate(params.replace(velocity=v), prep,
                                     cfg).images)

    v = params.velocity + jnp.asarray([[0.2, -0.1, 0.3]])  # the cube's
    t = jnp.ones_like(v)
    _, fwd = jax.jit(lambda v, t: jax.jvp(f, (v,), (t,)))(v, t)
    rev = float(jnp.vdot(jax.jit(jax.grad(f))(v), t))
    self.assertGreater(abs(rev), 1e-6)
    np.testing.assert_allclose(float(fwd), rev, rtol=1e-3)
    fast = dataclasses.replace(cfg, render='fast')
    with self.assertRaisesRegex(pl.PipelineError, "forward mode .* through "
                                "the images: render='fast' .* has no "
                                "derivative: use render='differentiable'"):
      jax.jvp(lambda v: f(v, fast), (v,), (t,))
    # simulate_jit too (a jvp of the jitted call was JAX's TypeError).
    with self.assertRaisesRegex(pl.PipelineError, "render='fast'"):
      jax.jvp(lambda v: pl.simulate_jit(params.replace(velocity=v), prep,
                                        fast).images.sum(), (v,), (t,))

  def test_params_round_trip_through_a_file(self):
    # orbax refuses the (0, 3) forces of a scene without forces.
    cfg = dataclasses.replace(_config(num_frames=1), use_mpdp=True)
    prep, _ = pl.prepare_scene(0, _scene(), [_RUBBER, _WOOD], cfg)
    params = pl.init_params(prep, cfg)
    self.assertEqual(params.forces.shape, (0, 3))
    params = params.replace(velocity=params.velocity + 1.5, mpdp=jax.tree.map(
      lambda a: a * 2.0, params.mpdp))
    with tempfile.TemporaryDirectory() as d:
      path = os.path.join(d, 'sub', 'params.npz')
      self.assertEqual(ps_io.save_tree(path, params), path)
      back = ps_io.load_tree(path, like=pl.init_params(prep, cfg))
      self.assertIsInstance(back, pl.Params)
      for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(back),
                      strict=True):
        np.testing.assert_array_equal(a, b)
      with self.assertRaisesRegex(ps_io.TreeFileError, r'params.npz: does '
                                  r"not fit the template: not in the "
                                  r"template \[\".mpdp\['Dense_0'\]"):
        ps_io.load_tree(path, like=pl.init_params(prep, dataclasses.replace(
          cfg, use_mpdp=False)))
      with self.assertRaisesRegex(ps_io.TreeFileError,
                                  r'\.velocity is float32 \(1, 3\) in the '
                                  r'file, float32 \(2, 3\) in the template'):
        ps_io.load_tree(path, like=params.replace(
          velocity=jnp.zeros((2, 3))))
      with self.assertRaisesRegex(ps_io.TreeFileError, 'no such file'):
        ps_io.load_tree(os.path.join(d, 'none.npz'), like=params)
      np.save(os.path.join(d, 'one.npy'), np.ones(3))
      with self.assertRaisesRegex(ps_io.TreeFileError, r'single array'):
        ps_io.load_tree(os.path.join(d, 'one.npy'), like=params)
      # NumPy's format has no bfloat16 (it read back as raw bytes, |V2).
      with self.assertRaisesRegex(ps_io.TreeFileError, r"\['a'\] is "
                                  'bfloat16, which .npz does not store'):
        ps_io.save_tree(path, {'a': jnp.ones(2, jnp.bfloat16)})
      self.assertEqual(sorted(os.listdir(os.path.dirname(path))),
                       ['params.npz'])  # no temporary file left

  def test_check_finite_names_bad_inputs_before_the_time_step(self):
    # A NaN initial velocity was blamed on the time step ("raise
    # substeps_per_frame ... lower E").
    cfg = _config(num_frames=1)
    prep, _ = pl.prepare_scene(0, _scene(), [_RUBBER, _WOOD], cfg)
    params = pl.init_params(prep, cfg)
    traj = pl.simulate_jit(params, prep, cfg)
    self.assertIs(pl.check_finite(traj, prep), traj)
    bad = params.replace(velocity=params.velocity.at[0, 2].set(jnp.nan))
    traj = pl.simulate_jit(bad, prep, cfg)
    with self.assertRaisesRegex(
        mpm.SimulationError, r"frame 1 \(objects \['cube'\]\), caused by "
        r"the inputs, not the time step: Params\.velocity is not finite for "
        r"objects \['cube'\]; give every movable object a finite initial "
        r'velocity') as cm:
      pl.check_finite(traj, prep)
    self.assertNotIn('substeps_per_frame', str(cm.exception))
    # Non-finite materials (here from the field).
    field = jnp.ones((prep.num_particles, 3)).at[3, 0].set(jnp.nan)
    traj = pl.simulate_jit(params, prep, cfg, field)
    with self.assertRaisesRegex(mpm.SimulationError,
                                r"inputs, not the time step: material E is "
                                r"not finite for 1 of \d+ drivers \(objects "
                                r"\['cube'\]\); check Params\.log_scale"):
      pl.check_finite(traj, prep)
    # A NaN density leaves every position finite (the particle's NaN mass
    # is masked out of the grid; it stands still): still refused.
    field = jnp.ones((prep.num_particles, 3)).at[3, 2].set(jnp.nan)
    traj = pl.simulate_jit(params, prep, cfg, field)
    self.assertTrue(np.asarray(traj.finite).all())
    with self.assertRaisesRegex(mpm.SimulationError,
                                r"positions stayed finite but the inputs are "
                                r"not: material rho is not finite for 1 of "):
      pl.check_finite(traj, prep)

  def test_velocity_gradient_is_elapsed_time(self):
    scene = _scene(with_table=False)
    cfg = _config(ground='none', num_frames=2, margin=3.0)
    prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER], cfg)
    params = pl.init_params(prep, cfg)

    def loss(p):
      return pl.simulate(p, prep, cfg).means[-1, :, 0].mean()

    g = jax.jit(jax.grad(loss))(params)
    T = cfg.num_frames / cfg.fps
    np.testing.assert_allclose(np.asarray(g.velocity)[0], [T, 0.0, 0.0],
                               rtol=_GRAD_RTOL, atol=1e-5)

  def test_log_E_gradient_matches_finite_differences_x64(self):
    with jax.enable_x64(True):
      # A push on one side of the cube deforms it: E matters.
      scene = _scene(seed=1)
      cfg = _config(num_frames=1, substeps_per_frame=40, forces=(
        pl.ForceSpec('point', 'cube', vector=(0.0, 0.0, 60.0),
                     point=(0.03, 0.0, 0.05), radius=0.025, start=0.0,
                     end=1.0),))
      prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER, _WOOD], cfg)
      prep = prep.astype(jnp.float64)
      params = pl.init_params(prep, cfg)  # float64, as prep

      def loss(p):
        m = pl.simulate(p, prep, cfg).means[-1]
        return jnp.mean((m[:, 2] - jnp.mean(m[:, 2]))**2)

      # The differences from the gradient's program: one compile, not two.
      value_and_grad = jax.jit(jax.value_and_grad(loss))
      g = value_and_grad(params)[1].log_scale[0, 0]
      eps = 1e-4
      e = jnp.zeros_like(params.log_scale).at[0, 0].set(eps)
      fd = (value_and_grad(params.replace(log_scale=params.log_scale + e))[0]
            - value_and_grad(params.replace(
              log_scale=params.log_scale - e))[0]) / (2 * eps)
      self.assertTrue(np.isfinite(float(g)))
      np.testing.assert_allclose(float(g), float(fd), rtol=1e-4, atol=1e-12)

  def test_mpdp_field_keeps_each_objects_volume_weighted_means(self):
    # The object's mass and mean E are the perceived ones however PGAS
    # spaced its particles (the plain mean over particles was off by up to
    # 4.5 % in E on the tabletop); the field prepare_scene keeps for the
    # time step is the one simulate computes.
    scene = _scene(seed=2)
    cfg = _config(use_mpdp=True, sampling='pgas')
    prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER, _WOOD],
                               cfg)
    params = pl.init_params(prep, cfg)
    E, _, rho = (np.asarray(a, np.float64)
                 for a in pl.driver_materials(params, prep, cfg))
    vol = np.asarray(prep.volume, np.float64)
    cube = np.asarray(prep.driver_object) == 0
    self.assertGreater(np.ptp(vol[cube]) / vol[cube].mean(), 0.1)
    self.assertGreater(np.ptp(E[cube]) / E[cube].mean(), 0.05)
    for got, want in ((E, _RUBBER.E), (rho, _RUBBER.rho)):
      np.testing.assert_allclose(
        (got[cube] * vol[cube]).sum() / vol[cube].sum(), want, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(prep.field)[cube, 0] * _RUBBER.E,
                               E[cube], rtol=1e-5)

  def test_same_shapes_compile_once(self):
    # The same scene moved elsewhere: different arrays, identical shapes and
    # static spec, so simulate_jit must not recompile.
    cfg = _config(num_frames=1, substeps_per_frame=40)
    sa = _scene(seed=4)
    g = sa.gaussians
    sb = sa.replace(gaussians=g.replace(
      means=g.means + jnp.asarray([0.3, -0.2, 0.1], g.means.dtype)))
    a, _ = pl.prepare_scene(jax.random.PRNGKey(0), sa, [_RUBBER, _WOOD], cfg)
    b, _ = pl.prepare_scene(jax.random.PRNGKey(0), sb, [_RUBBER, _WOOD], cfg)
    self.assertEqual(a.spec, b.spec)
    self.assertFalse(np.allclose(a.frame.shift, b.frame.shift))
    traces = []

    def sim(params, prepared):
      traces.append(1)  # runs once per trace, i.e. per compilation
      return pl.simulate(params, prepared, cfg)

    fn = jax.jit(sim)
    ta = fn(pl.init_params(a, cfg), a)
    tb = fn(pl.init_params(b, cfg), b)
    self.assertLen(traces, 1)
    # ... and the moved scene moves the same way, displaced.
    np.testing.assert_allclose(tb.means - ta.means, jnp.broadcast_to(
      jnp.asarray([0.3, -0.2, 0.1]), ta.means.shape), atol=2e-4)


class RunTest(absltest.TestCase):

  def test_run_writes_video_frames_and_positions(self):
    scene = _scene()
    cfg = _config(render='fast', num_frames=2, substeps_per_frame=None,
                  initial_velocity=(('cube', (0.2, 0.0, 0.0)),))
    prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER, _WOOD], cfg)
    params = pl.init_params(prep, cfg)
    with tempfile.TemporaryDirectory() as d:
      # An earlier, longer run's .spz frame (and a partial one) in the way.
      os.makedirs(os.path.join(d, 'spz'))
      for name in ('frame_0009.spz', '.frame_0001.1-ab12cd.partial.spz'):
        with open(os.path.join(d, 'spz', name), 'w') as f:
          f.write('earlier run')
      out = pl.run(params, prep, cfg, out_dir=d, ply=True, spz=True)
      frames = sorted(os.listdir(os.path.join(d, 'frames')))
      self.assertLen(frames, cfg.num_frames + 1)
      names = [f'frame_{i:04d}' for i in range(cfg.num_frames + 1)]
      self.assertEqual(sorted(os.listdir(out.files['spz'])),
                       [n + '.spz' for n in names])
      for i, n in enumerate(names):
        back = spz_io.load_spz(os.path.join(d, 'spz', n + '.spz'))
        # The .spz frame is the PLY frame of the same run, quantised: the
        # same bytes as encoding the PLY's Gaussians (at the scene's SH
        # degree), centres within half a step (tests/spz_test.py).
        want = ply_io.load_ply(os.path.join(d, 'ply', n + '.ply'))
        want = want.replace(normals=None).with_sh_degree(0)
        again = spz_io.decode_spz(spz_io.encode_spz(want))
        for name in ('means', 'log_scales', 'quats', 'opacity_logits',
                     'sh'):
          np.testing.assert_array_equal(getattr(back, name),
                                        getattr(again, name), err_msg=name)
        np.testing.assert_allclose(back.means, want.means,
                                   atol=0.5 / 4096 + 1e-6)
        np.testing.assert_allclose(back.means[:300],
                                   out.gaussian_positions[i],
                                   atol=0.5 / 4096 + 1e-6)
      # The free-space estimate of the .spz frames holds them (these
      # uniform Gaussians gzip far better than a trained scene's).
      got = sum(os.path.getsize(os.path.join(d, 'spz', n + '.spz'))
                for n in names)
      need = host.output_sizes(prep, cfg.num_frames, spz=True)['spz']
      self.assertGreaterEqual(need, got)
      self.assertEqual(host.output_sizes(prep, cfg.num_frames)['spz'], 0.0)
      # ... and the PLY frames' estimate is their size (62 float32
      # properties and the header).
      got = sum(os.path.getsize(os.path.join(d, 'ply', n + '.ply'))
                for n in names)
      need = host.output_sizes(prep, cfg.num_frames, ply=True)['ply']
      self.assertGreaterEqual(need, 0.98 * got)
      self.assertLessEqual(need, got)
      self.assertTrue(os.path.getsize(out.files['video']) > 0)
      traj = np.load(out.files['trajectory'])
      np.testing.assert_array_equal(traj['x'], out.gaussian_positions)
      np.testing.assert_array_equal(traj['ids'], np.arange(300))
      np.testing.assert_allclose(traj['t'], np.arange(3) / cfg.fps)
    self.assertEqual(out.gaussian_positions.shape,
                     (cfg.num_frames + 1, 300, 3))
    # The cube moves along +x and stays above the table.
    com = out.gaussian_positions.mean(1)
    self.assertGreater(com[-1, 0], com[0, 0])
    self.assertGreater(out.gaussian_positions[-1, :, 2].min(), -0.01)
    for k in ('compile', 'simulate', 'deform', 'render', 'write', 'total'):
      self.assertIn(k, out.timings)
    parts = [out.timings[f'render.{k}'] for k in ('dispatch', 'wait', 'fetch')]
    self.assertTrue(all(t >= 0 for t in parts))
    self.assertLessEqual(sum(parts), out.timings['render'] + 1e-6)
    # Every frame was rendered with one of the listed capacities.
    caps = out.render_stats['capacities']
    self.assertNotEmpty(caps)
    self.assertTrue(all(isinstance(c, int) and c >= 1024 for c in caps))
    self.assertGreaterEqual(out.render_stats['reruns'], 0)

  def test_frames_reuse_the_first_counted_capacity(self):
    """A scene large enough for its intersections to be counted (here:
    a small min_capacity) is counted once, at frame 0, even when the count
    is below the automatic capacity: the later frames reuse it instead of
    counting again (a wait for the device each) and compiling a renderer
    per count."""
    from physsplat_jax.render import images
    from physsplat_jax.render.config import RenderConfig
    scene = _scene()
    cfg = _config(render='fast', num_frames=3,
                  render_config=RenderConfig(min_capacity=256))
    prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER, _WOOD],
                               cfg)
    count = images.count_intersections
    with mock.patch.object(images, 'count_intersections',
                           side_effect=count) as counted:
      out = pl.run(pl.init_params(prep, cfg), prep, cfg, pipelined=False)
    self.assertEqual(counted.call_count, 1)
    self.assertLen(out.render_stats['capacities'], 1)
    # The count is below the automatic capacity (4 slots per Gaussian).
    self.assertLess(out.render_stats['capacities'][0], 4 * 600)

  def test_pipelined_run_equals_serial_and_overlaps_the_next_frame(self):
    from physsplat_jax.pipeline import host
    scene = _scene()
    cfg = _config(render='fast', num_frames=3,
                  initial_velocity=(('cube', (0.2, 0.0, 0.0)),))
    prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene,
                               [_RUBBER, _WOOD], cfg)
    params = pl.init_params(prep, cfg)
    real = mpm.FrameLoop._dispatch  # pylint: disable=protected-access
    outs = {}
    for pipelined in (False, True):
      events, seen = [], []
      outs[pipelined] = seen

      def dispatch(loop, state, _real=real, _ev=events):
        _ev.append('sim')
        return _real(loop, state)

      def on_frame(f, means, image, _ev=events, _seen=seen):
        _ev.append(f)
        _seen.append((f, means, image))

      threads = {}
      real_maker = host._FrameMaker.dispatch  # pylint: disable=protected-access

      def make(maker, f, t, state, _real=real_maker, _th=threads):
        _th[f] = threading.current_thread() is threading.main_thread()
        return _real(maker, f, t, state)

      with mock.patch.object(mpm.FrameLoop, '_dispatch', dispatch), \
          mock.patch.object(host._FrameMaker, 'dispatch', make):
        pl.run(params, prep, cfg, on_frame=on_frame, pipelined=pipelined)
      # Pipelined, frame 0's programs compile on a second thread while the
      # MPM frame compiles; every later frame is dispatched by the loop.
      self.assertEqual(threads, {0: not pipelined, 1: True, 2: True, 3: True})
      frames_out = [e for e in events if e != 'sim']
      self.assertEqual(frames_out, [0, 1, 2, 3])
      sims_before = [events[:events.index(f)].count('sim') for f in range(4)]
      # Serial: frame f is handed out after f frames were simulated;
      # pipelined: the next frame (and the one after, since frame f is
      # collected an iteration late) is already under way.
      self.assertEqual(sims_before, [min(f + 2 * pipelined, 3)
                                     for f in range(4)])
    for (fa, ma, ia), (fb, mb, ib) in zip(outs[False], outs[True]):
      self.assertEqual(fa, fb)
      np.testing.assert_array_equal(ma, mb)
      np.testing.assert_array_equal(ia, ib)

  def test_pipelined_run_writes_every_frame_before_a_failure(self):
    scene = _scene()
    cfg = _config(render='fast', num_frames=4)
    prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene,
                               [_RUBBER, _WOOD], cfg)
    params = pl.init_params(prep, cfg)
    from physsplat_jax.mpm import solver
    real = solver.check_state

    def check(config, stats, frame, t):
      if frame == 2:
        raise mpm.SimulationError(
          'frame 2: blew up (test). Use a smaller dt (now 1e-3 s; '
          'mpm.choose_substeps picks a stable one), lower E.', 2, 'nan')
      real(config, stats, frame, t)

    class Collect:
      def __init__(self):
        self.frames, self.closed = [], False

      def write(self, frame):
        self.frames.append((frame.index, frame.image))

      def close(self):
        self.closed = True
        return {}

    for pipelined in (False, True):
      w = Collect()
      # The solver's fix (dt, damping) said in the pipeline's settings.
      with mock.patch.object(solver, 'check_state', check), \
          self.assertRaisesRegex(
            mpm.SimulationError,
            r'frame 2: blew up \(test\)\. Give more substeps per frame '
            rf'\(now {prep.spec.substeps_per_frame}: substeps_per_frame=')\
          as cm:
        pl.run(params, prep, cfg, writers=[w], pipelined=pipelined)
      self.assertEqual((cm.exception.frame, cm.exception.reason), (2, 'nan'))
      self.assertTrue(w.closed)
      self.assertEqual([f for f, _ in w.frames], [0, 1])
      self.assertTrue(all(im is not None and np.isfinite(im).all()
                          for _, im in w.frames))

  def test_other_frame_counts_and_seeds_reuse_the_compiled_programs(self):
    # pylint: disable=protected-access
    from physsplat_jax import program_store
    from physsplat_jax.pipeline import host
    scene = _scene()
    programs = (host._deform_jit, host._assemble_jit, host._camera_jit,
                host._initial_state_jit)

    def go(**kw):
      cfg = _config(render='fast', **kw)
      prep, _ = pl.prepare_scene(jax.random.PRNGKey(cfg.seed), scene,
                                 [_RUBBER, _WOOD], cfg)
      out = pl.run(pl.init_params(prep, cfg), prep, cfg)
      sizes = tuple(p._cache_size() for p in programs)
      frames = sum(k[1] == 'mpm_frame' for k in program_store._COMPILED)
      return out, prep.spec.substeps_per_frame, frames, sizes

    a, n_a, frames_a, sizes_a = go(num_frames=2)
    b, n_b, frames_b, sizes_b = go(num_frames=4, seed=3,
                                   orbit_degrees=90.0, camera_path='orbit')
    self.assertEqual(n_a, n_b)  # same bucket of automatic substeps
    self.assertEqual(frames_b, frames_a)  # no new MPM frame program
    self.assertEqual(sizes_b, sizes_a)  # nor deform, assemble, camera, init
    self.assertLen(b.gaussian_positions, 5)
    # A new seed moved the particles, so the run did not replay the first.
    self.assertFalse(np.array_equal(a.particle_positions[0],
                                    b.particle_positions[0]))

  def test_automatic_substeps_are_bucketed(self):
    from physsplat_jax.pipeline import prepare
    ns = np.arange(1, 5000)
    got = np.array([prepare.bucket_substeps(n) for n in ns])
    self.assertTrue(np.all(got >= ns))
    self.assertTrue(np.all(got <= np.ceil(ns * 1.0625)))
    self.assertTrue(np.all(np.diff(got) >= 0))
    np.testing.assert_array_equal(got[:31], ns[:31])  # exact below 32
    values = np.unique(got)
    for lo in (256, 1024, 2048):  # 16 values per octave
      self.assertLen(values[(values >= lo) & (values < 2 * lo)], 16)


class DampingTest(absltest.TestCase):

  def test_a_solid_objects_viscosity_damps_its_deformation(self):
    """A solid given a viscosity is a Kelvin-Voigt solid: the pipeline
    turns the solver's dashpot on, bounds the substep by it, and the cube
    landing on the table wobbles less; its fall is not slowed."""
    import dataclasses
    from physsplat_jax.pipeline import simulation
    scene = _scene()
    cfg = _config(num_frames=6)
    wobble, fall = {}, {}
    for eta in (0.0, 30.0):
      mat = dataclasses.replace(_RUBBER, params=(('viscosity', eta),))
      prep, rep = pl.prepare_scene(jax.random.PRNGKey(0), scene, [mat, _WOOD],
                                   cfg)
      sc = simulation.make_sim_config(prep.spec, cfg)
      self.assertEqual(sc.solid_viscosity, eta > 0)
      traj = pl.simulate_jit(pl.init_params(prep, cfg), prep, cfg)
      x = np.asarray(traj.x, np.float64)
      v = (x[1:] - x[:-1]) * cfg.fps
      # Velocity about the centre of mass's in the last frames (landed):
      # the deformation's.
      wobble[eta] = float(np.mean(np.linalg.norm(
        v[-3:] - v[-3:].mean(1, keepdims=True), axis=-1)))
      fall[eta] = x[1].mean(0) - x[0].mean(0)  # before it lands
    self.assertLess(wobble[30.0], 0.75 * wobble[0.0])  # measured 0.62
    np.testing.assert_allclose(fall[30.0], fall[0.0], atol=1e-5)
    # A viscosity that binds: substeps of at most rho dx^2 / (6 eta).
    mat = dataclasses.replace(_RUBBER, params=(('viscosity', 300.0),))
    prep, rep = pl.prepare_scene(jax.random.PRNGKey(0), scene, [mat, _WOOD],
                                 cfg)
    dx = rep.grid['dx_m']
    bound = 1000.0 * dx * dx / (6 * 300.0)
    self.assertAlmostEqual(rep.time_step['viscous_dt_s'], bound)
    self.assertLessEqual(rep.time_step['dt_s'], bound)
    # Substeps given by hand above the bound: named, with the count.
    with self.assertRaisesRegex(
        pl.PipelineError, r"above the explicit viscous stress's bound .* "
        r'use substeps_per_frame >= \d+'):
      pl.prepare_scene(jax.random.PRNGKey(0), scene, [mat, _WOOD],
                       _config(num_frames=6, substeps_per_frame=64))
    # Automatic substeps over the maximum because of the viscosity: said so
    # (it blamed the wave speed and said to lower E).
    mat = dataclasses.replace(_RUBBER, params=(('viscosity', 3e4),))
    with self.assertRaisesRegex(
        pl.PipelineError, r'the most viscous material needs \d+ substeps '
        r'.*lower the viscosity'):
      pl.prepare_scene(jax.random.PRNGKey(0), scene, [mat, _WOOD], cfg)


  def test_a_maxwell_branch_from_the_objects_params(self):
    """An object given a Maxwell branch (maxwell_E, ...) is viscoelastic:
    the solver carries its F_N, the time step counts the branch's
    stiffness, and the cube runs."""
    import dataclasses
    from physsplat_jax.pipeline import simulation
    scene = _scene()
    cfg = _config(num_frames=2)
    mat = dataclasses.replace(_RUBBER, params=(
      ('maxwell_E', 9e4), ('maxwell_nu', 0.3), ('maxwell_viscosity', 50.0)))
    prep, rep = pl.prepare_scene(jax.random.PRNGKey(0), scene, [mat, _WOOD],
                                 cfg)
    _, plain = pl.prepare_scene(jax.random.PRNGKey(0), scene,
                                [_RUBBER, _WOOD], cfg)
    self.assertTrue(simulation.make_sim_config(prep.spec, cfg).maxwell)
    # P-wave moduli add: E_N = 3 E at one nu doubles the wave speed.
    self.assertAlmostEqual(rep.time_step['max_wave_speed_m_s'],
                           2 * plain.time_step['max_wave_speed_m_s'])
    traj = pl.simulate_jit(pl.init_params(prep, cfg), prep, cfg)
    self.assertTrue(bool(np.all(np.asarray(traj.finite))))


class DomainTest(absltest.TestCase):

  def test_grid_holds_the_ballistic_peak(self):
    # A 1 m/s throw upwards peaks v^2 / 2g = 5.1 cm above the object; the
    # grid (minus its 3 boundary cells) must reach that high.
    from physsplat_jax.pipeline import prepare as prep_lib

    lo, hi = np.zeros(3), np.array([0.04, 0.04, 0.04])
    rlo, rhi = prep_lib.motion_reach(lo, hi, [(0.0, 0.0, 1.0)], 9.8)
    self.assertAlmostEqual(rhi[2] - hi[2], 1.0 / (2 * 9.8), places=9)
    np.testing.assert_array_equal(rlo, lo)
    # Sideways: speed times the flight time back down to the lowest point.
    _, rhi = prep_lib.motion_reach(lo, hi, [(0.5, 0.0, 0.0)], 9.8)
    self.assertAlmostEqual(rhi[0] - hi[0], 0.5 * np.sqrt(2 * 0.04 / 9.8))
    scene = _scene()
    cfg = _config(initial_velocity=(('', (0.0, 0.0, 1.0)),), margin=0.3)
    prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene,
                               [_RUBBER, _WOOD], cfg)
    top = float(np.max(np.asarray(prep.x0)[:, 2]))
    spec = prep.spec
    usable_top = spec.grid_lower[2] + spec.grid_size - 3 * spec.dx
    self.assertGreater(usable_top, top + 1.0 / (2 * 9.8))

  def test_a_sideways_launch_leaves_room_behind(self):
    """A launch that sets the grid's size by its reach still leaves every
    wall 4 cells (a grid under 32 cells: grid_res / 8) from the objects, so
    nothing starts inside the domain box's 3-cell border on the side away
    from the motion (2.7 cells at 32 cells before)."""
    scene = _scene(with_table=False)
    for res in (16, 32):
      cfg = _config(grid_res=res, margin=0.3, max_particles=400,
                    initial_velocity=(('', (2.0, 0.0, 0.0)),))
      prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene, [_RUBBER],
                                 cfg)
      spec, x = prep.spec, np.asarray(prep.x0)
      self.assertGreater(spec.grid_size, 3 * 0.06)  # sized by the reach
      near = min(x[:, 0].min(), x[:, 1].min(),
                 spec.grid_size - x[:, 1].max()) / spec.dx
      self.assertGreaterEqual(near, min(4.0, res / 8) - 1e-3, res)


if __name__ == '__main__':
  absltest.main()
