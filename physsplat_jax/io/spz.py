"""Niantic ``.spz`` files: quantised, compressed 3D Gaussians (SH 0-3).

Facts from Niantic's reference implementation (GitHub ``nianticlabs/spz``,
library 1.1.0, commit 21715c3): ``src/cc/load-spz.cc`` (file layout,
packing), ``src/cc/load-spz.h`` (versions, magic), ``src/cc/splat-utils.h``
(colour scale, unpacking), ``src/cc/splat-types.h`` (coordinate systems),
``extensions/README.md`` and ``extensions/cc/coordinate-system-adobe.cc``
(extension records). All integers little-endian.

Containers. Versions 1-3: the whole file is one gzip stream holding a
16-byte header ``u32 magic 0x5053474e ("NGSP"), u32 version, u32 count,
u8 sh_degree, u8 fractional_bits, u8 flags, u8 0``, then each attribute for
all Gaussians in turn, in the order positions, alphas, colours, scales,
rotations, SH (the code's order; the README's sections list them
otherwise), then extension records if ``flags & 2``. Version 4 (the
reference's default writer since 2026) is not gzip: a plain 32-byte header
(the same fields, then ``u8 num_streams, u32 toc_offset``, 12 zero bytes),
extension records up to ``toc_offset``, a table of ``(u64 compressed, u64
raw)`` sizes, then one zstd stream per non-empty attribute in the same
order. zstd is not in Python's standard library before 3.14: version 4 is
read when ``compression.zstd`` or the ``zstandard`` package is importable
and refused with an SpzError otherwise; it is never written (this writer
writes version 3, which every reference reader since 2025-07 reads).

Per Gaussian (``K`` Gaussians, reading inverts each line):

  position  3 x 24-bit signed fixed point, ``round(x * 2**f)``, ``f`` =
            fractional_bits (12 here and in the reference: step 1/4096,
            range [-2048, 2048)); version 1: 3 x float16
  alpha     u8 ``round(sigmoid(opacity) * 255)``
  colour    u8 ``round(f_dc * 0.15 * 255 + 127.5)``: scale 0.15, not SH_C0,
            so |f_dc| <= 3.33 fits
  scale     u8 ``round((log_scale + 10) * 16)``: log range [-10, 5.94]
  rotation  versions 1-2: 3 x u8 ``round(q * 127.5 + 127.5)`` of x, y, z of
            the unit quaternion with w >= 0, ``w = sqrt(1 - |xyz|^2)``;
            versions 3-4: u32 "smallest three": bits 31-30 the index (x y z
            w = 0 1 2 3) of the largest |component|, made positive; the
            other three from bit 29 down in index order, 10 bits each: a
            sign bit and ``floor(|q_i| / sqrt(1/2) * 511 + 0.5)``
  SH        ``(d + 1)**2 - 1`` coefficients x 3 channels, channel fastest
            (``sh[k, 1 + j, c]`` here), u8 ``round(x * 128) + 128`` snapped
            to buckets of ``2**(8 - bits)``: 5 bits for degree 1, 4 for
            degrees 2-3 (reference defaults); read as ``(u8 - 128) / 128``

Quaternions are x y z w in the file, w x y z here. Values outside a field's
range are clamped, as the reference does (logged); positions outside the
fixed-point range are refused instead (choose ``fractional_bits``).
Opacity bytes 0 and 255 read as ``logit(0.5 / 255)`` and ``logit(254.5 /
255)`` (the reference gives -inf and inf). The reference reads SH degree 4
(``SH_MAX_DEGREE``); our Gaussians stop at 3, so degree 4 is an SpzError.

Flags: ``0x1`` the scene was trained with antialiasing (Mip-Splatting's 2D
filter). Gaussians have no field for it: :func:`load_spz` logs a warning
and :func:`read_spz_header` returns it; render such a scene with
``RenderConfig(rasterize_mode='antialiased')``. ``save_spz(...,
antialiased=True)`` sets it. ``0x2``: extension records ``u32 type, u32
length, payload``; type ``0xADBE0003`` (``SPZ_ADOBE_coordinate_system``)
holds the u32 coordinate system the data is stored in; others are skipped.

Coordinates. The format stores RUB (x right, y up, z back: OpenGL,
three.js) unless that extension names another system; INRIA PLY files, and
so this package's Gaussians, are RDF (y down, z forward). Loading converts
the stored system to RDF and saving converts RDF to RUB, as the reference
does with ``UnpackOptions.to_coord = RDF`` / ``PackOptions.from_coord =
RDF``: a sign per axis on positions, ``(s_y s_z, s_x s_z, s_x s_y)`` on the
quaternion's x, y, z and the reference's sign per SH coefficient; RUB <->
RDF is a 180-degree turn about x. Niantic's ``ply_to_spz`` tool (and the
Python ``load_splat_from_ply`` + ``save_spz`` with default options) leaves
the system UNSPECIFIED and stores the PLY's RDF data unconverted: load those
with ``stored_frame='RDF'`` (docs/scenes.md, "Scene file formats"). Only
the 8 systems without an axis swap (LDB ... RUF) are supported; the
reference's rotated family (a y/z swap, which rotates SH within bands) is
an SpzError.
"""

