"""The main job on a built-in scene: simulate it and write a video.

  python -m experiments.demo                     # tabletop -> out/demo
  python -m experiments.demo --scene=ficus --out=out/ficus

Runs the whole pipeline (perception from the material library, MPDP, PGAS,
MLS-MPM, deformed Gaussians, rendering) with the CPU-sized settings of
experiments/configs/demo.py (``--config.num_frames=12`` etc. override them)
and the scene's motion from the config file's ``SCENE_MOTIONS`` (those of
experiments/configs/simulate.py where it has none), then prints
where the video is and where the time went. ``make demo`` runs it.
"""

import os
import sys

from absl import flags
from absl import logging

from experiments.lib import cli
from experiments.lib import simulate as lib
from physsplat_jax import pipeline as pl

_CONFIG = cli.define_config_file(
  'config', os.path.join(os.path.dirname(__file__), 'configs', 'demo.py'),
  'demo settings')
_SCENE = flags.DEFINE_string('scene', 'tabletop',
                             'built-in scene (tabletop, ficus, donut) or PLY')
_OUT = flags.DEFINE_string('out', 'out/demo', 'output directory')
_PIPELINED = flags.DEFINE_bool(
  'pipelined', True, 'overlap the host\'s per-frame work (checks, '
  'rendering, writing) with the device simulating the next frame; '
  '--nopipelined runs the stages in turn, for exact per-stage times')


def main(argv):
  del argv
  process = cli.start_run()
  sha = lib.git_sha()
  # The --config file's motions (a user's file was ignored for simulate.py's).
  config = lib.build_config(_SCENE.value, _CONFIG.value,
                            motions=lib.flag_motions(fallback=True))
  logging.info('git %s, config %s', sha, config)
  # (the report said 'make demo' for any command line, and no revision)
  report = lib.run_scene(_SCENE.value, config, _OUT.value,
                         extra_report=dict(command=' '.join(sys.argv),
                                           git=sha),
                         pipelined=_PIPELINED.value,
                         process=process)
  print(pl.summary(report))
  print(f'\nvideo: {report["files"].get("video")}')


if __name__ == '__main__':
  cli.run(main, cpu_devices=2, fast_exit=True)
