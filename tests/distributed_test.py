"""Tests of physsplat_jax.distributed on fake CPU devices.

The device count is fixed when JAX starts, and pytest has already started
JAX for other test files, so the multi-device checks run in one fresh
interpreter (tests/distributed_worker.py) with
``XLA_FLAGS=--xla_force_host_platform_device_count=4`` and float64; this
file asserts on what it reports. ``jax.config.update('jax_num_cpu_devices',
N)`` after the backend has started raises instead of adding devices
(checked below through ``initialize(cpu_devices=...)``), which is why a
subprocess is needed. The single-device parts (padding, batching helpers,
argument checks, cluster detection) run in-process.
"""

import json
import os
import socket
import subprocess
import sys
import tempfile
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl import flags
from absl.testing import absltest

import codegen
from physsplat_jax import distributed as dist
from physsplat_jax import mpm
from physsplat_jax import pipeline as pl
from physsplat_jax import struct
from physsplat_jax.distributed import runtime

_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_WORKER = os.path.join(_REPO, 'tests', 'distributed_worker.py')
_TIMEOUT_S = 900
_X64_ENV = dict(
  XLA_FLAGS=(os.environ.get('XLA_FLAGS', '') +
             ' --xla_force_host_platform_device_count=4'),
  JAX_ENABLE_X64='1')

# float64 throughout the worker: sharded and single-device runs differ only
# in the order of float sums (observed ~1e-13 relative).
_STATE_RTOL = 1e-9
_GRAD_RTOL = 1e-8
_BATCH_RTOL = 1e-12


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(('127.0.0.1', 0))
    return s.getsockname()[1]


def run_worker(checks, env=None, args=(), timeout=_TIMEOUT_S):
  """Runs tests/distributed_worker.py; returns its JSON (raises with the
  subprocess's output on failure)."""
  with tempfile.TemporaryDirectory() as tmp:
    out = os.path.join(tmp, 'result.json')
    cmd = [sys.executable, _WORKER, f'--checks={",".join(checks)}',
           f'--out={out}', *args]
    full_env = dict(os.environ, JAX_PLATFORMS='cpu', **(env or {}))
    try:
      proc = subprocess.run(cmd, env=full_env, capture_output=True,
                            text=True, timeout=timeout, cwd=_REPO)
    except subprocess.TimeoutExpired as e:
      raise AssertionError(
        f'{" ".join(cmd)} timed out after {timeout} s; output:\n'
        f'{(e.stdout or "")[-3000:]}\n{(e.stderr or "")[-3000:]}') from None
    if proc.returncode != 0 or not os.path.exists(out):
      raise AssertionError(
        f'{" ".join(cmd)} failed (exit {proc.returncode}):\n'
        f'{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}')
    with open(out) as f:
      result = json.load(f)
  for name in checks:
    if 'error' in result[name]:
      raise AssertionError(f'worker check {name!r} raised:\n'
                           f'{result[name]["error"]}')
  return result


