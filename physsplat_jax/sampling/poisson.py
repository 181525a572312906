"""Poisson-disk subsampling of a point set with a per-point radius.

Candidates are the input points themselves (3DGS centres and fill particles).
Each candidate gets a random priority from ``key``; the kept set is the
*greedy maximal independent set in priority order* of the conflict graph

  i ~ j  <=>  |x_i - x_j| < min(r_i, r_j)

(the "min" convention): a point is kept iff no kept point of higher priority
conflicts with it. This is deterministic for a key. Guarantees (tested):

- separation: any two kept points satisfy ``|x_i - x_j| >= min(r_i, r_j)``;
- coverage: every input point ``p`` is within ``2 r_p`` of a kept point
  (within ``r_p`` without thinning: a dropped point conflicts with a kept one).

Two implementations of exactly these semantics (same priorities -> same kept
set, tested against each other and against a sequential greedy pass):

- :func:`poisson_disk`: jittable, fixed capacities, ``valid`` mask and
  overflow flags. A conflict list per point is built once from a sorted cell
  list, then parallel Luby-style rounds (``lax.while_loop``, early exit)
  decide the points: an undecided point whose priority beats every
  undecided neighbour is kept and its neighbours dropped.
- :func:`poisson_disk_host`: NumPy/SciPy, for host-side scene preparation
  (sampling is discrete and never differentiated). It visits the points in
  priority order in geometrically growing blocks: the points of a block that
  are still alive are decided by Luby rounds among themselves (pairs from a
  k-d tree over those survivors), and the block's kept points then kill
  their conflicts in later blocks (ball queries on a k-d tree over all
  points). Pairs are enumerated only among survivors and around kept
  points, so it costs ``O(N log N)`` sorting plus ``O(kept)`` queries:
  about 0.1-0.3 CPU s for 100k candidates.

Thinning (``thin=True``, both paths): radii fall in levels a factor 2
apart, ``r in (h_l / 2, h_l]`` with ``h_l = r_max / 2^l`` (the last level
takes all smaller radii). Each level is cut into voxels of side
``c_l = h_l / 4`` and only one representative per (level, voxel) is kept as
a candidate: the point with the smallest radius, then the highest priority.
Since ``sqrt(3) c_l <= h_l / 2 < r`` every point is within its own radius of
a representative whose radius is no larger, which gives the ``2 r`` coverage.
Because ``h_l / c_l = 4`` exactly, a level-``l`` cell of side ``h_l`` holds
at most ``4^3 = 64`` representatives of its level whatever the input density:
that is the cell capacity :data:`MAX_PER_CELL` of the jittable path. (The
last level is refined to ``c = h / 2^(2+j)`` when it holds radii below
``h / 2``, so that ``sqrt(3) c <= r_min``; its cells then hold up to
``64 * 8^j`` and the capacity overflow flag says so.)
"""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import scipy

from physsplat_jax import struct
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.types import Array


class SamplingError(PhysSplatError, ValueError):
  """Bad input to driver sampling and selection; the message names the
  field and the fix."""


_HASH_PRIMES = (73856093, 19349663, 83492791)
_SQRT3 = np.float32(math.sqrt(3.0))
# Representatives per level cell of side h: (h / c)^3 with c = h / 4.
MAX_PER_CELL = 64
# Refinements (halvings) of the last level's voxels for small radii.
_MAX_REFINE = 8
# cKDTree ball queries are run this much wider (float64) and then filtered
# with the exact float32 test shared with the jittable path.
_QUERY_SLACK = 1.0 + 1e-5
# Threads for k-d tree queries (-1: all cores).
_WORKERS = -1


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
      4 neighbours, 8 rounds, 16 radius range / extent (host diagnostics).
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


