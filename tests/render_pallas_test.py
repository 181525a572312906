"""Tests for the Pallas compositor (render/pallas_raster.py) without a GPU.

The kernels run in Pallas interpret mode on the CPU and are compared with the
pure-JAX compositor (itself checked against the brute-force reference in
render_test.py): images, alpha, depth and gradients, on random scenes and on
the real scene crops in tests/data; gradients also against central finite
differences in float64. A lowering test checks that both kernels lower to
Triton for CUDA (no GPU needed to lower; compiling to PTX needs one).
"""

import dataclasses
import functools
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl.testing import absltest

from physsplat_jax import cameras
from physsplat_jax import gaussians as gs
from physsplat_jax import platforms
from physsplat_jax import test_util
from physsplat_jax.io.scene import load_scene
from physsplat_jax.render import pallas_raster
from physsplat_jax.render.project import project
from physsplat_jax.render import raster
from physsplat_jax.render import views
from physsplat_jax.types import make_camera

DATA = pathlib.Path(__file__).parent / 'data'

_IMAGE_ATOL = 1e-4  # float32, Pallas vs JAX compositor, max abs
_DEPTH_RTOL = 1e-4
_GRAD_RTOL = 1e-3  # float32, Pallas vs JAX gradients
_GRAD_ATOL = 1e-4  # relative to the largest gradient entry
_FD_RTOL = 1e-5  # float64, analytic vs central differences
_FD_STEP = 1e-6

_JAX = raster.RenderConfig(backend='jax')
_PALLAS = raster.RenderConfig(backend='pallas', interpret=True)


def _camera(width, height, eye=(0.0, -3.5, 1.0), focal=60.0, cx=None,
            cy=None, dtype=jnp.float32):
  vm = cameras.look_at(np.asarray(eye), np.zeros(3))
  return make_camera(vm, focal, focal, width, height, cx=cx, cy=cy,
                     dtype=dtype)


def _weights(shape, seed):
  rng = np.random.default_rng(seed)
  h, w = shape
  return (jnp.asarray(rng.normal(size=(h, w, 3)), jnp.float32),
          jnp.asarray(rng.normal(size=(h, w)), jnp.float32),
          jnp.asarray(rng.normal(size=(h, w)), jnp.float32))


def _loss_fn(cam, config, background, weights):
  """(loss, outputs) of a weighted sum of image, alpha and depth."""
  w_img, w_alpha, w_depth = weights

  def loss(params, g):
    kw = {k: v for k, v in params.items() if k in ('covariances',
                                                    'view_rotations')}
    g = g.replace(**{k: v for k, v in params.items() if k not in kw})
    out = raster.render_differentiable(g, cam, background=background,
                                       config=config, **kw)
    val = (jnp.sum(out.image * w_img) + jnp.sum(out.alpha * w_alpha)
           + 0.1 * jnp.sum(out.depth * w_depth))
    return val, out

  return jax.jit(jax.value_and_grad(loss, has_aux=True))


def _compare(test, g, cam, config, params, background=(0.0, 0.0, 0.0),
             seed=0):
  """Renders with both compositors; asserts equal outputs and gradients."""
  weights = _weights((cam.height, cam.width), seed)
  res = {}
  for name, cfg in (('jax', dataclasses.replace(config, backend='jax')),
                    ('pallas', config)):
    fn = _loss_fn(cam, cfg, jnp.asarray(background), weights)
    (_, out), grads = fn(params, g)
    res[name] = (jax.tree.map(np.asarray, out),
                 jax.tree.map(np.asarray, grads))
  (oj, gj), (op, gp) = res['jax'], res['pallas']
  test.assertFalse(bool(oj.overflow))
  test.assertFalse(bool(op.overflow))
  np.testing.assert_allclose(op.image, oj.image, atol=_IMAGE_ATOL,
                             err_msg='image')
  np.testing.assert_allclose(op.alpha, oj.alpha, atol=_IMAGE_ATOL,
                             err_msg='alpha')
  drawn = oj.alpha > 0.05
  np.testing.assert_allclose(op.depth[drawn], oj.depth[drawn],
                             rtol=_DEPTH_RTOL, err_msg='depth')
  for k in params:
    scale = np.abs(gj[k]).max()
    test.assertGreater(scale, 0.0, msg=k)
    np.testing.assert_allclose(gp[k], gj[k], rtol=_GRAD_RTOL,
                               atol=_GRAD_ATOL * scale,
                               err_msg=f'gradient: {k}')
  return oj