class MultiDeviceTest(absltest.TestCase):
  """Sharded vs single-device results on 4 fake CPU devices (one worker,
  ~1.5 min on 2 cores, mostly compilation)."""

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    cls.result = run_worker(['particles', 'sweep', 'render_device',
                             'helpers'], env=_X64_ENV)

  def test_worker_saw_four_devices_in_float64(self):
    self.assertLen(self.result['devices'], 4)
    self.assertTrue(self.result['x64'])
    self.assertEqual(self.result['process_count'], 1)

  def test_frames_rendered_on_a_second_cpu_device_are_the_same(self):
    """pipeline.run's render_device='auto' renders on cpu:1 beside the
    simulation on cpu:0 (not when unpipelined); frames bit for bit."""
    r = self.result['render_device']
    self.assertEqual(r['auto_device'], 'cpu:1')
    self.assertEqual(r['serial_device'], 'None')
    self.assertEqual(r['num_frames'], 4)
    self.assertGreater(r['image_range'], 0.1)  # something was drawn
    self.assertEqual(r['image_err'], 0.0)
    self.assertEqual(r['pos_err'], 0.0)

  def test_batches_that_do_not_divide_are_padded_and_cut(self):
    # 1 and 5 items on 4 devices: the padded copies must neither show in
    # the results nor weigh in the mean loss and its gradient.
    r = self.result['helpers']
    for b, padded in ((1, 4), (5, 8)):
      self.assertEqual(r[f'padded{b}'], padded)
      self.assertEqual(r[f'vmap{b}_shape'], [b, 7])
      self.assertEqual(r[f'losses{b}_shape'], [b])
      self.assertLessEqual(r[f'vmap{b}_err'], 1e-14)
      self.assertLessEqual(r[f'loss{b}_err'], 1e-12)
      self.assertLessEqual(r[f'grad{b}_err'],
                           _GRAD_RTOL * r[f'grad{b}_scale'])

  def test_particle_sharded_rollout_matches_single_device(self):
    r = self.result['particles']
    self.assertNotEqual(r['num_particles'] % 4, 0)  # ghosts are needed
    self.assertGreater(r['rigid_particles'], 0)
    self.assertGreater(r['motion'], 1e-3)  # the block moved [m]
    self.assertLessEqual(r['d4_err'], _STATE_RTOL * r['scale'],
                         msg=f'mismatch: 4 devices {r}')
    self.assertLessEqual(r['d4_x_err'], _STATE_RTOL * r['x_scale'],
                         msg=f'mismatch: positions {r}')

  def test_without_psum_the_shards_disagree(self):
    # The control shows the comparison above sees cross-shard coupling:
    # without the psum the error is > 1e4 times the sharded run's.
    r = self.result['particles']
    self.assertGreater(r['nopsum_err'], 1e-2 * r['frame1_motion'])
    self.assertGreater(r['nopsum_err'], 1e4 * max(r['d4_x_err'], 1e-16))

  def test_parameter_sweep_matches_unsharded_vmap(self):
    r = self.result['sweep']
    self.assertEqual(r['num_items'], 6)  # padded to 8 on 4 devices
    self.assertLessEqual(r['err'], _BATCH_RTOL * r['scale'],
                         msg=f'mismatch: sweep {r}')
    # The items differ: stiffness and velocity change the motion.
    self.assertGreater(r['spread'], 1e-2 * r['motion'])

  def test_particle_sharded_pipeline_matches_single_device(self):
    r = self.result['sweep']
    self.assertLessEqual(r['particles_err'], _STATE_RTOL * r['scale'],
                         msg=f'mismatch: simulate_sharded {r}')

  def test_scene_batch_matches_unsharded_vmap_and_stays_sharded(self):
    r = self.result['sweep']
    self.assertLessEqual(r['scenes_err'], _BATCH_RTOL * r['scenes_scale'],
                         msg=f'mismatch: scenes {r}')
    self.assertEqual(r['scenes_spec'], "P('batch',)")


@pytest.mark.slow  # ~2 min on 2 cores: compiling two backward passes
class MultiDeviceGradientTest(absltest.TestCase):
  """Gradients through the psum and through a sharded training batch."""

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    cls.result = run_worker(['particles_grad', 'grad'], env=_X64_ENV)

  def test_particle_sharded_gradient_matches_single_device(self):
    r = self.result['particles_grad']
    self.assertGreater(r['grad_scale'], 0.0)
    self.assertLessEqual(r['d4_grad_err'], _GRAD_RTOL * r['grad_scale'],
                         msg=f'mismatch: gradient {r}')
    self.assertLessEqual(r['d4_loss_err'], 1e-10)

  def test_batch_mean_gradient_matches_single_device(self):
    r = self.result['grad']
    self.assertGreater(r['grad_scale'], 0.0)
    self.assertGreater(r['losses_spread'], 0.0)  # four different scenes
    self.assertLessEqual(r['grad_err'], _GRAD_RTOL * r['grad_scale'],
                         msg=f'mismatch: MPDP gradient {r}')
    self.assertLessEqual(r['loss_err'], _BATCH_RTOL * r['loss'])


