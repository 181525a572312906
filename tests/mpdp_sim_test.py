"""Tests for physsplat_jax.training.simtrain: MPDP through pipeline.simulate.

Tiny cantilevers (12^3 grid, 64 driving particles, 2 frames x 20 substeps):
the ground-truth field hook sets the simulated materials, the gradient of a
trajectory loss with respect to the network weights matches a central
finite difference in float64, a few Adam steps through the simulator lower
the loss, the orbax run resumes, and E fitted to a trajectory and to
rendered frames (slow) moves toward the truth.
"""

import dataclasses
import functools
import json
import os
import shutil
import tempfile
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from absl.testing import absltest

from experiments.configs import mpdp_test as test_config
from physsplat_jax import pipeline as pl
from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp import pretrained
from physsplat_jax.training import checks
from physsplat_jax.training import optim
from physsplat_jax.training import simtrain
from physsplat_jax.mpdp import synthetic

_MEAN_TOL = 1e-6      # |mean(field) - 1|, float64 rule
_FD_RTOL = 1e-4       # directional central difference, float64
_F32_RTOL = 1e-4      # same loss, jitted grad vs forward pass, float32
_FIT_E_RTOL = 0.01    # fitted mean E vs truth (measured 0.26%)
_FIT_FIELD_LOG_RMSE = 0.05  # fitted E field vs truth (measured 0.022)
# The tiny task of experiments/configs/mpdp_test.py (float32 by default).
_TINY = simtrain.TaskConfig.from_dict(test_config.get_config().sim.task)


@functools.lru_cache(maxsize=None)
def _task(seed, dtype='float32', render='none'):
  return simtrain.make_task(seed, dataclasses.replace(_TINY, dtype=dtype),
                            render=render)


class SceneTest(absltest.TestCase):

  def test_tasks_share_one_spec_and_truth_follows_the_rules(self):
    a, b = _task(0), _task(1)
    # Same static spec and shapes: one compilation serves both beams.
    self.assertEqual(a.prepared.spec, b.prepared.spec)
    self.assertEqual(jax.tree.structure(a.prepared),
                     jax.tree.structure(b.prepared))
    self.assertLen(a.prepared.spec.colliders.anchors, 1)  # the wall
    self.assertFalse(np.allclose(a.prepared.x0, b.prepared.x0))
    for t in (a, b):
      f = np.asarray(t.field, np.float64)
      # Volume-weighted mean 1, as simulate scales the MPDP field it trains.
      v = np.asarray(t.prepared.volume, np.float64)[:, None]
      np.testing.assert_allclose((v * f).sum(0) / v.sum(), 1.0, atol=1e-5)
      # Stiffer near the support (the wall at x = 0) than at the tip.
      x = np.asarray(t.prepared.frame.to_scene(t.prepared.x0))[:, 0]
      root = f[x < np.quantile(x, 0.25), 0].mean()
      tip = f[x > np.quantile(x, 0.75), 0].mean()
      self.assertGreater(root, 1.5 * tip)
      self.assertTrue(np.all(np.isfinite(np.asarray(t.target))))
      # The beam sags under gravity; the anchored root stays put.
      dz = np.asarray(t.target[-1, :, 2] - t.target[0, :, 2])
      xs = np.asarray(t.target[0, :, 0])
      self.assertLess(dz[xs > 0.9 * _TINY.length].mean(), -1e-3)
      self.assertLess(np.abs(dz[xs < 0.02 * _TINY.length]).max(), 1e-3)

  def test_field_at_applies_the_rule_at_nearest_points(self):
    o = synthetic.make_beam(3, 64)
    f = synthetic.field_at(o, o.points)
    np.testing.assert_allclose(
      f, synthetic.ground_truth_field(o.dist, o.thickness, o.E, o.model),
      rtol=1e-6)
    moved = synthetic.transform_object(o, 2.5, (1.0, -2.0, 0.5))
    np.testing.assert_allclose(synthetic.field_at(moved, moved.points), f,
                               rtol=1e-5)
    q = o.points[:10] + 1e-4
    np.testing.assert_allclose(synthetic.field_at(o, q).mean(0), 1.0,
                               atol=_MEAN_TOL)
    with self.assertRaisesRegex(ValueError, 'query must be'):
      synthetic.field_at(o, np.zeros((4, 2)))


