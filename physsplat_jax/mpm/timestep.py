"""Time-step bounds: elastic-wave CFL, particle speed and fluid viscosity.

Explicit MLS-MPM is stable while an elastic wave crosses less than a cell
per substep::

  dt <= cfl * dx / c_p,   c_p = sqrt((lam + 2 mu) / rho)

(``c_p`` the P-wave speed; for the Newtonian fluid the sound speed
``sqrt(K / rho)``, ``K = E / (3 (1 - 2 nu))``). PhysGaussian's own configs
sit at ``cfl = 0.35-0.37`` (REFERENCE.md 1.4: 2e6 Pa / 200 kg/m^3 / dx 0.04
-> 1e-4 s; 5e7 / 2000 / dx 0.01 -> 2e-5 s; 7e10 / 2700 / dx 0.0167 -> 1e-6
s), which is ``DEFAULT_CFL``. ``check_dt`` raises above ``UNSTABLE_CFL`` = 1:
measured on a 1000-particle block hitting a floor at 2 m/s (24^3 grid, 1000
substeps), fixed corotated, neo-Hookean and StVK all ran at Courant numbers
0.3-1.0 and all produced NaN in the first frame at 1.2 (docs/mpm.md).
Further bounds: a particle speed ``v_max`` must not cross more than ``cfl``
cells per substep, and an explicit viscous stress (the Newtonian fluid's,
a solid's Kelvin-Voigt damping: ``models.KELVIN_VOIGT_MODELS``) needs
``dt <= rho dx^2 / (6 eta)``.

Rigid particles (``body_id >= 0`` or model 'rigid') are ignored: their
stiffness never enters the solver.
"""

from __future__ import annotations

import math

import numpy as np

from physsplat_jax.mpm import base
from physsplat_jax.mpm import inputs
from physsplat_jax.mpm.base import MPMInputError
from physsplat_jax.mpm.models import KELVIN_VOIGT_MODELS

DEFAULT_CFL = 0.35
UNSTABLE_CFL = 1.0


def wave_speed(E, nu, rho, fluid=False, E_N=0.0, nu_N=0.0):
  """Elastic wave speed [m/s] (P-wave, or bulk sound speed for fluids);
  a Maxwell branch (``E_N``, ``nu_N``) stiffens the instantaneous response:
  its P-wave modulus adds."""
  E, nu, rho, E_N, nu_N = (np.asarray(a, np.float64)
                           for a in (E, nu, rho, E_N, nu_N))
  nu = np.minimum(nu, 0.499)
  bulk = E / (3.0 * (1.0 - 2.0 * nu))
  p_wave = E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))
  branch = E_N * (1.0 - nu_N) / ((1.0 + nu_N) * (1.0 - 2.0 * nu_N))
  return np.sqrt((np.where(fluid, bulk, p_wave) + branch) / rho)


def cfl_dt(E, nu, rho, dx, cfl: float = DEFAULT_CFL, fluid=False) -> float:
  """Largest substep with ``cfl`` cells per elastic wave crossing [s].

  Args:
    E, nu, rho: scalars or arrays (the stiffest entry wins) [Pa, -, kg/m^3].
    dx: cell size [m].
    cfl: Courant number.
    fluid: scalar or array flag, use the bulk sound speed.

  Returns:
    dt [s] (inf for an empty array).
  """
  with np.errstate(all='ignore'):
    c = np.atleast_1d(wave_speed(E, nu, rho, fluid))
  if c.size == 0:
    return math.inf
  if not np.all(np.isfinite(c) & (c > 0)):
    raise MPMInputError(
      f'cfl_dt: no elastic wave speed for E={E}, nu={nu}, rho={rho}: need '
      'E > 0, rho > 0 and -1 < nu < 0.5 (all finite)')
  return float(cfl * dx / np.max(c))


def _active(materials: base.Materials, models, body_id):
  """Host arrays of the non-rigid particles: (E, nu, rho, eta, fluid,
  viscous, E_N, nu_N), ``viscous`` where ``eta`` is an explicit viscous
  stress (the fluid's, a solid's Kelvin-Voigt damping), ``E_N, nu_N`` the
  Maxwell branch's (0 without)."""
  E = np.asarray(materials.E, np.float64)
  nu = np.asarray(materials.nu, np.float64)
  E_N, nu_N = (np.broadcast_to(np.asarray(
    0.0 if a is None else a, np.float64), E.shape)
    for a in (materials.maxwell_E, materials.maxwell_nu))
  rho = np.asarray(materials.rho, np.float64)
  eta = np.asarray(materials.viscosity, np.float64)
  mid = np.asarray(materials.model_id)
  names = np.asarray(list(models) if models else ['fixed_corotated'])
  keep = np.ones(E.shape, bool)
  if models:
    keep &= names[mid] != 'rigid'
  if body_id is not None:
    keep &= np.asarray(body_id) < 0
  fluid = np.zeros(E.shape, bool)
  viscous = np.zeros(E.shape, bool)  # (without models: none known)
  if models:
    fluid = np.isin(names[mid], base.FLUID_MODELS)
    viscous = np.isin(names[mid], KELVIN_VOIGT_MODELS) | fluid
  viscous &= eta > 0
  return (E[keep], nu[keep], rho[keep], eta[keep], fluid[keep],
          viscous[keep], E_N[keep], nu_N[keep])


def viscous_dt(rho, eta, dx: float) -> float:
  """The explicit viscous stress's bound ``min rho dx^2 / (6 eta)`` [s]
  over the points with ``eta > 0`` [kg/m^3, Pa s] (inf without)."""
  rho, eta = (np.asarray(a, np.float64) for a in (rho, eta))
  on = eta > 0
  if not np.any(on):
    return math.inf
  return float(np.min(rho[on] * dx * dx / (6.0 * eta[on])))


