"""The substeps of a prepared scene: the bounds of its materials' waves, of
the speeds the config gives and of its viscous stresses
(``prepare_scene``'s time-step stage; ``mpm.timestep`` for a solver-level
run).
"""

from __future__ import annotations

import math

import numpy as np

from physsplat_jax.mpm import timestep
from physsplat_jax.mpm.base import FLUID_MODELS
from physsplat_jax.mpm.base import model_default
from physsplat_jax.mpm.models import KELVIN_VOIGT_MODELS
from physsplat_jax.mpm.timestep import bucket_substeps
from physsplat_jax.pipeline.config import ForceKind
from physsplat_jax.pipeline.config import PipelineError
from physsplat_jax.pipeline.config import PrepareConfig


def given_speed(cfg) -> float:
  """The fastest a particle can move by what the config gives it [m/s]:
  the largest initial speed plus every impulse's velocity change (impulses
  on one object add up). ``cfg``: a PrepareConfig or PipelineConfig."""
  v0 = max([float(np.linalg.norm(v)) for _, v in cfg.initial_velocity]
           + [0.0])
  return v0 + sum(float(np.linalg.norm(f.vector)) for f in cfg.forces
                  if f.kind is ForceKind.IMPULSE)


def _object_param(mats, rigid, dobj, name: str, kinds) -> np.ndarray:
  """Per driver, its object's parameter ``name`` (its model's default
  where not given) when the object is deformable and its model one of
  ``kinds``; 0 otherwise."""
  return np.array([
    m.params_dict.get(name, model_default(m.model, name))
    if not r and m.model in kinds else 0.0
    for m, r in zip(mats, rigid)])[dobj]


def viscous_dt(mats, rigid, field, dobj, dx: float) -> float:
  """The explicit viscous stress's time-step bound (``mpm.timestep``) of
  the deformable points whose viscosity is a stress (a fluid's, a solid's
  Kelvin-Voigt damping; the MPDP field's density included); inf
  without."""
  eta = _object_param(mats, rigid, dobj, 'viscosity',
                      KELVIN_VOIGT_MODELS + FLUID_MODELS)
  rho = np.array([m.rho for m in mats])[dobj] * field[:, 2]
  return timestep.viscous_dt(rho, eta, dx)


def time_step_stage(mats, rigid, field, dobj, dx: float, cfg: PrepareConfig,
                    gravity: float) -> tuple[int, float]:
  """(substeps per frame, largest wave speed): the CFL bound of the stiffest
  deformable point (MPDP field included) and of the speeds given: the
  largest initial speed plus every impulse's velocity change (an impulse
  of 2000 m/s took 1 substep per frame and blew up). A point force's
  speed depends on what resists it and is not bounded here, nor is free
  fall's; the CFL number's margin covers moderate ones. A viscosity that is
  a stress (:func:`viscous_dt`) bounds the substep too."""
  deform = ~np.asarray(rigid)[dobj]
  c_max = 0.0
  if deform.any():
    E = np.array([m.E for m in mats])[dobj] * field[:, 0]
    nu = np.clip(np.array([m.nu for m in mats])[dobj] * field[:, 1], 0, 0.49)
    rho = np.array([m.rho for m in mats])[dobj] * field[:, 2]
    # A Maxwell branch stiffens the instantaneous response (its own E_N,
    # nu_N, not the MPDP field's).
    E_N, nu_N = (_object_param(mats, rigid, dobj, k, KELVIN_VOIGT_MODELS)
                 for k in ('maxwell_E', 'maxwell_nu'))
    c = timestep.wave_speed(E, nu, rho, E_N=E_N, nu_N=nu_N)
    c_max = float(np.max(c[deform]))
  frame_dt = cfg.frame_dt
  v_max = given_speed(cfg)
  dt_visc = viscous_dt(mats, rigid, field, dobj, dx)
  # Elastic waves and particle motion both limited to cfl cells per step;
  # with neither, one frame of free fall sets the scale.
  speed = c_max + v_max
  if speed == 0:
    speed = max(1.0, abs(gravity) * frame_dt)
  if cfg.substeps_per_frame is not None:
    substeps = int(cfg.substeps_per_frame)
    if speed > 0 and frame_dt / substeps > 2 * cfg.cfl * dx / speed:
      raise PipelineError(
        f'substeps_per_frame={substeps} gives dt={frame_dt / substeps:.3g} s, '
        f'above the stability bound {cfg.cfl * dx / speed:.3g} s (wave speed '
        f'{c_max:.3g} m/s + initial and impulse speeds {v_max:.3g} m/s, '
        f'dx={dx:.3g} m); use '
        f'substeps_per_frame >= {math.ceil(frame_dt * speed / (cfg.cfl * dx))}'
        ' or None (automatic), or lower E, the initial velocity or the '
        'impulses.')
    if frame_dt / substeps > dt_visc:
      raise PipelineError(
        f'substeps_per_frame={substeps} gives dt={frame_dt / substeps:.3g} s, '
        f'above the explicit viscous stress\'s bound {dt_visc:.3g} s (rho '
        'dx^2 / (6 viscosity)); use substeps_per_frame >= '
        f'{math.ceil(frame_dt / dt_visc)} or None (automatic), or lower the '
        'viscosity.')
    return substeps, c_max
  dt_cfl = cfg.cfl * dx / speed
  n_visc = int(math.ceil(frame_dt / dt_visc * (1.0 - 1e-9)))
  substeps = max(1, int(math.ceil(frame_dt / dt_cfl)), n_visc)
  if substeps <= cfg.max_substeps_per_frame:
    substeps = min(bucket_substeps(substeps), cfg.max_substeps_per_frame)
  if substeps > cfg.max_substeps_per_frame:
    # The usual causes, when the numbers say so: frames far apart, or a
    # scene whose units are not metres.
    hints = ''
    if frame_dt > 0.2:
      hints += f'; a frame lasts {frame_dt:.3g} s (fps={cfg.fps:g}): raise fps'
    if dx < 1e-4:
      hints += (f'; a grid cell is {dx:.3g} m: if the scene is not in '
                'metres, give its scale (--meters_per_unit)')
    if n_visc >= substeps:
      raise PipelineError(
        f'the most viscous material needs {n_visc} substeps per frame at '
        f'dx={dx:.3g} m (its explicit viscous stress: dt <= rho dx^2 / (6 '
        f'viscosity) = {dt_visc:.3g} s), over max_substeps_per_frame='
        f'{cfg.max_substeps_per_frame}: lower the viscosity, lower grid_res, '
        f'or raise max_substeps_per_frame{hints}.')
    raise PipelineError(
      f'the stiffest material (wave speed {c_max:.3g} m/s) and initial and '
      f'impulse speeds ({v_max:.3g} m/s) need {substeps} substeps per frame at '
      f'dx={dx:.3g} m, over max_substeps_per_frame='
      f'{cfg.max_substeps_per_frame}: lower E (or mark the object rigid), '
      'lower grid_res or the velocities, or raise max_substeps_per_frame'
      f'{hints}.')
  return substeps, c_max
