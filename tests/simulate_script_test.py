"""Tests of experiments/simulate.py: flag parsing and config layering."""

from absl import app
from absl.testing import absltest

from experiments.lib import simulate as sim
from physsplat_jax import pipeline as pl
from physsplat_jax.render import RenderConfig


class MotionFlagsTest(absltest.TestCase):

  def test_velocity_impulse_poke(self):
    m = sim.motion_from_flags(
      velocity=['*:0,0,1', 'rubber ball:0.5,0,0'],
      impulse=['jelly cube:1,0,0@0.5'],
      poke=['leaves:-40,0,0@0.1,0.2,0.3/0.05@0.1-0.4'])
    self.assertEqual(m['initial_velocity'],
                     [('', (0.0, 0.0, 1.0)), ('rubber ball', (0.5, 0.0, 0.0))])
    imp, poke = m['forces']
    self.assertEqual(imp, dict(kind='impulse', object='jelly cube',
                               vector=(1.0, 0.0, 0.0), start=0.5))
    self.assertEqual(poke['point'], (0.1, 0.2, 0.3))
    self.assertEqual(poke['radius'], 0.05)
    self.assertEqual((poke['start'], poke['end']), (0.1, 0.4))

  def test_bad_values_name_the_flag(self):
    with self.assertRaisesRegex(app.UsageError, 'velocity'):
      sim.motion_from_flags(velocity=['ball:1,2'])
    with self.assertRaisesRegex(app.UsageError, 'NAME:values'):
      sim.motion_from_flags(impulse=['1,2,3'])
    with self.assertRaisesRegex(app.UsageError, 'poke'):
      sim.motion_from_flags(poke=['ball:1,2,3'])


class BuildConfigTest(absltest.TestCase):

  def test_layering(self):
    # File defaults, then the scene's motion, then command-line overrides.
    c = sim.build_config('tabletop', overrides=dict(num_frames=5,
                                                    grid_res=None))
    self.assertIsInstance(c, pl.PipelineConfig)
    self.assertEqual(c.num_frames, 5)
    self.assertEqual(c.grid_res, 40)  # None keeps the file's value
    self.assertEqual(c.initial_velocity, (('', (0.0, 0.25, 1.2)),))
    c = sim.build_config('ficus')
    self.assertEqual(c.forces[0].object, 'leaves')
    c = sim.build_config('tabletop', motion=dict(initial_velocity=[
      ('jelly cube', (1.0, 0.0, 0.0))]))
    self.assertEqual(c.initial_velocity, (('jelly cube', (1.0, 0.0, 0.0)),))

  def test_render_config_from_the_file(self):
    # The file's render_config is the default RenderConfig (same compiled
    # renderer); --config.render_config.rasterize_mode=... reaches it.
    d, _ = sim.load_config_file()
    self.assertEqual(sim.build_config('tabletop', d).render_config,
                     RenderConfig())
    d['render_config']['rasterize_mode'] = 'antialiased'
    c = sim.build_config('tabletop', d)
    self.assertEqual(c.simulate.render_config,
                     RenderConfig(rasterize_mode='antialiased'))

  def test_unknown_field_is_an_error(self):
    with self.assertRaisesRegex(pl.PipelineError, 'unknown pipeline config'):
      sim.build_config('tabletop', overrides=dict(num_frame=3))


class SummaryTest(absltest.TestCase):

  def _report(self, pipelined, **stages):
    return dict(scene='s', num_frames=2, num_particles=10,
                num_simulated_gaussians=20, num_gaussians=30,
                time_step=dict(substeps_per_frame=4),
                particle_substeps_per_s=1e6, pipelined=pipelined,
                stage_seconds=stages)

  def test_overlapping_stages_are_said_to_overlap(self):
    # Pipelined, frame 0's deform and render compile beside 'compile':
    # 'time 9.6 s: ... compile 7.4 s (78%), ... render 3.6 s (37%)' added
    # up to 147% without a word.
    text = pl.summary(self._report(True, compile=7.4, simulate=0.4,
                                   deform=1.2, render=3.6, total=9.6))
    self.assertIn('the stages overlap', text)
    text = pl.summary(self._report(False, compile=5.8, simulate=0.6,
                                   deform=1.0, render=1.9, total=10.6))
    self.assertNotIn('overlap', text)


class PhysGaussianModeTest(absltest.TestCase):

  def test_renders_video_frames_ply_and_report(self):
    import json
    import os
    import tempfile

    import numpy as np

    from physsplat_jax.io import ply as ply_io
    from physsplat_jax.io import spz as spz_io

    scene = os.path.join(os.path.dirname(__file__), 'data', 'udon_crop.ply')
    cfg = dict(material='jelly', E=2e4, nu=0.3, density=200, n_grid=16,
               grid_lim=2.0, substep_dt=2e-4, frame_dt=4e-3, frame_num=2,
               g=[0.0, 0.0, -9.8], scale=0.5,
               boundary_conditions=[{'type': 'bounding_box'}])
    with tempfile.TemporaryDirectory() as d:
      path = os.path.join(d, 'c.json')
      with open(path, 'w') as f:
        json.dump(cfg, f)
      out = os.path.join(d, 'out')
      sim.run_physgaussian(scene, path, out, pl.PipelineConfig(
        width=48, height=32), ply=True, spz=True)
      frames = sorted(os.listdir(os.path.join(out, 'frames')))
      self.assertEqual(frames, [f'frame_{i:04d}.png' for i in range(3)])
      self.assertGreater(os.path.getsize(os.path.join(out, 'video.mp4')), 0)
      report = json.load(open(os.path.join(out, 'report.json')))
      self.assertEqual(report['num_frames'], 2)
      # The last PLY holds the simulated Gaussians at their trajectory's end.
      traj = np.load(os.path.join(out, 'trajectory.npz'))
      last = ply_io.load_ply(os.path.join(out, 'ply', 'frame_0002.ply'))
      np.testing.assert_allclose(np.asarray(last.means)[traj['ids']],
                                 traj['x'][-1], atol=1e-5)
      # ... and so does the last .spz frame, to half its position step.
      last = spz_io.load_spz(os.path.join(out, 'spz', 'frame_0002.spz'))
      np.testing.assert_allclose(np.asarray(last.means)[traj['ids']],
                                 traj['x'][-1], atol=0.5 / 4096 + 1e-5)