from __future__ import annotations

import dataclasses
import gzip
import io
import os
import struct
import zlib

from absl import logging
import jax.numpy as jnp
import numpy as np

from physsplat_jax.io.ply import PlyError, gaussians_to_vertex
from physsplat_jax.io.ply import float_dtype
from physsplat_jax.io.ply_format import _read_bytes, check_writable_file
from physsplat_jax.io.ply_format import open_output
from physsplat_jax.types import Gaussians

MAGIC = 0x5053474E
READ_VERSIONS = (1, 2, 3, 4)
WRITE_VERSIONS = (2, 3)
DEFAULT_VERSION = 3
FRACTIONAL_BITS = 12
COLOR_SCALE = 0.15
SH1_BITS = 5
SH_REST_BITS = 4
FLAG_ANTIALIASED = 0x1
FLAG_EXTENSIONS = 0x2
EXT_COORDINATE_SYSTEM = 0xADBE0003
# The reference's CoordinateSystem enum (splat-types.h); 9..16 are the
# rotated family (y and z swapped), not supported here.
SYSTEMS = ('UNSPECIFIED', 'LDB', 'RDB', 'LUB', 'RUB', 'LDF', 'RDF', 'LUF',
           'RUF', 'LFD', 'RFD', 'LFU', 'RFU', 'LBD', 'RBD', 'LBU', 'RBU')
OUR_FRAME = 'RDF'
_LEGACY_HEADER = struct.Struct('<IIIBBBB')
_NGSP_HEADER = struct.Struct('<IIIBBBBI12x')
_ALPHA_EPS = 0.5 / 255.0
_SQRT1_2 = np.float32(0.707106781186547524401)


class SpzError(PlyError):
  """A ``.spz`` file that cannot be read or Gaussians that cannot be written.

  A subclass of :class:`~physsplat_jax.io.ply.PlyError` (so of ValueError).
  """


@dataclasses.dataclass(frozen=True)
class SpzHeader:
  """The header of a ``.spz`` file (no Gaussians decoded).

  Attributes:
    version: format version, 1-4.
    num_points: number of Gaussians.
    sh_degree: SH degree stored.
    fractional_bits: fixed-point fraction bits of the positions.
    antialiased: flag 0x1, the scene was trained with antialiasing.
    has_extensions: flag 0x2, extension records are present.
  """

  version: int
  num_points: int
  sh_degree: int
  fractional_bits: int
  antialiased: bool
  has_extensions: bool


# ----------------------------------------------------------------------------
# Coordinate systems.


def _system(name, path, what) -> str:
  s = str(name).upper() if isinstance(name, str) else None
  if s not in SYSTEMS[1:9]:
    raise SpzError(
      f'{path}: {what}={name!r}; give one of {", ".join(SYSTEMS[1:9])} '
      "(RUB: the .spz convention; RDF: INRIA PLY, e.g. files from Niantic's "
      'ply_to_spz tool, which stores the PLY unconverted)'
    )
  return s


