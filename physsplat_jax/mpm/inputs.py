"""Host-side checks of a run's inputs, before the first frame (``mpm.run``).

A non-finite or impossible value in the initial state, the materials or the
forces used to surface one frame later as "the simulation blew up, most
likely because the time step is too large", which sent users after the
wrong fix. These checks read the concrete arrays once (NumPy; on a GPU one
transfer of the state) and name the field, how many particles and which.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax.mpm.errors import MPMInputError
from physsplat_jax.mpm.models import KELVIN_VOIGT_MODELS
from physsplat_jax.mpm.models import MODEL_PARAMS
from physsplat_jax.types import rows_text


def _rows(bad: np.ndarray) -> str:
  return rows_text(np.flatnonzero(bad))


def material_fault(E, nu, rho, stressed=True):
  """The first material value no time step can simulate, as ``(label,
  mask, fix)``, or None: rho <= 0 anywhere, E <= 0 or nu outside
  (-1, 0.5) where ``stressed`` (NaN counts as outside every range)."""
  E, nu, rho = (np.asarray(a, np.float64) for a in (E, nu, rho))
  for label, bad, fix in (
      ('rho <= 0', ~(rho > 0), 'a density in kg/m^3'),
      ('E <= 0', stressed & ~(E > 0), "a Young's modulus in Pa"),
      ('nu outside (-1, 0.5)', stressed & ~((nu > -1) & (nu < 0.5)),
       "a Poisson's ratio below 0.5 (0.5 is incompressible: no time step "
       'is stable)')):
    if np.any(bad):
      return label, bad, fix
  return None


def check_dtypes(state, materials, dtype: str) -> None:
  """Every floating array of ``state`` and ``materials`` is ``dtype``
  (``SimConfig.dtype``); another one crashed inside the solver's loop
  ("scan body ... float32 vs float64"). Static: safe under ``jit``."""
  want = jnp.dtype(dtype)
  for what, tree in (('state', state), ('materials', materials)):
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
      got = getattr(leaf, 'dtype', None)
      # (canonical: NumPy's float64 is float32 to JAX without x64 mode)
      if got is not None and jnp.issubdtype(got, jnp.floating) and (
          jax.dtypes.canonicalize_dtype(got) != want):
        raise MPMInputError(
          f'{what}{jax.tree_util.keystr(path)} is {got} but '
          f"SimConfig.dtype is '{dtype}': build both with the same dtype "
          '(mpm.make_materials(..., dtype=config.dtype) and mpm.init_state '
          'with that config) or change SimConfig.dtype')


def _per_particle(a, n: int) -> np.ndarray:
  a = np.asarray(a)
  return a.reshape(n, -1) if a.ndim and a.shape[0] == n else a.reshape(1, -1)


def check_run_inputs(state, materials, forces, config,
                     caller: str = 'mpm.run') -> None:
  """Raises :class:`MPMInputError` for an initial state, materials or
  forces that no time step can simulate (names field, count, particles;
  each message starts with ``caller``).

  Checked: at least one particle; finite material fields, density > 0,
  and for particles with a stress (every model but 'rigid') E > 0 and
  -1 < nu < 0.5; viscosity >= 0, 0 on sand, and 0 on the other solids
  unless ``config.solid_viscosity`` (else it would be ignored); finite
  positions, velocities, F, C, masses and volumes, masses and volumes
  >= 0 and not all 0 (a massless particle follows the
  grid); finite force values.
  """
  n = int(np.shape(state.x)[0])
  if n == 0:
    raise MPMInputError(f'{caller}: the state has no particles; build it with '
                        'mpm.init_state from at least one position.')
  models = np.asarray(config.models)[np.asarray(materials.model_id)]
  stressed = models != 'rigid'
  for name, value in vars(materials).items():
    if name == 'model_id' or value is None:
      continue
    a = _per_particle(value, n)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
      raise MPMInputError(
        f'{caller}: material field {name} is not finite for {int(bad.sum())} '
        f'of {n} particles ({_rows(bad)}); check the materials (and the '
        'MPDP field or params they came from).')
  fault = material_fault(
    *(np.broadcast_to(np.asarray(a), (n,))
      for a in (materials.E, materials.nu, materials.rho)), stressed)
  if fault:
    label, bad, fix = fault
    raise MPMInputError(
      f'{caller}: {label} for {int(bad.sum())} of {n} particles '
      f'({_rows(bad)}); give each {fix}.')
  _check_viscosity(materials, models, config, n, caller)
  _check_maxwell(materials, models, config, n, caller)
  for name in ('x', 'v', 'F', 'C', 'mass', 'vol0', 'F_N'):
    a = getattr(state, name, None)
    if a is None:
      continue
    bad = ~np.isfinite(_per_particle(a, n)).all(axis=1)
    if bad.any():
      raise MPMInputError(
        f'{caller}: the initial state has non-finite {name} for '
        f'{int(bad.sum())} of {n} particles ({_rows(bad)}); the inputs it '
        'was built from (positions, velocities, materials, params) are not '
        'finite.')
    if name in ('mass', 'vol0'):
      # Zero is allowed, as init_state allows it: a massless particle (a
      # driver a sampler left without candidates) follows the grid.
      a = _per_particle(a, n)
      low = ~(a >= 0).all(axis=1)
      if low.any():
        raise MPMInputError(
          f'{caller}: {name} < 0 for {int(low.sum())} of {n} particles '
          f'({_rows(low)}); give every particle a volume >= 0 and a '
          'density > 0.')
      if not (a > 0).any():
        raise MPMInputError(
          f'{caller}: {name} is 0 for all {n} particles, so nothing would '
          'move; give the particles their volumes (init_state\'s volume, '
          '[m^3]).')
  for value, bc in zip(forces.values, config.boundary_conditions):
    if not np.all(np.isfinite(np.asarray(value))):
      raise MPMInputError(
        f'{caller}: the value of {type(bc).__name__} is not finite: '
        f'{np.asarray(value).tolist()}')


def _check_viscosity(materials, models, config, n: int, caller: str) -> None:
  """A negative viscosity, or a solid's viscosity that the config would
  ignore (``SimConfig.solid_viscosity`` off), named with the fix."""
  eta = np.broadcast_to(np.asarray(materials.viscosity, np.float64), (n,))
  bad = eta < 0
  if bad.any():
    raise MPMInputError(
      f'{caller}: viscosity < 0 for {int(bad.sum())} of {n} particles '
      f'({_rows(bad)}); give a viscosity >= 0 [Pa s].')
  deaf = [m for m, ps in MODEL_PARAMS.items()
          if 'viscosity' not in ps and m != 'rigid']
  bad = np.isin(models, deaf) & (eta > 0)
  if bad.any():
    raise MPMInputError(
      f'{caller}: {int(bad.sum())} of {n} particles of '
      f'{sorted(set(np.asarray(models)[bad].tolist()))} have a viscosity, '
      'which that model does not read (a dashpot on sand would carry shear '
      'and tension outside its cone); give them viscosity 0.')
  solid = np.isin(models, KELVIN_VOIGT_MODELS) & (eta > 0)
  if solid.any() and not config.solid_viscosity:
    kinds = sorted(set(np.asarray(models)[solid].tolist()))
    raise MPMInputError(
      f'{caller}: {int(solid.sum())} of {n} particles of solid models '
      f'{kinds} have a viscosity (up to {float(eta[solid].max()):.3g} Pa s), '
      'which a solid reads as Kelvin-Voigt damping only with '
      'SimConfig(solid_viscosity=True); set it, or give them viscosity 0.')


def _check_maxwell(materials, models, config, n: int, caller: str) -> None:
  """The Maxwell branch's fields: with ``SimConfig.maxwell`` and only then,
  physical, and on solids only."""
  E_N = materials.maxwell_E
  if E_N is None:
    if config.maxwell:
      raise MPMInputError(
        f'{caller}: SimConfig.maxwell is on but the materials have no '
        'Maxwell branch; build them with mpm.make_materials(..., '
        'maxwell_E=..., maxwell_nu=..., maxwell_viscosity=...).')
    return
  E_N, nu_N, eta_N = (np.broadcast_to(np.asarray(a, np.float64), (n,)) for a
                      in (E_N, materials.maxwell_nu,
                          materials.maxwell_viscosity))
  on = E_N != 0
  if on.any() and not config.maxwell:
    raise MPMInputError(
      f'{caller}: {int(on.sum())} of {n} particles have a Maxwell branch '
      '(maxwell_E), computed only with SimConfig(maxwell=True); set it, or '
      'give them maxwell_E 0.')
  for label, bad, fix in (
      ('maxwell_E < 0', E_N < 0, "a Young's modulus >= 0 [Pa]"),
      ('maxwell_nu outside [0, 0.5)', ~((nu_N >= 0) & (nu_N < 0.5)),
       "a Poisson's ratio in [0, 0.5)"),
      ('maxwell_viscosity < 0', eta_N < 0, 'a viscosity >= 0 [Pa s]'),
      ('a Maxwell branch on a model that is not a solid',
       on & ~np.isin(models, KELVIN_VOIGT_MODELS + ('rigid',)),
       f'maxwell_E 0 (solids: {list(KELVIN_VOIGT_MODELS)})')):
    if bad.any():
      raise MPMInputError(
        f'{caller}: {label} for {int(bad.sum())} of {n} particles '
        f'({_rows(bad)}); give each {fix}.')
