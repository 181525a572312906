"""`make demo` settings: the simulate defaults, sized for a 2-core CPU.

The per-scene motions come from experiments/configs/simulate.py.
"""

from experiments.configs import simulate as base

SCENE_MOTIONS = base.SCENE_MOTIONS


def get_config():
  c = base.get_config()
  c.num_frames = 36
  c.fps = 24.0
  c.grid_res = 32
  c.max_particles = 6_000
  c.width = 480
  c.height = 360
  return c
