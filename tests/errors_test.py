"""Bad input ends in one clear error, before any work is lost.

The scripts' one error path (experiments/lib/cli.py), validation at the
boundary (configs, flags, scenes, materials, output folders), refusal of
impossible runs, the jitted path's finite flag, and report.json on failure.
"""

import contextlib
import io
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app
from absl.testing import absltest

from experiments.lib import cli
from experiments.lib import simulate as lib
from physsplat_jax import pipeline as pl
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.mpm import SimulationError
from physsplat_jax.io import outputs
from physsplat_jax.types import DataError
from physsplat_jax.types import Gaussians
from physsplat_jax.types import ObjectInfo
from physsplat_jax.types import Scene
from physsplat_jax.types import make_camera

_RUBBER = pl.ObjectMaterial('fixed_corotated', 3e4, 0.3, 1000.0)
_KEY = jax.random.PRNGKey(0)


def _block_scene(n=6, spread=0.05):
  g = np.stack(np.meshgrid(*[np.linspace(0, spread, n)] * 3, indexing='ij'),
               -1).reshape(-1, 3).astype(np.float32)
  k = len(g)
  gs = Gaussians(
    means=jnp.asarray(g), log_scales=jnp.full((k, 3), np.log(spread / n)),
    quats=jnp.tile(jnp.array([1.0, 0, 0, 0]), (k, 1)),
    opacity_logits=jnp.full((k,), 2.0), sh=jnp.full((k, 1, 3), 0.5))
  return Scene(gaussians=gs, object_ids=jnp.zeros(k, jnp.int32),
               objects=(ObjectInfo('block'),), name='block')


_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _script(module, *args):
  """``python -m module args`` from the repository root: (exit code, its
  ``error:`` line or the last line of stderr, stderr)."""
  proc = subprocess.run([sys.executable, '-m', module, *args],
                        capture_output=True, text=True, check=False,
                        timeout=120, cwd=_ROOT)
  lines = [ln for ln in proc.stderr.splitlines() if ln.strip()] or ['']
  error = [ln for ln in lines if ln.startswith('error:')] or lines[-1:]
  return proc.returncode, error[-1], proc.stderr


def _run_guarded(exc):
  def main(argv):
    del argv
    raise exc

  err = io.StringIO()
  with contextlib.redirect_stderr(err), absltest.mock.patch.object(
      cli, '_verbose', return_value=False), absltest.mock.patch.object(
        cli, '_setup'):
    try:
      cli.guard(main)([])
    except SystemExit as e:
      return e.code, err.getvalue()
  return None, err.getvalue()