def radius_levels(radius, valid, num_levels: int):
  """Level of each point: radii in ``(r_max / 2^(l+1), r_max / 2^l]``.

  The last level also takes every smaller radius. Levels are found by exact
  comparisons with ``r_max / 2^l`` (no logarithm), so the NumPy and JAX
  paths agree bit for bit. Works on NumPy (host) or JAX arrays.

  Args:
    radius: (N,) float32 radii.
    valid: (N,) bool.
    num_levels: static number of levels L.

  Returns:
    (level (N,) int32, cell size per level h (L,), r_max ()).
  """
  xp = np if isinstance(radius, np.ndarray) else jnp
  r = xp.where(valid, radius, xp.zeros((), radius.dtype))
  r_max = xp.maximum(xp.max(r), np.float32(1e-30)).astype(radius.dtype)
  h = r_max / xp.asarray(2.0 ** np.arange(num_levels), radius.dtype)
  lvl = xp.sum(r[:, None] <= h[None, 1:], axis=1).astype(xp.int32)
  return lvl, h, r_max


def _voxel_size(h, r_min):
  """Thinning voxel side per level: ``h / 4``, refined on the last level.

  Returns:
    (c (L,), refine_overflow () bool: the last level needed more than
    :data:`_MAX_REFINE` halvings).
  """
  xp = np if isinstance(h, np.ndarray) else jnp
  c = h / h.dtype.type(4.0)
  c_last = c[-1]
  halvings = xp.asarray(2.0 ** np.arange(_MAX_REFINE + 1), h.dtype)
  need = _SQRT3 * (c_last / halvings) > r_min  # (J + 1,), monotone
  j = xp.minimum(xp.sum(need), _MAX_REFINE)
  c_last = c_last / halvings[j]
  if xp is np:
    c = c.copy()
    c[-1] = c_last
  else:
    c = c.at[-1].set(c_last)
  return c, need[-1]


def _thin_keys(points, radius, valid, num_levels: int):
  """Shared by both paths: (level, voxel (N, 3) int32, overflow bits)."""
  xp = np if isinstance(points, np.ndarray) else jnp
  lvl, h, _ = radius_levels(radius, valid, num_levels)
  inf = xp.asarray(np.inf, radius.dtype)
  r_min = xp.min(xp.where(valid, radius, inf))
  c, refine_over = _voxel_size(h, r_min)
  lo = xp.min(xp.where(valid[:, None], points, inf), axis=0)
  lo = xp.where(xp.isfinite(lo), lo, xp.zeros((), points.dtype))
  u = (points - lo) / c[lvl][:, None]
  u = xp.where(valid[:, None] & xp.isfinite(u), u, xp.zeros((), u.dtype))
  too_wide = refine_over | (xp.max(u) > 2.0**30)  # int32 voxel indices
  vox = xp.floor(xp.minimum(u, 2.0**30)).astype(xp.int32)
  return lvl, vox, too_wide


def thin_candidates(
  points: Array, radius: Array, priority: Array, valid: Array,
  num_levels: int = 3,
) -> tuple[Array, Array]:
  """One representative per (radius level, voxel of side ``h_l / 4``).

  In each voxel the point with the smallest radius (then the highest
  priority) represents the others, so every point ``p`` has a representative
  ``q`` with ``|p - q| < r_p`` and ``r_q <= r_p``; coverage of ``q`` within
  ``r_q`` then gives coverage of ``p`` within ``2 r_p``. At most 64
  representatives of a level share one of its cells (side ``h_l``).

  Args:
    points: (N, 3) float32 positions.
    radius: (N,) float32 radii.
    priority: (N,) distinct priorities (higher wins).
    valid: (N,) bool.
    num_levels: static number of radius levels.

  Returns:
    ((N,) bool mask of representatives (a subset of ``valid``),
    () bool: the radius range or extent is too wide for int32 voxels).
  """
  n = points.shape[0]
  lvl, vox, too_wide = _thin_keys(points, radius, valid, num_levels)
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
  return rep & valid, too_wide


