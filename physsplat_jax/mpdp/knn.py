"""Static-shape k nearest neighbours of a masked point cloud (jittable).

Two implementations of one function, ``(points (N, 3), mask (N,), k) ->
(N, k) int32`` indices of the ``k`` nearest *valid* points of every point
(itself included), ordered by ``(distance, index)``; slots with no valid
neighbour point to the row itself:

- :func:`knn_brute`: ``lax.top_k`` over each row of the (N, N) distance
  matrix, :data:`BRUTE_BLOCK` rows at a time (O(N^2) time, O(BRUTE_BLOCK
  N) memory). The reference, and the one ``'auto'`` picks up to
  :data:`BRUTE_MAX_POINTS` points: a program that compiles in a fraction
  of a second, where the grid's takes seconds.
- :func:`knn_grid`: sorted cell lists (jax-md ``partition.cell_list``
  style), O(N (k + L)) memory for L cell sizes. Pure ``jnp``/``lax`` with
  static shapes, so it runs unchanged on CPU and GPU.

**Grid.** Points are binned in cubic cells at ``L`` sizes ``h_l = h 2^(l -
finer_levels)``; per level one sort by hashed cell key gives the sorted
order and, per key, where its points start (a table of ``4 N`` keys). The
base side ``h`` comes from the data (below). Each point then picks its own
level: the finest whose ``3^3`` cells around it hold at least
``block_target = 12 k`` points (27 table look-ups per level), so dense and
sparse parts of one object (the shell and the interior of a captured
object, a refined PGAS region) each get cells that fit them. It scans those
27 cells, near side first, up to ``budget = 32 k`` candidates, keeps the
``k + extra`` nearest (``lax.top_k``), and orders them by ``(d2, index)``.
Rows are processed ``batch_size`` at a time (``lax.map``), so the working
set is ``batch_size * budget`` (~2M candidates).

**Exactness.** A cell-size guess can miss neighbours, so every row is
*certified* or recomputed. A point at ``u = (x - lo) / h_l`` in cell
``floor(u)`` is at least ``h_l (1 + min_a min(f_a, 1 - f_a))``, ``f = u -
floor(u)``, from any point outside the 27 cells, and at least its
point-to-box distance from the points of a cell the budget cut off. If the
``k``-th candidate distance is below the smaller bound (less a margin for
float rounding of the cell coordinates), no unseen point can be among the
``k`` nearest: the row is exact. Rows that fail are retried (up to
``max_retries``, ``4 budget`` candidates) at the level whose side exceeds
their best known ``k``-th distance (then the 27 cells hold every
neighbour), one level finer after a cut-off nearby, one coarser when the
block held fewer than ``k`` points; what still fails is recomputed by brute
force against all points, ``repair_batch`` rows at a time in a
``lax.while_loop`` (memory ``repair_batch * N``). So the result is exact for
any input, and a bad input costs time only (``num_repaired``,
``num_brute``). Cells whose keys collide share one range, scanned once; the
foreign points in it are real points at their true distances, harmless.

**Ties.** Both paths order neighbours by ``(squared distance, index)`` with
the same expression ``sum((x_i - x_j)^2)``: the brute force because
``lax.top_k`` keeps the lower index first among equal values (XLA's TopK is
stable), the grid by ranking its ``k + extra`` best candidates by ``(d2,
index)``. A row whose tie at the ``k``-th distance runs past those is not
certified. Both return the same indices in the same order (tested on CPU,
lattices with exact ties included) as long as XLA rounds the distances the
same in both programs; otherwise only points at equal distance (to the
last bit) can swap.

**Integer coordinates.** Float distances are rounded differently by
different programs (a reduction in another order in another JAX version,
fused or reordered arithmetic on another backend), and point sets with
exact ties (PGAS samples of a lattice, mirror-symmetric ones) then swap
neighbours at the ``k``-th distance. Given int32 points
(:func:`lattice_coordinates`: the points snapped to a lattice of ``2^14``
steps across their largest extent) both paths compute squared distances
in integer arithmetic, exactly, and rank them as float32 (a deterministic
conversion): the same indices on every backend and in every JAX version.
The MPDP network searches its neighbours this way.

**Cell size.** The base side ``h`` is found in-graph by a bisection on
``log2 h`` (20 steps of O(N): hash, scatter-add, gather) for the smallest
``h`` at which a valid point shares its cell with on average
``block_target / 27`` valid points. Unlike a mean spacing from the
bounding box (far too large for a shell or a rod, whose points fill a
small part of their box), the occupancy adapts to the cloud's local
dimension; the per-point level then adapts to its density, from 8x finer
to 16x coarser (``finer_levels``, ``coarser_levels``), i.e. density ratios
up to 512x down and 4096x up before the brute force takes over.

**XLA note.** XLA may recompute a fused elementwise value separately for
each consumer and round it differently (seen on CPU, and
``optimization_barrier`` does not stop it): a cell key computed twice could
file a point on a cell face under two cells. So a level's key, order and
sorted positions all come out of one ``lax.sort``, and its ranges are
counted from the sorted keys.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax import struct

Array = jax.Array

_HASH_PRIMES = (73856093, 19349663, 83492791)
# Neighbour-cell offsets, (27, 3).
_OFFSETS = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing='ij'),
                    -1).reshape(27, 3).astype(np.int32)
# The same offsets with +1 meaning "towards the near side" of each axis,
# ordered by expected point-to-cell distance (own cell, near faces, ...,
# far corner): scanning cells in this order truncates the far ones first.
_NEAR_FIRST = _OFFSETS[np.argsort(
  ((_OFFSETS == 1) * 0.0625 + (_OFFSETS == -1) * 0.5625).sum(1),
  kind='stable')]
# Bisection steps on log2(cell size).
_BISECT_STEPS = 20
# Working-set budgets (elements) of one grid batch and one repair block.
_GRID_BUDGET = 2**21
_REPAIR_BUDGET = 2**24


class KnnResult(struct.PyTreeNode):
  """Grid kNN with its diagnostics.

  Attributes:
    index: (N, k) int32 neighbour indices, exact (see module docstring);
      invalid rows point to themselves.
    cell_size: () cell side ``h`` chosen from the data [units of points].
    num_repaired: () int32 valid rows not certified by their first scan
      (then retried; cost only, not error).
    num_brute: () int32 of those, rows recomputed by brute force.
    overflow: () bool, True if some scan was cut off by its ``budget``
      closer than its ``k``-th distance (those rows were retried: a cost
      flag, the result is still exact).
  """

  index: Array
  cell_size: Array
  num_repaired: Array
  num_brute: Array
  overflow: Array


# Steps of :func:`lattice_coordinates` across the largest extent: squared
# distances of points this far apart stay below 2^31 (3 * 2^28) in int32.
LATTICE_STEPS = 2**14


def lattice_coordinates(points: Array, mask: Array) -> Array:
  """(N, 3) int32: the valid points snapped to a lattice of
  :data:`LATTICE_STEPS` steps across their largest extent, from their
  lowest corner (invalid rows 0).

  Every step is one correctly rounded operation on the given floats, so the
  same points give the same integers on every backend; the kNN functions
  compute these points' distances exactly (module docstring, "Integer
  coordinates"). A step is ``1 / 16384`` of the extent, so neighbours whose
  distances differ by less than about two steps may be ranked either way.
  """
  points = jax.lax.stop_gradient(jnp.asarray(points))
  mask = jnp.asarray(mask, bool)
  lo, ext = _bounds(points, mask)
  scale = jnp.asarray(LATTICE_STEPS, points.dtype) / ext
  q = jnp.clip(jnp.round((points - lo) * scale), 0, LATTICE_STEPS)
  return jnp.where(mask[:, None], q, 0).astype(jnp.int32)


# Rows of the distance matrix :func:`knn_brute` holds at a time.
BRUTE_BLOCK = 512


def knn_brute(points: Array, mask: Array, k: int) -> Array:
  """Reference kNN over the (N, N) distance matrix, :data:`BRUTE_BLOCK`
  rows at a time (O(N^2) time, O(BRUTE_BLOCK N) memory).

  Args:
    points: (N, 3) positions, or int32 :func:`lattice_coordinates`
      (distances then exact).
    mask: (N,) bool validity; invalid points are never neighbours.
    k: number of neighbours (static); clipped to N.

  Returns:
    (N, min(k, N)) int32 indices by increasing distance (ties: lower index
    first); slots with no valid neighbour point to the row itself.
  """
  points, exact = _as_positions(jax.lax.stop_gradient(points))
  n = points.shape[0]
  k = min(k, n)
  if n <= BRUTE_BLOCK:
    return _brute_rows(points, mask, jnp.arange(n, dtype=jnp.int32), k,
                       exact)
  blocks = -(-n // BRUTE_BLOCK)
  # The last block repeats the last row where it runs past N.
  rows = jnp.minimum(jnp.arange(blocks * BRUTE_BLOCK, dtype=jnp.int32),
                     n - 1).reshape(blocks, BRUTE_BLOCK)
  out = jax.lax.map(lambda r: _brute_rows(points, mask, r, k, exact), rows)
  return out.reshape(blocks * BRUTE_BLOCK, k)[:n]


def _sq_dist(a: Array, b: Array, exact: bool) -> Array:
  """Squared distances over the last axis: float32 of the exact integer
  ones for integer-valued coordinates (``exact``, at most
  :data:`LATTICE_STEPS` apart), else ``sum((a - b)^2)``."""
  d = a - b
  if exact:
    d = d.astype(jnp.int32)
    return jnp.sum(d * d, axis=-1).astype(jnp.float32)
  return jnp.sum(d ** 2, axis=-1)


def _as_positions(points: Array) -> tuple[Array, bool]:
  """``(float positions, exact)``: integer points (coordinates in [0,
  :data:`LATTICE_STEPS`], as :func:`lattice_coordinates` gives; wider ones
  would overflow int32 squared distances) as float32, which holds them
  exactly, and ``exact=True``."""
  points = jnp.asarray(points)
  if jnp.issubdtype(points.dtype, jnp.integer):
    return points.astype(jnp.float32), True
  return points, False


def _brute_rows(points: Array, mask: Array, rows: Array, k: int,
                exact: bool = False) -> Array:
  """Rows ``rows`` of :func:`knn_brute` (same expression), (B, k)."""
  d2 = _sq_dist(points[rows][:, None, :], points[None, :, :], exact)
  d2 = jnp.where(mask[None, :], d2, jnp.inf)
  neg, idx = jax.lax.top_k(-d2, k)
  return jnp.where(jnp.isfinite(neg), idx, rows[:, None]).astype(jnp.int32)


def _hash(c: Array, table: int) -> Array:
  """Cell coordinates (..., 3) int32 (>= 0) -> keys in [0, table)."""
  c = c.astype(jnp.uint32)
  h = (c[..., 0] * np.uint32(_HASH_PRIMES[0])) ^ (
    c[..., 1] * np.uint32(_HASH_PRIMES[1])) ^ (
    c[..., 2] * np.uint32(_HASH_PRIMES[2]))
  return (h % np.uint32(table)).astype(jnp.int32)


def _table_size(n: int) -> int:
  table = 1
  while table < 4 * n:  # sparse: few cells share a key
    table *= 2
  return table


def _bounds(points: Array, mask: Array) -> tuple[Array, Array]:
  """(lo (3,), extent ()) of the valid points (0 and 1 if none)."""
  inf = jnp.asarray(jnp.inf, points.dtype)
  lo = jnp.min(jnp.where(mask[:, None], points, inf), axis=0)
  hi = jnp.max(jnp.where(mask[:, None], points, -inf), axis=0)
  ok = jnp.all(jnp.isfinite(lo))
  lo = jnp.where(ok, lo, 0.0)
  ext = jnp.where(ok, jnp.max(hi - lo), 0.0)
  return lo, jnp.where(ext > 0, ext, 1.0)


def cell_size(points: Array, mask: Array, occupancy: float,
              table: int | None = None) -> Array:
  """Smallest cell side at which valid points share a cell with about
  ``occupancy`` valid points (point-weighted mean, hashed cells).

  Bisection on ``log2 h`` over ``[ext / (4 N), 2 ext]`` (``ext`` the largest
  extent of the valid points); O(N) per step.

  Args:
    points: (N, 3) positions.
    mask: (N,) bool validity.
    occupancy: target mean number of valid points in a valid point's cell
      (itself included).
    table: hash table size (default 4 N rounded up to a power of 2).

  Returns:
    () cell side h [units of points].
  """
  n = points.shape[0]
  table = table or _table_size(n)
  lo, ext = _bounds(points, mask)
  m = mask.astype(jnp.int32)
  num = jnp.maximum(jnp.sum(m), 1).astype(points.dtype)
  p = jnp.where(mask[:, None], points - lo, 0.0)

  def occ(log_h):
    u = p / jnp.exp2(log_h)
    key = _hash(jnp.floor(u).astype(jnp.int32), table)
    cnt = jnp.zeros((table,), jnp.int32).at[key].add(m)
    return jnp.sum(jnp.where(mask, cnt[key], 0)).astype(points.dtype) / num

  def step(_, ab):
    a, b = ab
    mid = 0.5 * (a + b)
    small = occ(mid) < occupancy
    return jnp.where(small, mid, a), jnp.where(small, b, mid)

  log_ext = jnp.log2(ext)
  a = log_ext - np.log2(4.0 * max(n, 1))
  b = log_ext + 1.0
  _, b = jax.lax.fori_loop(0, _BISECT_STEPS, step, (a, b))
  return jnp.exp2(b)


class _Cells(struct.PyTreeNode):
  """Cell lists of sides ``h[l]``, stacked over levels ``l`` (leading axis):
  points sorted by hashed cell key, and where each key's points start."""

  h: Array       # (L,) cell sides
  order: Array   # (L, N) int32 sorted position -> point
  start: Array   # (L, T + 1) int32 first sorted position of a key
  x: Array       # (L, N, 3) sorted positions


