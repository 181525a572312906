"""Recovers a beam's Young's modulus (mean + smooth field) by gradient descent.

The observations are simulated with physsplat_jax.pipeline.simulate from the
ground-truth synthetic field (physsplat_jax.mpdp.synthetic rules) of a
cantilever (physsplat_jax.training.simtrain.make_task, the ``sim.task`` section
of the config). E is then fitted through the MLS-MPM rollout, starting from
``--E_init`` x the true mean and a uniform field, either from the Gaussian
centres ('trajectory') or from the frames rendered by the differentiable
renderer ('video'), by L-BFGS (default) or Adam (``--optimizer=adam``).
Prints recovered vs true, one JSON line per fit; ``--out`` is rewritten
after each fit (``complete`` is true once every fit has run).

python experiments/fit_material.py --config=experiments/configs/mpdp.py \
  [--seeds=10,11] [--observe=trajectory,video] [--steps=20] [--out=f.json]
"""

import json
import math
import os
import subprocess

import jax
import numpy as np
from absl import flags
from absl import logging

from experiments.lib import cli
from physsplat_jax.training import checks
from physsplat_jax.training import simtrain

_SEEDS = flags.DEFINE_list('seeds', ['10', '11'], 'beam seeds')
_OBSERVE = flags.DEFINE_list('observe', ['trajectory', 'video'],
                             "what is observed: 'trajectory' and/or 'video'")
_OPTIMIZER = flags.DEFINE_enum('optimizer', 'lbfgs', checks.FIT_OPTIMIZERS,
                               'L-BFGS with a line search, or Adam')
_STEPS = flags.DEFINE_integer('steps', None, 'optimiser steps per fit '
                              '(default: 20 L-BFGS, 60 Adam)')
_LR = flags.DEFINE_float('learning_rate', 0.1, 'peak Adam step size (Adam '
                         'only)')
_E_INIT = flags.DEFINE_float('E_init', 0.3, 'initial E / true mean E')
_DEGREE = flags.DEFINE_integer('field_degree', 2, 'polynomial log-field '
                               'degree: 0 (mean only), 1 or 2')
_OUT = flags.DEFINE_string('out', None, 'optional JSON results path')
_CONFIG = cli.define_config_file('config', None, 'config file '
                                 '(its sim.task is used)', lock_config=True,
                                 needs=('sim.task',),
                                 example='experiments/configs/mpdp.py')
flags.mark_flags_as_required(['config'])


def _check_flags() -> list[int]:
  """The seeds; a flag no fit can use is a usage error before any work."""
  try:
    seeds = [int(s) for s in _SEEDS.value]
    # (none ran nothing and exited 0; a negative one was NumPy's traceback)
    if not seeds or min(seeds) < 0:
      raise ValueError
  except ValueError:
    raise cli.usage_error(f'--seeds={",".join(_SEEDS.value)}: give integer '
                          'seeds >= 0 separated by commas') from None
  for name, ok, want in (
      ('E_init', math.isfinite(_E_INIT.value) and _E_INIT.value > 0,
       'a finite fraction of the true mean E > 0'),
      ('learning_rate', math.isfinite(_LR.value) and _LR.value > 0,
       'a finite step size > 0'),
      ('field_degree', _DEGREE.value in checks.FIELD_DEGREES,
       f'one of {checks.FIELD_DEGREES} (0: the mean only)'),
      ('steps', _STEPS.value is None or _STEPS.value >= 1,
       'an integer >= 1')):
    if not ok:
      raise cli.usage_error(f'--{name}={flags.FLAGS[name].value}: give '
                            f'{want}')
  bad = sorted(set(_OBSERVE.value) - {'trajectory', 'video'})
  if bad:
    raise cli.usage_error(f'--observe: unknown {bad}; use trajectory and/or '
                          'video')
  if not _OBSERVE.value:  # (it ran nothing and exited 0)
    raise cli.usage_error('--observe=: give trajectory and/or video')
  if _OUT.value:
    folder = os.path.dirname(os.path.abspath(_OUT.value))
    if os.path.isdir(_OUT.value) or not os.path.isdir(folder) or not (
        os.access(folder, os.W_OK)):
      raise cli.usage_error(f'--out={_OUT.value}: give a JSON file path in '
                            'an existing, writable folder')
  return seeds


def main(argv):
  del argv
  seeds = _check_flags()
  tc = simtrain.TaskConfig.from_dict(_CONFIG.value.sim.task)
  if tc.dtype == 'float64':
    jax.config.update('jax_enable_x64', True)
  sha = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'],
                       capture_output=True, text=True).stdout.strip()
  logging.info('devices %s, git %s, task %s', jax.devices(), sha, tc)
  render = 'differentiable' if 'video' in _OBSERVE.value else 'none'
  rows = []
  for seed in seeds:
    task = simtrain.make_task(seed, tc, render=render)
    for observe in _OBSERVE.value:
      r = simtrain.fit_material(
        task, observe, num_steps=_STEPS.value, learning_rate=_LR.value,
        E_init=_E_INIT.value, field_degree=_DEGREE.value,
        optimizer=_OPTIMIZER.value,
        log_fn=lambda i, loss, E: logging.info('step %d loss %.4g E %.4g',
                                               i, loss, E))
      true = np.asarray(task.field[:, 0], np.float64)
      # None (JSON null) for a uniform fitted field (field_degree=0).
      corr = checks.field_correlation(r['field_E'], true)
      # Per-driver E error of the start (E_init, uniform) and of a uniform
      # field at the true mean, for reference against E_point_mare.
      init_mare = np.mean(np.abs(_E_INIT.value - true) / true)
      row = dict(seed=seed, observe=observe, git=sha,
                 field_corr_log=corr,
                 init_point_mare=float(init_mare),
                 uniform_point_mare=float(np.mean(np.abs(1 - true) / true)),
                 loss_start=r['history'][0],
                 **{k: v for k, v in r.items()
                    if k not in ('field_E', 'history')})
      if corr is None:
        row['field_corr_note'] = checks.UNDEFINED_CORRELATION
      print(json.dumps(row), flush=True)
      rows.append(row)
      # After every fit, not at the end: an interrupted or failed later fit
      # lost the earlier ones' results ('complete' says whether all ran).
      cli.write_json(_OUT.value, {
        'task_config': tc.__dict__, 'steps': _STEPS.value,
        'optimizer': _OPTIMIZER.value, 'learning_rate': _LR.value,
        'E_init': _E_INIT.value, 'field_degree': _DEGREE.value,
        'complete': len(rows) == len(seeds) * len(_OBSERVE.value),
        'fits': rows})


if __name__ == '__main__':
  cli.run(main)
