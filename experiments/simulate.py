"""Simulates a 3DGS scene and writes video, frames, trajectory and report.

The full pipeline (segmented scene -> perception -> MPDP -> PGAS -> MLS-MPM
-> deformed Gaussians -> renders)::

  python -m experiments.simulate --scene=tabletop --out=out/tabletop
  python -m experiments.simulate --scene=ficus --frames=24 --ply --out=out/f
  python -m experiments.simulate --scene=scene.ply --objects=donut \\
      --velocity=donut:0,0,-1 --material_override=donut=jelly --out=out/d

writes ``video.mp4``, ``frames/frame_%04d.png``, ``trajectory.npz``
(``x`` float32 (frames+1, K, 3) positions of the simulated Gaussians in the
input's coordinates, ``ids`` their rows, ``t`` seconds), ``report.json``
(materials and which path chose them, particle counts, time of every stage)
and, with ``--ply``, ``ply/frame_%04d.ply``.

With a PhysGaussian JSON config (``--config=cfg.json``) it runs that
config's physics as PhysGaussian does (every selected Gaussian is a
particle, normalised domain) and writes ``trajectory.npz``::

  python -m experiments.simulate --scene=PATH.ply --config=cfg.json --out=DIR

Settings: ``--config=experiments/configs/simulate.py`` (default) holds the
pipeline's defaults; flags override them. Material perception is offline
(library by object name) unless ``--mllm_base_url`` is given.
"""

import os
import subprocess
import sys
import types

import jax
import numpy as np
from absl import app
from absl import flags
from absl import logging

from physsplat_jax import perception
from physsplat_jax import pipeline as pl
from physsplat_jax import physgaussian as pg
from physsplat_jax.io import ply as ply_io
from physsplat_jax import scenes
from physsplat_jax import physgaussian as mpm_pg

def define_flags():
  """Defines the command-line flags (only when run as a script, so that
  importing this module never clashes with other scripts' flags)."""
  scene = flags.DEFINE_string(
    'scene', 'tabletop', 'built-in scene name (tabletop, ficus, donut) or a '
    '3DGS .ply/.splat path')
  config = flags.DEFINE_string(
    'config', None, 'pipeline config (.py with get_config(); default '
    'experiments/configs/simulate.py) or a PhysGaussian .json')
  out = flags.DEFINE_string('out', None, 'output directory')
  frames = flags.DEFINE_integer('frames', None, 'frames to simulate')
  fps = flags.DEFINE_float('fps', None, 'frames per second')
  grid = flags.DEFINE_integer('grid_res', None, 'MPM grid cells per axis')
  particles = flags.DEFINE_integer('max_particles', None,
                                    'upper bound on driving particles')
  substeps = flags.DEFINE_integer('substeps', None,
                                   'substeps per frame (default: CFL)')
  width = flags.DEFINE_integer('width', None, 'video width [px]')
  height = flags.DEFINE_integer('height', None, 'video height [px]')
  camera = flags.DEFINE_integer('camera', None,
                                 'scene camera index (-1: fitted)')
  sampling = flags.DEFINE_enum('sampling', None, ['pgas', 'uniform', 'kmeans'],
                                'driving-particle method')
  gravity = flags.DEFINE_float('gravity', None, 'gravity [m/s^2], 0 = off')
  no_mpdp = flags.DEFINE_bool('no_mpdp', False,
                               'uniform materials instead of MPDP fields')
  objects = flags.DEFINE_list(
    'objects', None, 'only these objects move (the others are fixed)')
  velocity = flags.DEFINE_multi_string(
    'velocity', None, 'NAME:vx,vy,vz initial velocity [m/s] ("*" = all)')
  impulse = flags.DEFINE_multi_string(
    'impulse', None, 'NAME:dvx,dvy,dvz[@t] velocity change over one frame')
  poke = flags.DEFINE_multi_string(
    'poke', None, 'NAME:ax,ay,az@x,y,z/r[@t0-t1] acceleration [m/s^2] of the '
    "object's particles within r [m] of a point (scene coordinates)")
  ply = flags.DEFINE_bool('ply', False, 'write per-frame PLY files')
  video = flags.DEFINE_bool('video', True, 'write video.mp4 and PNG frames')
  auto = flags.DEFINE_bool('auto_substeps', False, 'PhysGaussian configs: '
                            'replace an unstable substep_dt by a stable one')
  fill = flags.DEFINE_bool('fill', True, 'fill object interiors')
  perception.define_flags()
  return types.SimpleNamespace(
    scene=scene,
    config=config,
    out=out,
    frames=frames,
    fps=fps,
    grid=grid,
    particles=particles,
    substeps=substeps,
    width=width,
    height=height,
    camera=camera,
    sampling=sampling,
    gravity=gravity,
    objects=objects,
    velocity=velocity,
    impulse=impulse,
    poke=poke,
    ply=ply,
    video=video,
    auto=auto,
    fill=fill,
    no_mpdp=no_mpdp,
  )