# ---------------------------------------------------- single-device parts


class _Holder(struct.PyTreeNode):
  x: jax.Array
  cfg: mpm.SimConfig = struct.field(pytree_node=False)


def _tiny_state(n=10, rigid_first=True):
  config = mpm.SimConfig(
    grid=mpm.GridSpec(res=8), models=('fixed_corotated', 'rigid'),
    num_bodies=1, boundary_conditions=(
      mpm.ParticleImpulse(force=(1.0, 0.0, 0.0), point=(0.5, 0.5, 0.5),
                          size=(0.01, 0.01, 0.01)),))
  rng = np.random.default_rng(0)
  x = rng.uniform(0.3, 0.6, (n, 3))
  x[1] = (0.5, 0.5, 0.5)  # selected by the impulse
  mid = np.zeros(n, np.int32)
  body = np.full(n, -1)
  if rigid_first:
    mid[0], body[0] = 1, 0
  mat = mpm.make_materials(mid, 1e4, 0.3, 1000.0,
                           config_models=config.models)
  state = mpm.init_state(x, (0.0, 0.0, 1.0), 1e-3, mat, config,
                         body_id=body)
  return state, mat, config


class PaddingTest(absltest.TestCase):

  def test_ghosts_copy_a_free_particle_with_negligible_mass(self):
    state, mat, _ = _tiny_state(10)
    sp, mp = dist.pad_particles(state, mat, 4)
    self.assertEqual(sp.x.shape, (12, 3))
    self.assertEqual(mp.E.shape, (12,))
    np.testing.assert_array_equal(sp.x[:10], state.x)
    np.testing.assert_array_equal(sp.mass[:10], state.mass)
    # Particle 0 is rigid and particle 1 selected by the impulse: the
    # ghosts copy particle 2.
    np.testing.assert_array_equal(sp.x[10:], np.broadcast_to(state.x[2],
                                                             (2, 3)))
    np.testing.assert_allclose(sp.mass[10:],
                               dist.GHOST_FRACTION * state.mass[2])
    np.testing.assert_allclose(sp.vol0[10:],
                               dist.GHOST_FRACTION * state.vol0[2])
    np.testing.assert_array_equal(sp.body_id[10:], [-1, -1])
    np.testing.assert_array_equal(sp.bc_data[0][10:], [0, 0])
    self.assertEqual(float(state.bc_data[0][1]), 1.0)

  def test_ghosts_skip_particles_held_by_a_sequential_release(self):
    # A release's unselected particles carry -inf, not 0: the ghosts copied
    # particle 0 (here rigid) whenever a release was configured.
    config = mpm.SimConfig(
      grid=mpm.GridSpec(res=8), models=('fixed_corotated', 'rigid'),
      num_bodies=1, boundary_conditions=(
        mpm.SequentialRelease(axis=0, start_position=0.45, end_position=0.5,
                              num_layers=2),))
    x = np.asarray([[0.4, 0.5, 0.5], [0.49, 0.5, 0.5], [0.3, 0.5, 0.5],
                    [0.35, 0.4, 0.5], [0.6, 0.6, 0.6]])
    mat = mpm.make_materials(np.asarray([1, 0, 0, 0, 0]), 1e4, 0.3, 1000.0,
                             config_models=config.models)
    state = mpm.init_state(x, (0.0, 0.0, 0.0), 1e-3, mat, config,
                           body_id=np.asarray([0, -1, -1, -1, -1]))
    held = np.asarray(state.bc_data[0])
    self.assertTrue(np.isfinite(held[1]) and np.isneginf(held[2]))
    sp, mp = dist.pad_particles(state, mat, 4)
    # Particle 0 is rigid and particle 1 held: the ghosts copy particle 2.
    np.testing.assert_array_equal(sp.x[5:], np.broadcast_to(state.x[2],
                                                            (3, 3)))
    np.testing.assert_array_equal(mp.model_id[5:], [0, 0, 0])

  def test_no_padding_when_divisible(self):
    state, mat, _ = _tiny_state(8)
    sp, mp = dist.pad_particles(state, mat, 4)
    self.assertIs(sp, state)
    self.assertIs(mp, mat)

  def test_one_device_mesh_matches_rollout(self):
    # The sharded code path on one device (psum over one shard).
    state, mat, config = _tiny_state(10)
    config = config.replace(num_frames=1, substeps_per_frame=2)
    mesh = dist.make_mesh(1, dist.PARTICLE_AXIS)
    ref = jax.jit(lambda s, m: mpm.rollout(s, m, None, config))(state, mat)
    out = jax.jit(lambda s, m: dist.rollout_sharded(s, m, None, config,
                                                    mesh))(state, mat)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(out)):
      codegen.allclose_across_programs(b, a, 1e-6, 1e-7,
                                       legacy_scale=1e-4)


  def test_one_device_mesh_with_a_maxwell_branch(self):
    # The branch's F_N is padded, sharded and carried like F.
    state, mat, config = _tiny_state(10)
    config = config.replace(num_frames=1, substeps_per_frame=2, maxwell=True)
    full = lambda v: jnp.full_like(mat.E, v)  # noqa: E731
    mat = mat.replace(maxwell_E=full(5e3), maxwell_nu=full(0.3),
                      maxwell_viscosity=full(1.0))
    state = state.replace(F_N=jnp.broadcast_to(
      jnp.eye(3, dtype=state.F.dtype), state.F.shape))
    sp, mp = dist.pad_particles(state, mat, 4)
    self.assertEqual(sp.F_N.shape, (12, 3, 3))
    self.assertEqual(mp.maxwell_E.shape, (12,))
    mesh = dist.make_mesh(1, dist.PARTICLE_AXIS)
    ref = jax.jit(lambda s, m: mpm.rollout(s, m, None, config))(state, mat)
    out = jax.jit(lambda s, m: dist.rollout_sharded(s, m, None, config,
                                                    mesh))(state, mat)
    self.assertIsNotNone(ref[0].F_N)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(out)):
      codegen.allclose_across_programs(b, a, 1e-6, 1e-7,
                                       legacy_scale=1e-4)