def _flips(stored: str):
  """Signs (positions, quaternion xyz, 15 SH coefficients) stored <-> RDF.

  The conversion is a sign per axis, its own inverse; SH signs are the
  reference's ``coordinateConverter`` table (splat-types.h) for degree 3.
  """
  a, b = SYSTEMS.index(stored) - 1, SYSTEMS.index(OUR_FRAME) - 1
  x, y, z = (1.0 if (a >> i) & 1 == (b >> i) & 1 else -1.0 for i in range(3))
  p = np.array([x, y, z])
  q = np.array([y * z, x * z, x * y])
  sh = np.array([y, z, x, x * y, y * z, 1, x * z, 1, y, x * y * z, y, z, x, z,
                 x], np.float64)
  return p, q, sh


# ----------------------------------------------------------------------------
# Reading.


def _zstd_decompress():
  """A zstd ``decompress(bytes, size)`` if the interpreter has one, else None.
  """
  try:
    from compression import zstd  # Python >= 3.14
    return lambda b, n: zstd.decompress(b)
  except ImportError:
    pass
  try:
    import zstandard
  except ImportError:
    return None
  d = zstandard.ZstdDecompressor()
  return lambda b, n: d.decompress(b, max_output_size=n)


def _legacy_header(raw: bytes, path) -> SpzHeader:
  if len(raw) < _LEGACY_HEADER.size:
    raise SpzError(
      f'{path}: truncated .spz: the unzipped stream is {len(raw)} bytes, '
      f'shorter than the {_LEGACY_HEADER.size}-byte header'
    )
  magic, version, n, deg, fb, flags, _ = _LEGACY_HEADER.unpack_from(raw)
  _check_magic(magic, path)
  return _header(version, n, deg, fb, flags, path)


def _header(version, n, deg, fb, flags, path) -> SpzHeader:
  """The checked :class:`SpzHeader` of either container's fields."""
  return _check_header(
    SpzHeader(version, n, deg, fb, bool(flags & FLAG_ANTIALIASED),
              bool(flags & FLAG_EXTENSIONS)), path)


def _ngsp_header(data: bytes, path) -> tuple[SpzHeader, int, int]:
  """``(header, number of streams, table-of-contents offset)`` of a
  version 4 file (``data`` not gzip)."""
  if data[:4] != struct.pack('<I', MAGIC):
    hint = ('a PLY file: rename it to .ply' if data.startswith(b'ply')
            else 'neither gzip (versions 1-3) nor "NGSP" (version 4)')
    raise SpzError(f'{path}: not a .spz file: {hint} (first bytes '
                   f'{data[:4].hex()})')
  if len(data) < _NGSP_HEADER.size:
    raise SpzError(f'{path}: truncated .spz: {len(data)} bytes, shorter '
                   f'than the {_NGSP_HEADER.size}-byte version 4 header')
  _, version, n, deg, fb, flags, streams, toc = (
    _NGSP_HEADER.unpack_from(data))
  h = _header(version, n, deg, fb, flags, path)
  if version < 4:
    raise SpzError(f'{path}: version {version} in a version 4 container '
                   '(versions 1-3 are gzip files); the file is damaged')
  return h, streams, toc


def _check_magic(magic, path):
  if magic != MAGIC:
    raise SpzError(
      f'{path}: not a .spz file: magic 0x{magic:08x}, expected '
      f'0x{MAGIC:08x} ("NGSP"); check the file type (.ply, .splat?)'
    )


