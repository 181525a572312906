"""Tests for Niantic .spz reading and writing (physsplat_jax.io.spz).

The reference files in tests/data/*.spz were written by Niantic's own
library (physsplat_jax/data/README.md): reading them checks our reader
against the reference without installing it.
"""

import gzip
import pathlib
import struct
import tempfile
from unittest import mock

import jax
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax import gaussians as gs
from physsplat_jax import test_util
from physsplat_jax.io import ply
from physsplat_jax.io import scene as scene_io
from physsplat_jax.io import spz
from physsplat_jax.types import Gaussians

REPO = pathlib.Path(__file__).resolve().parents[1]
DATA = REPO / 'tests' / 'data'
DONUT = REPO / 'physsplat_jax' / 'data' / 'scenes' / 'donut.ply'
# Quantisation: half a step of each field (the writer rounds to nearest),
# plus float32 rounding.
POS_HALF_STEP = 0.5 / 4096 + 1e-6
LOG_SCALE_HALF_STEP = 0.5 / 16 + 1e-6
ALPHA_HALF_STEP = 0.5 / 255 + 1e-6
DC_HALF_STEP = 0.5 / (0.15 * 255) + 1e-6
# SH: round(x * 128), then snapped to a bucket of 8 (degree 1) or 16 bytes.
SH1_MAX_ERR = (0.5 + 4) / 128 + 1e-6
SH23_MAX_ERR = (0.5 + 8) / 128 + 1e-6
# Rotation angle between quaternions: 9-bit smallest three (version 3, max
# 0.2 degrees seen) and 8-bit xyz with w rebuilt (version 2: large where w
# is near 0).
ROT_DEG_V3 = 0.25
ROT_DEG_V2 = 12.0


def _np(g: Gaussians):
  return jax.tree.map(np.asarray, g)


def _sub(g: Gaussians, s) -> Gaussians:
  return Gaussians(means=g.means[s], log_scales=g.log_scales[s],
                   quats=g.quats[s], opacity_logits=g.opacity_logits[s],
                   sh=g.sh[s])


def _rot_deg(qa, qb) -> np.ndarray:
  ra, rb = gs.quat_to_rotmat_np(qa), gs.quat_to_rotmat_np(qb)
  c = (np.trace(np.einsum('kji,kjl->kil', ra, rb), axis1=1, axis2=2) - 1) / 2
  return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _in_range(g: Gaussians) -> Gaussians:
  """g with every field inside the .spz ranges (nothing clamped)."""
  g = _np(g)
  return g.replace(log_scales=np.clip(g.log_scales, -9.9, 5.9),
                   sh=np.clip(g.sh, -0.99, 0.99))


