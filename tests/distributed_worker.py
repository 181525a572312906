"""Helper process for the distributed tests (not collected by pytest).

Runs sharded computations next to their single-device references and
writes what it measured (max errors, scales, seconds) as JSON to ``--out``.
The tests launch it in a fresh interpreter because the device count is
fixed when JAX starts:

  XLA_FLAGS=--xla_force_host_platform_device_count=4 \\
    python tests/distributed_worker.py --checks=particles,sweep,grad \\
    --out=r.json

  # two processes over loopback (gloo), 2 CPU devices each:
  python tests/distributed_worker.py --checks=multiprocess --cpu_devices=2 \\
    --coordinator_address=127.0.0.1:PORT --num_processes=2 --process_id=I \\
    --out=r_I.json

Checks:
  particles     mpm rollout with particles split over 4 devices vs one
                device (float64; two elastic models + a rigid body, a total
                PointForce, a ParticleImpulse, a sticky floor, 301
                particles: 3 ghosts); and a control without the psum,
                which must disagree.
  particles_grad  d(loss)/d(E scale, v0) of that rollout, 4 devices vs one
                (slow: ~80 s of compilation on 2 cores).
  sweep         pipeline.simulate over a batch of Params (E, velocity)
                for one scene (experiments/sweep.py run_sweep), and over a
                batch of 4 stacked scenes, split over 4 devices, vs the
                unsharded vmap; two items again with their particles split
                over 4 devices (simulate_sharded).
  grad          gradient of the mean MPDP trajectory loss over a batch of 4
                scenes, batch split over 4 devices, vs one device (slow).
  helpers       sharded_vmap and sharded_value_and_grad on 1 and 5 items
                (padded to 4 and 8) vs the unsharded vmap.
  multiprocess  (2 processes) batch sweep of mpm.rollout over E and a
                particle-sharded rollout with a rigid body on the global
                mesh of both processes, vs this process's single device.
"""

import functools
import json
import os
import sys
import time
import traceback

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(
  __file__))))

from absl import app  # noqa: E402
from absl import flags  # noqa: E402

from physsplat_jax.distributed import runtime  # noqa: E402

runtime.define_flags()
_CHECKS = flags.DEFINE_list('checks', ['particles'], 'checks to run')
_OUT = flags.DEFINE_string('out', None, 'JSON output path')


def _max_err(a, b):
  import jax
  import numpy as np
  err, scale = 0.0, 0.0
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    x, y = np.asarray(x), np.asarray(y)
    if x.shape != y.shape:
      raise AssertionError(f'shapes differ: {x.shape} vs {y.shape}')
    if np.issubdtype(x.dtype, np.floating):
      err = max(err, float(np.max(np.abs(x - y), initial=0.0)))
      scale = max(scale, float(np.max(np.abs(x), initial=0.0)))
  return err, scale


# ------------------------------------------------------------------ scenes


def _mpm_setup(n=301, models=('fixed_corotated', 'rigid'),
               forces=True):
  """A block of up to three materials (the last may be a rigid body)
  thrown at a sticky floor."""
  import jax.numpy as jnp
  import numpy as np
  from physsplat_jax import mpm
  rng = np.random.default_rng(0)
  grid = mpm.GridSpec(res=16, lower=(0.0, 0.0, 0.0), size=1.0)
  x = rng.uniform(0.3, 0.6, (n, 3))
  rigid = models[-1] == 'rigid'
  mid = np.minimum(np.floor((x[:, 0] - 0.3) / 0.1), len(models) - 1)
  mid = mid.astype(np.int32)
  body = np.where(mid == len(models) - 1, 0, -1) if rigid else None
  bcs = [mpm.SurfaceCollider(point=(0.0, 0.0, 0.31), surface='sticky')]
  if forces:
    bcs += [mpm.PointForce(point=(0.45, 0.45, 0.45), radius=0.1,
                           force=(1.0, 0.0, 0.0), per_particle=False),
            mpm.ParticleImpulse(force=(0.0, 0.1, 0.0), num_dt=2,
                                point=(0.35, 0.45, 0.45),
                                size=(0.05, 0.1, 0.1))]
  dtype = 'float64' if jnp.zeros(()).dtype == jnp.float64 else 'float32'
  config = mpm.SimConfig(
    grid=grid, dt=2e-4, substeps_per_frame=4, num_frames=3, models=models,
    num_bodies=1 if rigid else 0, boundary_conditions=tuple(bcs),
    remat_frames=False, dtype=dtype)
  mat = mpm.make_materials(mid, 2e4, 0.3, 1000.0, config_models=models,
                           dtype=config.jnp_dtype)
  state = mpm.init_state(x, (0.0, 0.0, -1.0), (1 / 32) ** 3, mat, config,
                         body_id=body)
  return state, mat, config


