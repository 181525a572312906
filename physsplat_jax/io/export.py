"""Export of deformed Gaussians: per-frame INRIA PLY, .splat and .spz.

A simulation moves each Gaussian's centre and changes its covariance to
``Sigma' = F Sigma F^T`` (:func:`physsplat_jax.deform.deform`), with a local
rotation ``R = polar(F)`` that turns its view-dependent colour. The renderer
takes ``Sigma'`` and ``R`` directly; viewers (SuperSplat, antimatter15,
mkkellogg, Spark) only read scale + quaternion + SH files, so export:

1. splits ``Sigma'`` (float64, on the host) into ``Q diag(s^2) Q^T`` by an
   eigen-decomposition; eigenvalues below ``min_variance`` (flattened or
   degenerate Gaussians, round-off negatives) are floored. A float32
   ``Sigma'`` cannot carry a thin axis (variance ~1e-6 of the largest: its
   rounding is ~1e-3 in log-scale), so a covariance equal to the rigidly
   moved rest one (to ``RIGID_RTOL``) keeps the rest scales exactly, and
   callers that have ``F`` pass ``deformation=F``: the scales are then the
   singular values of ``F Q_0 diag(s_0)`` in float64, exact for any
   motion;
2. orders and signs the eigenvectors to follow the Gaussian's own axes
   carried by the motion, ``R Q_0`` (``Q_0`` its rest rotation): the
   permutation of the eigenvectors that best matches those axes is chosen,
   each axis flipped to point the same way, and the last column flipped if
   that left a reflection. So ``det Q = +1`` always, and a rigid motion
   gives exactly the rotated quaternion ``q_R * q_0`` and the rest scales
   (a bare eigen-decomposition would sort the axes by size and could flip
   them from frame to frame);
3. rotates the SH coefficients by ``R`` (:func:`rotate_sh`), so that a
   viewer evaluating them at the world view direction ``d`` sees
   ``SH(R^T d)``, which is what the renderer computes with
   ``view_rotations=R``;
4. writes the INRIA layout (``x y z nx ny nz f_dc_* f_rest_* opacity
   scale_* rot_*``, 62 float32 properties with SH degree 3, normals zero),
   the 32-byte antimatter15 ``.splat`` rows (SH dropped) or a Niantic
   ``.spz`` (:mod:`physsplat_jax.io.spz`: quantised and gzipped: 20 bytes
   per Gaussian plus 3 per SH coefficient of degree >= 1 before gzip, SH
   rotated as in the PLY).

For sequences, :class:`DeformedFrameWriter` writes ``frame_0000.ply``,
``frame_0001.ply``, ... (what PhysGaussian ships with ``--output_ply``),
or ``.splat`` / ``.spz`` frames.
"""

from __future__ import annotations

import itertools
import os

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax.gaussians import quat_to_rotmat_np as quat_to_rotmat_np
from physsplat_jax.io import paths
from physsplat_jax.io.ply import PlyError
from physsplat_jax.io.ply import save_ply
from physsplat_jax.io import spz as spz_lib
from physsplat_jax.io.splat import save_splat
from physsplat_jax.sh_rotation import rotate_sh
from physsplat_jax.types import Gaussians

PathLike = str | os.PathLike

# Variance floor [scene units^2]: exp(0.5 log(1e-20)) = 1e-10, a flat but
# finite Gaussian.
MIN_VARIANCE = 1e-20
# Eigenvalues of a covariance below -NEGATIVE_RTOL times its largest are not
# round-off (a float32 F Sigma F^T is off by ~1e-7 of its largest entry):
# such a matrix is not a covariance, and is refused instead of floored.
NEGATIVE_RTOL = 1e-4
# Relative tolerance under which a covariance counts as the rigidly moved
# rest covariance (~32 float32 ulps of its largest entry; a float32
# R S^2 R^T of the tabletop's Gaussians is off by up to 1.2e-6).
RIGID_RTOL = 4e-6
# Gaussians per SH-rotation batch (bounds memory: ~4 kB per Gaussian at SH
# degree 3).
_SH_BATCH = 32768
PLY_PATTERN = 'frame_%04d.ply'
SPLAT_PATTERN = 'frame_%04d.splat'
SPZ_PATTERN = 'frame_%04d.spz'
_PATTERNS = {'ply': PLY_PATTERN, 'splat': SPLAT_PATTERN, 'spz': SPZ_PATTERN}
_PERMS = np.array(list(itertools.permutations(range(3))))  # (6, 3)