class SpzTest(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    self.tmp = pathlib.Path(tmp.name)

  def assert_close_to(self, want: Gaussians, got: Gaussians, version=3):
    """got within the quantisation of want (fields inside the ranges)."""
    want, got = _np(want), _np(got)
    sig = lambda x: 1 / (1 + np.exp(-np.asarray(x, np.float64)))
    err = lambda a, b: float(np.max(np.abs(a - b)))
    self.assertLessEqual(err(want.means, got.means), POS_HALF_STEP)
    s = (want.log_scales >= -10) & (want.log_scales <= 5.9375)
    self.assertLessEqual(err(want.log_scales[s], got.log_scales[s]),
                         LOG_SCALE_HALF_STEP)
    self.assertLessEqual(err(sig(want.opacity_logits),
                             sig(got.opacity_logits)), ALPHA_HALF_STEP)
    dc = np.abs(want.sh[:, 0]) <= 0.5 / 0.15
    self.assertLessEqual(err(want.sh[:, 0][dc], got.sh[:, 0][dc]),
                         DC_HALF_STEP)
    self.assertEqual(want.sh.shape, got.sh.shape)
    if want.sh.shape[1] > 1:
      ok = np.abs(want.sh) <= 127 / 128
      d = np.abs(want.sh - got.sh)
      self.assertLessEqual(d[:, 1:4][ok[:, 1:4]].max(), SH1_MAX_ERR)
      if want.sh.shape[1] > 4:
        self.assertLessEqual(d[:, 4:][ok[:, 4:]].max(), SH23_MAX_ERR)
    rot = _rot_deg(want.quats, got.quats).max()
    self.assertLessEqual(rot, ROT_DEG_V3 if version >= 3 else ROT_DEG_V2)

  # Round trips ---------------------------------------------------------

  @parameterized.product(degree=(0, 1, 2, 3), version=(2, 3))
  def test_round_trip(self, degree, version):
    g = _in_range(test_util.random_gaussians(jax.random.PRNGKey(degree),
                                             300, degree))
    path = self.tmp / 'a.spz'
    spz.save_spz(path, g, version=version)
    self.assertEqual(path.read_bytes()[:2], b'\x1f\x8b')
    h = spz.read_spz_header(path)
    self.assertEqual((h.version, h.num_points, h.sh_degree,
                      h.fractional_bits, h.antialiased),
                     (version, 300, degree, 12, False))
    back = spz.load_spz(path)
    self.assert_close_to(g, back, version)
    # Decoded values lie on the grid: encoding them again changes nothing
    # (a rotation may change its largest component, not its value).
    again = _np(spz.decode_spz(spz.encode_spz(back, version=version)))
    back = _np(back)
    for name in ('means', 'log_scales', 'opacity_logits', 'sh'):
      np.testing.assert_array_equal(getattr(again, name), getattr(back, name))
    self.assertLess(_rot_deg(again.quats, back.quats).max(),
                    ROT_DEG_V3 if version >= 3 else ROT_DEG_V2)

  def test_stored_frame_is_rub_and_flips_back(self):
    g = _in_range(test_util.random_gaussians(jax.random.PRNGKey(1), 50, 3))
    rub = spz.decode_spz(spz.encode_spz(g), stored_frame='RDF')
    # Read without converting back: a 180-degree turn about x.
    np.testing.assert_allclose(np.asarray(rub.means),
                               np.asarray(g.means) * [1, -1, -1],
                               atol=POS_HALF_STEP)
    flip = np.diag([1.0, -1.0, -1.0])
    turned = flip @ gs.quat_to_rotmat_np(np.asarray(g.quats)) @ flip
    np.testing.assert_array_less(
      _rot_deg(gs.rotmat_to_quat(turned), rub.quats), ROT_DEG_V3)
    # The SH signs turn the colour field with the scene: the colour seen
    # along -d' (turned) equals the one seen along d before.
    d = np.random.default_rng(0).normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    before = np.asarray(gs.eval_sh(np.asarray(g.sh), d))
    after = np.asarray(gs.eval_sh(np.asarray(rub.sh), d * [1, -1, -1]))
    np.testing.assert_allclose(after, before, atol=0.15)
    self.assertGreater(np.abs(before - np.asarray(
      gs.eval_sh(np.asarray(rub.sh), d))).max(), 0.15)
    # Unconverted on both ends is a plain round trip.
    same = spz.decode_spz(spz.encode_spz(g, stored_frame='RDF'),
                          stored_frame='RDF')
    self.assert_close_to(g, same)

  @parameterized.parameters('LDB', 'RDB', 'LUB', 'LDF', 'LUF', 'RUF')
  def test_every_standard_system_round_trips(self, system):
    g = _in_range(test_util.random_gaussians(jax.random.PRNGKey(3), 40, 3))
    back = spz.decode_spz(spz.encode_spz(g, stored_frame=system),
                          stored_frame=system)
    self.assert_close_to(g, back)

  def test_sh_signs_reflect_the_colour_field(self):
    # For a flip F of the axes, eval_sh(sh', F d) == eval_sh(sh, d): the
    # reference's per-coefficient signs agree with our SH basis.
    rng = np.random.default_rng(2)
    sh = rng.normal(size=(20, 16, 3))
    d = rng.normal(size=(20, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    for system in spz.SYSTEMS[1:9]:
      fp, _, fsh = spz._flips(system)
      flipped = sh.copy()
      flipped[:, 1:] *= fsh[:, None]
      np.testing.assert_allclose(gs.eval_sh(flipped, d * fp),
                                 gs.eval_sh(sh, d), atol=1e-5,
                                 err_msg=system)

  def test_version_1_float16_positions(self):
    # Version 1 (never released, still read by the reference): float16
    # positions and 3-byte rotations. Built by hand.
    means = np.array([[0.5, -1.25, 3.0], [100.0, 0.0, -0.001]], np.float16)
    body = [means.tobytes(), bytes([255, 0]), bytes([128] * 6),
            bytes([160] * 6), bytes([128, 128, 128, 255, 128, 128])]
    raw = struct.pack('<IIIBBBB', spz.MAGIC, 1, 2, 0, 12, 0, 0)
    g = _np(spz.decode_spz(gzip.compress(raw + b''.join(body)),
                           stored_frame='RDF'))
    np.testing.assert_array_equal(g.means, means.astype(np.float32))
    np.testing.assert_allclose(g.log_scales, 0.0)
    np.testing.assert_allclose(g.quats, [[1, 0, 0, 0], [0, 1, 0, 0]],
                               atol=0.01)
    self.assertGreater(g.opacity_logits[0], 6)
    self.assertLess(g.opacity_logits[1], -6)

  def test_antialiased_flag(self):
    g = test_util.random_gaussians(jax.random.PRNGKey(0), 5)
    path = self.tmp / 'aa.spz'
    spz.save_spz(path, g, antialiased=True)
    self.assertTrue(spz.read_spz_header(path).antialiased)
    with self.assertLogs(level='WARNING') as logs:
      spz.load_spz(path)
    self.assertIn("rasterize_mode='antialiased'", logs.output[0])

  def test_fractional_bits_widen_the_range(self):
    g = test_util.random_gaussians(jax.random.PRNGKey(0), 5)
    g = g.replace(means=g.means * 0 + np.array([3000.0, -2.0, 0.5]))
    with self.assertRaisesRegex(
        spz.SpzError, r'a\.spz: Gaussian 0 at \[3000.0, -2.0, 0.5\] \(5 in '
        r'all\) lies outside .* \+-2048 .* pass fractional_bits=11'):
      spz.save_spz(self.tmp / 'a.spz', g)
    self.assertFalse((self.tmp / 'a.spz').exists())
    spz.save_spz(self.tmp / 'a.spz', g, fractional_bits=11)
    back = spz.load_spz(self.tmp / 'a.spz')
    np.testing.assert_allclose(back.means, g.means, atol=0.5 / 2048)

  # Niantic's files -----------------------------------------------------

  @parameterized.parameters(('donut_every46_v3.spz', 3),
                            ('donut_every46_v2.spz', 2))
  def test_reference_file_matches_the_donut_ply(self, name, version):
    want = _sub(ply.load_ply(DONUT), slice(None, None, 46))
    self.assertEqual(spz.read_spz_header(DATA / name).version, version)
    self.assert_close_to(want, spz.load_spz(DATA / name), version)

  def test_reference_file_with_sh_degree_3(self):
    want = _sub(ply.load_ply(DATA / 'udon_crop.ply'), slice(None, None, 4))
    got = spz.load_spz(DATA / 'udon_every4_v3.spz')
    self.assertEqual(got.sh_degree, 3)
    self.assert_close_to(want, got)

  def test_our_writer_matches_the_reference_bytes(self):
    # The payload Niantic's writer made from the same PLY (RUB, version 3).
    g = _sub(ply.load_ply(DATA / 'udon_crop.ply'), slice(None, None, 4))
    ref = gzip.decompress((DATA / 'udon_every4_v3.spz').read_bytes())
    with self.assertLogs(level='WARNING'):  # (some values are clamped)
      ours = gzip.decompress(spz.encode_spz(g))
    self.assertEqual(ours, ref)

  def test_unconverted_file_needs_stored_frame(self):
    # Niantic's ply_to_spz stores the PLY's RDF data as it is.
    want = _sub(ply.load_ply(DONUT), slice(None, None, 46))
    path = DATA / 'donut_every46_unconverted_v3.spz'
    self.assert_close_to(want, spz.load_spz(path, stored_frame='RDF'))
    turned = _np(spz.load_spz(path))
    np.testing.assert_allclose(turned.means, _np(want).means * [1, -1, -1],
                               atol=POS_HALF_STEP)

  def test_version_4(self):
    path = DATA / 'udon_every4_v4.spz'
    self.assertEqual(spz.read_spz_header(path).version, 4)
    if spz._zstd_decompress() is None:
      with self.assertRaisesRegex(
          spz.SpzError, r'udon_every4_v4\.spz: \.spz version 4 .*zstd.*'
          r'pip install zstandard'):
        spz.load_spz(path)
    else:
      v3 = _np(spz.load_spz(DATA / 'udon_every4_v3.spz'))
      v4 = _np(spz.load_spz(path))
      for name in ('means', 'log_scales', 'quats', 'opacity_logits', 'sh'):
        np.testing.assert_array_equal(getattr(v4, name), getattr(v3, name))

  def test_version_4_container_without_zstd(self):
    """The version 4 container (header, extension records, table of
    contents, a stream per attribute) parsed with the codec replaced by
    the identity: the udon crop's version 3 payload, re-packed as raw
    streams with a coordinate-system extension (LUF, read back into RDF),
    decodes as the version 3 file re-framed. (Runs without zstd.)"""
    raw = gzip.decompress((DATA / 'udon_every4_v3.spz').read_bytes())
    _, _, n, deg, fb, flags, _ = struct.unpack_from('<IIIBBBB', raw)
    h = spz.SpzHeader(4, n, deg, fb, False, True)
    streams, o = [], 16
    for size in spz._sizes(h):
      if size:
        streams.append(raw[o:o + size])
      o += size
    ext = struct.pack('<III', spz.EXT_COORDINATE_SYSTEM, 4,
                      spz.SYSTEMS.index('LUF'))
    toc = 32 + len(ext)
    data = (struct.pack('<IIIBBBBI12x', spz.MAGIC, 4, n, deg, fb, flags | 2,
                        len(streams), toc) + ext
            + b''.join(struct.pack('<QQ', len(x), len(x)) for x in streams)
            + b''.join(streams))
    with mock.patch.object(spz, '_zstd_decompress',
                           lambda: (lambda b, size: b)):
      v4 = _np(spz.decode_spz(data, 'v4.spz'))
      with self.assertRaisesRegex(spz.SpzError, r'v4\.spz: truncated'):
        spz.decode_spz(data[:-10], 'v4.spz')
    v3 = _np(spz.decode_spz((DATA / 'udon_every4_v3.spz').read_bytes(),
                            stored_frame='LUF'))
    for name in ('means', 'log_scales', 'quats', 'opacity_logits', 'sh'):
      np.testing.assert_array_equal(getattr(v4, name), getattr(v3, name),
                                    err_msg=name)
    # (and LUF is not RUB: the extension was read)
    rub = _np(spz.load_spz(DATA / 'udon_every4_v3.spz'))
    self.assertGreater(float(np.abs(v4.means - rub.means).max()), 1e-3)

  def test_load_scene(self):
    sc = scene_io.load_scene(DATA / 'donut_every46_v3.spz', num_cameras=1)
    self.assertEqual(sc.gaussians.num, 992)
    self.assertEqual(sc.objects[0].name, 'donut_every46_v3')

  # Bad input -----------------------------------------------------------

  def _bad(self, data: bytes, pattern: str, name='bad.spz'):
    path = self.tmp / name
    path.write_bytes(data)
    with self.assertRaisesRegex(spz.SpzError, f'{name}: {pattern}'):
      spz.load_spz(path)

  def test_bad_files(self):
    good = gzip.decompress((DATA / 'udon_every4_v3.spz').read_bytes())
    head = lambda **kw: struct.pack(
      '<IIIBBBB', kw.get('magic', spz.MAGIC), kw.get('version', 3),
      kw.get('n', 539), kw.get('deg', 3), 12, 0, 0)
    self._bad(b'hello world', r'not a \.spz file: neither gzip')
    self._bad(DONUT.read_bytes()[:4000], r'not a \.spz file: a PLY file')
    self._bad(gzip.compress(head(magic=0x12345678) + good[16:]),
              r'not a \.spz file: magic 0x12345678, expected 0x5053474e')
    self._bad(gzip.compress(head(version=7) + good[16:]),
              r'unsupported \.spz version 7; this reader reads versions '
              r'1, 2, 3, 4')
    self._bad(gzip.compress(head(deg=4) + good[16:]),
              r'SH degree 4; .* re-export the scene with SH degree 3')
    self._bad(gzip.compress(good[:-100]),
              r'truncated \.spz payload: 539 Gaussians of SH degree 3 '
              r'\(version 3\) need \d+ bytes .* copy the file again')
    self._bad((DATA / 'udon_every4_v3.spz').read_bytes()[:-50],
              r'corrupt \.spz: the gzip stream does not decompress')
    self._bad(gzip.compress(good[:10]), r'truncated \.spz: .* 16-byte')

  def test_bad_writes(self):
    g = test_util.random_gaussians(jax.random.PRNGKey(0), 6, 1)
    for field, value in (('means', np.nan), ('log_scales', np.inf)):
      a = np.array(getattr(g, field)).copy()
      a[2, 0] = value
      with self.assertRaisesRegex(
          spz.SpzError, r'n\.spz: refusing to write non-finite values .*1 '
          r'rows.*before saving a \.spz'):
        spz.save_spz(self.tmp / 'n.spz', g.replace(**{field: a}))
    self.assertFalse((self.tmp / 'n.spz').exists())
    with self.assertRaisesRegex(spz.SpzError, r'version 4 needs zstd'):
      spz.encode_spz(g, version=4)
    with self.assertRaisesRegex(spz.SpzError, r'sh1_bits=9'):
      spz.encode_spz(g, sh1_bits=9)
    with self.assertRaisesRegex(spz.SpzError, r"stored_frame='XYZ'"):
      spz.encode_spz(g, stored_frame='XYZ')
    # Huge SH values clamp to their own end of the range (they were cast
    # to integers first and wrapped to the other sign).
    sh = np.array(g.sh).copy()
    sh[0, 1, 0], sh[1, 1, 0] = -1e20, 1e20
    with self.assertLogs(level='WARNING'):
      back = spz.decode_spz(spz.encode_spz(g.replace(sh=sh)))
    self.assertLessEqual(float(back.sh[0, 1, 0]), -0.9)
    self.assertGreaterEqual(float(back.sh[1, 1, 0]), 0.9)
    with self.assertRaisesRegex(spz.SpzError, r'compress_level=0; give a '
                                r'whole number in 1\.\.9'):
      spz.encode_spz(g, compress_level=0)
    # The level changes the gzip stream only, not what it holds.
    fast, small = (spz.encode_spz(g, compress_level=k) for k in (1, 9))
    self.assertNotEqual(fast, small)
    self.assertEqual(gzip.decompress(fast), gzip.decompress(small))


if __name__ == '__main__':
  absltest.main()