@functools.lru_cache(maxsize=None)
def _pipeline_setup():
  """A tiny rubber cube thrown onto a fixed slab, prepared for simulate.

  The cube starts on the ground moving down at 1 m/s, so it is squashed
  within the first frames and its motion depends on its stiffness. With
  x64 enabled every floating array is converted to float64.
  """
  import jax
  import jax.numpy as jnp
  import numpy as np
  from physsplat_jax import pipeline as pl
  from physsplat_jax.types import Gaussians
  from physsplat_jax.types import ObjectInfo
  from physsplat_jax.types import Scene
  rng = np.random.default_rng(0)
  n = 150
  cube = rng.uniform(-0.03, 0.03, (n, 3)) + [0.0, 0.0, 0.032]
  slab = rng.uniform([-0.12, -0.12, -0.02], [0.12, 0.12, 0.0], (n, 3))
  m = np.concatenate([cube, slab])
  K = len(m)
  g = Gaussians(
    means=jnp.asarray(m, jnp.float32),
    log_scales=jnp.full((K, 3), np.log(0.004), jnp.float32),
    quats=jnp.tile(jnp.array([1.0, 0, 0, 0], jnp.float32), (K, 1)),
    opacity_logits=jnp.full((K,), 2.0, jnp.float32),
    sh=jnp.zeros((K, 1, 3), jnp.float32))
  scene = Scene(gaussians=g, object_ids=jnp.asarray(np.repeat([0, 1], n)),
                objects=(ObjectInfo('cube', 'rubber'),
                         ObjectInfo('table', 'wood', fixed=True)),
                up_axis='z', meters_per_unit=1.0, name='tiny')
  config = pl.PipelineConfig(
    grid_res=16, num_frames=3, fps=240.0, substeps_per_frame=None,
    sampling='kmeans', max_particles=64, particles_per_cell=2.0,
    use_mpdp=True, render='none', width=32, height=24, margin=1.5,
    fill=False, initial_velocity=(('', (0.0, 0.0, -1.0)),))
  mats = [pl.ObjectMaterial('fixed_corotated', 3e4, 0.3, 1000.0),
          pl.ObjectMaterial('rigid', 1e10, 0.3, 700.0, rigid=True)]
  prepared, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene, mats, config)
  params = pl.init_params(prepared, config)
  if jnp.zeros(()).dtype == jnp.float64:
    prepared = prepared.astype(jnp.float64)
    params = params.astype(jnp.float64)
  return prepared, params, config


def _scene_batch(prepared, num):
  """``num`` same-spec variants of a prepared scene (drivers nudged)."""
  import jax.numpy as jnp
  from physsplat_jax import distributed as dist
  dx = prepared.spec.dx
  items = []
  for i in range(num):
    shift = jnp.asarray([0.1 * i * dx, -0.05 * i * dx, 0.0],
                        prepared.x0.dtype)
    items.append(prepared.replace(x0=prepared.x0 + shift))
  return dist.stack_trees(items)


# ------------------------------------------------------------------ checks


def check_particles():
  import jax
  import jax.numpy as jnp
  from jax.sharding import PartitionSpec as P
  from physsplat_jax import distributed as dist
  from physsplat_jax import mpm
  from physsplat_jax.distributed import particles as dp
  state, mat, config = _mpm_setup()
  out = {'num_particles': int(state.num)}
  t0 = time.perf_counter()
  ref = jax.jit(lambda s, m: mpm.rollout(s, m, None, config))(state, mat)
  out['ref_s'] = time.perf_counter() - t0
  out['motion'] = float(jnp.max(jnp.abs(ref[1][-1] - ref[1][0])))
  out['rigid_particles'] = int(jnp.sum(state.body_id >= 0))
  mesh = dist.make_mesh(4, dist.PARTICLE_AXIS)
  t0 = time.perf_counter()
  res = jax.jit(lambda s, m: dist.rollout_sharded(s, m, None, config, mesh))(
    state, mat)
  out['d4_s'] = time.perf_counter() - t0
  out['d4_err'], out['scale'] = _max_err(ref, res)
  out['d4_x_err'], out['x_scale'] = _max_err(ref[1], res[1])
  out['d4_x_spec'] = str(res[1].sharding.spec)
  # Control: the same shards without the psum must not match.
  sp, mp = dp.pad_particles(state, mat, 4)
  spec = dp._state_specs(sp, dist.PARTICLE_AXIS)  # noqa: SLF001
  forces = mpm.make_forces(config, state.x.dtype)
  nopsum = jax.jit(jax.shard_map(
    lambda s, m, f: mpm.rollout(s, m, f, config, 1), mesh=mesh,
    in_specs=(spec, jax.tree.map(lambda _: P('particles'), mp),
              jax.tree.map(lambda _: P(), forces)),
    out_specs=(spec, P(None, 'particles'), P(None, 'particles'))))
  _, xs1, _ = nopsum(sp, mp, forces)
  out['nopsum_err'] = float(jnp.max(jnp.abs(
    xs1[1, :state.num] - ref[1][1])))
  out['frame1_motion'] = float(jnp.max(jnp.abs(ref[1][1] - ref[1][0])))
  return out


