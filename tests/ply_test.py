"""Tests for 3DGS PLY, compressed PLY and .splat reading and writing."""

import os
import pathlib
import struct
import tempfile
import warnings

import jax
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax import test_util
from physsplat_jax.gaussians import SH_C0
from physsplat_jax.io import ply
from physsplat_jax.io import splat
from physsplat_jax.types import Gaussians

REPO = pathlib.Path(__file__).resolve().parents[1]
SHIPPED = {
  'donut': REPO / 'physsplat_jax' / 'data' / 'scenes' / 'donut.ply',
  'udon_crop': REPO / 'tests' / 'data' / 'udon_crop.ply',
  'train_1000': REPO / 'tests' / 'data' / 'train_1000.ply',
}
# (Gaussians, SH degree, has normals) of the shipped files.
SHIPPED_SHAPES = {
  'donut': (45624, 0, False),
  'udon_crop': (2153, 3, True),
  'train_1000': (1000, 3, True),
}
INRIA_ORDER = (
  ['x', 'y', 'z', 'nx', 'ny', 'nz', 'f_dc_0', 'f_dc_1', 'f_dc_2']
  + [f'f_rest_{i}' for i in range(45)]
  + ['opacity', 'scale_0', 'scale_1', 'scale_2']
  + ['rot_0', 'rot_1', 'rot_2', 'rot_3']
)
# Quantisation steps of the lossy formats.
POS_STEP_10BIT = 1.0 / 1023.0
SH_BYTE_STEP = 8.0 / 256.0
ALPHA_BYTE_STEP = 1.0 / 255.0
QUAT_10BIT_STEP = np.sqrt(2.0) / 1023.0


def _np(g: Gaussians):
  return jax.tree.map(np.asarray, g)


def _assert_gaussians_equal(test, a, b):
  a, b = _np(a), _np(b)
  for name in ('means', 'log_scales', 'quats', 'opacity_logits', 'sh'):
    np.testing.assert_array_equal(
      getattr(a, name), getattr(b, name), err_msg=f'mismatch: {name}'
    )
  test.assertEqual(a.normals is None, b.normals is None)
  if a.normals is not None:
    np.testing.assert_array_equal(a.normals, b.normals)
  test.assertEqual(list(a.extras), list(b.extras))
  for k in a.extras:
    np.testing.assert_array_equal(a.extras[k], b.extras[k], err_msg=k)
    test.assertEqual(a.extras[k].dtype, b.extras[k].dtype)


def _random(num, degree, seed=0, normals=False, extras=None):
  g = test_util.random_gaussians(jax.random.PRNGKey(seed), num, degree)
  if normals:
    n = np.random.default_rng(seed).normal(size=(num, 3)).astype(np.float32)
    g = g.replace(normals=n)
  if extras:
    g = g.replace(extras=extras)
  return g


def _inria_bytes(rows: np.ndarray, names, endian='<', types=None) -> bytes:
  """A PLY written by hand with struct (independent of ply.write_ply)."""
  types = types or ['float'] * len(names)
  code = {'float': 'f', 'double': 'd', 'uchar': 'B', 'int': 'i',
          'float32': 'f', 'uint8': 'B', 'float64': 'd', 'short': 'h'}
  fmt = 'binary_little_endian' if endian == '<' else 'binary_big_endian'
  head = f'ply\nformat {fmt} 1.0\nelement vertex {len(rows)}\n'
  head += ''.join(f'property {t} {n}\n' for t, n in zip(types, names))
  head += 'end_header\n'
  fmt = endian + ''.join(code[t] for t in types)
  cast = [int if code[t] in 'Bih' else float for t in types]
  body = b''.join(
    struct.pack(fmt, *[c(x) for c, x in zip(cast, r)]) for r in rows
  )
  return head.encode() + body


