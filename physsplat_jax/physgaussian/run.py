"""Runs a PhysGaussian config on a scene file and writes its outputs.

PhysGaussian mode of ``experiments/simulate.py``: every selected Gaussian
is a particle in the normalised domain (:mod:`.driver`); each frame goes
to the :mod:`physsplat_jax.io.outputs` writers (video and PNG frames with
every Gaussian rendered, the simulated ones with ``Sigma' = F Sigma F^T``
and their SH view direction rotated by ``polar(F)``, from the config's
camera (:mod:`.camera`: a dataset camera, or PhysGaussian's orbit, moving
with ``move_camera``); per-frame PLY or .spz; ``trajectory.npz``) and
``report.json`` is written, also when the run fails.
"""

from __future__ import annotations

import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import logging

from physsplat_jax import cameras as cam_lib
from physsplat_jax import deform
from physsplat_jax.io import outputs as out_lib
from physsplat_jax.io import ply as ply_io
from physsplat_jax.io import scene as scene_io
from physsplat_jax.physgaussian import camera as camera_lib
from physsplat_jax.physgaussian import driver
from physsplat_jax.physgaussian import schema
from physsplat_jax.physgaussian import transform
from physsplat_jax.render import images


def _selected_rows(cfg, gaussians) -> np.ndarray:
  """Exactly the selection of :func:`driver.prepare_config`."""
  op = np.asarray(jax.nn.sigmoid(jnp.asarray(
    gaussians.opacity_logits, jnp.float32)), np.float64)
  return transform.select_particles(
    cfg, np.asarray(gaussians.means, np.float64), op)


class _Frames:
  """Builds the :class:`~physsplat_jax.io.outputs.Frame` of each step."""

  def __init__(self, cfg, gaussians, rows, camera, render: bool,
               need_all: bool):
    self.cfg, self.gaussians = cfg, gaussians
    self.camera = camera  # a Camera, or frame -> Camera
    self.render, self.need_all = render, need_all or render
    # PhysGaussian removes Gaussians under opacity_threshold from the
    # scene; those outside sim_area stay, static.
    faint = np.asarray(gaussians.opacities) < cfg.opacity_threshold
    self.shown = gaussians.replace(opacity_logits=jnp.where(
      jnp.asarray(faint), -30.0, gaussians.opacity_logits))
    self.ids = jnp.asarray(rows)
    covs0 = gaussians.covariances

    @jax.jit
    def assemble(ids, x, F):
      c = F @ covs0[ids] @ jnp.swapaxes(F, -1, -2)
      eye = jnp.broadcast_to(jnp.eye(3, dtype=c.dtype), covs0.shape)
      return (gaussians.means.at[ids].set(x), covs0.at[ids].set(c),
              eye.at[ids].set(deform.polar_rotation(F)))

    self.assemble = assemble

  def __call__(self, f: int, x, F) -> out_lib.Frame:
    frame = out_lib.Frame(index=f, time=f * self.cfg.frame_dt,
                          positions=np.asarray(x, np.float32))
    if self.need_all:
      means, covs, rots = self.assemble(self.ids, jnp.asarray(x),
                                        jnp.asarray(F))
      frame.gaussians = self.gaussians.replace(means=means)
      frame.covariances, frame.rotations = covs, rots
      if self.render:
        cam = self.camera(f) if callable(self.camera) else self.camera
        # Without render_image's input checks: the Gaussians were checked
        # once at loading and the positions by the run's stability checks.
        img = images.render_image_async(
          self.shown.replace(means=means), cam,
          background=(1.0, 1.0, 1.0), covariances=covs,
          view_rotations=rots).result()
        frame.image = np.clip(img.image, 0.0, 1.0)
    return frame


def _camera(cfg, scene, gaussians, rows, width, height, camera_index,
            report):
  """The render camera: a Camera, or frame -> Camera for an orbit."""
  index = cfg.camera.default_camera_index if camera_index is None else (
    camera_index)
  base = cam_lib.scene_camera(scene, width, height, max(index, 0))
  centre, axes = camera_lib.viewpoint(cfg, driver.transform_host(
    cfg, np.asarray(gaussians.means, np.float64)[rows]))
  if cfg.camera.show_hint:
    hint = camera_lib.camera_hint(base, centre, axes)
    report['camera_hint'] = hint
    logging.info('show_hint: camera %d has azimuth %.3f, elevation %.3f, '
                 'radius %.4g about the viewpoint centre (init_azimuthm, '
                 'init_elevation, init_radius)', max(index, 0),
                 hint['init_azimuthm'], hint['init_elevation'],
                 hint['init_radius'])
  if index >= 0:
    return base
  report['camera'] = dict(
    path='moving orbit' if cfg.camera.move_camera else 'orbit',
    first=camera_lib.frame_angles(cfg, 0))
  camera_lib.frame_camera(cfg, base, centre, axes, 0)  # checks the radius
  return lambda f: camera_lib.frame_camera(cfg, base, centre, axes, f)


