"""Internal particle filling: 3DGS objects are shells; fill their interior.

PhysGaussian-style (Xie et al. 2024, Sec. 5.1 "internal filling"), made
bounded and vectorised:

1. Occupancy grid. On a cubic grid of ``grid_res^3`` cells spanning the
   object's bounding box (plus a margin), each Gaussian adds its opacity-
   weighted density ``a_g exp(-d^T Sigma_g^-1 d / 2)`` to the cell centres in
   a fixed ``(2 f + 1)^3`` window around it. Standard deviations are clipped
   to ``[s_min dx, s_max dx]`` (``s_max = f / 3`` so the 3-sigma ellipsoid
   fits in the window). This is the fix for PhysGaussian's filler hanging for
   days on unstable covariances ("Large r ... 2147483647", issue #47): the
   work is ``K (2 f + 1)^3`` and the memory ``grid_res^3 + chunk (2 f + 1)^3``
   whatever the covariances. A cell is occupied if its density reaches
   ``density_threshold`` or it holds a Gaussian centre.
2. Inside test by ray casting along the 6 axis directions: an empty cell is
   interior if at least ``min_ray_hits`` of the 6 axis rays from it hit an
   occupied cell (a cumulative max along each axis, O(grid_res^3)).
   6 of 6 (the default) is the strictest; 5 tolerates one hole in the shell.
3. ``particles_per_cell`` points per interior cell, jittered uniformly in the
   cell with ``key`` (cell centres when ``key`` is None), written into a
   fixed-capacity array with a valid mask and an overflow flag.

:func:`fill_mesh` does the same from a closed mesh with trimesh's containment
test when a mesh is known.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from physsplat_jax import gaussians as _g
from physsplat_jax.types import Array

_MAX_GRID_RES = 256


@dataclasses.dataclass(frozen=True)
class FillConfig:
  """Static filling settings.

  Attributes:
    grid_res: cells along each axis of the cubic grid (<= 256).
    margin_cells: empty cells around the bounding box.
    footprint: f, half-width in cells of each Gaussian's splat window.
    min_sigma_cells: s_min, lower clip on std devs [cells].
    density_threshold: occupancy threshold on the summed density.
    opacity_threshold: Gaussians below this opacity are ignored.
    min_ray_hits: axis rays (of 6) that must hit the shell for "inside".
    particles_per_cell: fill points per interior cell.
    chunk: Gaussians splatted per scan step (bounds memory).
  """

  grid_res: int = 64
  margin_cells: int = 2
  footprint: int = 2
  min_sigma_cells: float = 0.5
  density_threshold: float = 0.5
  opacity_threshold: float = 0.02
  min_ray_hits: int = 6
  particles_per_cell: int = 1
  chunk: int = 8192

  def __post_init__(self):
    if not 8 <= self.grid_res <= _MAX_GRID_RES:
      raise ValueError(f'FillConfig.grid_res={self.grid_res}: use 8..'
                       f'{_MAX_GRID_RES} (memory grows as grid_res^3)')
    if not 1 <= self.footprint <= 4:
      raise ValueError(f'FillConfig.footprint={self.footprint}: use 1..4')
    if not 1 <= self.min_ray_hits <= 6:
      raise ValueError(f'FillConfig.min_ray_hits={self.min_ray_hits}: use '
                       '1..6')
    if self.particles_per_cell < 1:
      raise ValueError('FillConfig.particles_per_cell must be >= 1')
    if not self.min_sigma_cells < self.footprint / 3.0:
      raise ValueError('FillConfig.min_sigma_cells must be < footprint / 3')


class FillResult(struct.PyTreeNode):
  """Fixed-capacity fill particles.

  Attributes:
    points: (max_particles, 3) positions (0 where invalid).
    valid: (max_particles,) bool.
    count: () int32 number of interior points (may exceed capacity).
    overflow: () bool, True if count > max_particles.
    occupied: (G, G, G) bool shell occupancy.
    inside: (G, G, G) bool interior cells.
    origin: (3,) grid corner; cell (i, j, k) spans origin + dx [i, i+1) ...
    dx: () cell size.
  """

  points: Array
  valid: Array
  count: Array
  overflow: Array
  occupied: Array
  inside: Array
  origin: Array
  dx: Array


def occupancy_grid(
  means: Array, log_scales: Array, quats: Array, opacities: Array,
  origin: Array, dx: Array, config: FillConfig,
) -> tuple[Array, Array]:
  """Density and occupancy on the cubic grid (jittable, bounded cost).

  Args:
    means: (K, 3) centres.
    log_scales: (K, 3) log std devs (any value: clipped).
    quats: (K, 4) wxyz rotations.
    opacities: (K,) in [0, 1].
    origin: (3,) grid corner.
    dx: () cell size.
    config: :class:`FillConfig`.

  Returns:
    (density (G, G, G), occupied (G, G, G) bool).
  """
  G = config.grid_res
  f = config.footprint
  k = means.shape[0]
  ch = min(config.chunk, max(k, 1))
  nchunks = -(-k // ch)
  pad = nchunks * ch - k
  dt = means.dtype
  ls = jnp.nan_to_num(log_scales, nan=0.0, posinf=60.0, neginf=-60.0)
  sig = jnp.clip(jnp.exp(jnp.clip(ls, -60.0, 60.0)),
                 config.min_sigma_cells * dx, f / 3.0 * dx)
  R = _g.quat_to_rotmat(jnp.nan_to_num(quats))
  prec = (R / sig[:, None, :] ** 2) @ jnp.swapaxes(R, -1, -2)  # Sigma^-1
  alpha = jnp.where(opacities >= config.opacity_threshold, opacities, 0.0)
  padf = lambda a: jnp.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1))
  mu_c = padf(means).reshape(nchunks, ch, 3)
  prec_c = padf(prec).reshape(nchunks, ch, 3, 3)
  al_c = padf(alpha).reshape(nchunks, ch)
  offs = np.stack(np.meshgrid(*[np.arange(-f, f + 1)] * 3, indexing='ij'),
                  -1).reshape(-1, 3)
  offs = jnp.asarray(offs, jnp.int32)

  def splat(grid, xs):
    mu, P, a = xs
    c0 = jnp.floor((mu - origin) / dx).astype(jnp.int32)
    cells = c0[:, None, :] + offs  # (ch, W, 3)
    ctr = origin + (cells.astype(dt) + 0.5) * dx
    d = ctr - mu[:, None, :]
    q = jnp.einsum('cwa,cab,cwb->cw', d, P, d)
    val = a[:, None] * jnp.exp(-0.5 * q)
    ok = jnp.all((cells >= 0) & (cells < G), -1)
    flat = (cells[..., 0] * G + cells[..., 1]) * G + cells[..., 2]
    flat = jnp.where(ok, flat, G**3)
    grid = grid.at[flat.ravel()].add(val.ravel(), mode='drop')
    return grid, None

  grid, _ = jax.lax.scan(splat, jnp.zeros((G**3,), dt),
                         (mu_c, prec_c, al_c))
  density = grid.reshape(G, G, G)
  # Cells holding a (visible) Gaussian centre are occupied too, so thin
  # shells made of tiny Gaussians have no holes between cell centres.
  c0 = jnp.floor((means - origin) / dx).astype(jnp.int32)
  okc = jnp.all((c0 >= 0) & (c0 < G), -1) & (alpha > 0)
  flat = jnp.where(okc, (c0[:, 0] * G + c0[:, 1]) * G + c0[:, 2], G**3)
  has_centre = jnp.zeros((G**3,), bool).at[flat].set(True, mode='drop')
  occupied = (density >= config.density_threshold) | has_centre.reshape(
    G, G, G)
  return density, occupied


def interior_cells(occupied: Array, min_ray_hits: int = 6) -> Array:
  """Empty cells enclosed by occupied ones along >= min_ray_hits axis rays.

  Args:
    occupied: (G, G, G) bool.
    min_ray_hits: 1..6.

  Returns:
    (G, G, G) bool interior mask.
  """
  occ = occupied.astype(jnp.int8)
  hits = jnp.zeros(occupied.shape, jnp.int8)
  for ax in range(3):
    # Occupied strictly beyond the cell in the + and - direction.
    fwd = jax.lax.cummax(occ, axis=ax, reverse=True)
    bwd = jax.lax.cummax(occ, axis=ax)
    hits = hits + fwd + bwd
  return (~occupied) & (hits >= min_ray_hits)


def _bounds(means: Array, config: FillConfig) -> tuple[Array, Array]:
  lo = jnp.min(means, 0)
  hi = jnp.max(means, 0)
  ext = jnp.maximum(jnp.max(hi - lo), 1e-9)
  inner = config.grid_res - 2 * config.margin_cells
  dx = ext / inner
  centre = 0.5 * (lo + hi)
  origin = centre - 0.5 * config.grid_res * dx
  return origin, dx


def fill_gaussians(
  key: Array | None,
  means: Array,
  log_scales: Array,
  quats: Array,
  opacities: Array,
  max_particles: int,
  config: FillConfig = FillConfig(),
) -> FillResult:
  """Interior fill particles of one object's Gaussians (jittable).

  Args:
    key: PRNG key for the jitter, or None for cell centres (then
      ``particles_per_cell`` must be 1).
    means: (K, 3) centres (finite).
    log_scales: (K, 3) log std devs (clipped internally, any value).
    quats: (K, 4) wxyz.
    opacities: (K,) in [0, 1].
    max_particles: static output capacity.
    config: :class:`FillConfig`.

  Returns:
    A :class:`FillResult`.
  """
  if key is None and config.particles_per_cell != 1:
    raise ValueError('fill_gaussians: key=None places one point at each cell '
                     'centre; pass a PRNG key for particles_per_cell > 1')
  origin, dx = _bounds(means, config)
  _, occ = occupancy_grid(means, log_scales, quats, opacities, origin, dx,
                          config)
  inside = interior_cells(occ, config.min_ray_hits)
  G = config.grid_res
  m = config.particles_per_cell
  ncell = jnp.sum(inside).astype(jnp.int32)
  count = ncell * m
  max_cells = -(-max_particles // m)
  (idx,) = jnp.nonzero(inside.ravel(), size=max_cells, fill_value=0)
  ijk = jnp.stack([idx // (G * G), (idx // G) % G, idx % G], -1)
  base = origin + ijk.astype(means.dtype) * dx  # (C, 3) cell corners
  if key is None:
    u = jnp.full((max_cells, 1, 3), 0.5, means.dtype)
  else:
    u = jax.random.uniform(key, (max_cells, m, 3), means.dtype)
  pts = (base[:, None, :] + u * dx).reshape(-1, 3)[:max_particles]
  valid = jnp.arange(max_particles) < jnp.minimum(count, max_particles)
  pts = jnp.where(valid[:, None], pts, 0.0)
  return FillResult(points=pts, valid=valid, count=count,
                    overflow=count > max_particles, occupied=occ,
                    inside=inside, origin=origin, dx=dx)


def quat_to_rotmat_host(q):
  """NumPy twin of :func:`physsplat_jax.gaussians.quat_to_rotmat`.

  Non-finite entries read as 0 and quaternions of norm <= 1e-6 as the
  identity (bad covariances must not stall the filler).
  """
  q = np.nan_to_num(np.asarray(q, np.float64))
  n2 = np.sum(q * q, -1, keepdims=True)
  return _g.quat_to_rotmat_np(
    np.where(n2 > 1e-12, q, [1.0, 0.0, 0.0, 0.0]))


def occupancy_grid_host(means, log_scales, quats, opacities, origin, dx,
                        config: FillConfig):
  """NumPy twin of :func:`occupancy_grid` (float64, no compilation).

  Same splat (clipped std devs, fixed ``(2 f + 1)^3`` window, centre cells),
  accumulated with ``np.bincount`` over chunks of ``config.chunk``
  Gaussians: work ``K (2 f + 1)^3``, memory ``grid_res^3 + chunk (2f+1)^3``.

  Returns:
    (density (G, G, G), occupied (G, G, G) bool), NumPy.
  """
  G = config.grid_res
  f = config.footprint
  means = np.asarray(means, np.float64)
  origin = np.asarray(origin, np.float64)
  dx = float(dx)
  ls = np.nan_to_num(np.asarray(log_scales, np.float64), nan=0.0,
                     posinf=60.0, neginf=-60.0)
  sig = np.clip(np.exp(np.clip(ls, -60.0, 60.0)),
                config.min_sigma_cells * dx, f / 3.0 * dx)
  R = quat_to_rotmat_host(quats)
  prec = (R / sig[:, None, :] ** 2) @ np.swapaxes(R, -1, -2)
  op = np.asarray(opacities, np.float64)
  alpha = np.where(op >= config.opacity_threshold, op, 0.0)
  offs = np.stack(np.meshgrid(*[np.arange(-f, f + 1)] * 3, indexing='ij'),
                  -1).reshape(-1, 3)
  grid = np.zeros(G**3)
  for s in range(0, len(means), config.chunk):
    mu, P, a = (means[s:s + config.chunk], prec[s:s + config.chunk],
                alpha[s:s + config.chunk])
    c0 = np.floor((mu - origin) / dx).astype(np.int64)
    # Offset of each window cell centre from the mean, per axis: (c, W).
    base = origin + (c0 + 0.5) * dx - mu
    d = [base[:, i:i + 1] + offs[None, :, i] * dx for i in range(3)]
    q = (P[:, 0, 0, None] * d[0] * d[0] + P[:, 1, 1, None] * d[1] * d[1]
         + P[:, 2, 2, None] * d[2] * d[2]
         + 2.0 * (P[:, 0, 1, None] * d[0] * d[1]
                  + P[:, 0, 2, None] * d[0] * d[2]
                  + P[:, 1, 2, None] * d[1] * d[2]))
    val = a[:, None] * np.exp(-0.5 * q)
    cells = c0[:, None, :] + offs
    ok = np.all((cells >= 0) & (cells < G), -1) & (val > 0)
    flat = (cells[..., 0] * G + cells[..., 1]) * G + cells[..., 2]
    grid += np.bincount(flat[ok], val[ok], minlength=G**3)
  density = grid.reshape(G, G, G)
  c0 = np.floor((means - origin) / dx).astype(np.int64)
  okc = np.all((c0 >= 0) & (c0 < G), -1) & (alpha > 0)
  has_centre = np.zeros(G**3, bool)
  has_centre[((c0[okc, 0] * G + c0[okc, 1]) * G + c0[okc, 2])] = True
  occupied = (density >= config.density_threshold) | has_centre.reshape(
    G, G, G)
  return density, occupied


def interior_cells_host(occupied, min_ray_hits: int = 6):
  """NumPy twin of :func:`interior_cells`."""
  occ = np.asarray(occupied, bool)
  hits = np.zeros(occ.shape, np.int8)
  o8 = occ.astype(np.int8)
  for ax in range(3):
    bwd = np.maximum.accumulate(o8, axis=ax)
    fwd = np.flip(np.maximum.accumulate(np.flip(o8, ax), axis=ax), ax)
    hits += fwd + bwd
  return (~occ) & (hits >= min_ray_hits)


def _numpy_rng(key):
  """A NumPy generator seeded from a JAX PRNG key (raw or typed)."""
  if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
    key = jax.random.key_data(key)
  return np.random.default_rng(np.asarray(key, np.uint32).ravel().tolist())


def fill_gaussians_host(key, means, log_scales, quats, opacities,
                        max_particles: int,
                        config: FillConfig = FillConfig()) -> FillResult:
  """NumPy twin of :func:`fill_gaussians` (no compilation; host side).

  Same grid, occupancy and interior test (float64 instead of float32, so a
  cell on the density threshold may differ). The jitter comes from a NumPy
  generator seeded by ``key``, so the points differ from the jitted
  function's but are deterministic for the key. Unlike
  :func:`fill_gaussians` the result is not padded: ``points`` has
  ``min(count, max_particles)`` rows, all valid.

  Returns:
    A :class:`FillResult` of NumPy arrays.
  """
  if key is None and config.particles_per_cell != 1:
    raise ValueError('fill_gaussians_host: key=None places one point at each '
                     'cell centre; pass a PRNG key for particles_per_cell > 1')
  means = np.asarray(means, np.float64)
  G = config.grid_res
  lo, hi = means.min(0), means.max(0)
  ext = max(float(np.max(hi - lo)), 1e-9)
  dx = ext / (G - 2 * config.margin_cells)
  origin = 0.5 * (lo + hi) - 0.5 * G * dx
  _, occ = occupancy_grid_host(means, log_scales, quats, opacities, origin,
                               dx, config)
  inside = interior_cells_host(occ, config.min_ray_hits)
  m = config.particles_per_cell
  idx = np.flatnonzero(inside.ravel())
  count = len(idx) * m
  ncell = min(len(idx), -(-max_particles // m))
  idx = idx[:ncell]
  ijk = np.stack([idx // (G * G), (idx // G) % G, idx % G], -1)
  base = origin + ijk * dx
  if key is None:
    u = np.full((ncell, 1, 3), 0.5)
  else:
    u = _numpy_rng(key).uniform(size=(ncell, m, 3))
  pts = (base[:, None, :] + u * dx).reshape(-1, 3)[:max_particles]
  return FillResult(points=pts.astype(np.float32),
                    valid=np.ones(len(pts), bool), count=np.int32(count),
                    overflow=np.bool_(count > max_particles), occupied=occ,
                    inside=inside, origin=origin, dx=np.float64(dx))


def fill_objects(
  key: Array | None,
  gaussians,
  object_ids,
  objects=None,
  max_particles_per_object: int = 200_000,
  config: FillConfig = FillConfig(),
  return_info: bool = False,
  backend: str = 'host',
):
  """Fills every object of a scene (host loop over objects).

  Args:
    key: PRNG key (split per object) or None for cell centres.
    gaussians: :class:`~physsplat_jax.types.Gaussians`.
    object_ids: (K,) int object id per Gaussian (-1 = background, skipped).
    objects: optional iterable of object ids to fill (default: all >= 0).
    max_particles_per_object: capacity per object.
    config: :class:`FillConfig`.
    return_info: also return a dict object id -> {'dx', 'num_inside',
      'num_occupied'} (cell size and cell counts, e.g. for volumes).
    backend: 'host' (default: :func:`fill_gaussians_host`, NumPy, no
      compilation, ~0.1 s per 10^5 Gaussians) or 'jax'
      (:func:`fill_gaussians` jitted; compiles once per object size).

  Returns:
    (points (P, 3) float32, object (P,) int32), deterministic for ``key``
    (plus the info dict if ``return_info``).

  Raises:
    ValueError: non-finite means, or more interior points than the capacity.
  """
  oid = np.asarray(object_ids)
  means = np.asarray(gaussians.means)
  if oid.shape != (means.shape[0],):
    raise ValueError(f'object_ids has shape {oid.shape}; expected '
                     f'({means.shape[0]},)')
  if objects is None:
    objects = sorted(int(o) for o in np.unique(oid) if o >= 0)
  if backend == 'host':
    fill = fill_gaussians_host
  elif backend == 'jax':
    fill = jax.jit(fill_gaussians,
                   static_argnames=('max_particles', 'config'))
  else:
    raise ValueError(f"fill_objects: backend={backend!r}; use 'host' or "
                     "'jax'")
  pts_all, ids_all, info = [], [], {}
  for i, o in enumerate(objects):
    m = oid == o
    if not m.any():
      continue
    if not np.all(np.isfinite(means[m])):
      raise ValueError(f'fill_objects: object {o} has '
                       f'{int((~np.isfinite(means[m])).any(1).sum())} '
                       'Gaussians with non-finite means; drop them first')
    k = None if key is None else jax.random.fold_in(key, i)
    g = gaussians.subset(m)
    if backend == 'host':  # NumPy in, so nothing is traced or compiled
      args = (means[m], np.asarray(g.log_scales), np.asarray(g.quats),
              1.0 / (1.0 + np.exp(-np.asarray(g.opacity_logits,
                                              np.float64))))
    else:
      args = (g.means, g.log_scales, g.quats, g.opacities)
    res = fill(k, *args, max_particles=max_particles_per_object,
               config=config)
    if bool(res.overflow):
      raise ValueError(
        f'fill_objects: object {o} has {int(res.count)} interior points > '
        f'max_particles_per_object={max_particles_per_object}; raise it or '
        'lower FillConfig.grid_res / particles_per_cell')
    info[int(o)] = {'dx': float(res.dx),
                     'num_inside': int(np.sum(res.inside)),
                     'num_occupied': int(np.sum(res.occupied))}
    v = np.asarray(res.valid)
    pts_all.append(np.asarray(res.points)[v].astype(np.float32))
    ids_all.append(np.full(int(v.sum()), o, np.int32))
  if not pts_all:
    out = np.zeros((0, 3), np.float32), np.zeros((0,), np.int32)
  else:
    out = np.concatenate(pts_all), np.concatenate(ids_all)
  return (*out, info) if return_info else out


def fill_mesh(mesh, spacing: float, max_points: int = 2_000_000,
              jitter_key=None) -> np.ndarray:
  """Lattice points inside a closed trimesh (host side).

  Args:
    mesh: a watertight ``trimesh.Trimesh``.
    spacing: lattice spacing [scene units].
    max_points: bound on the lattice size before the containment test.
    jitter_key: optional PRNG key to jitter points within their cell.

  Returns:
    (P, 3) float32 interior points.
  """
  if not getattr(mesh, 'is_watertight', False):
    raise ValueError('fill_mesh: the mesh is not watertight, so "inside" is '
                     'undefined; repair it (trimesh.repair.fill_holes) or '
                     'fill from the Gaussians with fill_gaussians')
  if not spacing > 0:
    raise ValueError(f'fill_mesh: spacing={spacing} must be > 0')
  lo, hi = mesh.bounds
  n = np.floor((hi - lo) / spacing).astype(int) + 1
  if np.prod(n) > max_points:
    raise ValueError(f'fill_mesh: lattice of {n.tolist()} points exceeds '
                     f'max_points={max_points}; raise spacing')
  axes = [lo[d] + (np.arange(n[d]) + 0.5) * spacing for d in range(3)]
  grid = np.stack(np.meshgrid(*axes, indexing='ij'), -1).reshape(-1, 3)
  if jitter_key is not None:
    u = np.asarray(jax.random.uniform(jitter_key, grid.shape)) - 0.5
    grid = grid + u * spacing
  return grid[mesh.contains(grid)].astype(np.float32)