def stable_dt(materials: base.Materials, dx: float, models=None,
              body_id=None, max_speed: float = 0.0,
              cfl: float = DEFAULT_CFL) -> tuple[float, str]:
  """Smallest of the time-step bounds and the name of the binding one.

  Args:
    materials: per-particle materials (host-readable).
    dx: cell size [m].
    models: ``SimConfig.models`` (to skip rigid and treat fluids).
    body_id: (N,) rigid body ids or None.
    max_speed: expected largest particle speed [m/s].
    cfl: Courant number.

  Returns:
    ``(dt, reason)`` with reason 'elastic', 'speed', 'viscosity' or 'none'.
  """
  E, nu, rho, eta, fluid, visc, E_N, nu_N = _active(materials, models,
                                                   body_id)
  fault = inputs.material_fault(E, nu, rho)
  if fault:   # (NaN included) no wave speed, no time step
    label, bad, fix = fault
    raise MPMInputError(
      f'stable_dt: {label} (or not finite) for {int(bad.sum())} of '
      f'{bad.size} stressed particles; give each {fix}.')
  cands = [(math.inf, 'none')]
  if E.size:
    c = wave_speed(E, nu, rho, fluid, E_N, nu_N)
    cands.append((cfl * dx / float(np.max(c)), 'elastic'))
    if np.any(visc):
      cands.append((viscous_dt(rho[visc], eta[visc], dx), 'viscosity'))
  if max_speed > 0:
    cands.append((cfl * dx / max_speed, 'speed'))
  return min(cands)


def choose_substeps(config: base.SimConfig | float, frame_dt: float,
                    materials: base.Materials, body_id=None,
                    max_speed: float = 0.0,
                    cfl: float = DEFAULT_CFL) -> int:
  """Substeps per frame so that ``frame_dt / n`` meets every bound.

  Args:
    config: a ``SimConfig`` (its grid and models) or the cell size dx [m].
    frame_dt: time between frames [s].
    materials: per-particle materials.
    body_id: (N,) rigid body ids (rigid particles are ignored) or None.
    max_speed: expected largest particle speed [m/s] (e.g. from impulses or
      a drop height: sqrt(2 g h)).
    cfl: Courant number.

  Returns:
    n >= 1; the substep is ``frame_dt / n``.
  """
  if isinstance(config, base.SimConfig):
    dx, models = config.grid.dx, config.models
  else:
    dx, models = float(config), None
  dt, _ = stable_dt(materials, dx, models, body_id, max_speed, cfl)
  if not frame_dt > 0:
    raise MPMInputError(f'choose_substeps: frame_dt = {frame_dt} must be > 0.')
  return max(1, int(math.ceil(frame_dt / dt * (1.0 - 1e-9))))


def check_dt(config: base.SimConfig, materials: base.Materials,
             body_id=None, max_speed: float = 0.0,
             limit: float = UNSTABLE_CFL) -> float:
  """Raises ``SimulationError`` if ``config.dt`` is unstable.

  Args:
    config: the config whose ``dt`` is checked.
    materials: per-particle materials.
    body_id: (N,) rigid body ids or None.
    max_speed: expected largest particle speed [m/s].
    limit: Courant number above which the run is called unstable.

  Returns:
    The Courant number ``config.dt / stable_dt(cfl=1)``.

  Raises:
    SimulationError (reason 'dt'): the message names the bound, the largest
      stable dt and the substeps per frame that would meet it.
  """
  dx = config.grid.dx
  dt1, why = stable_dt(materials, dx, config.models, body_id, max_speed, 1.0)
  courant = config.dt / dt1 if math.isfinite(dt1) else 0.0
  if courant > limit:
    ok = limit * dt1
    n = max(1, math.ceil(config.frame_dt / (DEFAULT_CFL * dt1)))
    E, nu, rho, eta, _, visc, E_N, nu_N = _active(materials, config.models,
                                                  body_id)
    detail = ''
    if why == 'elastic':
      i = int(np.argmax(wave_speed(E, nu, rho, E_N=E_N, nu_N=nu_N)))
      detail = (f' (stiffest particle: E={E[i]:.3g} Pa, nu={nu[i]:.3g}, '
                f'rho={rho[i]:.3g} kg/m^3, dx={dx:.3g} m)')
    elif why == 'viscosity':
      detail = f' (viscosity up to {float(np.max(eta[visc])):.3g} Pa s)'
    raise base.SimulationError(
      f'dt = {config.dt:.3g} s is unstable: the {why} bound allows at most '
      f'{ok:.3g} s{detail}, Courant number {courant:.2f} > {limit}. Use '
      f'dt <= {DEFAULT_CFL * dt1:.3g} s, i.e. substeps_per_frame >= {n} '
      f'for frame_dt = {config.frame_dt:.3g} s (mpm.choose_substeps), or '
      'lower E, raise the density, or coarsen the grid.',
      frame=None, reason='dt')
  return courant


def bucket_substeps(n: int) -> int:
  """``n`` rounded up to 16 steps per octave (exact below 32).

  The substep count is static in the compiled frame (the scan's length and
  the time step), so an automatic count that moves with the seed, the
  particle budget or a small change of material would recompile every time;
  on this ladder it changes only when the wave speed moves by more than a
  step. Rounding up only lowers the time step (at most 6.25 % more
  substeps, ~3 % on average).
  """
  n = int(n)
  step = 1 << max(0, n.bit_length() - 5)
  return -(-n // step) * step
