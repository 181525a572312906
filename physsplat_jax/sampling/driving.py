"""End-to-end driving-particle selection for a scene (host side).

``candidates = Gaussian centres (surface) + interior fill particles``; the
driving particles are then chosen by one of

- ``'pgas'``: variable-radius Poisson disk with the PGAS radius
  (:mod:`physsplat_jax.sampling.pgas`),
- ``'uniform'``: Poisson disk with one radius everywhere,
- ``'kmeans'``: K-means centres (PhysDreamer),
- ``'pgas-cvt'``: the PGAS density allocated per object and placed by
  weighted Lloyd iterations (:mod:`physsplat_jax.sampling.centroidal`),

optionally scaled to a fixed budget (a secant search on the radius scale,
3-5 Poisson-disk evaluations; for PGAS the base radius stays an upper bound
first, :func:`~physsplat_jax.sampling.pgas.capped_family`). The Poisson disk
runs on the host by default
(:func:`~physsplat_jax.sampling.poisson.poisson_disk_host`, the same kept
set as the jittable :func:`~physsplat_jax.sampling.poisson.poisson_disk`).
Each driver gets the volume of the candidates closest to it (a discrete
Voronoi volume), so ``mass = rho * volume`` sums to the object's mass.
Sampling is discrete and stays outside the gradient path.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from absl import logging
import scipy

from physsplat_jax import struct
from physsplat_jax.sampling import centroidal
from physsplat_jax.sampling import clustering
from physsplat_jax.sampling import filling
from physsplat_jax.sampling import pgas
from physsplat_jax.sampling import poisson
from physsplat_jax.sampling.poisson import SamplingError
from physsplat_jax.types import device_array


class Candidates(struct.PyTreeNode):
  """Candidate points of a scene's simulated objects (NumPy arrays).

  Attributes:
    x: (M, 3) positions: Gaussian centres, then fill particles.
    is_surface: (M,) bool, True for Gaussian centres.
    object_ids: (M,) int32 object per point.
    covariances: (M, 3, 3) Gaussian covariances (zero for fill points).
    volume: (M,) volume per candidate [scene units^3]. With fill: a fill
      point owns ``dx^3 / particles_per_cell`` of its interior cell and the
      object's Gaussian centres share the rest of the volume enclosed by the
      surface through them (``fill_objects`` info 'volume'; at least the
      open-sheet volume 'sheet_volume'), so the density is uniform.
      Without fill: the convex hull split evenly over the candidates.
    gaussian_index: (M,) int32 source Gaussian (-1 for fill points).
  """

  x: np.ndarray
  is_surface: np.ndarray
  object_ids: np.ndarray
  covariances: np.ndarray
  volume: np.ndarray
  gaussian_index: np.ndarray


class Drivers(struct.PyTreeNode):
  """Driving particles.

  Attributes:
    x: (N, 3) rest positions.
    object_ids: (N,) int32.
    volume: (N,) Voronoi volume over the candidates.
    candidate_index: (N,) int32 index into the candidates (-1 for K-means
      and for 'pgas-cvt' drivers moved by the Lloyd steps).
    radius: (N,) the Poisson radius used (0 for K-means; for 'pgas-cvt'
      the target spacing ``r n^(-1/3)`` at the driver).
  """

  x: np.ndarray
  object_ids: np.ndarray
  volume: np.ndarray
  candidate_index: np.ndarray
  radius: np.ndarray


# Below this fraction of its convex hull, the enclosed volume of a filled
# object with no flat Gaussians is taken to have failed (make_candidates).
# Real thin objects stay above it (the ficus stem at fill grid 64: 1.9 %).
_MIN_ENCLOSED_FRACTION = 0.01


def _hull_volume(points) -> float:
  """Convex-hull volume, 0 for degenerate (flat, collinear, < 4) sets."""
  if len(points) < 4:
    return 0.0
  try:
    return float(scipy.spatial.ConvexHull(points).volume)
  except scipy.spatial.QhullError:
    return 0.0


def make_candidates(
  key, gaussians, object_ids, fill: bool = True,
  fill_config: filling.FillConfig = filling.FillConfig(),
  max_fill_per_object: int = 200_000,
) -> Candidates:
  """Gaussian centres of objects ``>= 0`` plus their interior fill."""
  oid = np.asarray(object_ids).astype(np.int32)
  sel = np.nonzero(oid >= 0)[0]
  if len(sel) == 0:
    raise SamplingError('make_candidates: no Gaussian has object_id >= 0')
  g = gaussians.subset(sel)
  # R S^2 R^T in NumPy (op-by-op JAX would compile per object size).
  R = filling.quat_to_rotmat_host(g.quats)
  s2 = np.exp(2.0 * np.asarray(g.log_scales, np.float64))
  covs = (R * s2[:, None, :]) @ np.swapaxes(R, -1, -2)
  xs = [np.asarray(g.means, np.float64)]
  surf = [np.ones(len(sel), bool)]
  ids = [oid[sel]]
  cov_l = [covs]
  gidx = [sel.astype(np.int32)]
  info = {}
  if fill:
    fp, fo, info = filling.fill_objects(
      key, g, oid[sel], max_particles_per_object=max_fill_per_object,
      config=fill_config, return_info=True)
    xs.append(fp.astype(np.float64))
    surf.append(np.zeros(len(fp), bool))
    ids.append(fo)
    cov_l.append(np.zeros((len(fp), 3, 3)))
    gidx.append(np.full(len(fp), -1, np.int32))
  x = np.concatenate(xs)
  ob = np.concatenate(ids)
  is_surf = np.concatenate(surf)
  vol = np.zeros(len(x))
  log_scales = np.asarray(g.log_scales, np.float64)
  for o in np.unique(ob):
    m = ob == o
    if int(o) in info:
      # Each fill point owns its share of an interior cell; the Gaussian
      # centres share the rest of the volume enclosed by the surface through
      # them (at least the sheet volume of an open shell), so the density
      # is uniform rather than piled onto the densely splatted shell.
      f = info[int(o)]
      v_fill = f['num_inside'] * f['dx'] ** 3
      v_shell = max(f['volume'] - v_fill, f['sheet_volume'])
      # The hull (a Qhull run over every candidate) only where it decides.
      v_hull = _hull_volume(x[m]) if f['sheet_volume'] <= 0.0 else 0.0
      if v_fill + v_shell < _MIN_ENCLOSED_FRACTION * v_hull:
        # An object only a few fill cells thick and splatted through (a
        # thin solid bar of round Gaussians, no flat ones to read as a
        # sheet): its centres lie in the middle of the occupancy band, so
        # the surface level set encloses about nothing. The convex hull, as
        # without fill, is the better estimate.
        logging.info('make_candidates: object %d encloses %.3g of its '
                     'convex hull %.3g; using the hull volume', int(o),
                     (v_fill + v_shell) / v_hull, v_hull)
        v_shell = v_hull - v_fill
      vol[m & ~is_surf] = f['dx'] ** 3 / fill_config.particles_per_cell
      ms = m & is_surf
      vol[ms] = v_shell / max(int(ms.sum()), 1)
    else:
      v = _hull_volume(x[m])
      if v <= 0.0:  # coplanar centres: read the flat Gaussians as a sheet
        # (no fill points here, so x[m] are this object's Gaussians)
        v = filling.sheet_volume_host(x[m], log_scales[oid[sel] == o])
      vol[m] = v / m.sum()
    if not np.sum(vol[m]) > 0.0:
      raise SamplingError(
        f'make_candidates: object {int(o)} has zero volume ({int(m.sum())} '
        'candidates, coplanar or collinear with round Gaussians); give it '
        'thickness (scales), turn fill on, or leave it out of the '
        'simulation (object_id -1)')
  return Candidates(x=x, is_surface=is_surf, object_ids=ob,
                    covariances=np.concatenate(cov_l), volume=vol,
                    gaussian_index=np.concatenate(gidx))


def _voronoi_volume(cand: Candidates, drivers_x, driver_obj,
                    return_centroid: bool = False):
  """Volume (and volume centroid) of the candidates nearest to each driver.

  Candidates go to the nearest driver of their own object (a discrete
  Voronoi cell); drivers of an object that got no candidate keep volume 0.
  """
  vol = np.zeros(len(drivers_x))
  cen = np.zeros((len(drivers_x), 3))
  for o in np.unique(cand.object_ids):
    dm = np.nonzero(driver_obj == o)[0]
    cm = np.nonzero(cand.object_ids == o)[0]
    if len(dm) == 0:
      raise SamplingError(f'object {o} got no driving particle; raise the '
                          'budget or lower the radius')
    _, nn = scipy.spatial.cKDTree(drivers_x[dm]).query(cand.x[cm], workers=-1)
    w = cand.volume[cm]
    vol[dm] = np.bincount(nn, w, minlength=len(dm))
    if return_centroid:
      for a in range(3):
        cen[dm, a] = np.bincount(nn, w * cand.x[cm, a], minlength=len(dm))
  if return_centroid:
    ok = vol > 0
    cen[ok] /= vol[ok, None]
    cen[~ok] = drivers_x[~ok]
    return vol, cen
  return vol


def _lloyd(cand: Candidates, x, ob, steps: int):
  """``steps`` Lloyd steps: each driver moves to its cell's mass centroid."""
  for _ in range(steps):
    _, x = _voronoi_volume(cand, x, ob, return_centroid=True)
  return x