class BatchHelpersTest(absltest.TestCase):

  def test_sharded_vmap_pads_and_cuts(self):
    mesh = dist.make_mesh(1)
    fn = dist.sharded_vmap(lambda a, b: a * b['s'] + 1.0, mesh,
                           in_axes=(0, None))
    a = np.arange(6.0).reshape(3, 2)
    out = fn(a, {'s': np.float32(2.0)})
    np.testing.assert_allclose(np.asarray(out), a * 2.0 + 1.0)
    self.assertEqual(out.shape, (3, 2))

  def test_value_and_grad_is_the_batch_mean(self):
    mesh = dist.make_mesh(1)
    loss = lambda w, x, y: jnp.sum((w * x - y) ** 2)  # noqa: E731
    grad_fn = dist.sharded_value_and_grad(loss, mesh, in_axes=(0, 0))
    x = np.asarray([[1.0, 2.0], [3.0, 4.0], [0.5, 1.0]], np.float32)
    y = np.ones_like(x)
    w = jnp.asarray([0.3, -0.2])
    (l, losses), g = grad_fn(w, x, y)
    ref_l, ref_g = jax.value_and_grad(
      lambda w: jnp.mean(jax.vmap(loss, (None, 0, 0))(w, x, y)))(w)
    np.testing.assert_allclose(float(l), float(ref_l), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(g), np.asarray(ref_g), rtol=1e-6)
    self.assertEqual(losses.shape, (3,))

  def test_batch_size_mismatch_is_named(self):
    fn = dist.sharded_vmap(lambda a, b: a + b, dist.make_mesh(1))
    with self.assertRaisesRegex(ValueError, r'batch sizes \[2, 3\]'):
      fn(np.zeros(2), np.zeros(3))

  def test_too_many_devices_is_explained(self):
    with self.assertRaisesRegex(ValueError, 'xla_force_host_platform'):
      dist.make_mesh(jax.device_count() + 1)

  def test_stack_trees_names_the_static_difference(self):
    a = pl.Params(mpdp=None, log_scale=jnp.zeros((1, 3)),
                  velocity=jnp.zeros((1, 3)), forces=jnp.zeros((0, 3)))
    st = dist.stack_trees([a, a])
    self.assertEqual(st.log_scale.shape, (2, 1, 3))
    with self.assertRaisesRegex(ValueError, r"velocity'?\]? of shape \(2, 3\)"):
      dist.stack_trees([a, a.replace(velocity=jnp.zeros((2, 3)))])
    spec = mpm.SimConfig()
    with self.assertRaisesRegex(ValueError, r'dt: 0\.0001 vs 0\.0002'):
      dist.stack_trees([_Holder(x=jnp.zeros(2), cfg=spec),
                        _Holder(x=jnp.zeros(2), cfg=spec.replace(dt=2e-4))])

  def test_sweep_params_is_a_cartesian_product(self):
    base = pl.Params(mpdp={'w': jnp.ones(3)},
                     log_scale=jnp.zeros((2, 3)),
                     velocity=jnp.zeros((2, 3)), forces=jnp.zeros((1, 3)))
    batch, table = dist.sweep_params(base, E_scale=(0.5, 2.0),
                                     velocity=[(0, 0, 1), (1, 0, 0),
                                               (0, 1, 0)])
    self.assertLen(table, 6)
    self.assertEqual(batch.log_scale.shape, (6, 2, 3))
    self.assertEqual(batch.velocity.shape, (6, 2, 3))
    self.assertEqual(batch.forces.shape, (6, 1, 3))
    self.assertEqual(batch.mpdp['w'].shape, (3,))  # shared weights
    np.testing.assert_allclose(np.exp(batch.log_scale[:, 0, 0]),
                               [0.5, 0.5, 0.5, 2.0, 2.0, 2.0], rtol=1e-6)
    np.testing.assert_allclose(batch.velocity[4, 1], [1, 0, 0])
    self.assertEqual(table[4], dict(E_scale=2.0, nu_scale=1.0,
                                    rho_scale=1.0, velocity=[1.0, 0.0, 0.0]))
    with self.assertRaisesRegex(ValueError, 'E_scale'):
      dist.sweep_params(base, E_scale=(0.0,))
    with self.assertRaisesRegex(ValueError, 'velocity = \\[\\]'):
      dist.sweep_params(base, velocity=[])  # was NumPy's 'need at least one'
    # One number, or one 3-vector, is a sweep of one value (they were
    # Python TypeErrors).
    one, table = dist.sweep_params(base, E_scale=2.0, velocity=(0, 0, 1))
    self.assertLen(table, 1)
    np.testing.assert_allclose(np.exp(one.log_scale[0, :, 0]), 2.0,
                               rtol=1e-6)
    np.testing.assert_allclose(one.velocity[0], [[0, 0, 1]] * 2)
    for kwargs, message in (
        (dict(E_scale=(0.0,)), 'E_scale = \\(0.0,\\); give one or more finite'),
        (dict(nu_scale=float('inf')), 'nu_scale = inf'),
        (dict(rho_scale=('a',)), 'rho_scale'),
        (dict(rho_scale=(True,)), 'rho_scale'),
        (dict(velocity=[(1.0, 2.0)]), 'must be 3 finite numbers'),
        (dict(velocity=[(0, 0, float('nan'))]), 'must be 3 finite numbers'),
        (dict(velocity=3.0), 'velocity 3.0 must be 3 finite')):
      with self.subTest(**kwargs):
        with self.assertRaisesRegex(dist.DistributedError, message):
          dist.sweep_params(base, **kwargs)


  def test_sweep_substeps_cover_the_stiffest_item(self):
    # experiments/sweep.py: the items share the scene's substep count,
    # chosen for its unscaled materials (E * 1e4 went NaN, silently).
    from experiments import sweep as sweep_script
    from physsplat_jax.mpm import timestep

    report = mock.Mock(time_step=dict(max_wave_speed_m_s=10.0,
                                      substeps_per_frame=200))
    config = pl.PipelineConfig(initial_velocity=(('a', (2.0, 0.0, 0.0)),))
    need = sweep_script.sweep_substeps
    self.assertIsNone(need(report, config, E_scale=(0.5, 1.0)))
    # 100x the wave speed (sqrt(1e4)), the initial speed 2 m/s unchanged.
    self.assertEqual(need(report, config, E_scale=(1.0, 1e4)),
                     int(np.ceil(200 * (10 * 100 + 2) / 12)))
    self.assertEqual(need(report, config, rho_scale=(0.25,)),
                     int(np.ceil(200 * 22 / 12)))
    self.assertEqual(need(report, config, velocity=[(0, 0, 14.0)]),
                     int(np.ceil(200 * 24 / 12)))
    # nu 0.3 -> 0.45 raises the P-wave speed; the factor covers any base nu.
    got = need(report, config, nu_scale=(1.5,))
    f = float(timestep.wave_speed(1, 0.45, 1) / timestep.wave_speed(1, 0.3,
                                                                     1))
    self.assertGreaterEqual(got, np.ceil(200 * (10 * f + 2) / 12))