def _check_header(h: SpzHeader, path) -> SpzHeader:
  if h.version not in READ_VERSIONS:
    raise SpzError(
      f'{path}: unsupported .spz version {h.version}; this reader reads '
      f'versions {", ".join(map(str, READ_VERSIONS))}, as Niantic\'s '
      'reference 1.1.0 does: re-save the file with a current Niantic tool'
    )
  if h.num_points == 0:
    raise SpzError(f'{path}: the .spz header says 0 Gaussians (the '
                   'reference refuses such files too)')
  if h.sh_degree > 3:
    raise SpzError(
      f'{path}: SH degree {h.sh_degree}; Gaussians here support degrees '
      '0-3: re-export the scene with SH degree 3 or less'
    )
  return h


def _sizes(h: SpzHeader) -> list[int]:
  """Bytes of positions, alphas, colours, scales, rotations, SH."""
  n, dim = h.num_points, (h.sh_degree + 1) ** 2 - 1
  return [n * (6 if h.version == 1 else 9), n, 3 * n, 3 * n,
          n * (3 if h.version < 3 else 4), 3 * dim * n]


def payload_bytes(num_points: int, sh_degree: int,
                  version: int = DEFAULT_VERSION) -> int:
  """Bytes of ``num_points`` Gaussians' attributes before compression
  (version 3: 20 a Gaussian, 3 more per SH coefficient above degree 0)."""
  return sum(_sizes(SpzHeader(version, num_points, sh_degree,
                              FRACTIONAL_BITS, False, False)))


def _read_extensions(buf: bytes, path) -> str:
  """The stored coordinate system named by extension records (else RUB)."""
  system, o = 'RUB', 0
  while len(buf) - o >= 8:
    kind, length = struct.unpack_from('<II', buf, o)
    o += 8
    if length > len(buf) - o:
      logging.warning('%s: .spz extension 0x%08x claims %d bytes, %d left; '
                      'ignored', path, kind, length, len(buf) - o)
      break
    if kind == EXT_COORDINATE_SYSTEM and length >= 4:
      v = struct.unpack_from('<I', buf, o)[0]
      if v >= len(SYSTEMS):
        raise SpzError(f'{path}: coordinate-system extension value {v} is '
                       'not a coordinate system (0-16)')
      system = SYSTEMS[v] if v else 'RUB'  # (UNSPECIFIED: RUB, as Niantic)
      if v > 8:
        raise SpzError(
          f'{path}: stored in coordinate system {system}, of the rotated '
          'family (y and z swapped); only LDB..RUF are supported: convert '
          "it to RUB with Niantic's library (PackOptions.from_coord)"
        )
    else:
      logging.info('%s: skipped .spz extension 0x%08x (%d bytes)', path,
                   kind, length)
    o += length
  return system


def _unzip(data: bytes, path) -> tuple[SpzHeader, bytes, bytes]:
  """(header, attribute bytes, extension bytes) of either container."""
  if data[:2] == b'\x1f\x8b':
    try:
      raw = gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as e:
      raise SpzError(
        f'{path}: corrupt .spz: the gzip stream does not decompress ({e}); '
        'the file is truncated or damaged: copy it again'
      ) from None
    h = _legacy_header(raw, path)
    return h, raw[_LEGACY_HEADER.size:], None
  h, streams, toc = _ngsp_header(data, path)
  decompress = _zstd_decompress()
  if decompress is None:
    raise SpzError(
      f'{path}: .spz version 4 (zstd-compressed streams, the default of '
      "Niantic's writer since 2026); reading it needs zstd, which Python "
      'has from 3.14 (compression.zstd): pip install zstandard, or '
      "re-save it as version 3 with Niantic's library (PackOptions.version "
      '= 3)'
    )
  want = [s for s in _sizes(h) if s]
  end = toc + 16 * streams
  if streams != len(want) or toc < _NGSP_HEADER.size or end > len(data):
    raise SpzError(
      f'{path}: bad version 4 table of contents ({streams} streams at byte '
      f'{toc}, expected {len(want)} within {len(data)} bytes); the file is '
      'truncated or damaged'
    )
  parts, o = [], end
  for i, size in enumerate(want):
    csize, usize = struct.unpack_from('<QQ', data, toc + 16 * i)
    if usize != size or o + csize > len(data):
      raise SpzError(
        f'{path}: truncated .spz: stream {i} is {csize} bytes at {o} of '
        f'{len(data)} ({usize} raw, expected {size}); copy the file again')
    try:
      parts.append(decompress(data[o:o + csize], size))
    except Exception as e:  # (each codec has its own error class)
      raise SpzError(f'{path}: corrupt .spz: zstd stream {i} does not '
                     f'decompress ({e})') from None
    o += csize
  return h, b''.join(parts), data[_NGSP_HEADER.size:toc]


