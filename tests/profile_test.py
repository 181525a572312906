"""experiments/lib/profile.py (device time per kernel from a profiler trace)
and hlo.kernel_labels, which ``benchmark_substep --profile`` uses."""

import collections
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from experiments.lib import hlo
from experiments.lib import profile
from physsplat_jax import pipeline as pl
from physsplat_jax.types import Gaussians
from physsplat_jax.types import ObjectInfo
from physsplat_jax.types import Scene

_Event = collections.namedtuple('_Event', 'name start_ns duration_ns')


class LeavesTest(absltest.TestCase):

  def test_keeps_the_innermost_events(self):
    events = [
      _Event('while.5', 0, 100),        # encloses the body's thunks
      _Event('fusion.1', 10, 20),
      _Event('fusion.2', 30, 10),       # starts where fusion.1 ends
      _Event('outer', 50, 40),
      _Event('inner', 55, 10),
      _Event('after', 120, 5),
      _Event('end: after', 125, 1),     # the CPU's end markers
      _Event('StartRegion', 126, 0),    # zero-length markers
      _Event('ThunkExecutor::Execute', 130, 9),
    ]
    host = [e.name for e in profile._leaves(events, host=True)]
    self.assertEqual(host, ['fusion.1', 'fusion.2', 'inner', 'after'])
    # On a device '::' is part of template kernels' names.
    dev = [e.name for e in profile._leaves(events, host=False)]
    self.assertEqual(dev, ['fusion.1', 'fusion.2', 'inner', 'after',
                           'ThunkExecutor::Execute'])

  def test_per_call(self):
    times = dict(device='/device:GPU:0', busy_ns=9000.0, span_ns=12000.0,
                 kernels={'a_fusion': dict(count=4, ns=6000.0),
                          'b_fusion_1': dict(count=2, ns=3000.0)})
    got = profile.per_call(times, 2, {'b_fusion_1': 'p2g/scatter-add'},
                           top=1)
    # Kernels keyed by their program find their labels too.
    times['kernels']['jit_frame:b_fusion_1'] = times['kernels'].pop(
      'b_fusion_1')
    labelled = profile.per_call(times, 2, {'b_fusion_1': 'p2g/scatter-add'})
    self.assertEqual(labelled['top'][1]['label'], 'p2g/scatter-add')
    self.assertEqual(got['device'], '/device:GPU:0')
    self.assertAlmostEqual(got['busy_us'], 4.5)
    self.assertAlmostEqual(got['launches'], 3.0)
    self.assertEqual(got['top'], [dict(kernel='a_fusion', label='', us=3.0,
                                       launches=2.0)])


class TraceTest(absltest.TestCase):

  def test_kernels_of_a_traced_loop(self):
    """A scan traced on the CPU: its body's thunks, each run once per
    trip, labelled with their name scopes."""
    trips = 7

    def f(x):
      def body(c, _):
        with jax.named_scope('stepper'):
          c = jnp.sin(c) @ c.T + jnp.cos(c)
        return c, None
      return jax.lax.scan(body, x, None, length=trips)[0]

    fn = jax.jit(f)
    x = jnp.ones((96, 96))
    labels = hlo.kernel_labels(fn.lower(x).compile().as_text())
    self.assertIn('stepper', ' '.join(labels.values()))
    jax.block_until_ready(fn(x))
    with tempfile.TemporaryDirectory() as logdir:
      out, path = profile.trace(lambda: fn(x), logdir)
      times = profile.kernel_times(path)
    self.assertEqual(out.shape, (96, 96))
    self.assertEqual(times['device'], '/host:CPU')
    self.assertGreater(times['busy_ns'], 0.0)
    self.assertLessEqual(times['busy_ns'], 2 * times['span_ns'])
    # Every kernel is one of the program's instructions, named after it;
    # the product in the body runs once per trip (XLA:CPU may split it
    # into tasks).
    for name in times['kernels']:
      module, _, kernel = name.rpartition(':')
      self.assertIn(module, ('', 'jit_f'))
      self.assertIn(kernel, labels)
    steps = [k for name, k in times['kernels'].items()
             if 'stepper' in labels[name.rpartition(':')[2]]]
    self.assertNotEmpty(steps)
    self.assertTrue(all(k['count'] >= trips for k in steps))
    got = profile.per_call(times, trips, labels, top=3)
    self.assertLen(got['top'], 3)
    self.assertGreaterEqual(got['top'][0]['us'], got['top'][-1]['us'])

  def test_no_trace_is_an_error(self):
    with (tempfile.TemporaryDirectory() as logdir,
          self.assertRaisesRegex(FileNotFoundError, 'no trace under')):
      profile.newest_trace(logdir)


