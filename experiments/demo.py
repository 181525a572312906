"""Interim demo: build a scene, render an orbit, write PNG frames and a video.

  python -m experiments.demo --scene=tabletop --out=out/demo

``--scene`` is a built-in name (``tabletop``, ``ficus``, ``donut``) or a 3DGS
``.ply`` / ``.splat`` file or output folder (see ``physsplat_jax.io.scene``).
Writes ``<out>/frames/frame_0000.png``..., ``<out>/orbit.mp4`` (a GIF if no
ffmpeg is available) and ``<out>/scene.ply`` (+ ``scene.scene.json``). The
full pipeline (simulation) will replace the orbit.
"""

from __future__ import annotations

import os
import time

from absl import app
from absl import flags
from absl import logging

from physsplat_jax.io import video
from physsplat_jax.io.scene import load_scene, save_scene
from physsplat_jax.render import render_image

_SCENE = flags.DEFINE_string('scene', 'tabletop', 'Built-in name or path.')
_OUT = flags.DEFINE_string('out', 'out/demo', 'Output folder.')
_FRAMES = flags.DEFINE_integer('frames', 24, 'Orbit frames.')
_WIDTH = flags.DEFINE_integer('width', 384, 'Image width [px].')
_HEIGHT = flags.DEFINE_integer('height', 288, 'Image height [px].')
_FPS = flags.DEFINE_float('fps', 12.0, 'Video frame rate.')
_BACKGROUND = flags.DEFINE_list('background', ['0.92', '0.93', '0.95'],
                                'Background RGB in [0, 1].')


def main(argv):
  del argv
  t0 = time.perf_counter()
  scene = load_scene(_SCENE.value, num_cameras=_FRAMES.value,
                     width=_WIDTH.value, height=_HEIGHT.value)
  logging.info('scene %s: %d Gaussians, objects %s', scene.name,
               scene.gaussians.num, scene.object_names)
  ply = os.path.join(_OUT.value, 'scene.ply')
  sidecar = save_scene(ply, scene)
  step = max(1, len(scene.cameras) // _FRAMES.value)
  # Camera names are static jit arguments: drop them to compile once.
  cams = [c.replace(name='') for c in scene.cameras[::step][:_FRAMES.value]]
  bg = tuple(float(x) for x in _BACKGROUND.value)
  frames_dir = os.path.join(_OUT.value, 'frames')
  with video.PngFrameWriter(frames_dir) as pngs, video.VideoWriter(
    os.path.join(_OUT.value, 'orbit.mp4'), _FPS.value
  ) as mp4:
    for i, cam in enumerate(cams):
      img = render_image(scene.gaussians, cam, background=bg).image
      pngs.append(img)
      mp4.append(img)
      logging.log_every_n(logging.INFO, 'frame %d/%d', 6, i + 1, len(cams))
  print(f'scene {scene.name!r} ({scene.gaussians.num} Gaussians, objects '
        f'{", ".join(scene.object_names)}) in '
        f'{time.perf_counter() - t0:.1f} s; wrote:')
  print(f'  {ply} and {sidecar}')
  print(f'  {pngs.num_frames} frames {frames_dir}/frame_0000.png ...')
  print(f'  {mp4.path} ({mp4.format}, {mp4.num_frames} frames)')


if __name__ == '__main__':
  app.run(main)
