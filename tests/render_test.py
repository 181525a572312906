"""Tests for physsplat_jax.render: parity with a brute-force reference,
capacity/overflow handling, SH view rotation, precomputed covariances,
gradients against central finite differences (x64) and gsplat's antialiased
rasterize mode."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax import cameras
from physsplat_jax import gaussians as gs
from physsplat_jax import pipeline as pl
from physsplat_jax import test_util
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.render.project import project
from physsplat_jax.render import images
from physsplat_jax.render import raster
from physsplat_jax.render.config import RenderConfigError
from physsplat_jax.render.config import RenderInputError
from physsplat_jax.render import reference
from physsplat_jax import sh_rotation
from physsplat_jax.render import views
from physsplat_jax.types import DataError
from physsplat_jax.types import Scene
from physsplat_jax.types import make_camera

_IMAGE_TOL = 1e-4  # float32 renderer vs float64 reference, max abs
_DEPTH_RTOL = 1e-4
_GRAD_RTOL = 1e-5  # x64 analytic vs central differences
_FD_STEP = 1e-6

_render_jit = jax.jit(raster.render, static_argnames=('config',))


def _scene(seed=0, num=200, sh_degree=0, scale_boost=1.0, dtype=jnp.float32):
  g = test_util.random_gaussians(jax.random.PRNGKey(seed), num,
                                 sh_degree=sh_degree, dtype=dtype)
  return g.replace(log_scales=g.log_scales + scale_boost)


def _camera(width=64, height=48, eye=(0.0, -3.5, 1.0), focal=60.0, cx=None,
            cy=None, near=0.01, dtype=jnp.float32):
  vm = cameras.look_at(np.asarray(eye), np.zeros(3))
  return make_camera(vm, focal, focal, width, height, cx=cx, cy=cy,
                     near=near, dtype=dtype)


def _reference(g, cam, colors, background=(0.0, 0.0, 0.0), covs=None,
               alpha_max=0.999, rasterize_mode='classic'):
  covs = g.covariances if covs is None else covs
  return reference.render_reference(
    np.asarray(g.means), np.asarray(covs), np.asarray(colors),
    np.asarray(g.opacities), np.asarray(cam.viewmat), cam.fx, cam.fy,
    cam.cx, cam.cy, cam.width, cam.height, cam.near, cam.far,
    background=background, alpha_max=alpha_max,
    rasterize_mode=rasterize_mode)


def _assert_matches(test, out, image, alpha, depth):
  """``out`` equals the reference on a scene that exercises saturation
  (early stop) and empty pixels."""
  test.assertGreater(alpha.max(), 0.999)
  test.assertLess(alpha.min(), 0.5)
  np.testing.assert_allclose(out.image, image, atol=_IMAGE_TOL,
                             err_msg='mismatch: image')
  np.testing.assert_allclose(out.alpha, alpha, atol=_IMAGE_TOL,
                             err_msg='mismatch: alpha')
  drawn = alpha > 0.05
  np.testing.assert_allclose(out.depth[drawn], depth[drawn],
                             rtol=_DEPTH_RTOL, err_msg='mismatch: depth')


class ReferenceParityTest(parameterized.TestCase):

  @parameterized.named_parameters(
    ('_sh0', 0, 64, 48, None, (0.0, 0.0, 0.0)),
    ('_sh3_background', 3, 64, 64, None, (0.2, 0.5, 1.0)),
    ('_odd_size_offcentre', 1, 37, 29, (15.0, 11.0), (1.0, 1.0, 1.0)),
  )
  def test_matches_reference(self, degree, width, height, principal, bg):
    g = _scene(seed=degree, sh_degree=degree)
    cx, cy = principal if principal else (None, None)
    cam = _camera(width, height, cx=cx, cy=cy)
    out = images.render_image(g, cam, background=bg)
    self.assertFalse(out.overflow)
    colors = raster.gaussian_colors(g, cam)
    image, alpha, depth = _reference(g, cam, colors, bg)
    _assert_matches(self, out, image, alpha, depth)

  def test_colors_come_from_the_view_direction(self):
    """``gaussian_colors`` against NumPy from the camera's eye: degree 1 in
    closed form (basis C0, -C1 y, C1 z, -C1 x of the unit direction from
    the eye to the mean; + 0.5, clamped at 0), and with per-Gaussian
    rotations the direction taken into the rest frame, R^T d. The parity
    tests hand the renderer's own colours to the reference: a flipped view
    direction passed them."""
    from scipy.spatial.transform import Rotation
    c0, c1 = 0.28209479177387814, 0.4886025119029199
    eye = np.array([0.4, -3.5, 1.0])
    g = _scene(seed=3, num=50, sh_degree=1)
    cam = _camera(eye=eye)
    sh = np.asarray(g.sh, np.float64)

    def colors(d):
      d = d / np.linalg.norm(d, axis=1, keepdims=True)
      basis = np.stack([np.full(len(d), c0), -c1 * d[:, 1], c1 * d[:, 2],
                        -c1 * d[:, 0]], 1)
      return np.maximum(np.einsum('kb,kbc->kc', basis, sh[:, :4]) + 0.5, 0)

    d = np.asarray(g.means, np.float64) - eye
    want = colors(d)
    self.assertGreater(np.abs(colors(-d) - want).max(), 0.05)  # it matters
    np.testing.assert_allclose(raster.gaussian_colors(g, cam), want,
                               atol=1e-5)
    rot = Rotation.random(g.num, random_state=1).as_matrix()
    np.testing.assert_allclose(
      raster.gaussian_colors(g, cam, jnp.asarray(rot, jnp.float32)),
      colors(np.einsum('kji,kj->ki', rot, d)), atol=1e-5)

  def test_differentiable_path_matches_reference(self):
    g = _scene(seed=5, num=120)
    cam = _camera(48, 40)
    cfg = raster.RenderConfig(chunk_size=16)
    out = images.render_image(g, cam, config=cfg, differentiable=True)
    colors = raster.gaussian_colors(g, cam)
    image, alpha, _ = _reference(g, cam, colors)
    np.testing.assert_allclose(out.image, image, atol=_IMAGE_TOL)
    np.testing.assert_allclose(out.alpha, alpha, atol=_IMAGE_TOL)

  def test_inria_alpha_cap_and_cumsum_prefix(self):
    g = _scene(seed=7, num=150)
    cam = _camera(48, 48)
    cfg = raster.RenderConfig(alpha_max=0.99, prefix='cumsum', chunk_size=8)
    out = images.render_image(g, cam, config=cfg)
    image, _, _ = _reference(g, cam, raster.gaussian_colors(g, cam),
                             alpha_max=0.99)
    np.testing.assert_allclose(out.image, image, atol=_IMAGE_TOL)

  def test_near_plane_and_behind_camera_are_culled(self):
    g = _scene(seed=3, num=60)
    cam = _camera(32, 32, eye=(0.0, -1.5, 0.0), near=0.8)
    out = images.render_image(g, cam)
    z = np.asarray(g.means @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3])[:, 2]
    self.assertGreater(np.sum(z <= 0.8), 5)  # some are culled ...
    self.assertLess(int(out.num_visible), np.sum(z > 0.8) + 1)
    image, _, _ = _reference(g, cam, raster.gaussian_colors(g, cam))
    np.testing.assert_allclose(out.image, image, atol=_IMAGE_TOL)


class CapacityTest(parameterized.TestCase):

  def test_overflow_flag_and_rerun(self):
    g = _scene(seed=1)
    cam = _camera()
    big = images.render_image(g, cam)
    total = int(big.num_intersections)
    self.assertGreater(total, 100)
    small = raster.RenderConfig(capacity=total // 3)
    out = jax.tree.map(np.asarray, _render_jit(g, cam, config=small))
    self.assertTrue(out.overflow)
    self.assertEqual(int(out.num_intersections), total)
    rerun = images.render_image(g, cam, config=small)
    self.assertFalse(rerun.overflow)
    np.testing.assert_array_equal(rerun.image, big.image)
    # The async form counts its re-runs; a fitting config needs none.
    pending = images.render_image_async(g, cam, config=small)
    np.testing.assert_array_equal(pending.result().image, big.image)
    self.assertGreaterEqual(pending.reruns, 1)
    self.assertGreaterEqual(pending.config.capacity, total)
    again = images.render_image_async(g, cam, config=pending.config)
    np.testing.assert_array_equal(again.result().image, big.image)
    self.assertEqual(again.reruns, 0)

  def test_async_fetches_only_the_image_clipped_on_the_device(self):
    """fetch=('image',), clip=True (pipeline.run's frames): the image comes
    to the host clipped to [0, 1], alpha and depth stay JAX arrays with the
    full render's values, the flags come as NumPy; also after a re-run."""
    g = _scene(seed=1)
    cam = _camera()
    full = images.render_image(g, cam, background=(2.0, 0.5, 0.0))
    self.assertGreater(float(full.image.max()), 1.0)  # something to clip
    small = raster.RenderConfig(capacity=int(full.num_intersections) // 3)
    for config in (raster.RenderConfig(), small):
      pending = images.render_image_async(g, cam, background=(2.0, 0.5, 0.0),
                                          config=config, fetch=('image',),
                                          clip=True)
      out = pending.result()
      self.assertIsInstance(out.image, np.ndarray)
      self.assertIsInstance(out.overflow, np.ndarray)
      self.assertIsInstance(out.alpha, jax.Array)
      np.testing.assert_array_equal(out.image, np.clip(full.image, 0, 1))
      np.testing.assert_array_equal(np.asarray(out.depth), full.depth)
    self.assertGreaterEqual(pending.reruns, 1)
    with self.assertRaisesRegex(RenderInputError, "fetch=.*'normals'.*use"):
      images.render_image_async(g, cam, fetch=('image', 'normals'))

  def test_async_capacity_has_the_head_room_asked_for(self):
    """The capacity a count or an overflow sets is the intersections times
    ``headroom`` (10 % by default; the pipeline asks 50 % for a video's
    frames), rounded up, never below; the image is the same."""
    g = _scene(seed=3, num=600)
    cam = _camera(96, 64)
    full = images.render_image(g, cam)
    total = int(full.num_intersections)
    self.assertGreater(total, 2048)  # above the ladder's 1024 floor
    counted = raster.RenderConfig(min_capacity=16)  # counts first
    short = raster.RenderConfig(capacity=total // 3)  # overflows, re-runs
    for config in (counted, short):
      caps = {}
      for headroom in (1.1, 1.5):
        pending = images.render_image_async(g, cam, config=config,
                                            headroom=headroom)
        np.testing.assert_array_equal(pending.result().image, full.image)
        caps[headroom] = pending.config.capacity
        self.assertGreaterEqual(caps[headroom], headroom * total)
        self.assertLess(caps[headroom], 1.25 * headroom * total)
      self.assertEqual(caps[1.1], images._next_capacity(total))
      self.assertGreater(caps[1.5], caps[1.1])

  def test_capacity_exact_boundary(self):
    g = _scene(seed=2, num=80)
    cam = _camera(48, 32)
    total = int(images.render_image(g, cam).num_intersections)
    exact = _render_jit(g, cam, config=raster.RenderConfig(capacity=total))
    short = _render_jit(g, cam,
                        config=raster.RenderConfig(capacity=total - 1))
    self.assertFalse(bool(exact.overflow))
    self.assertTrue(bool(short.overflow))
    ref, _, _ = _reference(g, cam, raster.gaussian_colors(g, cam))
    np.testing.assert_allclose(exact.image, ref, atol=_IMAGE_TOL)

  def test_count_and_binning_variants_agree(self):
    # The host-side count sizes the capacity exactly; sub-tiles and tight
    # bounds change the work, not the image.
    g = _scene(seed=6, num=150)
    cam = _camera(48, 40)
    out = images.render_image(g, cam)
    self.assertEqual(images.count_intersections(g, cam),
                     int(out.num_intersections))
    plain = raster.RenderConfig(subtile_size=None, tight_bounds=False)
    base = images.render_image(g, cam, config=plain)
    self.assertGreater(int(base.num_intersections), 0)
    np.testing.assert_allclose(out.image, base.image, atol=1e-6)
    with self.assertRaisesRegex(ValueError, 'must divide'):
      raster.render(g, cam, config=raster.RenderConfig(subtile_size=6))

  def test_differentiable_max_chunks_overflow(self):
    g = _scene(seed=4, num=100)
    cam = _camera(32, 32)
    cfg = raster.RenderConfig(chunk_size=4, max_chunks=1)
    out = jax.jit(raster.render_differentiable,
                  static_argnames=('config',))(g, cam, config=cfg)
    self.assertGreater(int(out.max_tile_count), 4)
    self.assertTrue(bool(out.overflow))
    fitted = images.fit_render_config(g, cam, cfg)
    self.assertGreaterEqual(fitted.max_chunks * 4, int(out.max_tile_count))
    out2 = images.render_image(g, cam, config=cfg, differentiable=True)
    self.assertFalse(out2.overflow)
    ref = images.render_image(g, cam)
    np.testing.assert_allclose(out2.image, ref.image, atol=1e-6)

  def test_everything_culled_gives_background(self):
    g = _scene(seed=0, num=10)
    cam = _camera(32, 16, eye=(0.0, -3.5, 1.0))
    g = g.replace(means=11.0 * cam.position[None] + 0.0 * g.means)
    out = images.render_image(g, cam, background=(0.1, 0.2, 0.3))
    self.assertEqual(int(out.num_intersections), 0)
    np.testing.assert_allclose(
      out.image, np.broadcast_to([0.1, 0.2, 0.3], (16, 32, 3)), atol=1e-7)
    np.testing.assert_array_equal(out.alpha, 0.0)

  def test_single_gaussian_matches_closed_form(self):
    # One isotropic Gaussian straight ahead: alpha(p) = o exp(-|d|^2 / 2 s2)
    # with s2 = (f s / z)^2 + 0.3 (the EWA footprint plus the low-pass).
    s, z, f, o = 0.05, 2.0, 40.0, 0.7
    g = gs_single(s, o)
    cam = make_camera(jnp.eye(4).at[2, 3].set(z), f, f, 33, 33)
    out = images.render_image(g, cam, colors=jnp.ones((1, 3)))
    s2 = (f * s / z) ** 2 + 0.3
    jj, ii = np.meshgrid(np.arange(33) + 0.5, np.arange(33) + 0.5)
    d2 = (jj - 16.5) ** 2 + (ii - 16.5) ** 2
    a = o * np.exp(-0.5 * d2 / s2)
    a = np.where(a >= 1 / 255, a, 0.0)
    np.testing.assert_allclose(out.alpha, a, atol=1e-6)
    np.testing.assert_allclose(out.depth[16, 16], z, rtol=1e-6)

  def test_bad_inputs_raise_clear_errors(self):
    g = _scene(num=5)
    cam = _camera(16, 16)
    # The package's own errors (one line in the scripts), still ValueErrors.
    with self.assertRaisesRegex(RenderInputError, 'covariances has shape'):
      raster.render(g, cam, covariances=jnp.zeros((4, 3, 3)))
    with self.assertRaisesRegex(RenderInputError, 'colors has shape'):
      raster.render(g, cam, colors=jnp.zeros((5, 4)))
    with self.assertRaisesRegex(RenderInputError, 'background has shape'):
      raster.render(g, cam, background=(1.0, 1.0))
    with self.assertRaisesRegex(RenderInputError, 'no Gaussians'):
      raster.render(g.subset(np.zeros(5, bool)), cam)
    with self.assertRaisesRegex(RenderConfigError, 'prefix'):
      raster.render(g, cam, config=raster.RenderConfig(prefix='scan'))
    with self.assertRaisesRegex(RenderInputError, r'opacity_logits has shape '
                                r'\(5, 1\), expected \(5,\)'):
      raster.render(g.replace(opacity_logits=g.opacity_logits[:, None]), cam)
    # The host wrapper also checks values, and takes colour names.
    bad = g.replace(log_scales=g.log_scales.at[2, 1].set(jnp.nan))
    with self.assertRaisesRegex(RenderInputError,
                                r'non-finite log_scales \(rows 2\)'):
      images.render_image(bad, cam)
    with self.assertRaisesRegex(RenderInputError, 'colors has non-finite'):
      images.render_image(g, cam, colors=jnp.full((5, 3), jnp.nan))
    # A camera edited with replace (make_camera's checks skipped): was a
    # black image.
    for bad_cam, want in ((cam.replace(near=jnp.asarray(9.0),
                                       far=jnp.asarray(1.0)),
                           r'near=9\.0, far=1\.0; need 0 < near < far'),
                          (cam.replace(fx=jnp.asarray(jnp.nan)),
                           'focal length fx=nan')):
      with self.subTest(want), self.assertRaisesRegex(RenderInputError, want):
        images.render_image(g, bad_cam)
    np.testing.assert_array_equal(
      images.render_image(g, cam, background='white').image,
      images.render_image(g, cam, background=(1.0, 1.0, 1.0)).image)
    # The render-only path has no reverse pass: the error says what to use
    # (JAX's own named only its while loop); the differentiable path works.
    loss = lambda fn, m: fn(g.replace(means=m), cam).image.mean()  # noqa
    with self.assertRaisesRegex(RenderInputError, 'render_differentiable'):
      jax.grad(functools.partial(loss, raster.render))(g.means)
    grad = jax.grad(functools.partial(loss, raster.render_differentiable))(
      g.means)
    self.assertTrue(np.all(np.isfinite(grad)))
    for cls in (RenderInputError, RenderConfigError):
      self.assertTrue(issubclass(cls, PhysSplatError))
      self.assertTrue(issubclass(cls, ValueError))

  def test_render_image_refuses_silently_wrong_inputs(self):
    g = _scene(num=5)
    cam = _camera(16, 16)
    # No Gaussians: the package's message, not NumPy's reshape error.
    with self.assertRaisesRegex(RenderInputError, r'no Gaussians \(K = 0\)'):
      images.render_image(g.subset(np.zeros(5, bool)), cam)
    # Non-finite covariances or rotations dropped the Gaussian without a
    # word; covariances that are not symmetric positive definite drew it
    # wrong.
    covs = np.asarray(g.covariances)
    nan = covs.copy()
    nan[1, 0, 0] = np.nan
    rots = np.tile(np.eye(3, dtype=np.float32), (5, 1, 1))
    rots[3, 2, 2] = np.inf
    asym = covs.copy()
    asym[2, 0, 1] += 0.5
    for kw, want in (
        (dict(covariances=nan), r'covariances has non-finite values in 1 of '
         r'5 rows \(rows 1\)'),
        (dict(view_rotations=rots), r'view_rotations has non-finite values '
         r'in 1 of 5 rows \(rows 3\)'),
        (dict(covariances=-1e-3 * np.tile(np.eye(3, dtype=np.float32),
                                          (5, 1, 1))),
         r'covariances rows 0, 1, 2, 3, 4 \(5 of 5\) are not positive '
         r'definite .*pass symmetric positive definite'),
        (dict(covariances=asym), r'covariances rows 2 \(1 of 5\) are not '
         'symmetric')):
      with self.subTest(want), self.assertRaisesRegex(RenderInputError, want):
        images.render_image(g, cam, **kw)
    # Rounding is not refused: a flat Gaussian's smallest eigenvalue (1e-14
    # of the largest) rounds to about zero in float32, and F Sigma F^T is
    # symmetric only up to rounding.
    flat = g.replace(log_scales=g.log_scales.at[:, 2].set(-16.0))
    F = 0.3 * jax.random.normal(jax.random.PRNGKey(1), (5, 3, 3)) + jnp.eye(3)
    for c in (g.covariances, flat.covariances,
              F @ flat.covariances @ jnp.swapaxes(F, 1, 2)):
      self.assertEqual([r.size for r in images._not_spd_rows(c)], [0, 0])
    # An SH degree above the Gaussians' broadcast their one coefficient.
    with self.assertRaisesRegex(
        RenderConfigError, r'RenderConfig\.sh_degree=3, but the Gaussians '
        r'have SH degree 0 .*Gaussians\.with_sh_degree\(3\)'):
      images.render_image(g, cam, config=raster.RenderConfig(sh_degree=3))
    with self.assertRaisesRegex(RenderConfigError, 'sh_degree=1'):
      raster.render(g, cam, config=raster.RenderConfig(sh_degree=1))


def gs_single(s, o):
  from physsplat_jax.types import Gaussians

  return Gaussians(
    means=jnp.zeros((1, 3)), log_scales=jnp.full((1, 3), np.log(s)),
    quats=jnp.array([[1.0, 0.0, 0.0, 0.0]]),
    opacity_logits=jnp.array([np.log(o / (1 - o))]),
    sh=jnp.zeros((1, 1, 3)))


class CovarianceAndShTest(parameterized.TestCase):

  def test_precomputed_covariances_equal_scale_rotation_path(self):
    g = _scene(seed=11, num=150, sh_degree=1)
    cam = _camera()
    a = images.render_image(g, cam)
    b = images.render_image(g, cam, covariances=g.covariances)
    np.testing.assert_allclose(a.image, b.image, atol=1e-6)
    np.testing.assert_allclose(a.alpha, b.alpha, atol=1e-6)

  def test_explicit_colors_equal_sh_dc(self):
    g = _scene(seed=12, num=150, sh_degree=0)
    cam = _camera()
    a = images.render_image(g, cam)
    b = images.render_image(g, cam, colors=jnp.maximum(g.rgb_dc, 0.0))
    np.testing.assert_allclose(a.image, b.image, atol=1e-6)

  def test_rotating_scene_camera_and_view_rotation_keeps_image(self):
    # Rotate every Gaussian (mean and covariance) and the camera by Q and pass
    # Q as the view rotation: the SH see the same rest-frame direction, so
    # the image is unchanged, although the world directions all changed.
    g = _scene(seed=13, num=150, sh_degree=3)
    cam = _camera()
    q = np.array([0.8, 0.3, -0.4, 0.3])
    Q = np.asarray(gs.quat_to_rotmat(jnp.asarray(q / np.linalg.norm(q))))
    Qj = jnp.asarray(Q, jnp.float32)
    g_rot = g.replace(means=g.means @ Qj.T)
    covs = Qj @ g.covariances @ Qj.T
    vm = np.asarray(cam.viewmat, np.float64).copy()
    vm[:3, :3] = vm[:3, :3] @ Q.T
    cam_rot = cam.replace(viewmat=jnp.asarray(vm, jnp.float32))
    rots = jnp.broadcast_to(Qj, (g.num, 3, 3))
    a = images.render_image(g, cam)
    b = images.render_image(g_rot, cam_rot, covariances=covs,
                            view_rotations=rots)
    c = images.render_image(g_rot, cam_rot, covariances=covs)
    np.testing.assert_allclose(a.image, b.image, atol=2e-4)
    # Without the view rotation the degree-3 colours differ.
    self.assertGreater(np.abs(a.image - c.image).max(), 1e-2)
    # Rotating the SH coefficients instead gives the same image too.
    sh_rot = sh_rotation.rotate_sh(g.sh, rots)
    d = images.render_image(g_rot.replace(sh=sh_rot), cam_rot,
                            covariances=covs)
    np.testing.assert_allclose(a.image, d.image, atol=2e-4)


class GradientTest(parameterized.TestCase):

  def test_gradients_match_central_differences_x64(self):
    with jax.enable_x64(True):
      g = _scene(seed=21, num=8, scale_boost=1.5, dtype=jnp.float64)
      cam = _camera(24, 20, focal=24.0, dtype=jnp.float64)
      cfg = raster.RenderConfig(chunk_size=4, tile_size=8)
      rng = np.random.default_rng(0)
      w_img = jnp.asarray(rng.normal(size=(20, 24, 3)))
      w_alpha = jnp.asarray(rng.normal(size=(20, 24)))
      colors0 = jnp.asarray(rng.uniform(0.1, 0.9, size=(8, 3)))
      covs0 = g.covariances

      def loss(means, covs, colors, logits):
        out = raster.render_differentiable(
          g.replace(means=means, opacity_logits=logits), cam,
          covariances=covs, colors=colors, background=(0.3, 0.2, 0.1),
          config=cfg)
        return jnp.sum(out.image * w_img) + jnp.sum(out.alpha * w_alpha)

      args = (g.means, covs0, colors0, g.opacity_logits)
      out = raster.render_differentiable(g, cam, config=cfg)
      self.assertFalse(bool(out.overflow))
      self.assertGreater(float(out.alpha.max()), 0.5)
      grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(*args)
      test_util.assert_tree_all_finite(grads)
      loss_j = jax.jit(loss)
      names = ('means', 'covariances', 'colors', 'opacity_logits')
      for i, name in enumerate(names):
        d = jnp.asarray(rng.normal(size=args[i].shape))
        if name == 'covariances':
          d = 1e-3 * (d + jnp.swapaxes(d, -1, -2))  # stay symmetric and PD
        plus = list(args)
        minus = list(args)
        plus[i] = args[i] + _FD_STEP * d
        minus[i] = args[i] - _FD_STEP * d
        fd = (loss_j(*plus) - loss_j(*minus)) / (2 * _FD_STEP)
        an = jnp.sum(grads[i] * d)
        self.assertGreater(abs(float(an)), 1e-6, msg=name)
        np.testing.assert_allclose(an, fd, rtol=_GRAD_RTOL,
                                   err_msg=f'gradient mismatch: {name}')

  def test_sh_color_gradients_match_central_differences_x64(self):
    """Colours from degree-1 SH (no colours passed): the gradient with
    respect to the SH, and the part of the means' gradient that comes
    through the view direction, against central differences. (The test
    above passes colours, so neither was checked.) Colours stay inside
    (0, 1): no clamp at 0 for the differences to straddle."""
    with jax.enable_x64(True):
      g = _scene(seed=22, num=8, scale_boost=1.5, dtype=jnp.float64)
      rng = np.random.default_rng(1)
      sh = np.zeros((8, 4, 3))
      sh[:, 0] = (rng.uniform(0.3, 0.7, (8, 3)) - 0.5) / gs.SH_C0
      sh[:, 1:] = 0.3 * rng.normal(size=(8, 3, 3))
      g = g.replace(sh=jnp.asarray(sh))
      cam = _camera(24, 20, focal=24.0, dtype=jnp.float64)
      cfg = raster.RenderConfig(chunk_size=4, tile_size=8)
      w_img = jnp.asarray(rng.normal(size=(20, 24, 3)))
      rgb = np.asarray(raster.gaussian_colors(g, cam))
      self.assertTrue(np.all((rgb > 0.05) & (rgb < 0.95)))

      def loss(means, sh):
        out = raster.render_differentiable(
          g.replace(means=means, sh=sh), cam, config=cfg)
        return jnp.sum(out.image * w_img)

      def colors_only(means, sh):  # the view direction's part alone
        return jnp.sum(raster.gaussian_colors(
          g.replace(means=means, sh=sh), cam) * w_img[0, :8])

      args = (g.means, g.sh)
      for fn in (loss, colors_only):
        grads = jax.jit(jax.grad(fn, argnums=(0, 1)))(*args)
        fn_j = jax.jit(fn)
        for i, name in enumerate(('means', 'sh')):
          d = jnp.asarray(rng.normal(size=args[i].shape))
          plus, minus = list(args), list(args)
          plus[i] = args[i] + _FD_STEP * d
          minus[i] = args[i] - _FD_STEP * d
          fd = (fn_j(*plus) - fn_j(*minus)) / (2 * _FD_STEP)
          an = jnp.sum(grads[i] * d)
          self.assertGreater(abs(float(an)), 1e-6, msg=name)
          np.testing.assert_allclose(
            an, fd, rtol=_GRAD_RTOL,
            err_msg=f'gradient mismatch: {fn.__name__} {name}')


_AA = raster.RenderConfig(rasterize_mode='antialiased')


class AntialiasedTest(absltest.TestCase):
  """gsplat's ``rasterize_mode='antialiased'`` (Mip-Splatting's 2D filter)."""

  def test_matches_reference_on_both_paths(self):
    # Small, opaque Gaussians: compensations spread over (0.29, 0.98), pixels
    # saturate (early stop) and some stay empty.
    g = _scene(seed=1, num=200, scale_boost=0.3)
    g = g.replace(opacity_logits=g.opacity_logits + 3.0)
    cam = _camera()
    bg = (0.2, 0.5, 1.0)
    out = images.render_image(g, cam, background=bg, config=_AA)
    image, alpha, depth = _reference(g, cam, raster.gaussian_colors(g, cam),
                                     bg, rasterize_mode='antialiased')
    _assert_matches(self, out, image, alpha, depth)
    diff = images.render_image(g, cam, background=bg, differentiable=True,
                               config=dataclasses.replace(_AA, chunk_size=16))
    np.testing.assert_allclose(diff.image, image, atol=_IMAGE_TOL,
                               err_msg='mismatch: differentiable image')
    # The mode matters on this scene, and the tight bounds use the
    # compensated opacity (fewer intersections), counted exactly on the host.
    classic = images.render_image(g, cam, background=bg)
    self.assertGreater(np.abs(classic.image - out.image).max(), 0.1)
    self.assertLess(int(out.num_intersections),
                    int(classic.num_intersections))
    self.assertEqual(images.count_intersections(g, cam, config=_AA),
                     int(out.num_intersections))

  def test_single_gaussian_matches_closed_form(self):
    # Isotropic, sub-pixel: with s2 = (f s / z)^2 the compensation is
    # sqrt(s2^2 / (s2 + 0.3)^2) = s2 / (s2 + 0.3), so alpha(p) = o s2 /
    # (s2 + 0.3) exp(-|d|^2 / 2 (s2 + 0.3)): the low-pass spreads the splat's
    # weight (o 2 pi s2 before and after) instead of adding to it.
    s, z, f, o = 0.03, 2.0, 40.0, 0.9
    g = gs_single(s, o)
    cam = make_camera(jnp.eye(4).at[2, 3].set(z), f, f, 17, 17)
    out = images.render_image(g, cam, colors=jnp.ones((1, 3)), config=_AA)
    s2 = (f * s / z) ** 2
    jj, ii = np.meshgrid(np.arange(17) + 0.5, np.arange(17) + 0.5)
    d2 = (jj - 8.5) ** 2 + (ii - 8.5) ** 2
    a = o * s2 / (s2 + 0.3) * np.exp(-0.5 * d2 / (s2 + 0.3))
    a = np.where(a >= 1 / 255, a, 0.0)
    self.assertLess(a.max(), 0.5)  # classic would give o = 0.9 here
    np.testing.assert_allclose(out.alpha, a, atol=1e-6)

  def test_compensation_gradients_match_central_differences_x64(self):
    # The compensation alone (projection: means, covariances), then through
    # the whole differentiable render (means, scales, quaternions,
    # opacities).
    with jax.enable_x64(True):
      g = _scene(seed=22, num=8, scale_boost=0.8, dtype=jnp.float64)
      g = g.replace(opacity_logits=g.opacity_logits + 2.0)
      cam = _camera(24, 20, focal=24.0, dtype=jnp.float64)
      rng = np.random.default_rng(2)
      w_comp = jnp.asarray(rng.normal(size=8))

      def comp_loss(p):
        proj = project(p['means'], p['covariances'], cam, antialiased=True)
        return jnp.sum(proj.compensations * w_comp), proj.compensations

      fn = jax.jit(jax.value_and_grad(comp_loss, has_aux=True))
      params = {'means': g.means, 'covariances': g.covariances}
      comp = _check_directional_fd(self, fn, params, rng)
      self.assertLess(float(comp.min()), 0.6)  # far from 1: it matters
      # A point (zero covariance) has compensation 0 and a finite gradient.
      point = dict(params, covariances=params['covariances'].at[0].set(0.0))
      (_, comp), grads = fn(point)
      self.assertEqual(float(comp[0]), 0.0)
      test_util.assert_tree_all_finite(grads)

      cfg = dataclasses.replace(_AA, chunk_size=4, tile_size=8)
      w_img = jnp.asarray(rng.normal(size=(20, 24, 3)))
      w_alpha = jnp.asarray(rng.normal(size=(20, 24)))

      def loss(p):
        out = raster.render_differentiable(
          g.replace(**p), cam, background=(0.3, 0.2, 0.1), config=cfg)
        val = jnp.sum(out.image * w_img) + jnp.sum(out.alpha * w_alpha)
        return val, out

      fn = jax.jit(jax.value_and_grad(loss, has_aux=True))
      names = ('means', 'log_scales', 'quats', 'opacity_logits')
      out = _check_directional_fd(self, fn, {k: getattr(g, k) for k in names},
                                  rng)
      self.assertFalse(bool(out.overflow))
      self.assertGreater(float(out.alpha.max()), 0.5)

  def test_bad_mode_is_a_clear_package_error(self):
    with self.assertRaisesRegex(PhysSplatError, r"RenderConfig\.rasterize_mode"
                                r" is 'mip'; use 'classic' or 'antialiased'"):
      raster.RenderConfig(rasterize_mode='mip')
    with self.assertRaises(ValueError):
      dataclasses.replace(_AA, rasterize_mode='Antialiased')
    with self.assertRaisesRegex(PhysSplatError, 'rasterize_mode'):
      pl.config_from_dict({'render_config': {'rasterize_mode': 'aa'}})
    c = pl.config_from_dict({'render_config': {'rasterize_mode':
                                               'antialiased'}})
    self.assertEqual(c.simulate.render_config, _AA)


def _check_directional_fd(test, fn, params, rng):
  """Analytic vs central-difference derivative (x64) along a random direction
  of each leaf of ``params`` (symmetric for covariances); ``fn`` is a jitted
  ``value_and_grad(loss, has_aux=True)``. Returns the aux at ``params``."""
  (_, aux), grads = fn(params)
  test_util.assert_tree_all_finite(grads)
  for name, x in params.items():
    d = jnp.asarray(rng.normal(size=x.shape))
    if name == 'covariances':
      d = 1e-3 * (d + jnp.swapaxes(d, -1, -2))  # stay symmetric and PD
    (plus, _), _ = fn(dict(params, **{name: x + _FD_STEP * d}))
    (minus, _), _ = fn(dict(params, **{name: x - _FD_STEP * d}))
    fd = (plus - minus) / (2 * _FD_STEP)
    an = jnp.sum(grads[name] * d)
    test.assertGreater(abs(float(an)), 1e-6, msg=name)
    np.testing.assert_allclose(an, fd, rtol=_GRAD_RTOL,
                               err_msg=f'gradient mismatch: {name}')
  return aux


class BatchedCamerasTest(absltest.TestCase):

  def test_vmap_over_cameras_equals_one_by_one(self):
    # Cameras of one size stack into one Camera pytree; jax.vmap renders
    # them in one program.
    g = _scene(seed=32, num=60)
    cams = [_camera(32, 24, eye=e, focal=40.0)
            for e in ((0.0, -3.5, 1.0), (2.0, -2.5, 1.5))]
    batch = jax.tree.map(lambda *x: jnp.stack(x), *cams)
    out = jax.jit(jax.vmap(lambda c: raster.render(g, c)))(batch)
    self.assertEqual(out.image.shape, (2, 24, 32, 3))
    for i, cam in enumerate(cams):
      one = _render_jit(g, cam)
      self.assertFalse(bool(out.overflow[i]))
      self.assertGreater(float(one.alpha.max()), 0.5)
      np.testing.assert_allclose(out.image[i], one.image, atol=1e-6)
      np.testing.assert_allclose(out.alpha[i], one.alpha, atol=1e-6)
    self.assertGreater(float(jnp.abs(out.image[0] - out.image[1]).max()), 0.1)


class ShRotationTest(absltest.TestCase):

  def test_rotate_sh_rotates_the_function(self):
    rng = np.random.default_rng(3)
    sh = jnp.asarray(rng.normal(size=(5, 16, 3)), jnp.float32)
    q = rng.normal(size=(5, 4))
    R = gs.quat_to_rotmat(jnp.asarray(q, jnp.float32))
    d = jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)
    # Reflections too: deform_gaussians passes polar(F) of an inverted F.
    for name, Q in (('rotations', R), ('reflections', -R)):
      rot = sh_rotation.rotate_sh(sh, Q)
      want = gs.eval_sh(sh, jnp.einsum('kji,kj->ki', Q, d))
      got = gs.eval_sh(rot, d)
      with self.subTest(name):
        np.testing.assert_allclose(got, want, atol=1e-4)
        np.testing.assert_allclose(rot[:, 0], sh[:, 0], atol=1e-6)
    # One rotation per Gaussian or one for all; else a message, not JAX's
    # broadcast error.
    with self.assertRaisesRegex(DataError, r'rotations has shape \(4, 3, 3\)'
                                r'.*\(5, 3, 3\)'):
      sh_rotation.rotate_sh(sh, R[:4])


class ViewsTest(absltest.TestCase):

  def test_background_outside_unit_range_is_refused(self):
    # '2,0,0' was accepted though the message (and --background's help)
    # says three numbers in [0, 1].
    for bad in ('2,0,0', '0,-0.1,0', (0.0, 0.0, 1.5), 'nan,0,0'):
      with self.subTest(bad), self.assertRaisesRegex(
          RenderInputError, r'three numbers in \[0, 1\]'):
        views.parse_background(bad)
    self.assertEqual(views.parse_background('0,1,0.5'), (0.0, 1.0, 0.5))
    self.assertEqual(views.parse_background((1, 1, 1)), (1.0, 1.0, 1.0))

  def test_render_scene_fitted_camera_and_helpers(self):
    g = _scene(seed=31, num=60)
    out = views.render_scene(g, width=40, background='white',
                             return_output=True)
    self.assertEqual(out.image.shape, (30, 40, 3))
    # The fitted camera frames the scene: the centre is covered, the
    # corners show the white background.
    self.assertGreater(float(out.alpha[15, 20]), 0.5)
    np.testing.assert_allclose(out.image[0, 0], 1.0, atol=1e-3)
    img = views.render_scene(g, width=40, background=(1.0, 1.0, 1.0))
    np.testing.assert_allclose(img, np.clip(out.image, 0, 1), atol=1e-6)
    self.assertEqual(views.parse_background('0.1, 0.2,0.3'), (0.1, 0.2, 0.3))
    with self.assertRaisesRegex(ValueError, 'background'):
      views.parse_background('blue-ish')
    # Resizing to another aspect keeps the vertical field of view.
    cam = _camera(64, 48)
    wide = views.resize_camera(cam, 96, 48)
    self.assertEqual((wide.width, wide.height), (96, 48))
    np.testing.assert_allclose(wide.fy, cam.fy)
    np.testing.assert_allclose(wide.cx, 48.0)
    with self.assertRaisesRegex(ValueError, 'has 0 cameras'):
      views.scene_camera(Scene(gaussians=g, object_ids=jnp.zeros(60)), 2)


if __name__ == '__main__':
  absltest.main()
