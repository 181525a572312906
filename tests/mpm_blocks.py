"""A small multi-material MPM scene shared by tests (no test here).

Four blocks of 8 particles, fixed corotated, neo-Hookean, Drucker-Prager
and a rigid body, on a 'separate' plane with friction, 16^3 grid, 2
substeps of 1 ms: every kind of constitutive slice, a body and a contact
plane in a frame that compiles in seconds.
"""

import numpy as np

from physsplat_jax import mpm

MODELS = ('fixed_corotated', 'neo_hookean', 'drucker_prager', 'rigid')


def four_blocks(velocity=np.zeros(3), model_counts=(8, 8, 8, 8), **config):
  """``(state, materials, forces, config)``; ``config`` overrides
  ``SimConfig`` fields."""
  g = mpm.GridSpec(res=16, size=1.0)
  sp = g.dx / 2
  cell = np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing='ij'),
                  -1).reshape(-1, 3)
  x = np.concatenate([0.3 + 0.12 * k + (cell + 0.5) * sp for k in range(4)])
  names = [m for m in MODELS for _ in range(8)]
  mat = mpm.make_materials(names, 2e4, 0.3, 1000.0, config_models=MODELS)
  cfg = mpm.SimConfig(
    grid=g, dt=1e-3, substeps_per_frame=2, models=MODELS, num_bodies=1,
    model_counts=model_counts,
    boundary_conditions=(mpm.SurfaceCollider(
      point=(0, 0, 0.25), surface='separate', friction=0.5),), **config)
  body = np.array([-1] * 24 + [0] * 8)
  s = mpm.init_state(x, velocity, sp ** 3, mat, cfg, body_id=body)
  return s, mat, mpm.make_forces(cfg), cfg


def one_block(velocity=np.zeros(3)):
  """``(state, materials, forces, config)`` of 8 fixed-corotated particles
  on an 8^3 grid, 2 substeps: a frame that compiles in about a second, for
  tests of what happens around a frame rather than in it."""
  g = mpm.GridSpec(res=8, size=1.0)
  sp = g.dx / 2
  cell = np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing='ij'),
                  -1).reshape(-1, 3)
  x = 0.4 + (cell + 0.5) * sp
  models = ('fixed_corotated',)
  mat = mpm.make_materials(np.zeros(8, np.int32), 2e4, 0.3, 1000.0,
                           config_models=models)
  cfg = mpm.SimConfig(grid=g, dt=1e-3, substeps_per_frame=2, models=models)
  s = mpm.init_state(x, velocity, sp ** 3, mat, cfg)
  return s, mat, mpm.make_forces(cfg), cfg