def _cell_coords(points, lo, h):
  u = (points - lo) / h
  # +1 keeps neighbour cells >= 0 (the hash takes unsigned coordinates).
  return u, jnp.floor(u).astype(jnp.int32) + 1


def _build(points, mask, lo, h, table: int) -> _Cells:
  """One level (unstacked) of :class:`_Cells`.

  The keys, the order and the sorted positions all come out of one sort,
  and the key ranges are counted from its sorted keys: XLA may recompute a
  fused elementwise value separately for each consumer, rounding
  differently (seen on CPU), so a key computed twice could file a point
  on a cell face under two different cells.
  """
  n = points.shape[0]
  _, c = _cell_coords(jnp.where(mask[:, None], points, lo), lo, h)
  key = jnp.where(mask, _hash(c, table), table)  # invalid points sort last
  skey, order, x0, x1, x2 = jax.lax.sort(
    (key, jnp.arange(n, dtype=jnp.int32), points[:, 0], points[:, 1],
     points[:, 2]), num_keys=1, is_stable=True)
  count = jnp.zeros((table + 1,), jnp.int32).at[skey].add(1)
  start = (jnp.cumsum(count) - count).astype(jnp.int32)
  return _Cells(h=h, order=order, start=start,
                x=jnp.stack([x0, x1, x2], axis=-1))


