"""Tests for camera utilities and camera-file readers (OpenCV conventions)."""

import json
import math
import pathlib
import tempfile
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax import cameras
from physsplat_jax.io import cameras as cam_io
from physsplat_jax.types import make_camera

# Pixel agreement of float32 projections of O(1) scenes.
PIXEL_TOL = 1e-3
ORTHO_TOL = 1e-5


def _rot(axis, deg):
  a = np.deg2rad(deg)
  c, s = np.cos(a), np.sin(a)
  i, j = [(1, 2), (2, 0), (0, 1)][axis]
  R = np.eye(3)
  R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
  return R


# A known camera: OpenCV camera-to-world rotation (columns = camera axes in
# world coordinates), centre, intrinsics.
C2W_R = _rot(2, 30.0) @ _rot(0, -110.0) @ _rot(1, 10.0)
CENTER = np.array([0.3, -2.5, 1.2])
W, H = 64, 48
FX, FY = 70.0, 72.0


def _expected_pixel(X, fx, fy, cx, cy):
  """Brute-force pinhole projection in float64 with the known camera."""
  pc = C2W_R.T @ (X - CENTER)
  return np.array([fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy]), pc[2]


def _points():
  # Points in front of the known camera: centre + depth * forward + offsets.
  fwd, right, down = C2W_R[:, 2], C2W_R[:, 0], C2W_R[:, 1]
  return [
    CENTER + 3.0 * fwd,
    CENTER + 2.0 * fwd + 0.4 * right - 0.3 * down,
    CENTER + 5.0 * fwd - 1.0 * right + 0.7 * down,
  ]


def _opengl_c2w():
  c2w = np.eye(4)
  c2w[:3, :3] = C2W_R * np.array([1.0, -1.0, -1.0])
  c2w[:3, 3] = CENTER
  return c2w



def _cloud(n):
  """``n`` small Gaussians in a unit box around the origin."""
  from physsplat_jax.types import Gaussians
  rng = np.random.default_rng(0)
  return Gaussians(
    means=jnp.asarray(rng.uniform(-0.5, 0.5, (n, 3)), jnp.float32),
    log_scales=jnp.full((n, 3), -3.0), quats=jnp.tile(
      jnp.array([1.0, 0, 0, 0]), (n, 1)),
    opacity_logits=jnp.full((n,), 2.0), sh=jnp.zeros((n, 1, 3)))

