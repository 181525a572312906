"""Guessing a capture's up direction: from its cameras or its dominant plane.

A user's 3DGS capture rarely says which way is up: COLMAP's world frame is
that of its first image (so ``z``, the default, is usually a viewing
direction). :func:`guess_up` tries, in order:

1. the cameras (if the scene has some from a file): captures are shot
   upright, so the mean of the cameras' up vectors (minus the image ``y``
   axis, i.e. ``-viewmat[1, :3]`` in the OpenCV/COLMAP convention of
   :mod:`physsplat_jax.cameras`) is up, when the cameras agree (mean of the
   unit vectors longer than :data:`MIN_CAMERA_AGREEMENT`);
2. the dominant plane of the Gaussians' centres (RANSAC, refined by PCA on
   its inliers): the ground or table of a capture, when it holds at least
   :data:`MIN_PLANE_FRACTION` of the (opaque) centres; its normal's sign is
   chosen so that most of the off-plane centres lie above it;
3. ``'z'``.

A direction within :data:`SNAP_DEG` degrees of a signed world axis is
snapped to it (``'-y'``); any other is written ``'x,y,z'``
(:func:`physsplat_jax.types.up_vector` reads both). Every guess is
overridden by ``up_axis=`` (``--up_axis``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from physsplat_jax.types import up_vector

SNAP_DEG = 5.0
MIN_CAMERA_AGREEMENT = 0.3
MIN_PLANE_FRACTION = 0.2
# Fewer (opaque) centres than this carry no reliable plane.
MIN_PLANE_POINTS = 100
# Inlier distance of the plane, as a fraction of the diagonal of the
# 1st-99th percentile box of the centres.
PLANE_TOL = 0.01


@dataclasses.dataclass(frozen=True)
class UpGuess:
  """The up direction chosen for a scene, and why.

  Attributes:
    axis: label for ``Scene.up_axis`` ('-y' or 'x,y,z').
    source: 'given', 'sidecar', 'cameras', 'plane' or 'default'.
    detail: one human line (agreement, inlier share, snapping).
  """

  axis: str
  source: str
  detail: str = ''

  @property
  def vector(self) -> np.ndarray:
    return up_vector(self.axis)

  def to_dict(self) -> dict:
    return dict(up_axis=self.axis, up_source=self.source,
                up_detail=self.detail,
                up_vector=[round(float(c), 6) for c in self.vector])


def axis_label(v, snap_deg: float = SNAP_DEG) -> tuple[str, float]:
  """(label, angle [deg] to the nearest signed axis) of a direction ``v``;
  the label is the axis when the angle is at most ``snap_deg``."""
  v = np.asarray(v, np.float64)
  v = v / np.linalg.norm(v)
  a = int(np.argmax(np.abs(v)))
  angle = math.degrees(math.acos(min(1.0, abs(float(v[a])))))
  if angle <= snap_deg:
    return ('-' if v[a] < 0 else '') + 'xyz'[a], angle
  return ','.join(f'{c:.4f}' for c in v), angle


def up_from_cameras(cameras) -> tuple[np.ndarray | None, float]:
  """(mean camera up or None, agreement in [0, 1]).

  Each camera's up is ``-viewmat[1, :3]`` (image up in world axes); the
  agreement is the length of the mean of these unit vectors (1: all
  parallel). None when there are no cameras or they disagree.
  """
  if not cameras:
    return None, 0.0
  ups = np.stack([-np.asarray(c.viewmat, np.float64)[1, :3] for c in cameras])
  ups /= np.maximum(np.linalg.norm(ups, axis=1, keepdims=True), 1e-12)
  m = ups.mean(0)
  agreement = float(np.linalg.norm(m))
  if agreement < MIN_CAMERA_AGREEMENT:
    return None, agreement
  return m / agreement, agreement


def up_from_plane(means, opacities=None, *, max_points: int = 20_000,
                  iters: int = 256, seed: int = 0
                  ) -> tuple[np.ndarray | None, float]:
  """(normal of the dominant plane pointing to most of the mass, or None;
  the plane's share of the centres).

  RANSAC over ``iters`` random triples of (at most ``max_points``) centres
  with opacity >= 0.1, inliers within :data:`PLANE_TOL` of the robust
  diagonal, refined by PCA of the inliers. None when the best plane holds
  less than :data:`MIN_PLANE_FRACTION` of the centres, or there are fewer
  than :data:`MIN_PLANE_POINTS` of them.
  """
  x = np.asarray(means, np.float64)
  if opacities is not None:
    x = x[np.asarray(opacities) >= 0.1]
  x = x[np.all(np.isfinite(x), axis=1)]
  if len(x) < MIN_PLANE_POINTS:
    return None, 0.0
  rng = np.random.default_rng(seed)
  if len(x) > max_points:
    x = x[rng.choice(len(x), max_points, replace=False)]
  lo, hi = np.percentile(x, [1.0, 99.0], axis=0)
  tol = PLANE_TOL * float(np.linalg.norm(hi - lo))
  if not tol > 0:
    return None, 0.0
  tri = x[rng.integers(0, len(x), (iters, 3))]
  n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
  norm = np.linalg.norm(n, axis=1)
  ok = norm > 1e-12 * tol * tol
  n, p0 = n[ok] / norm[ok, None], tri[ok, 0]
  if not len(n):
    return None, 0.0
  best_i, best_count = -1, -1
  for s in range(0, len(n), 32):  # (32, N) distances at a time
    d = np.abs(x @ n[s:s + 32].T - np.sum(p0[s:s + 32] * n[s:s + 32], 1)).T
    counts = (d < tol).sum(1)
    j = int(np.argmax(counts))
    if counts[j] > best_count:
      best_i, best_count = s + j, int(counts[j])
  inl = np.abs((x - p0[best_i]) @ n[best_i]) < tol
  c = x[inl].mean(0)
  _, vecs = np.linalg.eigh(np.cov((x[inl] - c).T))
  normal = vecs[:, 0]
  d = (x - c) @ normal
  inl = np.abs(d) < tol
  share = float(inl.mean())
  if share < MIN_PLANE_FRACTION:
    return None, share
  if np.sum(d > tol) < np.sum(d < -tol):
    normal = -normal
  return normal, share


def guess_up(means, opacities=None, cameras=(), *,
             given: str | None = None, sidecar: str | None = None
             ) -> UpGuess:
  """The scene's up direction (see the module docstring).

  Args:
    means: (K, 3) Gaussian centres.
    opacities: (K,) activated opacities, or None.
    cameras: the scene's cameras read from a file (fitted ones carry no
      information: pass ()).
    given: the user's ``up_axis`` ('auto' or None: guess).
    sidecar: the up axis of the scene's sidecar, if any.

  Returns:
    :class:`UpGuess`.
  """
  if given is not None and given != 'auto':
    up_vector(given)  # validates
    return UpGuess(given, 'given', 'up_axis set by the user')
  if sidecar is not None:
    up_vector(sidecar)  # validates
    return UpGuess(sidecar, 'sidecar', 'from the scene sidecar')
  def guess(v, source, what):
    label, angle = axis_label(v)
    return UpGuess(label, source, (
      f'{what}, {angle:.1f} deg from the nearest axis'
      + (' (snapped)' if angle <= SNAP_DEG else '')))

  v, agree = up_from_cameras(cameras)
  if v is not None:
    return guess(v, 'cameras', f'mean up of {len(cameras)} cameras '
                 f'(agreement {agree:.2f})')
  v, share = up_from_plane(means, opacities)
  if v is not None:
    return guess(v, 'plane', 'normal of the dominant plane '
                 f'({100 * share:.0f}% of the centres)')
  why = ('no cameras' if not cameras else
         f'cameras disagree (agreement {agree:.2f})')
  return UpGuess('z', 'default', f'{why} and no dominant plane (best holds '
                 f'{100 * share:.0f}% of the centres): z assumed; set '
                 '--up_axis if it is wrong')
