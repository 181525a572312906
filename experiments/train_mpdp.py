"""Trains the MPDP point network on synthetic objects.

Supervised (default):
python experiments/train_mpdp.py --workdir=/tmp/mpdp \
  --config=experiments/configs/mpdp.py [--config.train.num_steps=500] \
  [--export=physsplat_jax/data/mpdp]

Through the simulator (physsplat_jax.pipeline.simulate; trajectory loss
against targets simulated from the ground-truth fields; config.sim; writes
workdir/simulator.json, resumes from workdir/checkpoints):
python experiments/train_mpdp.py --workdir=/tmp/mpdp_sim \
  --config=experiments/configs/mpdp.py --mode=simulator \
  [--config.sim.num_steps=30] [--config.sim.init=pretrained]
"""

import json
import subprocess

import jax
from absl import flags
from absl import logging

from experiments.lib import cli
from physsplat_jax.io import outputs
from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp import pretrained
from physsplat_jax.training import simtrain
from physsplat_jax.mpdp import train

_WORKDIR = flags.DEFINE_string('workdir', None, 'checkpoints + metrics dir')
_EXPORT = flags.DEFINE_string('export', None,
                              'if set, write the final params (npz) here')
_MODE = flags.DEFINE_enum('mode', 'supervised', ['supervised', 'simulator'],
                          'training mode')
_CONFIG = cli.define_config_file('config', None, 'config file',
                                 lock_config=True,
                                 needs=('model', 'data', 'train'),
                                 example='experiments/configs/mpdp.py')
flags.mark_flags_as_required(['workdir', 'config'])


def main(argv):
  del argv
  sha = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'],
                       capture_output=True, text=True).stdout.strip()
  config = _CONFIG.value
  if _EXPORT.value:  # a bad --export fails now, not after the training
    try:
      outputs.check_output_dir(_EXPORT.value)
    except outputs.OutputError as e:
      raise outputs.OutputError(f'--export={_EXPORT.value}: {e}') from None
  if _MODE.value == 'simulator' and config.sim.task.dtype == 'float64':
    jax.config.update('jax_enable_x64', True)
  logging.info('devices %s, git %s, mode %s, config %s', jax.devices(), sha,
               _MODE.value, config.to_dict())
  if _MODE.value == 'simulator':
    result = simtrain.train_and_evaluate(config.sim, _WORKDIR.value)
  else:
    result = train.train_and_evaluate(config, _WORKDIR.value)
  params = result.pop('params')
  logging.info('final: %s', result)
  print(json.dumps(dict(result, git=sha), indent=1, default=str))
  if _EXPORT.value:
    cfg = model_lib.ModelConfig.from_dict(config.model.to_dict())
    if _MODE.value == 'simulator':
      cfg = model_lib.ModelConfig()  # the pipeline's architecture
      result = {'held_out': result['held_out'], 'mode': 'simulator'}
    pretrained.save_params(params, cfg, _EXPORT.value,
                           metadata=dict(result, git=sha))


if __name__ == '__main__':
  cli.run(main)
