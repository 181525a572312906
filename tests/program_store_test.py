"""Programs stored traced between processes (``program_store``).

A second process (simulated: the in-process caches cleared) reads the
stored MPM frame instead of tracing it, and computes the same bits; a
damaged file is traced and stored again, one that does not compile is
traced instead; the stored name follows everything the lowering depends
on; the MPDP network, stored the same way, gives the same field.
"""

import os
import tempfile
from unittest import mock

import numpy as np
from absl.testing import absltest

import mpm_blocks
from physsplat_jax import mpm
from physsplat_jax import program_store
from physsplat_jax.mpm import solver


class FrameStoreTest(absltest.TestCase):

  def setUp(self):
    super().setUp()
    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    self.folder = tmp.name
    v = np.random.default_rng(0).normal(size=(32, 3))
    self.blocks = mpm_blocks.four_blocks(v)
    # What happens around a stored frame (damaged file, failed compile)
    # does not depend on the physics in it: a frame that compiles in ~1 s.
    self.small = mpm_blocks.one_block(v[:8])

  def _run(self, folder, blocks=None):
    """Three frames as a new process would run them: (final state, how
    often the frame function was traced)."""
    traced = []
    real = solver.make_frame

    def counting(config, reduce_fn=None):
      frame = real(config, reduce_fn)

      def traced_frame(*args):
        traced.append(1)
        return frame(*args)

      return traced_frame

    solver._jitted.cache_clear()
    program_store._COMPILED.clear()
    try:
      with mock.patch.object(solver, 'make_frame', counting), \
          mock.patch.object(program_store, 'folder', lambda: folder):
        s, mat, forces, cfg = blocks or self.blocks
        res = mpm.run(s, mat, forces, cfg, 3)
    finally:
      solver._jitted.cache_clear()
      program_store._COMPILED.clear()
    return res.state, len(traced)

  def _stored(self):
    sub = os.path.join(self.folder, program_store.FOLDER)
    return sorted(os.listdir(sub)) if os.path.isdir(sub) else []

  def _assert_same(self, got, want):
    for f in ('x', 'v', 'F', 'C', 'Jp', 't'):
      np.testing.assert_array_equal(getattr(got, f), getattr(want, f),
                                    err_msg=f)

  def test_a_stored_frame_is_read_back_untraced_with_the_same_bits(self):
    want, n = self._run(None)  # no cache folder: traced, nothing stored
    self.assertEqual(n, 1)
    self.assertEqual(self._stored(), [])
    got, n = self._run(self.folder)  # traced and stored
    self.assertEqual(n, 1)
    self.assertLen(self._stored(), 1)
    self._assert_same(got, want)
    got, n = self._run(self.folder)  # read back: not traced
    self.assertEqual(n, 0)
    self._assert_same(got, want)

  def test_a_damaged_file_is_traced_and_stored_again(self):
    want, _ = self._run(self.folder, self.small)
    (name,) = self._stored()
    path = os.path.join(self.folder, program_store.FOLDER, name)
    with open(path, 'wb') as f:
      f.write(b'not a stored frame')
    with self.assertLogs(level='WARNING') as logs:
      got, n = self._run(self.folder, self.small)
    self.assertIn('cannot read', '\n'.join(logs.output))
    self.assertEqual(n, 1)
    self._assert_same(got, want)
    got, n = self._run(self.folder, self.small)  # stored again, readable
    self.assertEqual(n, 0)
    self._assert_same(got, want)

  def test_a_stored_frame_that_does_not_compile_is_traced_instead(self):
    want, _ = self._run(self.folder, self.small)  # stored
    real = solver.graphs.compile_frame
    calls = []

    def failing_once(lowered, gpu_graphs, **kw):
      calls.append(1)
      if len(calls) == 1:
        raise RuntimeError('INTERNAL: simulated compile failure')
      return real(lowered, gpu_graphs, **kw)

    with mock.patch.object(solver.graphs, 'compile_frame', failing_once), \
        self.assertLogs(level='WARNING') as logs:
      got, n = self._run(self.folder, self.small)
    self.assertIn('did not compile', '\n'.join(logs.output))
    self.assertEqual((n, len(calls)), (1, 2))  # traced anew, compiled
    self._assert_same(got, want)

  def test_the_name_follows_what_the_lowering_depends_on(self):
    import dataclasses

    import jax

    s, mat, forces, cfg = self.blocks
    with mock.patch.object(program_store, 'folder', lambda: self.folder):
      def name(s, mat, forces, cfg):
        leaves, tree = jax.tree.flatten((s, mat, forces))
        return program_store.path_for('mpm_frame', repr(cfg), tree, leaves)

      base = name(s, mat, forces, cfg)
      self.assertEqual(name(s, mat, forces, cfg), base)
      self.assertNotEqual(
        name(s, mat, forces, dataclasses.replace(cfg, dt=cfg.dt / 2)), base)
      longer = s.replace(x=np.zeros((s.x.shape[0] + 1, 3), np.float32))
      self.assertNotEqual(name(longer, mat, forces, cfg), base)
    with mock.patch.object(program_store, 'folder', lambda: None):
      self.assertIsNone(name(s, mat, forces, cfg))