class ScriptProcessTest(absltest.TestCase):

  def test_a_run_reports_its_process_and_ends_with_its_output_complete(self):
    """The script as a user runs it: its report holds the process's start
    and setup times, and the process ends at once after ``main``
    (``fast_exit``) with every output complete: the summary printed, the
    video finalised (its index written at the end), the trajectory
    readable; ``import physsplat_jax`` brought in neither optax nor orbax
    (training loads them when first used)."""
    import json
    import os
    import subprocess
    import sys
    import tempfile

    import numpy as np

    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory() as d:
      out = os.path.join(d, 'out')
      proc = subprocess.run(
        [sys.executable, '-m', 'experiments.simulate', '--scene=tabletop',
         f'--out={out}', f'--compile_cache={d}/cache',
         '--config.num_frames=2', '--config.grid_res=16',
         '--config.width=32', '--config.height=24',
         '--config.max_particles=600', '--spz'],
        capture_output=True, text=True, check=False, timeout=300, cwd=repo)
      self.assertEqual(proc.returncode, 0, proc.stderr[-2000:])
      self.assertIn('before it: ', proc.stdout)
      self.assertIn('video: ', proc.stdout)  # the summary's last lines
      report = json.load(open(os.path.join(out, 'report.json')))
      self.assertIn('device_kind', report)  # what benchmarks compare
      times = report['process_seconds']
      self.assertGreater(times['start'], 0.0)
      self.assertGreaterEqual(times['setup'], 0.0)
      with open(os.path.join(out, 'video.mp4'), 'rb') as f:
        self.assertIn(b'moov', f.read())  # the MP4's index: a closed file
      traj = np.load(os.path.join(out, 'trajectory.npz'))
      self.assertEqual(traj['x'].shape[0], 3)
      # --spz: one .spz frame per frame, named in the report.
      self.assertEqual(sorted(os.listdir(report['files']['spz'])),
                       [f'frame_{i:04d}.spz' for i in range(3)])
    proc = subprocess.run(
      [sys.executable, '-c', 'import sys, physsplat_jax as ps; '
       'import experiments.simulate; '
       'print(sorted(m for m in ("optax", "orbax.checkpoint", "flax", '
       '"scipy.spatial", "scipy.ndimage", "scipy.sparse", "trimesh") '
       'if m in sys.modules)); ps.training; print("optax" in sys.modules); '
       'ps.mpdp.PointNet; print("flax.linen" in sys.modules)'],
      capture_output=True, text=True, check=True, timeout=120, cwd=repo)
    # A simulation imports neither the training libraries nor Flax (the
    # network is imported when it is first traced), and importing the
    # package or a script loads none of SciPy's heavy submodules (0.5 s of
    # every start: they load on first use) nor trimesh.
    self.assertEqual(proc.stdout.split(), ['[]', 'True', 'True'])

  def test_demo_reports_its_own_command_and_revision(self):
    """experiments.demo's report said command 'make demo' whatever the
    command line, and had no git revision (a run refused for its time step
    still writes report.json)."""
    import json
    import os
    import subprocess
    import sys
    import tempfile

    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory() as d:
      out = os.path.join(d, 'out')
      proc = subprocess.run(
        [sys.executable, '-m', 'experiments.demo', f'--out={out}',
         '--compile_cache=off', '--config.substeps_per_frame=1',
         '--config.grid_res=16', '--config.max_particles=300'],
        capture_output=True, text=True, check=False, timeout=300, cwd=repo)
      self.assertEqual(proc.returncode, 1, proc.stderr[-2000:])
      self.assertIn('error: substeps_per_frame=1', proc.stderr)
      report = json.load(open(os.path.join(out, 'report.json')))
      self.assertIn('--config.substeps_per_frame=1', report['command'])
      self.assertIn('git', report)
      # A --config file's own SCENE_MOTIONS drive the demo (simulate.py's
      # were used whatever the file said).
      conf = os.path.join(d, 'mine.py')
      with open(conf, 'w') as f:
        f.write('from experiments.configs.demo import get_config\n'
                "SCENE_MOTIONS = {'tabletop': dict(initial_velocity="
                "{'': (0.0, 0.0, 0.7)})}\n")
      proc = subprocess.run(
        [sys.executable, '-m', 'experiments.demo', f'--out={out}',
         f'--config={conf}', '--compile_cache=off',
         '--config.substeps_per_frame=1', '--config.grid_res=16',
         '--config.max_particles=300'],
        capture_output=True, text=True, check=False, timeout=300, cwd=repo)
      self.assertEqual(proc.returncode, 1, proc.stderr[-2000:])
      report = json.load(open(os.path.join(out, 'report.json')))
      self.assertEqual(report['config']['initial_velocity'],
                       [['', [0.0, 0.0, 0.7]]])


if __name__ == '__main__':
  absltest.main()