class ErrorPathTest(absltest.TestCase):

  def test_package_errors_are_one_line_exit_1(self):
    code, text = _run_guarded(pl.PipelineError('object x: bad, use y'))
    self.assertEqual(code, 1)
    self.assertEqual(text, 'error: object x: bad, use y\n')
    code, text = _run_guarded(FileNotFoundError(2, 'No such file', 'a.ply'))
    self.assertEqual(code, 1)
    self.assertIn("a.ply", text)

  def test_orbax_log_lines_are_quiet_unless_debug(self):
    # A short training run logged 97 orbax INFO lines of its 103; on a
    # full disk four tracebacks stood above the one-line error.
    def record(level, path, exc=None):
      return logging.LogRecord('absl', level, path, 1, 'msg', None, exc)

    orbax = os.path.join('', 'site-packages', 'orbax', 'checkpoint', 'x.py')
    quiet = cli._QuietOrbax()  # noqa: SLF001
    try:
      raise ValueError('deep')
    except ValueError:
      exc = sys.exc_info()
    with absltest.mock.patch.object(cli, '_verbose', return_value=False):
      self.assertFalse(quiet.filter(record(logging.INFO, orbax)))
      self.assertTrue(quiet.filter(record(logging.INFO, '/pkg/train.py')))
      err = record(logging.ERROR, orbax, exc)
      self.assertTrue(quiet.filter(err))
      self.assertIsNone(err.exc_info)
    with absltest.mock.patch.object(cli, '_verbose', return_value=True):
      self.assertTrue(quiet.filter(record(logging.INFO, orbax)))
      err = record(logging.ERROR, orbax, exc)
      self.assertTrue(quiet.filter(err))
      self.assertIsNotNone(err.exc_info)

  def test_list_flags_of_counts_are_checked(self):
    # benchmark_mpm --sizes=0 was an IndexError from inside the solver.
    self.assertEqual(cli.positive_ints('sizes', ['10', '2']), [10, 2])
    for bad in (['0'], ['abc'], [], ['3', '-1']):
      with self.subTest(bad), self.assertRaisesRegex(
          app.UsageError, '--sizes=.*: give whole numbers >= 1'):
        cli.positive_ints('sizes', bad)

  def test_out_of_memory_is_one_line_with_what_to_shrink(self):
    # XLA's RESOURCE_EXHAUSTED came out as a JAX traceback.
    try:
      jax.jit(lambda: jnp.zeros((2 ** 44,), jnp.float32))().block_until_ready()
    except RuntimeError as e:
      oom = e
    else:
      self.skipTest('this machine allocated 64 TiB')
    code, text = _run_guarded(oom)
    self.assertEqual(code, 1)
    self.assertRegex(text, r'^error: out of memory \(Out of memory '
                     r'allocating 70368744177664 bytes\.\): .*'
                     r'--config\.max_particles, --config\.grid_res')
    self.assertEqual(text.count('\n'), 1)
    with self.assertRaisesRegex(RuntimeError, 'something else'):
      _run_guarded(RuntimeError('something else'))

  def test_usage_errors_exit_2(self):
    code, text = _run_guarded(app.UsageError('--poke: expected NAME:values'))
    self.assertEqual(code, 2)
    self.assertEqual(text, 'error: --poke: expected NAME:values\n')

  def test_sigterm_takes_the_interrupts_way_out(self):
    # SIGTERM (a batch system's time limit, kill) ended a script at once:
    # frames queued for the writers, report.json and the training steps
    # since the last checkpoint were lost. Now it is raised as Terminated,
    # a KeyboardInterrupt, and the script exits 143.
    seen = []

    def main(argv):
      del argv
      try:
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(500):
          time.sleep(0.01)
      except KeyboardInterrupt as e:
        seen.append(e)
        raise

    err = io.StringIO()
    with contextlib.redirect_stderr(err), absltest.mock.patch.object(
        cli, '_verbose', return_value=False), absltest.mock.patch.object(
          cli, '_setup'):
      with self.assertRaises(SystemExit) as cm:
        cli.guard(main)([])
    self.assertEqual(cm.exception.code, 143)
    self.assertEqual(err.getvalue(), 'error: terminated (SIGTERM)\n')
    self.assertIsInstance(seen[0], cli.Terminated)
    self.assertIs(signal.getsignal(signal.SIGTERM), signal.SIG_DFL)

  def test_sigterm_still_caught_after_jax_distributed_starts(self):
    # jax.distributed's preemption service installs its own SIGTERM handler
    # (C level): the signal was swallowed and a sweep under Slurm ran on
    # until SIGKILL. cli.catch_sigterm() (sweep.py calls it) takes it back.
    code = (
      'import os, signal, socket, time\n'
      'from experiments.lib import cli\n'
      'def main(argv):\n'
      '  import jax\n'
      '  s = socket.socket(); s.bind(("127.0.0.1", 0))\n'
      '  port = s.getsockname()[1]; s.close()\n'
      '  jax.distributed.initialize(f"127.0.0.1:{port}", 1, 0)\n'
      '  cli.catch_sigterm()\n'
      '  os.kill(os.getpid(), signal.SIGTERM)\n'
      '  for _ in range(1000): time.sleep(0.01)\n'
      '  print("ran on")\n'
      'cli.run(main)\n')
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True,
                          text=True, timeout=120, cwd=_ROOT,
                          env=dict(os.environ, JAX_PLATFORMS='cpu'))
    self.assertEqual(proc.returncode, 143, proc.stderr[-2000:])
    self.assertIn('error: terminated (SIGTERM)', proc.stderr)
    self.assertNotIn('ran on', proc.stdout)

  def test_a_second_sigterm_lets_the_cleanup_finish(self):
    # A second SIGTERM during the cleanup (writers closing, a checkpoint
    # being saved) raised again and lost the output.
    with tempfile.TemporaryDirectory() as d:
      done = os.path.join(d, 'done')
      code = (
        'import os, signal, sys, time\n'
        'from experiments.lib import cli\n'
        'def main(argv):\n'
        '  try:\n'
        '    os.kill(os.getpid(), signal.SIGTERM)\n'
        '    for _ in range(1000): time.sleep(0.01)\n'
        '  finally:\n'
        '    os.kill(os.getpid(), signal.SIGTERM)\n'
        '    for _ in range(20): time.sleep(0.01)\n'
        '    open(sys.argv[1], "w").write("closed")\n'
        'cli.run(main)\n')
      proc = subprocess.run([sys.executable, '-c', code, done],
                            capture_output=True, text=True, timeout=120,
                            cwd=_ROOT, env=dict(os.environ,
                                                JAX_PLATFORMS='cpu'))
      self.assertEqual(proc.returncode, 143, proc.stderr[-2000:])
      self.assertIn('SIGTERM again: still closing', proc.stderr)
      self.assertIn('error: terminated (SIGTERM)', proc.stderr)
      with open(done) as f:
        self.assertEqual(f.read(), 'closed')

  def test_a_terminated_parent_lets_its_child_end_in_order(self):
    # benchmark_pipeline's experiments.simulate runs: subprocess.run
    # SIGKILLed the child 0.25 s after the parent's interruption, so the
    # child lost the frames and report.json it would have written.
    child = ('import signal, sys, time\n'
             'def bye(*_):\n'
             '  time.sleep(0.5)\n'
             '  open(sys.argv[1], "w").write("closed")\n'
             '  sys.exit(0)\n'
             'signal.signal(signal.SIGTERM, bye)\n'
             'print("ready", flush=True)\n'
             'time.sleep(30)\n')
    with tempfile.TemporaryDirectory() as d:
      done = os.path.join(d, 'done')
      timer = threading.Timer(1.5, os.kill, (os.getpid(), signal.SIGTERM))
      with cli._sigterm_as_interrupt():  # noqa: SLF001
        timer.start()
        with self.assertRaises(cli.Terminated):
          cli.run_child([sys.executable, '-c', child, done])
      timer.join()
      with open(done) as f:
        self.assertEqual(f.read(), 'closed')

  def test_unknown_config_field_is_one_line_exit_2(self):
    # ml_collections applies --config.* overrides while the script's flag
    # is defined, at import, or, with --config=FILE, while flags are
    # parsed: no traceback from inside it either way. A near miss, which
    # ml_collections words with a suggestion, was a traceback.
    file = 'experiments/configs/simulate.py'
    for args, want in (
        (['--config.nosuch=1'], "error: the config has no field 'nosuch' "
         f'(--config.nosuch=1); {file} lists the fields\n'),
        ([f'--config={file}', '--config.nosuch=1'],
         "error: the config has no field 'nosuch' (--config.nosuch=1); "
         f'{file} lists the fields\n'),
        (['--config.grid_rez=1'], "error: the config has no field "
         "'grid_rez' (--config.grid_rez=1); did you mean 'grid_res'? "
         f'{file} lists the fields\n'),
        # absl's space form names the file too (it named the default).
        (['--config', 'experiments/configs/demo.py', '--config.nosuch=1'],
         "error: the config has no field 'nosuch' (--config.nosuch=1); "
         'experiments/configs/demo.py lists the fields\n')):
      proc = subprocess.run(
        [sys.executable, '-m', 'experiments.simulate', *args,
         '--config.num_frames=2'], capture_output=True, text=True,
        check=False, timeout=120,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
      with self.subTest(args):
        self.assertEqual(proc.returncode, 2, proc.stderr)
        self.assertNotIn('Traceback', proc.stderr)
        self.assertTrue(proc.stderr.endswith(want), proc.stderr)

  def test_config_file_is_read_from_flags_before_double_dash(self):
    # After absl's '--' nothing is a flag: a '--config=' there is a
    # positional argument, not the config file the message should name.
    argv = ['prog', '--config', 'a.py', '--config.x=1', '--', '--config=b.py']
    self.assertEqual(cli._given(argv, 'config'), 'a.py')
    self.assertIsNone(cli._given(['prog', '--', '--config=b.py'], 'config'))
    self.assertEqual(cli._given(['prog', '--config=c.py'], 'config'), 'c.py')

  def test_bad_flags_are_one_line_exit_2(self):
    for args, want in ((['--config.num_frames=abc'],
                        "error: flag --config.num_frames=abc: invalid "
                        "literal for int()"),
                       (['--nosuch_flag=1'], 'error: Unknown command line '
                        'flag \'nosuch_flag\'')):
      proc = subprocess.run(
        [sys.executable, '-m', 'experiments.simulate', *args],
        capture_output=True, text=True, check=False, timeout=120,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
      with self.subTest(args[0]):
        self.assertEqual(proc.returncode, 2, proc.stderr)
        self.assertNotIn('Traceback', proc.stderr)
        self.assertNotIn('FATAL', proc.stderr)
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        self.assertTrue(lines[-1].startswith(want), lines[-1])

  def test_bad_config_files_are_one_line_exit_2(self):
    # Both were tracebacks from inside ml_collections.
    with tempfile.TemporaryDirectory() as d:
      broken = os.path.join(d, 'broken.py')
      with open(broken, 'w') as fh:
        fh.write('def get_config(:\n')
      for path, want in (
          ('experiments/configs/jelly_drop.json',
           'error: --config=experiments/configs/jelly_drop.json: not a '
           'config file'),
          (broken, f'error: config file {broken}, line 1: invalid syntax')):
        proc = subprocess.run(
          [sys.executable, '-m', 'experiments.simulate', '--out=/nonexistent',
           f'--config={path}'], capture_output=True, text=True, check=False,
          timeout=120,
          cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        with self.subTest(path):
          self.assertEqual(proc.returncode, 2, proc.stderr)
          self.assertNotIn('Traceback', proc.stderr)
          self.assertTrue(proc.stderr.strip().splitlines()[-1].startswith(
            want), proc.stderr[-500:])

  def test_physgaussian_refuses_flags_it_would_ignore(self):
    proc = subprocess.run(
      [sys.executable, '-m', 'experiments.simulate', '--out=/nonexistent',
       '--physgaussian=experiments/configs/jelly_drop.json',
       '--velocity=*:5,0,0', '--config.num_frames=1', '--config.width=64'],
      capture_output=True, text=True, check=False, timeout=120,
      cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    self.assertEqual(proc.returncode, 2, proc.stderr)
    last = proc.stderr.strip().splitlines()[-1]
    self.assertIn('--velocity, --config.num_frames would be ignored', last)
    self.assertNotIn('width', last.split('would be ignored')[0])
    # It blamed the default --scene: "PLY file not found: tabletop".
    proc = subprocess.run(
      [sys.executable, '-m', 'experiments.simulate', '--out=/nonexistent',
       '--physgaussian=experiments/configs/jelly_drop.json'],
      capture_output=True, text=True, check=False, timeout=120,
      cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    self.assertEqual(proc.returncode, 2, proc.stderr)
    self.assertTrue(proc.stderr.endswith(
      '--scene=tabletop is a built-in scene: give --scene=FILE.ply, the '
      'Gaussians the JSON was written for\n'), proc.stderr[-300:])

  def test_library_calls_with_the_wrong_kind_of_argument_are_named(self):
    # Each was an AttributeError or a silent wrong value from inside.
    import types as pytypes

    import physsplat_jax as ps
    with self.assertRaisesRegex(pl.PipelineError, "scene must be a "
                                r"physsplat_jax\.Scene, got str 'tabletop'.*"
                                'load_scene'):
      pl.prepare_scene(_KEY, 'tabletop', [], pl.PipelineConfig())
    prepared = pytypes.SimpleNamespace(
      spec=pytypes.SimpleNamespace(object_names=('a',)),
      x0=np.zeros((1, 3), np.float32))
    with self.assertRaisesRegex(pl.PipelineError, 'config is a '
                                'SimulateConfig; give a PrepareConfig'):
      pl.init_params(prepared, pl.PipelineConfig().simulate, use_mpdp=False)
    self.assertEqual(
      pl.init_params(prepared, pl.PipelineConfig(initial_velocity=(
        ('a', (1.0, 2.0, 3.0)),)), use_mpdp=False).velocity.tolist(),
      [[1.0, 2.0, 3.0]])
    # Forces as dicts, as config files write them.
    c = pl.PipelineConfig(forces=[dict(kind='point', object='a',
                                       vector=(1, 0, 0), end=0.5)])
    self.assertEqual(c.forces[0], pl.ForceSpec('point', 'a', (1.0, 0.0, 0.0),
                                               end=0.5))
    g = _block_scene().gaussians
    for camera, want in (([1], r'camera is a list, not a physsplat_jax\.'
                          r'Camera; pick one, e\.g\. scene\.cameras\[0\]'),
                         (None, 'camera is a NoneType')):
      with self.subTest(camera), self.assertRaisesRegex(PhysSplatError, want):
        ps.render_image(g, camera)
    for call, want in (
        (lambda: ps.quat_to_rotmat(jnp.ones(3)), r'quaternions have shape '
         r'\(3,\); give \(\.\.\., 4\)'),
        (lambda: ps.covariance(jnp.ones((2, 2)), jnp.ones((2, 4))),
         r'log-scales have shape \(2, 2\)'),
        (lambda: ps.eval_sh(jnp.ones((2, 5, 3)), jnp.ones((2, 3))),
         r'SH coefficients have shape \(2, 5, 3\)'),
        (lambda: ps.eval_sh(jnp.ones((2, 4, 3)), jnp.ones((2, 2))),
         r'directions have shape \(2, 2\)')):
      with self.subTest(want), self.assertRaisesRegex(DataError, want):
        call()
    # mpm.run is a host loop: under jit it was a TracerArrayConversionError.
    from physsplat_jax import mpm
    cfg = mpm.SimConfig(grid=mpm.GridSpec(res=8, size=1.0), dt=1e-3,
                        substeps_per_frame=1)
    mats = mpm.make_materials('fixed_corotated', 1e4, 0.3, 1000.0, num=1)
    state = mpm.init_state(np.full((1, 3), 0.5), np.zeros((1, 3)), 1e-4,
                           mats, cfg)
    with self.assertRaisesRegex(mpm.MPMInputError, r'mpm\.run is a host '
                                r'loop.*mpm\.rollout'):
      jax.jit(lambda s: mpm.run(s, mats, None, cfg, 1).state.x)(state)

  def test_a_segmentation_with_nothing_to_move_says_so(self):
    # prepare_scene said "clear ObjectInfo.fixed", which a script user
    # cannot do.
    from physsplat_jax.pipeline import job
    rng = np.random.default_rng(0)
    k = 400  # a flat square: the support plane, nothing on it
    means = np.c_[rng.uniform(-1, 1, (k, 2)), np.zeros(k)]
    g = Gaussians(means=jnp.asarray(means, jnp.float32),
                  log_scales=jnp.full((k, 3), np.log(0.02), jnp.float32),
                  quats=jnp.tile(jnp.array([1.0, 0, 0, 0]), (k, 1)),
                  opacity_logits=jnp.full((k,), 2.0),
                  sh=jnp.full((k, 1, 3), 0.3))
    scene = Scene(gaussians=g, object_ids=jnp.zeros(k, jnp.int32),
                  objects=(ObjectInfo('all'),), name='flat')
    with self.assertRaisesRegex(pl.PipelineError, r"segmenting scene 'flat' "
                                r"with 'geometric' found .*nothing to move\. "
                                'Try another method'):
      job.segment_stage(scene, 'geometric')

  def test_a_video_too_wide_for_the_encoder_is_refused_first(self):
    # libx264 failed at the end of the run, after the whole simulation.
    import types as pytypes

    from physsplat_jax.pipeline import host
    prepared = pytypes.SimpleNamespace(camera=pytypes.SimpleNamespace(
      width=16385, height=384))
    with tempfile.TemporaryDirectory() as d:
      with self.assertRaisesRegex(outputs.OutputError, 'frames of 16385 x '
                                  '384 pixels: the MP4 encoder'):
        host.default_writers(prepared, d, 24.0)
      self.assertEqual(os.listdir(d), [])

  def test_outputs_of_an_earlier_run_are_named_in_the_report(self):
    # A failed rerun into the same --out left the earlier video and
    # trajectory beside a report.json with "error", nothing telling them
    # apart; a rerun without --ply kept the earlier ply/ silently.
    from physsplat_jax.pipeline import job
    with tempfile.TemporaryDirectory() as d:
      for name in ('video.mp4', 'trajectory.npz', 'ply/frame_0000.ply',
                   'spz/frame_0000.spz', 'frames/frame_0000.png'):
        os.makedirs(os.path.dirname(os.path.join(d, name)), exist_ok=True)
        with open(os.path.join(d, name), 'w') as fh:
          fh.write('x')
        os.utime(os.path.join(d, name), (1e9, 1e9))
      # This run wrote the frames and the trajectory anew.
      os.utime(os.path.join(d, 'frames/frame_0000.png'), (3e9, 3e9))
      os.utime(os.path.join(d, 'trajectory.npz'), (3e9, 3e9))
      report = {}
      with self.assertLogs(level='WARNING') as logs:
        job._note_earlier_outputs(d, 2e9, report)
      self.assertEqual(report['earlier_files'], ['video.mp4', 'ply', 'spz'])
      self.assertIn('video.mp4, ply, spz from an earlier run',
                    ' '.join(logs.output))
      self.assertTrue(os.path.exists(os.path.join(d, 'video.mp4')))
      fresh = {}
      job._note_earlier_outputs(d, 5e8, fresh)
      self.assertNotIn('earlier_files', fresh)
      # A finished run says what it wrote: the rest is earlier.
      done = {}
      with self.assertLogs(level='WARNING'):
        job._note_earlier_outputs(d, 5e8, done, written={
          'video': os.path.join(d, 'video.mp4'),
          'frames': os.path.join(d, 'frames')})
      self.assertEqual(done['earlier_files'],
                       ['trajectory.npz', 'ply', 'spz'])

  def test_help_lists_the_config_flag_and_exits_0(self):
    # --help showed only the module's own DEFINEs (--config was cli's) and
    # exited 1, absl's default, which a `set -e` script took for a failure.
    proc = subprocess.run(
      [sys.executable, '-m', 'experiments.fit_material', '--help'],
      capture_output=True, text=True, check=False, timeout=120,
      cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    self.assertEqual(proc.returncode, 0, proc.stderr[-500:])
    self.assertIn('--config: config file (its sim.task is used)',
                  proc.stdout + proc.stderr)

  def test_config_files_of_the_wrong_kind_are_named(self):
    # Each was an AttributeError from the script, or ml_collections' whole
    # traceback squashed into one line.
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory() as tmp:
      plain = os.path.join(tmp, 'plain.py')
      with open(plain, 'w') as fh:
        fh.write('def get_config():\n  return {"sim": 1}\n')
      typed = os.path.join(tmp, 'typed.py')
      with open(typed, 'w') as fh:
        fh.write('from experiments.configs.simulate import get_config as g'
                 '\n\n\ndef get_config():\n  c = g()\n'
                 '  c.gravity = (0.0, 0.0, -9.8)\n  return c\n')
      for script, config, want in (
          ('fit_material', 'experiments/configs/simulate.py',
           'error: --config=experiments/configs/simulate.py: this script '
           'reads sim.task from its config, which this file does not have; '
           'experiments/configs/mpdp.py is one that fits'),
          ('fit_material', plain, f'error: --config={plain}: its '
           'get_config() returned a dict; return an ml_collections.'
           'ConfigDict'),
          ('simulate', typed, f'error: config file {typed}, line 6: '
           "TypeError: Could not override field 'gravity'")):
        proc = subprocess.run(
          [sys.executable, '-m', f'experiments.{script}', f'--config={config}',
           '--out=/nonexistent'], capture_output=True, text=True,
          check=False, timeout=120, cwd=root)
        with self.subTest(script=script, config=config):
          self.assertEqual(proc.returncode, 2, proc.stderr[-500:])
          self.assertNotIn('Traceback', proc.stderr)
          self.assertTrue(proc.stderr.strip().splitlines()[-1].startswith(
            want), proc.stderr[-500:])

  def test_sweep_checks_scales_and_devices_first(self):
    # A negative or NaN scale was a math domain error in the substep
    # estimate; --num_devices=2 on one CPU named XLA_FLAGS, not the
    # script's own --cpu_devices.
    for arg, want in (('--e_scale=1,-1', '--e_scale=1,-1: give numbers > 0'),
                      ('--rho_scale=nan', '--rho_scale=nan: give numbers'),
                      ('--num_devices=0', '--num_devices=0: give 1 to '),
                      ('--num_devices=2', '--cpu_devices=N splits it'),
                      # 0.45 x 1.1 was clipped to 0.49 and recorded as run
                      ('--nu_scale=1,1.1', 'exceeds 0.49, the largest one')):
      proc = subprocess.run(
        [sys.executable, '-m', 'experiments.sweep', '--out=/nonexistent',
         '--frames=1', arg], capture_output=True, text=True, check=False,
        timeout=120,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
      with self.subTest(arg):
        self.assertEqual(proc.returncode, 2, proc.stderr[-500:])
        self.assertNotIn('Traceback', proc.stderr)
        self.assertIn(want, proc.stderr.strip().splitlines()[-1])

  def test_fit_material_checks_its_flags_first(self):
    # --E_init=-1 used to end in a FloatingPointError traceback at step 0.
    proc = subprocess.run(
      [sys.executable, '-m', 'experiments.fit_material',
       '--config=experiments/configs/mpdp.py', '--E_init=-1'],
      capture_output=True, text=True, check=False, timeout=120,
      cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    self.assertEqual(proc.returncode, 2, proc.stderr)
    self.assertEqual(proc.stderr.strip().splitlines()[-1],
                     'error: --E_init=-1.0: give a finite fraction of the '
                     'true mean E > 0')
    # A negative seed was NumPy's traceback after the scene was prepared;
    # no --observe ran nothing and exited 0.
    for arg, want in (('--seeds=-1', 'error: --seeds=-1: give integer seeds '
                       '>= 0'),
                      ('--observe=', 'error: --observe=: give trajectory '
                       'and/or video')):
      proc = subprocess.run(
        [sys.executable, '-m', 'experiments.fit_material',
         '--config=experiments/configs/mpdp.py', arg],
        capture_output=True, text=True, check=False, timeout=120,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
      with self.subTest(arg):
        self.assertEqual(proc.returncode, 2, proc.stderr[-500:])
        self.assertTrue(proc.stderr.strip().splitlines()[-1].startswith(
          want), proc.stderr[-300:])

  def test_every_script_runs_through_cli_run(self):
    # app.run directly would keep absl's 'FATAL Flags parsing error' (exit
    # 1) and the package's errors as tracebacks.
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    folder = os.path.join(root, 'experiments')
    scripts = [f for f in sorted(os.listdir(folder)) if f.endswith('.py')
               and "__name__ == '__main__'" in open(
                 os.path.join(folder, f)).read()]
    self.assertGreater(len(scripts), 10)
    for name in scripts:
      with self.subTest(name):
        text = open(os.path.join(folder, name)).read()
        main = text[text.index("__name__ == '__main__'"):]
        self.assertIn('cli.run(', main)
        self.assertNotIn('app.run(', main)

  def test_missing_config_file_with_overrides_is_one_line(self):
    # With a --config.X override ml_collections raised from deep inside
    # itself (a long traceback); without one it was already one line.
    for args in (['--config=/no/such.py', '--config.num_frames=2'],
                 ['--config=/no/such.py']):
      code, error, stderr = _script('experiments.simulate',
                                    '--out=/nonexistent', *args)
      with self.subTest(len(args)):
        self.assertEqual(code, 2, stderr)
        self.assertNotIn('Traceback', stderr)
        self.assertEqual(
          error, "error: --config='/no/such.py': no such .py config file")

  def test_render_checks_out_and_background_before_rendering(self):
    # Each failed only after rendering (a raw errno message), or, for the
    # background, was accepted.
    with tempfile.TemporaryDirectory() as d:
      blocker = os.path.join(d, 'somefile')
      open(blocker, 'w').close()
      cases = [([f'--out={blocker}/x.png'], 1,
                f'error: --out={blocker}/x.png: output folder '
                f"'{blocker}' is a file; give a folder name"),
               ([f'--out={d}/x.png', '--background=2,0,0'], 2,
                'error: --background=2,0,0: give a name (black, white, '
                'grey, gray) or three numbers in [0, 1]'),
               ([f'--out={d}/x.png', '--width=0'], 2,
                'error: --width=0: give a whole number of pixels >= 1'),
               ([f'--out={d}/x.png', '--height=-4'], 2,
                'error: --height=-4: give a whole number of pixels >= 1'),
               ([f'--out={d}/x.png', '--sh_degree=4'], 2,
                'error: --sh_degree=4: give 0..3')]
      if os.path.isdir('/proc'):
        cases.append((['--out=/proc/x.png'], 1,
                      "error: --out=/proc/x.png: output folder '/proc' "
                      'cannot be written'))
      for args, want_code, want in cases:
        code, error, stderr = _script('experiments.render', '--scene=donut',
                                      *args)
        with self.subTest(args[-1]):
          self.assertEqual(code, want_code, stderr)
          self.assertNotIn('Traceback', stderr)
          self.assertTrue(error.startswith(want), error)
      self.assertEqual(os.listdir(d), ['somefile'])  # nothing rendered

  def test_validate_physics_checks_its_flags_before_the_cases(self):
    # --phis=abc was float('abc') in a traceback; a bad --out failed after
    # every case had run.
    code, error, stderr = _script('experiments.validate_physics',
                                  '--cases=repose', '--quick', '--phis=abc')
    self.assertEqual(code, 2, stderr)
    self.assertNotIn('Traceback', stderr)
    self.assertEqual(error, 'error: --phis=abc: give friction angles in '
                     '(0, 90) deg separated by commas, such as '
                     '--phis=20,30,40')
    with tempfile.TemporaryDirectory() as d:
      blocker = os.path.join(d, 'somefile')
      open(blocker, 'w').close()
      out = os.path.join(blocker, 'x.json')
      code, error, stderr = _script('experiments.validate_physics',
                                    '--cases=free_fall', '--quick',
                                    f'--out={out}')
    self.assertEqual(code, 1, stderr)
    self.assertTrue(error.startswith(f'error: --out={out}: output folder'),
                    error)
    self.assertNotIn('free_fall', stderr.replace('--cases=free_fall', ''))

  def test_benchmarks_check_their_flags_before_the_runs(self):
    # Each was found after the runs (a bad --out: the results lost to a
    # raw errno message), only inside a case's subprocess (exit 0), or as
    # a traceback (--repeats=0: min() of an empty sequence).
    with tempfile.TemporaryDirectory() as d:
      blocker = os.path.join(d, 'somefile')
      open(blocker, 'w').close()
      out = os.path.join(blocker, 'x.json')
      cases = [
        (['experiments.benchmark_mpm', '--sizes=64', '--steps=1',
          '--repeats=1', '--nonaive', '--nograd', f'--out={out}'], 1,
         f'error: --out={out}: output folder'),
        (['experiments.benchmark_mpm', '--steps=0'], 2,
         'error: flag --steps=0: 0 is not a positive integer'),
        (['experiments.benchmark_render', '--repeats=0'], 2,
         'error: flag --repeats=0: 0 is not a positive integer'),
        (['experiments.benchmark_mpdp', '--methods=grid,bogus'], 2,
         "error: --methods=grid,bogus: unknown ['bogus']; use grid, brute"),
        (['experiments.benchmark_mpdp', '--shapes=cube'], 2,
         "error: --shapes=cube: unknown ['cube']; use torus, donut, plate"),
        (['experiments.benchmark_substep', '--variants=foo'], 2,
         "error: --variants: unknown ['foo']; use some of scene"),
      ]
      for args, want_code, want in cases:
        code, error, stderr = _script(*args)
        with self.subTest(' '.join(args[:2])):
          self.assertEqual(code, want_code, stderr)
          self.assertNotIn('Traceback', stderr)
          self.assertTrue(error.startswith(want), error)

  def test_benchmarks_name_the_machine_and_a_failed_childs_error(self):
    info = cli.machine()
    self.assertTrue(info['cpu'])
    self.assertEqual(info['device_kind'], jax.devices()[0].device_kind)
    self.assertEqual(info['cores'], os.cpu_count())
    self.assertNotIn('device_kind', cli.machine(devices=False))
    # JAX prints its note on filtered frames after the error itself.
    stderr = ('Traceback (most recent call last):\n  File "x.py"\n'
              "RuntimeError: Unable to initialize backend 'bogus'\n"
              '--------------------\nFor simplicity, JAX has removed its '
              'internal frames from the traceback\n')
    self.assertEqual(cli.last_error(stderr),
                     "RuntimeError: Unable to initialize backend 'bogus'")
    self.assertEqual(cli.last_error('log\nerror: --x=1: bad\nmore\n'),
                     'error: --x=1: bad')
    self.assertEqual(cli.last_error('a\nkilled\n'), 'killed')
    self.assertEqual(cli.last_error(''), '')

  def test_physgaussian_missing_file_names_its_flag(self):
    # It said 'pass --config=PATH.json': --config is the .py config.
    code, error, stderr = _script(
      'experiments.simulate', '--out=/nonexistent',
      '--physgaussian=/no/such.json')
    self.assertEqual(code, 2, stderr)
    self.assertEqual(
      error, 'error: --physgaussian=/no/such.json: no such file; give the '
      'path of a PhysGaussian .json config (e.g. '
      'experiments/configs/jelly_drop.json)')

  def test_unexpected_errors_keep_their_traceback(self):
    with self.assertRaises(ZeroDivisionError):
      _run_guarded(ZeroDivisionError('bug'))

  def test_every_error_class_is_a_physsplat_error(self):
    import physsplat_jax as ps
    from physsplat_jax.io import mllm
    from physsplat_jax.io import video

    for cls in (ps.PlyError, ps.SceneFileError, ps.PipelineError,
                ps.SimulationError, ps.physgaussian.ConfigError,
                mllm.MLLMError, video.VideoError, outputs.OutputError,
                ps.perception.MaterialChoiceError,
                ps.perception.PerceptionError,
                ps.segmentation.SegmentationError,
                ps.distributed.DistributedError,
                ps.distributed.DistributedStartError, ps.mpm.MPMInputError,
                ps.mpdp.MPDPError, ps.training.TrainingError,
                ps.training.DivergedError,
                ps.sampling.SamplingError, ps.cameras.CameraError,
                ps.deform.DeformError, ps.types.DataError,
                ps.types.UnknownObjectError, ps.render.RenderCapacityError):
      self.assertTrue(issubclass(cls, PhysSplatError), cls)
    # Still what a caller caught before: a KeyError, a RuntimeError.
    with self.assertRaises(KeyError) as cm:
      _block_scene().object_mask('ball')
    self.assertIsInstance(cm.exception, PhysSplatError)
    self.assertTrue(str(cm.exception).startswith("scene 'block' has no"))
    self.assertTrue(issubclass(ps.render.RenderCapacityError, RuntimeError))
    self.assertTrue(issubclass(ps.training.DivergedError, FloatingPointError))


class ValidationTest(absltest.TestCase):

  def test_configs_reject_non_finite_and_bad_modes(self):
    with self.assertRaisesRegex(pl.PipelineError, r'PipelineConfig\.gravity'):
      pl.PipelineConfig(gravity=float('nan'))
    with self.assertRaisesRegex(pl.PipelineError, r'PipelineConfig\.fps'):
      pl.PipelineConfig(fps=float('inf'))
    with self.assertRaisesRegex(pl.PipelineError, 'num_frames'):
      pl.PipelineConfig(num_frames=0)
    with self.assertRaisesRegex(pl.PipelineError, "'slip', 'sticky'"):
      pl.PipelineConfig(ground='slippery')
    with self.assertRaisesRegex(pl.PipelineError, 'grid_res'):
      pl.PipelineConfig(grid_res=1)
    with self.assertRaisesRegex(pl.PipelineError, 'finite'):
      pl.ForceSpec(kind='point', vector=(1.0, float('nan'), 0.0), end=1.0)
    self.assertIs(pl.PipelineConfig(ground='sticky').ground, pl.Ground.STICKY)
    # Shapes and types of values a user writes by hand.
    for kw, want in ((dict(height=-2), r'PipelineConfig\.height=-2'),
                     (dict(grid_res=16.5), r'grid_res=16\.5 .*whole'),
                     # Were truncated (2.5) or TypeErrors deep inside.
                     (dict(num_frames=2.5), r'num_frames=2\.5 is invalid: '
                      'use a whole number'),
                     (dict(gravity='9.8'), r"gravity='9\.8' is invalid: "
                      'use a number'),
                     (dict(render_config='fast'), 'use a physsplat_jax.'
                      'render.RenderConfig'),
                     (dict(substeps_per_frame=2.5), 'whole number or None'),

                     (dict(initial_velocity=(('a', (1.0, 0, 0)),
                                             ('a', (0, 1.0, 0)))),
                      "initial_velocity names 'a' more than once"),
                     (dict(initial_velocity=('cube', (1.0, 0.0, 0.0))),
                      r"initial_velocity entry 'cube': give \(object name")):
      with self.subTest(want), self.assertRaisesRegex(pl.PipelineError, want):
        pl.PipelineConfig(**kw)
    with self.assertRaisesRegex(pl.PipelineError, r'vector=\(0, 1\) must'):
      pl.ForceSpec('impulse', 'cube', (0, 1))
    # A force that starts after the last frame does nothing: said once.
    with self.assertLogs(level='WARNING') as logs:
      pl.PipelineConfig(num_frames=2, fps=24.0, forces=(
        pl.ForceSpec('impulse', 'cube', (0, 0, 1.0), start=98.75),))
    self.assertIn("force on 'cube' starts at 98.8 s, after the run ends",
                  ' '.join(logs.output))
    # So does an upward gravity (the field is a magnitude along -up).
    with self.assertLogs(level='WARNING') as logs:
      pl.PipelineConfig(gravity=-9.75).simulate
    self.assertIn('gravity = -9.75 m/s^2 pulls up', ' '.join(logs.output))
    # A background by name, as render's --background takes it; from a
    # config file or --config.background=white (a 1-tuple there) too. A
    # string or a short tuple there was a ValueError from float().
    self.assertEqual(pl.PipelineConfig(background='Grey').background,
                     (0.5, 0.5, 0.5))
    self.assertEqual(pl.config_from_dict({'background': ('white',)})
                     .background, (1.0, 1.0, 1.0))
    for d, want in (({'background': 'pink'}, r"background='pink' is "
                     r'invalid: use three numbers in \[0, 1\] or a name'),
                    ({'background': (1, 2)}, r'background = \(1, 2\): give '
                     '3 numbers'),
                    ({'roi': (0, 1, 'a', 1, 0, 1)}, 'roi = .*give 6 numbers'),
                    ({'forces': [{'kind': 'impulse', 'vector': 'up'}]},
                     r"forces\[0\]\.vector = 'up': give 3 numbers")):
      with self.subTest(d), self.assertRaisesRegex(pl.PipelineError, want):
        pl.config_from_dict(d)
    scene = _block_scene()
    for mats, want in (({'block': _RUBBER}, 'got dict'),
                       (['jelly'], "material 'jelly' is not a material")):
      with self.subTest(want), self.assertRaisesRegex(pl.PipelineError, want):
        pl.prepare_scene(_KEY, scene, mats, pl.PipelineConfig())
    with self.assertRaisesRegex(pl.PipelineError, 'must be a PipelineConfig'):
      pl.simulate_scene(scene, pl.PipelineConfig().prepare)

  def test_motion_flags_name_the_bad_value(self):
    with self.assertRaisesRegex(app.UsageError, 'radius'):
      lib.motion_from_flags(poke=['ball:1,0,0@0,0,0/abc'])
    with self.assertRaisesRegex(app.UsageError, 'finite'):
      lib.motion_from_flags(velocity=['ball:inf,0,0'])

  def test_output_folder_checked_first(self):
    with tempfile.TemporaryDirectory() as d:
      f = os.path.join(d, 'file')
      open(f, 'w').close()
      with self.assertRaisesRegex(outputs.OutputError, 'is a file'):
        outputs.check_output_dir(f)
      self.assertEqual(outputs.check_output_dir(os.path.join(d, 'a', 'b')),
                       os.path.join(d, 'a', 'b'))

  def test_output_file_folder_checked_first(self):
    with tempfile.TemporaryDirectory() as d:
      f = os.path.join(d, 'file')
      open(f, 'w').close()
      with self.assertRaisesRegex(
          outputs.OutputError, f'--out={f}/x.png: output folder .* is a '
          'file; give a folder name'):
        cli.check_output_file('out', os.path.join(f, 'x.png'))
      cli.check_output_file('out', os.path.join(d, 'new', 'x.json'))
      self.assertTrue(os.path.isdir(os.path.join(d, 'new')))
      cli.check_output_file('out', None)

  def test_scene_problems_are_named(self):
    scene = _block_scene()
    point = scene.replace(gaussians=scene.gaussians.replace(
      means=jnp.zeros_like(scene.gaussians.means)))
    with self.assertRaisesRegex(pl.PipelineError, 'zero extent'):
      pl.prepare_scene(_KEY, point, [_RUBBER], pl.PipelineConfig())
    nan = scene.replace(gaussians=scene.gaussians.replace(
      means=scene.gaussians.means.at[3, 1].set(jnp.nan)))
    with self.assertRaisesRegex(DataError, r'1 of 216 Gaussians have non-'
                                r'finite means \(rows 3\)'):
      pl.prepare_scene(_KEY, nan, [_RUBBER], pl.PipelineConfig())
    with self.assertRaisesRegex(pl.PipelineError, 'one material per object'):
      pl.prepare_scene(_KEY, scene, [], pl.PipelineConfig())

  def test_every_gaussian_field_ids_and_units_are_checked(self):
    """Not only the means: a NaN scale or opacity dropped its Gaussian from
    every frame without a word; ids and units gave IndexErrors."""
    scene = _block_scene()
    g = scene.gaussians
    nan = jnp.nan
    cases = (
      (dict(gaussians=g.replace(log_scales=g.log_scales.at[:9, 0].set(nan))),
       r'9 of 216 Gaussians have non-finite log_scales \(rows 0, 1, 2, 3, '
       r'4, \.\.\.\)'),
      (dict(gaussians=g.replace(opacity_logits=g.opacity_logits.at[5].set(
        jnp.inf))), r'non-finite opacity_logits \(rows 5\)'),
      (dict(gaussians=g.replace(sh=g.sh.at[7, 0, 2].set(nan))),
       r'non-finite sh \(rows 7\)'),
      (dict(gaussians=g.replace(quats=g.quats[:, :3])),
       r'quats has shape \(216, 3\), expected \(216, 4\)'),
      (dict(gaussians=g.replace(sh=jnp.zeros((216, 2, 3)))),
       'SH coefficient count 2'),
      (dict(object_ids=jnp.zeros(10, jnp.int32)),
       r'object_ids has shape \(10,\)'),
      (dict(object_ids=jnp.zeros(216)), 'dtype float32; expected'),
      (dict(object_ids=jnp.full(216, 7)), r'outside -1\.\.0 \(e\.g\. 7\)'),
      (dict(meters_per_unit=0.0), 'meters_per_unit=0.0 must be'),
    )
    for change, want in cases:
      with self.subTest(want), self.assertRaisesRegex(DataError, want):
        pl.prepare_scene(_KEY, scene.replace(**change), [_RUBBER],
                         pl.PipelineConfig())
    with self.assertRaisesRegex(pl.PipelineError, 'not a PRNG key'):
      pl.prepare_scene('seed', scene, [_RUBBER], pl.PipelineConfig())

  def test_run_inputs_are_checked_before_the_first_frame(self):
    """A NaN velocity, nu = 0.5 or E <= 0 used to surface a frame later as
    "the time step is too large"; now mpm.run names the field first."""
    from physsplat_jax import mpm

    grid = mpm.GridSpec(res=12, size=1.0)
    x = 0.5 + 0.02 * np.random.default_rng(0).uniform(-1, 1, (20, 3))
    cfg = mpm.SimConfig(grid=grid, dt=1e-3, substeps_per_frame=2)
    mat = mpm.make_materials('fixed_corotated', 1e4, 0.3, 1000.0, num=20)

    def run(v=np.zeros((20, 3)), m=mat):
      s = mpm.init_state(x, v, 1e-4, m, cfg)
      return mpm.run(s, m, None, cfg, 1)

    run()
    v = np.zeros((20, 3))
    v[4, 1] = np.nan
    for kw, want in ((dict(v=v), r'non-finite v for 1 of 20 particles \(4\)'),
                     (dict(m=mat.replace(nu=mat.nu.at[2:].set(0.5))),
                      r'nu outside \(-1, 0\.5\) for 18 of 20'),
                     (dict(m=mat.replace(E=-mat.E)), 'E <= 0 for 20 of 20'),
                     (dict(m=mat.replace(rho=mat.rho.at[0].set(0.0))),
                      r'rho <= 0 for 1 of 20 particles \(0\)')):
      with self.subTest(want), self.assertRaisesRegex(mpm.MPMInputError,
                                                      want):
        run(**kw)
    with self.assertRaisesRegex(mpm.MPMInputError, 'gravity.*3 finite'):
      mpm.SimConfig(grid=grid, dt=1e-3, gravity=(0.0, 0.0, np.nan))
    # A massless particle (init_state allows volume 0) runs and follows the
    # grid: inside a block moving at a uniform velocity, it moves with it.
    vol = np.full(20, 1e-4)
    vol[5] = 0.0
    v0 = np.array([0.3, -0.2, 0.1])
    s = mpm.init_state(x, v0, vol, mat, cfg)
    end = mpm.run(s, mat, None, cfg, 1).state
    g = np.asarray(cfg.gravity)
    np.testing.assert_allclose(np.asarray(end.v[5]), v0 + 2e-3 * g,
                               atol=1e-5)
    # x advances by dt * v after each substep's velocity update.
    np.testing.assert_allclose(np.asarray(end.x[5] - s.x[5]),
                               2e-3 * v0 + 3e-6 * g, atol=1e-7)
    for st, want in ((s.replace(mass=s.mass.at[3].set(-1.0)),
                      r'mass < 0 for 1 of 20 particles \(3\)'),
                     (mpm.init_state(x, v0, 0.0, mat, cfg),
                      'is 0 for all 20 particles')):
      with self.subTest(want), self.assertRaisesRegex(mpm.MPMInputError,
                                                      want):
        mpm.run(st, mat, None, cfg, 1)

  def test_init_state_names_bad_volumes_and_shapes(self):
    from physsplat_jax import mpm

    cfg = mpm.SimConfig(grid=mpm.GridSpec(res=12, size=1.0))
    x = np.full((10, 3), 0.5)
    mat = mpm.make_materials('fixed_corotated', 1e4, 0.3, 1000.0, num=10)
    vol = np.full(10, 1e-6)
    vol[7] = -1e-6
    for kw, want in (
        (dict(volume=np.ones(3)), r'volume has shape \(3,\); expected '
         r'\(10,\) or a scalar'),
        (dict(volume=vol), r'volume is -1e-06 for particle 7 \(1 of 10'),
        (dict(volume=np.nan), 'volume is nan for particle 0'),
        (dict(volume=1e-6, F=np.ones((10, 3))),
         r'F has shape \(10, 3\); expected \(10, 3, 3\)')):
      with self.subTest(want), self.assertRaisesRegex(mpm.MPMInputError,
                                                      want):
        mpm.init_state(x, np.zeros(3), materials=mat, config=cfg, **kw)
    # A massless particle (a driver a sampler left without candidates) is
    # allowed; it follows the grid.
    vol[7] = 0.0
    s = mpm.init_state(x, np.zeros(3), vol, mat, cfg)
    self.assertEqual(float(s.mass[7]), 0.0)

  def test_params_and_time_step_inputs_are_checked(self):
    from physsplat_jax import mpm

    scene = _block_scene()
    cfg = pl.PipelineConfig(grid_res=16, max_particles=64, fill=False,
                            num_frames=1, render='none')
    prep, _ = pl.prepare_scene(_KEY, scene, [_RUBBER], cfg)
    params = pl.init_params(prep, cfg)
    bad = params.replace(velocity=jnp.zeros((3, 3)))
    with self.assertRaisesRegex(pl.PipelineError, r'Params\.velocity has '
                                r'shape \(3, 3\); expected \(1, 3\)'):
      pl.simulate(bad, prep, cfg.simulate)
    mat = mpm.make_materials('fixed_corotated', 0.0, 0.3, 1000.0, num=4)
    with self.assertRaisesRegex(mpm.MPMInputError, 'E <= 0'):
      mpm.choose_substeps(0.01, 1 / 30, mat)
    with self.assertRaisesRegex(mpm.MPMInputError, 'no elastic wave speed'):
      mpm.cfl_dt(-1e5, 0.3, 1e3, 0.1)

  def test_silent_no_ops_are_warned_about(self):
    """A point force whose ball holds no particle, a camera that sees no
    Gaussian: runs that did nothing visible without a word."""
    from physsplat_jax import cameras

    away = make_camera(cameras.look_at((0.0, -1.0, 0.0), (0.0, -2.0, 0.0)),
                       40.0, 40.0, 32, 24)
    scene = _block_scene().replace(cameras=(away,))
    cfg = pl.PipelineConfig(
      grid_res=16, max_particles=64, fill=False, num_frames=1, width=32,
      height=24, camera_index=0, forces=(pl.ForceSpec(
        'point', 'block', (0.0, 0.0, 1.0), point=(5.0, 5.0, 5.0),
        radius=0.01, end=1.0),))
    with self.assertLogs('absl', level='WARNING') as logs:
      prep, _ = pl.prepare_scene(_KEY, scene, [_RUBBER], cfg)
      pl.run(pl.init_params(prep, cfg), prep, cfg)
    text = '\n'.join(logs.output)
    self.assertIn("point force on 'block': its ball", text)
    self.assertIn('frame 0: the camera sees none of the', text)

  def test_cameras_are_checked(self):
    good = dict(viewmat=np.eye(4), fx=40.0, fy=40.0, width=32, height=24)
    make_camera(**good)
    scaled = np.diag([2.0, 2.0, 2.0, 1.0])
    for change, want in ((dict(fx=0.0), 'fx=0.0 must be a positive'),
                         (dict(fy=np.nan), 'fy=nan'),
                         (dict(width=0), 'image size 0x24'),
                         (dict(viewmat=np.eye(3)), r'shape \(3, 3\)'),
                         (dict(viewmat=scaled), 'not a rigid transform'),
                         (dict(near=5.0, far=1.0), 'need 0 < near < far'),
                         (dict(cx=np.nan), 'principal point cx=nan'),
                         (dict(cy=np.inf), 'principal point cy=inf')):
      with self.subTest(want), self.assertRaisesRegex(DataError, want):
        make_camera(**{**good, **change})
    with self.assertRaisesRegex(DataError, 'image size 0x0'):
      make_camera(**good).resized(0, 0)

  def test_unknown_object_names(self):
    scene = _block_scene()
    cfg = pl.PipelineConfig(initial_velocity=(('ball', (0.0, 0.0, 1.0)),))
    with self.assertRaisesRegex(pl.PipelineError, r"\['ball'\].*block"):
      lib.check_scene_objects(scene, (), cfg)
    with self.assertRaisesRegex(pl.PipelineError, 'material_override'):
      lib.check_overrides(scene, {'cube': 'jelly'})
    lib.check_overrides(scene, {'block': 'jelly', '*': 'wood'})

  def test_bad_material_overrides_fail_before_any_question(self):
    """A bad override value is a one-line package error, raised before
    perception asks about any object (the MLLM client is never called)."""
    from physsplat_jax import perception

    class Client:
      def complete(self, *args, **kwargs):
        raise AssertionError('asked the MLLM before checking the overrides')

    # Object 0 ('ball') would be asked first; the bad override is object 1's.
    block = _block_scene()
    half = block.gaussians.num // 2
    scene = block.replace(
      object_ids=jnp.asarray(np.arange(block.gaussians.num) >= half,
                             jnp.int32),
      objects=(ObjectInfo('ball'), ObjectInfo('block')))
    for spec, want in (('unobtainium', 'not in the library'),
                       ({'material': 'jelly', 'E': 'x'}, "E='x' is not a "),
                       ({'E': -5}, 'invalid E=-5'),
                       ({'material': 'jelly', 'colour': 1}, 'unknown field')):
      opts = perception.PerceptionOptions(overrides={'block': spec})
      with self.assertRaisesRegex(perception.MaterialChoiceError, want):
        perception.perceive_scene(scene, opts, client=Client())
      code, text = _run_guarded(perception.MaterialChoiceError(want))
      self.assertEqual(code, 1)
    with self.assertRaisesRegex(PhysSplatError, 'expected name=key'):
      perception.parse_overrides('noequals')

  def test_override_without_material_names_the_fix(self):
    """A mapping without "material" for an object whose name matches no
    library entry says to add one and which keys there are (it said only
    what was missing)."""
    from physsplat_jax import perception

    scene = _block_scene().replace(objects=(ObjectInfo('OBJ'),))
    opts = perception.PerceptionOptions(
      overrides=perception.parse_overrides('OBJ={"E": 1e5, "nu": 0.5}'))
    with self.assertRaisesRegex(
        perception.MaterialChoiceError,
        r'override for object \'OBJ\': no "material" given .*; add '
        r'"material": KEY to the mapping, KEY a library key such as '
        r"'\w+'.* \(all \d+: physsplat_jax\.perception\."
        r'default_library\(\)\.keys, docs/materials\.md\)'):
      perception.perceive_scene(scene, opts)

  def test_library_checks_are_package_errors(self):
    """The solver's, cameras' and samplers' own argument checks raise
    PhysSplatErrors too (library callers catch one base class)."""
    import physsplat_jax as ps

    with self.assertRaisesRegex(ps.mpm.MPMInputError, 'frame_dt'):
      ps.mpm.choose_substeps(0.01, 0.0, ps.mpm.make_materials(
        'fixed_corotated', 1e4, 0.3, 1000.0, num=2))
    with self.assertRaises(PhysSplatError):
      ps.gaussians.sh_basis(5, jnp.zeros((2, 3)))

  def test_unknown_segmentation_method(self):
    from physsplat_jax import segmentation

    with self.assertRaisesRegex(segmentation.SegmentationError, 'bogus'):
      segmentation.segment(_block_scene().gaussians, 'bogus')

  def test_impossible_time_step_is_refused_with_the_numbers(self):
    steel_like = pl.ObjectMaterial('fixed_corotated', 1e15, 0.3, 1000.0)
    cfg = pl.PipelineConfig(grid_res=16, max_particles=200, use_mpdp=False,
                            fill=False)
    with self.assertRaisesRegex(
        pl.PipelineError, r'max_substeps_per_frame=20000.*rigid'):
      pl.prepare_scene(_KEY, _block_scene(), [steel_like], cfg)

  def test_initial_speed_enters_the_time_step(self):
    from physsplat_jax.pipeline import prepare as prep_lib

    dobj = np.zeros(10, np.int32)
    field = np.ones((10, 3))

    def substeps(**kw):
      cfg = pl.PrepareConfig(**kw)
      return prep_lib.time_step_stage([_RUBBER], (False,), field, dobj, 0.01,
                                      cfg, 9.8)[0]

    slow = substeps()
    fast = substeps(initial_velocity=(('', (300.0, 0.0, 0.0)),))
    # Wave speed ~6.3 m/s: 300 m/s more needs ~48x the substeps.
    self.assertGreater(fast, 40 * slow)
    with self.assertRaisesRegex(pl.PipelineError,
                                'initial and impulse speeds 300'):
      substeps(initial_velocity=(('', (300.0, 0.0, 0.0)),),
               substeps_per_frame=slow)
    # An impulse counts as its velocity change (2000 m/s took 1 substep);
    # a point force, whose speed depends on the material, does not.
    kick = pl.ForceSpec('impulse', '', (0.0, 180.0, 240.0), start=0.1)
    self.assertEqual(substeps(initial_velocity=(('', (300.0, 0.0, 0.0)),),
                              forces=(kick,)),
                     substeps(initial_velocity=(('', (600.0, 0.0, 0.0)),)))
    self.assertEqual(substeps(forces=(pl.ForceSpec(
      'point', '', (0.0, 0.0, 900.0), end=1.0),)), slow)
    # Too many substeps because frames are far apart or the scene is not
    # in metres: the message says which (it named neither).
    with self.assertRaisesRegex(pl.PipelineError,
                                r'a frame lasts 1e\+04 s \(fps=0\.0001\): '
                                'raise fps'):
      substeps(fps=1e-4)
    with self.assertRaisesRegex(pl.PipelineError, 'give its scale '
                                r'\(--meters_per_unit\)'):
      prep_lib.time_step_stage([_RUBBER], (False,), field, dobj, 1e-7,
                               pl.PrepareConfig(), 9.8)


class FailureTest(absltest.TestCase):

  def test_jitted_path_flags_the_first_bad_frame(self):
    cfg = pl.PipelineConfig(num_frames=3, grid_res=16, max_particles=200,
                            use_mpdp=False, fill=False, render='none',
                            fps=120.0, margin=1.0)
    prepared, _ = pl.prepare_scene(_KEY, _block_scene(), [_RUBBER], cfg)
    params = pl.init_params(prepared, cfg)
    traj = pl.simulate_jit(params, prepared, cfg)
    self.assertTrue(bool(np.all(traj.finite)))
    self.assertIs(pl.check_finite(traj, prepared), traj)
    bad = params.replace(velocity=params.velocity.at[0, 0].set(jnp.nan))
    traj = pl.simulate_jit(bad, prepared, cfg)
    self.assertFalse(bool(np.asarray(traj.finite)[-1]))
    with self.assertRaisesRegex(SimulationError, r"frame \d.*\['block'\]"):
      pl.check_finite(traj, prepared)

  def test_report_written_when_the_run_fails(self):
    cfg = pl.PipelineConfig(num_frames=2, grid_res=16, max_particles=200,
                            use_mpdp=False, fill=False, render='none')
    with tempfile.TemporaryDirectory() as d:
      with self.assertRaises(pl.PipelineError):
        pl.simulate_scene(_block_scene(), cfg, d, materials=[])
      report = json.load(open(os.path.join(d, 'report.json')))
      self.assertIn('PipelineError', report['error'])
      self.assertIn('one material per object', report['error'])
      self.assertEqual([f for f in os.listdir(d) if 'partial' in f], [])

  def test_a_full_disk_names_the_file_and_the_report_records_it(self):
    # Was '[Errno 28] No space left on device' alone, the report not
    # written (its own write's error hid the trajectory's), temporary
    # files left.
    import errno  # noqa: PLC0415
    from unittest import mock  # noqa: PLC0415
    cfg = pl.PipelineConfig(num_frames=2, grid_res=16, max_particles=200,
                            use_mpdp=False, fill=False, render='none')
    full = OSError(errno.ENOSPC, 'No space left on device')
    with tempfile.TemporaryDirectory() as d:
      with mock.patch.object(np, 'savez', side_effect=full):
        with self.assertRaisesRegex(
            outputs.OutputError, r'trajectory\.npz: cannot write the '
            r'trajectory file \(No space left on device: free space'):
          pl.simulate_scene(_block_scene(), cfg, d, materials=[_RUBBER])
      report = json.load(open(os.path.join(d, 'report.json')))
      self.assertIn('trajectory.npz: cannot write', report['error'])
      self.assertEqual([f for f in os.listdir(d) if f.startswith('.')], [])
      # The report's own write failing too: the run's error is raised.
      with mock.patch.object(outputs, 'write_json', side_effect=full):
        with self.assertLogs(level='ERROR') as logs, self.assertRaisesRegex(
            pl.PipelineError, 'one material per object'):
          pl.simulate_scene(_block_scene(), cfg, d, materials=[])
      self.assertIn('report.json not written', logs.output[0])

  def test_report_written_when_the_run_is_interrupted(self):
    # Ctrl-C (KeyboardInterrupt is no Exception) left the frames so far
    # without a report.json, or beside an earlier run's.
    cfg = pl.PipelineConfig(num_frames=3, grid_res=16, max_particles=200,
                            use_mpdp=False, fill=False, render='none')

    def on_frame(frame, *_):
      if frame == 1:
        raise KeyboardInterrupt

    with tempfile.TemporaryDirectory() as d:
      with open(os.path.join(d, 'report.json'), 'w') as fh:
        fh.write('{"scene": "an earlier run"}')
      with self.assertRaises(KeyboardInterrupt):
        pl.simulate_scene(_block_scene(), cfg, d, materials=[_RUBBER],
                          on_frame=on_frame)
      report = json.load(open(os.path.join(d, 'report.json')))
      self.assertEqual(report['error'], 'KeyboardInterrupt')
      self.assertEqual(report['scene'], 'block')
      self.assertIn('total', report['stage_seconds'])


class ValuesTest(absltest.TestCase):
  """physsplat_jax.values: the one definition of a number in user input."""

  def test_what_counts_as_a_number(self):
    import fractions  # noqa: PLC0415

    from physsplat_jax import values  # noqa: PLC0415
    nan, inf = float('nan'), float('inf')
    # value: (is_number, is_real, is_int, is_whole)
    table = [
      (3, (True, True, True, True)),
      (np.int64(3), (True, True, True, True)),
      (3.0, (True, True, False, True)),
      (np.float32(2.5), (True, True, False, False)),
      (fractions.Fraction(1, 2), (True, True, False, False)),
      (-0.0, (True, True, False, True)),
      (inf, (True, False, False, False)),
      (np.float64(nan), (True, False, False, False)),
      (True, (False, False, False, False)),
      (np.bool_(False), (False, False, False, False)),
      ('3', (False, False, False, False)),
      (None, (False, False, False, False)),
      (np.ones(1), (False, False, False, False)),
      (1 + 0j, (False, False, False, False)),
    ]
    tests = (values.is_number, values.is_real, values.is_int,
             values.is_whole)
    for value, want in table:
      with self.subTest(value=repr(value)):
        self.assertEqual(tuple(t(value) for t in tests), want)

  def test_every_check_refuses_a_bool_for_a_number(self):
    """The option, config and sidecar checks share the definition."""
    from physsplat_jax.io import scene as scene_io  # noqa: PLC0415
    from physsplat_jax.mpdp import model as model_lib  # noqa: PLC0415
    from physsplat_jax.perception import checks  # noqa: PLC0415
    from physsplat_jax.physgaussian import fields  # noqa: PLC0415
    self.assertIsNone(checks.number(True))
    self.assertEqual(checks.number(np.float32(2.0)), 2.0)
    self.assertFalse(model_lib.is_real(True))
    with self.assertRaisesRegex(PhysSplatError, 'finite number'):
      scene_io._Fields('scene.json').number(True, 'meters_per_unit')
    with self.assertRaisesRegex(PhysSplatError, 'a number'):
      fields._float('config.json', 'E', True)


if __name__ == '__main__':
  absltest.main()