def thin_candidates_host(points, radius, rank, valid, num_levels: int = 3):
  """NumPy twin of :func:`thin_candidates` (same representatives).

  One sort by (level, voxel) key; the representative of a group is its
  minimum of ``(radius, rank)`` packed into one int64 (float32 radius bits
  are monotone for positive radii).

  Args:
    points: (N, 3) float32.
    radius: (N,) float32 (positive where valid).
    rank: (N,) int priority rank (0 = highest priority), distinct.
    valid: (N,) bool.
    num_levels: number of radius levels.

  Returns:
    ((N,) bool representatives, bool too_wide).
  """
  n = len(points)
  rep = np.zeros(n, bool)
  if n == 0:
    return rep, False
  lvl, vox, too_wide = _thin_keys(points, radius, valid, num_levels)
  v = vox.astype(np.int64)
  dims = v.max(0) + 1
  lvl = np.where(valid, lvl, num_levels).astype(np.int64)
  if float(np.prod(dims.astype(np.float64))) * (num_levels + 1) < 2.0**62:
    # One int64 key per (level, voxel); invalid points share a level.
    gkey = ((lvl * dims[0] + v[:, 0]) * dims[1] + v[:, 1]) * dims[2] + v[:, 2]
  else:  # dense ranks of the (level, voxel) tuples
    _, gkey = np.unique(np.c_[lvl, v], axis=0, return_inverse=True)
    gkey = gkey.reshape(-1)
  order = np.argsort(gkey, kind='stable')
  sk = gkey[order]
  starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
  rbits = np.maximum(radius, 0).astype(np.float32).view(np.int32)
  k2 = (rbits.astype(np.int64) << 32) | np.asarray(rank, np.int64)
  k2 = k2[order]
  mn = np.minimum.reduceat(k2, starts)
  rep[order] = k2 == np.repeat(mn, np.diff(np.r_[starts, n]))
  return rep & valid, bool(too_wide)