def check_particles_grad():
  """d(loss)/d(E scale, v0) through the psum-ed rollout vs one device."""
  import jax
  import jax.numpy as jnp
  import numpy as np
  from physsplat_jax import distributed as dist
  from physsplat_jax import mpm
  state, mat, config = _mpm_setup()
  w = jnp.asarray(np.random.default_rng(1).normal(size=state.x.shape),
                  state.x.dtype)

  def loss(theta, rollout_fn):
    m = mat.replace(E=mat.E * theta[0])
    s = state.replace(v=state.v + theta[1] * jnp.asarray([0.0, 0.0, 1.0],
                                                         state.x.dtype))
    final, _, _ = rollout_fn(s, m)
    return jnp.sum(final.x * w)

  theta = jnp.asarray([1.0, 0.0], state.x.dtype)
  out = {}
  mesh = dist.make_mesh(4, dist.PARTICLE_AXIS)
  fns = dict(
    ref=lambda s, m: mpm.rollout(s, m, None, config),
    d4=lambda s, m: dist.rollout_sharded(s, m, None, config, mesh))
  vals = {}
  for name, fn in fns.items():
    t0 = time.perf_counter()
    vals[name] = jax.jit(jax.value_and_grad(
      functools.partial(loss, rollout_fn=fn)))(theta)
    out[f'{name}_s'] = time.perf_counter() - t0
  (lref, gref), (l, g) = vals['ref'], vals['d4']
  out['grad_scale'] = float(jnp.max(jnp.abs(gref)))
  out['d4_loss_err'] = float(abs(l - lref))
  out['d4_grad_err'] = float(jnp.max(jnp.abs(g - gref)))
  return out


def check_sweep():
  import jax
  import numpy as np
  from experiments import sweep as sweep_script
  from physsplat_jax import distributed as dist
  from physsplat_jax import pipeline as pl
  from physsplat_jax.distributed import sweep
  out = {}
  t0 = time.perf_counter()
  prepared, params, config = _pipeline_setup()
  out['prepare_s'] = time.perf_counter() - t0
  # 6 items on 4 devices (padded to 8).
  E_scale = (0.3, 1.0, 3.0)
  velocity = [(0.0, 0.0, -1.0), (0.3, 0.0, -1.5)]
  batch, table = dist.sweep_params(params, E_scale=E_scale,
                                   velocity=velocity)
  out['num_items'] = len(table)
  mesh = dist.make_mesh(4)
  sel = lambda t: (t.means, t.x)  # noqa: E731
  one = lambda p, s: sel(pl.simulate(p, s, config))  # noqa: E731
  t0 = time.perf_counter()
  ref = jax.jit(jax.vmap(one, in_axes=(sweep.PARAMS_AXES, None)))(
    batch, prepared)
  out['ref_s'] = time.perf_counter() - t0
  # The sweep command's code path (make_simulate_batch, compiled once).
  t0 = time.perf_counter()
  res = sweep_script.run_sweep(prepared, params, config, mesh, E_scale,
                               velocity=velocity)
  out['sharded_s'] = time.perf_counter() - t0
  out['err'], out['scale'] = _max_err(ref, (res.means, res.x))
  means = np.asarray(ref[0])
  # Different parameters give different motions (the sweep is not a no-op).
  out['spread'] = float(np.max(np.abs(means[:, -1] - means[0, -1])))
  out['motion'] = float(np.max(np.abs(means[:, -1] - means[:, 0])))
  # Items one by one with the particles split over 4 devices
  # (distributed.simulate_sharded): items 0 and 4 of the batch above.
  t0 = time.perf_counter()
  res_p = sweep_script.run_sweep(
    prepared, params, config, dist.make_mesh(4, dist.PARTICLE_AXIS),
    (E_scale[0], E_scale[2]), velocity=velocity[:1], mode='particles')
  out['particles_s'] = time.perf_counter() - t0
  out['particles_err'], _ = _max_err(
    jax.tree.map(lambda a: np.asarray(a)[[0, 4]], ref),
    (res_p.means, res_p.x))
  # A batch of 4 stacked scenes, each with its own parameters.
  scenes = _scene_batch(prepared, 4)
  b4 = jax.tree.map(lambda a: a[:4], batch.replace(mpdp=None))
  b4 = b4.replace(mpdp=batch.mpdp)
  t0 = time.perf_counter()
  ref4 = jax.jit(jax.vmap(one, in_axes=(sweep.PARAMS_AXES, 0)))(b4, scenes)
  fn4 = dist.make_simulate_batch(config, mesh, batch_scenes=True,
                                 select=sel)
  res4 = fn4(b4, scenes)
  out['scenes_s'] = time.perf_counter() - t0
  out['scenes_err'], out['scenes_scale'] = _max_err(ref4, res4)
  out['scenes_spec'] = str(res4[0].sharding.spec)
  return out