class ExportError(PlyError):
  """Deformed Gaussians that cannot be exported (a PlyError/ValueError)."""


def _as_f64(a, shape, name) -> np.ndarray:
  a = np.asarray(a, np.float64)
  if a.shape != shape:
    raise ExportError(
      f'export: {name} has shape {a.shape}; expected {shape}'
    )
  bad = ~np.isfinite(a)
  if bad.any():
    rows = np.unique(np.nonzero(bad.reshape(shape[0], -1))[0])
    raise ExportError(
      f'export: {name} has non-finite values in {rows.size} Gaussians '
      f'(first: {rows[:5].tolist()}); the simulation blew up or the inputs '
      'are wrong'
    )
  return a


def _check_min_variance(min_variance) -> float:
  v = float(min_variance)
  if not (np.isfinite(v) and v > 0):
    raise ExportError(
      f'export: min_variance must be a positive number (the variance floor '
      f'[scene units^2], default {MIN_VARIANCE:g}), got {min_variance!r}'
    )
  return v


def _check_sh_degree(sh_degree) -> None:
  if sh_degree is None:
    return
  if (isinstance(sh_degree, (bool, np.bool_))
      or not isinstance(sh_degree, (int, np.integer))
      or not 0 <= sh_degree <= 3):
    raise ExportError(
      f'export: sh_degree must be 0..3 (3: the INRIA layout of 62 '
      f'properties) or None (the scene\'s), got {sh_degree!r}'
    )


def _check_psd(w) -> None:
  """Refuses covariances with clearly negative eigenvalues ``w`` (K, 3)."""
  bad = w[:, 0] < -NEGATIVE_RTOL * np.abs(w).max(axis=1)
  if bad.any():
    rows = np.nonzero(bad)[0]
    i = rows[0]
    raise ExportError(
      f'export: covariances of {rows.size} Gaussians are not positive '
      f'semi-definite (first: {rows[:5].tolist()}; Gaussian {i} has '
      f'eigenvalues {np.round(w[i], 12).tolist()}); pass the deformed '
      'covariances F Sigma F^T (symmetric positive semi-definite)'
    )


def _align(w, V, reference, min_variance):
  """Orders/signs eigenpairs ``(w, V)`` to follow ``reference`` (see below)."""
  if reference is not None:
    ref = np.asarray(reference, np.float64)
    M = np.abs(np.einsum('kai,kaj->kij', V, ref))  # |<v_i, ref_j>|
    score = M[:, _PERMS, np.arange(3)].sum(-1)  # (K, 6)
    perm = _PERMS[np.argmax(score, axis=1)]  # (K, 3): axis j <- eigvec p_j
    V = np.take_along_axis(V, perm[:, None, :], axis=2)
    w = np.take_along_axis(w, perm, axis=1)
    dots = np.einsum('kai,kai->ki', V, ref)
    V = V * np.where(dots < 0, -1.0, 1.0)[:, None, :]
    align = np.abs(dots)
  else:
    align = np.broadcast_to([1.0, 1.0, 0.0], w.shape)
  # Still a reflection (only where the axes matched badly): flip the worst
  # aligned axis.
  det = np.linalg.det(V)
  worst = np.argmin(align, axis=1)
  flip = np.ones_like(w)
  flip[np.arange(len(w)), worst] = np.where(det < 0, -1.0, 1.0)
  V = V * flip[:, None, :]
  log_scales = 0.5 * np.log(np.maximum(w, min_variance))
  return log_scales, V


