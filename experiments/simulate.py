"""Simulates a 3DGS scene with a PhysGaussian config; writes the trajectory.

python -m experiments.simulate --scene=PATH.ply --config=PATH.json --out=DIR

Writes DIR/trajectory.npz with ``x`` float32 (frames+1, K, 3): positions of
the simulated input Gaussians in the PLY's coordinates (frame 0 = initial),
``ids`` (K,) their row numbers in the PLY and ``t`` (frames+1,) seconds.
The logic lives in :func:`simulate_file` (tested) and
``physsplat_jax.mpm.physgaussian.simulate_config``.
"""

import os
import subprocess

import jax
import numpy as np
from absl import app
from absl import flags
from absl import logging

from physsplat_jax.configs import physgaussian as pg
from physsplat_jax.io import ply
from physsplat_jax.mpm import physgaussian as mpm_pg

_SCENE = flags.DEFINE_string('scene', None, '3DGS .ply file')
_CONFIG = flags.DEFINE_string('config', None, 'PhysGaussian JSON config')
_OUT = flags.DEFINE_string('out', None, 'output directory')
_FRAMES = flags.DEFINE_integer('frames', None, 'override frame_num')
_AUTO = flags.DEFINE_bool('auto_substeps', False,
                          'replace an unstable substep_dt by a stable one')
_FILL = flags.DEFINE_bool('fill', True, 'honour particle_filling')


def simulate_file(scene: str, config: str, out: str, frames=None,
                  auto_substeps=False, fill=True) -> str:
  """Loads, simulates and writes ``out/trajectory.npz``; returns its path."""
  cfg = pg.load_config(config)
  gaussians = ply.load_ply(scene)
  x, ids, t = mpm_pg.simulate_config(
    gaussians, cfg, num_frames=frames, auto_substeps=auto_substeps,
    fill=fill)
  os.makedirs(out, exist_ok=True)
  path = os.path.join(out, 'trajectory.npz')
  np.savez(path, x=x.astype(np.float32), ids=ids.astype(np.int64),
           t=t.astype(np.float64))
  logging.info('wrote %s: x %s, %d Gaussians, t = 0..%.3g s', path, x.shape,
               len(ids), t[-1])
  return path


def _git_sha() -> str:
  try:
    return subprocess.check_output(
      ['git', 'rev-parse', '--short', 'HEAD'],
      cwd=os.path.dirname(os.path.abspath(__file__)),
      stderr=subprocess.DEVNULL).decode().strip()
  except (OSError, subprocess.CalledProcessError):
    return 'unknown'


def main(argv):
  del argv
  logging.info('devices %s, git %s', jax.devices(), _git_sha())
  simulate_file(_SCENE.value, _CONFIG.value, _OUT.value, _FRAMES.value,
                _AUTO.value, _FILL.value)


if __name__ == '__main__':
  flags.mark_flags_as_required(['scene', 'config', 'out'])
  app.run(main)
