"""What ``experiments/simulate.py`` and ``experiments/demo.py`` do, as
importable, tested functions: parse the motion shorthands, layer the config
(file < scene motion < command line), validate every input before any
expensive work, and run the pipeline or a PhysGaussian config."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import time
from typing import Any, Sequence

from absl import app
from absl import flags
from absl import logging
from ml_collections import config_flags

from physsplat_jax import cameras
from physsplat_jax import mpdp
from physsplat_jax import perception
from physsplat_jax import physgaussian
from physsplat_jax import pipeline as pl
from physsplat_jax import scenes
from physsplat_jax.io import outputs
from physsplat_jax.io import segment_inputs

DEFAULT_CONFIG = os.path.join(os.path.dirname(os.path.dirname(__file__)),
                              'configs', 'simulate.py')


def _vec(text: str, what: str, n: int = 3) -> tuple[float, ...]:
  try:
    v = tuple(float(c) for c in text.split(','))
  except ValueError:
    v = ()
  if len(v) != n or not all(abs(c) < float('inf') for c in v):
    raise app.UsageError(f'{what}: expected {n} comma-separated finite '
                         f'numbers, got {text!r}')
  return v


def _number(text: str, what: str) -> float:
  try:
    v = float(text)
  except ValueError:
    v = float('nan')
  if not abs(v) < float('inf'):
    raise app.UsageError(f'{what}: expected a finite number, got {text!r}')
  return v


def _split_name(item: str, flag: str) -> tuple[str, str]:
  if ':' not in item:
    raise app.UsageError(f'--{flag}={item!r}: expected NAME:values')
  name, rest = item.split(':', 1)
  return ('' if name in ('*', '') else name), rest


def _poke(item: str) -> dict:
  name, rest = _split_name(item, 'poke')
  parts = rest.split('@')
  if len(parts) < 2 or '/' not in parts[1]:
    raise app.UsageError(f'--poke={item!r}: expected '
                         'NAME:ax,ay,az@x,y,z/r[@t0-t1]')
  point, radius = parts[1].split('/', 1)
  t0, t1 = 0.0, 0.25
  if len(parts) > 2:
    t0, t1 = _vec(parts[2].replace('-', ',', 1), f'--poke {item} time', 2)
  return dict(kind='point', object=name,
              vector=_vec(parts[0], f'--poke {item} acceleration'),
              point=_vec(point, f'--poke {item} point'),
              radius=_number(radius, f'--poke {item} radius'),
              start=t0, end=t1)


def motion_from_flags(velocity=(), impulse=(), poke=()) -> dict:
  """Pipeline-config fields from --velocity/--impulse/--poke values."""
  out: dict[str, Any] = {}
  if velocity:
    out['initial_velocity'] = [
      (n, _vec(v, f'--velocity {n or "*"}'))
      for n, v in (_split_name(i, 'velocity') for i in velocity)]
  forces = []
  for item in impulse or ():
    name, rest = _split_name(item, 'impulse')
    vec, _, t = rest.partition('@')
    forces.append(dict(kind='impulse', object=name,
                       vector=_vec(vec, f'--impulse {item}'),
                       start=_number(t or '0', f'--impulse {item} time')))
  forces += [_poke(item) for item in poke or ()]
  if forces:
    out['forces'] = forces
  return out


def load_config_file(path: str | None = None) -> tuple[dict, dict]:
  """``(get_config() as a dict, SCENE_MOTIONS)`` of a .py config file."""
  path = path or DEFAULT_CONFIG
  if not os.path.exists(path):
    raise app.UsageError(f'--config={path!r}: no such .py config file')
  spec = importlib.util.spec_from_file_location('_sim_config', path)
  mod = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(mod)
  return dict(mod.get_config().to_dict()), getattr(mod, 'SCENE_MOTIONS', {})


def flag_motions(flag: str = 'config', fallback: bool = False) -> dict:
  """The ``SCENE_MOTIONS`` of the .py file given as ``--flag``; with
  ``fallback``, experiments/configs/simulate.py's where that file has
  none."""
  path = config_flags.get_config_filename(flags.FLAGS[flag])
  motions = load_config_file(path)[1]
  return motions or (load_config_file()[1] if fallback else {})


def build_config(scene_name: str, config: Any = None, overrides=None,
                 motion=None, motions=None) -> pl.PipelineConfig:
  """Config defaults < scene motion < command-line overrides.

  Args:
    scene_name: picks the scene's motion from ``motions``.
    config: a config dict / ConfigDict, or a .py path (default
      experiments/configs/simulate.py, whose SCENE_MOTIONS are used).
    overrides: fields to set (None values keep the config's).
    motion: fields from the motion flags; empty uses the scene's motion.
    motions: scene name -> motion fields (default: the config file's).
  """
  if config is None or isinstance(config, str):
    d, file_motions = load_config_file(config)
  else:
    d = dict(config.to_dict() if hasattr(config, 'to_dict') else config)
    file_motions = {}
  motions = file_motions if motions is None else motions
  if not motion:
    motion = motions.get(scene_name, {})
  d.update(motion)
  d.update({k: v for k, v in (overrides or {}).items() if v is not None})
  return pl.config_from_dict(d)


def check_scene_objects(scene, objects: Sequence[str], config) -> None:
  """Every object name the command line gives exists (before any work)."""
  known = [o.name for o in scene.objects]
  named = list(objects or ())
  named += [n for n, _ in config.initial_velocity if n]
  named += [f.object for f in config.forces if f.object]
  bad = sorted({n for n in named if n not in known})
  if bad:
    raise pl.PipelineError(
      f'object(s) {bad} are not in scene {scene.name!r}; its objects are '
      f'{known}.')


def check_overrides(scene, overrides) -> None:
  """Every ``--material_override`` names an object of the scene."""
  known = [o.name for o in scene.objects]
  keys = set(known) | {str(i) for i in range(len(known))} | {'*'}
  bad = sorted(set(overrides or {}) - keys)
  if bad:
    raise pl.PipelineError(
      f'--material_override names {bad}, which are not objects of scene '
      f'{scene.name!r}; its objects are {known} (or use an index, or *).')


def perception_options_from_flags():
  """:class:`perception.PerceptionOptions` from the flags; a malformed
  value is a usage error naming the flag."""
  try:
    return perception.options_from_flags()
  except ValueError as e:
    raise app.UsageError(str(e)) from None


def load_mpdp(path: str | None):
  """MPDP params from a checkpoint folder (``save_params`` layout), or None
  for the shipped weights."""
  if not path:
    return None
  try:
    params, cfg, _ = mpdp.load_params(path)
  except ValueError as e:
    raise pl.PipelineError(f'--mpdp_checkpoint={path!r}: {e}') from None
  if cfg != mpdp.ModelConfig():
    raise pl.PipelineError(
      f'--mpdp_checkpoint={path!r} holds a network of another architecture '
      f'({cfg}); the pipeline runs the default ModelConfig().')
  return params


def run_scene(scene_name: str, config: pl.PipelineConfig, out: str, *,
              objects: Sequence[str] = (), ply: bool = False,
              spz: bool = False,
              segment: str | None = None, boxes: str | None = None,
              masks: str | None = None,
              mask_names: Sequence[str] | None = None,
              perception_options=None,
              extra_report: dict | None = None,
              scene_options: dict | None = None,
              mpdp_checkpoint: str | None = None,
              pipelined: bool = True, on_frame=None,
              process: dict | None = None) -> dict:
  """The pipeline on a built-in scene or a scene file; the report.

  ``scene_options`` go to :func:`physsplat_jax.load_scene` for a scene file
  (``up_axis``, ``meters_per_unit``, ...); ``mpdp_checkpoint`` is a folder of
  MPDP weights to use instead of the shipped ones; ``on_frame`` is called
  after each frame (``pipeline.run``). ``process`` (``start_s``: seconds
  from the process's start to the script's ``main``, ``main_t0``: its
  ``time.perf_counter()`` there) adds the report's ``process_seconds``: the
  start (Python, imports), the setup before the pipeline (config, JAX's
  backend, reading the scene) and, with ``segment``, the segmentation
  (``segment``: reading its files, lifting masks). ``boxes`` (a JSON file)
  and ``masks`` (a folder of label images, objects named ``mask_names``)
  are read by :mod:`physsplat_jax.io.segment_inputs`; either implies its
  ``segment`` method when ``segment`` is None.
  """
  outputs.check_output_dir(out)
  mpdp_params = load_mpdp(mpdp_checkpoint)
  options = {k: v for k, v in (scene_options or {}).items() if v is not None}
  if options and scene_name in scenes.list_scenes():
    raise app.UsageError(f'{sorted(options)} apply to scene files; the '
                         f'built-in scene {scene_name!r} is already in metres, '
                         'z up.')
  if scene_name not in scenes.list_scenes():
    options['details'] = details = {}
  scene = scenes.load_scene(scene_name, **options)
  if 'details' in options:
    extra_report = {**(extra_report or {}), 'scene_frame': dict(
      details, meters_per_unit=scene.meters_per_unit)}
  t_seg = time.perf_counter()
  inputs = {}
  if boxes is not None:
    segment = segment or 'boxes'
    inputs = segment_inputs.load_boxes(boxes)
  if masks is not None:
    segment = segment or 'masks'
    if options.get('details', {}).get('cameras') == 'fitted':
      raise pl.PipelineError(
        f'--masks={masks}: scene {scene_name} has no cameras of its own (an '
        'orbit was fitted), so no mask can be placed; put the capture\'s '
        'cameras.json (INRIA) or transforms.json beside the PLY, or give '
        'the INRIA output folder as --scene')
    cams, label_masks, names = segment_inputs.load_masks(
      masks, scene.cameras, mask_names)
    logging.info('masks: %d views, objects %s', len(cams), ', '.join(names))
    inputs = dict(cameras=cams, masks=label_masks, names=names)
  scene = pl.segment_stage(scene, segment, **inputs)
  t_seg = time.perf_counter() - t_seg
  check_scene_objects(scene, objects, config)
  if objects:
    scene = pl.select_objects(scene, objects)
  if perception_options is not None:
    check_overrides(scene, perception_options.overrides)
  try:  # the camera is checked before any expensive work
    cameras.scene_camera(scene, config.width, config.height,
                         config.camera_index)
  except ValueError as e:
    raise pl.PipelineError(f'--config.camera_index: {e}') from None
  if process is not None:
    extra_report = {**(extra_report or {}), 'process_seconds': dict(
      start=None if process.get('start_s') is None
      else round(process['start_s'], 3),
      setup=round(time.perf_counter() - process['main_t0'] - t_seg, 3))}
    if segment is not None:
      extra_report['process_seconds']['segment'] = round(t_seg, 3)
  _, report = pl.simulate_scene(
    scene, config, out, perception_options=perception_options, ply=ply,
    spz=spz,
    extra_report=extra_report, mpdp_params=mpdp_params, pipelined=pipelined,
    on_frame=on_frame)
  return report


def run_physgaussian(scene_path: str, json_path: str, out: str,
                     config: pl.PipelineConfig, *, ply: bool = False,
                     spz: bool = False,
                     auto_substeps: bool = False,
                     num_frames: int | None = None) -> dict:
  """A PhysGaussian JSON config as PhysGaussian runs it; the report.

  Physics, frame count and camera come from the JSON (``num_frames``
  overrides its ``frame_num``); ``config`` gives the video size, filling
  and whether to render.
  """
  return physgaussian.run_config(
    scene_path, json_path, out, num_frames=num_frames,
    auto_substeps=auto_substeps, fill=config.fill,
    video=config.render != 'none', ply=ply, spz=spz, width=config.width,
    height=config.height)


def git_sha() -> str:
  """Short git SHA of this checkout, or 'unknown'."""
  try:
    return subprocess.check_output(
      ['git', 'rev-parse', '--short', 'HEAD'],
      cwd=os.path.dirname(os.path.abspath(__file__)),
      stderr=subprocess.DEVNULL).decode().strip()
  except (OSError, subprocess.CalledProcessError):
    return 'unknown'