def check_grad():
  import jax
  import jax.numpy as jnp
  from physsplat_jax import distributed as dist
  from physsplat_jax.training import simtrain
  out = {}
  prepared, params, config = _pipeline_setup()
  scenes = _scene_batch(prepared, 4)
  # Targets: the same scenes with a stiffer, faster cube.
  tgt_params = params.replace(
    log_scale=params.log_scale.at[:, 0].add(jnp.log(3.0)))
  loss_fn = simtrain.make_loss(config)
  targets = jax.jit(jax.vmap(
    lambda s: simtrain.pl.simulate(tgt_params, s, config).means))(scenes)

  def item_loss(mpdp_params, prepared, target):
    return loss_fn(mpdp_params, params, prepared, target)

  def mean_loss(mpdp_params):
    return jnp.mean(jax.vmap(item_loss, in_axes=(None, 0, 0))(
      mpdp_params, scenes, targets))

  t0 = time.perf_counter()
  lref, gref = jax.jit(jax.value_and_grad(mean_loss))(params.mpdp)
  out['ref_s'] = time.perf_counter() - t0
  mesh = dist.make_mesh(4)
  grad_fn = dist.sharded_value_and_grad(item_loss, mesh, in_axes=(0, 0))
  t0 = time.perf_counter()
  (l, losses), g = grad_fn(params.mpdp, scenes, targets)
  out['sharded_s'] = time.perf_counter() - t0
  out['loss'] = float(lref)
  out['loss_err'] = float(abs(l - lref))
  out['grad_err'], out['grad_scale'] = _max_err(gref, g)
  out['losses_spread'] = float(jnp.max(losses) - jnp.min(losses))
  out['grad_spec'] = str(jax.tree.leaves(g)[0].sharding.spec)
  return out


def check_multiprocess():
  import jax
  import jax.numpy as jnp
  import numpy as np
  from physsplat_jax import distributed as dist
  from physsplat_jax import mpm
  out = {'process_index': jax.process_index(),
         'process_count': jax.process_count(),
         'num_devices': jax.device_count(),
         'num_local_devices': jax.local_device_count()}
  state, mat, config = _mpm_setup(n=150, models=('fixed_corotated', 'rigid'),
                                  forces=False)
  # Batch sweep over E (global mesh of both processes).
  scales = np.asarray([0.5, 1.0, 2.0, 4.0, 8.0, 16.0], state.x.dtype)

  def one(scale, s, m):
    final, xs, _ = mpm.rollout(s, m.replace(E=m.E * scale), None, config)
    return xs

  host = dist.to_host((state, mat))  # identical on every process
  ref = jax.jit(jax.vmap(one, in_axes=(0, None, None)))(scales, *host)
  mesh = dist.make_mesh(None, dist.BATCH_AXIS)
  res = dist.sharded_vmap(one, mesh, in_axes=(0, None, None))(scales, *host)
  res = dist.to_host(res)
  out['sweep_err'], out['sweep_scale'] = _max_err(ref, res)
  out['sweep_spread'] = float(np.max(np.abs(res[:, -1] - res[0, -1])))
  # One rollout with particles split over all devices of both processes.
  ref1 = jax.jit(lambda s, m: mpm.rollout(s, m, None, config))(*host)
  pmesh = dist.make_mesh(None, dist.PARTICLE_AXIS)
  placed = dist.put(host, dist.replicated(pmesh))
  res1 = jax.jit(lambda s, m: dist.rollout_sharded(s, m, None, config,
                                                   pmesh))(*placed)
  out['particles_err'], out['particles_scale'] = _max_err(
    ref1, dist.to_host(res1))
  out['particles_motion'] = float(np.max(np.abs(ref1[1][-1] - ref1[1][0])))
  out['ref_device'] = str(ref1[1].devices())
  return out