def _block_counts(cells: _Cells, x, lo):
  """(L,) points in the 3^3 cells around ``x`` at every level."""
  table = cells.start.shape[1] - 1
  levels = jnp.arange(cells.h.shape[0])[:, None]
  _, c = _cell_coords(x, lo, cells.h[:, None])  # (L, 3)
  hk = _hash(c[:, None, :] + jnp.asarray(_OFFSETS), table)  # (L, 27)
  return jnp.sum(cells.start[levels, hk + 1] - cells.start[levels, hk],
                 axis=1)


def _query(cells: _Cells, lvl, x, i, ok, lo, eps, k: int, kx: int,
           budget: int, exact: bool = False):
  """kNN row of point ``i`` (at ``x``) from the 3^3 cells of level ``lvl``.

  The 27 cells are visited near side first (own cell, then faces, edges
  and corners on the side of the point, :data:`_NEAR_FIRST`) and their
  points concatenated; the first ``budget`` of them are scanned.

  Returns:
    (idx (k,), certified, kth (k-th smallest candidate d2, inf if fewer
    than k), truncated (a cell not fully scanned is closer than kth)).
  """
  n = cells.x.shape[1]
  table = cells.start.shape[1] - 1
  h = cells.h[lvl]
  u, c = _cell_coords(x, lo, h)
  f = u - jnp.floor(u)
  offs = jnp.asarray(_NEAR_FIRST) * jnp.where(f >= 0.5, 1, -1).astype(
    jnp.int32)
  gap = jnp.where(offs < 0, f, jnp.where(offs > 0, 1.0 - f, 0.0))
  box2 = jnp.sum(gap * gap, -1)  # (27,) point-to-cell distance^2 [cells^2]
  hk = _hash(c + offs, table)
  # Cells sharing a key (hash collisions) share one range: scan it once.
  # A range may hold points of other cells too: harmless, they are real
  # points at their true distances.
  eq = hk[:, None] == hk[None, :]
  first = jnp.argmax(eq, axis=1)  # first cell with the same key
  st = cells.start[lvl, hk]
  ct = jnp.where(first == jnp.arange(27), cells.start[lvl, hk + 1] - st, 0)
  end = jnp.cumsum(ct)
  # Candidate t is the (t - end[cid - 1])-th point of cell cid.
  t = jnp.arange(budget, dtype=jnp.int32)
  cid = jnp.minimum(jnp.sum(end[None, :] <= t[:, None], axis=1), 26)
  slot = jnp.minimum(st[cid] + t - (end - ct)[cid], n - 1)
  d2 = _sq_dist(x, cells.x[lvl, slot], exact)
  d2 = jnp.where(t < end[-1], d2, jnp.inf)
  neg, pos = jax.lax.top_k(-d2, kx)
  d2s = -neg
  j = cells.order[lvl, slot[pos]]
  # Order by (d2, index), as the brute force: rank by pairwise comparison
  # (cheaper than a lexsort of kx entries on CPU). The position breaks the
  # remaining ties (empty slots repeat an index) so ranks are a permutation.
  p = jnp.arange(kx)
  before = (d2s[None, :] < d2s[:, None]) | (
    (d2s[None, :] == d2s[:, None]) & (
      (j[None, :] < j[:, None]) | ((j[None, :] == j[:, None])
                                   & (p[None, :] < p[:, None]))))
  rank = jnp.sum(before, axis=1)
  j = jnp.zeros((kx,), jnp.int32).at[rank].set(j)
  d2s = jnp.zeros((kx,), d2s.dtype).at[rank].set(d2s)
  # Lower bound on the distance to any point not seen, in cell units: the
  # faces of the 3^3 block, and the nearest cell not fully scanned.
  rho2 = (1.0 + jnp.min(jnp.minimum(f, 1.0 - f))) ** 2
  cut2 = jnp.min(jnp.where(end[first] > budget, box2, jnp.inf))
  b = jnp.sqrt(jnp.minimum(rho2, cut2))
  bound = h * jnp.maximum(b - eps, 0.0)
  dk = d2s[k - 1]
  cert = (dk < bound * bound * (1.0 - 2.0**-20)) & (
    (kx == k) | (d2s[kx - 1] > dk))
  idx = jnp.where(jnp.isfinite(d2s[:k]), j[:k], i)
  idx = jnp.where(ok, idx, i)
  return idx, cert | ~ok, dk, ok & (cut2 * h * h <= dk)


