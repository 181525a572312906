"""PGAS: physics-guided adaptive sampling of driving particles (PhysSplat).

The paper's radius rule (Sec. 3.4) is ``r_hat = min(r, k sqrt(E / K_hat) r)``
with ``K = l3 / (l1 + l2 + l3)``, ``K_hat = clip(K, V_min=1, V_max=10)`` and
``k = sqrt(10)``. Taken literally it never changes anything (``K <= 1/3`` so
``K_hat == 1``, and ``sqrt(E)`` in pascals is ~1e3), so we fix units:

- ``E_hat = clip(E / E_ref, e_hat_min, 1)`` with a reference modulus
  ``E_ref`` (default 1e7 Pa, the stiff end of jelly/rubber); pascals in,
  dimensionless out.
- ``K_hat`` maps curvature onto ``[V_min, V_max] = [1, 10]``
  (:func:`~physsplat_jax.sampling.curvature.normalize_curvature`):

  * object level: the mean per-Gaussian ``K_g`` of the object (paper's
    formula) over its theoretical range ``[0, 1/3]`` -> ``K_hat_obj``;
  * local level: PCA surface variation of the ``k`` nearest Gaussian
    centres, over its observed range in the scene (5th-95th percentile of
    surface points, at least 1e-4 wide so that a flat scene's noise stays
    flat) -> ``K_hat_loc``.

  Surface points (Gaussians) use ``sqrt(K_hat_obj * K_hat_loc)`` (the object
  sets the level, local shape modulates it); interior fill particles, which
  have no surface around them, use ``K_hat_obj``.
- ``r_hat = clip(k sqrt(E_hat / K_hat) r, min_radius_frac r, r)``: the floor
  bounds the particle count (a 5x smaller radius is 125x more particles).

So softer material and higher curvature give a smaller radius, i.e. more
driving particles, which is what the paper describes. The sample itself is a
variable-radius Poisson disk over the candidate points
(:func:`~physsplat_jax.sampling.poisson.poisson_disk`).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax.sampling import curvature as curv
from physsplat_jax.sampling import poisson
from physsplat_jax.sampling.poisson import SamplingError
from physsplat_jax.types import device_array


# Smallest range of local surface variation mapped onto [v_min, v_max]:
# above float noise on a plane (1e-12), below a ball 10 neighbour spacings
# across (~2e-3).
_LOCAL_SPAN = 1e-4


@dataclasses.dataclass(frozen=True)
class PGASConfig:
  """Static PGAS settings.

  Attributes:
    base_radius: r, the largest Poisson radius [scene units].
    k: the paper's k (sqrt(10)).
    v_min, v_max: curvature range [V_min, V_max].
    e_ref: reference Young's modulus [Pa] for ``E_hat = E / e_ref``.
    e_hat_min: floor on ``E_hat``.
    min_radius_frac: floor of ``r_hat / r``.
    curvature_neighbors: k nearest centres for the local curvature.
    local_percentiles: observed range used to normalise the local curvature.
  """

  base_radius: float
  k: float = math.sqrt(10.0)
  v_min: float = 1.0
  v_max: float = 10.0
  e_ref: float = 1e7
  e_hat_min: float = 1e-6
  min_radius_frac: float = 0.2
  curvature_neighbors: int = 16
  local_percentiles: tuple[float, float] = (5.0, 95.0)

  def __post_init__(self):
    if not self.base_radius > 0:
      raise SamplingError(
        f'PGASConfig.base_radius={self.base_radius}: must be > 0')
    if not 1.0 <= self.v_min < self.v_max:
      raise SamplingError(f'PGASConfig: need 1 <= v_min < v_max, got '
                          f'{self.v_min}, {self.v_max}')
    if not self.e_ref > 0:
      raise SamplingError(f'PGASConfig.e_ref={self.e_ref}: must be > 0 [Pa]')
    if not 0 < self.min_radius_frac <= 1:
      raise SamplingError(f'PGASConfig.min_radius_frac={self.min_radius_frac}: '
                          'must be in (0, 1]')


def adaptive_radius(E, K_hat, config: PGASConfig):
  """The PGAS radius ``clip(k sqrt(E_hat / K_hat) r, r_min, r)``.

  Args:
    E: (N,) Young's modulus [Pa].
    K_hat: (N,) normalised curvature in [v_min, v_max].
    config: :class:`PGASConfig`.

  Returns:
    (N,) radii [scene units]. Works on NumPy or JAX arrays.
  """
  xp = jnp if isinstance(E, jax.Array) or isinstance(K_hat, jax.Array) else np
  e_hat = xp.clip(E / config.e_ref, config.e_hat_min, 1.0)
  r = config.base_radius
  rr = config.k * xp.sqrt(e_hat / K_hat) * r
  return xp.clip(rr, config.min_radius_frac * r, r)


def pgas_curvature(
  points, is_surface, object_ids, covariances, config: PGASConfig,
  surface_points=None,
):
  """Normalised curvature ``K_hat`` per candidate point (host side).

  Args:
    points: (N, 3) candidates (Gaussian centres and fill particles).
    is_surface: (N,) bool, True for Gaussian centres.
    object_ids: (N,) int object index per point.
    covariances: (N, 3, 3) covariances (only rows of surface points are
      read; fill rows may be anything).
    config: :class:`PGASConfig`.
    surface_points: optional (S, 3) surface to measure local curvature on
      (default: the surface candidates).

  Returns:
    (K_hat (N,), info dict with 'k_obj' per object id and 'k_loc' (N,)).
  """
  pts = np.asarray(points, np.float64)
  surf = np.asarray(is_surface, bool)
  oid = np.asarray(object_ids)
  n = len(pts)
  if surf.shape != (n,) or oid.shape != (n,):
    raise SamplingError(f'is_surface {surf.shape} and object_ids {oid.shape} '
                        f'must both have shape ({n},)')
  if not surf.any():
    raise SamplingError('pgas_curvature: no surface points (is_surface is all '
                        'False); pass the Gaussian centres as candidates')
  kg = np.zeros(n)
  kg[surf] = curv.gaussian_curvature(np.asarray(covariances)[surf])
  sp = pts[surf] if surface_points is None else np.asarray(surface_points)
  k_loc = np.zeros(n)
  k_loc[surf] = curv.local_curvature(sp, config.curvature_neighbors,
                                     query=pts[surf])
  lo, hi = np.percentile(k_loc[surf], config.local_percentiles)
  # A span of at least _LOCAL_SPAN (surface variation is in [0, 1/3]): on a
  # flat scene the observed range is only noise, which the affine map
  # stretched over [v_min, v_max] (a plate with 1e-7 noise got 1.07-3.37).
  hi = max(hi, lo + _LOCAL_SPAN)
  kh_loc = curv.normalize_curvature(k_loc, lo, hi, config.v_min, config.v_max)
  k_hat = np.empty(n)
  k_obj = {}
  for o in np.unique(oid):
    m = oid == o
    ms = m & surf
    mean_kg = kg[ms].mean() if ms.any() else kg[surf].mean()
    kh_obj = float(curv.normalize_curvature(mean_kg, 0.0, 1.0 / 3.0,
                                            config.v_min, config.v_max))
    k_obj[int(o)] = kh_obj
    k_hat[ms] = np.sqrt(kh_obj * kh_loc[ms])
    k_hat[m & ~surf] = kh_obj
  return k_hat, {'k_obj': k_obj, 'k_loc': k_loc}


def pgas_sample(
  key, points, radius, max_samples: int, valid=None, **capacities
) -> poisson.PoissonResult:
  """Driving particles: variable-radius Poisson disk with PGAS radii.

  Args:
    key: PRNG key.
    points: (N, 3) candidates.
    radius: (N,) radii from :func:`adaptive_radius`.
    max_samples: static capacity.
    valid: optional (N,) bool.
    **capacities: ``max_per_cell``, ``max_neighbors``, ``max_rounds``.

  Returns:
    A :class:`~physsplat_jax.sampling.poisson.PoissonResult`.
  """
  return poisson.poisson_disk(key, jnp.asarray(points), jnp.asarray(radius),
                              max_samples, valid=valid, **capacities)


def capped_family(radius, cap: float):
  """PGAS radii for a budget that honour the cap ``r`` first.

  ``r(t) = min(cap * max(1, t / T0), t * radius)`` with
  ``T0 = cap / min(radius)``: for ``t <= 1`` every radius shrinks (more
  drivers everywhere, PGAS shape kept); for ``1 < t <= T0`` only the
  refined radii grow towards the cap (soft / curved regions lose their
  extra drivers first; regions already at the cap, e.g. stiff ones, keep
  the base resolution); beyond ``T0`` the uniform radius grows. This is the
  paper's ``r_hat = min(r, .)`` with ``r`` an upper bound tied to the
  grid, so a tight budget cannot starve stiff objects below the base
  resolution while soft ones hold most of the drivers.

  Args:
    radius: (N,) PGAS radii (<= cap).
    cap: the base radius ``r``.

  Returns:
    ``t -> (N,) radii``, monotone (non-decreasing) in ``t``.
  """
  radius = np.asarray(radius, np.float64)
  t0 = cap / max(float(radius.min()), 1e-30)

  def radius_fn(t):
    return np.minimum(cap * max(1.0, t / t0), t * radius)

  return radius_fn


def scale_for_budget(
  sample_fn, radius, budget: int, lo: float = 0.05, hi: float = 20.0,
  iters: int = 18, rtol: float = 0.0, x0: float = 1.0, dim: float = 2.5,
) -> tuple[float, poisson.PoissonResult]:
  """Host search on a radius multiplier to keep at most ``budget`` samples.

  The count falls about as ``m^-d`` with the multiplier ``m`` (``d`` = 2 on
  surfaces, 3 in volumes), so a safeguarded secant on ``log count`` vs
  ``log m`` (starting slope ``-dim``, then the slope through the last two
  evaluations; a geometric bisection step whenever the secant leaves the
  bracket) lands in ``[(1 - rtol) budget, budget]`` in 3-5 evaluations of
  ``sample_fn`` from a reasonable ``x0``, instead of ~12 bisection steps.

  Args:
    sample_fn: ``radius (N,) -> PoissonResult`` (capacity >= budget).
    radius: (N,) radius field whose shape is kept (``m * radius``), or a
      callable ``m -> (N,) radii`` for another monotone family (e.g.
      :func:`capped_family`).
    budget: the most samples to keep.
    lo, hi: bracket of the multiplier.
    iters: most evaluations of ``sample_fn``.
    rtol: stop as soon as ``(1 - rtol) budget <= count <= budget``
      (0: only an exact hit stops early).
    x0: first multiplier tried (clipped into the bracket).
    dim: starting guess of ``d``.

  Returns:
    (multiplier, result with count <= budget, the largest count found).
  """
  radius_fn = radius if callable(radius) else (
    lambda m, r=np.asarray(radius): m * r)
  best = None
  goal = budget * (1.0 - 0.5 * rtol) if rtol > 0 else budget - 0.5
  lo_, hi_ = lo, hi
  m = float(np.clip(x0, lo, hi))
  prev = None  # (log m, log count) of the previous evaluation
  for _ in range(iters):
    res = sample_fn(device_array(radius_fn(m), jnp.float32))
    cnt = int(res.count)
    if int(res.overflow_code) & 6:
      # Radius too large for the jittable path's capacities: shrink it.
      hi = m
      cnt = None
    elif cnt > budget:
      lo = m
    else:
      if best is None or cnt > int(best[1].count):
        best = (m, res)
      hi = m
      if cnt >= (1.0 - rtol) * budget:
        break
    nxt = None
    if cnt:
      cur = (math.log(m), math.log(cnt))
      slope = -dim
      stalled = False
      if prev is not None and abs(cur[0] - prev[0]) > 1e-12:
        s = (cur[1] - prev[1]) / (cur[0] - prev[0])
        # A flat stretch (e.g. capped_family near its cap) gives a shallow
        # slope and long steps; a step that barely moved the count bisects.
        slope = float(np.clip(s, -6.0, -0.05)) if s < 0 else slope
        stalled = abs(cur[1] - prev[1]) < 0.005
      nxt = math.exp(cur[0] + (math.log(goal) - cur[1]) / slope)
      if stalled:
        nxt = None
      prev = cur
    # Bisect (geometrically) when the secant leaves the bracket.
    if nxt is None or not lo * 1.0001 < nxt < hi * 0.9999:
      nxt = math.sqrt(lo * hi)
    if hi / lo < 1.0 + 1e-6:
      break
    m = nxt
  if best is None:
    raise SamplingError(
      f'scale_for_budget: no radius multiplier in [{lo_:.3g}, {hi_:.3g}] '
      f'keeps <= {budget} samples within the capacities; raise hi, or the '
      'max_per_cell / max_neighbors of sample_fn')
  return best