def _conflict_d2(xi, xj):
  # Written out so that NumPy and XLA evaluate it in the same order.
  d = xj - xi
  return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def conflict_neighbors(
  points: Array, radius: Array, max_per_cell: int = MAX_PER_CELL,
  max_neighbors: int = 256, valid: Array | None = None,
  num_levels: int = 3, batch_size: int = 1024,
) -> tuple[Array, Array, Array, Array]:
  """Fixed-capacity lists of conflicting pairs ``|x_i-x_j| < min(r_i, r_j)``.

  Sorted cell list (jax-md ``partition.cell_list`` style): points are binned
  per radius level ``l`` into cells of side ``h_l = r_max / 2^l`` (>= every
  radius of that level), the cell keys (hashed, level included) are sorted
  once, and each point scans the 27 level-``l`` cells around it at every
  level (ranges found by ``searchsorted``), since a level-``l`` conflict is
  closer than ``r_j <= h_l``. Conflicts are compacted into the list by a
  prefix sum (no top-k).

  Args:
    points: (N, 3) positions.
    radius: (N,) positive radii (same units).
    max_per_cell: capacity of one cell (64 suffices for thinned input).
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
  M = max_neighbors
  valid = jnp.ones((n,), bool) if valid is None else valid
  r = jnp.where(valid, radius, 0.0)
  lvl, h, _ = radius_levels(radius, valid, L)
  lo = jnp.min(jnp.where(valid[:, None], points, jnp.inf), axis=0)
  lo = jnp.where(jnp.isfinite(lo), lo, 0.0)
  # Cell of every point at every level: (N, L, 3); +1 keeps neighbours >= 0.
  cell_all = jnp.floor((points - lo)[:, None, :] / h[None, :, None])
  cell_all = cell_all.astype(jnp.int32) + 1
  cell = jnp.take_along_axis(cell_all, lvl[:, None, None], axis=1)[:, 0]
  table = 1
  while table < 8 * n:  # sparse table: few collisions inflate a range
    table *= 2
  key = _cell_hash(cell, lvl, table)
  key = jnp.where(valid, key, table)  # invalid points sort last
  order = jnp.argsort(key)
  skey = key[order]
  offs = jnp.asarray(
    np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing='ij'),
             -1).reshape(27, 3), jnp.int32)
  levels = jnp.arange(L, dtype=jnp.int32)[:, None]

  def one(args):
    # Conflicts of one point; mapped in batches to bound memory.
    i, x_i, r_i, c_i, ok_i = args
    nc = c_i[:, None, :] + offs  # (L, 27, 3)
    nkey = _cell_hash(nc, levels, table)
    start = jnp.searchsorted(skey, nkey, side='left')
    end = jnp.searchsorted(skey, nkey, side='right')
    over = ok_i & jnp.any(end - start > max_per_cell)
    slot = start[..., None] + jnp.arange(max_per_cell)  # (L, 27, C)
    j = order[jnp.clip(slot, 0, n - 1)]
    same = jnp.all(cell[j] == nc[..., None, :], axis=-1) & (
      lvl[j] == levels[..., None])
    d2 = _conflict_d2(x_i, points[j])
    rmin = jnp.minimum(r[j], r_i)
    conf = ((slot < end[..., None]) & same & (j != i) & (d2 < rmin * rmin)
            & ok_i & valid[j]).ravel()
    pos = jnp.cumsum(conf) - 1
    dst = jnp.where(conf & (pos < M), pos, M)
    nbr = jnp.zeros((M,), jnp.int32).at[dst].set(j.ravel(), mode='drop')
    return nbr, jnp.arange(M) <= pos[-1], over, pos[-1] + 1

  nbr, mask, over, num = jax.lax.map(
    one, (jnp.arange(n), points, r, cell_all, valid), batch_size=batch_size)
  return nbr, mask, jnp.any(over), jnp.any(num > M)


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
  nb_prio = jnp.where(nbr_mask, priority[nbr], -jnp.inf)

  def cond(c):
    state, it = c
    return jnp.any(state == UND) & (it < max_rounds)

  def body(c):
    state, it = c
    und = state == UND
    nb_best = jnp.max(jnp.where(und[nbr], nb_prio, -jnp.inf), axis=1)
    win = und & (priority > nb_best)
    nb_win = jnp.any(nbr_mask & win[nbr], axis=1)
    state = jnp.where(win, KEEP, jnp.where(und & nb_win, DROP, state))
    return state.astype(jnp.int8), it + 1

  state, _ = jax.lax.while_loop(cond, body, (state0, jnp.int32(0)))
  return state == KEEP, jnp.any(state == UND)


def _ranked_priority(key, priority, n):
  """Distinct float priorities ``-rank`` (stable: ties to the lower index)."""
  if priority is None:
    if key is None:
      raise SamplingError(
        'poisson_disk: pass a PRNG key or explicit priorities')
    priority = jax.random.uniform(key, (n,), jnp.float32)
  rank = jnp.argsort(jnp.argsort(-priority)).astype(jnp.float32)
  return -rank  # exact in f32 up to 2^24 points


def _compact(keep, prio, points, count, max_samples: int):
  n = points.shape[0]
  score = jnp.where(keep, prio, -jnp.inf)
  _, idx = jax.lax.top_k(score, min(max_samples, n))
  if max_samples > n:
    idx = jnp.pad(idx, (0, max_samples - n))
  sel_valid = jnp.arange(max_samples) < jnp.minimum(count, max_samples)
  idx = jnp.where(sel_valid, idx, 0).astype(jnp.int32)
  pts = jnp.where(sel_valid[:, None], points[idx], 0.0)
  return idx, pts, sel_valid


def poisson_disk(
  key: Array | None,
  points: Array,
  radius: Array | float,
  max_samples: int,
  valid: Array | None = None,
  max_per_cell: int = MAX_PER_CELL,
  max_neighbors: int = 256,
  max_rounds: int = 256,
  priority: Array | None = None,
  thin: bool = True,
  num_levels: int = 3,
) -> PoissonResult:
  """Poisson-disk subsample of ``points`` with per-point radius (jittable).

  Args:
    key: PRNG key for the random priorities (ignored if ``priority`` given).
    points: (N, 3) candidate positions.
    radius: (N,) or scalar Poisson radius per point (same units).
    max_samples: static output capacity.
    valid: optional (N,) bool mask of usable candidates.
    max_per_cell, max_neighbors, max_rounds: static capacities; see module
      docstring (64 per cell is the bound for thinned input). A point's
      conflicts in a dense thinned cloud number about
      ``4.19 * 64 * (r / h_l)^3`` per level (34 at the bottom of a level,
      ~270 at the top), so 256 neighbours can overflow on very dense input.
      Overflow of any of them sets ``overflow``.
    priority: optional (N,) explicit priorities (higher kept first).
    thin: first keep one representative per small voxel
      (:func:`thin_candidates`); bounds the cell occupancy on dense inputs,
      and the coverage bound becomes ``2 r`` instead of ``r``. With
      ``thin=False`` the result is exactly the sequential greedy pass in
      priority order.
    num_levels: static number of radius levels (factor 2 apart); 3 covers
      the radius range ``r_max / 8 .. r_max`` (PGAS clips at ``r / 5``).
      Smaller radii share the last level, which is then scanned with finer
      voxels (more points per cell).

  Returns:
    A :class:`PoissonResult`.
  """
  n = points.shape[0]
  points = jnp.asarray(points, jnp.float32)
  radius = jnp.broadcast_to(jnp.asarray(radius, jnp.float32), (n,))
  valid = jnp.ones((n,), bool) if valid is None else valid
  # Same rule as the host path: no position or no positive radius, no point.
  valid = valid & jnp.isfinite(radius) & (radius > 0) & jnp.all(
    jnp.isfinite(points), axis=1)
  prio = _ranked_priority(key, priority, n)
  too_wide = jnp.asarray(False)
  if thin:
    valid, too_wide = thin_candidates(points, radius, prio, valid,
                                      num_levels)
  nbr, mask, cell_of, nbr_of = conflict_neighbors(
    points, radius, max_per_cell, max_neighbors, valid, num_levels)
  keep, unfinished = greedy_independent_set(prio, nbr, mask, valid,
                                            max_rounds)
  count = jnp.sum(keep).astype(jnp.int32)
  idx, pts, sel_valid = _compact(keep, prio, points, count, max_samples)
  code = ((count > max_samples) * 1 + cell_of * 2 + nbr_of * 4
          + unfinished * 8 + too_wide * 16).astype(jnp.int32)
  return PoissonResult(
    index=idx, points=pts, valid=sel_valid, count=count, keep=keep,
    overflow=code > 0, overflow_code=code)


# ---------------------------------------------------------------------------
# Host path (NumPy / SciPy).


def _luby_host(num: int, a, b) -> np.ndarray:
  """Greedy MIS of nodes ``0..num-1`` (index = priority rank) in rounds.

  Args:
    num: number of nodes; a lower index has a higher priority.
    a, b: (E,) int edges, both directions present.

  Returns:
    (num,) bool kept.
  """
  und = np.ones(num, bool)
  kept = np.zeros(num, bool)
  fwd = a < b  # a beats b
  a, b = a[fwd], b[fwd]
  while und.any():
    act = und[a] & und[b]
    a, b = a[act], b[act]
    blocked = np.zeros(num, bool)
    blocked[b] = True
    win = und & ~blocked
    kept |= win
    lose = np.zeros(num, bool)
    lose[b[win[a]]] = True
    und &= ~(win | lose)
  return kept


def _tree_rank(tree, data_index, n):
  """(n,) position of each point of ``x`` in the tree's leaf order."""
  rank = np.zeros(n, np.int64)
  idx = tree.indices if data_index is None else data_index[tree.indices]
  rank[idx] = np.arange(len(idx))
  return rank