def read_spz_header(path) -> SpzHeader:
  """The header of a ``.spz`` file (version, count, flags), nothing else.

  Args:
    path: file path.

  Returns:
    :class:`SpzHeader` (``antialiased`` is the flag Gaussians cannot hold).

  Raises:
    SpzError: not a .spz file, or a header this reader refuses.
    FileNotFoundError: no such file (named).
  """
  data = _read_bytes(path, '.spz', SpzError)
  if data[:2] == b'\x1f\x8b':
    try:
      with gzip.GzipFile(fileobj=io.BytesIO(data)) as f:
        raw = f.read(_LEGACY_HEADER.size)
    except (OSError, EOFError, zlib.error) as e:
      raise SpzError(f'{path}: corrupt .spz: the gzip stream does not '
                     f'decompress ({e})') from None
    return _legacy_header(raw, path)
  return _ngsp_header(data, path)[0]


def _unpack(h: SpzHeader, body: bytes, path):
  """Float64 arrays (means, log_scales, xyzw quats, logits, sh) as stored."""
  sizes = _sizes(h)
  if len(body) < sum(sizes):
    raise SpzError(
      f'{path}: truncated .spz payload: {h.num_points} Gaussians of SH '
      f'degree {h.sh_degree} (version {h.version}) need {sum(sizes)} bytes '
      f'after the header, the file has {len(body)}; copy the file again'
    )
  n, o, a = h.num_points, 0, []
  for s in sizes:
    a.append(np.frombuffer(body, np.uint8, s, o))
    o += s
  pos, alpha, color, scale, rot, sh = a
  if h.version == 1:
    means = pos.view('<f2').reshape(n, 3).astype(np.float64)
  else:
    b = pos.reshape(n, 3, 3).astype(np.int64)
    fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
    fixed -= (fixed & 0x800000) << 1  # sign extension
    means = fixed * 2.0 ** -h.fractional_bits
  al = np.clip(alpha / 255.0, _ALPHA_EPS, 1.0 - _ALPHA_EPS)
  logits = np.log(al) - np.log1p(-al)
  dc = (color.reshape(n, 3) / 255.0 - 0.5) / COLOR_SCALE
  log_scales = scale.reshape(n, 3) / 16.0 - 10.0
  if h.version < 3:
    xyz = rot.reshape(n, 3) / 127.5 - 1.0
    w = np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz ** 2, -1)))
    q = np.concatenate([xyz, w[:, None]], -1)
  else:
    comp = rot.view('<u4').astype(np.int64)
    big = comp >> 30
    q = np.zeros((n, 4))
    for i in (3, 2, 1, 0):
      m = big != i
      v = (comp & 511) / 511.0 * float(_SQRT1_2)
      q[:, i] = np.where(m, np.where((comp >> 9) & 1, -v, v), 0.0)
      comp = np.where(m, comp >> 10, comp)
    q[np.arange(n), big] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(q * q, -1)))
  rest = (sh.reshape(n, -1, 3) - 128.0) / 128.0
  return means, log_scales, q, logits, np.concatenate([dc[:, None], rest], 1)