def decompose_aligned(
  covariances, reference=None, min_variance: float = MIN_VARIANCE
) -> tuple[np.ndarray, np.ndarray]:
  """Covariances -> log-scales and proper rotations, following given axes.

  Args:
    covariances: (K, 3, 3) symmetric PSD matrices.
    reference: (K, 3, 3) rotations whose columns the output axes should
      follow (order and sign), e.g. the rest axes carried by the motion; None
      keeps eigh's ascending order.
    min_variance: floor of the eigenvalues.

  Returns:
    (log_scales (K, 3), rotations (K, 3, 3)) float64 with
    ``rot diag(exp(2 log_scales)) rot^T == covariance`` (up to the floor) and
    ``det(rot) == +1``.

  Raises:
    ExportError: ``min_variance`` not positive, or a covariance with an
      eigenvalue below ``-NEGATIVE_RTOL`` times its largest (not PSD).
  """
  min_variance = _check_min_variance(min_variance)
  C = np.asarray(covariances, np.float64)
  C = 0.5 * (C + np.swapaxes(C, -1, -2))
  w, V = np.linalg.eigh(C)
  _check_psd(w)
  return _align(w, V, reference, min_variance)


def decompose_deformed(
  deformation, rest_rotations, rest_log_scales, reference=None,
  min_variance: float = MIN_VARIANCE,
) -> tuple[np.ndarray, np.ndarray]:
  """``F Q0 diag(s0)`` -> log-scales and rotations, without forming Sigma'.

  An SVD of the covariance's factor ``L = F Q0 diag(s0)`` (float64) gives
  its square roots ``s`` with a relative accuracy the eigenvalues of a
  float32 ``F Sigma F^T`` lack: a thin axis (``log s0 = -11.4`` next to
  ``-5``, a variance ratio ~1e-6) loses ~1e-3 in log-scale through a
  float32 covariance and nothing here. At ``F = I`` the result is the rest
  scales and axes.

  Args:
    deformation: (K, 3, 3) local deformation gradients ``F``.
    rest_rotations: (K, 3, 3) rest axes ``Q0``.
    rest_log_scales: (K, 3) rest log-scales.
    reference, min_variance: as :func:`decompose_aligned`.

  Returns:
    As :func:`decompose_aligned`.
  """
  min_variance = _check_min_variance(min_variance)
  F = np.asarray(deformation, np.float64)
  s0 = np.exp(np.asarray(rest_log_scales, np.float64))
  L = F @ np.asarray(rest_rotations, np.float64) * s0[:, None, :]
  U, sv, _ = np.linalg.svd(L)
  return _align(sv * sv, U, reference, min_variance)


def _rest_if_rigid(C, ref, rest_log_scales, log_scales, Q, rtol):
  """Keeps the rest scales where ``C`` is the rigidly moved rest covariance.

  Where ``C`` equals ``ref diag(s0^2) ref^T`` to ``rtol`` of its largest
  entry (float32 rounding of an undeformed Gaussian), ``(s0, ref)`` is an
  exact decomposition of it, and the only one that keeps thin axes: the
  rounding of a float32 covariance swamps variances ~1e-6 of the largest.
  """
  ls0 = np.asarray(rest_log_scales, np.float64)
  C_rig = np.einsum('kai,ki,kbi->kab', ref, np.exp(2.0 * ls0), ref)
  scale = np.abs(C_rig).max(axis=(1, 2))
  rigid = np.abs(C - C_rig).max(axis=(1, 2)) <= rtol * scale
  return (np.where(rigid[:, None], ls0, log_scales),
          np.where(rigid[:, None, None], ref, Q))


def rotmat_to_quat_np(R) -> np.ndarray:
  """(K, 3, 3) proper rotations -> (K, 4) unit wxyz quaternions, w >= 0.

  NumPy float64 twin of :func:`physsplat_jax.gaussians.rotmat_to_quat`
  (Shepperd's method: the largest of 4w^2, 4x^2, 4y^2, 4z^2 picks the
  branch).
  """
  R = np.asarray(R, np.float64)
  m = lambda i, j: R[..., i, j]
  tr = m(0, 0) + m(1, 1) + m(2, 2)
  cands = np.stack([
    np.stack([1 + tr, m(2, 1) - m(1, 2), m(0, 2) - m(2, 0),
              m(1, 0) - m(0, 1)], -1),
    np.stack([m(2, 1) - m(1, 2), 1 + m(0, 0) - m(1, 1) - m(2, 2),
              m(0, 1) + m(1, 0), m(0, 2) + m(2, 0)], -1),
    np.stack([m(0, 2) - m(2, 0), m(0, 1) + m(1, 0),
              1 - m(0, 0) + m(1, 1) - m(2, 2), m(1, 2) + m(2, 1)], -1),
    np.stack([m(1, 0) - m(0, 1), m(0, 2) + m(2, 0), m(1, 2) + m(2, 1),
              1 - m(0, 0) - m(1, 1) + m(2, 2)], -1),
  ], -2)
  best = np.argmax(np.stack([cands[..., i, i] for i in range(4)], -1), -1)
  q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
  q = q / np.linalg.norm(q, axis=-1, keepdims=True)
  return np.where(q[..., :1] < 0, -q, q)


