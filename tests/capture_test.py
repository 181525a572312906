"""A user's own capture: up axis, floaters, ROI/opacity, camera paths."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl.testing import absltest

from physsplat_jax import cameras as cam_lib
from physsplat_jax import physgaussian as pg
from physsplat_jax import pipeline as pl
from physsplat_jax.io import up_axis
from physsplat_jax.physgaussian import camera as pg_camera
from physsplat_jax.pipeline import capture
from physsplat_jax.types import Gaussians, ObjectInfo, Scene
from physsplat_jax.types import make_camera, up_vector


def _gaussians(means, opacity=0.9) -> Gaussians:
  n = len(means)
  logit = math.log(opacity / (1 - opacity))
  return Gaussians(
    means=jnp.asarray(means, jnp.float32),
    log_scales=jnp.full((n, 3), -4.0, jnp.float32),
    quats=jnp.tile(jnp.array([1.0, 0, 0, 0], jnp.float32), (n, 1)),
    opacity_logits=jnp.full((n,), logit, jnp.float32),
    sh=jnp.zeros((n, 1, 3), jnp.float32))


def _ground_and_objects(seed=0, up=(0.0, 0.0, 1.0)) -> np.ndarray:
  """A 2x2 ground (600 centres) and two boxes standing on it (400), turned
  so that the ground's normal is ``up``."""
  rng = np.random.default_rng(seed)
  ground = np.c_[rng.uniform(-1, 1, (600, 2)), rng.normal(0, 1e-3, 600)]
  boxes = np.r_[rng.uniform([-0.6, -0.6, 0], [-0.2, -0.2, 0.5], (200, 3)),
                rng.uniform([0.2, 0.1, 0], [0.5, 0.6, 0.3], (200, 3))]
  x = np.r_[ground, boxes]
  R = pl.frames.up_rotation(np.asarray(up, np.float64)).T  # z -> up
  return x @ R.T


class _Cam:
  """An OpenCV camera at ``eye`` looking at the origin with ``up`` up (the
  rows of ``viewmat`` as in cameras.look_at; NumPy, no compilation)."""

  def __init__(self, eye, up):
    z = -np.asarray(eye, float) / np.linalg.norm(eye)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    self.viewmat = np.eye(4)
    self.viewmat[:3, :3] = [x, np.cross(z, x), z]