class PallasParityTest(absltest.TestCase):

  def test_random_scene_forward_and_gradients_match_jax(self):
    # 300 overlapping Gaussians, 8x8 sub-tiles, batches of 32: several
    # batches per sub-tile, saturated pixels (early stop) and empty ones.
    g = test_util.random_gaussians(jax.random.PRNGKey(3), 300, sh_degree=1)
    g = g.replace(log_scales=g.log_scales + 1.0,
                  opacity_logits=g.opacity_logits + 2.0)
    cam = _camera(64, 48)
    cfg = dataclasses.replace(_PALLAS, pallas_block=32)
    params = {k: getattr(g, k) for k in
              ('means', 'log_scales', 'quats', 'opacity_logits', 'sh')}
    oj = _compare(self, g, cam, cfg, params, background=(0.2, 0.5, 1.0))
    self.assertGreater(int(oj.max_tile_count), 3 * cfg.pallas_block)
    # Pixels stop once T would drop to t_min = 1e-4, so T < 2e-4 marks a
    # stopped pixel.
    self.assertGreater(np.mean(oj.alpha > 1.0 - 2e-4), 0.05)
    self.assertLess(oj.alpha.min(), 0.5)

  def test_antialiased_mode_matches_jax(self):
    # gsplat's antialiased mode: the compensation rides on the opacity
    # feature, so the kernels composite it and their VJP carries its
    # gradient on to means, scales, quaternions and opacities.
    g = test_util.random_gaussians(jax.random.PRNGKey(5), 120)
    g = g.replace(log_scales=g.log_scales + 0.3,
                  opacity_logits=g.opacity_logits + 3.0)
    cam = _camera(32, 24, focal=30.0)
    cfg = dataclasses.replace(_PALLAS, pallas_block=16,
                              rasterize_mode='antialiased')
    params = {k: getattr(g, k) for k in
              ('means', 'log_scales', 'quats', 'opacity_logits')}
    comp = project(g.means, g.covariances, cam, antialiased=True)
    self.assertLess(float(comp.compensations.min()), 0.5)  # it matters
    oj = _compare(self, g, cam, cfg, params, seed=2)
    self.assertGreater(int(oj.max_tile_count), cfg.pallas_block)

  @pytest.mark.slow  # ~45 s in interpret mode; gradients also in x64 test
  def test_deformation_inputs_odd_size_full_tiles(self):
    # Precomputed covariances and view rotations (the deformation path),
    # 16x16 compositing tiles (P = 256), an odd image with an off-centre
    # principal point.
    g = test_util.random_gaussians(jax.random.PRNGKey(4), 200, sh_degree=2)
    g = g.replace(log_scales=g.log_scales + 1.0)
    rng = np.random.default_rng(1)
    F = jnp.asarray(np.eye(3) + 0.2 * rng.normal(size=(200, 3, 3)),
                    jnp.float32)
    covs = F @ g.covariances @ jnp.swapaxes(F, 1, 2)
    q = jnp.asarray(rng.normal(size=(200, 4)), jnp.float32)
    rots = gs.quat_to_rotmat(q / jnp.linalg.norm(q, axis=1, keepdims=True))
    cam = _camera(37, 29, cx=15.0, cy=11.0)
    cfg = dataclasses.replace(_PALLAS, subtile_size=None, pallas_block=64)
    params = {'means': g.means, 'covariances': covs, 'view_rotations': rots,
              'sh': g.sh, 'opacity_logits': g.opacity_logits}
    _compare(self, g, cam, cfg, params, background=(1.0, 1.0, 1.0), seed=1)

  def _crop(self, fname, size):
    sc = load_scene(DATA / fname)
    cam = views.scene_camera(sc, 0, *size)
    g = sc.gaussians
    params = {'means': g.means, 'opacity_logits': g.opacity_logits,
              'log_scales': g.log_scales, 'sh': g.sh}
    oj = _compare(self, g, cam, _PALLAS, params)
    self.assertGreater(float(oj.alpha.mean()), 0.02)  # the object is seen

  @pytest.mark.slow  # ~40 s in interpret mode
  def test_udon_crop_matches_jax(self):
    self._crop('udon_crop.ply', (48, 32))

  @pytest.mark.slow
  def test_train_crop_matches_jax(self):
    self._crop('train_1000.ply', (40, 32))