@out_lib.holds_output_dir('report.json')
def run_config(scene_path: str, config_path: str, out_dir: str, *,
               num_frames: int | None = None, auto_substeps: bool = False,
               fill: bool = True, video: bool = False, ply: bool = False,
               spz: bool = False,
               width: int = 512, height: int = 384,
               camera_index: int | None = None) -> dict:
  """Simulates ``config_path`` on ``scene_path`` as PhysGaussian does.

  Writes ``out_dir/trajectory.npz`` (``x`` (T+1, K, 3) float32 positions of
  the selected Gaussians in the scene's coordinates, ``ids`` their rows,
  ``t`` seconds) and ``report.json``; with ``video`` also ``video.mp4`` and
  ``frames/``, with ``ply`` ``ply/frame_%04d.ply``, with ``spz``
  ``spz/frame_%04d.spz``. The camera is the
  config's (``default_camera_index``, or its orbit for -1; see
  :mod:`.camera`) unless ``camera_index`` names a scene camera.

  Returns:
    The report dict (``files`` names what was written).
  """
  t0 = time.perf_counter()
  report = dict(scene=scene_path, config=config_path)
  times = dict(simulate_and_write=0.0)
  writers = []
  try:
    cfg = schema.load_config(config_path)
    gaussians = ply_io.load_ply(scene_path)
    report['material'] = cfg.material
    rows = _selected_rows(cfg, gaussians)
    camera = None
    if video or cfg.camera.show_hint:
      scene = scene_io.load_scene(scene_path)
      camera = _camera(cfg, scene, gaussians, rows, width, height,
                       camera_index, report)
    if video:
      writers += [
        out_lib.VideoOutput(os.path.join(out_dir, 'video.mp4'),
                            1.0 / cfg.frame_dt),
        out_lib.PngOutput(os.path.join(out_dir, 'frames'))]
    for kind, on in ((out_lib.PlyOutput, ply), (out_lib.SpzOutput, spz)):
      if on:
        writers.append(kind(os.path.join(out_dir, kind.format), gaussians))
    writers.append(out_lib.TrajectoryOutput(
      os.path.join(out_dir, 'trajectory.npz'), rows))
    make = _Frames(cfg, gaussians, rows, camera, video, ply or spz)
    sink = out_lib.BackgroundWriters(writers)  # encoded on writer threads

    def on_frame(f, x, F):
      sink.write(make(f, x, F))
      logging.log_every_n(logging.INFO, 'frame %d queued for writing', 1, f)

    t1 = time.perf_counter()
    try:
      _, ids, t = driver.simulate_config(
        gaussians, cfg, num_frames=num_frames, auto_substeps=auto_substeps,
        fill=fill, on_frame_F=on_frame)
    except BaseException:
      out_lib.close_after_failure(sink)  # (the simulation's error wins)
      raise
    report['files'] = sink.close()
    times['simulate_and_write'] = time.perf_counter() - t1
    report.update(num_gaussians=int(len(ids)), num_frames=int(len(t) - 1))
  except BaseException as e:
    report['error'] = f'{type(e).__name__}: {e}' if str(e) else type(e).__name__
    times['total'] = time.perf_counter() - t0
    report['stage_seconds'] = {k: round(v, 3) for k, v in times.items()}
    out_lib.write_failure_report(os.path.join(out_dir, 'report.json'),
                                 report)
    raise
  times['total'] = time.perf_counter() - t0
  report['stage_seconds'] = {k: round(v, 3) for k, v in times.items()}
  path = out_lib.write_json(os.path.join(out_dir, 'report.json'), report)
  report.setdefault('files', {})['report'] = path
  logging.info('wrote %s: %d Gaussians, %d frames (%.1f s)', out_dir,
               report['num_gaussians'], report['num_frames'], times['total'])
  return report
