"""The stress update as one Pallas kernel (mpm/pallas_constitutive.py).

On a CUDA GPU ``SimConfig.constitutive_kernel='auto'`` runs it compiled;
on the CPU it runs in Pallas interpret mode (the same kernel body: masked
loads and stores per block of particles, one ``pl.when`` per slice; on a
GPU these tests run it compiled) and must equal the pure-JAX update, for
every model, at block edges and slice boundaries inside a block, in
float32 and float64, in value and gradient, and inside a whole frame.
tests/gpu_program_test.py checks that CUDA gets the kernel and the CPU
does not.
"""

import contextlib
import dataclasses
import os
import tempfile
import threading
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl.testing import absltest

import codegen
import mpm_blocks
from physsplat_jax import mpm
from physsplat_jax.mpm import constitutive
from physsplat_jax.mpm import pallas_constitutive as pc

_MODELS = mpm.CANONICAL_MODELS
# Compiled (Triton) where a GPU runs the tests (experiments/gpu_session.sh
# tests), interpreted elsewhere.
_INTERPRET = jax.default_backend() != 'gpu'


def _inputs(models, counts, dtype, seed=0):
  """Random trial states near the rest state: F = I + noise, a velocity
  gradient C, a plastic state (Jp, ep) and per-model default materials,
  sorted by model."""
  n = sum(counts)
  rng = np.random.default_rng(seed)
  F = np.eye(3)[:, :, None] + 0.08 * rng.standard_normal((3, 3, n))
  C = 2.0 * rng.standard_normal((3, 3, n))
  Jpep = np.stack([rng.uniform(0.9, 1.1, n), rng.uniform(0.0, 0.05, n)])
  names = [m for m, c in zip(models, counts) for _ in range(c)]
  E = rng.uniform(2e4, 2e5, n)
  mat = mpm.make_materials(names, E, 0.3, 1000.0, config_models=models,
                           dtype=dtype)
  cast = lambda a: jnp.asarray(a, dtype)  # noqa: E731
  return cast(F), cast(C), cast(Jpep), mat


@contextlib.contextmanager
def _no_logs():
  yield


def _assert_close(test, got, want, rtol):
  for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
    g, w = np.asarray(g), np.asarray(w)
    scale = np.maximum(np.abs(w).max(axis=-1, keepdims=True), 1e-30)
    test.assertLess(float(np.max(np.abs(g - w) / scale)), rtol)