class FieldHookTest(absltest.TestCase):

  def test_field_override_sets_the_simulated_materials(self):
    t = _task(0)
    cfg = dataclasses.replace(t.config, render='none')
    sim = jax.jit(pl.simulate, static_argnames='config')
    truth = sim(t.params, t.prepared, cfg, field=t.field)
    E, nu, rho = (np.asarray(m) for m in truth.materials)
    means = np.asarray(t.prepared.means)[0]
    f = np.asarray(t.field)
    np.testing.assert_allclose(E, means[0] * f[:, 0], rtol=1e-6)
    np.testing.assert_allclose(nu, np.minimum(means[1] * f[:, 1],
                                              model_lib.NU_MAX), rtol=1e-6)
    np.testing.assert_allclose(rho, means[2] * f[:, 2], rtol=1e-6)
    self.assertGreater(E.max() / E.min(), 2.0)
    # field = 1 is exactly the uniform (MPDP-off) run ...
    ones = sim(t.params, t.prepared, cfg, field=jnp.ones_like(t.field))
    uniform = sim(t.params, t.prepared, cfg)  # params.mpdp is None
    np.testing.assert_array_equal(np.asarray(ones.means),
                                  np.asarray(uniform.means))
    np.testing.assert_allclose(np.asarray(ones.materials[0]), means[0],
                               rtol=1e-6)
    # ... and the heterogeneous truth moves differently.
    err = float(simtrain.trajectory_error(ones.means, truth.means,
                                          t.prepared))
    self.assertGreater(err, 1e-5)
    np.testing.assert_allclose(truth.means, t.target, atol=1e-6)
    with self.assertRaisesRegex(pl.PipelineError, 'field has shape'):
      pl.simulate(t.params, t.prepared, cfg, field=jnp.ones((3, 3)))


class GradientTest(absltest.TestCase):

  def test_gradient_into_network_weights_matches_fd_x64(self):
    with jax.enable_x64(True):
      t = _task(0, dtype='float64')
      params = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64),
                            pretrained.load_pretrained())
      # The differences below from the gradient's own program: one
      # compile, not two.
      value_and_grad = jax.jit(jax.value_and_grad(simtrain.make_loss(
        t.config)))
      loss, grads = value_and_grad(params, t.params, t.prepared, t.target)
      self.assertGreater(float(loss), 0.0)
      for g in jax.tree.leaves(grads):
        self.assertTrue(np.all(np.isfinite(np.asarray(g))))
      leaves, tree = jax.tree.flatten(params)
      keys = jax.random.split(jax.random.key(5), len(leaves))
      direction = jax.tree.unflatten(tree, [
        jax.random.normal(k, x.shape, x.dtype) for x, k in zip(leaves, keys)])
      analytic = sum(float(jnp.vdot(g, d)) for g, d in zip(
        jax.tree.leaves(grads), jax.tree.leaves(direction)))
      eps = 1e-6

      def shift(s):
        return jax.tree.map(lambda x, d: x + s * d, params, direction)

      numeric = (float(value_and_grad(shift(eps), t.params, t.prepared,
                                      t.target)[0])
                 - float(value_and_grad(shift(-eps), t.params, t.prepared,
                                        t.target)[0])) / (2 * eps)
      self.assertGreater(abs(analytic), 1e-8)
      np.testing.assert_allclose(analytic, numeric, rtol=_FD_RTOL)


