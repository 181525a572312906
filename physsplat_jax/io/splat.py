"""antimatter15 ``.splat`` files: 32 bytes per Gaussian, no header, no SH.

Layout (``antimatter15/splat:convert.py``, ``main.js``; also written by
``gsplat/exporter.py:splat2splat_bytes`` and read by mkkellogg's
``SplatParser.js``), little-endian, one row per Gaussian::

  float32 x, y, z                 position
  float32 sx, sy, sz              scale = exp(log_scale)   (activated)
  uint8   r, g, b, a              (0.5 + C0 f_dc) * 255, sigmoid(opacity) * 255
  uint8   q0, q1, q2, q3          q / |q| * 128 + 128, wxyz (rot_0..rot_3)

Writing quantises colour, opacity and rotation to 8 bits (rounded to nearest;
antimatter15's converter truncates) and drops SH degree > 0, normals and
extras. By default rows are sorted by decreasing ``exp(sum log_scale) *
sigmoid(opacity)`` as antimatter15 does (viewers stream big splats first).

Reading inverts this: ``log_scale = log(s)``, ``opacity = logit(a / 255)``,
``f_dc = (rgb / 255 - 0.5) / C0``, ``q = (byte - 128) / 128`` (not
normalised; the activation normalises). Opacity bytes 0 and 255 map to
``logit(0.5 / 255)`` and ``logit(254.5 / 255)`` so logits stay finite; zero
scales are an error (their log is -inf).
"""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np

from physsplat_jax.gaussians import SH_C0
from physsplat_jax.io.ply import PlyError, gaussians_to_vertex
from physsplat_jax.io.ply import float_dtype
from physsplat_jax.io.ply_format import _read_bytes, check_writable_file
from physsplat_jax.io.ply_format import open_output
from physsplat_jax.types import Gaussians

ROW_BYTES = 32
SPLAT_DTYPE = np.dtype([
  ('position', '<f4', (3,)),
  ('scale', '<f4', (3,)),
  ('rgba', 'u1', (4,)),
  ('rot', 'u1', (4,)),
])
_ALPHA_EPS = 0.5 / 255.0


class SplatError(PlyError):
  """A ``.splat`` file that cannot be read or Gaussians that cannot be written.

  A subclass of :class:`~physsplat_jax.io.ply.PlyError` (so of ValueError).
  """


def _to_byte(x: np.ndarray) -> np.ndarray:
  return np.clip(np.round(x), 0, 255).astype(np.uint8)


def encode_splat(
  gaussians: Gaussians, *, sort: bool = True, path='<gaussians>'
) -> np.ndarray:
  """Gaussians -> structured ``(K,)`` array of :data:`SPLAT_DTYPE` rows.

  Args:
    gaussians: the Gaussians (SH degree > 0, normals and extras dropped).
    sort: order rows by decreasing ``exp(sum log_scale) * opacity``.
    path: used in error messages only.

  Returns:
    (K,) structured array; ``.tobytes()`` is the file content.

  Raises:
    SplatError: inconsistent shapes, non-finite values, or log-scales whose
      ``exp`` is not a positive finite float32 (the file stores scales).
  """
  v = gaussians_to_vertex(
    gaussians.replace(normals=None, extras={}), path
  )
  k = len(v['x'])
  f64 = lambda names: np.stack([v[n] for n in names], -1).astype(np.float64)
  log_scales = f64(['scale_0', 'scale_1', 'scale_2'])
  with np.errstate(over='ignore'):
    scales = np.exp(log_scales).astype(np.float32)
  bad = np.flatnonzero(~np.all(np.isfinite(scales) & (scales > 0), axis=-1))
  if bad.size:
    i = int(bad[0])
    raise SplatError(
      f'{path}: Gaussians.log_scales row {i} = '
      f'{[float(f"{x:.6g}") for x in log_scales[i]]} '
      f'({bad.size} row(s) in all): a .splat file stores exp(log_scale) as '
      'float32, which is inf or 0 for these; the loadable range is about '
      '[-103, 88]: clamp or drop those Gaussians before saving'
    )
  opacity = 1.0 / (1.0 + np.exp(-v['opacity'].astype(np.float64)))
  q = f64(['rot_0', 'rot_1', 'rot_2', 'rot_3'])
  qn = np.linalg.norm(q, axis=-1, keepdims=True)
  q = np.where(qn > 0, q / np.where(qn > 0, qn, 1.0), [1.0, 0.0, 0.0, 0.0])
  rows = np.empty(k, SPLAT_DTYPE)
  rows['position'] = np.stack([v['x'], v['y'], v['z']], -1)
  rows['scale'] = scales
  rgb = 0.5 + SH_C0 * f64(['f_dc_0', 'f_dc_1', 'f_dc_2'])
  rows['rgba'] = _to_byte(np.concatenate([rgb, opacity[:, None]], -1) * 255)
  rows['rot'] = _to_byte(q * 128.0 + 128.0)
  if sort:
    order = np.argsort(
      -np.exp(log_scales.sum(-1)) * opacity, kind='stable'
    )
    rows = rows[order]
  return rows