class PallasConstitutiveTest(absltest.TestCase):

  def test_every_model_equals_the_jax_update(self):
    """All models blended in one slice, 150 particles in blocks of 64
    (the last block partial), float32 and float64."""
    counts = (20, 10, 10, 15, 15, 10, 15, 15, 15, 15, 10)
    slices = ((_MODELS, 0, 0, sum(counts)),)
    for dtype, rtol in ((jnp.float32, 2e-5), (jnp.float64, 1e-11)):
      with self.subTest(str(dtype)), jax.enable_x64(dtype == jnp.float64):
        F, C, Jpep, mat = _inputs(_MODELS, counts, dtype)
        got = pc.constitute(slices, 1e-4, F, C, Jpep, mat,
                            interpret=_INTERPRET, block=64)
        want = pc._reference(slices, 1e-4, False, F, C, Jpep, mat, None)
        self.assertEqual(got[0].dtype, dtype)
        _assert_close(self, got, want, rtol)
        # The solids' Kelvin-Voigt stress (SimConfig.solid_viscosity).
        visc = mat.replace(viscosity=jnp.linspace(0.5, 2.0, mat.num,
                                                  dtype=dtype))
        got = pc.constitute(slices, 1e-4, F, C, Jpep, visc,
                            interpret=_INTERPRET, block=64,
                            solid_viscosity=True)
        want = pc._reference(slices, 1e-4, False, F, C, Jpep, visc, None,
                             True)
        _assert_close(self, got, want, rtol)
        plain = pc._reference(slices, 1e-4, False, F, C, Jpep, visc, None)
        self.assertGreater(float(jnp.max(jnp.abs(got[2] - plain[2]))), 0.1)

  def test_slices_inside_blocks_equal_the_per_model_update(self):
    """A pipeline-style scene sorted by model with SimConfig.model_counts:
    the merged slices (one SVD for the spectral models, as on a GPU) with
    boundaries inside blocks, against the per-model slices of the CPU
    path; the rigid slice keeps F and has no stress."""
    models = ('fixed_corotated', 'drucker_prager', 'snow', 'newtonian',
              'rigid')
    counts = (30, 45, 20, 25, 30)
    cfg = mpm.SimConfig(models=models, model_counts=counts, num_bodies=1)
    merged = constitutive.constitutive_slices(cfg, merge=True)
    single = constitutive.constitutive_slices(cfg, merge=False)
    self.assertLess(len(merged), len(single))
    F, C, Jpep, mat = _inputs(models, counts, jnp.float32, seed=1)
    got = pc.constitute(merged, 1e-4, F, C, Jpep, mat,
                        interpret=_INTERPRET, block=32)
    want = pc._reference(single, 1e-4, False, F, C, Jpep, mat, None)
    _assert_close(self, got, want, 2e-5)
    np.testing.assert_array_equal(got[0][..., -30:], F[..., -30:])
    np.testing.assert_array_equal(got[2][..., -30:], 0.0)
    # F and C as rows of one (18, N) array (the solver's carry): the same.
    FC = jnp.concatenate([F.reshape(9, -1), C.reshape(9, -1)])
    packed = pc.constitute(merged, 1e-4, (FC, 0), (FC, 9), Jpep, mat,
                           interpret=_INTERPRET, block=32)
    for a, b in zip(packed, got):
      codegen.assert_same_bits(a, b)

  def test_solver_update_gradient_equals_the_jax_path(self):
    """Through ``constitutive.make_update`` (F and C packed as the solver
    carries them), 'pallas' against 'jax', with model_counts (slices) and
    without (body_id marks the rigid particles): values and the gradient
    with respect to FC, the plastic state and E (float64)."""
    models = ('neo_hookean', 'snow', 'rigid')
    counts = (9, 11, 6)
    with jax.enable_x64(True):
      F, C, Jpep, mat = _inputs(models, counts, jnp.float64, seed=5)
      FC = jnp.concatenate([F.reshape(9, -1), C.reshape(9, -1)])
      body = jnp.asarray([-1] * 20 + [0] * 6, jnp.int32)
      rng = np.random.default_rng(6)
      w = [[jnp.asarray(rng.standard_normal(26)) for _ in range(3)]
           for _ in range(3)]
      for model_counts in (counts, None):
        cfg = mpm.SimConfig(models=models, model_counts=model_counts,
                            num_bodies=1, dtype='float64')

        def loss(kernel, FC, Jpep, E, cfg=cfg):
          update = constitutive.make_update(
            dataclasses.replace(cfg, constitutive_kernel=kernel))
          Fe, J, tau = update(FC, Jpep, body, mat.replace(E=E))
          return (sum(jnp.sum(w[i][j] * (Fe[i][j] + 1e-5 * tau[i][j]))
                      for i in range(3) for j in range(3))
                  + jnp.sum(J * J))

        with self.subTest(model_counts=model_counts):
          got = jax.jit(jax.value_and_grad(
            lambda *a: loss('pallas', *a), (0, 1, 2)))(FC, Jpep, mat.E)
          want = jax.jit(jax.value_and_grad(
            lambda *a: loss('jax', *a), (0, 1, 2)))(FC, Jpep, mat.E)
          _assert_close(self, got, want, 1e-10)

  def test_batched_by_vmap(self):
    """A sweep vmaps the simulation over materials: the batched kernel
    (an extra grid axis) equals one call per item."""
    models = ('neo_hookean', 'drucker_prager')
    F, C, Jpep, mat = _inputs(models, (40, 50), jnp.float32)
    slices = ((models, 0, 0, 90),)

    def one(E):
      return pc.constitute(slices, 1e-4, F, C, Jpep, mat.replace(E=E),
                           interpret=_INTERPRET, block=64)

    Es = jnp.stack([mat.E, 3.0 * mat.E])
    got = jax.vmap(one)(Es)
    for k in range(2):
      for a, b in zip(got, one(Es[k])):
        codegen.assert_same_bits(a[k], b)

  def test_rigid_particles_marked_by_body_id_get_no_stress(self):
    """One slice of every model with rigid particles marked by body_id (a
    scene without model_counts), float64."""
    models = ('neo_hookean', 'von_mises', 'rigid')
    with jax.enable_x64(True):
      F, C, Jpep, mat = _inputs(models, (9, 11, 6), jnp.float64, seed=2)
      body = jnp.asarray([-1] * 20 + [0] * 6, jnp.int32)
      one = ((models, 0, 0, 26),)
      got = pc.constitute(one, 1e-4, F, C, Jpep, mat, body,
                          interpret=_INTERPRET, block=16)
      want = pc._reference(one, 1e-4, True, F, C, Jpep, mat, body)
      _assert_close(self, got, want, 1e-11)
      np.testing.assert_array_equal(got[2][..., 20:], 0.0)

  # ~25 s interpreted on 2 cores; the default run checks the kernel's VJP
  # through the solver's update (test_solver_update_gradient_...).
  @pytest.mark.slow
  def test_gradient_is_the_jax_updates(self):
    """The kernel's VJP differentiates the pure-JAX update (float64)."""
    models = ('neo_hookean', 'von_mises', 'rigid')
    counts = (9, 11, 6)
    slices = ((models[:2], 0, 0, 20), (models[2:], 2, 20, 26))
    with jax.enable_x64(True):
      F, C, Jpep, mat = _inputs(models, counts, jnp.float64, seed=2)
      w = [jnp.asarray(np.random.default_rng(3).standard_normal(s))
           for s in ((3, 3, 26), (2, 26), (3, 3, 26))]

      def loss(fn, F, E):
        out = fn(F, mat.replace(E=E))
        return sum(jnp.sum(a * b) for a, b in zip(out, w))

      def kernel(F, m):
        return pc.constitute(slices, 1e-4, F, C, Jpep, m,
                             interpret=_INTERPRET, block=16)

      def reference(F, m):
        return pc._reference(slices, 1e-4, False, F, C, Jpep, m, None)

      got = jax.grad(lambda *a: loss(kernel, *a), (0, 1))(F, mat.E)
      want = jax.grad(lambda *a: loss(reference, *a), (0, 1))(F, mat.E)
      _assert_close(self, got, want, 1e-12)
      self.assertTrue(all(np.all(np.isfinite(g)) for g in got))
      # Forward mode, and a second derivative (reverse over forward): the
      # rule's value went through pallas_call's JVP, which refuses the
      # aliased plastic state ('JVP with aliasing not supported').
      dF = jnp.asarray(np.random.default_rng(4).standard_normal(F.shape))

      def hvp(fn):
        return jax.grad(lambda F: jax.jvp(
          lambda G: loss(fn, G, mat.E), (F,), (dF,))[1])(F)

      jk = jax.jvp(lambda G: loss(kernel, G, mat.E), (F,), (dF,))[1]
      jr = jax.jvp(lambda G: loss(reference, G, mat.E), (F,), (dF,))[1]
      _assert_close(self, (jk,), (jr,), 1e-12)
      _assert_close(self, (hvp(kernel),), (hvp(reference),), 1e-12)

  def test_a_frame_with_the_kernel_equals_the_jax_frame(self):
    """Two substeps of a scene of three materials and a rigid body on a
    plane, sorted by model (model_counts): 'pallas' (interpreted here)
    against 'jax'. (Without model_counts the update is checked through
    make_update in test_solver_update_gradient_equals_the_jax_path.)"""
    v = np.random.default_rng(4).normal(size=(32, 3))
    for counts in ((8, 8, 8, 8),):
      s, mat, forces, cfg = mpm_blocks.four_blocks(v, counts)
      out = {k: jax.jit(mpm.make_frame(dataclasses.replace(
        cfg, constitutive_kernel=k)))(s, mat, forces)
             for k in ('jax', 'pallas')}
      with self.subTest(counts=counts):
        for f in ('x', 'v', 'F', 'C', 'Jp', 'ep'):
          np.testing.assert_allclose(
            getattr(out['pallas'], f), getattr(out['jax'], f),
            atol=2e-5 * max(1.0, float(np.abs(getattr(out['jax'], f)).max())),
            err_msg=f)

  def test_auto_falls_back_where_the_kernel_does_not_build(self):
    """On a GPU whose JAX cannot build the kernel, 'auto' warns once and
    keeps the pure-JAX update; the check runs eagerly even while a frame
    is traced. (The GPU and the failure are simulated.)"""
    calls, visc = [], []
    real = pc.constitute

    def interpreted(*args, **kw):
      calls.append(threading.current_thread() is threading.main_thread())
      visc.append(kw.get('solid_viscosity', False))
      return real(*args, **dict(kw, interpret=True))

    def broken(*args, **kw):
      raise AttributeError("module 'triton' has no attribute 'load'")

    cfg = mpm.SimConfig(models=('neo_hookean',))
    FC = jnp.zeros((18, 4)).at[jnp.array([0, 4, 8])].set(1.0)  # F = I, C = 0
    mat = mpm.make_materials('neo_hookean', 1e4, 0.3, 1e3, num=4)
    args = (FC, jnp.ones((2, 4)), jnp.full(4, -1), mat)
    try:
      with mock.patch.object(jax, 'default_backend', lambda: 'gpu'), \
          mock.patch.object(pc, 'probe_record', lambda dtype: None):
        for fake, want in ((broken, False), (interpreted, True)):
          pc._available.cache_clear()
          with mock.patch.object(pc, 'constitute', fake), \
              self.assertLogs(level='WARNING') if not want else \
              _no_logs():
            update = constitutive.make_update(cfg)
            traced = jax.jit(update).trace(*args)  # the check, inside a trace
          self.assertEqual(pc.available(), want)
          if not want:  # no kernel in the program, for CUDA either
            self.assertNotIn('triton', traced.lower(
              lowering_platforms=('cuda',)).as_text())
      # Built on a thread of its own, in the solver's two forms (slices;
      # one slice with body_id), once (and traced once more for the
      # frame's CUDA branch, on this one).
      self.assertEqual(calls.count(False), 2)
      # ... one of them with the solids' dashpot (SimConfig.
      # solid_viscosity), whose terms the kernel then has.
      self.assertIn(True, visc[:2])
      self.assertIn(False, visc[:2])
    finally:
      pc._available.cache_clear()

  def test_the_check_can_start_ahead_in_the_background(self):
    """``start_probe`` (the pipeline calls it when it prepares a scene)
    runs the check on a thread of its own, once however often it is
    started; ``available`` then waits for it instead of checking again.
    (The GPU is simulated.)"""
    calls = []
    real = pc.constitute

    def interpreted(*args, **kw):
      calls.append(threading.current_thread().name)
      return real(*args, **dict(kw, interpret=True))

    try:
      pc._available.cache_clear()
      pc._PROBES.clear()
      with mock.patch.object(jax, 'default_backend', lambda: 'gpu'), \
          mock.patch.object(pc, 'probe_record', lambda dtype: None), \
          mock.patch.object(pc, 'constitute', interpreted):
        pc.start_probe('float32')
        pc.start_probe('float32')
        self.assertLen(pc._PROBES, 1)
        self.assertTrue(pc.available('float32'))
      self.assertLen(calls, 2)  # the solver's two forms, once
      self.assertNotIn(threading.main_thread().name, calls)
    finally:
      pc._available.cache_clear()
      pc._PROBES.clear()

  def test_a_passed_check_is_recorded_and_not_repeated(self):
    """A check that passed is recorded (in the compilation cache's
    folder) and a later process skips it; a failed one is not recorded.
    The record's name changes with the dtype, and there is none without a
    cache. (The GPU and the later process are simulated.)"""
    calls = []
    real = pc.constitute

    def interpreted(*args, **kw):
      calls.append(1)
      return real(*args, **dict(kw, interpret=True))

    def broken(*args, **kw):
      raise AttributeError("module 'triton' has no attribute 'load'")

    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    folder = tmp.name
    record = os.path.join(folder, 'checks', 'stress_kernel')
    try:
      with mock.patch.object(jax, 'default_backend', lambda: 'gpu'), \
          mock.patch.object(pc, 'probe_record', lambda dtype: record):
        pc._available.cache_clear()
        with mock.patch.object(pc, 'constitute', broken), \
            self.assertLogs(level='WARNING'):
          self.assertFalse(pc._available('float32'))
        self.assertFalse(os.path.exists(record))
        pc._available.cache_clear()
        with mock.patch.object(pc, 'constitute', interpreted):
          self.assertTrue(pc._available('float32'))
        self.assertLen(calls, 2)  # checked: the solver's two forms
        self.assertTrue(os.path.exists(record))
        pc._available.cache_clear()  # a later process
        with mock.patch.object(pc, 'constitute', broken):
          self.assertTrue(pc._available('float32'))  # not checked again
        self.assertLen(calls, 2)
    finally:
      pc._available.cache_clear()
    a, b = pc.probe_record('float32', folder), pc.probe_record('float64',
                                                               folder)
    self.assertTrue(a.startswith(folder))
    self.assertNotEqual(a, b)
    self.assertIsNone(pc.probe_record('float32', ''))

  def test_particles_split_over_devices_keep_the_jax_update(self):
    """Inside shard_map (particles varying over a mesh axis) even
    'pallas' runs the pure-JAX update: the same values as outside."""
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    models = ('neo_hookean', 'drucker_prager')
    F, C, Jpep, mat = _inputs(models, (10, 6), jnp.float32)
    body = jnp.full(16, -1)
    cfg = mpm.SimConfig(models=models, constitutive_kernel='pallas')
    update = constitutive.make_update(cfg)
    mesh = jax.make_mesh((1,), ('p',))
    FC = jnp.concatenate([F.reshape(9, -1), C.reshape(9, -1)])
    specs = (P(None, 'p'), P(None, 'p'), P('p'), P('p'))
    args = [jax.device_put(a, NamedSharding(mesh, s))
            for a, s in zip((FC, Jpep, body, mat), specs)]
    mat_spec = ((P('p'),) * 3,) * 3  # nested-tuple (N,) fields
    got = jax.jit(jax.shard_map(
      update, mesh=mesh, in_specs=specs,
      out_specs=(mat_spec, P(None, 'p'), mat_spec)))(*args)
    want = jax.jit(constitutive.make_update(
      dataclasses.replace(cfg, constitutive_kernel='jax')))(FC, Jpep, body,
                                                            mat)
    _assert_close(self, got, want, 1e-6)

  def test_unknown_kernel_is_named(self):
    with self.assertRaisesRegex(mpm.MPMInputError,
                                "constitutive_kernel = 'triton'; use 'auto'"):
      mpm.SimConfig(constitutive_kernel='triton')


if __name__ == '__main__':
  absltest.main()