def knn_grid(
  points: Array, mask: Array, k: int, *,
  budget: int | None = None, block_target: int | None = None,
  extra: int | None = None, finer_levels: int = 3, coarser_levels: int = 4,
  max_retries: int = 3, retry_budget: int | None = None,
  batch_size: int | None = None, repair_batch: int | None = None,
  cell: Array | float | None = None,
) -> KnnResult:
  """Exact kNN from sorted cell lists, O(N k) memory (see module docstring).

  Same result as :func:`knn_brute` (same sets and order, ties included),
  except that invalid rows point to themselves.

  Args:
    points: (N, 3) positions (no gradient flows through the indices), or
      int32 :func:`lattice_coordinates` (distances then exact).
    mask: (N,) bool validity; invalid points are never neighbours.
    k: number of neighbours (static); clipped to N.
    budget: candidates scanned per row (static; default ``32 k``).
    block_target: a row uses the finest level whose 27 cells hold at least
      this many points (default ``12 k``).
    extra: candidates kept beyond ``k`` to break ties by index (static;
      default ``k + 4``).
    finer_levels, coarser_levels: cell lists of sides ``h / 2^j`` and
      ``h 2^j`` around the base side ``h`` (static).
    max_retries: grid retries per row before the brute force (static).
    retry_budget: candidates per row in the retries (static; default
      ``4 budget``).
    batch_size: rows per ``lax.map`` step (static; default keeps the
      working set near 2M candidates).
    repair_batch: rows per brute-force step (static; default keeps
      ``repair_batch * N`` near 16M).
    cell: optional fixed base cell side (overrides the in-graph choice; any
      value stays exact, it only changes the cost).

  Returns:
    A :class:`KnnResult`.
  """
  points, exact = _as_positions(jax.lax.stop_gradient(points))
  mask = jnp.asarray(mask, bool)
  n = points.shape[0]
  k = min(k, n)
  budget = int(min(budget or 32 * k, n))
  rbudget = int(min(retry_budget or 4 * budget, n))
  target = int(block_target or 12 * k)
  kx = min(k + (k + 4 if extra is None else extra), budget)
  batch = int(batch_size or max(1, min(n, _GRID_BUDGET // budget)))
  rbatch = int(max(1, min(n, _GRID_BUDGET // rbudget)))
  rb = int(repair_batch or max(1, min(n, _REPAIR_BUDGET // max(n, 1))))
  table = _table_size(n)
  num_levels = finer_levels + 1 + coarser_levels
  dt = points.dtype

  lo, ext = _bounds(points, mask)
  if cell is None:
    h = cell_size(points, mask, max(target / 27.0, 1.0), table)
  else:
    h = jnp.asarray(cell, dt)
  hs = h * jnp.exp2(jnp.arange(num_levels, dtype=dt) - finer_levels)
  # Float-rounding margin of the certified radius, in cell units of the
  # finest level: cell coordinates are off by a few ulps of their magnitude.
  eps = (ext / hs[0] + 2.0) * np.float32(2.0**-20)
  cells = jax.vmap(_build, (None, None, None, 0, None))(
    points, mask, lo, hs, table)

  def next_level(lvl, kth, trunc):
    # Smallest level whose cell side exceeds the known bound on the k-th
    # distance (then the 3^3 block holds every neighbour); finer after a
    # truncation nearby, coarser when the block held too few points.
    fit = jnp.sum(hs * hs * (1.0 - 2.0**-10) <= kth[..., None],
                  axis=-1).astype(jnp.int32)
    return jnp.where(jnp.isfinite(kth),
                     jnp.where(trunc, jnp.minimum(fit, lvl - 1),
                               jnp.maximum(fit, lvl + 1)),
                     lvl + 1)

  def first(a):
    x, i, ok = a
    # The finest level whose 27 cells hold `target` points.
    cnt = _block_counts(cells, x, lo)
    lvl = jnp.minimum(jnp.sum(cnt < target), num_levels - 1).astype(
      jnp.int32)
    return (lvl,) + _query(cells, lvl, x, i, ok, lo, eps, k, kx, budget,
                           exact)

  # First pass: every point, in the sorted order of the base level, in
  # blocks of `batch` (padded: one compiled body, no remainder).
  order = cells.order[finer_levels]
  nb = -(-n // batch)
  batch = -(-n // nb)  # same block count, least padding
  pad = lambda a: jnp.pad(a, [(0, nb * batch - n)] + [(0, 0)] * (a.ndim - 1))
  blocks = tuple(pad(a).reshape((nb, batch) + a.shape[1:]) for a in (
    cells.x[finer_levels], order, mask[order]))
  lvl_s, idx_s, cert_s, kth_s, trunc_s = (
    a.reshape((nb * batch,) + a.shape[2:])[:n] for a in jax.lax.map(
      jax.vmap(first), blocks))
  inv = jnp.zeros((n,), jnp.int32).at[order].set(
    jnp.arange(n, dtype=jnp.int32))
  idx, cert, kth, trunc, lvl = (a[inv] for a in (
    idx_s, cert_s, kth_s, trunc_s, lvl_s))
  lvl = next_level(lvl, kth, trunc)
  overflow = jnp.any(trunc)
  num_repaired = jnp.sum(~cert).astype(jnp.int32)

  def pending(cert, lvl, tries):
    return ~cert & (lvl >= 0) & (lvl < num_levels) & (tries < max_retries)

  def retry(carry):
    idx, cert, kth, lvl, tries, overflow = carry
    rows = jnp.nonzero(pending(cert, lvl, tries), size=rbatch,
                       fill_value=n)[0].astype(jnp.int32)
    live = rows < n
    rc = jnp.minimum(rows, n - 1)
    new, ok, kth_r, trunc_r = jax.vmap(
      lambda x, i, l: _query(cells, l, x, i, mask[i], lo, eps, k, kx,
                             rbudget, exact))(points[rc], rc, lvl[rc])
    kth_r = jnp.minimum(kth_r, kth[rc])
    dst = jnp.where(live, rows, n)
    upd = jnp.where(live & ok, rows, n)
    return (idx.at[upd].set(new, mode='drop'),
            cert.at[upd].set(True, mode='drop'),
            kth.at[dst].set(kth_r, mode='drop'),
            lvl.at[dst].set(next_level(lvl[rc], kth_r, trunc_r),
                            mode='drop'),
            tries.at[dst].add(1, mode='drop'),
            overflow | jnp.any(trunc_r & live))

  tries = jnp.zeros((n,), jnp.int32)
  idx, cert, _, _, _, overflow = jax.lax.while_loop(
    lambda c: jnp.any(pending(c[1], c[3], c[4])), retry,
    (idx, cert, kth, lvl, tries, overflow))

  # Exact fallback: brute force against all points.
  def brute_block(carry):
    idx, cert = carry
    rows = jnp.nonzero(~cert, size=rb, fill_value=n)[0].astype(jnp.int32)
    new = _brute_rows(points, mask, jnp.minimum(rows, n - 1), k, exact)
    return (idx.at[rows].set(new, mode='drop'),
            cert.at[rows].set(True, mode='drop'))

  num_brute = jnp.sum(~cert).astype(jnp.int32)
  idx, _ = jax.lax.while_loop(lambda c: jnp.any(~c[1]), brute_block,
                              (idx, cert))
  return KnnResult(index=idx, cell_size=h, num_repaired=num_repaired,
                   num_brute=num_brute, overflow=overflow)


# Up to this many points (static N) 'auto' uses the brute force: its
# program compiles in ~0.2 s against ~3 s for the grid's (CPU), which at
# these sizes outweighs its O(N^2) time (6,000 points: 0.8 s against 0.6 s
# on the 2-core CPU; not yet measured on a GPU). docs/mpdp.md.
BRUTE_MAX_POINTS = 8192
METHODS = ('auto', 'grid', 'brute')


def knn_indices(points: Array, mask: Array, k: int,
                method: str = 'auto') -> Array:
  """(N, min(k, N)) int32 k nearest valid neighbours (self included).

  Args:
    points: (N, 3) positions, or int32 :func:`lattice_coordinates`
      (distances then exact).
    mask: (N,) bool validity; invalid points are never neighbours.
    k: number of neighbours (static).
    method: 'brute' (:func:`knn_brute`, O(N^2) time), 'grid'
      (:func:`knn_grid`, O(N k) memory) or 'auto' (brute for N <=
      :data:`BRUTE_MAX_POINTS`, else grid). All give the same valid rows.

  Returns:
    Indices ordered by (distance, index); slots with no valid neighbour
    point to the row itself.
  """
  if method not in METHODS:
    raise ValueError(f'knn method {method!r}; use one of {METHODS}')
  if method == 'auto':
    method = 'brute' if points.shape[0] <= BRUTE_MAX_POINTS else 'grid'
  if method == 'brute':
    return knn_brute(points, mask, k)
  return knn_grid(points, mask, k).index
