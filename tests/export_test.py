"""Tests for physsplat_jax.io.export: deformed Gaussians -> PLY/.splat/.spz.

The central check: rendering the exported-and-reloaded file equals rendering
the deformed Gaussians directly (covariances F Sigma F^T plus view rotations)
within float tolerance; a rigid motion gives rotated quaternions and the rest
scales; rotations are always proper."""

import os
import shutil
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from physsplat_jax import cameras
from physsplat_jax import deform
from physsplat_jax import gaussians as gs
from physsplat_jax import test_util
from physsplat_jax.io import export
from physsplat_jax.io import ply
from physsplat_jax.io import splat
from physsplat_jax.io import spz
from physsplat_jax.render import images
from physsplat_jax.types import make_camera

# float32 PLY + least-squares SH rotation vs the direct render.
_IMAGE_TOL = 3e-4
_COV_RTOL = 1e-5
# .spz quantisation (tests/spz_test.py): half a position step (12 fraction
# bits), degree 2-3 SH in buckets of 16/128 (+ rounding), rotations 0.25 deg.
_SPZ_POS_HALF_STEP = 0.5 / 4096 + 1e-6
_SPZ_SH23_MAX_ERR = (0.5 + 8) / 128 + 1e-6
_SPZ_ROT_DEG = 0.25


def _scene(num=120, degree=3, seed=0):
  g = test_util.random_gaussians(jax.random.PRNGKey(seed), num,
                                 sh_degree=degree)
  return g.replace(log_scales=g.log_scales + 1.0)


def _camera():
  vm = cameras.look_at(np.array([0.5, -3.5, 1.0]), np.zeros(3))
  return make_camera(vm, 60.0, 60.0, 64, 48)


def _random_rotations(rng, n):
  q = rng.normal(size=(n, 4))
  return np.asarray(gs.quat_to_rotmat(jnp.asarray(q)), np.float64)


