"""Geometric segmentation: a support plane by RANSAC, then clusters.

1. **Support plane** (:func:`fit_plane_ransac`): hypotheses from random point
   triples of a subsample (at most ``max_samples`` points), scored by their
   inlier count (``|n . x + d| <= threshold``) on that subsample; optionally
   only near-horizontal planes (angle to ``up`` below ``max_tilt_deg``).
   The best is refined by least squares (SVD) on its inliers, and the final
   inliers are found on all points. Cost O(iterations x max_samples + K).
2. **Clusters** (:func:`cluster_points`), a DBSCAN-like pass on a voxel
   grid: points are binned into voxels of side ``eps``; voxels with at least
   ``min_voxel_points`` points are nodes; two nodes are joined when their
   voxels touch (26-neighbourhood) AND their mean colours differ by less
   than ``color_threshold`` (colour affinity: touching objects of different
   colours separate); connected components (SciPy) are the clusters;
   clusters with fewer than ``min_cluster_points`` points are noise (-1).
   Neighbour lookup is a sorted-key search, so time and memory are
   O(K log K) and O(K) -- about a second for a million Gaussians.

:func:`segment_geometric` combines them: the plane's inliers (and, by
default, everything below it) form a fixed ``'support'`` object, the
clusters of the rest become ``'object_<i>'`` (largest first).
"""

from __future__ import annotations

import numpy as np
import scipy

from physsplat_jax.segmentation.base import BACKGROUND
from physsplat_jax.segmentation.base import Segmentation
from physsplat_jax.segmentation.base import SegmentationError
from physsplat_jax.segmentation.base import compact_labels
from physsplat_jax.types import Gaussians

_NEIGHBOUR_OFFSETS = np.array(
  [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
   if (i, j, k) > (0, 0, 0)], np.int64)  # 13 half-neighbourhood offsets


def _diag(points: np.ndarray) -> float:
  return float(np.linalg.norm(points.max(0) - points.min(0))) or 1.0


def fit_plane_ransac(
  points,
  threshold: float | None = None,
  num_iterations: int = 256,
  max_samples: int = 20000,
  up=None,
  max_tilt_deg: float | None = 30.0,
  seed: int = 0,
) -> tuple[np.ndarray, float, np.ndarray]:
  """Dominant plane ``n . x + d = 0`` of a point set.

  Args:
    points: (K, 3) positions.
    threshold: inlier distance; default 1 % of the bounding-box diagonal.
    num_iterations: RANSAC hypotheses.
    max_samples: points used to score hypotheses (a random subsample).
    up: (3,) world up; when given, ``n`` is oriented along it and planes
      tilted more than ``max_tilt_deg`` from horizontal are rejected.
    max_tilt_deg: see ``up``; None accepts any orientation.
    seed: NumPy seed (deterministic).

  Returns:
    ``(n (3,) unit normal, d, inliers (K,) bool)``.

  Raises:
    ValueError: fewer than 3 points, or no acceptable plane.
  """
  x = _as_points(points, 'fit_plane_ransac')
  if x.shape[0] < 3:
    raise SegmentationError(f'fit_plane_ransac: need (K >= 3, 3) points, got '
                            f'{x.shape}')
  if threshold is None:
    threshold = 0.01 * _diag(x)
  rng = np.random.default_rng(seed)
  sub = x if x.shape[0] <= max_samples else x[
    rng.choice(x.shape[0], max_samples, replace=False)]
  u = None
  if up is not None:
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
  cos_tilt = None if (u is None or max_tilt_deg is None) else np.cos(
    np.deg2rad(max_tilt_deg))
  tri = rng.integers(0, sub.shape[0], size=(num_iterations, 3))
  a, b, c = sub[tri[:, 0]], sub[tri[:, 1]], sub[tri[:, 2]]
  n = np.cross(b - a, c - a)
  norm = np.linalg.norm(n, axis=1)
  ok = norm > 1e-12
  n = n / np.where(ok, norm, 1.0)[:, None]
  if cos_tilt is not None:
    ok &= np.abs(n @ u) >= cos_tilt
  if not ok.any():
    raise SegmentationError('fit_plane_ransac: no acceptable plane hypothesis '
                            f'(max_tilt_deg={max_tilt_deg}); the points may be '
                            'degenerate or the up axis wrong')
  n, a = n[ok], a[ok]
  d = -np.sum(n * a, axis=1)
  # Score in chunks to bound memory (iterations x samples).
  best, best_count = 0, -1
  for s in range(0, n.shape[0], 32):
    dist = np.abs(sub @ n[s:s + 32].T + d[s:s + 32])
    cnt = np.sum(dist <= threshold, axis=0)
    i = int(np.argmax(cnt))
    if cnt[i] > best_count:
      best, best_count = s + i, int(cnt[i])
  nb, db = n[best], d[best]
  inl = np.abs(sub @ nb + db) <= threshold
  # Least-squares refinement on the inliers.
  p = sub[inl]
  centroid = p.mean(0)
  _, _, vt = np.linalg.svd(p - centroid, full_matrices=False)
  nr = vt[-1]
  if cos_tilt is None or abs(nr @ u) >= cos_tilt:
    nb, db = nr, -float(nr @ centroid)
  if u is not None and nb @ u < 0:
    nb, db = -nb, -db
  elif u is None:
    # Orient towards the side with more points (objects sit on supports).
    side = np.sign(sub @ nb + db)
    if np.sum(side > 0) < np.sum(side < 0):
      nb, db = -nb, -db
  inliers = np.abs(x @ nb + db) <= threshold
  return nb, float(db), inliers


