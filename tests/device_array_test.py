"""types.device_array: jnp.asarray without compiling for host data, and a
scene's preparation without eager per-operation programs."""

import contextlib

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from physsplat_jax import cameras
from physsplat_jax import mpm
from physsplat_jax import pipeline as pl
from physsplat_jax.types import Gaussians
from physsplat_jax.types import ObjectInfo
from physsplat_jax.types import Scene
from physsplat_jax.types import device_array

_COMPILE = '/jax/core/compile/backend_compile_duration'


@contextlib.contextmanager
def _count_compiles():
  """Counts XLA compiles (jax.monitoring) inside the block."""
  events = []

  def listener(name, duration, **kwargs):
    del duration, kwargs
    if name == _COMPILE:
      events.append(name)

  jax.monitoring.register_event_duration_secs_listener(listener)
  try:
    yield events
  finally:
    jax.monitoring.unregister_event_duration_listener(listener)


class DeviceArrayTest(absltest.TestCase):

  def test_same_as_asarray(self):
    rng = np.random.default_rng(0)
    cases = [
      (rng.normal(size=(5, 3)), None), (rng.normal(size=(5, 3)), jnp.float32),
      (rng.normal(size=4).astype(np.float32), None),
      (np.arange(6, dtype=np.int64).reshape(2, 3), None),
      (np.arange(6), jnp.float32), (rng.uniform(size=7) > 0.5, None),
      ([0.5, 1.5, 2.5], None), ([[1, 2], [3, 4]], jnp.int32), (2.5, None),
    ]
    for x, dtype in cases:
      with self.subTest(x=np.asarray(x).dtype, dtype=dtype):
        got, want = device_array(x, dtype), jnp.asarray(x, dtype)
        self.assertIsInstance(got, jax.Array)
        self.assertEqual(got.dtype, want.dtype)
        self.assertEqual(got.shape, want.shape)
        np.testing.assert_array_equal(got, want)
    with jax.enable_x64(True):
      self.assertEqual(device_array(np.ones(3)).dtype, jnp.float64)

  def test_compiles_nothing_for_host_data(self):
    with _count_compiles() as control:
      jax.jit(lambda a: a + 1)(jnp.ones(13))
    self.assertNotEmpty(control)  # the counter sees compiles
    with _count_compiles() as events:
      device_array(np.zeros((17, 3)))
      device_array(np.zeros((19, 2)), jnp.float32)
      device_array([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11], jnp.float32)
    self.assertEmpty(events)

  def test_passes_jax_arrays_and_tracers_through(self):
    a = jnp.arange(4.0)
    self.assertIs(device_array(a), a)
    out = jax.jit(lambda x: device_array(x, jnp.float32) * 2)(
      jnp.arange(3))
    np.testing.assert_array_equal(out, [0.0, 2.0, 4.0])
    self.assertEqual(out.dtype, jnp.float32)


class PreparationCompilesTest(absltest.TestCase):

  def test_few_programs_compile_to_prepare_a_scene(self):
    """Scene, cameras and preparation of a small block: each eager JAX
    operation on host data used to compile a program of its own (~140
    for the tabletop, ~14 ms each on the CPU)."""
    n, spread = 6, 0.05
    g = np.stack(np.meshgrid(*[np.linspace(0, spread, n)] * 3,
                             indexing='ij'), -1).reshape(-1, 3)
    k = len(g)
    with _count_compiles() as events:
      gs = Gaussians(
        means=device_array(g, jnp.float32),
        log_scales=device_array(np.full((k, 3), np.log(spread / n)),
                                jnp.float32),
        quats=device_array(np.tile([1.0, 0, 0, 0], (k, 1)), jnp.float32),
        opacity_logits=device_array(np.full(k, 2.0), jnp.float32),
        sh=device_array(np.full((k, 1, 3), 0.5), jnp.float32))
      cams = tuple(cameras.orbit_cameras((0.0, 0.0, 0.0), 1.0, 20.0, 6))
      scene = Scene(gaussians=gs, object_ids=device_array(np.zeros(k, int)),
                    objects=(ObjectInfo('block'),), cameras=cams,
                    name='block')
      cfg = pl.PipelineConfig(grid_res=16, max_particles=200,
                              use_mpdp=False, fill=False)
      rubber = pl.ObjectMaterial('fixed_corotated', 3e4, 0.3, 1000.0)
      pl.prepare_scene(jax.random.PRNGKey(0), scene, [rubber], cfg)
    self.assertLess(len(events), 25)

  def test_mpm_state_from_host_data_compiles_nothing(self):
    """mpm.make_materials and mpm.init_state on NumPy data (9 programs
    per new particle count before); the same arrays as through jnp."""
    models = ('fixed_corotated', 'neo_hookean', 'rigid')
    cfg = mpm.SimConfig(grid=mpm.GridSpec(res=16, size=1.0), dt=1e-3,
                        models=models, num_bodies=1, maxwell=True)
    rng = np.random.default_rng(3)

    def build(n, wrap):
      x = 0.3 + 0.4 * rng.uniform(size=(n, 3))
      body = np.where(np.arange(n) % 3 == 2, 0, -1)
      mat = mpm.make_materials([models[i % 3] for i in range(n)],
                               wrap(rng.uniform(1e4, 2e4, n)), 0.3, 1000.0,
                               config_models=models, maxwell_E=wrap(3e3))
      return mat, mpm.init_state(wrap(x), wrap(np.array([0.0, 0.0, -1.0])),
                                 wrap(rng.uniform(1e-6, 2e-6, n)), mat, cfg,
                                 body_id=wrap(body))

    build(6, np.asarray)  # first: whatever every particle count shares
    with _count_compiles() as events:
      host = build(37, np.asarray)
      jax.block_until_ready(host)
    self.assertEmpty(events)
    rng = np.random.default_rng(3)
    build(6, np.asarray)
    on_device = build(37, jnp.asarray)  # the jnp path, same values
    for a, b in zip(jax.tree.leaves(host), jax.tree.leaves(on_device),
                    strict=True):
      self.assertEqual((a.dtype, a.shape, a.weak_type),
                       (b.dtype, b.shape, b.weak_type))
      np.testing.assert_array_equal(a, b)


if __name__ == '__main__':
  absltest.main()