DEFAULT_CONFIG = os.path.join(os.path.dirname(__file__), 'configs',
                              'simulate.py')


def _vec(text, what, n=3):
  try:
    v = tuple(float(c) for c in text.split(','))
  except ValueError:
    v = ()
  if len(v) != n:
    raise app.UsageError(f'{what}: expected {n} comma-separated numbers, '
                         f'got {text!r}')
  return v


def _split_name(item, flag):
  if ':' not in item:
    raise app.UsageError(f'--{flag}={item!r}: expected NAME:values')
  name, rest = item.split(':', 1)
  return ('' if name in ('*', '') else name), rest


def motion_from_flags(velocity=(), impulse=(), poke=()) -> dict:
  """Pipeline-config fields from --velocity/--impulse/--poke values."""
  out = {}
  if velocity:
    out['initial_velocity'] = [
      (n, _vec(v, f'--velocity {n}'))
      for n, v in (_split_name(i, 'velocity') for i in velocity)]
  forces = []
  for item in impulse or ():
    name, rest = _split_name(item, 'impulse')
    vec, _, t = rest.partition('@')
    forces.append(dict(kind='impulse', object=name,
                       vector=_vec(vec, f'--impulse {item}'),
                       start=float(t or 0.0)))
  for item in poke or ():
    name, rest = _split_name(item, 'poke')
    parts = rest.split('@')
    if len(parts) < 2 or '/' not in parts[1]:
      raise app.UsageError(f'--poke={item!r}: expected '
                           'NAME:ax,ay,az@x,y,z/r[@t0-t1]')
    point, radius = parts[1].split('/')
    t0, t1 = 0.0, 0.25
    if len(parts) > 2:
      t0, t1 = _vec(parts[2].replace('-', ',', 1), f'--poke {item} time', 2)
    forces.append(dict(kind='point', object=name,
                       vector=_vec(parts[0], f'--poke {item}'),
                       point=_vec(point, f'--poke {item} point'),
                       radius=float(radius), start=t0, end=t1))
  if forces:
    out['forces'] = forces
  return out


def load_pipeline_config(path=None) -> dict:
  """The ``get_config()`` dict of a .py config file."""
  import importlib.util

  path = path or DEFAULT_CONFIG
  spec = importlib.util.spec_from_file_location('_sim_config', path)
  if spec is None or not os.path.exists(path):
    raise app.UsageError(f'--config={path!r}: no such .py config file')
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return dict(mod.get_config().to_dict()), getattr(mod, 'SCENE_MOTIONS', {})