def _pairs(x, r, rows, tree, data_index=None):
  """Conflicts (src, dst) of points ``rows`` with the points of ``tree``.

  One k-d tree ball query per row at its own radius (slightly widened, in
  float64), then the exact float32 test ``d^2 < min(r_s, r_d)^2`` shared
  with the jittable path.

  Args:
    x: (n, 3) float32 positions; r: (n,) float32 radii.
    rows: (q,) int indices into ``x`` of the query points.
    tree: cKDTree over ``x[data_index]`` (or over ``x`` if None).
    data_index: optional (t,) int indices of the tree's points into ``x``.

  Returns:
    (src, dst) int64 indices into ``x``, ``src`` in ``rows``, src != dst.
  """
  if len(rows) == 0:
    e = np.zeros(0, np.int64)
    return e, e
  # Queries in the tree's own (spatially coherent) order run faster.
  rows = rows[np.argsort(_tree_rank(tree, data_index, len(x))[rows])]
  lists = tree.query_ball_point(
    x[rows].astype(np.float64), r[rows].astype(np.float64) * _QUERY_SLACK,
    return_sorted=False, workers=_WORKERS)
  lens = np.fromiter(map(len, lists), np.int64, len(lists))
  dst = np.fromiter(itertools.chain.from_iterable(lists), np.int64,
                    int(lens.sum()))
  if data_index is not None:
    dst = data_index[dst]
  src = np.repeat(rows, lens)
  rm = np.minimum(r[src], r[dst])
  conf = (_conflict_d2(x[src], x[dst]) < rm * rm) & (src != dst)
  return src[conf], dst[conf]