def decode_spz(data: bytes, path='<bytes>', dtype=jnp.float32, *,
               stored_frame: str | None = None) -> Gaussians:
  """Decodes ``.spz`` bytes (versions 1-4) into Gaussians in the RDF frame.

  Args:
    data: the file content.
    path: used in error messages.
    dtype: float dtype of the result.
    stored_frame: the coordinate system the data is stored in; None: the
      file's (RUB unless an extension names another). ``'RDF'`` for files
      written by Niantic's ``ply_to_spz`` with default options.

  Returns:
    :class:`~physsplat_jax.types.Gaussians` (SH degree of the file).

  Raises:
    SpzError: not gzip or NGSP, wrong magic, unsupported version or SH
      degree, truncated or corrupt data, version 4 without zstd.
  """
  h, body, ext = _unzip(bytes(data), path)
  if ext is None:  # (legacy: extensions follow the attributes)
    ext = body[sum(_sizes(h)):]
  means, log_scales, q, logits, sh = _unpack(h, body, path)
  if h.has_extensions:
    system = _read_extensions(ext, path)
  else:
    system = 'RUB'
    if ext:
      logging.warning('%s: %d bytes after the Gaussians ignored', path,
                      len(ext))
  if stored_frame is not None:
    system = _system(stored_frame, path, 'stored_frame')
  if h.antialiased:
    logging.warning(
      '%s: the .spz says the scene was trained with antialiasing; render '
      "it with RenderConfig(rasterize_mode='antialiased')", path)
  fp, fq, fsh = _flips(system)
  f = lambda a: jnp.asarray(np.asarray(a).astype(np.float32)
                            .astype(np.dtype(dtype)))
  quats = np.concatenate([q[:, 3:], q[:, :3] * fq], -1)  # xyzw -> wxyz
  sh[:, 1:] *= fsh[:sh.shape[1] - 1, None]
  return Gaussians(means=f(means * fp), log_scales=f(log_scales),
                   quats=f(quats), opacity_logits=f(logits), sh=f(sh))


def load_spz(path, dtype=jnp.float32, *,
             stored_frame: str | None = None) -> Gaussians:
  """Loads a Niantic ``.spz`` file (see :func:`decode_spz`).

  Raises:
    SpzError: see :func:`decode_spz`; also a directory, or a non-float
      ``dtype``.
    FileNotFoundError: no such file (named).
  """
  float_dtype(dtype, 'load_spz', SpzError)
  data = _read_bytes(path, '.spz', SpzError)
  return decode_spz(data, os.fspath(path), dtype, stored_frame=stored_frame)


# ----------------------------------------------------------------------------
# Writing.


def _round(x: np.ndarray) -> np.ndarray:
  """C's ``round``: halves away from zero (NumPy rounds them to even)."""
  a = np.abs(x)
  r = np.floor(a)
  return np.copysign(r + (a - r >= 0.5), x)


def _to_u8(x: np.ndarray) -> np.ndarray:
  return np.clip(_round(x), 0, 255).astype(np.uint8)