def simulate_file(scene: str, config: str, out: str, frames=None,
                  auto_substeps=False, fill=True, video=False, ply=False,
                  width=512, height=384, camera_index=0) -> str:
  """PhysGaussian mode: simulate a JSON config as PhysGaussian does.

  Writes ``out/trajectory.npz`` and ``out/report.json``; with ``video``
  also ``video.mp4`` and ``frames/`` (every Gaussian rendered, the simulated
  ones with ``Sigma' = F Sigma F^T`` and their SH view direction rotated by
  ``polar(F)``), with ``ply`` per-frame PLY files. Returns the trajectory
  path.
  """
  import json
  import time

  t0 = time.perf_counter()
  cfg = pg.load_config(config)
  gaussians = ply_io.load_ply(scene)
  os.makedirs(out, exist_ok=True)
  files = {}
  times = dict(render=0.0, write=0.0)
  cb = None
  writers = []
  if video or ply:
    import jax.numpy as jnp

    from physsplat_jax import deform
    from physsplat_jax.io import export
    from physsplat_jax.io import video as video_lib
    from physsplat_jax.render import raster

    # PhysGaussian removes Gaussians under opacity_threshold from the scene;
    # those outside sim_area stay, static.
    faint = np.asarray(gaussians.opacities) < cfg.opacity_threshold
    shown = gaussians.replace(opacity_logits=jnp.where(
      jnp.asarray(faint), -30.0, gaussians.opacity_logits))
    cam_scene = scenes.load_scene(scene)
    cam = pl.render_camera(cam_scene, pl.PipelineConfig(
      width=width, height=height, camera_index=camera_index))
    covs0 = gaussians.covariances
    state = {}

    @jax.jit
    def assemble(ids, x, F):
      c = F @ covs0[ids] @ jnp.swapaxes(F, -1, -2)
      eye = jnp.broadcast_to(jnp.eye(3, dtype=c.dtype), covs0.shape)
      return (gaussians.means.at[ids].set(x), covs0.at[ids].set(c),
              eye.at[ids].set(deform.polar_rotation(F)))

    if video:
      vw = video_lib.VideoWriter(os.path.join(out, 'video.mp4'), fps=1.0 /
                                 cfg.frame_dt)
      pw = video_lib.PngFrameWriter(os.path.join(out, 'frames'))
      writers += [vw, pw]
      files['frames'] = os.path.join(out, 'frames')

    def cb(f, x, F):
      t1 = time.perf_counter()
      ids = state.setdefault('ids', None)
      if ids is None:  # the selected rows: the Gaussians at their x
        # Exactly the selection of physgaussian.prepare_config.
        op = np.asarray(jax.nn.sigmoid(jnp.asarray(
          gaussians.opacity_logits, jnp.float32)), np.float64)
        ids = state['ids'] = jnp.asarray(pg.select_particles(
          cfg, np.asarray(gaussians.means, np.float64), op))
      means, covs, rots = assemble(ids, jnp.asarray(x), jnp.asarray(F))
      if video:
        img = raster.render_image(shown.replace(means=means), cam,
                                  background=(1.0, 1.0, 1.0),
                                  covariances=covs, view_rotations=rots)
        times['render'] += time.perf_counter() - t1
        t2 = time.perf_counter()
        frame = np.clip(img.image, 0.0, 1.0)
        vw.append(frame)
        pw.append(frame)
        times['write'] += time.perf_counter() - t2
      if ply:
        t2 = time.perf_counter()
        export.save_deformed_ply(
          os.path.join(out, 'ply', f'frame_{f:04d}.ply'), gaussians, means,
          covs, rots)
        files['ply'] = os.path.join(out, 'ply')
        times['write'] += time.perf_counter() - t2
      logging.log_every_n(logging.INFO, 'frame %d written', 1, f)

  try:
    x, ids, t = mpm_pg.simulate_config(
      gaussians, cfg, num_frames=frames, auto_substeps=auto_substeps,
      fill=fill, on_frame_F=cb)
  finally:
    for w in writers:
      w.close()
  if video:
    files['video'] = writers[0].path
  path = os.path.join(out, 'trajectory.npz')
  np.savez(path, x=x.astype(np.float32), ids=ids.astype(np.int64),
           t=t.astype(np.float64))
  files['trajectory'] = path
  times['total'] = time.perf_counter() - t0
  report = dict(scene=scene, config=config, material=cfg.material,
                num_gaussians=int(len(ids)), num_frames=int(len(t) - 1),
                stage_seconds={k: round(v, 3) for k, v in times.items()},
                files=files)
  with open(os.path.join(out, 'report.json'), 'w') as fh:
    json.dump(report, fh, indent=1)
  logging.info('wrote %s: x %s, %d Gaussians, t = 0..%.3g s (%.1f s)', path,
               x.shape, len(ids), t[-1], times['total'])
  return path


def build_config(scene_name: str, config_path=None, overrides=None,
                 motion=None) -> pl.PipelineConfig:
  """Config file defaults < scene motion < command-line overrides."""
  d, motions = load_pipeline_config(config_path)
  if not motion:
    motion = motions.get(scene_name, {})
  d.update(motion)
  d.update({k: v for k, v in (overrides or {}).items() if v is not None})
  return pl.config_from_dict(d)


def _git_sha() -> str:
  try:
    return subprocess.check_output(
      ['git', 'rev-parse', '--short', 'HEAD'],
      cwd=os.path.dirname(os.path.abspath(__file__)),
      stderr=subprocess.DEVNULL).decode().strip()
  except (OSError, subprocess.CalledProcessError):
    return 'unknown'


def main(argv, f=None):
  del argv
  f = f or _FLAGS
  if not f.out.value:
    raise app.UsageError('--out=DIR is required')
  sha = _git_sha()
  logging.info('devices %s, git %s', jax.devices(), sha)
  if f.config.value and f.config.value.endswith('.json'):
    simulate_file(f.scene.value, f.config.value, f.out.value, f.frames.value,
                  f.auto.value, f.fill.value, video=f.video.value,
                  ply=f.ply.value, width=f.width.value or 512,
                  height=f.height.value or 384,
                  camera_index=0 if f.camera.value is None else f.camera.value)
    return
  scene = scenes.load_scene(f.scene.value)
  if f.objects.value:
    scene = pl.select_objects(scene, f.objects.value)
  overrides = dict(
    num_frames=f.frames.value, fps=f.fps.value, grid_res=f.grid.value,
    max_particles=f.particles.value, substeps_per_frame=f.substeps.value,
    width=f.width.value, height=f.height.value, camera_index=f.camera.value,
    sampling=f.sampling.value, gravity=f.gravity.value, fill=f.fill.value,
    use_mpdp=False if f.no_mpdp.value else None,
    render=None if f.video.value else 'none')
  motion = motion_from_flags(f.velocity.value, f.impulse.value, f.poke.value)
  config = build_config(scene.name, f.config.value, overrides, motion)
  options = perception.options_from_flags()
  _, report = pl.simulate_scene(
    scene, config, f.out.value, perception_options=options, ply=f.ply.value,
    extra_report=dict(command=' '.join(sys.argv), git=sha))
  print(pl.summary(report))


_FLAGS = None

if __name__ == '__main__':
  _FLAGS = define_flags()
  app.run(main)