class PlyTest(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    self.tmp = pathlib.Path(tmp.name)

  def _write(self, name, data: bytes):
    p = self.tmp / name
    p.write_bytes(data)
    return p

  # Shipped files ------------------------------------------------------------

  @parameterized.named_parameters(*[(f'_{k}', k) for k in SHIPPED])
  def test_shipped_file_round_trip_is_byte_identical(self, name):
    path = SHIPPED[name]
    g = ply.load_ply(path)
    num, degree, has_normals = SHIPPED_SHAPES[name]
    self.assertEqual(g.num, num)
    self.assertEqual(g.sh_degree, degree)
    self.assertEqual(g.normals is not None, has_normals)
    self.assertEqual(g.means.dtype, np.float32)
    out = self.tmp / 'out.ply'
    ply.save_ply(out, g)
    self.assertEqual(out.read_bytes(), path.read_bytes())
    # ASCII round trip keeps every float32 bit too.
    ply.save_ply(self.tmp / 'a.ply', g, binary=False)
    self.assertEqual(ply.read_ply_header(self.tmp / 'a.ply').format, 'ascii')
    _assert_gaussians_equal(self, ply.load_ply(self.tmp / 'a.ply'), g)

  def test_sh_layout_is_channel_major_on_disk(self):
    path = SHIPPED['udon_crop']
    _, el = ply.read_ply(path)
    v = el['vertex']
    g = _np(ply.load_ply(path))
    for c in range(3):
      np.testing.assert_array_equal(g.sh[:, 0, c], v[f'f_dc_{c}'])
      for k in range(1, 16):
        np.testing.assert_array_equal(
          g.sh[:, k, c], v[f'f_rest_{c * 15 + k - 1}'], err_msg=f'{k},{c}'
        )
    np.testing.assert_array_equal(g.quats[:, 0], v['rot_0'])  # w first
    np.testing.assert_array_equal(g.log_scales[:, 2], v['scale_2'])
    np.testing.assert_array_equal(g.opacity_logits, v['opacity'])
    np.testing.assert_array_equal(g.normals[:, 1], v['ny'])

  def test_load_float64(self):
    with jax.enable_x64(True):
      g = ply.load_ply(SHIPPED['train_1000'], dtype=np.float64)
      self.assertEqual(g.means.dtype, np.float64)
      g32 = _np(ply.load_ply(SHIPPED['train_1000']))
      np.testing.assert_array_equal(np.asarray(g.sh), g32.sh)

  # Format edge cases -------------------------------------------------------

  @parameterized.named_parameters(
    ('_deg0', 0, 0), ('_deg1', 1, 9), ('_deg2', 2, 24), ('_deg3', 3, 45)
  )
  def test_sh_degrees_round_trip(self, degree, num_rest):
    g = _random(7, degree, seed=degree, normals=degree % 2 == 1)
    path = self.tmp / 'g.ply'
    ply.save_ply(path, g)
    header = ply.read_ply_header(path)
    names = header.element('vertex').property_names
    self.assertLen([n for n in names if n.startswith('f_rest_')], num_rest)
    h = ply.load_ply(path)
    self.assertEqual(h.sh_degree, degree)
    _assert_gaussians_equal(self, g, h)
    # Channel-major: f_rest_{c * (B-1) + k - 1} is channel c of coefficient k.
    _, el = ply.read_ply(path)
    nb = (degree + 1) ** 2
    sh = np.asarray(g.sh)
    for k in range(1, nb):
      for c in range(3):
        np.testing.assert_array_equal(
          el['vertex'][f'f_rest_{c * (nb - 1) + k - 1}'], sh[:, k, c]
        )

  def test_full_inria_layout_with_zero_normals(self):
    g = _random(3, 3)
    g = g.replace(normals=np.zeros((3, 3), np.float32))
    ply.save_ply(self.tmp / 'g.ply', g)
    header = ply.read_ply_header(self.tmp / 'g.ply')
    self.assertEqual(list(header.element('vertex').property_names),
                     INRIA_ORDER)
    self.assertEqual(os.path.getsize(self.tmp / 'g.ply'),
                     header.size + 3 * 248)

  def test_big_endian_hand_packed(self):
    names = ['x', 'y', 'z', 'f_dc_0', 'f_dc_1', 'f_dc_2', 'opacity',
             'scale_0', 'scale_1', 'scale_2', 'rot_0', 'rot_1', 'rot_2',
             'rot_3']
    rows = np.arange(2 * 14, dtype=np.float32).reshape(2, 14) * 0.25 - 1.0
    path = self._write('be.ply', _inria_bytes(rows, names, endian='>'))
    g = _np(ply.load_ply(path))
    np.testing.assert_array_equal(g.means, rows[:, :3])
    np.testing.assert_array_equal(g.sh[:, 0], rows[:, 3:6])
    np.testing.assert_array_equal(g.opacity_logits, rows[:, 6])
    np.testing.assert_array_equal(g.log_scales, rows[:, 7:10])
    np.testing.assert_array_equal(g.quats, rows[:, 10:14])
    self.assertIsNone(g.normals)

  def test_big_endian_real_file_matches_little_endian(self):
    header, el = ply.read_ply(SHIPPED['udon_crop'])
    ply.write_ply(self.tmp / 'be.ply', el, format='binary_big_endian')
    self.assertEqual(
      ply.read_ply_header(self.tmp / 'be.ply').format, 'binary_big_endian'
    )
    _assert_gaussians_equal(
      self, ply.load_ply(self.tmp / 'be.ply'),
      ply.load_ply(SHIPPED['udon_crop'])
    )

  def test_ascii_hand_written(self):
    text = (
      'ply\r\nformat ascii 1.0\r\ncomment made by hand\r\n'
      'element vertex 2\r\n'
      + ''.join(f'property float {n}\r\n' for n in (
        'x', 'y', 'z', 'opacity', 'rot_0', 'rot_1', 'rot_2', 'rot_3',
        'scale_0', 'scale_1', 'scale_2', 'f_dc_0', 'f_dc_1', 'f_dc_2'))
      + 'property int object_id\r\n'
      + 'element face 1\r\nproperty list uchar int vertex_indices\r\n'
      + 'end_header\r\n'
      + '1 2 3 0.5 1 0 0 0 -1 -2 -3 0.1 0.2 0.3 7\r\n'
      + '-1.5e-3 4 5 -0.5 0 1 0 0 -4 -5 -6 1e2 2 3 -2\r\n'
      + '3 0 1 0\r\n'
    )
    path = self._write('a.ply', text.encode())
    header, el = ply.read_ply(path)
    self.assertEqual(header.comments, ('made by hand',))
    self.assertEqual(el['face']['vertex_indices'][0].tolist(), [0, 1, 0])
    g = _np(ply.load_ply(path))
    np.testing.assert_array_equal(
      g.means, np.float32([[1, 2, 3], [-1.5e-3, 4, 5]])
    )
    np.testing.assert_array_equal(g.opacity_logits, np.float32([0.5, -0.5]))
    np.testing.assert_array_equal(
      g.quats, np.float32([[1, 0, 0, 0], [0, 1, 0, 0]])
    )
    np.testing.assert_array_equal(
      g.log_scales, np.float32([[-1, -2, -3], [-4, -5, -6]])
    )
    np.testing.assert_array_equal(
      g.sh[:, 0], np.float32([[0.1, 0.2, 0.3], [100, 2, 3]])
    )
    self.assertEqual(g.extras['object_id'].tolist(), [7, -2])
    self.assertEqual(g.extras['object_id'].dtype, np.int32)

  def test_double_and_aliased_types_with_shuffled_order(self):
    # scale_*, rot_* and f_rest_* given out of order and with mixed types.
    names = (['rot_3', 'rot_1', 'rot_0', 'rot_2', 'x', 'y', 'z', 'opacity']
             + ['scale_2', 'scale_0', 'scale_1', 'f_dc_0', 'f_dc_1', 'f_dc_2']
             + [f'f_rest_{i}' for i in (8, 0, 1, 2, 3, 4, 5, 6, 7)]
             + ['label'])
    types = (['double'] * 4 + ['float64', 'float32', 'float', 'double']
             + ['double'] * 6 + ['float'] * 9 + ['uint8'])
    rng = np.random.default_rng(3)
    rows = rng.normal(size=(4, len(names)))
    rows[:, -1] = [0, 1, 255, 3]
    path = self._write('d.ply', _inria_bytes(rows, names, types=types))
    g = _np(ply.load_ply(path))
    col = {n: rows[:, i] for i, n in enumerate(names)}
    f32 = lambda a: np.asarray(a).astype(np.float32)
    np.testing.assert_array_equal(
      g.quats, f32(np.stack([col[f'rot_{i}'] for i in range(4)], -1))
    )
    np.testing.assert_array_equal(
      g.log_scales, f32(np.stack([col[f'scale_{i}'] for i in range(3)], -1))
    )
    self.assertEqual(g.sh.shape, (4, 4, 3))
    np.testing.assert_array_equal(g.sh[:, 2, 1], f32(col['f_rest_4']))
    np.testing.assert_array_equal(g.sh[:, 3, 2], f32(col['f_rest_8']))
    self.assertEqual(g.extras['label'].dtype, np.uint8)
    self.assertEqual(g.extras['label'].tolist(), [0, 1, 255, 3])

  def test_extras_round_trip_with_types(self):
    extras = {
      'object_id': np.array([0, 3, -1, 2], np.int32),
      'label': np.array([1, 2, 3, 250], np.uint8),
      'confidence': np.array([0.5, 0.25, 1.0, 0.0], np.float32),
    }
    g = _random(4, 1, extras=extras)
    ply.save_ply(self.tmp / 'e.ply', g)
    header = ply.read_ply_header(self.tmp / 'e.ply')
    self.assertEqual(
      list(header.element('vertex').property_names[-3:]), list(extras)
    )
    h = ply.load_ply(self.tmp / 'e.ply')
    _assert_gaussians_equal(self, g, h)
    # The subset of a loaded scene keeps its extras, and saves again.
    sub = h.subset(np.array([True, False, True, True]))
    ply.save_ply(self.tmp / 's.ply', sub)
    self.assertEqual(
      ply.load_ply(self.tmp / 's.ply').extras['object_id'].tolist(),
      [0, -1, 2],
    )

  def test_empty_file_of_gaussians(self):
    g = _random(3, 0).subset(np.zeros(3, bool))
    ply.save_ply(self.tmp / 'z.ply', g)
    self.assertEqual(ply.load_ply(self.tmp / 'z.ply').num, 0)

  # Compressed PLY -----------------------------------------------------------

  def _compressed_bytes(self, chunk, packed, sh=None, color_bounds=True):
    chunk_names = list(ply.CHUNK_PROPS)
    if color_bounds:
      chunk_names += list(ply.CHUNK_COLOR_PROPS)
    head = 'ply\nformat binary_little_endian 1.0\n'
    head += f'element chunk {len(chunk)}\n'
    head += ''.join(f'property float {n}\n' for n in chunk_names)
    head += f'element vertex {len(packed)}\n'
    head += ''.join(f'property uint {n}\n' for n in ply.PACKED_PROPS)
    if sh is not None:
      head += f'element sh {len(sh)}\n'
      head += ''.join(
        f'property uchar f_rest_{i}\n' for i in range(len(sh[0]))
      )
    head += 'end_header\n'
    body = b''.join(struct.pack(f'<{len(chunk_names)}f', *c) for c in chunk)
    body += b''.join(struct.pack('<4I', *p) for p in packed)
    if sh is not None:
      body += b''.join(bytes(r) for r in sh)
    return head.encode() + body

  def test_compressed_hand_packed_reference(self):
    chunk = [[
      -1.0, 2.0, 0.0, 3.0, 4.0, 2.0,  # position bounds
      -5.0, -6.0, -7.0, -1.0, -2.0, -3.0,  # log-scale bounds
      0.0, 0.25, -0.5, 1.0, 0.75, 1.5,  # colour bounds
    ]]
    # Gaussian 0: x at max, y at min, z at 1023/2047 of the range.
    pos0 = (2047 << 21) | (0 << 11) | 1023
    # Gaussian 1: x at 1/2047, y at 1023/1023, z at min.
    pos1 = (1 << 21) | (1023 << 11) | 0
    scale0 = (0 << 21) | (1023 << 11) | 2047
    scale1 = (2047 << 21) | (512 << 11) | 0
    # Rotation 0: largest = rot_0 (w), the others encode 0.5 -> 0.
    # Rotation 1: largest = rot_2, others rot_0, rot_1, rot_3 = bytes
    # 1023, 0, 512.
    rot0 = (0 << 30) | (511 << 20) | (511 << 10) | 511
    rot1 = (2 << 30) | (1023 << 20) | (0 << 10) | 512
    col0 = (255 << 24) | (0 << 16) | (128 << 8) | 128
    col1 = (0 << 24) | (255 << 16) | (51 << 8) | 0
    sh = [list(range(0, 9)), [255] * 8 + [128]]
    path = self._write(
      'c.ply',
      self._compressed_bytes(
        chunk, [[pos0, rot0, scale0, col0], [pos1, rot1, scale1, col1]], sh
      ),
    )
    g = _np(ply.load_ply(path))
    np.testing.assert_allclose(
      g.means,
      [[3.0, 2.0, 2.0 * 1023 / 2047], [-1.0 + 4.0 / 2047, 4.0, 0.0]],
      rtol=1e-6, atol=1e-6,
    )
    np.testing.assert_allclose(
      g.log_scales,
      [[-5.0, -2.0, -3.0], [-1.0, -6.0 + 4.0 * 512 / 1023, -7.0]],
      rtol=1e-6,
    )
    u = lambda b: (b / 1023 - 0.5) * np.sqrt(2.0)
    small = u(511)
    q0 = [np.sqrt(1 - 3 * small**2), small, small, small]
    a, b, c = u(1023), u(0), u(512)
    q1 = [a, b, np.sqrt(max(0.0, 1 - a * a - b * b - c * c)), c]
    np.testing.assert_allclose(g.quats, [q0, q1], atol=1e-6)
    rgb = np.array([[1.0, 0.25, -0.5 + 2.0 * 128 / 255],
                    [0.0, 0.75, -0.5 + 2.0 * 51 / 255]])
    np.testing.assert_allclose(g.sh[:, 0], (rgb - 0.5) / SH_C0, rtol=1e-5,
                               atol=1e-5)
    logit = lambda p: np.log(p / (1 - p))
    np.testing.assert_allclose(
      g.opacity_logits, [logit(128 / 255), logit(0.5 / 255)], rtol=1e-5
    )
    n = lambda b: 0.0 if b == 0 else 1.0 if b == 255 else (b + 0.5) / 256
    rest0 = np.array([(n(b) - 0.5) * 8 for b in range(9)]).reshape(3, 3).T
    np.testing.assert_allclose(g.sh[0, 1:], rest0, rtol=1e-6)
    self.assertEqual(g.sh[1, 1:, :2].tolist(), [[4.0] * 2] * 3)
    np.testing.assert_allclose(g.sh[1, 3, 2], (128.5 / 256 - 0.5) * 8)

  def test_compressed_without_colour_bounds(self):
    chunk = [[0.0] * 6 + [-1.0] * 6]
    col = (51 << 24) | (102 << 16) | (204 << 8) | 255
    path = self._write(
      'c12.ply',
      self._compressed_bytes(chunk, [[0, 0, 0, col]], color_bounds=False),
    )
    g = _np(ply.load_ply(path))
    np.testing.assert_allclose(
      g.sh[0, 0], (np.array([0.2, 0.4, 0.8]) - 0.5) / SH_C0, rtol=1e-6
    )
    np.testing.assert_allclose(
      g.opacity_logits, [np.log(254.5 / 0.5)], rtol=1e-6
    )
    self.assertEqual(g.sh_degree, 0)

  def test_compressed_round_trip_within_quantisation(self):
    g = ply.load_ply(SHIPPED['udon_crop'])
    ply.save_compressed_ply(self.tmp / 'c.ply', g)
    header = ply.read_ply_header(self.tmp / 'c.ply')
    self.assertEqual([e.name for e in header.elements],
                     ['chunk', 'vertex', 'sh'])
    self.assertEqual(header.element('chunk').count, -(-g.num // 256))
    h = _np(ply.load_ply(self.tmp / 'c.ply'))
    g = _np(g)
    idx = np.arange(g.num) // 256
    for name, bits in (('means', (11, 10, 11)), ('log_scales', (11, 10, 11))):
      a = getattr(g, name)
      for d in range(3):
        lo = np.array([a[idx == c, d].min() for c in range(idx.max() + 1)])
        hi = np.array([a[idx == c, d].max() for c in range(idx.max() + 1)])
        if name == 'log_scales':
          lo, hi = np.clip(lo, -20, 20), np.clip(hi, -20, 20)
        step = (hi - lo)[idx] / ((1 << bits[d]) - 1)
        err = np.abs(getattr(h, name)[:, d] - a[:, d])
        self.assertTrue(np.all(err <= 0.5 * step + 1e-5), f'{name}[{d}]')
    opa = lambda x: 1 / (1 + np.exp(-x.astype(np.float64)))
    self.assertLessEqual(
      np.abs(opa(h.opacity_logits) - opa(g.opacity_logits)).max(),
      0.5 * ALPHA_BYTE_STEP + 1e-6,
    )
    inside = np.abs(g.sh[:, 1:]) < 4.0 - SH_BYTE_STEP
    err = np.abs(h.sh[:, 1:] - g.sh[:, 1:])[inside]
    self.assertLessEqual(err.max(), SH_BYTE_STEP + 1e-6)
    qa = g.quats / np.linalg.norm(g.quats, axis=-1, keepdims=True)
    qb = h.quats / np.linalg.norm(h.quats, axis=-1, keepdims=True)
    sign = np.sign(np.sum(qa * qb, -1, keepdims=True))
    self.assertLessEqual(np.abs(qa - sign * qb).max(), 2 * QUAT_10BIT_STEP)

  # .splat -------------------------------------------------------------------

  def test_splat_hand_computed_row(self):
    log_scales = np.log(np.float32([[0.5, 0.25, 2.0]]))
    g = Gaussians(
      means=np.float32([[1.0, -2.0, 3.5]]),
      log_scales=log_scales,
      quats=np.float32([[2.0, 0.0, 0.0, 0.0]]),
      opacity_logits=np.float32([0.0]),
      sh=((np.float32([[0.2, 0.4, 1.0]]) - 0.5) / SH_C0)[:, None, :],
    )
    splat.save_splat(self.tmp / 'a.splat', g)
    scales = np.exp(log_scales[0].astype(np.float64))
    expected = struct.pack('<6f', 1.0, -2.0, 3.5, *scales)
    expected += bytes([51, 102, 255, 128, 255, 128, 128, 128])
    self.assertEqual((self.tmp / 'a.splat').read_bytes(), expected)

  def test_splat_round_trip_and_sort(self):
    g = _np(ply.load_ply(SHIPPED['train_1000']))
    splat.save_splat(self.tmp / 'a.splat', g)
    self.assertEqual(os.path.getsize(self.tmp / 'a.splat'), 32 * g.num)
    h = _np(splat.load_splat(self.tmp / 'a.splat'))
    self.assertEqual(h.sh_degree, 0)
    # Sorted by decreasing exp(sum log_scale) * sigmoid(opacity) (antimatter15).
    ls = g.log_scales.astype(np.float64)
    opa = 1 / (1 + np.exp(-g.opacity_logits.astype(np.float64)))
    order = np.argsort(-np.exp(ls.sum(-1)) * opa, kind='stable')
    np.testing.assert_array_equal(h.means, g.means[order])
    # Unsorted: rows line up with the input.
    splat.save_splat(self.tmp / 'b.splat', g, sort=False)
    h = _np(splat.load_splat(self.tmp / 'b.splat'))
    np.testing.assert_array_equal(h.means, g.means)
    np.testing.assert_allclose(h.log_scales, g.log_scales, atol=1e-6)
    rgb = np.clip(0.5 + SH_C0 * g.sh[:, 0], 0, 1)
    np.testing.assert_allclose(
      0.5 + SH_C0 * h.sh[:, 0], rgb, atol=0.5 / 255 + 1e-6
    )
    opa = lambda x: 1 / (1 + np.exp(-x.astype(np.float64)))
    np.testing.assert_allclose(
      opa(h.opacity_logits), np.clip(opa(g.opacity_logits), 0.5 / 255,
                                     254.5 / 255),
      atol=0.5 / 255 + 1e-6)
    qa = g.quats / np.linalg.norm(g.quats, axis=-1, keepdims=True)
    # 0.5/128 rounding, or 1/128 where a component near 1 clips at byte 255.
    np.testing.assert_allclose(h.quats, qa, atol=1 / 128 + 1e-6)

  def test_splat_bad_inputs(self):
    with self.assertRaisesRegex(splat.SplatError, r'not a multiple of 32'):
      splat.load_splat(self._write('t.splat', b'\0' * 40))
    with self.assertRaisesRegex(splat.SplatError, 'PLY file'):
      splat.load_splat(SHIPPED['train_1000'])
    row = struct.pack('<6f', 0, 0, 0, 1.0, 0.0, 1.0) + bytes(8)
    with self.assertRaisesRegex(splat.SplatError, r'scale <= 0: 1 rows'):
      splat.load_splat(self._write('z.splat', row))
    row = struct.pack('<6f', np.nan, 0, 0, 1.0, 1.0, 1.0) + bytes(8)
    with self.assertRaisesRegex(splat.SplatError, r'position: 1 rows'):
      splat.load_splat(self._write('n.splat', row))

  # Bad files ----------------------------------------------------------------

  def _udon_bytes(self):
    return SHIPPED['udon_crop'].read_bytes()

  def test_not_a_ply(self):
    p = self._write('x.ply', b'hello world\n' * 10)
    with self.assertRaisesRegex(ply.PlyError, r'x\.ply: not a PLY file'):
      ply.load_ply(p)
    with self.assertRaisesRegex(ply.PlyError, 'no "end_header"'):
      ply.load_ply(self._write('h.ply', b'ply\nformat ascii 1.0\n'))
    with self.assertRaises(FileNotFoundError):
      ply.load_ply(self.tmp / 'missing.ply')

  def test_unsupported_format_and_type(self):
    data = self._udon_bytes().replace(
      b'binary_little_endian', b'binary_middle_endian', 1
    )
    with self.assertRaisesRegex(ply.PlyError, 'unsupported format'):
      ply.load_ply(self._write('f.ply', data))
    data = self._udon_bytes().replace(b'property float x', b'property half x')
    with self.assertRaisesRegex(ply.PlyError, "unknown PLY type 'half'"):
      ply.load_ply(self._write('t.ply', data))

  def test_truncated_payload(self):
    data = self._udon_bytes()[:-100]
    with self.assertRaisesRegex(
      ply.PlyError,
      r't\.ply: truncated PLY payload: expected 533944 bytes after the '
      r'header \(vertex: 2153 x 248 B\), file has 533844',
    ):
      ply.load_ply(self._write('t.ply', data))
    with self.assertRaisesRegex(ply.PlyError, 'truncated ASCII'):
      ply.load_ply(self._write(
        'a.ply',
        b'ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n'
        b'property float y\nend_header\n1 2\n3\n'))

  def test_missing_property(self):
    data = self._udon_bytes().replace(b'property float opacity',
                                      b'property float opaque')
    with self.assertRaisesRegex(
      ply.PlyError, r"missing property \['opacity'\].*needs x y z"
    ):
      ply.load_ply(self._write('m.ply', data))
    head = b'ply\nformat ascii 1.0\nelement face 0\nend_header\n'
    with self.assertRaisesRegex(ply.PlyError, 'no "vertex" element'):
      ply.load_ply(self._write('f.ply', head))

  def test_non_finite_values(self):
    g = _np(ply.load_ply(SHIPPED['train_1000']))
    _, el = ply.read_ply(SHIPPED['train_1000'])
    v = dict(el['vertex'])
    v['scale_1'] = v['scale_1'].copy()
    v['scale_1'][[3, 10, 500]] = [np.nan, np.inf, -np.inf]
    v['f_rest_7'] = v['f_rest_7'].copy()
    v['f_rest_7'][0] = np.nan
    ply.write_ply(self.tmp / 'n.ply', {'vertex': v})
    with self.assertRaisesRegex(
      ply.PlyError, r'non-finite.*scale_1: 3 of 1000 rows; f_rest_7: 1 of'
    ):
      ply.load_ply(self.tmp / 'n.ply')
    bad = g.replace(opacity_logits=np.where(np.arange(g.num) < 2, np.nan,
                                            g.opacity_logits))
    with self.assertRaisesRegex(ply.PlyError, r'opacity: 2 rows'):
      ply.save_ply(self.tmp / 'w.ply', bad)

  def test_wrong_counts(self):
    _, el = ply.read_ply(SHIPPED['udon_crop'])
    v = {k: a for k, a in el['vertex'].items() if k != 'f_rest_44'}
    ply.write_ply(self.tmp / 'r.ply', {'vertex': v})
    with self.assertRaisesRegex(ply.PlyError, r'44 f_rest_\* properties'):
      ply.load_ply(self.tmp / 'r.ply')
    # Dropping the header line alone leaves 4 bytes a row unaccounted for
    # (every later value was read shifted by one property).
    data = self._udon_bytes().replace(b'property float f_rest_44\n', b'')
    with self.assertRaisesRegex(ply.PlyError, r'8612 bytes after the'):
      ply.load_ply(self._write('r.ply', data))
    data = self._udon_bytes().replace(b'element vertex 2153',
                                      b'element vertex 2154')
    with self.assertRaisesRegex(ply.PlyError, 'truncated'):
      ply.load_ply(self._write('c.ply', data))
    chunk = [[0.0] * 18, [0.0] * 18]
    with self.assertRaisesRegex(ply.PlyError, r'2 chunks for 1 Gaussians'):
      ply.load_ply(self._write('k.ply',
                               self._compressed_bytes(chunk, [[0, 0, 0, 0]])))

  def test_bad_gaussians_on_save(self):
    g = _random(4, 1)
    with self.assertRaisesRegex(ply.PlyError, r'log_scales has shape \(3, 3\)'):
      ply.save_ply(self.tmp / 'a.ply', g.replace(log_scales=g.log_scales[:3]))
    with self.assertRaisesRegex(ply.PlyError, r"extras\['id'\] has shape"):
      ply.save_ply(self.tmp / 'a.ply', g.replace(extras={'id': np.zeros(5)}))
    with self.assertRaisesRegex(ply.PlyError, 'clashes'):
      ply.save_ply(self.tmp / 'a.ply',
                   g.replace(extras={'opacity': np.zeros(4)}))

  # Rule breaks from review: shifted rows, dropped data, silent inf, raw
  # OS errors.

  def _ascii(self, rows, count=None, extra_head=''):
    head = (f'ply\nformat ascii 1.0\nelement vertex '
            f'{len(rows) if count is None else count}\n'
            + ''.join(f'property float {n}\n' for n in ply.REQUIRED)
            + extra_head + 'end_header\n')
    return (head + ''.join(f'{r}\n' for r in rows)).encode()

  def test_ascii_rows_are_lines(self):
    vals = ' '.join(['0'] * 14)
    # One value missing on row 0, one extra on row 1: was read shifted.
    short, long = ' '.join(['1'] * 13), ' '.join(['2'] * 15)
    path = self._write('s.ply', self._ascii([short, long]))
    with self.assertRaisesRegex(
        ply.PlyError, r's\.ply: ASCII row 0 has 13 values, the header '
        r"declares 14 properties \(element 'vertex', line 19\)"):
      ply.load_ply(path)
    # Data after the declared rows: was ignored.
    path = self._write('t.ply', self._ascii([vals, vals, vals], count=2))
    with self.assertRaisesRegex(
        ply.PlyError, r't\.ply: 1 line\(s\) of data \(from line 21.*after '
        r'the declared 2 vertex rows.*header count wrong'):
      ply.load_ply(path)
    # Blank lines and a list element still read.
    face = 'element face 1\nproperty list uchar int vertex_indices\n'
    text = self._ascii([vals, '', vals, '3 0 1 1'], count=2, extra_head=face)
    header, el = ply.read_ply(self._write('f.ply', text))
    self.assertEqual(el['face']['vertex_indices'][0].tolist(), [0, 1, 1])
    self.assertEqual(ply.load_ply(self.tmp / 'f.ply').num, 2)
    bad = self._ascii([vals, '3 0 1 1 1'], count=1, extra_head=face)
    with self.assertRaisesRegex(ply.PlyError, r'row 0 of element .face. '
                                r'\(line 22\) has 5 values'):
      ply.read_ply(self._write('g.ply', bad))

  def test_binary_data_after_the_declared_elements(self):
    rows = np.zeros((5, 14), np.float32)
    data = _inria_bytes(rows, ply.REQUIRED).replace(
      b'element vertex 5', b'element vertex 3')
    with self.assertRaisesRegex(
        ply.PlyError, r'b\.ply: 112 bytes after the declared 3 vertex rows.*'
        r"2 more vertex rows than the header's 3.*header count wrong"):
      ply.load_ply(self._write('b.ply', data))
    # Further declared elements (faces) account for their bytes.
    data = _inria_bytes(rows[:3], ply.REQUIRED).replace(
      b'end_header\n', b'element face 1\nproperty list uchar int '
      b'vertex_indices\nend_header\n')
    data += struct.pack('<B3i', 3, 0, 1, 2)
    _, el = ply.read_ply(self._write('f.ply', data))
    self.assertEqual(el['face']['vertex_indices'][0].tolist(), [0, 1, 2])
    self.assertEqual(ply.load_ply(self.tmp / 'f.ply').num, 3)
    with self.assertRaisesRegex(ply.PlyError, r'3 bytes after the declared '
                                r'3 vertex, 1 face rows'):
      ply.load_ply(self._write('g.ply', data + b'abc'))

  def test_double_beyond_float32_is_an_error(self):
    rows = np.zeros((3, 14))
    rows[1, 0] = 1e300
    types = ['double'] + ['float'] * 13
    path = self._write('d.ply', _inria_bytes(rows, ply.REQUIRED, types=types))
    with warnings.catch_warnings():
      warnings.simplefilter('error')  # no RuntimeWarning on the way
      with self.assertRaisesRegex(
          ply.PlyError, r"d\.ply: vertex property 'x' holds 1e\+300 in row "
          r'1 .*float32'):
        ply.load_ply(path)
      vals = ['0'] * 14
      path = self._write('a.ply', self._ascii([' '.join(vals),
                                               ' '.join(['1e300'] + vals[1:])]))
      with self.assertRaisesRegex(
          ply.PlyError, r'a\.ply: ASCII value 1e300 in vertex\.x \(value 1\) '
          r'is out of range for the declared type float'):
        ply.load_ply(path)
    with self.assertRaisesRegex(ply.PlyError, r'dtype=.*int32.*float dtype'):
      ply.load_ply(SHIPPED['train_1000'], dtype=np.int32)

  def test_duplicate_element(self):
    data = _inria_bytes(np.zeros((1, 14)), ply.REQUIRED)
    head, body = data.split(b'end_header\n')
    data = head + b'element vertex 1\nproperty float x\nend_header\n' + body
    with self.assertRaisesRegex(ply.PlyError, r"duplicate element 'vertex'"):
      ply.load_ply(self._write('dup.ply', data))

  def test_directories_and_missing_files(self):
    with self.assertRaisesRegex(splat.SplatError, 'is a directory'):
      splat.load_splat(self.tmp)
    with self.assertRaisesRegex(FileNotFoundError, r'\.splat file not found'):
      splat.load_splat(self.tmp / 'missing.splat')
    with self.assertRaisesRegex(ply.PlyError, 'is a directory'):
      ply.read_ply_header(self.tmp)
    with self.assertRaisesRegex(FileNotFoundError, 'PLY file not found'):
      ply.read_ply_header(self.tmp / 'missing.ply')
    with self.assertRaisesRegex(ply.PlyError, 'expected a PLY file path'):
      ply.load_ply(0)  # not file descriptor 0

  def test_output_paths_that_cannot_be_files(self):
    g = _random(3, 0)
    (self.tmp / 'dir.ply').mkdir()
    (self.tmp / 'dir.splat').mkdir()
    (self.tmp / 'file').write_text('x')
    for save, error, ext in (
        (ply.save_ply, ply.PlyError, 'ply'),
        (lambda p, g: ply.save_ply(p, g, binary=False), ply.PlyError, 'ply'),
        (ply.save_compressed_ply, ply.PlyError, 'ply'),
        (lambda p, g: ply.write_ply(p, {'vertex': {'x': np.zeros(3)}}),
         ply.PlyError, 'ply'),
        (splat.save_splat, splat.SplatError, 'splat')):
      with self.subTest(ext):
        with self.assertRaisesRegex(error, rf'dir\.{ext}: is a directory'):
          save(self.tmp / f'dir.{ext}', g)
        with self.assertRaisesRegex(error, r'cannot create the folder.*file '
                                    r'is a file, not a folder'):
          save(self.tmp / 'file' / 'sub' / f'a.{ext}', g)
    ply.save_ply(self.tmp / 'new' / 'sub' / 'a.ply', g)  # parents created
    self.assertEqual(ply.load_ply(self.tmp / 'new' / 'sub' / 'a.ply').num, 3)

  def test_splat_refuses_scales_beyond_float32(self):
    g = _random(4, 0)
    for value, word in ((100.0, 'inf'), (-200.0, '0')):
      bad = g.replace(log_scales=np.asarray(g.log_scales).copy())
      bad.log_scales[2, 1] = value
      with self.assertRaisesRegex(
          splat.SplatError, rf'log_scales row 2 = .*{value}.*inf or 0'):
        with warnings.catch_warnings():
          warnings.simplefilter('error')
          splat.save_splat(self.tmp / f'{word}.splat', bad, sort=False)
      self.assertFalse((self.tmp / f'{word}.splat').exists())


if __name__ == '__main__':
  absltest.main()