def _greedy_host(x, r, first_block: int) -> np.ndarray:
  """Greedy MIS of points already sorted by decreasing priority.

  Blocks of geometrically growing size are decided in order. The points of
  a block still alive (no conflict with a kept point of an earlier block)
  are decided by Luby rounds among themselves (pairs from a k-d tree over
  those survivors only), and the block's kept points then kill their
  conflicts in later blocks (pairs from a k-d tree over all points). So
  pairs are enumerated only around kept points and among survivors.

  Args:
    x: (n, 3) float32 positions, highest priority first.
    r: (n,) float32 radii.
    first_block: size of the first block (about the expected kept count).

  Returns:
    (n,) bool kept.
  """
  n = len(x)
  keep = np.zeros(n, bool)
  if n == 0:
    return keep
  tree = scipy.spatial.cKDTree(x.astype(np.float64), balanced_tree=False)
  dead = np.zeros(n, bool)
  start, size = 0, int(np.clip(first_block, 256, n))
  while start < n:
    end = min(n, start + size)
    surv = start + np.nonzero(~dead[start:end])[0]
    if len(surv):
      st = scipy.spatial.cKDTree(x[surv].astype(np.float64),
                                 balanced_tree=False)
      src, dst = _pairs(x, r, surv, st, surv)
      loc = np.zeros(n, np.int64)
      loc[surv] = np.arange(len(surv))
      kept = surv[_luby_host(len(surv), loc[src], loc[dst])]
      keep[kept] = True
      _, dst = _pairs(x, r, kept, tree)
      dead[dst] = True
    start, size = end, 2 * size
  return keep