def rotate_sh_batched(sh, rotations, batch: int = _SH_BATCH) -> np.ndarray:
  """:func:`~physsplat_jax.sh_rotation.rotate_sh` in fixed batches.

  Args:
    sh: (K, B, 3) coefficients.
    rotations: (K, 3, 3) rotations.
    batch: Gaussians per call (one compile; bounded memory).

  Returns:
    (K, B, 3) float32 rotated coefficients.
  """
  sh = np.asarray(sh, np.float32)
  K, B, _ = sh.shape
  if B == 1 or K == 0:
    return sh
  R = np.asarray(rotations, np.float32)
  n = min(batch, K)
  fn = jax.jit(rotate_sh)
  out = np.empty_like(sh)
  for i in range(0, K, n):
    s, r = sh[i:i + n], R[i:i + n]
    m = s.shape[0]
    if m < n:  # pad so every call has one shape
      s = np.concatenate([s, np.zeros((n - m, B, 3), s.dtype)])
      r = np.concatenate([r, np.broadcast_to(np.eye(3, dtype=r.dtype),
                                             (n - m, 3, 3))])
    out[i:i + m] = np.asarray(fn(jnp.asarray(s), jnp.asarray(r)))[:m]
  return out


def deformed_gaussians(
  gaussians: Gaussians,
  means,
  covariances,
  rotations=None,
  *,
  deformation=None,
  rotate_colors: bool = True,
  min_variance: float = MIN_VARIANCE,
) -> Gaussians:
  """Deformed Gaussians as plain scale/quaternion/SH Gaussians (host side).

  Args:
    gaussians: the rest Gaussians (opacity, SH and rest axes are taken from
      them).
    means: (K, 3) deformed centres.
    covariances: (K, 3, 3) deformed covariances ``F Sigma F^T``, or None
      when ``deformation`` is given.
    rotations: (K, 3, 3) local rotations ``polar(F)`` (as returned by
      :func:`physsplat_jax.deform.deform`) or None (no rotation: the axes
      follow the rest axes and the SH are unchanged).
    deformation: optional (K, 3, 3) local deformation gradients ``F``
      (:func:`physsplat_jax.deform.local_deformation`); when given, scales
      and axes come from :func:`decompose_deformed` (exact for thin
      Gaussians) instead of the covariances. Without it, a covariance that
      is the rigidly moved rest one (to float32 rounding) keeps the rest
      scales exactly; others are eigen-decomposed.
    rotate_colors: rotate the SH by ``rotations`` (view-dependent colour
      follows the object).
    min_variance: eigenvalue floor [scene units^2].

  Returns:
    :class:`~physsplat_jax.types.Gaussians` (float32, NumPy leaves) with the
    new means, log-scales, unit wxyz quaternions (``w >= 0``, proper) and
    SH; opacity and extras unchanged; normals cleared.

  Raises:
    ExportError: shapes that do not match ``gaussians``, non-finite inputs,
      covariances that are not PSD, or ``min_variance`` not positive.
  """
  min_variance = _check_min_variance(min_variance)
  K = gaussians.num
  x = _as_f64(means, (K, 3), 'means')
  R = None if rotations is None else _as_f64(rotations, (K, 3, 3),
                                              'rotations')
  Q0 = quat_to_rotmat_np(gaussians.quats)
  ref = Q0 if R is None else R @ Q0
  ls0 = np.asarray(gaussians.log_scales, np.float64)
  if deformation is not None:
    F = _as_f64(deformation, (K, 3, 3), 'deformation')
    if R is None:  # the axes follow polar(F)
      U, _, Wt = np.linalg.svd(F)
      R = U @ Wt
      ref = R @ Q0
    log_scales, Q = decompose_deformed(F, Q0, ls0, ref, min_variance)
    # A rotation (to rounding) keeps the rest scales and the moved rest axes
    # (the SVD's axes are arbitrary within equal scales).
    rigid = np.abs(np.swapaxes(F, -1, -2) @ F - np.eye(3)).max(
      axis=(1, 2)) <= RIGID_RTOL
    log_scales = np.where(rigid[:, None], ls0, log_scales)
    Q = np.where(rigid[:, None, None], ref, Q)
  elif covariances is None:
    raise ExportError('export: pass covariances or deformation')
  else:
    C = _as_f64(covariances, (K, 3, 3), 'covariances')
    log_scales, Q = decompose_aligned(C, ref, min_variance)
    log_scales, Q = _rest_if_rigid(C, ref, ls0, log_scales, Q, RIGID_RTOL)
  quats = rotmat_to_quat_np(Q)
  sh = np.asarray(gaussians.sh, np.float32)
  if rotate_colors and R is not None:
    sh = rotate_sh_batched(sh, R)
  f32 = lambda a: np.asarray(a, np.float32)
  return gaussians.replace(
    means=f32(x), log_scales=f32(log_scales), quats=f32(quats),
    opacity_logits=f32(gaussians.opacity_logits), sh=sh, normals=None,
  )