class PallasFiniteDifferenceTest(absltest.TestCase):

  def test_gradients_match_central_differences_x64(self):
    # Interpret mode runs the kernels in float64.
    with jax.enable_x64(True):
      g = test_util.random_gaussians(jax.random.PRNGKey(21), 8,
                                     dtype=jnp.float64)
      g = g.replace(log_scales=g.log_scales + 1.5)
      cam = _camera(24, 20, focal=24.0, dtype=jnp.float64)
      cfg = dataclasses.replace(_PALLAS, tile_size=8, pallas_block=4)
      rng = np.random.default_rng(0)
      w_img = jnp.asarray(rng.normal(size=(20, 24, 3)))
      w_alpha = jnp.asarray(rng.normal(size=(20, 24)))
      w_depth = jnp.asarray(rng.normal(size=(20, 24)))
      colors0 = jnp.asarray(rng.uniform(0.1, 0.9, size=(8, 3)))

      def loss(means, covs, colors, logits):
        out = raster.render(
          g.replace(means=means, opacity_logits=logits), cam,
          covariances=covs, colors=colors, background=(0.3, 0.2, 0.1),
          config=cfg)
        return (jnp.sum(out.image * w_img) + jnp.sum(out.alpha * w_alpha)
                + 0.1 * jnp.sum(out.depth * w_depth))

      args = (g.means, g.covariances, colors0, g.opacity_logits)
      out = jax.jit(functools.partial(raster.render, config=cfg))(g, cam)
      self.assertEqual(out.image.dtype, jnp.float64)
      self.assertGreater(int(out.max_tile_count), cfg.pallas_block)
      self.assertGreater(float(out.alpha.max()), 0.5)
      grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(*args)
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
        np.testing.assert_allclose(an, fd, rtol=_FD_RTOL,
                                   err_msg=f'gradient mismatch: {name}')


class PallasConfigTest(absltest.TestCase):

  def test_backend_selection_and_errors(self):
    self.assertEqual(raster.RenderConfig().resolved_backend(),
                     'pallas' if jax.default_backend() == 'gpu' else 'jax')
    # Triton needs power-of-two blocks: 'auto' keeps 12-px tiles on JAX.
    self.assertEqual(raster.RenderConfig(
      tile_size=12, subtile_size=None).resolved_backend(), 'jax')
    g = test_util.random_gaussians(jax.random.PRNGKey(0), 10)
    cam = _camera(32, 24)
    # Two pixels per thread in both kernels.
    self.assertEqual(raster.RenderConfig().resolved_pallas(), (32, 1, 1))
    self.assertEqual(raster.RenderConfig(
      subtile_size=None, pallas_block=8).resolved_pallas(), (8, 4, 4))
    self.assertEqual(raster.RenderConfig(
      subtile_size=2, pallas_num_warps=4).resolved_pallas(), (32, 4, 4))
    self.assertEqual(raster.RenderConfig(subtile_size=4).resolved_pallas(),
                     (32, 1, 1))
    bad = [raster.RenderConfig(backend='cuda'),
           dataclasses.replace(_PALLAS, pallas_block=48),
           dataclasses.replace(_PALLAS, tile_size=12, subtile_size=None)]
    if jax.default_backend() != 'gpu':
      bad.append(raster.RenderConfig(backend='pallas'))
    for cfg in bad:
      with self.subTest(str(cfg)):
        with self.assertRaises(ValueError):
          raster.render(g, cam, config=cfg)

  def test_kernels_lower_to_triton(self):
    # Lowering for CUDA runs the Pallas Triton lowering (Triton IR, with its
    # power-of-two and indexing rules) on any host; only compiling needs a
    # GPU. On a GPU the kernels are lowered for it as they are (jax 0.11.2
    # there refuses lowering_platforms without an abstract device) and also
    # compiled and run: finite outputs and gradients. (JAX 0.12 lowers them
    # for CUDA on a host without a GPU only for an abstract GPU device:
    # platforms.every_platform gives one.)
    on_gpu = jax.default_backend() == 'gpu'
    cfg = dataclasses.replace(_PALLAS, interpret=False)
    tx, ty, K, cap = 3, 2, 50, 1024
    gid = jnp.zeros((cap,), jnp.int32)
    ranges = jnp.zeros((tx * ty * 4 + 1,), jnp.int32)

    def f(feat):
      log_t, acc = pallas_raster.rasterize(feat, gid, ranges, tx, ty, cfg)
      return jnp.sum(log_t) + jnp.sum(acc)

    feat = jnp.zeros((K, 10), jnp.float32)
    for fn in (f, jax.grad(f)):
      if on_gpu:
        lowered = jax.jit(fn).trace(feat).lower()
      else:  # for the abstract GPU JAX 0.12's lowering asks for
        with platforms.every_platform():
          lowered = jax.jit(fn).trace(feat).lower(
            lowering_platforms=('cuda',))
      self.assertIn('triton', lowered.as_text())
      if on_gpu:
        out = lowered.compile()(feat)
        self.assertTrue(np.all(np.isfinite(np.asarray(out))))


if __name__ == '__main__':
  absltest.main()