def make_poisson_host(key=None, points=None, valid=None, priority=None,
                      thin: bool = True, num_levels: int = 3):
  """Host Poisson disk over fixed points and priorities, for many radii.

  The priority order is computed once; each call of the returned function
  thins and samples for a new radius field (the budget search of
  :func:`~physsplat_jax.sampling.pgas.scale_for_budget` calls it 3-5
  times).

  Args:
    key, points, valid, priority, thin, num_levels: as in
      :func:`poisson_disk_host`.

  Returns:
    ``sample_fn(radius, max_samples=None, expected_count=None) ->
    PoissonResult`` (NumPy arrays).
  """
  x = np.asarray(points, np.float32)
  n = len(x)
  valid0 = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
  if valid0.shape != (n,):
    raise SamplingError(f'poisson_disk_host: valid has shape {valid0.shape}; '
                        f'expected ({n},)')
  if priority is None:
    if key is None:
      raise SamplingError('poisson_disk_host: pass a PRNG key or explicit '
                          'priorities')
    priority = jax.random.uniform(key, (n,), jnp.float32)
  priority = np.asarray(priority, np.float32)
  order = np.argsort(-priority, kind='stable')  # rank -> point
  rank = np.empty(n, np.int64)
  rank[order] = np.arange(n)

  def sample_fn(radius, max_samples=None, expected_count=None):
    r = np.broadcast_to(np.asarray(radius, np.float32), (n,)).copy()
    ok = valid0 & np.isfinite(r) & (r > 0) & np.all(np.isfinite(x), axis=1)
    too_wide = False
    if thin:
      ok, too_wide = thin_candidates_host(x, r, rank, ok, num_levels)
    cand = order[ok[order]]  # candidates in priority order
    hint = expected_count if expected_count else max(len(cand) // 16, 1)
    kept_idx = cand[_greedy_host(x[cand], r[cand], hint)]  # priority order
    count = len(kept_idx)
    cap = count if max_samples is None else int(max_samples)
    m = min(cap, count)
    index = np.zeros(cap, np.int32)
    index[:m] = kept_idx[:m]
    sel_valid = np.arange(cap) < m
    pts = np.where(sel_valid[:, None], x[index], 0.0).astype(np.float32)
    keep = np.zeros(n, bool)
    keep[kept_idx] = True
    code = int(count > cap) * 1 + int(too_wide) * 16
    return PoissonResult(
      index=index, points=pts, valid=sel_valid, count=np.int32(count),
      keep=keep, overflow=np.bool_(code > 0), overflow_code=np.int32(code))

  return sample_fn


def poisson_disk_host(
  key=None,
  points=None,
  radius=None,
  max_samples: int | None = None,
  valid=None,
  priority=None,
  thin: bool = True,
  num_levels: int = 3,
  expected_count: int | None = None,
) -> PoissonResult:
  """NumPy/SciPy twin of :func:`poisson_disk` (same kept set for a key).

  Same arguments and result as :func:`poisson_disk` (NumPy arrays), without
  the cell/neighbour/round capacities, which it does not need: only
  ``max_samples`` can overflow (bit 1), and the radius range (bit 16).
  Positions and radii are rounded to float32 as in the jittable path, and
  the conflict test is evaluated in float32 with the same expression.
  Points with a non-finite position or a radius that is not > 0 are
  treated as invalid.

  Args:
    key: PRNG key for the priorities (``jax.random.uniform(key, (N,))``,
      as :func:`poisson_disk`), or None with ``priority``.
    points: (N, 3) candidate positions.
    radius: (N,) or scalar radii.
    max_samples: output capacity (default: the number kept).
    valid: optional (N,) bool.
    priority: optional (N,) explicit priorities (higher kept first).
    thin: as in :func:`poisson_disk`.
    num_levels: as in :func:`poisson_disk`.
    expected_count: optional hint for the first block size (speed only).

  Returns:
    A :class:`PoissonResult` of NumPy arrays.
  """
  sample_fn = make_poisson_host(key, points, valid, priority, thin,
                                num_levels)
  return sample_fn(radius, max_samples, expected_count)


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
    msgs.append('a cell holds more points than max_per_cell (raise '
                'max_per_cell, thin the candidates, or raise num_levels)')
  if code & 4:
    msgs.append('a point has more conflicts than max_neighbors (raise '
                'max_neighbors)')
  if code & 8:
    msgs.append('the independent-set rounds did not finish (raise '
                'max_rounds)')
  if code & 16:
    msgs.append('the radii span too many octaves or the points too large an '
                'extent for int32 voxels (raise num_levels, or clip the '
                'smallest radii)')
  raise SamplingError(f'{where} overflowed: ' + '; '.join(msgs))
