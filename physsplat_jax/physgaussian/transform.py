"""PhysGaussian configs as arrays: materials, rotations, the normalised domain.

``x_n = (R x - c) * s + (1, 1, 1)`` (see
:mod:`physsplat_jax.physgaussian.schema`).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from physsplat_jax.mpm import timestep
from physsplat_jax.physgaussian.schema import ConfigError
from physsplat_jax.physgaussian.schema import MaterialParams
from physsplat_jax.physgaussian.schema import NormTransform
from physsplat_jax.physgaussian.schema import PhysGaussianConfig
from physsplat_jax.segmentation import boxes
from physsplat_jax.types import Array


def material_params(config: PhysGaussianConfig, dtype=jnp.float32
                    ) -> MaterialParams:
  """The config's scalar material values as differentiable arrays.

  Args:
    config: parsed config.
    dtype: float dtype.

  Returns:
    ``MaterialParams`` with () arrays.
  """
  f = lambda v: jnp.asarray(v, dtype)  # noqa: E731
  return MaterialParams(
    E=f(config.E), nu=f(config.nu), density=f(config.density),
    yield_stress=f(config.yield_stress), hardening=f(config.hardening),
    xi=f(config.xi), friction_angle=f(config.friction_angle),
    plastic_viscosity=f(config.plastic_viscosity),
    softening=f(config.softening),
  )


def material_fields(
  config: PhysGaussianConfig, x_norm: Array,
  params: MaterialParams | None = None,
) -> tuple[Array, Array, Array]:
  """Per-particle E, nu, density with ``additional_material_params`` applied.

  A particle takes a box's values when ``|x_n - point|_i < size_i`` on every
  axis; later boxes win, as in PhysGaussian's sequential overwrite. A value
  a box leaves out is the base value there (PhysGaussian's decode_param
  gives a box without ``density`` the base density, which overwrites an
  earlier box's), not an earlier box's.

  Args:
    config: parsed config (static boxes).
    x_norm: (N, 3) particle positions in the normalised domain.
    params: base values (differentiable); defaults to ``material_params``.

  Returns:
    ``(E, nu, density)``, each (N,).
  """
  if params is None:
    params = material_params(config, x_norm.dtype)
  n = x_norm.shape[0]
  E = jnp.broadcast_to(params.E, (n,)).astype(x_norm.dtype)
  nu = jnp.broadcast_to(params.nu, (n,)).astype(x_norm.dtype)
  rho = jnp.broadcast_to(params.density, (n,)).astype(x_norm.dtype)
  base_E, base_nu, base_rho = E, nu, rho
  for box in config.additional_material_params:
    inside = jnp.all(
      jnp.abs(x_norm - jnp.asarray(box.point, x_norm.dtype))
      < jnp.asarray(box.size, x_norm.dtype), axis=-1,
    )
    E = jnp.where(inside, base_E if box.E is None else box.E, E)
    nu = jnp.where(inside, base_nu if box.nu is None else box.nu, nu)
    rho = jnp.where(inside, base_rho if box.density is None else box.density,
                    rho)
  return E, nu, rho


def rotation_matrix(config: PhysGaussianConfig) -> np.ndarray:
  """Preprocessing rotation ``R = R_k ... R_1`` (float64 (3, 3)).

  Each ``R_i`` rotates by ``rotation_degree[i]`` degrees about axis
  ``rotation_axis[i]`` (right-handed), applied in list order.
  """
  R = np.eye(3)
  for deg, axis in zip(config.rotation_degree, config.rotation_axis):
    t = math.radians(deg)
    c, s = math.cos(t), math.sin(t)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    Ri = np.eye(3)
    Ri[i, i], Ri[i, j], Ri[j, i], Ri[j, j] = c, -s, s, c
    R = Ri @ R
  return R


def select_particles(
  config: PhysGaussianConfig, means: np.ndarray,
  opacity: np.ndarray | None = None,
) -> np.ndarray:
  """Row indices that PhysGaussian simulates (host-side, static count).

  Drops Gaussians with ``opacity <= opacity_threshold`` (activated opacity),
  rotates, then keeps those strictly inside ``sim_area`` (PhysGaussian's
  ``>`` and ``<``).

  Args:
    config: parsed config.
    means: (K, 3) Gaussian centres in input coordinates.
    opacity: (K,) activated opacities in [0, 1], or None to keep all.

  Returns:
    (N,) int64 sorted row numbers.

  Raises:
    ConfigError: nothing left to simulate.
  """
  means = np.asarray(means, np.float64)
  keep = np.ones(means.shape[0], bool)
  if opacity is not None:
    keep &= np.asarray(opacity) > config.opacity_threshold
  if config.sim_area is not None:
    keep &= boxes.inside_box(means, config.sim_area,
                             rotation=rotation_matrix(config), strict=True)
  ids = np.nonzero(keep)[0]
  if ids.size == 0:
    raise ConfigError(
      f'{config.source}: no Gaussians left after opacity_threshold='
      f'{config.opacity_threshold} and sim_area={config.sim_area}; lower '
      'the threshold or widen sim_area.'
    )
  return ids


def make_norm_transform(config: PhysGaussianConfig, means: Array,
                        dtype=jnp.float32) -> NormTransform:
  """Builds PhysGaussian's input -> normalised-domain map for ``means``.

  Args:
    config: parsed config (rotation, scale).
    means: (N, 3) selected positions in input coordinates.
    dtype: float dtype of the transform.

  Returns:
    ``NormTransform`` mapping the points' rotated bounding box to a cube of
    side ``config.scale`` centred at (1, 1, 1).

  Raises:
    ConfigError: the points are degenerate (zero extent) or do not fit in
      ``[0, grid_lim]^3`` after normalisation.
  """
  means = np.asarray(means, np.float64)
  R = rotation_matrix(config)
  x = means @ R.T
  lo, hi = x.min(0), x.max(0)
  extent = float(np.max(hi - lo))
  if not extent > 0:
    raise ConfigError(
      f'{config.source}: the selected Gaussians have zero extent; cannot '
      'normalise a single point (select more Gaussians).'
    )
  half = 0.5 * config.scale
  if 1.0 - half < 0 or 1.0 + half > config.grid_lim:
    raise ConfigError(
      f"{config.source}: field 'scale' = {config.scale}: the object cube "
      f'[{1 - half}, {1 + half}] leaves the grid [0, {config.grid_lim}]; use '
      'scale <= 2 and grid_lim >= 1 + scale / 2.'
    )
  return NormTransform(
    rotation=jnp.asarray(R, dtype),
    centre=jnp.asarray(0.5 * (lo + hi), dtype),
    scale=jnp.asarray(config.scale / extent, dtype),
    offset=jnp.ones((3,), dtype),
  )


def normalise_positions(transform: NormTransform, x: Array) -> Array:
  """Input coordinates (..., 3) -> normalised simulation domain (..., 3)."""
  return (x @ transform.rotation.T - transform.centre) * transform.scale + (
    transform.offset
  )


def denormalise_positions(transform: NormTransform, x_norm: Array) -> Array:
  """Normalised domain (..., 3) -> input coordinates (..., 3)."""
  return ((x_norm - transform.offset) / transform.scale + transform.centre) @ (
    transform.rotation
  )


def normalise_velocity(transform: NormTransform, v: Array) -> Array:
  """Input-frame velocities (or forces per unit mass) -> normalised units."""
  return (v @ transform.rotation.T) * transform.scale


def denormalise_velocity(transform: NormTransform, v_norm: Array) -> Array:
  """Normalised-domain velocities -> input-frame velocities."""
  return (v_norm / transform.scale) @ transform.rotation


def cfl_substep(config: PhysGaussianConfig, cfl: float = 0.5) -> float:
  """Largest stable-ish substep from the P-wave speed: ``cfl dx / c_p``.

  ``c_p = sqrt((lam + 2 mu) / rho)`` with ``lam, mu`` from (E, nu); uses the
  stiffest of the base material and the boxes.

  Args:
    config: parsed config.
    cfl: Courant number.

  Returns:
    dt [s].
  """
  cands = [(config.E, config.nu, config.density)]
  for b in config.additional_material_params:
    cands.append((b.E or config.E, config.nu if b.nu is None else b.nu,
                  b.density or config.density))
  E, nu, rho = (np.array(v, np.float64) for v in zip(*cands))
  return timestep.cfl_dt(E, nu, rho, config.dx, cfl=cfl)