def _first_multiplier(x, radius, budget: int, num: int = 2000):
  """Radius multiplier expected to keep about ``budget`` points, and ``d``.

  A greedy Poisson disk keeps about one point per ``n(r) / kappa``
  candidates, ``n(r)`` the candidates within ``r`` of a point and
  ``kappa`` ~ 2.2 on a surface (random sequential adsorption of discs) to
  ~ 3.0 in a volume; the count then falls as ``m^-d`` with
  ``d = log2 n(r) / n(r / 2)`` (2 on surfaces, 3 in volumes). Both from
  ``num`` random candidates; only a starting point for the search.
  """
  n = len(x)
  rng = np.random.default_rng(0)
  sub = rng.choice(n, size=min(num, n), replace=False)
  tree = scipy.spatial.cKDTree(x, balanced_tree=False)
  n1 = tree.query_ball_point(x[sub], radius[sub], return_length=True)
  n2 = tree.query_ball_point(x[sub], 0.5 * radius[sub], return_length=True)
  d = float(np.clip(np.log2(n1.mean() / max(n2.mean(), 1.0)), 1.5, 3.0))
  est = n / len(sub) * np.sum(np.minimum(1.0, 2.6 / np.maximum(n1, 1)))
  return float((est / budget) ** (1.0 / d)), d