def _sh_bytes(x: np.ndarray, bits: int) -> np.ndarray:
  bucket = 1 << (8 - bits)
  # (Clipped before the integer cast: a huge value cast first wrapped to
  # the wrong sign.)
  q = _round(np.clip(x * np.float32(128), -256, 256)).astype(np.int64) + 128
  q = (q + bucket // 2) // bucket * bucket
  return np.clip(q, 0, 255).astype(np.uint8)


def _quat_bytes(q: np.ndarray, version: int) -> np.ndarray:
  """Unit xyzw quaternions (float32) -> (K, 3) or (K, 4) bytes."""
  if version < 3:
    q = q * np.where(q[:, 3:] < 0, np.float32(-127.5), np.float32(127.5))
    return _to_u8(q[:, :3] + np.float32(127.5))
  k = len(q)
  big = np.argmax(np.abs(q), -1)
  negate = q[np.arange(k), big] < 0
  comp = big.astype(np.uint32)
  for i in range(4):
    m = big != i
    neg = ((q[:, i] < 0) ^ negate).astype(np.uint32)
    mag = np.floor(np.float32(511) * (np.abs(q[:, i]) / _SQRT1_2)
                   + np.float32(0.5))
    mag = np.minimum(mag, 511).astype(np.uint32)
    comp = np.where(m, (comp << 10) | (neg << 9) | mag, comp)
  return comp.astype('<u4').view(np.uint8).reshape(k, 4)


def _clamped(name, x, lo, hi, counts):
  """Counts the Gaussians (rows of ``x``) with a value outside [lo, hi]."""
  out = (x < lo) | (x > hi)
  n = int(np.count_nonzero(out.reshape(len(x), -1).any(1)))
  if n:
    counts[name] = n


def encode_spz(
  gaussians: Gaussians, *, version: int = DEFAULT_VERSION,
  antialiased: bool = False, fractional_bits: int = FRACTIONAL_BITS,
  sh1_bits: int = SH1_BITS, sh_rest_bits: int = SH_REST_BITS,
  stored_frame: str = 'RUB', path='<gaussians>',
  warned: set[str] | None = None, compress_level: int = 6,
) -> bytes:
  """Gaussians (RDF frame) -> ``.spz`` bytes (gzip, version 2 or 3).

  Args:
    gaussians: the Gaussians (normals and extras dropped).
    version: 3 (default: smallest-three rotations) or 2 (8-bit xyz).
    antialiased: set the antialiasing flag (Mip-Splatting-trained scene).
    fractional_bits: position fraction bits: step ``2**-f``, range
      ``+-2**(23 - f)``; 12 as the reference.
    sh1_bits, sh_rest_bits: SH precision of degree 1 and degrees 2-3
      (1-8; the reference's defaults 5 and 4).
    stored_frame: the coordinate system to store: ``'RUB'`` as the format
      says; ``'RDF'`` stores the data unconverted, as ``ply_to_spz`` does.
    path: used in error messages only.
    warned: values clamped to the format's ranges are logged, per field
      (``f_dc``, ``log_scales``, ``sh (degree >= 1)``); a field named in
      this set is not, and a field logged now is added to it (a writer of
      many frames passes one set: each field warns once). None: every
      field that clamps is logged.
    compress_level: gzip level, 1 (fastest) to 9. 6, zlib's default,
      for a file to keep; the pipeline's per-frame files take 1: 5-6x
      faster, 3-10 % larger (300k Gaussians of SH degree 3: 0.44 s against
      2.25 s, 0.446 against 0.402 of the raw bytes; docs/pipeline.md).

  Returns:
    The file content.

  Raises:
    SpzError: bad options, no Gaussians, non-finite values or positions
      outside the fixed-point range.
  """
  if version not in WRITE_VERSIONS:
    why = ('needs zstd, not in the standard library before Python 3.14'
           if version == 4 else 'is not written by this writer')
    raise SpzError(
      f'{path}: version={version!r}: .spz version {version} {why}; write '
      f'version {DEFAULT_VERSION} (read by Niantic\'s library) or 2')
  for name, v, lo, hi in (('sh1_bits', sh1_bits, 1, 8),
                          ('sh_rest_bits', sh_rest_bits, 1, 8),
                          ('fractional_bits', fractional_bits, 0, 23),
                          ('compress_level', compress_level, 1, 9)):
    if not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
      raise SpzError(f'{path}: {name}={v!r}; give a whole number in '
                     f'{lo}..{hi}')
  system = _system(stored_frame, path, 'stored_frame')
  try:
    v = gaussians_to_vertex(gaussians.replace(normals=None, extras={}), path)
  except SpzError:
    raise
  except PlyError as e:
    raise SpzError(f'{e}; fix or drop those Gaussians before saving a '
                   '.spz') from None
  k = len(v['x'])
  if k == 0:
    raise SpzError(f'{path}: no Gaussians to write (Niantic\'s reader '
                   'refuses a .spz of 0 Gaussians)')
  col = lambda names: np.stack([v[n] for n in names], -1).astype(np.float32)
  fp, fq, fsh = (a.astype(np.float32) for a in _flips(system))
  fixed = _round(col(['x', 'y', 'z']) * fp * np.float32(2.0 **
                                                        fractional_bits))
  lim = 2 ** 23
  bad = np.flatnonzero(np.any((fixed < -lim) | (fixed >= lim), -1))
  if bad.size:
    i = int(bad[0])
    need = np.abs(col(['x', 'y', 'z'])).max()
    fit = int(np.clip(23 - np.floor(np.log2(need)) - 1, 0, 23))
    at = [float(f'{v[c][i]:.6g}') for c in 'xyz']
    raise SpzError(
      f'{path}: Gaussian {i} at {at} ({bad.size} in all) lies '
      f'outside the .spz position range +-{2.0 ** (23 - fractional_bits):g} '
      f'of fractional_bits={fractional_bits} (24-bit fixed point); pass '
      f'fractional_bits={fit} (step {2.0 ** -fit:g}) or rescale the scene')
  fixed = fixed.astype(np.int64).reshape(-1)
  pos = np.stack([fixed & 255, (fixed >> 8) & 255, (fixed >> 16) & 255], -1)
  logit = v['opacity'].astype(np.float32)
  with np.errstate(over='ignore'):
    alpha = np.float32(1) / (np.float32(1) + np.exp(-logit))
  dc = col(['f_dc_0', 'f_dc_1', 'f_dc_2'])
  log_s = col(['scale_0', 'scale_1', 'scale_2'])
  clamped = {}
  _clamped('f_dc', dc, -0.5 / COLOR_SCALE, 0.5 / COLOR_SCALE, clamped)
  _clamped('log_scales', log_s, -10.0, 5.9375, clamped)
  q = col(['rot_1', 'rot_2', 'rot_3', 'rot_0'])  # xyzw
  norm = np.sqrt(np.sum(q * q, -1, keepdims=True))
  q = np.where(norm > 0, q / np.where(norm > 0, norm, 1),
               np.float32([0, 0, 0, 1]))
  q[:, :3] *= fq
  rest = np.asarray(gaussians.sh)[:, 1:].astype(np.float32)  # (K, B-1, 3)
  rest = rest * fsh[:rest.shape[1], None]
  _clamped('sh (degree >= 1)', rest, -1.0, 127 / 128, clamped)
  new = [k for k in clamped if warned is None or k not in warned]
  if new:
    logging.warning('%s: values clamped to the .spz ranges (Gaussians: %s)',
                    path, ', '.join(f'{k}: {clamped[k]}' for k in new))
    if warned is not None:
      warned.update(new)
  sh = np.concatenate([_sh_bytes(rest[:, :3], sh1_bits),
                       _sh_bytes(rest[:, 3:], sh_rest_bits)], 1)
  flags = FLAG_ANTIALIASED if antialiased else 0
  header = _LEGACY_HEADER.pack(MAGIC, version, k, gaussians.sh_degree,
                               fractional_bits, flags, 0)
  body = [
    pos.astype(np.uint8),
    _to_u8(alpha * np.float32(255)),
    _to_u8(dc * (np.float32(COLOR_SCALE) * np.float32(255))
           + np.float32(127.5)),
    _to_u8((log_s + np.float32(10)) * np.float32(16)),
    _quat_bytes(q, version),
    sh,
  ]
  raw = header + b''.join(np.ascontiguousarray(b).tobytes() for b in body)
  return gzip.compress(raw, compresslevel=int(compress_level), mtime=0)


def save_spz(path, gaussians: Gaussians, **options) -> None:
  """Writes Gaussians as a Niantic ``.spz`` file (lossy; see the module).

  Args:
    path: output path (parent directories are created).
    gaussians: the Gaussians, RDF frame (as loaded from an INRIA PLY).
    **options: as :func:`encode_spz` (``version``, ``antialiased``,
      ``fractional_bits``, ``sh1_bits``, ``sh_rest_bits``,
      ``stored_frame``).

  Raises:
    SpzError: see :func:`encode_spz`; also a path that cannot be written.
  """
  check_writable_file(path, '.spz', SpzError)
  data = encode_spz(gaussians, path=os.fspath(path), **options)
  with open_output(path, '.spz', SpzError) as f:
    f.write(data)
