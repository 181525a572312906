"""The main job on a built-in scene: simulate it and write a video.

  python -m experiments.demo                     # tabletop -> out/demo
  python -m experiments.demo --scene=ficus --out=out/ficus

Runs the whole pipeline (perception from the material library, MPDP, PGAS,
MLS-MPM, deformed Gaussians, rendering) with the CPU-sized settings of
experiments/configs/demo.py and the scene's motion from
experiments/configs/simulate.py, then prints where the video is and where
the time went. ``make demo`` runs it.
"""

import os

from absl import app
from absl import flags

from experiments import simulate as sim
from physsplat_jax import pipeline as pl
from physsplat_jax import scenes

_SCENE = flags.DEFINE_string('scene', 'tabletop',
                             'built-in scene (tabletop, ficus, donut) or PLY')
_OUT = flags.DEFINE_string('out', 'out/demo', 'output directory')
_FRAMES = flags.DEFINE_integer('frames', None, 'frames (default: config)')

DEMO_CONFIG = os.path.join(os.path.dirname(__file__), 'configs', 'demo.py')


def main(argv):
  del argv
  scene = scenes.load_scene(_SCENE.value)
  config = sim.build_config(scene.name, DEMO_CONFIG,
                            dict(num_frames=_FRAMES.value))
  _, report = pl.simulate_scene(scene, config, _OUT.value,
                                extra_report=dict(command='make demo'))
  print(pl.summary(report))
  print(f'\nvideo: {report["files"].get("video")}')


if __name__ == '__main__':
  app.run(main)
