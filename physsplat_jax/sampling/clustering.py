"""K-means driving particles (PhysDreamer's downsampling baseline), jittable.

Lloyd iterations ``c_k <- mean{x_i : argmin_j |x_i - c_j| = k}`` from a
k-means++ initialisation (Arthur & Vassilvitskii 2007: each new centre drawn
with probability proportional to ``D(x)^2``) or a random subset. Empty
clusters keep their previous centre. Fixed shapes throughout. Points are
assigned in chunks, so memory is O(N + C) (not an (N, C) distance matrix);
time stays O(N C) per iteration, and the k-means++ seeding O(N C) in all.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from physsplat_jax import struct
from physsplat_jax.sampling.poisson import SamplingError
from physsplat_jax.types import Array


class KMeansResult(struct.PyTreeNode):
  """Attributes:
    centers: (C, 3) cluster centres.
    assign: (N,) int32 cluster of each point (-1 for invalid points).
    counts: (C,) int32 points per cluster.
    inertia: () sum of squared distances to the assigned centre.
  """

  centers: Array
  assign: Array
  counts: Array
  inertia: Array


# Elements of one (points chunk, centres) distance block: assignment memory
# is O(N + C + _ASSIGN_BUDGET), not O(N C).
_ASSIGN_BUDGET = 2**22


def _sq_dist(x: Array, c: Array) -> Array:
  d = (jnp.sum(x * x, 1)[:, None] - 2.0 * x @ c.T
       + jnp.sum(c * c, 1)[None, :])
  return jnp.maximum(d, 0.0)


def _assign(points: Array, centers: Array) -> tuple[Array, Array]:
  """Nearest centre and its squared distance, (N,) each, in point chunks."""
  n, c = points.shape[0], centers.shape[0]
  chunk = max(1, min(n, _ASSIGN_BUDGET // max(c, 1)))
  nb = -(-n // chunk)
  chunk = -(-n // nb)
  x = jnp.pad(points, ((0, nb * chunk - n), (0, 0))).reshape(nb, chunk, 3)

  def one(xc):
    d = _sq_dist(xc, centers)
    return jnp.argmin(d, 1), jnp.min(d, 1)

  a, dmin = jax.lax.map(one, x)
  return a.reshape(-1)[:n], dmin.reshape(-1)[:n]


def kmeans_pp_init(key: Array, points: Array, num_clusters: int,
                   valid: Array | None = None) -> Array:
  """k-means++ seeding; (C, 3) centres chosen among the valid points."""
  n = points.shape[0]
  valid = jnp.ones((n,), bool) if valid is None else valid
  keys = jax.random.split(key, num_clusters)
  logits0 = jnp.where(valid, 0.0, -jnp.inf)
  first = jax.random.categorical(keys[0], logits0)
  centers = jnp.zeros((num_clusters, 3), points.dtype).at[0].set(points[first])
  d2 = jnp.sum((points - points[first]) ** 2, 1)

  def body(i, carry):
    centers, d2 = carry
    logits = jnp.where(valid & (d2 > 0), jnp.log(jnp.maximum(d2, 1e-30)),
                       -jnp.inf)
    # All valid points coincide with centres: fall back to uniform.
    logits = jnp.where(jnp.any(jnp.isfinite(logits)), logits, logits0)
    j = jax.random.categorical(keys[i], logits)
    centers = centers.at[i].set(points[j])
    d2 = jnp.minimum(d2, jnp.sum((points - points[j]) ** 2, 1))
    return centers, d2

  centers, _ = jax.lax.fori_loop(1, num_clusters, body, (centers, d2))
  return centers


def kmeans(
  key: Array, points: Array, num_clusters: int, num_iters: int = 20,
  init: str = 'kmeans++', valid: Array | None = None,
) -> KMeansResult:
  """Lloyd's k-means with a fixed number of iterations (jittable).

  Args:
    key: PRNG key for the initialisation.
    points: (N, 3) positions.
    num_clusters: static C.
    num_iters: static number of Lloyd iterations.
    init: 'kmeans++' or 'random' (static).
    valid: optional (N,) bool mask.

  Returns:
    A :class:`KMeansResult`.
  """
  n = points.shape[0]
  if num_clusters < 1:
    raise SamplingError(f'kmeans: num_clusters={num_clusters} must be >= 1')
  valid = jnp.ones((n,), bool) if valid is None else valid
  if init == 'kmeans++':
    centers = kmeans_pp_init(key, points, num_clusters, valid)
  elif init == 'random':
    g = jax.random.gumbel(key, (n,))
    _, idx = jax.lax.top_k(jnp.where(valid, g, -jnp.inf), num_clusters)
    centers = points[idx]
  else:
    raise SamplingError(f"kmeans: init={init!r}; use 'kmeans++' or 'random'")
  w = valid.astype(points.dtype)

  def step(centers, _):
    a, _ = _assign(points, centers)
    cnt = jax.ops.segment_sum(w, a, num_clusters)
    s = jax.ops.segment_sum(points * w[:, None], a, num_clusters)
    new = jnp.where(cnt[:, None] > 0, s / jnp.maximum(cnt, 1.0)[:, None],
                    centers)
    return new, None

  centers, _ = jax.lax.scan(step, centers, None, length=num_iters)
  a, dmin = _assign(points, centers)
  counts = jnp.zeros((num_clusters,), jnp.int32).at[a].add(
    valid.astype(jnp.int32))
  inertia = jnp.sum(jnp.where(valid, dmin, 0.0))
  return KMeansResult(centers=centers,
                      assign=jnp.where(valid, a, -1).astype(jnp.int32),
                      counts=counts, inertia=inertia)