class CameraUtilTest(parameterized.TestCase):

  def test_look_at_target_at_centre_up_is_minus_y(self):
    eye = np.array([3.0, 2.0, 1.0])
    target = np.array([0.0, 0.5, 0.5])
    up = np.array([0.0, 0.0, 1.0])
    vm = np.asarray(cameras.look_at(eye, target, up), np.float64)
    R = vm[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=ORTHO_TOL)
    self.assertAlmostEqual(np.linalg.det(R), 1.0, places=5)
    cam = make_camera(vm, 50.0, 50.0, W, H)
    np.testing.assert_allclose(cam.position, eye, atol=1e-5)
    uv, z = cam.project(jnp.asarray(np.stack([target, target + 0.2 * up])))
    uv = np.asarray(uv)
    np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=PIXEL_TOL)
    self.assertGreater(float(z[0]), 0.0)
    # Up in the world is up in the image: smaller row, same column.
    self.assertLess(uv[1, 1], H / 2 - 1.0)
    self.assertAlmostEqual(uv[1, 0], W / 2, delta=PIXEL_TOL)
    # A point to the camera's right (forward x up) has a larger column.
    right = np.cross(target - eye, up)
    uv, _ = cam.project(jnp.asarray(target + 0.2 * right / np.linalg.norm(
      right)))
    self.assertGreater(float(uv[0]), W / 2 + 1.0)

  def test_look_at_vertical_view_and_bad_input(self):
    vm = np.asarray(cameras.look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0],
                                    [0.0, 0.0, 1.0]))
    self.assertTrue(np.all(np.isfinite(vm)))
    np.testing.assert_allclose(vm[:3, :3] @ vm[:3, :3].T, np.eye(3),
                               atol=ORTHO_TOL)
    np.testing.assert_allclose(vm[2, :3], [0.0, 0.0, -1.0], atol=ORTHO_TOL)
    with self.assertRaisesRegex(ValueError, 'same point'):
      cameras.look_at([1.0, 1.0, 1.0], [1.0, 1.0, 1.0])
    with self.assertRaisesRegex(ValueError, r'shape \(2,\)'):
      cameras.look_at([1.0, 1.0], [0.0, 0.0, 0.0])

  def test_look_at_is_differentiable_and_jittable(self):
    with jax.enable_x64(True):
      target = jnp.array([0.1, 0.2, 0.3])
      point = jnp.array([0.5, -0.2, 0.6])

      def pixel(eye):
        vm = cameras.look_at(eye, target, jnp.array([0.0, 0.0, 1.0]))
        pc = vm[:3, :3] @ point + vm[:3, 3]
        return 100.0 * pc[:2] / pc[2]

      eye = jnp.array([2.0, 1.0, 1.5])
      jac = jax.jit(jax.jacobian(pixel))(eye)
      eps = 1e-6
      fd = np.stack([
        (pixel(eye + eps * e) - pixel(eye - eps * e)) / (2 * eps)
        for e in np.eye(3)
      ], axis=-1)
      np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-6)

  def test_opengl_conversions_invert(self):
    vm = cameras.opengl_c2w_to_viewmat(_opengl_c2w())
    np.testing.assert_allclose(
      np.asarray(cameras.viewmat_to_opengl_c2w(vm)), _opengl_c2w(), atol=1e-5
    )
    np.testing.assert_allclose(
      np.asarray(vm)[:3, :3], C2W_R.T, atol=1e-6
    )
    self.assertAlmostEqual(
      float(cameras.fov_from_focal(cameras.focal_from_fov(40.0, 300), 300)),
      40.0, places=4)
    self.assertAlmostEqual(float(cameras.focal_from_fov(90.0, 200)), 100.0,
                           places=4)

  @parameterized.named_parameters(('_zup', (0.0, 0.0, 1.0)),
                                  ('_yup', (0.0, 1.0, 0.0)),
                                  ('_minus_yup', (0.0, -1.0, 0.0)))
  def test_orbit_cameras(self, up):
    center = np.array([0.5, -0.2, 0.1])
    up = np.asarray(up)
    cams = cameras.orbit_cameras(center, 2.0, 30.0, 8, up=up, fov_deg=60.0,
                                 width=W, height=H, start_azimuth_deg=10.0)
    self.assertLen(cams, 8)
    self.assertAlmostEqual(float(cams[0].fy), H / 2 / math.tan(math.pi / 6),
                           places=3)
    positions = np.stack([np.asarray(c.position, np.float64) for c in cams])
    rel = positions - center
    np.testing.assert_allclose(np.linalg.norm(rel, axis=-1), 2.0, atol=1e-5)
    np.testing.assert_allclose(rel @ up / 2.0, np.sin(np.deg2rad(30.0)),
                               atol=1e-5)
    horiz = rel - np.outer(rel @ up, up)
    cosang = np.sum(horiz * np.roll(horiz, -1, 0), -1) / np.sum(
      horiz * horiz, -1)
    np.testing.assert_allclose(cosang, np.cos(np.deg2rad(45.0)), atol=1e-5)
    # Counter-clockwise about up.
    self.assertGreater(float(np.cross(horiz[0], horiz[1]) @ up), 0.0)
    for c in cams:
      uv, z = c.project(jnp.asarray(np.stack([center, center + 0.3 * up])))
      uv = np.asarray(uv)
      np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=PIXEL_TOL)
      self.assertLess(uv[1, 1], H / 2)

  def test_fit_camera_frames_the_box(self):
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([3.0, 1.0, 2.5])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0])
                        for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    for az, el in ((0.0, 20.0), (130.0, -40.0), (250.0, 85.0)):
      cam = cameras.fit_camera(lo, hi, up=(0, 0, 1), width=80, height=40,
                               fov_deg=45.0, azimuth=az, elevation=el,
                               padding=1.0)
      uv, z = cam.project(jnp.asarray(corners))
      uv, z = np.asarray(uv), np.asarray(z)
      self.assertTrue(np.all(z > cam.near) and np.all(z < cam.far))
      self.assertTrue(np.all((uv >= 0) & (uv <= [80, 40])), f'{az},{el}')
      centre_uv, _ = cam.project(jnp.asarray(0.5 * (lo + hi)))
      np.testing.assert_allclose(centre_uv, [40, 20], atol=PIXEL_TOL)
      # Tight: the bounding sphere's silhouette touches the narrow side.
      r = 0.5 * np.linalg.norm(hi - lo)
      d = np.linalg.norm(np.asarray(cam.position) - 0.5 * (lo + hi))
      half = math.atan(20.0 / float(cam.fy))
      self.assertAlmostEqual(r / d, math.sin(half), places=4)
    with self.assertRaisesRegex(ValueError, 'below bounds_min'):
      cameras.fit_camera(hi, lo)
    with self.assertRaisesRegex(ValueError, 'fov_deg'):
      cameras.fit_camera(lo, hi, fov_deg=180.0)

  def test_framing_box_of_degenerate_scenes(self):
    # One Gaussian: render's --camera_index=-1 failed in look_at ("eye and
    # target are the same point"); centres near 1e29 failed as "viewmat is
    # not a rigid transform", blaming the camera.
    rng = np.random.default_rng(0)
    m = rng.normal(size=(500, 3))
    lo, hi = cameras.framing_box(m)
    np.testing.assert_allclose(lo, np.percentile(m, 1.0, axis=0))
    np.testing.assert_allclose(hi, np.percentile(m, 99.0, axis=0))
    lo, hi = cameras.framing_box(np.full((3, 3), 2.0))
    np.testing.assert_array_equal([lo, hi], [[1.5] * 3, [2.5] * 3])
    from physsplat_jax.render import views
    from physsplat_jax.types import Gaussians
    one = Gaussians(means=jnp.ones((1, 3)), log_scales=jnp.zeros((1, 3)),
                    quats=jnp.array([[1.0, 0, 0, 0]]),
                    opacity_logits=jnp.ones(1), sh=jnp.zeros((1, 1, 3)))
    cam = views.fit_scene_camera(one, width=32, height=24)
    uv, _ = cam.project(jnp.ones(3))
    np.testing.assert_allclose(uv, [16, 12], atol=PIXEL_TOL)
    m[:10, 0] = 1e29
    m[-10:, 0] = -1e29
    with self.assertRaisesRegex(cameras.CameraError, r'span \(-1e\+29, .*'
                                r'beyond 1e\+12 scene units'):
      cameras.framing_box(m)

  def test_label_and_depth_range_do_not_recompile_the_renderer(self):
    from physsplat_jax.render import images as host_render
    from physsplat_jax.render import raster
    g = _cloud(64)
    vm = cameras.look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0])
    cfg = raster.RenderConfig(capacity=4096)
    raster._render_jit.clear_cache()  # pylint: disable=protected-access
    images = []
    for near, far, name in ((0.01, 1e10, 'a.png'), (0.5, 100.0, 'b.png'),
                            (2.9, 100.0, '')):
      cam = make_camera(vm, 40.0, 40.0, 32, 24, near=near, far=far,
                        name=name)
      images.append(host_render.render_image(g, cam, config=cfg).image)
    # pylint: disable-next=protected-access
    self.assertEqual(raster._render_jit._cache_size(), 1)
    # The depth range still clips: a near plane past the centre (depth 3)
    # drops the nearer half of the cloud.
    np.testing.assert_array_equal(images[0], images[1])
    self.assertGreater(np.abs(images[0] - images[2]).max(), 0.05)

  def test_look_at_refuses_non_finite_input(self):
    for kwargs, name in (
        (dict(eye=[np.nan, 0.0, 0.0], target=[0.0, 0.0, 1.0]), 'eye'),
        (dict(eye=[0.0, 0.0, 0.0], target=[np.inf, 0.0, 1.0]), 'target'),
        (dict(eye=[0.0, -2.0, 0.0], target=[0.0, 0.0, 0.0],
              up=[0.0, np.nan, 1.0]), 'up')):
      with self.assertRaisesRegex(cameras.CameraError,
                                  f'look_at: {name} .*non-finite'):
        cameras.look_at(**kwargs)
    with self.assertRaisesRegex(cameras.CameraError, 'eye is not numeric'):
      cameras.look_at(['a', 'b', 'c'], [0.0, 0.0, 0.0])
    # Traced inputs are not checked (no host sync), and still compile.
    vm = jax.jit(cameras.look_at)(jnp.array([0.0, -2.0, 0.5]),
                                  jnp.zeros(3), jnp.array([0.0, 0.0, 1.0]))
    self.assertTrue(np.all(np.isfinite(np.asarray(vm))))

  def test_scene_camera_refuses_bad_size_and_index(self):
    from physsplat_jax.types import Scene
    g = _cloud(20)
    cam = make_camera(cameras.look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0]),
                      40.0, 40.0, 32, 24)
    sc = Scene(gaussians=g, object_ids=jnp.zeros(g.num, jnp.int32),
               cameras=(cam,), name='s')
    got = cameras.scene_camera(sc, 64, 48)
    self.assertEqual((got.width, got.height), (64, 48))
    np.testing.assert_allclose(got.fx, 80.0)
    for w, h, word in ((64, 0, 'height=0'), (0, 48, 'width=0'),
                       (64.5, 48, 'width=64.5'), (-3, 48, 'width=-3')):
      with self.assertRaisesRegex(cameras.CameraError, word):
        cameras.scene_camera(sc, w, h)
    with self.assertRaisesRegex(cameras.CameraError,
                                r'camera_index=-2.*-1 for a fitted'):
      cameras.scene_camera(sc, 64, 48, index=-2)
    with self.assertRaisesRegex(cameras.CameraError, 'camera_index=1.5'):
      cameras.scene_camera(sc, 64, 48, index=1.5)
    with self.assertRaisesRegex(cameras.CameraError, 'has 1 cameras'):
      cameras.scene_camera(sc, 64, 48, index=1)
    fitted = cameras.scene_camera(sc, 64, 48, index=-1)
    self.assertEqual((fitted.width, fitted.height), (64, 48))