def _as_points(points, where: str) -> np.ndarray:
  """(K, 3) finite float64 points, or a SegmentationError naming them."""
  x = np.asarray(points, np.float64)
  if x.ndim != 2 or x.shape[1] != 3:
    raise SegmentationError(f'{where}: points must be (K, 3), got shape '
                            f'{x.shape}')
  bad = np.flatnonzero(~np.isfinite(x).all(1))
  if bad.size:
    raise SegmentationError(
      f'{where}: {bad.size} of {len(x)} points are not finite (first: row '
      f'{int(bad[0])}, {x[bad[0]].tolist()}); drop them (Gaussians.subset) '
      'or fix the scene')
  return x


def cluster_points(
  points,
  eps: float,
  colors=None,
  color_threshold: float = 0.25,
  min_voxel_points: int = 1,
  min_cluster_points: int = 10,
) -> np.ndarray:
  """Voxel-grid connected components with colour affinity (DBSCAN-like).

  Args:
    points: (K, 3) positions.
    eps: voxel side (points closer than ``eps`` are in touching voxels).
    colors: (K, 3) RGB in [0, 1], or None for geometry only.
    color_threshold: largest Euclidean RGB distance between the mean
      colours of two touching voxels that are joined.
    min_voxel_points: voxels with fewer points are noise.
    min_cluster_points: clusters with fewer points are noise.

  Returns:
    (K,) int32 labels, 0..n-1 by decreasing size, -1 for noise.
  """
  x = _as_points(points, 'cluster_points')
  K = x.shape[0]
  if colors is not None and np.shape(colors) != (K, 3):
    raise SegmentationError(
      f'cluster_points: colors must be ({K}, 3) RGB like the points, got '
      f'shape {np.shape(colors)}')
  if K == 0:
    return np.zeros(0, np.int32)
  if not eps > 0:
    raise SegmentationError(f'cluster_points: eps must be > 0, got {eps}')
  cells = np.floor((x - x.min(0)) / eps)
  # +1 margin on each side for the neighbour offsets; checked in floats
  # before the integer cast (a tiny eps overflowed int64 silently).
  if float(np.prod(cells.max(0) + 3)) > 2.0 ** 62:
    raise SegmentationError(f'cluster_points: eps={eps} is too small for the '
                            f'extent {x.max(0) - x.min(0)}; raise eps')
  cell = cells.astype(np.int64)
  dims = cell.max(0) + 3
  cell += 1
  keys = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
  vkeys, inv, counts = np.unique(keys, return_inverse=True,
                                 return_counts=True)
  V = vkeys.size
  dense = counts >= min_voxel_points
  if colors is not None:
    c = np.asarray(colors, np.float64)
    mean_c = np.stack([np.bincount(inv, c[:, j], V) for j in range(3)],
                      axis=1) / counts[:, None]
  vcell = np.stack([vkeys // (dims[1] * dims[2]),
                    (vkeys // dims[2]) % dims[1], vkeys % dims[2]], axis=1)
  rows, cols = [], []
  for off in _NEIGHBOUR_OFFSETS:
    nk = ((vcell[:, 0] + off[0]) * dims[1] + vcell[:, 1] + off[1]) * dims[2] \
      + vcell[:, 2] + off[2]
    pos = np.searchsorted(vkeys, nk)
    pos = np.minimum(pos, V - 1)
    hit = (vkeys[pos] == nk) & dense & dense[pos]
    if colors is not None:
      hit &= np.linalg.norm(mean_c - mean_c[pos], axis=1) < color_threshold
    src = np.nonzero(hit)[0]
    rows.append(src)
    cols.append(pos[src])
  rows = np.concatenate(rows)
  cols = np.concatenate(cols)
  graph = scipy.sparse.coo_matrix(
    (np.ones(rows.size, np.int8), (rows, cols)), shape=(V, V)).tocsr()
  _, comp = scipy.sparse.csgraph.connected_components(graph, directed=False)
  comp = np.where(dense, comp, -1)
  labels = comp[inv]
  sizes = np.bincount(labels[labels >= 0]) if (labels >= 0).any() else (
    np.zeros(0, np.int64))
  small = np.nonzero(sizes < min_cluster_points)[0]
  labels = np.where(np.isin(labels, small), -1, labels)
  out, _ = compact_labels(labels, order='size')
  return out


def segment_geometric(
  gaussians: Gaussians,
  up=(0.0, 0.0, 1.0),
  plane_threshold: float | None = None,
  eps: float | None = None,
  color_threshold: float = 0.25,
  min_cluster_points: int = 20,
  min_plane_fraction: float = 0.05,
  below_is_support: bool = True,
  max_tilt_deg: float | None = 30.0,
  reclaim_passes: int = 3,
  seed: int = 0,
) -> Segmentation:
  """Support plane + clusters of the remaining Gaussians.

  Args:
    gaussians: the scene.
    up: world up (None: any plane orientation).
    plane_threshold: plane inlier distance; default 1 % of the scene's
      bounding-box diagonal.
    eps: cluster voxel size; default 2 % of the diagonal of the non-support
      Gaussians.
    color_threshold: colour affinity (see :func:`cluster_points`).
    min_cluster_points: smaller clusters are background.
    min_plane_fraction: a plane with fewer inliers (fraction of K) is not a
      support; everything is clustered.
    below_is_support: Gaussians below the plane (beyond the threshold)
      belong to the support too (table legs, floor under a table top).
    max_tilt_deg: largest support tilt from horizontal.
    reclaim_passes: region-growing passes that give plane-band Gaussians
      back to an object: a Gaussian within the plane threshold whose
      nearest object Gaussian is closer than ``eps`` and of similar colour
      (``color_threshold``) is the object's base, not the support (objects
      rest ON the plane, so their bottoms fall inside the band).
    seed: RANSAC seed.

  Returns:
    A :class:`Segmentation` (method 'geometric'): object 0 is 'support'
    (fixed) when a plane was found, then 'object_1', ... by size.
  """
  x = _as_points(gaussians.means, 'segment_geometric (Gaussians.means)')
  K = x.shape[0]
  colors_all = np.clip(np.asarray(gaussians.rgb_dc, np.float64), 0, 1)
  support = np.zeros(K, bool)
  band = np.zeros(K, bool)
  have_plane = False
  if K >= 3:
    try:
      n, d, inl = fit_plane_ransac(x, plane_threshold, up=up,
                                   max_tilt_deg=max_tilt_deg, seed=seed)
      if inl.sum() >= min_plane_fraction * K:
        have_plane = True
        support = inl.copy()
        band = inl
        if below_is_support:
          support |= (x @ n + d) < 0
    except ValueError:
      pass
  rest = ~support
  ids = np.full(K, BACKGROUND, np.int32)
  names, fixed = [], []
  if have_plane:
    ids[support] = 0
    names.append('support')
    fixed.append(True)
  if rest.any():
    xr = x[rest]
    if eps is None:
      eps = 0.02 * _diag(xr)
    lab = cluster_points(xr, eps, colors_all[rest], color_threshold,
                         min_cluster_points=min_cluster_points)
    base = len(names)
    sub = np.where(lab >= 0, lab + base, BACKGROUND)
    ids[rest] = sub
    for i in range(int(lab.max()) + 1 if lab.size and lab.max() >= 0 else 0):
      names.append(f'object_{base + i}')
      fixed.append(False)
    if have_plane:
      _reclaim_bases(x, colors_all, ids, band, base, eps, color_threshold,
                     reclaim_passes)
  return Segmentation(ids, tuple(names), tuple(fixed), method='geometric')


def _reclaim_bases(x, colors, ids, band, first_object, eps, color_threshold,
                   passes):
  """Gives plane-band Gaussians next to an object (same colour) to it."""
  import scipy.spatial

  for _ in range(passes):
    obj = ids >= first_object
    cand = np.nonzero(band & (ids < first_object))[0]
    if not obj.any() or cand.size == 0:
      return
    src = np.nonzero(obj)[0]
    tree = scipy.spatial.cKDTree(x[src])
    d, j = tree.query(x[cand], distance_upper_bound=eps)
    hit = np.isfinite(d)
    jj = src[np.where(hit, j, 0)]
    hit &= np.linalg.norm(colors[cand] - colors[jj], axis=1) < color_threshold
    if not hit.any():
      return
    ids[cand[hit]] = ids[jj[hit]]
