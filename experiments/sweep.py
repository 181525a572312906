"""A parameter sweep of the pipeline, sharded over devices and hosts.

Every item of the sweep is one ``pipeline.simulate`` run of the same
prepared scene with its own material multipliers and initial velocity
(the Cartesian product of the flags)::

  python -m experiments.sweep --scene=tabletop --e_scale=0.3,1,3 \\
      --velocity='0,0,1;0,0,2' --frames=12 --out=out/sweep

  # 4 fake devices on one CPU (checks the sharding, no speed-up):
  python -m experiments.sweep ... --cpu_devices=4

  # two processes on one machine (or one per host with its address):
  python -m experiments.sweep ... --coordinator_address=127.0.0.1:12355 \\
      --num_processes=2 --process_id=0   # and --process_id=1

  # Slurm: one process per GPU, everything auto-detected (docs/distributed.md)
  srun python -m experiments.sweep ...

``--mode=batch`` (default) splits the items over all devices of the job
(``distributed.make_simulate_batch``); ``--mode=particles`` runs the items
one after another, each with its driving particles split over all devices
(``distributed.simulate_sharded``: one large simulation). Process 0 writes
``sweep.npz`` (``means`` (B, T+1, K, 3) float32 simulated Gaussian centres,
``com`` (B, T+1, 3) the plain mean of those centres (every Gaussian of
the scene counts alike: not a mass-weighted centre), scene coordinates;
``t`` (T+1,) seconds) and ``sweep.json`` (the items, devices, processes,
compile and run seconds, ``final_com``: the last frame's ``com``).
Material perception is the offline library by object name.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import sys
import time
from typing import Any, Sequence

import numpy as np
from absl import app
from absl import flags
from absl import logging

from experiments.lib import cli
from physsplat_jax.distributed import runtime
from physsplat_jax.io import outputs
from physsplat_jax.io import paths

MODES = ('batch', 'particles')


@dataclasses.dataclass
class SweepResult:
  """Output of :func:`run_sweep` (NumPy, on every process).

  Attributes:
    table: one dict of settings per item (``sweep_params``).
    means: (B, T+1, K, 3) simulated Gaussian centres (scene coordinates).
    x: (B, T+1, N, 3) driving particles (scene coordinates).
    compile_s: seconds to compile.
    run_s: seconds to simulate every item (compiled).
    mode: 'batch' or 'particles'.
  """

  table: list[dict[str, Any]]
  means: np.ndarray
  x: np.ndarray
  compile_s: float
  run_s: float
  mode: str


def parse_velocities(text: str | None) -> list[tuple[float, float, float]]:
  """``'0,0,1;0,0,2'`` -> [(0, 0, 1), (0, 0, 2)] [m/s]; '' or None -> []."""
  out = []
  for item in (text or '').split(';'):
    if not item.strip():
      continue
    try:
      v = tuple(float(c) for c in item.split(','))
    except ValueError:
      v = ()
    if len(v) != 3:
      raise ValueError(f'--velocity: {item!r} is not 3 comma-separated '
                       "numbers; write e.g. --velocity='0,0,1;0.5,0,1'.")
    out.append(v)
  return out


def run_sweep(prepared, params, config, mesh, E_scale: Sequence[float] = (
    1.0,), nu_scale: Sequence[float] = (1.0,),
              rho_scale: Sequence[float] = (1.0,),
              velocity: Sequence[Sequence[float]] | None = None,
              mode: str = 'batch') -> SweepResult:
  """Simulates every item of the sweep on ``mesh`` (all processes call it).

  Args:
    prepared, params, config: one prepared scene, its base parameters and
      pipeline config (``render`` should be 'none').
    mesh: a one-axis device mesh over the job (``distributed.make_mesh``).
    E_scale, nu_scale, rho_scale, velocity: see ``sweep_params``.
    mode: 'batch' (items split over devices) or 'particles' (items one by
      one, particles split over devices).

  Returns:
    :class:`SweepResult`.
  """
  import jax

  from physsplat_jax import distributed as dist

  if mode not in MODES:
    raise ValueError(f'mode = {mode!r}; use one of {MODES}.')
  batch, table = dist.sweep_params(params, E_scale, nu_scale, rho_scale,
                                   velocity)
  sel = lambda t: (t.means, t.x)  # noqa: E731
  if mode == 'batch':
    fn = dist.make_simulate_batch(config, mesh, select=sel)
    args, n = fn.place(batch, prepared)
    t0 = time.perf_counter()
    compiled = fn.jitted.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    run_s = time.perf_counter() - t0
    means, x = (a[:n] for a in dist.to_host(out))
  else:
    items = [jax.tree.map(lambda a, i=i: a[i], batch.replace(mpdp=None))
             .replace(mpdp=batch.mpdp) for i in range(len(table))]
    rep = dist.replicated(mesh)
    placed_scene = dist.put(prepared, rep)
    placed = [dist.put(p, rep) for p in items]
    fn = jax.jit(lambda p, s: sel(dist.simulate_sharded(p, s, config, mesh)))
    t0 = time.perf_counter()
    compiled = fn.lower(placed[0], placed_scene).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    outs = [jax.block_until_ready(compiled(p, placed_scene)) for p in placed]
    run_s = time.perf_counter() - t0
    outs = dist.to_host(outs)
    means = np.stack([o[0] for o in outs])
    x = np.stack([o[1] for o in outs])
  return SweepResult(table=table, means=np.asarray(means),
                     x=np.asarray(x), compile_s=compile_s, run_s=run_s,
                     mode=mode)


def save_sweep(out_dir: str, result: SweepResult, frame_dt: float,
               extra: dict | None = None) -> dict[str, str]:
  """Writes ``sweep.npz`` and ``sweep.json``; returns their paths."""
  os.makedirs(out_dir, exist_ok=True)
  T = result.means.shape[1]
  npz = os.path.join(out_dir, 'sweep.npz')
  data = dict(means=result.means.astype(np.float32),
              com=result.means.mean(2).astype(np.float32),
              t=np.arange(T) * frame_dt)
  # (whole files or none: a full disk names the file, nothing half-written)
  paths.write_npz(npz, data, outputs.OutputError, what='sweep')
  report = dict(
    items=result.table, mode=result.mode, num_items=len(result.table),
    compile_s=round(result.compile_s, 3), run_s=round(result.run_s, 3),
    final_com=result.means[:, -1].mean(1).tolist(), **(extra or {}))
  js = os.path.join(out_dir, 'sweep.json')
  outputs.write_json(js, report)  # NaN: "nan"
  return dict(npz=npz, json=js)


def sweep_substeps(report, config, E_scale=(1.0,), nu_scale=(1.0,),
                   rho_scale=(1.0,), velocity=None) -> int | None:
  """Substeps per frame stable for every item of a sweep, or None when
  the prepared scene's own count already is.

  The items share one compiled program, hence one substep count, which
  ``prepare_scene`` chose for the unscaled materials: a stiffer or lighter
  item (E up, rho down, nu towards 0.5) or a faster one would blow up with
  it. The bound is ``prepare_scene``'s (CFL on the wave speed plus the
  initial and impulse speeds), with the largest wave-speed factor over the
  items.
  """

  from physsplat_jax.mpm import timestep
  from physsplat_jax.pipeline import prepare as prep_lib

  ts = report.time_step
  c_max, n0 = ts['max_wave_speed_m_s'], ts['substeps_per_frame']
  # The wave speed's factor for nu -> s nu (E and rho scale it as
  # sqrt(E / rho)), at the worst base nu (material values lie in [0, 0.49]).
  base_nu = np.linspace(0.0, 0.49, 50)
  nu_factor = max(float(np.max(
    timestep.wave_speed(1.0, np.minimum(base_nu * s, 0.499), 1.0)
    / timestep.wave_speed(1.0, base_nu, 1.0))) for s in nu_scale)
  factor = math.sqrt(max(E_scale) / min(rho_scale)) * max(nu_factor, 1.0)
  norm = lambda v: float(np.linalg.norm(v))  # noqa: E731
  # prepare_scene chose n0 for c_max + v0 (impulses included); the items'
  # velocities replace the initial ones, the impulses stay.
  v_init = max([norm(v) for _, v in config.initial_velocity] + [0.0])
  v0 = prep_lib.given_speed(config)
  v1 = max([norm(v) for v in velocity or ()] + [v_init]) + v0 - v_init
  speed0, speed1 = c_max + v0, c_max * factor + v1
  if speed0 <= 0 or speed1 <= speed0:
    return None
  # n0 was chosen for speed0 (and rounded up to its bucket): scaled by the
  # speeds it stays at or above the count the items need.
  return math.ceil(n0 * speed1 / speed0)


def prepare(scene_name: str, config_path: str | None, overrides: dict,
            scales: dict | None = None, velocity=None):
  """Loads, perceives (offline library) and prepares the scene; the arrays
  of process 0 are broadcast so that every process simulates the same
  bits (all processes call it). With the sweep's ``scales`` (``E_scale``,
  ``nu_scale``, ``rho_scale``) and ``velocity``, the substep count is the
  one stable for its stiffest, fastest item (:func:`sweep_substeps`)."""
  import jax
  from jax.experimental import multihost_utils

  from experiments.lib import simulate as sim
  from physsplat_jax import perception
  from physsplat_jax import pipeline as pl
  from physsplat_jax import scenes

  scene = scenes.load_scene(scene_name)
  config = sim.build_config(scene.name, config_path,
                            dict(overrides, render='none'))
  materials = perception.perceive_scene(scene)
  key = jax.random.PRNGKey(config.seed)
  prepared, report = pl.prepare_scene(key, scene, materials, config)
  need = sweep_substeps(report, config, velocity=velocity, **(scales or {}))
  if need is not None and config.substeps_per_frame is None:
    if need > config.max_substeps_per_frame:
      raise pl.PipelineError(
        f'sweep: its stiffest or fastest item needs {need} substeps per '
        f'frame (the scene itself {report.time_step["substeps_per_frame"]}), '
        f'over max_substeps_per_frame={config.max_substeps_per_frame}; narrow '
        '--e_scale/--nu_scale/--rho_scale or the velocities, or raise '
        'max_substeps_per_frame in a --config file.')
    logging.info('sweep: %d substeps per frame (the stiffest or fastest '
                 'item needs more than the scene\'s %d)', need,
                 report.time_step['substeps_per_frame'])
    config = dataclasses.replace(config, substeps_per_frame=need)
    prepared, _ = pl.prepare_scene(key, scene, materials, config)
  params = pl.init_params(prepared, config)
  if jax.process_count() > 1:
    multihost_utils.assert_equal(
      np.asarray(prepared.num_particles),
      'processes prepared different particle counts; run every process on '
      'the same scene file and code version.')
    prepared, params = multihost_utils.broadcast_one_to_all(
      (prepared, params))
  return prepared, params, config


def define_flags():
  """The sweep's flags and the multi-host flags (script use only)."""
  runtime.define_flags()
  flags.DEFINE_string('scene', 'tabletop', 'built-in scene name or a 3DGS '
                      '.ply/.splat/.spz path')
  flags.DEFINE_string('config', None, 'pipeline config .py (default '
                      'experiments/configs/simulate.py)')
  flags.DEFINE_string('out', None, 'output directory (process 0 writes)')
  flags.DEFINE_list('e_scale', ['1'], "multipliers of every object's E")
  flags.DEFINE_list('nu_scale', ['1'], 'multipliers of nu')
  flags.DEFINE_list('rho_scale', ['1'], 'multipliers of rho')
  flags.DEFINE_string('velocity', None, "initial velocities [m/s] given to "
                      "every object, ';'-separated: '0,0,1;0,0,2'")
  flags.DEFINE_enum('mode', 'batch', MODES, 'batch: items split over '
                    'devices; particles: one item at a time, particles '
                    'split over devices')
  flags.DEFINE_integer('num_devices', None, 'use the first N devices of the '
                       'job (default all)')
  flags.DEFINE_integer('frames', None, 'frames to simulate')
  flags.DEFINE_float('fps', None, 'frames per second')
  flags.DEFINE_integer('grid_res', None, 'MPM grid cells per axis')
  flags.DEFINE_integer('max_particles', None, 'driving particle budget')


