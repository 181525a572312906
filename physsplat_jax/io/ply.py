"""3D Gaussian Splatting PLY files: the INRIA layout and PlayCanvas's
compressed PLY, over the NumPy PLY reader and writer of
:mod:`physsplat_jax.io.ply_format` (no plyfile).

The INRIA layout (``graphdeco-inria/gaussian-splatting``,
``scene/gaussian_model.py``) is one ``vertex`` element of float32 properties::

  x y z  [nx ny nz]  f_dc_0..2  [f_rest_0..R-1]  opacity  scale_0..2  rot_0..3

All values are pre-activation (``opacity = sigmoid(opacity)``,
``scale = exp(scale_i)``, ``rot_0`` is ``w``), exactly the convention of
:class:`physsplat_jax.types.Gaussians`. ``f_rest`` is stored channel-major:
``f_rest_{c * (B - 1) + k}`` is channel ``c`` of SH coefficient ``k + 1``, so
``R = 3 (B - 1)`` is 0, 9, 24 or 45 for SH degree 0, 1, 2 or 3; in memory the
coefficients are ``(K, B, 3)``. ``f_rest_*``, ``scale_*`` and ``rot_*`` are
matched by their numeric suffix, not by file order.

What is read: binary little- and big-endian and ASCII PLY 1.0 with any scalar
types (``char/int8 uchar/uint8 short/int16 ushort/uint16 int/int32
uint/uint32 float/float32 double/float64``), converted to the requested float
dtype; normals are optional and kept in ``Gaussians.normals``; every other
scalar vertex property (``object_id``, ``label``, ...) is kept in
``Gaussians.extras`` with its integer type (floats are cast to ``dtype``) and
written back after ``rot_3``. Elements other than ``vertex`` are parsed (so
list properties such as faces are skipped correctly) and then ignored. The
PlayCanvas/SuperSplat ``compressed.ply`` (``chunk``/``vertex``/``sh``) is
read and written too (layout below).

What is written: binary little-endian (default) or ASCII, ``\\n`` line
endings, float32 for the Gaussian fields, so that ``save_ply(load_ply(f))``
reproduces an INRIA file byte for byte (normals are written only when present,
``f_rest`` only when the SH degree is above 0).

PlayCanvas compressed PLY (``playcanvas/splat-transform``,
``writers/compressed-chunk.ts`` and ``readers/decompress-ply.ts``): Gaussians
in chunks of 256; ``element chunk`` holds per-chunk float32 bounds
``min_x min_y min_z max_x max_y max_z`` (positions), ``min_scale_*``,
``max_scale_*`` (log-scales, clamped to [-20, 20]) and optionally
``min_r.. max_b`` (colours ``0.5 + C0 f_dc``); ``element vertex`` holds four
uint32 per Gaussian:

* ``packed_position``/``packed_scale``: 11-10-11 bit unorms ``(x << 21) |
  (y << 11) | z`` of ``t = (v - min) / (max - min)``, decoded as
  ``min (1 - t) + max t``;
* ``packed_rotation``: 2 bits for the index of the largest component of the
  unit quaternion ``(rot_0..rot_3)`` (made positive), then the other three
  in order as 10-bit unorms of ``q_i sqrt(2)/2 + 0.5``; the largest is
  ``sqrt(1 - sum of squares)``;
* ``packed_color``: 8-8-8-8 bit ``r g b sigmoid(opacity)``.

``element sh`` (optional) holds ``f_rest_*`` as uchar in the INRIA
channel-major order: ``byte = trunc(256 (f / 8 + 0.5))``, decoded as
``8 (n - 0.5)`` with ``n = (byte + 0.5) / 256`` (0 -> 0, 255 -> 1). An
opacity byte of 0 or 255 would decode to an infinite logit; we clamp it to
``logit(0.5 / 255)`` and ``logit(254.5 / 255)`` (about -/+6.2).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Mapping

import jax.numpy as jnp
import numpy as np

from physsplat_jax.gaussians import SH_C0
from physsplat_jax.io.ply_format import FORMATS as FORMATS
from physsplat_jax.io.ply_format import PLY_TYPES as PLY_TYPES
from physsplat_jax.io.ply_format import PathLike as PathLike
from physsplat_jax.io.ply_format import PlyElement as PlyElement
from physsplat_jax.io.ply_format import PlyError as PlyError
from physsplat_jax.io.ply_format import PlyHeader as PlyHeader
from physsplat_jax.io.ply_format import PlyProperty as PlyProperty
from physsplat_jax.io.ply_format import _header_start
from physsplat_jax.io.ply_format import _read
from physsplat_jax.io.ply_format import check_writable_file
from physsplat_jax.io.ply_format import open_output
from physsplat_jax.io.ply_format import read_ply as read_ply
from physsplat_jax.io.ply_format import read_ply_header as read_ply_header
from physsplat_jax.io.ply_format import write_ply as write_ply
from physsplat_jax.types import Gaussians
from physsplat_jax.types import device_array


# Number of f_rest_* properties for SH degree 0..3.
F_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}
REQUIRED = (
  ('x', 'y', 'z')
  + tuple(f'f_dc_{i}' for i in range(3))
  + ('opacity',)
  + tuple(f'scale_{i}' for i in range(3))
  + tuple(f'rot_{i}' for i in range(4))
)
NORMALS = ('nx', 'ny', 'nz')
# ----------------------------------------------------------------------------
# Gaussians <-> PLY.


def _indexed(names, prefix):
  """``{i: name}`` for names ``prefix<i>``."""
  out = {}
  for n in names:
    if n.startswith(prefix) and n[len(prefix) :].isdigit():
      out[int(n[len(prefix) :])] = n
  return out


def float_dtype(dtype, what: str, error=PlyError) -> np.dtype:
  """``dtype`` as a NumPy float dtype, or ``error`` naming ``what``."""
  try:
    dt = np.dtype(jnp.dtype(dtype))
  except TypeError:
    dt = None
  if dt is None or not jnp.issubdtype(dt, jnp.floating):
    name = getattr(dtype, '__name__', None) or repr(dtype)
    raise error(
      f'{what}: dtype={name}; Gaussians need a float dtype (jnp.float32, '
      'the default, or jnp.float64, jnp.float16, jnp.bfloat16)'
    )
  return dt


def _check_range(vertex, names, path, dtype) -> None:
  """Refuses values that the cast to ``dtype`` would turn into inf."""
  top = float(jnp.finfo(dtype).max)
  for n in names:
    a = vertex[n]
    info = np.finfo if a.dtype.kind == 'f' else np.iinfo
    if a.dtype.kind not in 'fiu' or float(info(a.dtype).max) <= top:
      continue
    with np.errstate(over='ignore'):
      over = np.flatnonzero(np.isinf(a.astype(dtype)) & np.isfinite(a))
    if over.size:
      i = int(over[0])
      v = f'{float(a[i]):.6g}' if a.dtype.kind == 'f' else str(a[i])
      raise PlyError(
        f'{path}: vertex property {n!r} holds {v} in row {i} '
        f'({over.size} row(s) in all), beyond the {np.dtype(dtype).name} '
        f'range (|v| <= {top:.4g}) the Gaussians are loaded as; fix those '
        'rows, or load with dtype=jnp.float64 (jax x64 enabled)'
      )


def _vertex_to_gaussians(
  vertex: Mapping[str, np.ndarray], path, dtype, mat=None
) -> Gaussians:
  names = list(vertex)
  where = {n: i for i, n in enumerate(names)}
  missing = [n for n in REQUIRED if n not in vertex]
  if missing:
    raise PlyError(
      f'{path}: vertex element is missing propert'
      f'{"y" if len(missing) == 1 else "ies"} {missing}; a 3DGS PLY needs '
      f'{" ".join(REQUIRED)} (and optionally nx ny nz, f_rest_*)'
    )
  rest = _indexed(names, 'f_rest_')
  if len(rest) not in F_REST_COUNTS or sorted(rest) != list(range(len(rest))):
    raise PlyError(
      f'{path}: found {len(rest)} f_rest_* properties '
      f'(indices {sorted(rest)[:5]}...); expected f_rest_0..f_rest_{{R-1}} '
      'with R = 0, 9, 24 or 45 (SH degree 0..3)'
    )
  for name in names:
    if isinstance(vertex[name], list):
      raise PlyError(
        f'{path}: vertex property {name!r} is a list; 3DGS PLY vertices '
        'have scalar properties only'
      )
  count = len(vertex['x'])
  used = list(REQUIRED) + [rest[i] for i in range(len(rest))]
  has_normals = all(n in vertex for n in NORMALS)
  if has_normals:
    used += list(NORMALS)
  bad = []
  all_finite = (
    mat is not None and mat.dtype.kind == 'f' and np.isfinite(mat).all()
  )
  for n in [] if all_finite else used:
    col = vertex[n]
    if col.dtype.kind == 'f':
      nonfinite = int(np.count_nonzero(~np.isfinite(col)))
      if nonfinite:
        bad.append(f'{n}: {nonfinite} of {count} rows')
  if bad:
    raise PlyError(
      f'{path}: non-finite values (NaN/inf) in {"; ".join(bad)}; clean '
      'the file (e.g. drop those rows) before loading'
    )
  floats = [n for n in names if n not in used and vertex[n].dtype.kind == 'f']
  _check_range(vertex, used + floats, path, dtype)
  def col(ns):
    idx = [where[n] for n in ns]
    if mat is not None and idx == list(range(idx[0], idx[0] + len(idx))):
      return mat[:, idx[0] : idx[0] + len(idx)]  # contiguous block: a view
    return np.stack([vertex[n] for n in ns], axis=-1)

  nr = len(rest) // 3
  dc = col([f'f_dc_{i}' for i in range(3)])[:, None, :]
  if nr:
    fr = col([rest[i] for i in range(len(rest))]).reshape(count, 3, nr)
    sh = np.concatenate([dc, fr.transpose(0, 2, 1)], axis=1)
  else:
    sh = dc
  # One correctly rounded cast (float64 -> float32 directly is exact-nearest).
  f = lambda a: device_array(a, dtype)
  extras = {}
  for n in names:
    if n in used or (has_normals and n in NORMALS):
      continue
    a = vertex[n]
    if a.dtype.kind == 'f':
      extras[n] = f(a)
    elif a.dtype.itemsize > 4:
      extras[n] = device_array(a.astype(np.int32))
    else:
      extras[n] = device_array(a)
  return Gaussians(
    means=f(col(['x', 'y', 'z'])),
    log_scales=f(col([f'scale_{i}' for i in range(3)])),
    quats=f(col([f'rot_{i}' for i in range(4)])),
    opacity_logits=f(vertex['opacity']),
    sh=f(sh),
    normals=f(col(NORMALS)) if has_normals else None,
    extras=extras,
  )


def load_ply(path: PathLike, dtype=jnp.float32) -> Gaussians:
  """Loads a 3DGS PLY file (INRIA layout or PlayCanvas compressed).

  Args:
    path: file path.
    dtype: float dtype of the returned arrays (float32 keeps the file's
      float32 values exactly).

  Returns:
    :class:`~physsplat_jax.types.Gaussians` with K rows: means (K, 3),
    log_scales (K, 3), quats (K, 4) wxyz, opacity_logits (K,), sh (K, B, 3),
    normals (K, 3) or None, extras {name: (K,)}.

  Raises:
    PlyError: not a PLY, unsupported format, truncated payload or data
      after it, missing properties, non-finite values or values beyond
      ``dtype``'s range, wrong counts or a non-float ``dtype`` (the message
      names the file and the problem).
    FileNotFoundError: no such file (named).
  """
  dtype = float_dtype(dtype, f'load_ply({os.fspath(path)!r})'
                      if isinstance(path, (str, os.PathLike)) else 'load_ply')
  header, elements, matrices = _read(path)
  if 'vertex' not in elements:
    raise PlyError(
      f'{path}: no "vertex" element (elements: '
      f'{[e.name for e in header.elements]}); a 3DGS PLY stores one vertex '
      'per Gaussian'
    )
  if 'chunk' in elements and 'packed_position' in elements['vertex']:
    return decode_compressed(elements, path, dtype)
  return _vertex_to_gaussians(
    elements['vertex'], path, dtype, matrices.get('vertex')
  )


def _vertex_matrix(g: Gaussians, path) -> tuple[list[str], np.ndarray]:
  """INRIA property names and the (K, P) float32 matrix of the Gaussians."""
  k = np.shape(g.means)[0] if np.ndim(g.means) == 2 else -1
  expect = {
    'means': (k, 3),
    'log_scales': (k, 3),
    'quats': (k, 4),
    'opacity_logits': (k,),
  }
  if g.normals is not None:
    expect['normals'] = (k, 3)
  for name, shape in expect.items():
    got = np.shape(getattr(g, name))
    if got != shape or k < 0:
      raise PlyError(
        f'{path}: Gaussians.{name} has shape {got}, expected {shape} '
        '(K = number of Gaussians from means)'
      )
  sh_shape = np.shape(g.sh)
  if len(sh_shape) != 3 or sh_shape[0] != k or sh_shape[2] != 3 or (
    sh_shape[1] not in (1, 4, 9, 16)
  ):
    raise PlyError(
      f'{path}: Gaussians.sh has shape {sh_shape}, expected ({k}, B, 3) '
      'with B in 1, 4, 9, 16'
    )
  def f32(a):
    a = np.asarray(a).astype(np.float32)
    return a if a.ndim == 2 else a[:, None]

  sh = np.asarray(g.sh).astype(np.float32)
  nr = 3 * (sh.shape[1] - 1)
  names = ['x', 'y', 'z']
  blocks = [f32(g.means)]
  if g.normals is not None:
    names += list(NORMALS)
    blocks.append(f32(g.normals))
  names += [f'f_dc_{c}' for c in range(3)] + [f'f_rest_{i}' for i in range(nr)]
  blocks += [sh[:, 0, :], sh[:, 1:, :].transpose(0, 2, 1).reshape(k, nr)]
  names += ['opacity'] + [f'scale_{i}' for i in range(3)]
  names += [f'rot_{i}' for i in range(4)]
  blocks += [f32(g.opacity_logits), f32(g.log_scales), f32(g.quats)]
  mat = np.concatenate(blocks, axis=1)
  if not np.isfinite(mat).all():
    counts = np.count_nonzero(~np.isfinite(mat), axis=0)
    bad = [f'{n}: {c} rows' for n, c in zip(names, counts) if c]
    raise PlyError(
      f'{path}: refusing to write non-finite values ({"; ".join(bad)})'
    )
  return names, mat


def gaussians_to_vertex(gaussians: Gaussians, path='<gaussians>') -> dict:
  """The INRIA-ordered ``{property: (K,) array}`` of a set of Gaussians.

  Args:
    gaussians: the Gaussians (any float dtype; written as float32).
    path: used in error messages only.

  Returns:
    An ordered dict of property name -> (K,) NumPy array (Gaussian fields
    float32, then the extras with their own dtypes).

  Raises:
    PlyError: inconsistent shapes, non-finite values or clashing extras.
  """
  g = gaussians
  names, mat = _vertex_matrix(g, path)
  k = mat.shape[0]
  out = {n: mat[:, i] for i, n in enumerate(names)}
  for name, a in g.extras.items():
    if name in out or (g.normals is not None and name in NORMALS):
      raise PlyError(
        f'{path}: Gaussians.extras[{name!r}] clashes with a 3DGS property '
        'name; rename it'
      )
    a = np.asarray(a)
    if a.shape != (k,):
      raise PlyError(
        f'{path}: Gaussians.extras[{name!r}] has shape {a.shape}; extras '
        f'must be per-Gaussian ({k},) arrays'
      )
    out[name] = a
  return out


def save_ply(
  path: PathLike, gaussians: Gaussians, *, binary: bool = True
) -> None:
  """Writes Gaussians as an INRIA 3DGS PLY file.

  Property order: ``x y z [nx ny nz] f_dc_0..2 [f_rest_*] opacity scale_0..2
  rot_0..3 [extras...]``; Gaussian fields as float32, extras with their own
  type. Normals are written only when ``gaussians.normals`` is set (INRIA
  writes zeros; pass ``normals=jnp.zeros((K, 3))`` for the full 62-property
  layout).

  Args:
    path: output path (parent directories are created).
    gaussians: the Gaussians.
    binary: binary little-endian (True) or ASCII (False).

  Raises:
    PlyError: inconsistent shapes, non-finite values, bad extras or a path
      that cannot be written (a directory, or a file where a parent folder
      should be).
  """
  check_writable_file(path)
  fast = binary and not gaussians.extras
  if fast:
    names, mat = _vertex_matrix(gaussians, path)
  else:
    vertex = gaussians_to_vertex(gaussians, path)
  if fast:
    # One contiguous float32 matrix, as INRIA writes it.
    lines = _header_start('binary_little_endian', ())
    lines.append(f'element vertex {mat.shape[0]}')
    lines += [f'property float {n}' for n in names] + ['end_header']
    with open_output(path) as f:
      f.write(('\n'.join(lines) + '\n').encode('ascii'))
      f.write(mat.astype('<f4', copy=False).tobytes())
    return
  write_ply(
    path,
    {'vertex': vertex},
    format='binary_little_endian' if binary else 'ascii',
  )



# ----------------------------------------------------------------------------
# PlayCanvas compressed PLY.

CHUNK_SIZE = 256
CHUNK_PROPS = (
  'min_x', 'min_y', 'min_z', 'max_x', 'max_y', 'max_z',
  'min_scale_x', 'min_scale_y', 'min_scale_z',
  'max_scale_x', 'max_scale_y', 'max_scale_z',
)  # fmt: skip
CHUNK_COLOR_PROPS = ('min_r', 'min_g', 'min_b', 'max_r', 'max_g', 'max_b')
PACKED_PROPS = (
  'packed_position', 'packed_rotation', 'packed_scale', 'packed_color'
)  # fmt: skip
# Log-scale bounds of the PlayCanvas encoder ("sometimes values are at
# infinity").
_SCALE_CLAMP = 20.0
# Opacity bytes 0/255 would decode to -/+inf; this keeps logits finite.
_ALPHA_EPS = 0.5 / 255.0


def _sh_byte_table() -> np.ndarray:
  b = np.arange(256, dtype=np.float64)
  n = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b + 0.5) / 256.0))
  return ((n - 0.5) * 8.0).astype(np.float32)  # exact in float32


# Decoded value of each SH byte (a lookup is one pass over the SH bytes).
_SH_BYTE_TABLE = _sh_byte_table()


def _unorm(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
  t = (1 << bits) - 1
  return ((v >> np.uint32(shift)) & np.uint32(t)).astype(np.float64) / t


def _pack_unorm(x: np.ndarray, bits: int) -> np.ndarray:
  t = (1 << bits) - 1
  return np.clip(np.floor(x * t + 0.5), 0, t).astype(np.uint32)


def _lerp(a, b, t):
  return a * (1.0 - t) + b * t


def decode_compressed(
  elements: Mapping[str, Mapping[str, np.ndarray]], path='<ply>',
  dtype=jnp.float32
) -> Gaussians:
  """Decodes the elements of a PlayCanvas ``compressed.ply`` into Gaussians.

  Args:
    elements: ``{element: {property: array}}`` as returned by
      :func:`read_ply`, with ``chunk``, ``vertex`` and optionally ``sh``.
    path: used in error messages.
    dtype: float dtype of the result.

  Returns:
    :class:`~physsplat_jax.types.Gaussians` (no normals, no extras).

  Raises:
    PlyError: missing properties, wrong counts or bad types.
  """
  chunk, vertex = elements['chunk'], elements['vertex']
  for ename, el, names in (
    ('chunk', chunk, CHUNK_PROPS),
    ('vertex', vertex, PACKED_PROPS),
  ):
    missing = [n for n in names if n not in el]
    if missing:
      raise PlyError(
        f'{path}: compressed PLY element {ename!r} is missing {missing}; '
        f'it needs {" ".join(names)}'
      )
  for n in PACKED_PROPS:
    if vertex[n].dtype.kind not in 'iu':
      raise PlyError(
        f'{path}: compressed PLY property vertex.{n} is '
        f'{vertex[n].dtype}; expected uint'
      )
  k = len(vertex['packed_position'])
  num_chunks = len(chunk['min_x'])
  if num_chunks != -(-k // CHUNK_SIZE):
    raise PlyError(
      f'{path}: compressed PLY has {num_chunks} chunks for {k} Gaussians; '
      f'expected ceil({k} / {CHUNK_SIZE}) = {-(-k // CHUNK_SIZE)}'
    )
  has_color = all(n in chunk for n in CHUNK_COLOR_PROPS)
  c = {
    n: np.asarray(chunk[n], np.float32).astype(np.float64)
    for n in CHUNK_PROPS + (CHUNK_COLOR_PROPS if has_color else ())
  }
  bad = [n for n, a in c.items() if not np.all(np.isfinite(a))]
  if bad:
    raise PlyError(f'{path}: non-finite chunk bounds in {bad}')
  ci = np.arange(k) // CHUNK_SIZE
  ch = {n: a[ci] for n, a in c.items()}
  u32 = lambda n: vertex[n].astype(np.uint32)

  def unpack_111011(v, lo, hi):
    t = [_unorm(v, 21, 11), _unorm(v, 11, 10), _unorm(v, 0, 11)]
    return np.stack(
      [_lerp(ch[lo[i]], ch[hi[i]], t[i]) for i in range(3)], axis=-1
    )

  means = unpack_111011(
    u32('packed_position'), ('min_x', 'min_y', 'min_z'),
    ('max_x', 'max_y', 'max_z')
  )  # fmt: skip
  log_scales = unpack_111011(
    u32('packed_scale'),
    ('min_scale_x', 'min_scale_y', 'min_scale_z'),
    ('max_scale_x', 'max_scale_y', 'max_scale_z'),
  )
  rot = u32('packed_rotation')
  abc = np.stack(
    [(_unorm(rot, s, 10) - 0.5) * np.sqrt(2.0) for s in (20, 10, 0)], -1
  )
  largest = (rot >> np.uint32(30)).astype(np.int64)
  m = np.sqrt(np.maximum(0.0, 1.0 - np.sum(abc**2, axis=-1)))
  quats = np.empty((k, 4))
  rows = np.arange(k)
  quats[rows, largest] = m
  others = np.array([[j for j in range(4) if j != i] for i in range(4)])
  for col in range(3):
    quats[rows, others[largest, col]] = abc[:, col]
  color = u32('packed_color')
  rgba = np.stack([_unorm(color, s, 8) for s in (24, 16, 8, 0)], axis=-1)
  rgb = rgba[:, :3]
  if has_color:
    rgb = np.stack(
      [_lerp(ch[f'min_{a}'], ch[f'max_{a}'], rgb[:, i])
       for i, a in enumerate('rgb')], axis=-1
    )  # fmt: skip
  dc = (rgb - 0.5) / SH_C0
  alpha = np.clip(rgba[:, 3], _ALPHA_EPS, 1.0 - _ALPHA_EPS)
  opacity = -np.log(1.0 / alpha - 1.0)
  sh = dc[:, None, :].astype(np.float32)
  if 'sh' in elements:
    shel = elements['sh']
    rest = _indexed(list(shel), 'f_rest_')
    if len(rest) not in (9, 24, 45) or sorted(rest) != list(range(len(rest))):
      raise PlyError(
        f'{path}: compressed PLY "sh" element has {len(rest)} f_rest_* '
        'properties; expected f_rest_0..f_rest_{R-1} with R = 9, 24 or 45'
      )
    if len(shel[rest[0]]) != k:
      raise PlyError(
        f'{path}: compressed PLY "sh" element has {len(shel[rest[0]])} rows '
        f'but there are {k} Gaussians'
      )
    b = np.stack([shel[rest[i]] for i in range(len(rest))], -1)
    if b.dtype.kind not in 'iu' or b.size and (b.min() < 0 or b.max() > 255):
      raise PlyError(
        f'{path}: compressed PLY "sh" values must be uchar (0..255)'
      )
    fr = _SH_BYTE_TABLE[b.astype(np.uint8)].reshape(k, 3, len(rest) // 3)
    sh = np.concatenate([sh, fr.transpose(0, 2, 1)], axis=1)
  # Decoded in float64 then rounded to float32, as the reference decoder does.
  f = lambda a: device_array(a.astype(np.float32).astype(np.dtype(dtype)))
  return Gaussians(
    means=f(means),
    log_scales=f(log_scales),
    quats=f(quats),
    opacity_logits=f(opacity),
    sh=f(sh),
  )


def encode_compressed(gaussians: Gaussians, path='<gaussians>') -> dict:
  """Encodes Gaussians as PlayCanvas compressed-PLY elements (file order kept).

  Args:
    gaussians: the Gaussians (normals and extras are not stored).
    path: used in error messages.

  Returns:
    ``{'chunk': {...}, 'vertex': {...}[, 'sh': {...}]}`` for
    :func:`write_ply`.
  """
  v = gaussians_to_vertex(gaussians.replace(normals=None, extras={}), path)
  k = len(v['x'])
  if k == 0:
    raise PlyError(f'{path}: cannot write an empty compressed PLY')
  num_chunks = -(-k // CHUNK_SIZE)
  pad = num_chunks * CHUNK_SIZE - k

  def chunked(a):
    # The encoder repeats the last Gaussian to fill the final chunk.
    a = np.concatenate([a, np.repeat(a[-1:], pad, axis=0)])
    return a.reshape(num_chunks, CHUNK_SIZE)

  def quantize(names, clamp=None):
    cols, lo, hi = [], [], []
    for n in names:
      a = v[n].astype(np.float64)
      ca = chunked(a)
      mn, mx = ca.min(axis=1), ca.max(axis=1)
      if clamp is not None:
        mn, mx = np.clip(mn, -clamp, clamp), np.clip(mx, -clamp, clamp)
      mnr = np.repeat(mn, CHUNK_SIZE)[:k]
      mxr = np.repeat(mx, CHUNK_SIZE)[:k]
      rng = mxr - mnr
      t = np.where(rng < 1e-5, 0.0, (a - mnr) / np.where(rng > 0, rng, 1.0))
      t = np.where(a <= mnr, 0.0, np.where(a >= mxr, 1.0, t))
      cols.append(t)
      lo.append(mn.astype(np.float32))
      hi.append(mx.astype(np.float32))
    return cols, lo, hi

  def pack_111011(t):
    return (
      (_pack_unorm(t[0], 11) << np.uint32(21))
      | (_pack_unorm(t[1], 10) << np.uint32(11))
      | _pack_unorm(t[2], 11)
    )

  pt, plo, phi = quantize(('x', 'y', 'z'))
  st, slo, shi = quantize(('scale_0', 'scale_1', 'scale_2'), _SCALE_CLAMP)
  for c in range(3):
    v[f'_rgb_{c}'] = (v[f'f_dc_{c}'].astype(np.float64) * SH_C0 + 0.5).astype(
      np.float32
    )
  ct, clo, chi = quantize(('_rgb_0', '_rgb_1', '_rgb_2'))
  alpha = 1.0 / (1.0 + np.exp(-v['opacity'].astype(np.float64)))
  color = (
    (_pack_unorm(ct[0], 8) << np.uint32(24))
    | (_pack_unorm(ct[1], 8) << np.uint32(16))
    | (_pack_unorm(ct[2], 8) << np.uint32(8))
    | _pack_unorm(alpha, 8)
  )
  q = np.stack([v[f'rot_{i}'] for i in range(4)], -1).astype(np.float64)
  qn = np.linalg.norm(q, axis=-1, keepdims=True)
  q = np.where(qn > 0, q / np.where(qn > 0, qn, 1.0), np.array([1.0, 0, 0, 0]))
  largest = np.argmax(np.abs(q), axis=-1)
  rows = np.arange(k)
  q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
  rot = largest.astype(np.uint32)
  others = np.array([[j for j in range(4) if j != i] for i in range(4)])
  for col in range(3):
    comp = q[rows, others[largest, col]]
    rot = (rot << np.uint32(10)) | _pack_unorm(
      comp * np.sqrt(2.0) * 0.5 + 0.5, 10
    )
  chunk = {}
  names = CHUNK_PROPS + CHUNK_COLOR_PROPS
  values = plo + phi + slo + shi + clo + chi
  for n, a in zip(names, values):
    chunk[n] = a
  out = {
    'chunk': chunk,
    'vertex': {
      'packed_position': pack_111011(pt),
      'packed_rotation': rot,
      'packed_scale': pack_111011(st),
      'packed_color': color,
    },
  }
  rest = [n for n in v if n.startswith('f_rest_')]
  if rest:
    out['sh'] = {
      n: np.clip(
        np.trunc((v[n].astype(np.float64) / 8.0 + 0.5) * 256.0), 0, 255
      ).astype(np.uint8)
      for n in rest
    }
  return out


def save_compressed_ply(path: PathLike, gaussians: Gaussians) -> None:
  """Writes Gaussians as a PlayCanvas/SuperSplat ``compressed.ply``.

  Lossy (about 16 bytes per Gaussian plus 1 byte per SH coefficient); the
  Gaussians keep their order (PlayCanvas sorts them in Morton order first,
  which only changes the quantisation chunks). Normals and extras are
  dropped. See the module docstring for the layout.

  Args:
    path: output path (parent directories are created).
    gaussians: the Gaussians.

  Raises:
    PlyError: inconsistent shapes, non-finite values or no Gaussians.
  """
  check_writable_file(path)
  elements = encode_compressed(gaussians, path)
  write_ply(path, elements, comments=('Generated by physsplat_jax',))
