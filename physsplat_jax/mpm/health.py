"""A frame's health: the statistics ``mpm.run`` reads after every frame and
the :class:`SimulationError` it raises for a blown-up one (NaN, particles
pinned at the wall or crossing a cell per substep, ``|F|`` or ``det F``
out of range), each naming the frame and the fix.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax.mpm import base


def _stats(config: base.SimConfig, state: base.MPMState):
  """The frame's statistics (device scalars) for :func:`check_state`.

  One program per particle count and dtype, whatever the config: the grid
  and time step come in as arguments (keyed by the whole config, every
  scene and test compiled its own, 0.2-0.4 s each on the 2-core VM).
  """
  grid = config.grid
  lo, hi = grid.particle_bounds
  # One host array (one transfer per frame): the grid's lower corner, the
  # particles' bounds relative to it, the wall margin and two speeds.
  limits = np.array([*grid.lower, lo, hi, 1e-3 * grid.dx,
                     0.1 * grid.dx / config.dt, grid.dx / config.dt],
                    state.x.dtype)
  return _state_stats(state.x, state.v, state.F, limits)


@jax.jit
def _state_stats(x, v, F, limits):
  lower, (lo, hi, eps, fast_speed, cell_speed) = limits[:3], limits[3:]
  rel = x - lower
  finite = (jnp.all(jnp.isfinite(x), 1) & jnp.all(jnp.isfinite(v), 1)
            & jnp.all(jnp.isfinite(F), (1, 2)))
  speed = jnp.sqrt(jnp.sum(v * v, 1))
  at_wall = jnp.any((rel <= lo + eps) | (rel >= hi - eps), axis=1)
  fast = speed > fast_speed
  Fn = jnp.sqrt(jnp.sum(F * F, (1, 2)))
  J = jnp.linalg.det(F)
  big = jnp.where(finite, Fn, 0.0)
  return dict(
    nonfinite=jnp.sum(~finite), wall=jnp.sum(at_wall & fast & finite),
    too_fast=jnp.sum((speed > cell_speed) & finite),
    max_F=jnp.max(big, initial=0.0),
    min_J=jnp.min(jnp.where(finite, J, 1.0), initial=1.0),
    max_J=jnp.max(jnp.where(finite, J, 1.0), initial=1.0),
    max_speed=jnp.max(jnp.where(finite, speed, 0.0), initial=0.0),
  )


MAX_F = 100.0
J_RANGE = (1e-2, 1e2)


# How check_state's messages start their fix: the pipeline and the
# PhysGaussian driver replace the fix from here on with one in their own
# terms (split_fix).
FIX_START = 'Use a smaller dt'


def split_fix(error: base.SimulationError) -> str | None:
  """What a :func:`check_state` error says before its fix (which callers
  reword in their users' terms), or None for another message."""
  head, sep, _ = str(error).partition(FIX_START)
  return head if sep else None


def check_state(config: base.SimConfig, stats: dict, frame: int,
                t: float) -> None:
  """Raises ``SimulationError`` for a blown-up frame (see ``run``)."""
  fix = (f'{FIX_START} (now {config.dt:.3g} s; mpm.choose_substeps picks '
         'a stable one), lower E, add damping, or enlarge the domain.')
  where = f'frame {frame} (t = {t:.4g} s)'
  if stats['nonfinite'] > 0:
    raise base.SimulationError(
      f'{where}: {int(stats["nonfinite"])} particles have NaN/inf positions, '
      'velocities or F: the simulation blew up, most likely because the time '
      f'step is too large for the stiffest material. {fix}', frame, 'nan')
  if stats['wall'] > 0:
    raise base.SimulationError(
      f'{where}: {int(stats["wall"])} particles are pinned at the domain wall '
      f'at speed (max speed {float(stats["max_speed"]):.3g} m/s): the '
      'simulation is unstable or the object is thrown out of the grid. '
      f'{fix}', frame, 'wall')
  if stats['too_fast'] > 0:
    raise base.SimulationError(
      f'{where}: {int(stats["too_fast"])} particles move more than a cell per '
      f'substep (max speed {float(stats["max_speed"]):.3g} m/s > dx/dt = '
      f'{config.grid.dx / config.dt:.3g} m/s). {fix}', frame, 'speed')
  if stats['max_F'] > MAX_F:
    raise base.SimulationError(
      f'{where}: |F| reached {float(stats["max_F"]):.3g} (> {MAX_F}): the '
      f'deformation is exploding. {fix}', frame, 'F')
  if not (J_RANGE[0] <= stats['min_J'] and stats['max_J'] <= J_RANGE[1]):
    raise base.SimulationError(
      f'{where}: det F left [{J_RANGE[0]}, {J_RANGE[1]}] (min '
      f'{float(stats["min_J"]):.3g}, max {float(stats["max_J"]):.3g}): '
      f'particles are crushed or torn apart. {fix}', frame, 'J')