def main(argv):
  del argv
  f = flags.FLAGS
  info = runtime.initialize_from_flags()  # before any JAX computation
  cli.catch_sigterm()  # (jax.distributed's preemption service took it)
  if not f.out:
    raise app.UsageError('--out=DIR is required')
  with contextlib.ExitStack() as held:
    if info.is_main:  # a bad or busy --out fails now, not after the sweep
      outputs.check_output_dir(f.out)
      held.enter_context(outputs.output_lock(f.out))
    _sweep(f, info)


def _sweep(f, info) -> None:
  """The sweep of ``main`` (the flags ``f``; process 0 holds ``--out``)."""
  import jax

  from physsplat_jax import distributed as dist

  try:
    velocity = parse_velocities(f.velocity) or None
  except ValueError as e:
    raise app.UsageError(str(e)) from None
  scales = {}
  for k in ('e_scale', 'nu_scale', 'rho_scale'):
    try:
      scales[k] = [float(v) for v in getattr(f, k)]
    except ValueError:
      scales[k] = [math.nan]
    if not all(math.isfinite(v) and v > 0 for v in scales[k]):
      # (before the substep estimate, which took their roots and logs)
      raise cli.usage_error(f'--{k}={",".join(getattr(f, k))}: give '
                            'numbers > 0 separated by commas')
  if f.num_devices is not None and not (
      1 <= f.num_devices <= jax.device_count()):
    raise cli.usage_error(
      f'--num_devices={f.num_devices}: give 1 to {jax.device_count()} '
      f'(the {jax.default_backend()} devices this run has), or leave it '
      'out to use them all; on a CPU, --cpu_devices=N splits it into N '
      'devices')
  logging.info('devices %s', jax.devices())
  overrides = dict(num_frames=f.frames, fps=f.fps, grid_res=f.grid_res,
                   max_particles=f.max_particles)
  prepared, params, config = prepare(
    f.scene, f.config, overrides, velocity=velocity,
    scales=dict(E_scale=scales['e_scale'], nu_scale=scales['nu_scale'],
                rho_scale=scales['rho_scale']))
  from physsplat_jax.mpdp import NU_MAX

  # (the deformable objects' means: a rigid body's nu is never used)
  deform = ~np.asarray(prepared.spec.rigid, bool)
  nus = np.asarray(prepared.means)[:, 1][deform]
  nu_max = float(nus.max()) if nus.size else 0.0
  if nu_max * max(scales['nu_scale']) > NU_MAX:
    raise cli.usage_error(
      f'--nu_scale={",".join(f.nu_scale)}: the largest Poisson ratio of the '
      f'scene ({nu_max:.3g}) times {max(scales["nu_scale"]):g} exceeds '
      f'{NU_MAX}, the largest one simulated (it would be clipped and the '
      f'sweep would record a value it did not run); use scales up to '
      f'{NU_MAX / nu_max:.3g}')
  axis = (dist.BATCH_AXIS if f.mode == 'batch' else dist.PARTICLE_AXIS)
  mesh = dist.make_mesh(f.num_devices, axis)
  result = run_sweep(prepared, params, config, mesh, scales['e_scale'],
                     scales['nu_scale'], scales['rho_scale'], velocity,
                     f.mode)
  logging.info('%d items, mode %s: compile %.2f s, run %.2f s',
               len(result.table), f.mode, result.compile_s, result.run_s)
  finite = [bool(np.all(np.isfinite(m))) for m in result.means]
  for row, ok in zip(result.table, finite):
    row['finite'] = ok
  if info.is_main:
    files = save_sweep(f.out, result, config.frame_dt, dict(
      scene=f.scene, devices=[str(d) for d in jax.devices()],
      process_count=info.process_count, num_particles=prepared.num_particles,
      command=' '.join(sys.argv)))
    print(f'{len(result.table)} items on {mesh.size} devices '
          f'({info.process_count} processes): compile '
          f'{result.compile_s:.1f} s, run {result.run_s:.1f} s -> '
          f'{files["npz"]}')
  bad = [row for row in result.table if not row['finite']]
  if bad:
    from physsplat_jax.pipeline import PipelineError

    raise PipelineError(
      f'sweep: {len(bad)} of {len(result.table)} items went non-finite '
      f'(e.g. {bad[0]}; "finite": false in sweep.json, their rows NaN) '
      f'with {prepared.spec.substeps_per_frame} substeps per frame: narrow '
      '--e_scale/--nu_scale/--rho_scale or lower --velocity, or give more '
      'substeps (substeps_per_frame in a --config file).')


if __name__ == '__main__':
  define_flags()
  cli.run(main)
