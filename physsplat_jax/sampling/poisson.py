"""Poisson-disk subsampling of a point set with a per-point radius (jittable).

Candidates are the input points themselves (3DGS centres and fill particles).
Each candidate gets a random priority from ``key``; the kept set is the
*greedy maximal independent set in priority order* of the conflict graph

  i ~ j  <=>  |x_i - x_j| < min(r_i, r_j)

(the "min" convention). It is computed in parallel with Luby-style rounds: an
undecided point whose priority beats every undecided neighbour is kept, and
its neighbours are dropped; the result is the same as the sequential greedy
pass, so it is deterministic for a key. Guarantees (checked in the tests):

- separation: any two kept points satisfy ``|x_i - x_j| >= min(r_i, r_j)``;
- coverage: every input point ``p`` is within ``2 r_p`` of a kept point
  (``r_p`` without thinning: a dropped point conflicts with a kept one).

Dense inputs are first thinned to one representative per voxel of side half
the lower bound of the point's radius level (:func:`thin_candidates`; the
representative has the smallest radius in its voxel), which keeps the
coverage within ``2 r`` and bounds the points per hash cell.

Neighbours come from a multi-level hashed cell grid (Teschner et al. 2003
spatial hashing; jax-md ``partition.cell_list``): radii are grouped in
levels a factor 2 apart, level ``l`` hashed in cells of side
``r_max / 2^l``, and each point scans the 27 cells around it at every level,
at most ``max_per_cell`` points per cell, keeping at most ``max_neighbors``
conflicts.
Everything has a fixed capacity; :class:`PoissonResult.overflow` says when a
capacity was too small (re-run with larger ones on the host).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

Array = jax.Array

_HASH_PRIMES = (73856093, 19349663, 83492791)


class PoissonResult(struct.PyTreeNode):
  """Fixed-capacity Poisson-disk sample.

  Attributes:
    index: (max_samples,) int32 indices of kept input points (0 where
      invalid); in priority order.
    points: (max_samples, 3) kept positions (0 where invalid).
    valid: (max_samples,) bool.
    count: () int32 number of kept points (may exceed ``max_samples`` when
      overflowing).
    keep: (N,) bool mask over the input points.
    overflow: () bool; True if any capacity (samples, cell occupancy,
      neighbours) or the round limit was exceeded: the result is then not a
      valid Poisson-disk sample.
    overflow_code: () int32 bit set: 1 samples, 2 cell occupancy,
      4 neighbours, 8 rounds (host-side diagnostics).
  """

  index: Array
  points: Array
  valid: Array
  count: Array
  keep: Array
  overflow: Array
  overflow_code: Array


def _cell_hash(c: Array, level: Array, table_size: int) -> Array:
  c = c.astype(jnp.uint32)
  h = (c[..., 0] * np.uint32(_HASH_PRIMES[0])) ^ (
    c[..., 1] * np.uint32(_HASH_PRIMES[1])) ^ (
    c[..., 2] * np.uint32(_HASH_PRIMES[2])) ^ (
    level.astype(jnp.uint32) * np.uint32(2654435761))
  return (h % np.uint32(table_size)).astype(jnp.int32)


def radius_levels(radius: Array, valid: Array, num_levels: int):
  """Level of each point: radii in ``(r_max / 2^(l+1), r_max / 2^l]``.

  The last level also takes every smaller radius.

  Returns:
    (level (N,) int32, cell size per level (L,), r_max ()).
  """
  r = jnp.where(valid, radius, 0.0)
  r_max = jnp.maximum(jnp.max(r), 1e-30)
  lvl = jnp.floor(jnp.log2(r_max / jnp.maximum(r, 1e-30)))
  lvl = jnp.clip(lvl, 0, num_levels - 1).astype(jnp.int32)
  h = r_max / 2.0 ** jnp.arange(num_levels)
  return lvl, h, r_max


def thin_candidates(
  points: Array, radius: Array, priority: Array, valid: Array,
  num_levels: int = 4,
) -> Array:
  """One representative per voxel of side ``r_lo / 2`` (per radius level).

  Voxel side ``c = r_lo / sqrt(3)``, ``r_lo`` the lower bound of the
  point's radius level (for the last level, at most half the smallest
  radius). In each voxel the point with the smallest radius (then the
  highest priority) represents the others, so every point ``p`` has a
  representative ``q`` with ``|p - q| < r_lo <= r_p`` and ``r_q <= r_p``;
  coverage of ``q`` within ``r_q`` then gives coverage of ``p`` within
  ``2 r_p``. It bounds the candidates per hash cell (at most
  ``(2 sqrt(3))^3 ~ 42`` per level) whatever the input density.

  Returns:
    (N,) bool mask of representatives (a subset of ``valid``).
  """
  n = points.shape[0]
  lvl, h, _ = radius_levels(radius, valid, num_levels)
  r_min = jnp.min(jnp.where(valid, radius, jnp.inf))
  # (sqrt(3) c <= h / 2 = the level's lower radius bound.)
  c = h / (2.0 * np.sqrt(3.0))
  c = c.at[-1].set(jnp.minimum(c[-1], 0.5 * r_min / np.sqrt(3.0)))
  lo = jnp.min(jnp.where(valid[:, None], points, jnp.inf), axis=0)
  lo = jnp.where(jnp.isfinite(lo), lo, 0.0)
  vox = jnp.floor((points - lo) / c[lvl][:, None]).astype(jnp.int32)
  big = jnp.iinfo(jnp.int32).max
  lvl_k = jnp.where(valid, lvl, big)
  keys = (-priority, radius, vox[:, 2], vox[:, 1], vox[:, 0], lvl_k)
  order = jnp.lexsort(keys)
  sv = vox[order]
  sl = lvl_k[order]
  first = jnp.concatenate([
    jnp.array([True]),
    jnp.any(sv[1:] != sv[:-1], axis=1) | (sl[1:] != sl[:-1])])
  rep = jnp.zeros((n,), bool).at[order].set(first)
  return rep & valid


def conflict_neighbors(
  points: Array, radius: Array, max_per_cell: int = 64,
  max_neighbors: int = 128, valid: Array | None = None,
  num_levels: int = 4, batch_size: int = 512,
) -> tuple[Array, Array, Array, Array]:
  """Fixed-capacity lists of conflicting pairs ``|x_i-x_j| < min(r_i, r_j)``.

  Points are binned per radius level ``l`` into hash cells of side
  ``h_l = r_max / 2^l`` (>= every radius of that level); a point finds its
  level-``l`` conflicts in the 27 level-``l`` cells around it, since a
  conflict is closer than ``r_j <= h_l``.

  Args:
    points: (N, 3) positions.
    radius: (N,) positive radii (same units).
    max_per_cell: capacity of one hash cell.
    max_neighbors: capacity of one point's conflict list.
    valid: optional (N,) bool; invalid points have no conflicts.
    num_levels: static number of radius levels (factor 2 apart).
    batch_size: points processed together (memory ~ batch_size *
      num_levels * 27 * max_per_cell).

  Returns:
    (nbr (N, max_neighbors) int32, nbr_mask (N, max_neighbors) bool,
    cell_overflow () bool, nbr_overflow () bool).
  """
  n = points.shape[0]
  L = num_levels
  valid = jnp.ones((n,), bool) if valid is None else valid
  r = jnp.where(valid, radius, 0.0)
  lvl, h, _ = radius_levels(radius, valid, L)
  lo = jnp.min(jnp.where(valid[:, None], points, jnp.inf), axis=0)
  lo = jnp.where(jnp.isfinite(lo), lo, 0.0)
  # Cell of every point at every level: (N, L, 3).
  cell_all = jnp.floor((points - lo)[:, None, :] / h[None, :, None])
  cell_all = cell_all.astype(jnp.int32) + 1
  cell = jnp.take_along_axis(cell_all, lvl[:, None, None], axis=1)[:, 0]
  table = 1
  while table < 2 * n:
    table *= 2
  key = _cell_hash(cell, lvl, table)
  key = jnp.where(valid, key, table)  # invalid points sort last
  order = jnp.argsort(key)
  skey = key[order]
  offs = jnp.asarray(
    np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing='ij'),
             -1).reshape(27, 3), jnp.int32)
  levels = jnp.arange(L, dtype=jnp.int32)[:, None]
  kk = min(max_neighbors, L * 27 * max_per_cell)

  def one(args):
    # Conflicts of one point; mapped in batches to bound memory.
    i, x_i, r_i, c_i, ok_i = args
    nc = c_i[:, None, :] + offs  # (L, 27, 3)
    nkey = _cell_hash(nc, levels, table)
    start = jnp.searchsorted(skey, nkey, side='left')
    end = jnp.searchsorted(skey, nkey, side='right')
    over = ok_i & jnp.any(end - start > max_per_cell)
    slot = start[..., None] + jnp.arange(max_per_cell)  # (L, 27, M)
    j = order[jnp.clip(slot, 0, n - 1)]
    same = jnp.all(cell[j] == nc[..., None, :], axis=-1) & (
      lvl[j] == levels[..., None])
    d2 = jnp.sum((points[j] - x_i) ** 2, axis=-1)
    rmin = jnp.minimum(r[j], r_i)
    conf = ((slot < end[..., None]) & same & (j != i) & (d2 < rmin * rmin)
            & ok_i & valid[j]).ravel()
    j = j.ravel()
    _, pos = jax.lax.top_k(conf.astype(jnp.int32), kk)
    return j[pos], conf[pos], over, jnp.sum(conf)

  nbr, mask, over, num = jax.lax.map(
    one, (jnp.arange(n), points, r, cell_all, valid), batch_size=batch_size)
  cell_overflow = jnp.any(over)
  nbr_overflow = jnp.any(num > max_neighbors)
  if kk < max_neighbors:
    pad = max_neighbors - kk
    nbr = jnp.pad(nbr, ((0, 0), (0, pad)))
    mask = jnp.pad(mask, ((0, 0), (0, pad)))
  return nbr.astype(jnp.int32), mask, cell_overflow, nbr_overflow


def greedy_independent_set(
  priority: Array, nbr: Array, nbr_mask: Array, valid: Array,
  max_rounds: int = 256,
) -> tuple[Array, Array]:
  """Greedy maximal independent set in decreasing priority (parallel rounds).

  Args:
    priority: (N,) distinct priorities (higher is picked first).
    nbr, nbr_mask: (N, M) conflict lists (symmetric relation).
    valid: (N,) bool; invalid points are never kept.
    max_rounds: round limit.

  Returns:
    (keep (N,) bool, unfinished () bool: True if rounds ran out).
  """
  UND, KEEP, DROP = 0, 1, 2
  state0 = jnp.where(valid, UND, DROP).astype(jnp.int8)

  def cond(c):
    state, it = c
    return jnp.any(state == UND) & (it < max_rounds)

  def body(c):
    state, it = c
    und = state == UND
    nb_und = nbr_mask & und[nbr]
    nb_best = jnp.max(jnp.where(nb_und, priority[nbr], -jnp.inf), axis=1)
    win = und & (priority > nb_best)
    nb_win = jnp.any(nbr_mask & win[nbr], axis=1)
    state = jnp.where(win, KEEP, jnp.where(und & nb_win, DROP, state))
    return state.astype(jnp.int8), it + 1

  state, _ = jax.lax.while_loop(cond, body, (state0, jnp.int32(0)))
  return state == KEEP, jnp.any(state == UND)


def poisson_disk(
  key: Array,
  points: Array,
  radius: Array | float,
  max_samples: int,
  valid: Array | None = None,
  max_per_cell: int = 64,
  max_neighbors: int = 128,
  max_rounds: int = 256,
  priority: Array | None = None,
  thin: bool = True,
  num_levels: int = 4,
) -> PoissonResult:
  """Poisson-disk subsample of ``points`` with per-point radius (jittable).

  Args:
    key: PRNG key for the random priorities (ignored if ``priority`` given).
    points: (N, 3) candidate positions.
    radius: (N,) or scalar Poisson radius per point (same units).
    max_samples: static output capacity.
    valid: optional (N,) bool mask of usable candidates.
    max_per_cell, max_neighbors, max_rounds: static capacities; see module
      docstring. Overflow of any of them sets ``overflow``.
    priority: optional (N,) explicit priorities (higher kept first).
    thin: first keep one representative per small voxel
      (:func:`thin_candidates`); bounds the work on dense inputs, and the
      coverage bound becomes ``2 r`` instead of ``r``. With ``thin=False``
      the result is exactly the sequential greedy pass in priority order.
    num_levels: static number of radius levels (factor 2 apart) of the
      multi-level hash grid; radii below ``r_max / 2^(L-1)`` share the last.

  Returns:
    A :class:`PoissonResult`.
  """
  n = points.shape[0]
  radius = jnp.broadcast_to(jnp.asarray(radius, points.dtype), (n,))
  valid = jnp.ones((n,), bool) if valid is None else valid
  if priority is None:
    priority = jax.random.uniform(key, (n,), jnp.float32)
  if priority is None and key is None:
    raise ValueError('poisson_disk: pass a PRNG key or explicit priorities')
  # Distinct priorities: ranks (argsort is stable, so ties go to the lower
  # index).
  rank = jnp.argsort(jnp.argsort(-priority)).astype(jnp.float32)
  prio = -rank  # distinct, exact in f32 up to 2^24 points
  if thin:
    valid = thin_candidates(points, radius, prio, valid, num_levels)
  nbr, mask, cell_of, nbr_of = conflict_neighbors(
    points, radius, max_per_cell, max_neighbors, valid, num_levels)
  keep, unfinished = greedy_independent_set(prio, nbr, mask, valid,
                                            max_rounds)
  count = jnp.sum(keep).astype(jnp.int32)
  # Kept indices in priority order, fixed capacity.
  score = jnp.where(keep, prio, -jnp.inf)
  _, idx = jax.lax.top_k(score, min(max_samples, n))
  if max_samples > n:
    idx = jnp.pad(idx, (0, max_samples - n))
  sel_valid = jnp.arange(max_samples) < jnp.minimum(count, max_samples)
  idx = jnp.where(sel_valid, idx, 0).astype(jnp.int32)
  pts = jnp.where(sel_valid[:, None], points[idx], 0.0)
  code = ((count > max_samples) * 1 + cell_of * 2 + nbr_of * 4
          + unfinished * 8).astype(jnp.int32)
  return PoissonResult(
    index=idx, points=pts, valid=sel_valid, count=count, keep=keep,
    overflow=code > 0, overflow_code=code)


def check_overflow(result: PoissonResult, where: str = 'poisson_disk'):
  """Host-side: raises a ValueError naming the capacity that overflowed."""
  code = int(result.overflow_code)
  if code == 0:
    return
  msgs = []
  if code & 1:
    msgs.append(f'{int(result.count)} samples > max_samples='
                f'{result.valid.shape[0]} (raise max_samples)')
  if code & 2:
    msgs.append('a hash cell holds more points than max_per_cell (raise '
                'max_per_cell, or thin the candidates)')
  if code & 4:
    msgs.append('a point has more conflicts than max_neighbors (raise '
                'max_neighbors)')
  if code & 8:
    msgs.append('the independent-set rounds did not finish (raise '
                'max_rounds)')
  raise ValueError(f'{where} overflowed: ' + '; '.join(msgs))
