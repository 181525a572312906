"""Curvature measures for PGAS.

Per-Gaussian (PhysSplat, Eq. for PGAS): with the covariance eigenvalues
``l1 >= l2 >= l3``::

  K_g = l3 / (l1 + l2 + l3)  in [0, 1/3]

(0 for a flat disc, 1/3 for an isotropic blob).

Local (per point), the PCA *surface variation* of Pauly et al. 2002: the same
ratio computed from the covariance of the ``k`` nearest neighbouring centres.
It is 0 on a plane and grows with the surface's curvature relative to the
neighbourhood size (1/3 for an isotropic volume).

Both are host-side (NumPy/SciPy): sampling happens once per scene, outside
the gradient path.
"""

from __future__ import annotations

import numpy as np
import scipy

from physsplat_jax.sampling.poisson import SamplingError


def eigen_ratio(cov) -> np.ndarray:
  """``l_min / trace`` of symmetric PSD matrices.

  Args:
    cov: (..., 3, 3) symmetric PSD matrices.

  Returns:
    (...,) values in [0, 1/3]; 0 where the trace is 0.
  """
  cov = np.asarray(cov, np.float64)
  cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
  ev = np.clip(np.linalg.eigvalsh(cov), 0.0, None)
  tr = ev.sum(-1)
  return np.where(tr > 0, ev[..., 0] / np.where(tr > 0, tr, 1.0), 0.0)


def gaussian_curvature(covariances) -> np.ndarray:
  """Per-Gaussian ``K = l3 / (l1 + l2 + l3)`` from (K, 3, 3) covariances."""
  covs = np.asarray(covariances)
  if covs.ndim != 3 or covs.shape[1:] != (3, 3):
    raise SamplingError(f'covariances have shape {covs.shape}; '
                        'expected (K, 3, 3)')
  return eigen_ratio(covs)


def local_curvature(points, k: int = 16, query=None) -> np.ndarray:
  """PCA surface variation of each query point's ``k`` nearest ``points``.

  Args:
    points: (N, 3) positions defining the surface (e.g. Gaussian centres).
    k: neighbourhood size (clipped to N).
    query: optional (Q, 3) points at which to evaluate (default ``points``).

  Returns:
    (Q,) values in [0, 1/3].
  """
  pts = np.asarray(points, np.float64)
  if pts.ndim != 2 or pts.shape[1] != 3:
    raise SamplingError(f'points have shape {pts.shape}; expected (N, 3)')
  q = pts if query is None else np.asarray(query, np.float64)
  k = int(min(max(k, 4), len(pts)))
  _, idx = scipy.spatial.cKDTree(pts).query(q, k=k, workers=-1)
  nb = pts[idx.reshape(len(q), k)]
  d = nb - nb.mean(1, keepdims=True)
  # The 6 distinct entries of the neighbourhood covariance (faster than a
  # batched einsum over (Q, k, 3, 3)).
  C = np.empty((len(q), 3, 3))
  for a in range(3):
    for b in range(a, 3):
      C[:, a, b] = C[:, b, a] = np.mean(d[..., a] * d[..., b], axis=1)
  return eigen_ratio(C)


def normalize_curvature(K, lo: float, hi: float, v_min: float = 1.0,
                        v_max: float = 10.0) -> np.ndarray:
  """Affine map of ``K`` from ``[lo, hi]`` onto ``[v_min, v_max]``, clipped.

  This is the normalisation that makes the paper's ``clip(K, V_min, V_max)``
  meaningful: raw ``K <= 1/3 < V_min`` would always clip to ``V_min``.
  """
  K = np.asarray(K, np.float64)
  span = max(hi - lo, 1e-12)
  t = np.clip((K - lo) / span, 0.0, 1.0)
  return v_min + (v_max - v_min) * t