class ExportRenderTest(absltest.TestCase):

  def setUp(self):
    super().setUp()
    self.dir = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, self.dir, ignore_errors=True)

  def test_reloaded_ply_renders_like_the_deformed_gaussians(self):
    g = _scene()
    K = g.num
    rng = np.random.default_rng(1)
    # Per-Gaussian deformation F = Q (I + A): rotation times a moderate
    # stretch/shear, and a smooth displacement of the centres.
    Q = _random_rotations(rng, K)
    A = 0.3 * rng.normal(size=(K, 3, 3))
    F = Q @ (np.eye(3) + A)
    F[np.linalg.det(F) < 0] *= -1.0  # keep det F > 0 (physical)
    F = jnp.asarray(F, jnp.float32)
    covs = F @ g.covariances @ jnp.swapaxes(F, 1, 2)
    R = deform.polar_rotation(F)
    means = g.means + 0.1 * jnp.sin(3.0 * g.means[:, ::-1])
    cam = _camera()
    direct = images.render_image(g.replace(means=means), cam,
                                 covariances=covs, view_rotations=R,
                                 background=(0.2, 0.3, 0.4))
    path = os.path.join(self.dir, 'f.ply')
    written = export.save_deformed_ply(path, g, means, covs, R)
    # Exact INRIA layout: 62 float properties, normals first after xyz.
    names = [p.name for p in ply.read_ply_header(path).element('vertex')
             .properties]
    self.assertLen(names, 62)
    self.assertEqual(names[:6], ['x', 'y', 'z', 'nx', 'ny', 'nz'])
    back = ply.load_ply(path)
    np.testing.assert_array_equal(back.quats, written.quats)
    dets = np.linalg.det(np.asarray(back.rotations, np.float64))
    np.testing.assert_allclose(dets, 1.0, atol=1e-5)
    np.testing.assert_allclose(back.covariances, covs, rtol=_COV_RTOL,
                               atol=_COV_RTOL * float(jnp.abs(covs).max()))
    # One compiled render for all three (same argument structure).
    eye = jnp.broadcast_to(jnp.eye(3), (K, 3, 3))
    view = lambda h: images.render_image(
      h.replace(normals=None), cam, covariances=h.covariances,
      view_rotations=eye, background=(0.2, 0.3, 0.4))
    out = view(back)
    self.assertGreater(float(out.alpha.max()), 0.9)
    np.testing.assert_allclose(out.image, direct.image, atol=_IMAGE_TOL,
                               err_msg='mismatch: exported render')
    # Without the SH rotation the view-dependent colours differ.
    plain = export.deformed_gaussians(g, means, covs, R, rotate_colors=False)
    out2 = view(jax.tree.map(jnp.asarray, plain))
    self.assertGreater(np.abs(out2.image - direct.image).max(), 1e-2)

  def test_rigid_motion_through_deform_gives_rotated_quaternions(self):
    g = _scene(num=60, degree=1, seed=2)
    rng = np.random.default_rng(3)
    # Distinct scales per Gaussian so the axes are well defined.
    g = g.replace(log_scales=jnp.asarray(
      np.log([0.02, 0.05, 0.1]) + rng.uniform(0, 0.3, (g.num, 1)),
      jnp.float32))
    drivers = rng.uniform(-1.2, 1.2, size=(40, 3))
    bind = deform.make_binding(np.asarray(g.means), drivers, k=8)
    Rq = np.array([0.6, -0.2, 0.7, 0.3])
    Rq /= np.linalg.norm(Rq)
    Rm = np.asarray(gs.quat_to_rotmat(jnp.asarray(Rq)), np.float64)
    t = np.array([0.3, -0.1, 0.2])
    moved = jnp.asarray(drivers @ Rm.T + t, jnp.float32)
    means, covs, R = deform.deform(bind, g, moved)
    np.testing.assert_allclose(R, np.broadcast_to(Rm, R.shape), atol=1e-4)
    out = export.deformed_gaussians(g, means, covs, R)
    want = np.array(gs.quat_multiply(jnp.asarray(Rq, jnp.float32),
                                       gs.normalize_quat(g.quats)))
    want *= np.where(want[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(out.quats, want, atol=1e-3)
    np.testing.assert_allclose(out.log_scales, g.log_scales, atol=1e-3)
    np.testing.assert_allclose(out.means, np.asarray(g.means) @ Rm.T + t,
                               atol=1e-4)
    # No Gaussians (an object emptied by a crop): an empty result, not
    # range()'s 'arg 3 must not be zero'.
    empty = export.deformed_gaussians(g.subset(np.zeros(g.num, bool)),
                                      means[:0], covs[:0], R[:0])
    self.assertEqual((empty.num, empty.sh.shape), (0, (0,) + g.sh.shape[1:]))


class SpzExportTest(absltest.TestCase):
  """save_deformed_spz writes the Gaussians of save_deformed_ply (SH
  rotated), quantised as .spz."""

  def setUp(self):
    super().setUp()
    self.dir = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, self.dir, ignore_errors=True)

  def test_spz_holds_the_deformed_gaussians_with_rotated_sh(self):
    g = _scene(num=60, degree=3, seed=5)
    # (a rotation mixes a band's coefficients: up to sqrt(7) times the
    # largest, still inside the .spz range of +-127/128)
    g = g.replace(sh=jnp.clip(g.sh, -0.35, 0.35))
    K = g.num
    rng = np.random.default_rng(2)
    F = _random_rotations(rng, K) @ (np.eye(3) + 0.2 * rng.normal(
      size=(K, 3, 3)))
    F[np.linalg.det(F) < 0] *= -1.0
    F = jnp.asarray(F, jnp.float32)
    covs = F @ g.covariances @ jnp.swapaxes(F, 1, 2)
    R = deform.polar_rotation(F)
    means = g.means + 0.1
    path = os.path.join(self.dir, 'f.spz')
    written = export.save_deformed_spz(path, g, means, covs, R)
    want = export.deformed_gaussians(g, means, covs, R)  # the PLY's
    np.testing.assert_array_equal(written.sh, want.sh)
    back = spz.load_spz(path)
    # Exactly the encoding of those Gaussians, within the steps.
    again = spz.decode_spz(spz.encode_spz(want))
    for name in ('means', 'log_scales', 'quats', 'opacity_logits', 'sh'):
      np.testing.assert_array_equal(getattr(back, name),
                                    getattr(again, name), err_msg=name)
    self.assertLessEqual(np.abs(back.means - want.means).max(),
                         _SPZ_POS_HALF_STEP)
    sh_err = np.abs(np.asarray(back.sh) - want.sh)
    self.assertLessEqual(sh_err.max(), _SPZ_SH23_MAX_ERR)
    # The rotated SH, not the rest ones: those differ by more.
    self.assertGreater(np.abs(np.asarray(back.sh) - g.sh).max(),
                       3 * _SPZ_SH23_MAX_ERR)
    ra = gs.quat_to_rotmat_np(np.asarray(back.quats))
    rb = gs.quat_to_rotmat_np(want.quats)
    cos = (np.trace(np.swapaxes(ra, 1, 2) @ rb, axis1=1, axis2=2) - 1) / 2
    self.assertLessEqual(np.degrees(np.arccos(np.clip(cos, -1, 1))).max(),
                         _SPZ_ROT_DEG)
    # sh_degree truncates: the degree-1 file holds the same first band.
    one = os.path.join(self.dir, 'one.spz')
    export.save_deformed_spz(one, g, means, covs, R, sh_degree=1)
    self.assertEqual(spz.read_spz_header(one).sh_degree, 1)
    np.testing.assert_array_equal(spz.load_spz(one).sh, back.sh[:, :4])

  def test_centres_beyond_the_default_range_get_fewer_fraction_bits(self):
    g = _scene(num=8, degree=0, seed=3)
    means = g.means + 5000.0  # beyond +-2048 of 12 fraction bits
    path = os.path.join(self.dir, 'far.spz')
    export.save_deformed_spz(path, g, means, g.covariances)
    bits = spz.read_spz_header(path).fractional_bits
    self.assertEqual(bits, 10)  # range +-8192
    np.testing.assert_allclose(spz.load_spz(path).means, means,
                               atol=0.5 * 2.0 ** -bits + 1e-3)
    with self.assertRaisesRegex(export.ExportError, 'fractional_bits=12'):
      export.save_deformed_spz(path, g, means, g.covariances,
                               fractional_bits=12)

  def test_bad_options_are_export_errors_before_any_file(self):
    g = _scene(num=4, degree=1, seed=2)
    d = os.path.join(self.dir, 'spz')
    for kwargs, msg in ((dict(level=9), 'unknown .spz option.* level'),
                        (dict(version=4), 'version 4'),
                        (dict(sh1_bits=0), 'sh1_bits=0'),
                        (dict(sh_degree=4), 'sh_degree must be 0..3')):
      with self.assertRaisesRegex(export.ExportError, msg):
        export.DeformedFrameWriter(d, g, format='spz', **kwargs)
      with self.assertRaisesRegex(export.ExportError, msg):
        export.save_deformed_spz(os.path.join(d, 'a.spz'), g, g.means,
                                 g.covariances, **kwargs)
    self.assertFalse(os.path.exists(d))


class DecompositionTest(absltest.TestCase):

  def test_rotations_are_always_proper(self):
    rng = np.random.default_rng(5)
    n = 400
    F = rng.normal(size=(n, 3, 3))
    F[:50] = -F[:50]  # reflections (det F < 0)
    F[50:100, :, 2] = 0.0  # flattened (rank 2)
    F[100:120] = 0.0  # collapsed (rank 0)
    F[120:150] = np.eye(3) * rng.uniform(0.1, 2, (30, 1, 1))  # isotropic
    F[150:200, :, 1:] *= 1e-4  # needle, near singular
    S = np.diag([0.01, 0.02, 0.03])
    C = F @ S @ np.swapaxes(F, 1, 2)
    for ref in (None, _random_rotations(rng, n)):
      if ref is not None:
        ref[:25] *= -1.0  # the reference itself may be a reflection
      log_s, V = export.decompose_aligned(C, ref)
      self.assertTrue(np.all(np.isfinite(log_s)))
      np.testing.assert_allclose(np.linalg.det(V), 1.0, atol=1e-9)
      np.testing.assert_allclose(np.swapaxes(V, 1, 2) @ V,
                                 np.broadcast_to(np.eye(3), V.shape),
                                 atol=1e-9)
      rec = V @ (np.exp(2 * log_s)[:, :, None] * np.swapaxes(V, 1, 2))
      scale = np.abs(C).max(axis=(1, 2)) + 1e-18
      err = np.abs(rec - C).max(axis=(1, 2)) / scale
      ok = np.ones(n, bool)
      ok[100:120] = False  # zero matrices come back at the variance floor
      self.assertLess(err[ok].max(), 1e-9)
      np.testing.assert_allclose(log_s[100:120], 0.5 * np.log(1e-20))
    # NumPy quaternion twins agree with the JAX ones.
    q = export.rotmat_to_quat_np(V)
    np.testing.assert_allclose(export.quat_to_rotmat_np(q), V, atol=1e-12)
    np.testing.assert_allclose(
      q, gs.rotmat_to_quat(jnp.asarray(V, jnp.float32)), atol=1e-5)
    # gaussians.decompose_covariance also reconstructs them (float64).
    with jax.enable_x64(True):
      ls2, q2 = gs.decompose_covariance(jnp.asarray(C))
      rec2 = np.asarray(gs.covariance(ls2, q2))
    np.testing.assert_allclose(rec2[ok], C[ok], atol=1e-12)

  def test_non_finite_and_shape_errors(self):
    g = _scene(num=4, degree=0)
    covs = np.asarray(g.covariances).copy()
    covs[2, 0, 0] = np.nan
    with self.assertRaisesRegex(export.ExportError, r'first: \[2\]'):
      export.deformed_gaussians(g, g.means, covs)
    with self.assertRaisesRegex(export.ExportError, r'means has shape'):
      export.deformed_gaussians(g, g.means[:3], g.covariances)


class ThinGaussiansTest(absltest.TestCase):
  """At rest the exported file is the input, thin Gaussians included."""

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    import physsplat_jax

    g = physsplat_jax.load_scene('tabletop').gaussians
    ls = np.array(g.log_scales)
    ls[::3, 2] = -11.4  # every third Gaussian a thin disc
    cls.g = g.replace(log_scales=jnp.asarray(ls, jnp.float32))
    cls.tmp = tempfile.mkdtemp()

  @classmethod
  def tearDownClass(cls):
    shutil.rmtree(cls.tmp)
    super().tearDownClass()

  def test_tabletop_at_rest_round_trips(self):
    g = self.g
    # Drivers: every 8th Gaussian centre (PGAS-like density), k = 8.
    drivers = np.asarray(g.means)[::8]
    bind = deform.make_binding(g.means, drivers, k=8)
    x = jnp.asarray(drivers, jnp.float32)
    _, F = jax.jit(deform.local_deformation)(bind, x)
    np.testing.assert_allclose(F, np.broadcast_to(np.eye(3), F.shape),
                               atol=1e-5)
    means, covs, rots = jax.jit(deform.deform)(bind, g, x)
    for name, kw in (('cov', {}), ('F', dict(deformation=F))):
      path = os.path.join(self.tmp, f'{name}.ply')
      export.save_deformed_ply(path, g, means, covs, rots, sh_degree=None,
                               **kw)
      back = ply.load_ply(path)
      np.testing.assert_allclose(back.log_scales, g.log_scales, atol=1e-4,
                                 err_msg=name)
      self.assertEqual(float(np.min(back.log_scales)), np.float32(-11.4))
      q0 = np.asarray(gs.normalize_quat(g.quats))
      np.testing.assert_allclose(np.abs(np.sum(back.quats * q0, 1)), 1.0,
                                 atol=1e-5, err_msg=name)
      np.testing.assert_allclose(back.means, g.means, atol=1e-6)
      np.testing.assert_allclose(back.sh, g.sh, atol=1e-5)
      np.testing.assert_array_equal(back.opacity_logits, g.opacity_logits)

  def test_known_affine_from_deformation_is_exact_for_thin(self):
    g = self.g
    rng = np.random.default_rng(0)
    A = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    F = np.broadcast_to(A, (g.num, 3, 3))
    out = export.deformed_gaussians(g, g.means, None, deformation=F)
    Q0 = gs.quat_to_rotmat_np(g.quats)
    s0 = np.exp(np.asarray(g.log_scales, np.float64))
    L = A @ Q0 * s0[:, None, :]
    want = L @ np.swapaxes(L, -1, -2)  # F Sigma F^T in float64
    Q = gs.quat_to_rotmat_np(out.quats)
    got = np.einsum('kai,ki,kbi->kab', Q, np.exp(2.0 * np.asarray(
      out.log_scales, np.float64)), Q)
    # Thin axes: relative accuracy of the smallest variance.
    w_want = np.linalg.svd(L, compute_uv=False)
    np.testing.assert_allclose(np.sort(np.exp(out.log_scales), 1),
                               np.sort(w_want, 1), rtol=1e-5)
    np.testing.assert_allclose(got, want, rtol=1e-4,
                               atol=1e-5 * np.abs(want).max())


class FilesTest(absltest.TestCase):

  def test_frame_writer_and_splat(self):
    d = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, d, ignore_errors=True)
    g = _scene(num=30, degree=0, seed=4)
    T = 3
    shift = jnp.arange(T, dtype=jnp.float32)[:, None, None] * 0.1
    means = g.means[None] + shift
    covs = jnp.broadcast_to(g.covariances, (T,) + g.covariances.shape)
    paths = export.save_deformed_sequence(os.path.join(d, 'ply'), g, means,
                                          covs)
    self.assertEqual([os.path.basename(p) for p in paths],
                     ['frame_0000.ply', 'frame_0001.ply', 'frame_0002.ply'])
    last = ply.load_ply(paths[-1])
    np.testing.assert_allclose(last.means, means[-1], atol=1e-6)
    # No deformation of the covariance: scales and axes are the rest ones.
    np.testing.assert_allclose(last.covariances, g.covariances, atol=1e-7)
    spaths = export.save_deformed_sequence(os.path.join(d, 'splat'), g,
                                           means, covs, format='splat',
                                           sort=False)
    self.assertTrue(spaths[0].endswith('frame_0000.splat'))
    s = splat.load_splat(spaths[1])
    np.testing.assert_allclose(s.means, means[1], atol=1e-6)
    np.testing.assert_allclose(s.log_scales, g.log_scales, atol=1e-5)
    zpaths = export.save_deformed_sequence(os.path.join(d, 'spz'), g, means,
                                           covs, format='spz')
    self.assertTrue(zpaths[2].endswith('frame_0002.spz'))
    np.testing.assert_allclose(spz.load_spz(zpaths[2]).means, means[2],
                               atol=_SPZ_POS_HALF_STEP)
    with self.assertRaisesRegex(export.ExportError, 'format'):
      export.DeformedFrameWriter(d, g, format='glb')