class MPDPStoreTest(absltest.TestCase):

  def test_the_stored_network_gives_the_same_field(self):
    """The MPDP field at preparation, traced then read back from the
    store, equals the field without a store (a second process: the
    in-process caches cleared)."""
    import jax
    import jax.numpy as jnp

    from physsplat_jax import mpdp
    from physsplat_jax.pipeline import prepare

    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    rng = np.random.default_rng(1)
    x0 = rng.normal(size=(300, 3)).astype(np.float32)
    counts = np.array([200, 100])
    dobj = np.repeat([0, 1], counts).astype(np.int32)
    import types
    mats = [types.SimpleNamespace(E=1e5, nu=0.3, rho=1e3, model='neo_hookean',
                                  rigid=False),
            types.SimpleNamespace(E=1e6, nu=0.25, rho=2e3,
                                  model='fixed_corotated', rigid=False)]
    fields, traced = [], []
    real = mpdp.predict
    for folder in (None, tmp.name, tmp.name):
      program_store._COMPILED.clear()
      jax.clear_caches()
      with mock.patch.object(program_store, 'folder', lambda: folder), \
          mock.patch.object(prepare, '_predict_jit', jax.jit(
            lambda *a: traced.append(1) or real(*a))):
        fields.append(prepare.mpdp_stage(x0, dobj, counts, mats, True,
                                         None)[3])
    program_store._COMPILED.clear()
    self.assertEqual(len(traced), 2)  # no store, then stored; then read
    self.assertLen(os.listdir(os.path.join(tmp.name, program_store.FOLDER)),
                   1)
    for f in fields[1:]:
      np.testing.assert_array_equal(f, fields[0])
    self.assertTrue(np.all(np.isfinite(jnp.asarray(fields[0]))))


class PruneTest(absltest.TestCase):

  def test_only_the_newest_programs_of_a_name_are_kept(self):
    import time

    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    h = lambda i: f'{i:040x}'  # noqa: E731 - a 40-digit hash
    names = [f'render_{h(i)}.jaxexport' for i in range(5)]
    # Another family whose name starts alike, another suffix, other files.
    names += [f'render_count_{h(9)}.jaxexport', f'render_{h(8)}.notstored',
              'other.txt']
    # Temporary files of killed writers (an hour old) go; a live writer's
    # (just now), another family's and another suffix's stay.
    killed = f'.render_{h(6)}.123-0a1b2c.partial.jaxexport'
    live = f'.render_{h(7)}.124-0a1b2c.partial.jaxexport'
    others = [f'.render_count_{h(6)}.123-0a.partial.jaxexport',
              f'.render_{h(6)}.123-0a.partial.notstored']
    names += [killed, live] + others
    for i, n in enumerate(names):
      path = os.path.join(tmp.name, n)
      with open(path, 'w') as f:
        f.write('x')
      t = time.time() + i - (7200 if n in [killed] + others else 0)
      os.utime(path, (t, t))
    with mock.patch.object(program_store, 'KEEP', 2):
      program_store.prune(tmp.name, 'render')
    self.assertEqual(sorted(os.listdir(tmp.name)), sorted([
      f'render_{h(3)}.jaxexport', f'render_{h(4)}.jaxexport',
      f'render_count_{h(9)}.jaxexport', f'render_{h(8)}.notstored',
      'other.txt', live] + others))