class TrainTest(absltest.TestCase):

  def test_train_and_evaluate_checkpoints_and_resumes(self):
    config = test_config.get_config().sim
    with tempfile.TemporaryDirectory() as workdir:
      r1 = simtrain.train_and_evaluate(config, workdir)
      self.assertEqual(r1['step'], config.num_steps)
      config.unlock()
      config.num_steps = config.num_steps + 1
      r2 = simtrain.train_and_evaluate(config, workdir)
      self.assertEqual(r2['step'], config.num_steps)
      with open(os.path.join(workdir, 'metrics.jsonl')) as f:
        records = [json.loads(line) for line in f]
      steps = [r['step'] for r in records]
      losses = [r['train_loss'] for r in records]
      self.assertEqual(steps, [1, 2, 3])  # resumed at 2, not restarted
      # The zero-initialised network is the mean-only baseline exactly, and
      # three Adam steps through the simulator lower the trajectory error.
      train = r2['train']
      np.testing.assert_allclose(losses[0], np.mean(train['baseline']),
                                 rtol=_F32_RTOL)
      self.assertLess(np.mean(train['simulator']),
                      0.9 * np.mean(train['baseline']))
      with open(os.path.join(workdir, 'simulator.json')) as f:
        saved = json.load(f)
      held = saved['held_out']
      self.assertEqual(set(held), {'baseline', 'supervised', 'simulator',
                                   'truth'})
      self.assertLess(max(held['truth']), 1e-12)
      self.assertGreater(held['baseline'][0], 0.0)
      # Interrupted after its last checkpoint (that of step 3 lost): the
      # run resumes at step 2, ends with the same weights and logs step 3
      # once (it was in metrics.jsonl twice).
      shutil.rmtree(os.path.join(workdir, 'checkpoints', '3'))
      r3 = simtrain.train_and_evaluate(config, workdir)
      for a, b in zip(jax.tree.leaves(r2['params']),
                      jax.tree.leaves(r3['params'])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
      with open(os.path.join(workdir, 'metrics.jsonl')) as f:
        again = [json.loads(line) for line in f]
      self.assertEqual([r['step'] for r in again], [1, 2, 3])
      self.assertEqual(again[-1]['train_loss'], losses[-1])


class FitTest(absltest.TestCase):

  def test_fit_recovers_E_and_its_field_from_a_trajectory(self):
    # Adam (the only optimiser before) overshot in log E and stopped where
    # its decayed rate left it: E 1.12x the truth after 60 steps here,
    # field RMS log error 0.20. L-BFGS: 0.997x, 0.022 (uniform: 0.78).
    t = _task(0)
    r = simtrain.fit_material(t, 'trajectory', E_init=0.3, field_degree=2)
    # At most the L-BFGS default of 20 steps (fewer where the line search
    # can lower the loss no further).
    self.assertBetween(len(r['history']), 5, 20)
    self.assertLess(r['E_rel_error'], _FIT_E_RTOL)
    self.assertLess(r['field_log_rmse'], _FIT_FIELD_LOG_RMSE)
    self.assertGreater(r['uniform_log_rmse'], 0.5)
    self.assertLess(r['final_loss'], 1e-4 * r['history'][0])

  def test_adam_fit_from_trajectory_moves_E_toward_truth(self):
    t = _task(0)
    r = simtrain.fit_material(t, 'trajectory', num_steps=4,
                              learning_rate=0.2, E_init=0.4,
                              field_degree=1, optimizer='adam')
    self.assertLess(abs(np.log(r['E_fit'] / r['E_true'])),
                    0.8 * abs(np.log(0.4)))
    self.assertLess(r['final_loss'], r['history'][0])
    v = np.asarray(t.prepared.volume, np.float64)
    np.testing.assert_allclose((v * r['field_E']).sum() / v.sum(), 1.0,
                               atol=1e-5)

  @pytest.mark.slow  # ~20-45 s: rollout + differentiable rendering backward
  def test_fit_from_rendered_frames_moves_E_toward_truth(self):
    t = _task(0, render='differentiable')
    self.assertEqual(t.images.shape, (3, _TINY.height, _TINY.width, 3))
    r = simtrain.fit_material(t, 'video', num_steps=3, learning_rate=0.2,
                              E_init=0.4, field_degree=0, optimizer='adam')
    # At least a fifth of the way (0.55 of the initial log error is left
    # after three steps, measured); the initial error itself as the limit
    # passed any step in the right direction.
    self.assertLess(abs(np.log(r['E_fit'] / r['E_true'])),
                    0.8 * abs(np.log(0.4)))
    self.assertLess(r['final_loss'], r['history'][0])
    with self.assertRaisesRegex(ValueError, 'render='):
      simtrain.fit_material(_task(0), 'video')


class HostLbfgsTest(absltest.TestCase):
  """training.optim.lbfgs (fit_material's L-BFGS) on a quadratic."""

  def test_minimises_records_each_step_and_names_a_non_finite_one(self):
    scale = jnp.asarray([1.0, 10.0])

    def f(th):
      return (3.0 * (th['a'] - 2.0) ** 2
              + jnp.sum(scale * (th['b'] - jnp.asarray([1.0, -3.0])) ** 2))

    th0 = {'a': jnp.asarray(0.0), 'b': jnp.zeros(2)}
    seen = []
    th, final = optim.lbfgs(jax.jit(jax.value_and_grad(f)), th0, 20,
                            lambda i, loss, t: seen.append((i, loss, t)),
                            lambda i: AssertionError(i))
    np.testing.assert_allclose(th['a'], 2.0, rtol=1e-4)
    np.testing.assert_allclose(th['b'], [1.0, -3.0], rtol=1e-4)
    self.assertLess(final, 1e-6)
    self.assertEqual([i for i, _, _ in seen], list(range(len(seen))))
    losses = [loss for _, loss, _ in seen]
    self.assertEqual(losses[0], float(f(th0)))  # the loss before step 0
    self.assertTrue(all(b < a for a, b in zip(losses, losses[1:])))
    self.assertLess(final, losses[-1])
    self.assertAlmostEqual(float(seen[-1][2]['a']), float(th['a']))
    # A non-finite loss stops the fit with the caller's error.
    nan_past_1 = jax.jit(jax.value_and_grad(
      lambda t: f(t) + jnp.where(t['a'] > 1.0, jnp.nan, 0.0)))
    with self.assertRaisesRegex(ValueError, r'^step \d+$'):
      optim.lbfgs(nan_past_1, th0, 20, lambda *a: None,
                  lambda i: ValueError(f'step {i}'))


class ChecksTest(absltest.TestCase):
  """Bad settings fail before any task is built or code compiled (they were
  NumPy/optax errors, NaN checkpoints, or silent wrong fits)."""

  def test_bad_task_sim_and_fit_settings_fail_up_front(self):
    for bad, want in (({'length': -0.5}, 'TaskConfig.length = -0.5'),
                      ({'num_gaussians': 0}, 'num_gaussians = 0; give an '
                       'integer >= 8'),
                      ({'E': '3e5'}, "TaskConfig.E = '3e5'; give a finite"),
                      ({'nu': 0.5}, r'nu = 0.5; give a number in \[0, 0.5\)'),
                      ({'num_particles': 4}, 'TaskConfig.num_particles=4'),
                      ({'dtype': 'float16'}, 'dtype')):
      with self.subTest(bad), self.assertRaisesRegex(simtrain.TrainingError,
                                                     want):
        simtrain.TaskConfig.from_dict(bad)
    with tempfile.TemporaryDirectory() as tmp:
      workdir = os.path.join(tmp, 'run')
      for field, value, want in (
          ('learning_rate', float('nan'), 'sim.learning_rate = nan'),
          ('learning_rate', -1e-2, 'sim.learning_rate = -0.01'),
          ('grad_clip', 0.0, 'sim.grad_clip = 0.0'),
          ('train_seeds', (), r'sim.train_seeds = \(\); give a non-empty'),
          ('eval_seeds', ('a',), 'sim.eval_seeds'),
          ('eval_seeds', (10, -1), r'sim.eval_seeds = \(10, -1\); give a '
           'non-empty list of integer seeds >= 0'),
          ('init', 'zeros', "sim.init = 'zeros'; give 'zero' or"),
          ('log_every', 0, 'sim.log_every = 0'),
          ('checkpoint_every', 0, 'sim.checkpoint_every = 0'),
          ('max_to_keep', 0, 'sim.max_to_keep = 0'),
          ('num_steps', -1, 'sim.num_steps = -1')):
        config = test_config.get_config().sim
        config[field] = value
        with self.subTest(field), self.assertRaisesRegex(
            simtrain.TrainingError, want):
          simtrain.train_and_evaluate(config, workdir)
      self.assertFalse(os.path.exists(workdir))  # before any work
      open(workdir, 'w').close()
      with self.assertRaisesRegex(simtrain.TrainingError,
                                  '--workdir.*is a file'):
        simtrain.train_and_evaluate(test_config.get_config().sim, workdir)
    # fit_material checks its arguments before it touches the task.
    for kw, want in (({'E_init': 0.0}, 'E_init = 0.0; give a finite '
                      'fraction'),
                     ({'E_init': -1.0}, 'E_init = -1.0'),
                     ({'learning_rate': float('nan')}, 'learning_rate = nan'),
                     ({'num_steps': 0}, 'num_steps = 0; give an integer >= 1'),
                     ({'field_degree': 7}, r'field_degree = 7; give one of '
                      r'\(0, 1, 2\)'),
                     ({'field_degree': -1}, 'field_degree = -1'),
                     ({'optimizer': 'sgd'}, "optimizer = 'sgd'; give one "
                      r"of \('lbfgs', 'adam'\)")):
      with self.subTest(kw), self.assertRaisesRegex(simtrain.TrainingError,
                                                    want):
        simtrain.fit_material(None, 'trajectory', **kw)
    with self.assertRaisesRegex(simtrain.TrainingError, 'learning_rate'):
      simtrain.train_through_simulator({}, [], 1, learning_rate=-1.0)
    with self.assertRaisesRegex(simtrain.TrainingError,
                                'make_task.seed = -1'):
      simtrain.make_task(-1, _TINY)  # NumPy's ValueError after the scene

  def test_field_correlation_of_a_uniform_field_is_null_not_nan(self):
    truth = np.linspace(0.5, 2.0, 16)
    with warnings.catch_warnings():
      warnings.simplefilter('error')  # NumPy warned on the NaN
      self.assertIsNone(checks.field_correlation(np.ones(16), truth))
      self.assertAlmostEqual(checks.field_correlation(truth**2, truth), 1.0)
    row = {'field_corr_log': checks.field_correlation(np.ones(16), truth)}
    self.assertEqual(json.dumps(row, allow_nan=False),
                     '{"field_corr_log": null}')
    self.assertIn('uniform', checks.UNDEFINED_CORRELATION)


if __name__ == '__main__':
  absltest.main()
