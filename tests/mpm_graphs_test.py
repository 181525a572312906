"""How a frame is launched on a GPU (``SimConfig.gpu_graphs``).

'frame' compiles ``mpm.run``'s frame with XLA's command buffers for the
whole substep loop (WHILE, CONDITIONAL), 'substep' with XLA's default,
'off' with none. The launch must not change a single value: on a GPU
(experiments/gpu_session.sh runs this file there) the three compile to
different executables and are compared here; on the CPU, whose XLA accepts
and ignores the options, ``compile_frame(force=True)`` still checks that
every option list parses.
"""

import dataclasses
import warnings

import jax
import numpy as np
from absl.testing import absltest

import mpm_blocks
from physsplat_jax import mpm
from physsplat_jax.mpm import graphs


class GpuGraphsTest(absltest.TestCase):

  def test_every_launch_gives_the_same_frames(self):
    """Three frames of four materials and a rigid body on a plane: the
    final state is bitwise the same however the frame is launched."""
    v = np.random.default_rng(0).normal(size=(32, 3))
    s, mat, forces, cfg = mpm_blocks.four_blocks(v)
    out = {}
    for g in mpm.GPU_GRAPHS:
      with warnings.catch_warnings():
        warnings.simplefilter('error')  # no fallback where XLA has them
        res = mpm.run(s, mat, forces, dataclasses.replace(cfg, gpu_graphs=g),
                      3)
      out[g] = res.state
    for g in ('substep', 'off'):
      for f in ('x', 'v', 'F', 'C', 'Jp'):
        np.testing.assert_array_equal(getattr(out[g], f),
                                      getattr(out['frame'], f),
                                      err_msg=f'{g}: {f}')

  def test_every_option_list_compiles(self):
    """Each gpu_graphs value's command-buffer list is one XLA accepts (the
    first of 'frame's lists: a fallback would warn, an error here), and the
    program it compiles computes what XLA's default compile does (a small
    frame: the lists do not depend on what the frame computes)."""
    s, mat, forces, cfg = mpm_blocks.one_block(np.ones(3))
    lowered = jax.jit(mpm.make_frame(cfg)).lower(s, mat, forces)
    want = lowered.compile()(s, mat, forces)
    for g in mpm.GPU_GRAPHS:
      with self.subTest(g), warnings.catch_warnings():
        warnings.simplefilter('error')
        got = graphs.compile_frame(lowered, g, force=True)(s, mat, forces)
        np.testing.assert_array_equal(got.x, want.x)

  def test_an_xla_without_the_options_falls_back_with_a_warning(self):
    """An XLA that lacks a kind of the first list gets the second, one that
    knows neither list XLA's default, each with a warning naming the
    setting; an error that is not about the option goes to XLA's default
    compile at once (its own error if that fails too)."""
    calls = []

    def lowered(accepts):

      class Lowered:

        def compile(self, compiler_options=None):
          calls.append(compiler_options)
          k = (compiler_options or {}).get('xla_gpu_enable_command_buffer')
          if k is not None and not accepts(k):
            raise ValueError('INVALID_ARGUMENT: While setting option '
                             "xla_gpu_enable_command_buffer, 'CUDNN' is not "
                             'a valid enum value.')
          return k if k is not None else 'default'

      return Lowered()

    first, second = graphs._GRAPH_KINDS['frame']
    with self.assertWarnsRegex(RuntimeWarning,
                               "gpu_graphs = 'frame'.*lacks a kind"):
      got = graphs.compile_frame(lowered(lambda k: 'CUDNN' not in k),
                                 'frame', force=True)
    self.assertEqual(got, second)
    self.assertLen(calls, 2)

    calls.clear()
    with self.assertWarnsRegex(RuntimeWarning, "gpu_graphs = 'frame'.*"
                               "gpu_graphs='substep'"):
      got = graphs.compile_frame(lowered(lambda k: False), 'frame',
                                 force=True)
    self.assertEqual(got, 'default')
    self.assertEqual(calls, [{'xla_gpu_enable_command_buffer': first},
                             {'xla_gpu_enable_command_buffer': second}, None])

    calls.clear()
    with warnings.catch_warnings():
      warnings.simplefilter('error')
      self.assertEqual(graphs.compile_frame(lowered(lambda k: True), 'frame',
                                            force=True), first)
    self.assertLen(calls, 1)

    calls.clear()

    class Broken:

      def compile(self, compiler_options=None):
        calls.append(compiler_options)
        raise RuntimeError('RESOURCE_EXHAUSTED: out of memory')

    with self.assertRaisesRegex(RuntimeError, 'out of memory'):
      graphs.compile_frame(Broken(), 'frame', force=True)
    self.assertLen(calls, 2)  # one try with the option, then the default

  def test_unknown_value_is_named(self):
    with self.assertRaisesRegex(mpm.MPMInputError,
                                "gpu_graphs = 'graph'; use 'substep'"):
      mpm.SimConfig(gpu_graphs='graph')


if __name__ == '__main__':
  absltest.main()