class StoredJitTest(absltest.TestCase):
  """``stored_jit``: jax.jit whose programs a later process reads back."""

  def setUp(self):
    super().setUp()
    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    self.folder = tmp.name
    self.traced = []

  def _fresh(self):
    """The function as a new process has it (nothing compiled yet)."""
    import jax.numpy as jnp

    traced = self.traced

    def fun(state, scale, mode='a', *, extra=None):
      traced.append(mode)
      out = {'y': state['x'] * scale + (0.0 if extra is None else extra),
             'n': jnp.sum(state['x'])}
      n = jnp.int32(state['x'].shape[0])  # not weakly typed: stored
      return (out, n) if mode == 'a' else (out, jnp.int32(-1))

    program_store._COMPILED.clear()
    return program_store.stored_jit(fun, name='test_fun',
                                    static_argnames=('mode',))

  def test_read_back_untraced_with_the_same_bits_and_tree(self):
    import jax
    import jax.numpy as jnp

    state = {'x': jnp.arange(6.0).reshape(3, 2)}
    with mock.patch.object(program_store, 'folder', lambda: None):
      want = self._fresh()(state, 2.0, 'a', extra=jnp.ones(()))
    self.assertEqual(self.traced, ['a'])
    with mock.patch.object(program_store, 'folder', lambda: self.folder):
      first = self._fresh()(state, 2.0, 'a', extra=jnp.ones(()))
      self.assertEqual(self.traced, ['a', 'a'])  # traced and stored
      got = self._fresh()(state, 2.0, mode='a', extra=jnp.ones(()))
      self.assertEqual(self.traced, ['a', 'a'])  # read back, not traced
      # Another static value, or shape, is another program.
      other = self._fresh()(state, 2.0, 'b')
      self.assertEqual(self.traced[-1], 'b')
      self._fresh()({'x': jnp.zeros((4, 2))}, 2.0, 'a')
      stored = os.listdir(os.path.join(self.folder, program_store.FOLDER))
    self.assertLen(stored, 3)
    for out in (first, got):
      self.assertEqual(jax.tree.structure(out), jax.tree.structure(want))
      for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(want)):
        np.testing.assert_array_equal(a, b)
    self.assertEqual(got[1], 3)  # a Python value of the result, kept
    self.assertEqual(other[1], -1)

  def test_inside_a_trace_it_is_the_plain_jit(self):
    import jax
    import jax.numpy as jnp

    state = {'x': jnp.arange(4.0).reshape(2, 2)}
    with mock.patch.object(program_store, 'folder', lambda: self.folder):
      f = self._fresh()
      g = jax.grad(lambda x: f({'x': x}, 3.0, 'a')[0]['n'] * 2.0)(
        state['x'])
      y = jax.jit(lambda x: f({'x': x}, 3.0, 'a')[0]['y'])(state['x'])
    np.testing.assert_array_equal(g, np.full((2, 2), 2.0))
    np.testing.assert_array_equal(y, 3.0 * np.asarray(state['x']))
    self.assertFalse(os.path.isdir(os.path.join(self.folder,
                                                program_store.FOLDER)))

  def test_a_program_that_cannot_be_stored_is_traced_at_once_later(self):
    import jax
    import jax.numpy as jnp
    from jax import export

    state = {'x': jnp.arange(4.0).reshape(2, 2)}
    tries = []

    def refusing(fn, **k):  # traces, then refuses (as for a custom call)
      def exporting(*args):
        tries.append(1)
        jax.make_jaxpr(fn)(*args)
        raise ValueError('custom call not guaranteed stable (test)')
      return exporting

    with mock.patch.object(program_store, 'folder', lambda: self.folder), \
        mock.patch.object(export, 'export', refusing):
      a = self._fresh()(state, 2.0, 'a')
      b = self._fresh()(state, 2.0, 'a')  # a new process: no second try
    self.assertEqual((len(tries), len(self.traced)), (1, 2))
    names = os.listdir(os.path.join(self.folder, program_store.FOLDER))
    self.assertLen(names, 1)
    self.assertTrue(names[0].endswith('.notstored'))
    for out in (a, b):
      np.testing.assert_array_equal(out[0]['y'], 2.0 * np.asarray(state['x']))

  def test_what_names_a_stored_program(self):
    import jax
    import jax.numpy as jnp

    x = jnp.arange(3.0)
    with mock.patch.object(program_store, 'folder', lambda: self.folder):
      # Two functions of one name are two programs.
      add = program_store.stored_jit(lambda x: x + 1.0, name='same')
      dbl = program_store.stored_jit(lambda x: x * 2.0, name='same')
      np.testing.assert_array_equal(add(x), np.arange(3.0) + 1)
      np.testing.assert_array_equal(dbl(x), np.arange(3.0) * 2)
      # Under another matmul precision, another program (as jax.jit).
      mm = program_store.stored_jit(lambda a: a @ a, name='mm')
      mm(jnp.eye(2))
      with jax.default_matmul_precision('highest'):
        mm(jnp.eye(2))
      self.assertEqual(sum(k[1] == 'mm' for k in program_store._COMPILED),
                       2)
      # Unhashable static values: jax.jit's own error, nothing stored.
      f = program_store.stored_jit(lambda x, s: x, name='unhashable',
                                   static_argnames=('s',))
      with self.assertRaisesRegex(ValueError, 'hashable'):
        f(x, s=np.ones(3))
      # Weakly typed results (from Python scalars only) are not stored.
      w = program_store.stored_jit(lambda x, s: (x, s * 2), name='weak')
      _, r = w(x, 2.0)
      self.assertTrue(r.weak_type)
      # Called inside a trace, it is staged like jax.jit: nothing runs or
      # is stored while tracing.
      c = program_store.stored_jit(lambda x: x * 3.0, name='staged')
      jaxpr = jax.make_jaxpr(lambda y: c(x) + y)(1.0)
      self.assertIn('jit[', str(jaxpr))
    stored = os.listdir(os.path.join(self.folder, program_store.FOLDER))
    self.assertLen([n for n in stored if n.startswith('same_')], 2)
    self.assertEqual([n.rsplit('.', 1)[1] for n in stored
                      if n.startswith('weak_')], ['notstored'])
    self.assertFalse([n for n in stored if n.startswith(('unhashable_',
                                                          'staged_'))])
    program_store._COMPILED.clear()

  def test_the_host_loop_reads_its_programs_back(self):
    # The pipeline's deformation, render and initial state are stored by a
    # first run and read back by a second (a new process: the in-process
    # caches cleared), untraced, with the same frames. (That a stored
    # program gives the bits of one never stored is
    # FrameStoreTest.test_a_stored_frame_is_read_back_untraced_...)
    import jax

    import pipeline_test
    from physsplat_jax import pipeline as pl
    from physsplat_jax.pipeline import simulation

    scene = pipeline_test._scene()
    cfg = pipeline_test._config(render='fast', num_frames=2)
    prep, _ = pl.prepare_scene(jax.random.PRNGKey(0), scene,
                               [pipeline_test._RUBBER, pipeline_test._WOOD],
                               cfg)
    params = pl.init_params(prep, cfg)
    traced = []
    real = simulation.deformed_gaussians

    def counting(*a, **k):
      traced.append(1)
      return real(*a, **k)

    outs = []
    for folder in (self.folder, self.folder):
      program_store._COMPILED.clear()
      jax.clear_caches()
      images = []
      with mock.patch.object(program_store, 'folder', lambda: folder), \
          mock.patch('physsplat_jax.pipeline.host.deformed_gaussians',
                     counting):
        outs.append(pl.run(params, prep, cfg, pipelined=False,
                           on_frame=lambda f, x, im: images.append(im)))
      outs[-1].traced = len(traced)
      outs[-1].images = images
    program_store._COMPILED.clear()
    self.assertEqual([o.traced for o in outs], [1, 1])
    names = os.listdir(os.path.join(self.folder, program_store.FOLDER))
    for name in ('host_deform', 'render', 'initial_state'):
      self.assertTrue(any(n.startswith(name + '_') for n in names), name)
    first, again = outs
    np.testing.assert_array_equal(again.gaussian_positions,
                                  first.gaussian_positions)
    np.testing.assert_array_equal(again.particle_positions,
                                  first.particle_positions)
    self.assertLen(again.images, 3)
    self.assertGreater(np.ptp(np.asarray(first.images[-1])), 0)  # drawn
    for a, b in zip(again.images, first.images):
      np.testing.assert_array_equal(a, b)


if __name__ == '__main__':
  absltest.main()