def check_helpers():
  """sharded_vmap and sharded_value_and_grad on batches that 4 devices do
  not divide (1 and 5 items: padded to 4 and 8) vs the unsharded vmap."""
  import jax
  import jax.numpy as jnp
  import numpy as np
  from physsplat_jax import distributed as dist
  mesh = dist.make_mesh(4)
  fn = lambda a, b: jnp.sin(a) * b + jnp.sum(a)  # noqa: E731
  loss = lambda w, x, y: jnp.sum((w * x - y) ** 2)  # noqa: E731
  vfn = dist.sharded_vmap(fn, mesh, in_axes=(0, None))
  grad_fn = dist.sharded_value_and_grad(loss, mesh, in_axes=(0, 0))
  w = jnp.asarray([0.3, -0.2])
  out = {}
  for b in (1, 5):
    rng = np.random.default_rng(b)
    a = rng.normal(size=(b, 7))
    x, y = rng.normal(size=(b, 2)), rng.normal(size=(b, 2))
    res = vfn(a, 2.0)
    out[f'vmap{b}_shape'] = list(res.shape)
    out[f'vmap{b}_err'], _ = _max_err(jax.vmap(fn, (0, None))(a, 2.0), res)
    out[f'padded{b}'] = vfn.place(a, 2.0)[0][0].shape[0]
    (l, losses), g = grad_fn(w, x, y)
    lref, gref = jax.value_and_grad(lambda w: jnp.mean(  # noqa: B023
      jax.vmap(loss, (None, 0, 0))(w, x, y)))(w)
    out[f'loss{b}_err'] = float(abs(l - lref))
    out[f'grad{b}_err'], out[f'grad{b}_scale'] = _max_err(gref, g)
    out[f'losses{b}_shape'] = list(losses.shape)
  return out


def check_render_device():
  """pipeline.run rendering on a second CPU device ('auto') against the
  simulation's own device: the same frames, bit for bit."""
  import dataclasses
  import numpy as np
  from physsplat_jax import pipeline as pl
  from physsplat_jax.pipeline import host
  prepared, params, config = _pipeline_setup()
  config = dataclasses.replace(config, render='fast')
  out = {}
  runs = {}
  for name, choice in (('same', None), ('auto', 'auto')):
    images = []
    res = pl.run(params, prepared, config, render_device=choice,
                 on_frame=lambda f, means, image: images.append(image))
    runs[name] = (np.stack(images), res.gaussian_positions)
  state0 = pl.simulation.initial_state(params, prepared, config)[0]
  out['auto_device'] = str(host._frame_device('auto', state0, True))
  out['serial_device'] = str(host._frame_device('auto', state0, False))
  out['image_err'] = float(np.max(np.abs(runs['same'][0] - runs['auto'][0])))
  out['pos_err'] = float(np.max(np.abs(runs['same'][1] - runs['auto'][1])))
  out['num_frames'] = int(len(runs['auto'][0]))
  out['image_range'] = float(np.ptp(runs['auto'][0]))
  return out


CHECKS = dict(render_device=check_render_device, particles=check_particles,
              helpers=check_helpers,
              particles_grad=check_particles_grad, sweep=check_sweep,
              grad=check_grad, multiprocess=check_multiprocess)


def main(argv):
  del argv
  t0 = time.perf_counter()
  info = runtime.initialize_from_flags()
  import jax
  import jax.numpy as jnp
  if os.environ.get('JAX_ENABLE_X64', '') in ('1', 'true', 'True'):
    jax.config.update('jax_enable_x64', True)
  result = dict(devices=[str(d) for d in jax.devices()],
                process_index=info.process_index,
                process_count=info.process_count, method=info.method,
                x64=bool(jnp.zeros(()).dtype == jnp.float64),
                startup_s=time.perf_counter() - t0)
  for name in _CHECKS.value:
    t1 = time.perf_counter()
    try:
      result[name] = CHECKS[name]()
    except Exception:  # reported to the test, which fails with it
      result[name] = {'error': traceback.format_exc()}
    result[name]['time_s'] = time.perf_counter() - t1
    print(f'{name}: {result[name]}', flush=True)
  result['total_s'] = time.perf_counter() - t0
  if _OUT.value:
    with open(_OUT.value, 'w') as f:
      json.dump(result, f, indent=1)


if __name__ == '__main__':
  app.run(main)