def _check_output(path) -> str:
  """:func:`physsplat_jax.io.paths.check_output_file`, as ExportError."""
  return paths.check_output_file(path, ExportError, what='export')


def _for_viewers(g: Gaussians, sh_degree: int | None,
                 keep_extras: bool) -> Gaussians:
  if sh_degree is not None:
    g = g.with_sh_degree(int(sh_degree))
  g = g.replace(normals=np.zeros((g.num, 3), np.float32))
  return g if keep_extras else g.replace(extras={})


def save_deformed_ply(
  path: PathLike,
  gaussians: Gaussians,
  means,
  covariances,
  rotations=None,
  *,
  deformation=None,
  sh_degree: int | None = 3,
  keep_extras: bool = False,
  rotate_colors: bool = True,
) -> Gaussians:
  """Writes deformed Gaussians as an INRIA 3DGS PLY (SuperSplat, viewers).

  Args:
    path: output ``.ply`` (parent folders are created).
    gaussians, means, covariances, rotations, deformation, rotate_colors:
      as :func:`deformed_gaussians`.
    sh_degree: SH degree written (zero-padded or truncated); 3 gives the
      exact INRIA layout of 62 properties; None keeps the scene's.
    keep_extras: also write extra per-Gaussian properties (object ids...).

  Returns:
    The Gaussians written.

  Raises:
    ExportError: bad inputs (see :func:`deformed_gaussians`), ``sh_degree``
      outside 0..3, or a path that cannot be written (checked first).
  """
  _check_sh_degree(sh_degree)
  _check_output(path)
  g = deformed_gaussians(gaussians, means, covariances, rotations,
                         deformation=deformation,
                         rotate_colors=rotate_colors)
  g = _for_viewers(g, sh_degree, keep_extras)
  save_ply(path, g)
  return g


def save_deformed_splat(
  path: PathLike, gaussians: Gaussians, means, covariances, rotations=None,
  *, deformation=None, sort: bool = True,
) -> Gaussians:
  """Writes deformed Gaussians as an antimatter15 ``.splat`` (SH dropped).

  Only the DC colour survives in ``.splat``, so the SH are not rotated.
  Returns the Gaussians written (before 8-bit quantisation).
  """
  _check_output(path)
  g = deformed_gaussians(gaussians, means, covariances, rotations,
                         deformation=deformation, rotate_colors=False)
  save_splat(path, g.replace(extras={}), sort=sort)
  return g


# What save_deformed_spz passes on to spz.encode_spz.
SPZ_OPTIONS = ('version', 'antialiased', 'fractional_bits', 'sh1_bits',
               'sh_rest_bits', 'stored_frame', 'warned',
               'compress_level')