class BadInputTest(absltest.TestCase):
  """Inputs export cannot honour are errors naming the field and the fix,
  raised before any file is written (never floored or -inf scales)."""

  def setUp(self):
    super().setUp()
    self.dir = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, self.dir, ignore_errors=True)
    self.g = _scene(num=6, degree=1, seed=6)
    self.covs = np.asarray(self.g.covariances)

  def test_covariances_that_are_not_psd(self):
    g = self.g
    with self.assertRaisesRegex(
        export.ExportError, r'covariances of 6 Gaussians are not positive '
        r'semi-definite \(first: \[0, 1, 2, 3, 4\]'):
      export.deformed_gaussians(g, g.means, -self.covs)
    covs = self.covs.copy()
    covs[3] = np.diag([1e-3, 1e-3, -1e-3])
    with self.assertRaisesRegex(export.ExportError, r'\(first: \[3\];'):
      export.decompose_aligned(covs)
    # Round-off negatives of a flattened Gaussian are floored as before.
    covs[3] = np.diag([1e-3, 1e-3, -1e-12])
    log_s, _ = export.decompose_aligned(covs)
    self.assertEqual(log_s[3].min(), 0.5 * np.log(export.MIN_VARIANCE))

  def test_min_variance_must_be_positive(self):
    g = self.g
    for v in (0.0, -1.0, np.nan):
      with self.assertRaisesRegex(export.ExportError,
                                  'min_variance must be a positive number'):
        export.deformed_gaussians(g, g.means, 0.0 * self.covs,
                                  min_variance=v)
      with self.assertRaisesRegex(export.ExportError, 'min_variance'):
        export.deformed_gaussians(g, g.means, None, min_variance=v,
                                  deformation=np.zeros((g.num, 3, 3)))

  def test_sequence_lengths_checked_before_writing(self):
    g = self.g
    means = np.stack([np.asarray(g.means)] * 3)
    d = os.path.join(self.dir, 'seq')
    with self.assertRaisesRegex(
        export.ExportError, r'covariances has shape \(2, 6, 3, 3\); '
        r'expected \(3, 6, 3, 3\)'):
      export.save_deformed_sequence(d, g, means, np.stack([self.covs] * 2))
    with self.assertRaisesRegex(export.ExportError, r'rotations has shape'):
      export.save_deformed_sequence(d, g, means, np.stack([self.covs] * 3),
                                    np.zeros((3, 5, 3, 3)))
    with self.assertRaisesRegex(export.ExportError,
                                r'means has shape \(6, 3\); expected'):
      export.save_deformed_sequence(d, g, g.means, self.covs)
    self.assertFalse(os.path.exists(d))

  def test_sh_degree_must_be_0_to_3(self):
    g = self.g
    path = os.path.join(self.dir, 'a.ply')
    for degree in (5, -1, 2.0):
      with self.assertRaisesRegex(export.ExportError,
                                  'sh_degree must be 0..3'):
        export.save_deformed_ply(path, g, g.means, self.covs,
                                 sh_degree=degree)
    with self.assertRaisesRegex(export.ExportError, 'sh_degree must be'):
      export.DeformedFrameWriter(self.dir, g, sh_degree=4)
    self.assertFalse(os.path.exists(path))

  def test_output_paths_that_cannot_be_written(self):
    g = self.g
    folder = os.path.join(self.dir, 'd.ply')
    os.makedirs(folder)
    with self.assertRaisesRegex(export.ExportError,
                                'd.ply: is a directory; give the export'):
      export.save_deformed_ply(folder, g, g.means, self.covs)
    file = os.path.join(self.dir, 'file')
    with open(file, 'w') as fh:
      fh.write('not a folder')
    in_the_way = f"{file} is a file, not a folder; choose another"
    for write in (
        lambda: export.save_deformed_ply(os.path.join(file, 'a.ply'), g,
                                         g.means, self.covs),
        lambda: export.save_deformed_splat(os.path.join(file, 'a.splat'),
                                           g, g.means, self.covs),
        lambda: export.DeformedFrameWriter(os.path.join(file, 'ply'), g)):
      with self.assertRaisesRegex(export.ExportError, in_the_way):
        write()


if __name__ == '__main__':
  absltest.main()
