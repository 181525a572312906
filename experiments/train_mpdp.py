"""Trains the MPDP point network on synthetic objects.

python experiments/train_mpdp.py --workdir=/tmp/mpdp \
  --config=experiments/configs/mpdp.py [--config.train.num_steps=500] \
  [--export=physsplat_jax/data/mpdp]
"""

import subprocess

import jax
from absl import app
from absl import flags
from absl import logging
from ml_collections import config_flags

from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp import pretrained
from physsplat_jax.mpdp import train

_WORKDIR = flags.DEFINE_string('workdir', None, 'checkpoints + metrics dir')
_EXPORT = flags.DEFINE_string('export', None,
                              'if set, write the final params (npz) here')
_CONFIG = config_flags.DEFINE_config_file('config', None, 'config file',
                                          lock_config=True)
flags.mark_flags_as_required(['workdir', 'config'])


def main(argv):
  del argv
  sha = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'],
                       capture_output=True, text=True).stdout.strip()
  logging.info('devices %s, git %s, config %s', jax.devices(), sha,
               _CONFIG.value.to_dict())
  result = train.train_and_evaluate(_CONFIG.value, _WORKDIR.value)
  params = result.pop('params')
  logging.info('final: %s', result)
  print({k: v for k, v in result.items()})
  if _EXPORT.value:
    cfg = model_lib.ModelConfig.from_dict(_CONFIG.value.model.to_dict())
    pretrained.save_params(params, cfg, _EXPORT.value,
                           metadata=dict(result, git=sha))


if __name__ == '__main__':
  app.run(main)