def spz_fractional_bits(means) -> int:
  """Position fraction bits for a ``.spz`` of centres ``means``.

  The reference's 12 (step 1/4096, range +-2048 scene units) unless a
  centre lies outside that range; then the most bits whose range holds
  every centre (each bit fewer doubles both the range and the step).
  """
  m = float(np.max(np.abs(np.asarray(means, np.float32)), initial=0.0))
  f = spz_lib.FRACTIONAL_BITS
  while f > 0 and m * 2.0 ** f >= 2 ** 23 - 0.5:
    f -= 1
  return f


def _check_spz_options(options: dict) -> dict:
  """``options`` for :func:`spz.encode_spz`, checked on one Gaussian
  (before any frame); ``fractional_bits=None`` is dropped (automatic)."""
  unknown = sorted(set(options) - set(SPZ_OPTIONS))
  if unknown:
    raise ExportError(
      f'export: unknown .spz option(s) {", ".join(unknown)}; the options '
      f'are {", ".join(SPZ_OPTIONS)} (physsplat_jax.io.spz.encode_spz)'
    )
  options = {k: v for k, v in options.items()
             if not (k == 'fractional_bits' and v is None)}
  one = Gaussians(
    means=np.zeros((1, 3), np.float32), log_scales=np.zeros((1, 3),
                                                            np.float32),
    quats=np.array([[1, 0, 0, 0]], np.float32),
    opacity_logits=np.zeros((1,), np.float32),
    sh=np.zeros((1, 1, 3), np.float32))
  try:
    spz_lib.encode_spz(one, path='export', **options)
  except spz_lib.SpzError as e:
    raise ExportError(f'export: {e}') from None
  return options


def save_deformed_spz(
  path: PathLike,
  gaussians: Gaussians,
  means,
  covariances,
  rotations=None,
  *,
  deformation=None,
  sh_degree: int | None = None,
  rotate_colors: bool = True,
  **spz_options,
) -> Gaussians:
  """Writes deformed Gaussians as a Niantic ``.spz`` (lossy, ~10x smaller
  than the PLY; :mod:`physsplat_jax.io.spz`).

  Args:
    path: output ``.spz`` (parent folders are created).
    gaussians, means, covariances, rotations, deformation, rotate_colors:
      as :func:`deformed_gaussians` (the SH rotated as in the PLY).
    sh_degree: SH degree written (truncated or zero-padded); None keeps the
      scene's. Degree 3 costs 45 of the 65 bytes a Gaussian takes before
      gzip.
    **spz_options: as :func:`physsplat_jax.io.spz.encode_spz`
      (``version``, ``antialiased``, ``fractional_bits``, ``sh1_bits``,
      ``sh_rest_bits``, ``stored_frame``); ``fractional_bits`` None or
      absent: :func:`spz_fractional_bits` of the deformed centres.

  Returns:
    The Gaussians written (before quantisation).

  Raises:
    ExportError: bad inputs (see :func:`deformed_gaussians`), ``sh_degree``
      outside 0..3, an unknown or bad option, a path that cannot be
      written (these checked first), or centres beyond the format's range.
  """
  _check_sh_degree(sh_degree)
  spz_options = _check_spz_options(spz_options)
  _check_output(path)
  g = deformed_gaussians(gaussians, means, covariances, rotations,
                         deformation=deformation,
                         rotate_colors=rotate_colors)
  if sh_degree is not None:
    g = g.with_sh_degree(int(sh_degree))
  g = g.replace(extras={})
  spz_options.setdefault('fractional_bits', spz_fractional_bits(g.means))
  try:
    # (Named as the file it becomes: the per-frame writers fill a
    # temporary name, paths.partial_path.)
    data = spz_lib.encode_spz(
      g, path=paths.final_path(path) or os.fspath(path), **spz_options)
  except spz_lib.SpzError as e:
    raise ExportError(f'export: {e}') from None
  with paths.open_output(path, ExportError, what='export') as f:
    f.write(data)
  return g


# The writer of each per-frame format (DeformedFrameWriter, io.outputs).
SAVE_DEFORMED = {'ply': save_deformed_ply, 'splat': save_deformed_splat,
                 'spz': save_deformed_spz}