def select_drivers(
  key, cand: Candidates, method: str = 'pgas', E=None,
  config: pgas.PGASConfig | None = None, budget: int | None = None,
  max_per_cell: int = poisson.MAX_PER_CELL, max_neighbors: int = 256,
  kmeans_iters: int = 20, bisect_iters: int = 12,
  backend: str = 'host', budget_rtol: float = 0.02,
  pgas_cap_first: bool = True, lloyd_steps: int = 0,
  cvt: centroidal.CVTConfig | None = None,
) -> Drivers:
  """Chooses driving particles among the candidates.

  Args:
    key: PRNG key.
    cand: from :func:`make_candidates`.
    method: 'pgas-cvt', 'pgas', 'uniform' or 'kmeans'.
    E: Young's modulus [Pa] per candidate (M,) or dict object id -> E;
      needed for 'pgas' and 'pgas-cvt'.
    config: :class:`~physsplat_jax.sampling.pgas.PGASConfig` (its
      ``base_radius`` is the uniform radius for 'uniform').
    budget: target driver count; required for 'kmeans' and 'pgas-cvt'
      (exactly ``budget`` drivers, unless the per-object floors exceed
      it: 4 per object for 'kmeans', ``cvt.min_per_object`` (8) for
      'pgas-cvt', each capped by the object's candidates), optional for
      the Poisson disks (the
      radius is then scaled to keep at most ``budget``, and at least
      ``(1 - budget_rtol) budget`` when the search gets there). A budget
      of at least the candidate count keeps every candidate, with its own
      volume, whatever the method (there is nothing to choose; logged).
    max_per_cell, max_neighbors: capacities of the jittable Poisson disk
      (``backend='jax'`` only).
    kmeans_iters: Lloyd iterations.
    bisect_iters: most Poisson-disk evaluations of the budget search.
    backend: Poisson disk implementation: 'host' (default;
      :func:`~physsplat_jax.sampling.poisson.poisson_disk_host`, NumPy/SciPy,
      ~0.1-0.3 s per 100k candidates, no capacities) or 'jax'
      (:func:`~physsplat_jax.sampling.poisson.poisson_disk`, jitted, fixed
      capacities). Both keep the same set for the same key and radii.
    budget_rtol: relative tolerance of the budget search.
    pgas_cap_first: for 'pgas' with a budget, search along
      :func:`~physsplat_jax.sampling.pgas.capped_family` (the base radius
      stays an upper bound as long as the budget allows it: refined
      regions give up drivers first, so stiff objects are not starved);
      False scales every PGAS radius by one factor.
    lloyd_steps: for the Poisson-disk methods, move each driver this many
      times to the volume centroid of the candidates nearest to it (Lloyd
      steps towards a centroidal Voronoi sampling, as K-means ends at): the
      driver then sits at the centre of the mass it carries. The drivers
      stop being candidate points, and the Poisson-disk separation holds
      only approximately.
    cvt: :class:`~physsplat_jax.sampling.centroidal.CVTConfig` for
      'pgas-cvt' (default settings if None). 'pgas-cvt' needs ``budget``
      and returns exactly ``min(budget, M)`` drivers.

  Returns:
    :class:`Drivers`.
  """
  m = len(cand.x)
  if method not in ('pgas-cvt', 'pgas', 'uniform', 'kmeans'):
    raise centroidal.SamplingError(
      f"select_drivers: method={method!r}; use 'pgas-cvt', 'pgas', "
      "'uniform' or 'kmeans'")
  if budget is not None and budget >= m:
    # Nothing to choose: every candidate drives, with its own volume (the
    # pipeline logs this at INFO with the field to change).
    logging.debug('select_drivers: budget %d >= %d candidates; every '
                 'candidate is a driver (no sampling)', budget, m)
    return Drivers(x=np.array(cand.x, np.float64),
                   object_ids=np.asarray(cand.object_ids, np.int32),
                   volume=np.array(cand.volume, np.float64),
                   candidate_index=np.arange(m, dtype=np.int32),
                   radius=np.zeros(m))
  x32 = device_array(cand.x, jnp.float32)
  if method == 'kmeans':
    if budget is None:
      raise SamplingError("select_drivers: method='kmeans' needs budget=")
    xs, obs = [], []
    objs, sizes = np.unique(cand.object_ids, return_counts=True)
    # Budget split by candidate count with largest-remainder rounding, so
    # the counts sum to the budget (rounding each share gave up to half a
    # driver more or less per object), at least 4 per object and at most
    # its candidates (more centres than points are duplicates of volume 0).
    counts = centroidal.allocate(budget, sizes, np.full(len(sizes), 4),
                                 sizes, min_count=4)
    for i, o in enumerate(objs):
      sel = cand.object_ids == o
      nb = int(counts[i])
      res = jax.jit(clustering.kmeans, static_argnums=(2, 3))(
        jax.random.fold_in(key, i), x32[np.nonzero(sel)[0]], nb,
        kmeans_iters)
      xs.append(np.asarray(res.centers, np.float64))
      obs.append(np.full(nb, o, np.int32))
    x = np.concatenate(xs)
    ob = np.concatenate(obs)
    return Drivers(x=x, object_ids=ob, volume=_voronoi_volume(cand, x, ob),
                   candidate_index=np.full(len(x), -1, np.int32),
                   radius=np.zeros(len(x)))
  if config is None:
    raise SamplingError(f"select_drivers: method={method!r} needs config=")
  if backend not in ('host', 'jax'):
    raise SamplingError(f"select_drivers: backend={backend!r}; use 'host' or "
                        "'jax'")
  if method in ('pgas', 'pgas-cvt'):
    if E is None:
      raise SamplingError(f"select_drivers: method={method!r} needs E=")
    if isinstance(E, dict):
      missing = set(np.unique(cand.object_ids).tolist()) - set(E)
      if missing:
        raise SamplingError(f'select_drivers: E has no entry for objects '
                            f'{sorted(missing)}')
      E = np.array([E[int(o)] for o in cand.object_ids], np.float64)
  if method == 'pgas-cvt':
    x, ob, idx, spacing, _ = centroidal.select_cvt(
      key, cand, E, config, budget,
      centroidal.CVTConfig() if cvt is None else cvt)
    return Drivers(x=x, object_ids=ob, volume=_voronoi_volume(cand, x, ob),
                   candidate_index=idx, radius=spacing)
  if method == 'pgas':
    k_hat, _ = pgas.pgas_curvature(cand.x, cand.is_surface, cand.object_ids,
                                   cand.covariances, config)
    radius = pgas.adaptive_radius(np.asarray(E, np.float64), k_hat, config)
  elif method == 'uniform':
    radius = np.full(m, config.base_radius)
  else:
    raise SamplingError(f"select_drivers: method={method!r}; use 'pgas-cvt', "
                        "'pgas', 'uniform' or 'kmeans'")
  cap = m if budget is None else min(m, budget)
  if backend == 'host':
    sample_fn = poisson.make_poisson_host(key, cand.x)

    def fn(r):
      return sample_fn(np.asarray(r), cap, cap if budget else None)
  else:
    fn = jax.jit(lambda r: poisson.poisson_disk(
      key, x32, r, cap, max_per_cell=max_per_cell,
      max_neighbors=max_neighbors))
  if budget is None:
    radius_fn = lambda t: radius  # noqa: E731
    mult, res = 1.0, fn(jnp.asarray(radius, jnp.float32))
    poisson.check_overflow(res, 'select_drivers')
  else:
    x0, dim = _first_multiplier(cand.x, radius, budget)
    if method == 'pgas' and pgas_cap_first:
      radius_fn = pgas.capped_family(radius, config.base_radius)
    else:
      radius_fn = lambda t: t * radius  # noqa: E731
    mult, res = pgas.scale_for_budget(
      fn, radius_fn, budget, iters=bisect_iters, rtol=budget_rtol, x0=x0,
      dim=dim, lo=min(0.05, x0 / 20), hi=max(20.0, x0 * 20))
  v = np.asarray(res.valid)
  idx = np.asarray(res.index)[v]
  ob = cand.object_ids[idx]
  x = _lloyd(cand, cand.x[idx], ob, lloyd_steps)
  return Drivers(x=x, object_ids=ob, volume=_voronoi_volume(cand, x, ob),
                 candidate_index=idx.astype(np.int32),
                 radius=np.asarray(radius_fn(mult))[idx])
