"""The frame program stored between processes (``mpm.frame_store``).

A second process (simulated: the in-process caches cleared) reads the
stored frame instead of tracing it, and computes the same bits; a damaged
file is traced and stored again; the stored name follows everything the
lowering depends on.
"""

import os
import tempfile
from unittest import mock

import numpy as np
from absl.testing import absltest

import mpm_blocks
from physsplat_jax import mpm
from physsplat_jax.mpm import frame_store
from physsplat_jax.mpm import solver


class FrameStoreTest(absltest.TestCase):

  def setUp(self):
    super().setUp()
    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    self.folder = tmp.name
    v = np.random.default_rng(0).normal(size=(32, 3))
    self.blocks = mpm_blocks.four_blocks(v)

  def _run(self, folder):
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

    solver._COMPILED.clear()
    solver._jitted.cache_clear()
    try:
      with mock.patch.object(solver, 'make_frame', counting), \
          mock.patch.object(frame_store, '_folder', lambda: folder):
        s, mat, forces, cfg = self.blocks
        res = mpm.run(s, mat, forces, cfg, 3)
    finally:
      solver._COMPILED.clear()
      solver._jitted.cache_clear()
    return res.state, len(traced)

  def _stored(self):
    sub = os.path.join(self.folder, frame_store.FOLDER)
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
    want, _ = self._run(self.folder)
    (name,) = self._stored()
    path = os.path.join(self.folder, frame_store.FOLDER, name)
    with open(path, 'wb') as f:
      f.write(b'not a stored frame')
    with self.assertLogs(level='WARNING') as logs:
      got, n = self._run(self.folder)
    self.assertIn('cannot read', '\n'.join(logs.output))
    self.assertEqual(n, 1)
    self._assert_same(got, want)
    got, n = self._run(self.folder)  # stored again, readable
    self.assertEqual(n, 0)
    self._assert_same(got, want)

  def test_a_stored_frame_that_does_not_compile_is_traced_instead(self):
    want, _ = self._run(self.folder)  # stored
    real = solver.graphs.compile_frame
    calls = []

    def failing_once(lowered, gpu_graphs, **kw):
      calls.append(1)
      if len(calls) == 1:
        raise RuntimeError('INTERNAL: simulated compile failure')
      return real(lowered, gpu_graphs, **kw)

    with mock.patch.object(solver.graphs, 'compile_frame', failing_once), \
        self.assertLogs(level='WARNING') as logs:
      got, n = self._run(self.folder)
    self.assertIn('did not compile', '\n'.join(logs.output))
    self.assertEqual((n, len(calls)), (1, 2))  # traced anew, compiled
    self._assert_same(got, want)

  def test_the_name_follows_what_the_lowering_depends_on(self):
    import dataclasses

    import jax

    s, mat, forces, cfg = self.blocks
    with mock.patch.object(frame_store, '_folder', lambda: self.folder):
      def name(s, mat, forces, cfg):
        leaves, tree = jax.tree.flatten((s, mat, forces))
        return frame_store._path(cfg, tree, leaves)

      base = name(s, mat, forces, cfg)
      self.assertEqual(name(s, mat, forces, cfg), base)
      self.assertNotEqual(
        name(s, mat, forces, dataclasses.replace(cfg, dt=cfg.dt / 2)), base)
      longer = s.replace(x=np.zeros((s.x.shape[0] + 1, 3), np.float32))
      self.assertNotEqual(name(longer, mat, forces, cfg), base)
    with mock.patch.object(frame_store, '_folder', lambda: None):
      self.assertIsNone(name(s, mat, forces, cfg))


if __name__ == '__main__':
  absltest.main()