class DeformedFrameWriter:
  """Writes one file per simulated frame: ``frame_0000.ply``, ...

  Example::

    with DeformedFrameWriter('out/ply', scene.gaussians) as frames:
      for t in range(T):
        means, covs, rots = deform.deform(binding, g, x[t])
        frames.append(means, covs, rots)

  Attributes:
    directory: output folder.
    format: ``'ply'``, ``'splat'`` or ``'spz'``.
    paths: files written so far.
  """

  def __init__(
    self,
    directory: PathLike,
    gaussians: Gaussians,
    *,
    format: str = 'ply',  # noqa: A002
    pattern: str | None = None,
    start: int = 0,
    **kwargs,
  ):
    """Args:
      directory: output folder (created).
      gaussians: the rest Gaussians.
      format: ``'ply'`` (INRIA, SH rotated), ``'splat'`` or ``'spz'``
        (Niantic, SH rotated).
      pattern: file name with one integer field (default
        ``frame_%04d.ply`` / ``.splat`` / ``.spz``).
      start: index of the first frame.
      **kwargs: passed to :func:`save_deformed_ply` (``sh_degree``,
        ``keep_extras``, ``rotate_colors``), :func:`save_deformed_splat`
        (``sort``) or :func:`save_deformed_spz` (``sh_degree``,
        ``rotate_colors`` and the ``.spz`` options, checked here).
    """
    if format not in SAVE_DEFORMED:
      raise ExportError(
        f"format must be 'ply', 'splat' or 'spz', got {format!r}")
    pattern = pattern or _PATTERNS[format]
    try:
      pattern % 0
    except (TypeError, ValueError) as e:
      raise ExportError(
        f'pattern {pattern!r} needs one integer field such as %04d'
      ) from e
    if format in ('ply', 'spz'):
      _check_sh_degree(kwargs.get('sh_degree'))
    if format == 'spz':
      _check_spz_options({k: v for k, v in kwargs.items()
                          if k not in ('sh_degree', 'rotate_colors')})
    self.directory = os.fspath(directory)
    _check_output(os.path.join(self.directory, pattern % int(start)))
    self.format = format
    self.pattern = pattern
    self._gaussians = gaussians
    self._kwargs = kwargs
    self._next = int(start)
    self.paths: list[str] = []

  def __enter__(self) -> DeformedFrameWriter:
    return self

  def __exit__(self, exc_type, exc, tb) -> None:
    self.close()

  def append(self, means, covariances, rotations=None,
             deformation=None) -> str:
    """Writes the next frame; returns its path (``deformation``: optional
    (K, 3, 3) ``F``, see :func:`deformed_gaussians`)."""
    path = os.path.join(self.directory, self.pattern % self._next)
    SAVE_DEFORMED[self.format](path, self._gaussians, means, covariances,
                               rotations, deformation=deformation,
                               **self._kwargs)
    self._next += 1
    self.paths.append(path)
    return path

  def close(self) -> None:
    """Nothing to flush (every file is complete when written)."""


def save_deformed_sequence(
  directory: PathLike, gaussians: Gaussians, means, covariances,
  rotations=None, **kwargs,
) -> list[str]:
  """Writes a (T, K, ...) trajectory of deformed Gaussians, one file a frame.

  Args:
    directory: output folder.
    gaussians: the rest Gaussians.
    means: (T, K, 3); covariances: (T, K, 3, 3); rotations: (T, K, 3, 3) or
      None.
    **kwargs: as :class:`DeformedFrameWriter`.

  Returns:
    The paths written.

  Raises:
    ExportError: shapes or frame counts that do not match (checked before
      any file is written), or as :class:`DeformedFrameWriter`.
  """
  K = gaussians.num
  shape = np.shape(means)
  if len(shape) != 3 or shape[1:] != (K, 3):
    raise ExportError(
      f'save_deformed_sequence: means has shape {shape}; expected (T, {K}, '
      '3), one row per Gaussian and frame'
    )
  T = shape[0]
  for name, a in (('covariances', covariances), ('rotations', rotations)):
    if a is not None and np.shape(a) != (T, K, 3, 3):
      raise ExportError(
        f'save_deformed_sequence: {name} has shape {np.shape(a)}; expected '
        f'({T}, {K}, 3, 3), one (K, 3, 3) per frame of means (T = {T})'
      )
  with DeformedFrameWriter(directory, gaussians, **kwargs) as w:
    for t in range(T):
      w.append(means[t], covariances[t],
               None if rotations is None else rotations[t])
  return w.paths
