"""Tests of experiments/simulate.py: flag parsing and config layering."""

from absl import app
from absl.testing import absltest

from experiments import simulate as sim
from physsplat_jax import pipeline as pl


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

  def test_unknown_field_is_an_error(self):
    with self.assertRaisesRegex(pl.PipelineError, 'unknown pipeline config'):
      sim.build_config('tabletop', overrides=dict(num_frame=3))


if __name__ == '__main__':
  absltest.main()