def save_splat(path, gaussians: Gaussians, *, sort: bool = True) -> None:
  """Writes Gaussians as an antimatter15 ``.splat`` file (lossy, SH degree 0).

  Args:
    path: output path (parent directories are created).
    gaussians: the Gaussians.
    sort: order rows by decreasing ``exp(sum log_scale) * opacity`` (as
      antimatter15's ``convert.py``); False keeps the input order.

  Raises:
    PlyError: inconsistent shapes or non-finite values.
    SplatError: scales out of float32 range, or a path that cannot be
      written (a directory, or a file where a parent folder should be).
  """
  check_writable_file(path, '.splat', SplatError)
  rows = encode_splat(gaussians, sort=sort, path=os.fspath(path))
  with open_output(path, '.splat', SplatError) as f:
    f.write(rows.tobytes())


def decode_splat(data: bytes, path='<bytes>', dtype=jnp.float32) -> Gaussians:
  """Decodes ``.splat`` bytes into Gaussians (SH degree 0).

  Args:
    data: the file content, a multiple of 32 bytes.
    path: used in error messages.
    dtype: float dtype of the result.

  Returns:
    :class:`~physsplat_jax.types.Gaussians`.

  Raises:
    SplatError: size not a multiple of 32, a PLY file given by mistake,
      non-finite positions/scales or non-positive scales.
  """
  if data.startswith(b'ply\n') or data.startswith(b'ply\r\n'):
    raise SplatError(
      f'{path}: this is a PLY file, not an antimatter15 .splat; rename it '
      'to .ply (or read it with load_ply)'
    )
  if len(data) % ROW_BYTES:
    raise SplatError(
      f'{path}: size {len(data)} bytes is not a multiple of {ROW_BYTES} '
      f'(a .splat file is {ROW_BYTES} bytes per Gaussian); the file is '
      f'truncated or not a .splat ({len(data) // ROW_BYTES} full rows, '
      f'{len(data) % ROW_BYTES} extra bytes)'
    )
  rows = np.frombuffer(data, SPLAT_DTYPE)
  pos = rows['position'].astype(np.float64)
  scale = rows['scale'].astype(np.float64)
  bad = []
  for name, a in (('position', pos), ('scale', scale)):
    n = int(np.count_nonzero(~np.all(np.isfinite(a), axis=-1)))
    if n:
      bad.append(f'{name}: {n} rows')
  n = int(np.count_nonzero(np.any(scale <= 0, axis=-1)))
  if n:
    bad.append(f'scale <= 0: {n} rows')
  if bad:
    raise SplatError(f'{path}: invalid values ({"; ".join(bad)})')
  rgba = rows['rgba'].astype(np.float64) / 255.0
  alpha = np.clip(rgba[:, 3], _ALPHA_EPS, 1.0 - _ALPHA_EPS)
  f = lambda a: jnp.asarray(
    np.asarray(a, np.float64).astype(np.float32).astype(np.dtype(dtype))
  )
  return Gaussians(
    means=f(pos),
    log_scales=f(np.log(scale)),
    quats=f((rows['rot'].astype(np.float64) - 128.0) / 128.0),
    opacity_logits=f(np.log(alpha) - np.log1p(-alpha)),
    sh=f(((rgba[:, :3] - 0.5) / SH_C0)[:, None, :]),
  )


def load_splat(path, dtype=jnp.float32) -> Gaussians:
  """Loads an antimatter15 ``.splat`` file.

  Args:
    path: file path.
    dtype: float dtype of the result.

  Returns:
    :class:`~physsplat_jax.types.Gaussians` with SH degree 0, no normals.

  Raises:
    SplatError: see :func:`decode_splat`; also a directory, or a non-float
      ``dtype``.
    FileNotFoundError: no such file (named).
  """
  float_dtype(dtype, 'load_splat', SplatError)
  return decode_splat(_read_bytes(path, '.splat', SplatError), path, dtype)