class CameraFileTest(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    self.tmp = pathlib.Path(tmp.name)

  def _json(self, name, data):
    p = self.tmp / name
    p.write_text(json.dumps(data))
    return p

  def _check(self, cam, fx, fy, cx, cy):
    self.assertEqual((cam.width, cam.height), (W, H))
    for X in _points():
      expected, depth = _expected_pixel(X, fx, fy, cx, cy)
      uv, z = cam.project(jnp.asarray(X, jnp.float32))
      np.testing.assert_allclose(np.asarray(uv), expected, atol=PIXEL_TOL)
      self.assertAlmostEqual(float(z), depth, places=4)

  def test_inria_cameras_json(self):
    entry = {
      'id': 0, 'img_name': 'frame_000', 'width': W, 'height': H,
      'position': CENTER.tolist(), 'rotation': C2W_R.tolist(),
      'fy': FY, 'fx': FX,
    }
    path = self._json('cameras.json', [entry, dict(entry, img_name='b')])
    cams = cam_io.load_cameras(path)
    self.assertLen(cams, 2)
    self.assertEqual(cams[0].name, 'frame_000')
    self._check(cams[0], FX, FY, W / 2, H / 2)
    # Writer round trip.
    cam_io.save_inria_cameras(self.tmp / 'out.json', cams)
    back = cam_io.load_inria_cameras(self.tmp / 'out.json')
    self._check(back[1], FX, FY, W / 2, H / 2)
    self.assertEqual(back[1].name, 'b')

  def test_nerf_synthetic_transforms(self):
    angle_x = 2.0 * math.atan(W / (2.0 * FX))
    frames = [{'file_path': './train/r_0', 'rotation': 0.0,
               'transform_matrix': _opengl_c2w().tolist()}]
    path = self._json('transforms_train.json',
                      {'camera_angle_x': angle_x, 'frames': frames})
    # Size from the image next to the file (file_path has no extension).
    import imageio.v3 as iio

    (self.tmp / 'train').mkdir()
    iio.imwrite(self.tmp / 'train' / 'r_0.png', np.zeros((H, W, 3), np.uint8))
    cams = cam_io.load_cameras(path)
    self.assertEqual(cams[0].name, './train/r_0')
    self._check(cams[0], FX, FX, W / 2, H / 2)
    # Or from arguments when there is no image.
    (self.tmp / 'train' / 'r_0.png').unlink()
    self._check(cam_io.load_cameras(path, width=W, height=H)[0], FX, FX,
                W / 2, H / 2)
    with self.assertRaisesRegex(cam_io.CameraFileError, 'no image size'):
      cam_io.load_cameras(path)

  def test_nerfstudio_transforms_with_applied_transform(self):
    # nerfstudio's COLMAP import: rows (x, z, -y) of the original world.
    A = np.eye(4)[:3]
    A = A[[0, 2, 1]]
    A[2] *= -1
    A4 = np.eye(4)
    A4[:3] = A
    cx, cy = 30.5, 25.25  # off-centre principal point
    frame = {'file_path': 'images/a.png',
             'transform_matrix': (A4 @ _opengl_c2w()).tolist()}
    other = dict(frame, fl_x=2 * FX, file_path='images/b.png')
    data = {'camera_model': 'OPENCV', 'fl_x': FX, 'fl_y': FY, 'cx': cx,
            'cy': cy, 'w': W, 'h': H, 'k1': 0.0, 'p1': 0.0,
            'applied_transform': A.tolist(), 'frames': [frame, other]}
    path = self._json('transforms.json', data)
    cams = cam_io.load_cameras(path, undo_applied_transform=True)
    self._check(cams[0], FX, FY, cx, cy)
    self._check(cams[1], 2 * FX, FY, cx, cy)  # per-frame intrinsics win
    # Without undoing, the camera lives in nerfstudio's rotated world.
    cam = cam_io.load_cameras(path)[0]
    for X in _points():
      expected, _ = _expected_pixel(X, FX, FY, cx, cy)
      uv, _ = cam.project(jnp.asarray(A @ np.r_[X, 1.0], jnp.float32))
      np.testing.assert_allclose(np.asarray(uv), expected, atol=PIXEL_TOL)

  def test_missing_fields_and_bad_files(self):
    entry = {'id': 0, 'img_name': 'a', 'width': W, 'height': H,
             'position': [0, 0, 0], 'rotation': np.eye(3).tolist(), 'fy': 1.0}
    with self.assertRaisesRegex(cam_io.CameraFileError,
                                r"camera 0 \(a\) is missing \['fx'\]"):
      cam_io.load_cameras(self._json('c.json', [entry]))
    with self.assertRaisesRegex(cam_io.CameraFileError,
                                r'rotation has shape \(2, 2\)'):
      cam_io.load_cameras(self._json(
        'c.json', [dict(entry, fx=1.0, rotation=[[1, 0], [0, 1]])]))
    with self.assertRaisesRegex(cam_io.CameraFileError, "'width' must be"):
      cam_io.load_cameras(self._json('c.json', [dict(entry, fx=1.0,
                                                     width=-3)]))
    frame = {'file_path': 'x', 'transform_matrix': np.eye(4).tolist()}
    with self.assertRaisesRegex(cam_io.CameraFileError,
                                r'frame 0 has no "transform_matrix"'):
      cam_io.load_cameras(self._json(
        't.json', {'camera_angle_x': 0.7, 'frames': [{'file_path': 'x'}]}))
    with self.assertRaisesRegex(cam_io.CameraFileError, 'no focal length'):
      cam_io.load_cameras(self._json('t.json', {'w': 4, 'h': 4,
                                                'frames': [frame]}))
    with self.assertRaisesRegex(cam_io.CameraFileError, 'OPENCV_FISHEYE'):
      cam_io.load_cameras(self._json('t.json', {
        'camera_model': 'OPENCV_FISHEYE', 'fl_x': 1, 'w': 4, 'h': 4,
        'frames': [frame]}))
    with self.assertRaisesRegex(cam_io.CameraFileError, 'no "applied_trans'):
      cam_io.load_cameras(
        self._json('t.json', {'fl_x': 1, 'w': 4, 'h': 4, 'frames': [frame]}),
        undo_applied_transform=True)
    with self.assertRaisesRegex(cam_io.CameraFileError, 'not valid JSON'):
      p = self.tmp / 'bad.json'
      p.write_text('{"frames": [')
      cam_io.load_cameras(p)
    with self.assertRaisesRegex(cam_io.CameraFileError, 'unknown camera file'):
      cam_io.load_cameras(self._json('u.json', {'cameras': []}))
    with self.assertRaisesRegex(cam_io.CameraFileError, '"frames" is empty'):
      cam_io.load_cameras(self._json('e.json', {'fl_x': 1, 'w': 4, 'h': 4,
                                                'frames': []}))
    with warnings.catch_warnings(record=True) as caught:
      warnings.simplefilter('always')
      cam_io.load_cameras(self._json('k.json', {
        'fl_x': 1, 'w': 4, 'h': 4, 'k1': 0.1, 'frames': [frame]}))
    self.assertTrue(any('distortion' in str(w.message) for w in caught))


  def _frame_file(self, name='t.json', matrix=None, **top):
    m = np.eye(4) if matrix is None else matrix
    data = {'camera_angle_x': 0.7, 'w': 64, 'h': 48, **top,
            'frames': [{'file_path': 'x', 'transform_matrix': m.tolist()}]}
    return self._json(name, data)

  @parameterized.parameters(40.0, 3.14159, 4.0, -1.0, 0.0)
  def test_camera_angle_out_of_range(self, angle):
    with self.assertRaisesRegex(
        cam_io.CameraFileError,
        r"t\.json: frame 0 field 'camera_angle_x'=.*must be in \(0, pi\) "
        r'radians \(degrees given\?\)'):
      cam_io.load_cameras(self._frame_file(camera_angle_x=angle))
    with self.assertRaisesRegex(cam_io.CameraFileError,
                                "field 'camera_angle_y'=.*in \\(0, pi\\)"):
      cam_io.load_cameras(self._frame_file(camera_angle_y=angle))

  def test_transform_matrix_last_row(self):
    m = np.eye(4)
    m[3] = [1, 2, 3, 1]
    with self.assertRaisesRegex(
        cam_io.CameraFileError,
        r'frame 0 transform_matrix last row \[1, 2, 3, 1\] must be '
        r'\[0, 0, 0, 1\] \(transposed\?\)'):
      cam_io.load_cameras(self._frame_file(matrix=m))
    # 3x4 matrices and a last row off by rounding still load, unchanged.
    m = _opengl_c2w()
    ref = cam_io.load_cameras(self._frame_file(matrix=m))[0]
    m34 = cam_io.load_cameras(self._frame_file(matrix=m[:3]))[0]
    m[3, 3] += 1e-9
    near = cam_io.load_cameras(self._frame_file(matrix=m))[0]
    for c in (m34, near):
      np.testing.assert_array_equal(c.viewmat, ref.viewmat)

  def test_malformed_camera_files(self):
    for frames in (5, {}, 'abc'):
      with self.assertRaisesRegex(cam_io.CameraFileError,
                                  r'u\.json: "frames" must be a list.*got '):
        cam_io.load_cameras(self._json('u.json', {'frames': frames}))
    with self.assertRaisesRegex(cam_io.CameraFileError,
                                'applied_transform .*singular'):
      cam_io.load_cameras(
        self._frame_file(applied_transform=np.zeros((3, 4)).tolist()),
        undo_applied_transform=True)
    with self.assertRaisesRegex(
        cam_io.CameraFileError,
        r"t\.json: frame 0 field 'k1' is not a number: 'abc'"):
      cam_io.load_cameras(self._frame_file(k1='abc'))
    # A JSON true was a width of 1 pixel.
    with self.assertRaisesRegex(
        cam_io.CameraFileError, r"t\.json: .*'w' is not a number: True"):
      cam_io.load_cameras(self._frame_file(w=True))
    with self.assertRaisesRegex(cam_io.CameraFileError,
                                'is a directory.*cameras.json'):
      cam_io.load_cameras(self.tmp)
    with self.assertRaisesRegex(cam_io.CameraFileError,
                                r'e\.json: .*empty.*no cameras'):
      cam_io.load_cameras(self._json('e.json', []))
    with self.assertRaisesRegex(cam_io.CameraFileError, 'no cameras'):
      cam_io.inria_cameras_from_json([])
    entry = {'id': 0, 'img_name': 'a', 'width': W, 'height': H,
             'position': [0, 0, 0], 'rotation': np.eye(3).tolist(),
             'fy': 1.0, 'fx': 1.0}
    for key in ('width', 'height'):
      with self.assertRaisesRegex(cam_io.CameraFileError,
                                  f"camera 0 field '{key}' = 1e\\+300 .*at "
                                  'most'):
        cam_io.load_cameras(self._json('c.json', [dict(entry,
                                                       **{key: 1e300})]))
    with self.assertRaisesRegex(cam_io.CameraFileError,
                                r"camera 0: 'fx'=1e\+300 .*float32"):
      cam_io.load_cameras(self._json('c.json', [dict(entry, fx=1e300)]))


if __name__ == '__main__':
  absltest.main()