class FrameWindowTest(absltest.TestCase):

  def test_traces_frames_of_a_pipeline_run(self):
    """``simulate_scene(on_frame=FrameWindow(1, 3))`` on a small block:
    two frames of the loop traced, the MPM's thunks among the kernels."""
    n, spread = 5, 0.05
    g = np.stack(np.meshgrid(*[np.linspace(0, spread, n)] * 3,
                             indexing='ij'), -1).reshape(-1, 3)
    k = len(g)
    gs = Gaussians(
      means=jnp.asarray(g, jnp.float32),
      log_scales=jnp.full((k, 3), np.log(spread / n)),
      quats=jnp.tile(jnp.array([1.0, 0, 0, 0]), (k, 1)),
      opacity_logits=jnp.full((k,), 2.0), sh=jnp.full((k, 1, 3), 0.5))
    scene = Scene(gaussians=gs, object_ids=jnp.zeros(k, jnp.int32),
                  objects=(ObjectInfo('block'),), name='block')
    cfg = pl.PipelineConfig(num_frames=4, grid_res=16, max_particles=200,
                            use_mpdp=False, fill=False, render='none')
    rubber = pl.ObjectMaterial('fixed_corotated', 3e4, 0.3, 1000.0)
    with tempfile.TemporaryDirectory() as logdir:
      window = profile.FrameWindow(1, 3, logdir)
      frames = []
      pl.simulate_scene(scene, cfg, None, materials=[rubber],
                        on_frame=lambda f, *a: (frames.append(f),
                                                window(f, *a)))
      self.assertFalse(window.tracing)
      got = window.summary(top=5)
    self.assertEqual(frames, [0, 1, 2, 3, 4])
    self.assertEqual(got['frames'], [1, 3])
    self.assertEqual(got['device'], '/host:CPU')
    self.assertGreater(got['wall_ms'], 0.0)
    self.assertGreater(got['busy_ms'], 0.0)
    self.assertGreater(got['launches'], 1.0)
    self.assertLen(got['top'], 5)

  def test_window_checks_and_closes(self):
    with self.assertRaisesRegex(ValueError, 'start < stop'):
      profile.FrameWindow(3, 3, '/tmp')
    with tempfile.TemporaryDirectory() as logdir:
      window = profile.FrameWindow(0, 5, logdir)
      self.assertIsNone(window.summary())
      window(0)
      self.assertTrue(window.tracing)
      jax.block_until_ready(jnp.sin(jnp.ones(1000)) * 2)
      window.close()  # the run ended before frame 5
      self.assertFalse(window.tracing)
      self.assertIsNotNone(window.summary())


class KernelLabelsTest(absltest.TestCase):

  def test_scopes_without_plumbing(self):
    text = (
      'ENTRY %main {\n'
      '  %input_reduce_fusion.1 = f32[2]{0} fusion(%p), kind=kInput, '
      'metadata={op_name="jit(frame_fn)/checkpoint/while/body/closed_call/'
      'checkpoint/g2p/reduce_sum" stack_frame_id=3}\n'
      '  ROOT %copy.4 = f32[2]{0} copy(%input_reduce_fusion.1), '
      'metadata={op_name="jit(f)/p2g/copy"}\n'
      '}\n')
    got = hlo.kernel_labels(text)
    self.assertEqual(got['input_reduce_fusion_1'], 'g2p/reduce_sum')
    self.assertEqual(got['input_reduce_fusion.1'], 'g2p/reduce_sum')
    self.assertEqual(got['copy_4'], 'p2g/copy')


if __name__ == '__main__':
  absltest.main()