def _ring(up, n=5, elevation=20.0):
  u, e1, e2 = cam_lib._orbit_basis(up)  # noqa: SLF001
  el = math.radians(elevation)
  return [_Cam(math.cos(el) * (math.cos(a) * e1 + math.sin(a) * e2)
               + math.sin(el) * u, u)
          for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


class UpAxisTest(absltest.TestCase):

  def test_from_cameras_snapped_and_general(self):
    g = up_axis.guess_up(np.zeros((10, 3)), cameras=_ring((0, -1, 0)))
    self.assertEqual((g.axis, g.source), ('-y', 'cameras'))
    tilt = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
    cams = _ring(tilt)
    g = up_axis.guess_up(np.zeros((10, 3)), cameras=cams)
    self.assertEqual(g.source, 'cameras')
    np.testing.assert_allclose(up_vector(g.axis), tilt, atol=1e-3)
    # The user's axis wins; cameras that disagree give no guess.
    self.assertEqual(up_axis.guess_up(np.zeros((1, 3)), cameras=cams,
                                      given='x').axis, 'x')
    cams = [_Cam((0, 1, 0.1), u) for u in ((0, 0, 1), (0, 0, -1))]
    self.assertIsNone(up_axis.up_from_cameras(cams)[0])

  def test_from_dominant_plane_both_signs_and_tilted(self):
    for up, want in (((0, 0, 1), 'z'), ((0, 0, -1), '-z'),
                     ((0, -1, 0), '-y')):
      g = up_axis.guess_up(_ground_and_objects(up=up))
      self.assertEqual((g.axis, g.source), (want, 'plane'), msg=str(up))
    tilt = np.array([0.2, -0.9, 0.3]) / np.linalg.norm([0.2, -0.9, 0.3])
    g = up_axis.guess_up(_ground_and_objects(up=tilt))
    self.assertEqual(g.source, 'plane')
    np.testing.assert_allclose(up_vector(g.axis), tilt, atol=5e-3)
    # A cloud without a plane keeps z, and says so.
    cloud = np.random.default_rng(1).uniform(-1, 1, (1000, 3))
    g = up_axis.guess_up(cloud)
    self.assertEqual((g.axis, g.source), ('z', 'default'))
    self.assertIn('--up_axis', g.detail)


def _scene(means, ids, opacity=0.9, fixed=()) -> Scene:
  n = int(max(ids)) + 1
  return Scene(gaussians=_gaussians(means, opacity),
               object_ids=jnp.asarray(ids, jnp.int32),
               objects=tuple(ObjectInfo(f'o{i}', fixed=i in fixed)
                             for i in range(n)),
               up_axis='z', meters_per_unit=0.5, name='t')


class FilterTest(absltest.TestCase):

  def test_floaters_leave_the_grid_sizing(self):
    rng = np.random.default_rng(0)
    cube = rng.uniform(0, 0.2, (500, 3))
    far = np.array([[3.0, 0, 0], [0, -2.5, 0.1], [0, 0.1, 4.0]])
    sc = _scene(np.r_[cube, far], np.zeros(503, int))
    cfg = pl.PrepareConfig()
    out, rep = capture.filter_scene(sc, cfg)
    self.assertEqual(rep['floaters'], 3)
    ids = np.asarray(out.object_ids)
    np.testing.assert_array_equal(ids[500:], -1)
    np.testing.assert_array_equal(ids[:500], 0)
    self.assertLess(rep['extent_m'], 0.11)  # 0.2 units x 0.5 m
    self.assertAlmostEqual(rep['extent_before_floaters_m'], 2.0, places=5)
    # The grid is sized on the movable Gaussians (prepare.sim_frame_stage):
    # now the cube alone.
    np.testing.assert_allclose(np.ptp(np.asarray(out.gaussians.means)[
      ids >= 0], axis=0), np.ptp(cube, axis=0), rtol=1e-6)
    unfiltered = capture.filter_scene(
      sc, pl.PrepareConfig(floater_factor=0))[0]
    self.assertIs(unfiltered, sc)

  def test_roi_and_min_opacity_keep_gaussians_static(self):
    x = np.random.default_rng(1).uniform(0, 1, (400, 3))
    ids = np.r_[np.zeros(300, int), np.ones(100, int)]
    op = np.where(np.arange(400) % 4 == 0, 0.05, 0.9)
    sc = _scene(x, ids, fixed=(1,))
    sc = sc.replace(gaussians=sc.gaussians.replace(opacity_logits=jnp.asarray(
      np.log(op / (1 - op)), jnp.float32)))
    cfg = pl.PrepareConfig(roi=(0, 0.5, 0, 1, 0, 1), min_opacity=0.1,
                           floater_factor=0)
    out, rep = capture.filter_scene(sc, cfg)
    got = np.asarray(out.object_ids)
    movable = ids == 0
    keep = movable & (x[:, 0] <= 0.5) & (op >= 0.1)
    np.testing.assert_array_equal(got[movable], np.where(keep, 0, -1)[movable])
    np.testing.assert_array_equal(got[~movable], 1)  # fixed: untouched
    self.assertEqual(rep['outside_roi'], int(np.sum(movable & (x[:, 0] > .5))))
    self.assertEqual(rep['below_min_opacity'],
                     int(np.sum(movable & (x[:, 0] <= .5) & (op < .1))))
    # Everything still renders: the Gaussians are the same.
    self.assertIs(out.gaussians, sc.gaussians)
    with self.assertRaisesRegex(pl.PipelineError, "'o0'.*widen roi"):
      capture.filter_scene(sc, pl.PrepareConfig(roi=(2, 3, 0, 1, 0, 1)))
    with self.assertRaisesRegex(pl.PipelineError, 'roi=.*six finite'):
      pl.PipelineConfig(roi=(0, 1, 0, 1, 1, 0))
    with self.assertRaisesRegex(pl.PipelineError, 'min_opacity=1.5'):
      pl.PipelineConfig(min_opacity=1.5)
    c = pl.config_from_dict(dict(roi=[0, 1, 0, 1, 0, 1],
                                 camera_path='orbit'))
    self.assertEqual((c.prepare.roi, c.prepare.camera_path),
                     ((0.0, 1.0, 0.0, 1.0, 0.0, 1.0), 'orbit'))


class GroundHeightTest(absltest.TestCase):

  @pytest.mark.slow  # ~4-9 s: compiles the frame stage's eager ops
  def test_ground_height_sets_the_support_plane(self):
    from physsplat_jax.pipeline import prepare  # noqa: PLC0415
    x = np.random.default_rng(2).uniform(0, 0.2, (64, 3))
    sc = _scene(x, np.zeros(64, int))  # 0.5 m per unit, z up
    found = prepare.sim_frame_stage(sc, [0], [], pl.PrepareConfig())
    fr = prepare.sim_frame_stage(sc, [0], [],
                                 pl.PrepareConfig(ground_height=-0.5))
    # Found: the lowest point; given: -0.5 units = -0.25 m, 0.25 m lower
    # (in the shifted simulation frame).
    shift = float(fr.frame.shift[2])
    self.assertAlmostEqual(fr.colliders.ground_z - shift, -0.25, places=5)
    self.assertAlmostEqual(
      found.colliders.ground_z - float(found.frame.shift[2]),
      0.5 * x[:, 2].min(), places=5)
    self.assertIn('ground_height=-0.5', fr.colliders.notes[0])
    with self.assertRaisesRegex(pl.PipelineError, 'ground_height.*above'):
      prepare.sim_frame_stage(sc, [0], [], pl.PrepareConfig(ground_height=1))


class CameraPathTest(absltest.TestCase):

  def test_orbit_turns_about_up_and_compiles_once(self):
    centre = np.array([0.2, -0.1, 0.5])
    vm = _Cam((3.0, 1.0, 1.0), (0, 0, 1)).viewmat
    vm[:3, 3] = -vm[:3, :3] @ (centre + (3.0, 1.0, 1.0))  # looks at centre
    cam = make_camera(jnp.asarray(vm, jnp.float32), 50.0, 50.0, 64, 48)
    orbit = capture.CameraOrbit(
      center=jnp.asarray(centre, jnp.float32),
      axis=jnp.array([0.0, 0.0, 1.0]), degrees=jnp.asarray(90.0))
    at = jax.jit(capture.frame_camera, static_argnames='num_frames')
    p0 = np.asarray(cam.position) - np.asarray(centre)
    at(cam, orbit, 1, num_frames=10)
    # Entries after the first call (other tests in this process may have
    # traced frame_camera already): later frame indices add none.
    compiled = at._cache_size()  # noqa: SLF001
    for f in (0, 5, 10):
      c = at(cam, orbit, f, num_frames=10)
      p = np.asarray(c.position) - np.asarray(centre)
      a = math.radians(9.0 * f)
      want = np.array([math.cos(a) * p0[0] - math.sin(a) * p0[1],
                       math.sin(a) * p0[0] + math.cos(a) * p0[1], p0[2]])
      np.testing.assert_allclose(p, want, atol=1e-4)
      # The centre is on the axis: the camera still looks at it.
      x = np.asarray(c.viewmat)[:3] @ np.r_[centre, 1.0]
      np.testing.assert_allclose(x[:2], 0.0, atol=1e-4)
    self.assertEqual(at._cache_size(), compiled)  # noqa: SLF001

  def test_physgaussian_move_camera_positions(self):
    raw = dict(material='jelly', default_camera_index=-1,
               init_azimuthm=30.0, init_elevation=10.0, init_radius=2.0,
               move_camera=True, delta_a=2.0, delta_e=0.5, delta_r=-0.01,
               show_hint=True, mpm_space_viewpoint_center=[1, 1, 1],
               mpm_space_vertical_upward_axis=[0, 0, 1])
    with self.assertNoLogs('absl', level='WARNING'):
      cfg = pg.parse_config(raw, 'test.json')
    self.assertTrue(cfg.camera.show_hint)
    # Scene = normalised domain shifted and halved: R = I, c = 0, s = 2.
    centre, axes = pg_camera.viewpoint(cfg, (np.eye(3), np.zeros(3), 2.0))
    np.testing.assert_allclose(centre, 0.0)
    h1 = np.array([1, 1, 0]) / math.sqrt(2)
    np.testing.assert_allclose(axes, np.c_[h1, [h1[1], -h1[0], 0], [0, 0, 1]],
                               atol=1e-12)
    base = make_camera(jnp.eye(4), 40.0, 40.0, 32, 32)
    for f in (0, 7):
      a, e, r = 30 + 2 * f, 10 + 0.5 * f, 2.0 - 0.01 * f
      c = pg_camera.frame_camera(cfg, base, centre, axes, f)
      ar, er = math.radians(a), math.radians(e)
      want = r * (math.cos(er) * (math.cos(ar) * axes[:, 0]
                                  + math.sin(ar) * axes[:, 1])
                  + math.sin(er) * axes[:, 2])
      vm = np.asarray(c.viewmat, np.float64)
      np.testing.assert_allclose(-vm[:3, :3].T @ vm[:3, 3], want, atol=1e-5)
      # Looks at the centre (on the optical axis), the vertical up in the
      # image (-y).
      np.testing.assert_allclose(vm[:2, 3], 0.0, atol=1e-5)
      self.assertLess(vm[1, 2], 0)
      hint = pg_camera.camera_hint(c, centre, axes)
      np.testing.assert_allclose(
        [hint['init_azimuthm'], hint['init_elevation'], hint['init_radius']],
        [a, e, r], atol=1e-3)
    still = dict(raw, move_camera=False)
    c = pg_camera.frame_camera(pg.parse_config(still, 's.json'), base,
                               centre, axes, 7)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(c.position)), 2.0,
                               atol=1e-5)
    bad = pg.parse_config(dict(raw, delta_r=-1.0), 'b.json')
    with self.assertRaisesRegex(pg.ConfigError, 'radius.*frame 2'):
      pg_camera.frame_camera(bad, base, centre, axes, 2)


if __name__ == '__main__':
  absltest.main()