class RuntimeTest(absltest.TestCase):

  def test_single_process_needs_no_runtime(self):
    with mock.patch.dict(os.environ, {}, clear=False):
      for k in ('SLURM_JOB_ID', 'OMPI_MCA_orte_hnp_uri'):
        os.environ.pop(k, None)
      info = runtime.initialize()
    self.assertEqual(info.method, 'single')
    self.assertEqual(info.process_count, 1)
    self.assertTrue(info.is_main)

  def test_cpu_devices_after_backend_start_is_explained(self):
    jax.devices()  # the backend is running
    with self.assertRaisesRegex(RuntimeError, 'call physsplat_jax.distri'):
      runtime.initialize(cpu_devices=4)

  def test_bad_arguments(self):
    with self.assertRaisesRegex(ValueError, 'mode'):
      runtime.initialize(mode='always')
    with self.assertRaisesRegex(ValueError, r'process_id = 2 must be in'):
      runtime.initialize(num_processes=2, process_id=2)
    with self.assertRaisesRegex(ValueError, 'cpu_collectives'):
      runtime.initialize(cpu_collectives='nccl')
    for bad in (0, 2.5, True):
      with self.assertRaisesRegex(ValueError, 'initialization_timeout = '):
        runtime.initialize(initialization_timeout=bad)

  def test_coordinator_address_needs_a_port(self):
    # JAX's own answer was a bare IndexError (no port) or a failed RPC
    # server (a port that is not a number).
    for addr in ('127.0.0.1', '127.0.0.1:abc', ':1234', 'host:70000'):
      with self.assertRaisesRegex(dist.DistributedError, 'give HOST:PORT'):
        runtime.initialize(coordinator_address=addr, num_processes=2,
                           process_id=0)
    with mock.patch.dict(os.environ, JAX_COORDINATOR_ADDRESS='10.0.0.1'):
      with self.assertRaisesRegex(dist.DistributedError,
                                  'JAX_COORDINATOR_ADDRESS'):
        runtime.initialize(num_processes=2, process_id=0)

  def test_a_join_that_times_out_is_explained_before_jax_aborts(self):
    # Process 1 of 2 with no coordinator running: JAX ends the process with
    # a C++ fatal error (no Python exception), so the hint is logged first.
    port = _free_port()
    # (Through the flags, as a script: --initialization_timeout reaches JAX.)
    code = ('from absl import flags, logging; logging.set_verbosity("info"); '
            'from physsplat_jax.distributed import runtime; '
            'runtime.define_flags(); flags.FLAGS(["p", '
            '"--coordinator_address=127.0.0.1:%d", "--num_processes=2", '
            '"--process_id=1", "--initialization_timeout=1"]); '
            'runtime.initialize_from_flags()' % port)
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True,
                          text=True, timeout=120, cwd=_REPO,
                          env=dict(os.environ, JAX_PLATFORMS='cpu'))
    self.assertNotEqual(proc.returncode, 0)
    self.assertIn('DEADLINE_EXCEEDED', proc.stderr)
    hint = proc.stderr.index('an abort with DEADLINE_EXCEEDED means not all')
    self.assertLess(hint, proc.stderr.index('Terminating process'))
    self.assertIn(f'joining 127.0.0.1:{port} as process 1 of 2 (waits up '
                  'to 1 s', proc.stderr)

  def test_cluster_detection(self):
    slurm = dict(SLURM_JOB_ID='7', SLURM_STEP_NODELIST='node[01-02]',
                 SLURM_NTASKS='2', SLURM_PROCID='1', SLURM_LOCALID='0')
    with mock.patch.dict(os.environ, slurm):
      self.assertEqual(runtime.cluster_environment(), 'slurm')
    with mock.patch.dict(os.environ, dict(slurm, SLURM_NTASKS='1')):
      self.assertIsNone(runtime.cluster_environment())
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(('SLURM_', 'OMPI_'))}
    with mock.patch.dict(os.environ, env, clear=True):
      self.assertIsNone(runtime.cluster_environment())
    ompi4 = dict(OMPI_MCA_orte_hnp_uri='123.0;tcp://10.0.0.1:5000',
                 OMPI_COMM_WORLD_SIZE='2', OMPI_COMM_WORLD_RANK='1')
    with mock.patch.dict(os.environ, dict(env, **ompi4), clear=True):
      self.assertEqual(runtime.cluster_environment(), 'ompi')
    with mock.patch.dict(os.environ, dict(env, **ompi4, **slurm), clear=True):
      self.assertEqual(runtime.cluster_environment(), 'ompi')  # JAX's order
    # Open MPI 5 sets no OMPI_MCA_orte_hnp_uri: JAX does not detect it, and
    # each rank ran the whole sweep alone, every one writing its outputs.
    ompi5 = dict(OMPI_COMM_WORLD_SIZE='2', OMPI_COMM_WORLD_RANK='1')
    with mock.patch.dict(os.environ, dict(env, **ompi5), clear=True):
      self.assertIsNone(runtime.cluster_environment())
      with self.assertRaisesRegex(
          runtime.DistributedError, r'one of 2 that Open MPI 5 or later '
          r'started .*--num_processes=\$OMPI_COMM_WORLD_SIZE --process_id='
          r'\$OMPI_COMM_WORLD_RANK.*--distributed=off'):
        runtime.initialize()
      self.assertEqual(runtime.initialize(mode='off').method, 'single')

  def test_flags(self):
    fv = flags.FlagValues()
    runtime.define_flags(fv)
    fv(['prog', '--coordinator_address=10.0.0.1:1234', '--num_processes=4',
        '--process_id=3', '--local_device_ids=0,1', '--cpu_devices=2'])
    self.assertEqual(fv.coordinator_address, '10.0.0.1:1234')
    self.assertEqual(fv.num_processes, 4)
    self.assertEqual(fv.local_device_ids, ['0', '1'])
    self.assertEqual(fv.distributed, 'auto')
    fv2 = flags.FlagValues()
    runtime.define_flags(fv2)
    fv2(['prog', '--local_device_ids=a,b', '--distributed=off'])
    with self.assertRaisesRegex(ValueError, 'local_device_ids=a,b'):
      runtime.initialize_from_flags(fv2)


if __name__ == '__main__':
  absltest.main()
