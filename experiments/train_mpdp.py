"""Trains the MPDP point network on synthetic objects.

Supervised (default):
python experiments/train_mpdp.py --workdir=/tmp/mpdp \
  --config=experiments/configs/mpdp.py [--config.train.num_steps=500] \
  [--export=physsplat_jax/data/mpdp]

Through the simulator (trajectory loss, from the mean-only baseline; writes
workdir/simulator.json):
python experiments/train_mpdp.py --workdir=/tmp/mpdp_sim \
  --config=experiments/configs/mpdp.py --mode=simulator --sim_steps=30
"""

import json
import os
import subprocess

import jax
from absl import app
from absl import flags
from absl import logging
from ml_collections import config_flags

from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp import pretrained
from physsplat_jax.mpdp import simtrain
from physsplat_jax.mpdp import train

_WORKDIR = flags.DEFINE_string('workdir', None, 'checkpoints + metrics dir')
_EXPORT = flags.DEFINE_string('export', None,
                              'if set, write the final params (npz) here')
_MODE = flags.DEFINE_enum('mode', 'supervised', ['supervised', 'simulator'],
                          'training mode')
_SIM_STEPS = flags.DEFINE_integer('sim_steps', 30, 'simulator-mode steps')
_CONFIG = config_flags.DEFINE_config_file('config', None, 'config file',
                                          lock_config=True)
flags.mark_flags_as_required(['workdir', 'config'])


def main(argv):
  del argv
  sha = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'],
                       capture_output=True, text=True).stdout.strip()
  logging.info('devices %s, git %s, config %s', jax.devices(), sha,
               _CONFIG.value.to_dict())
  if _MODE.value == 'simulator':
    run_simulator_mode(sha)
    return
  result = train.train_and_evaluate(_CONFIG.value, _WORKDIR.value)
  params = result.pop('params')
  logging.info('final: %s', result)
  print({k: v for k, v in result.items()})
  if _EXPORT.value:
    cfg = model_lib.ModelConfig.from_dict(_CONFIG.value.model.to_dict())
    pretrained.save_params(params, cfg, _EXPORT.value,
                           metadata=dict(result, git=sha))


def run_simulator_mode(sha):
  """Trajectory-loss training from the baseline; also scores the shipped
  supervised params on the same held-out beams."""
  os.makedirs(_WORKDIR.value, exist_ok=True)
  r = simtrain.run_demo(
    num_steps=_SIM_STEPS.value,
    log_fn=lambda i, loss: logging.info('sim step %d loss %.5f', i, loss))
  r.pop('params')
  eval_scenes = simtrain.make_scenes((10, 11), 128, simtrain.SimConfig())
  r['eval_pretrained_supervised'] = simtrain.trajectory_errors(
    pretrained.load_pretrained(), eval_scenes, simtrain.SimConfig())
  r['git'] = sha
  logging.info('simulator mode: %s', r)
  print(json.dumps(r))
  with open(os.path.join(_WORKDIR.value, 'simulator.json'), 'w') as f:
    json.dump(r, f, indent=1)


if __name__ == '__main__':
  app.run(main)
