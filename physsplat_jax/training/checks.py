"""Errors and up-front checks of :mod:`physsplat_jax.training.simtrain`.

Every setting of a simulator task (:class:`~.simtrain.TaskConfig`), of a
training run (``config.sim``) and of a material fit is checked before any
scene is prepared or any code compiled: a bad value raises
:class:`TrainingError` naming the field, the value and what to give,
instead of a NumPy/JAX/optax error deep inside the run, a silent wrong
result or NaN weights. :func:`field_correlation` reports an undefined
correlation as ``None`` (JSON ``null``), not NaN.
"""

from __future__ import annotations

import numpy as np

from physsplat_jax import pipeline as pl
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.values import is_int, is_real


class TrainingError(PhysSplatError, ValueError):
  """A training or fitting setup that cannot run (configs, data, shapes);
  the message names it and the fix."""


class DivergedError(PhysSplatError, FloatingPointError):
  """A simulation, training or fitting step went non-finite (a
  ``FloatingPointError``); the message names the step and what to
  change."""


# Polynomial degrees of fit_material's log-field: 0 (mean only), 1, 2.
FIELD_DEGREES = (0, 1, 2)
FIT_OPTIMIZERS = ('lbfgs', 'adam')
DTYPES = ('float32', 'float64')
_SEEDS = (lambda v: isinstance(v, (tuple, list)) and len(v) >= 1
          and all(is_int(s) and s >= 0 for s in v),
          'a non-empty list of integer seeds >= 0')


def check(owner: str, values) -> None:
  """:func:`physsplat_jax.mpdp.model.check_values` raising
  :class:`TrainingError`."""
  model_lib.check_values(owner, values, TrainingError)


def check_task_config(tc) -> None:
  """Checks a :class:`~.simtrain.TaskConfig` (run when one is made)."""
  check('TaskConfig', [
    ('num_gaussians', tc.num_gaussians, (
      lambda v: is_int(v) and v >= 8, 'an integer >= 8')),
    ('length', tc.length, '>0'), ('E', tc.E, '>0'),
    ('nu', tc.nu, (lambda v: is_real(v) and 0 <= v < 0.5,
                   'a number in [0, 0.5)')),
    ('rho', tc.rho, '>0'),
    ('substeps_per_frame', tc.substeps_per_frame, 'int>=1'),
    ('gaussian_scale', tc.gaussian_scale, '>0'),
    ('wall_seed', tc.wall_seed, 'int'),
    ('model', tc.model, (lambda v: v in model_lib.MODEL_NAMES,
                         f'one of {model_lib.MODEL_NAMES}')),
    ('dtype', tc.dtype, (lambda v: v in DTYPES, f'one of {DTYPES}'))])
  try:  # num_particles, num_frames, fps, grid_res, margin, width, height
    tc.pipeline_config()
  except pl.PipelineError as e:
    raise TrainingError(
      str(e).replace('PipelineConfig.max_particles', 'TaskConfig.'
                     'num_particles').replace('PipelineConfig.',
                                              'TaskConfig.')) from None


def check_optimizer(owner: str, num_steps, learning_rate, grad_clip=1.0,
                    min_steps: int = 0) -> None:
  """Steps (an integer >= ``min_steps``), a finite step size > 0 and a
  finite clip > 0 (a NaN rate trained NaN weights, a negative one ascent,
  a clip <= 0 froze the weights)."""
  check(owner, [
    ('num_steps', num_steps, f'int>={min_steps}'),
    ('learning_rate', learning_rate, '>0'),
    ('grad_clip', grad_clip, '>0')])


def check_sim_config(config) -> None:
  """Checks the ``sim`` section of ``experiments/configs/mpdp.py`` but its
  ``task`` (a :class:`~.simtrain.TaskConfig` checks itself)."""
  check_optimizer('config.sim', config.num_steps, config.learning_rate,
                  config.grad_clip)
  check('config.sim', [
    ('train_seeds', config.train_seeds, _SEEDS),
    ('eval_seeds', config.eval_seeds, _SEEDS),
    ('init', config.init, (lambda v: v in ('zero', 'pretrained'),
                           "'zero' or 'pretrained'")),
    ('log_every', config.log_every, 'int>=1'),
    ('checkpoint_every', config.checkpoint_every, 'int>=1'),
    ('max_to_keep', config.max_to_keep, (
      lambda v: v is None or (is_int(v) and v >= 1),
      'an integer >= 1 (or None: keep every checkpoint)'))])


def check_fit(num_steps, learning_rate, E_init, field_degree,
              optimizer='lbfgs') -> None:
  """Checks the arguments of :func:`~.simtrain.fit_material`."""
  check_optimizer('fit_material', num_steps, learning_rate, min_steps=1)
  check('fit_material', [
    ('optimizer', optimizer, (lambda v: v in FIT_OPTIMIZERS,
                              f'one of {FIT_OPTIMIZERS}')),
    ('E_init', E_init, (lambda v: is_real(v) and v > 0,
                        'a finite fraction of the true mean E > 0')),
    ('field_degree', field_degree, (
      lambda v: is_int(v) and v in FIELD_DEGREES,
      f'one of {FIELD_DEGREES} (0: the mean only)'))])


def field_correlation(field, truth) -> float | None:
  """Pearson correlation of ``log field`` with ``log truth`` ((N,) each).

  None where it is undefined: a uniform field (``field_degree=0`` fits the
  mean only) has no variation to correlate (NumPy gave NaN, which is not
  valid JSON, and RuntimeWarnings).
  """
  a = np.log(np.asarray(field, np.float64))
  b = np.log(np.asarray(truth, np.float64))
  if min(np.std(a), np.std(b)) <= 1e-12 or not (
      np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
    return None
  return float(np.corrcoef(a, b)[0, 1])


UNDEFINED_CORRELATION = ('undefined: the fitted E field is uniform '
                         '(field_degree=0 fits the mean only)')
