"""Tests for physsplat_jax.mpdp: network properties, data, training, I/O.

Training through the simulator is tested in tests/mpdp_sim_test.py.
"""

import copy
import dataclasses
import functools
import json
import os
import re
import shutil
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from absl.testing import absltest

from experiments.configs import mpdp_test as test_config
from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp import pretrained
from physsplat_jax.mpdp import synthetic
from physsplat_jax.mpdp import train as train_lib

_MEAN_TOL = 1e-5          # |mean(field) - 1| in float32
_EQUIV_TOL = 1e-5         # permutation / invariance tolerance, float32
_FD_RTOL = 1e-6           # float64 directional finite difference
_SMALL = model_lib.ModelConfig(
  features=(16, 16), edge_features=16, k_neighbors=4, global_features=16,
  cond_features=8, head_features=(16,))


@functools.partial(jax.jit, static_argnums=(0, 3))
def _noisy_params(config, seed, scale, num_points):
  params = model_lib.init_params(jax.random.key(seed), config, num_points)
  leaves, tree = jax.tree.flatten(params)
  keys = jax.random.split(jax.random.key(seed + 1), len(leaves))
  leaves = [x + scale * jax.random.normal(k, x.shape, x.dtype)
            for x, k in zip(leaves, keys)]
  return jax.tree.unflatten(tree, leaves)


def _random_params(config=_SMALL, seed=0, scale=0.3, num_points=16):
  """Initial params plus noise so the field is far from 1 (jitted: eager
  linen init is slow)."""
  return _noisy_params(config, seed, scale, num_points)


def _object(seed=3, n=64, kind=None, min_fill=0.75):
  o = synthetic.make_object(seed, n, kind=kind, min_fill=min_fill)
  return o, jnp.asarray(o.points), o.means, jnp.asarray(o.mask)


class ModelTest(absltest.TestCase):

  def setUp(self):
    super().setUp()
    self.predict = jax.jit(model_lib.make_predict(_SMALL))
    self.params = _random_params()

  def test_mean_exactly_one_with_padding(self):
    o, pts, means, mask = _object(min_fill=0.6)
    self.assertLess(int(mask.sum()), 64)  # there is padding to mask
    field = np.asarray(self.predict(self.params, pts, means, mask))
    valid = field[np.asarray(mask)]
    np.testing.assert_allclose(valid.mean(0), 1.0, atol=_MEAN_TOL)
    # The field is not trivially 1 (the test could fail).
    self.assertGreater(valid[:, 0].std(), 0.05)
    np.testing.assert_array_equal(field[~np.asarray(mask)], 1.0)
    self.assertTrue(np.all(field > 0))
    # Garbage in the padded rows changes nothing in the valid rows.
    junk = pts.at[~mask].set(1e3)
    field2 = np.asarray(self.predict(self.params, junk, means, mask))
    np.testing.assert_allclose(field2, field, atol=_EQUIV_TOL)

  def test_mean_one_batched_and_without_mask(self):
    data = synthetic.make_dataset(5, 3, 48, min_fill=0.5)
    f = np.asarray(self.predict(self.params, data['points'], data['means'],
                                data['mask']))
    for b in range(3):
      np.testing.assert_allclose(f[b][data['mask'][b]].mean(0), 1.0,
                                 atol=_MEAN_TOL)
    f1 = np.asarray(self.predict(self.params, data['points'][0],
                                 data['means'][0]))
    np.testing.assert_allclose(f1.mean(0), 1.0, atol=_MEAN_TOL)

  def test_weighted_mean_one(self):
    # With per-point weights (volumes) the weighted mean is 1: the plain
    # mean is not, and the field's shape is the unweighted one's.
    o, pts, means, mask = _object(min_fill=0.6)
    a = jnp.asarray(np.random.default_rng(5).uniform(0.2, 3.0, mask.shape))
    field = np.asarray(self.predict(self.params, pts, means, mask, a))
    plain = np.asarray(self.predict(self.params, pts, means, mask))
    m, w = np.asarray(mask), np.asarray(a)[np.asarray(mask)]
    np.testing.assert_allclose((w[:, None] * field[m]).sum(0) / w.sum(),
                               1.0, atol=_MEAN_TOL)
    self.assertGreater(np.abs(field[m].mean(0) - 1.0).max(), 1e-3)
    ratio = field[m] / plain[m]
    np.testing.assert_allclose(ratio, np.broadcast_to(ratio[:1], ratio.shape),
                               rtol=1e-5)
    np.testing.assert_array_equal(field[~m], 1.0)
    # Batched, and all-zero weights fall back to the plain mean.
    fb = np.asarray(self.predict(self.params, pts[None], means[None],
                                 mask[None], a[None]))
    np.testing.assert_allclose(fb[0], field, rtol=1e-6)
    f0 = np.asarray(self.predict(self.params, pts, means, mask,
                                 jnp.zeros_like(a)))
    np.testing.assert_allclose(f0, plain, rtol=1e-6)
    with self.assertRaisesRegex(model_lib.MPDPError, 'weights shape'):
      self.predict(self.params, pts, means, mask, a[:3])

  def test_permutation_equivariance_and_similarity_invariance(self):
    _, pts, means, mask = _object(min_fill=1.0)
    field = np.asarray(self.predict(self.params, pts, means, mask))
    perm = np.random.default_rng(0).permutation(pts.shape[0])
    fp = np.asarray(self.predict(self.params, pts[perm], means, mask[perm]))
    np.testing.assert_allclose(fp, field[perm], atol=_EQUIV_TOL)
    # Translation and uniform scale of the input leave the field unchanged.
    moved = pts * 3.7 + jnp.array([10.0, -2.0, 5.0])
    fm = np.asarray(self.predict(self.params, moved, means, mask))
    np.testing.assert_allclose(fm, field, atol=1e-4)

  def test_untrained_network_is_mean_only_baseline(self):
    params = model_lib.init_params(jax.random.key(0), _SMALL)
    _, pts, means, mask = _object()
    field = self.predict(params, pts, means, mask)
    np.testing.assert_array_equal(np.asarray(field), 1.0)

  def test_means_condition_the_field(self):
    _, pts, _, mask = _object(min_fill=1.0)
    a = self.predict(self.params, pts,
                     model_lib.encode_means(1e4, 0.3, 500.0, 'foam'), mask)
    b = self.predict(self.params, pts,
                     model_lib.encode_means(1e8, 0.3, 500.0, 'von_mises'),
                     mask)
    self.assertGreater(float(jnp.max(jnp.abs(a - b))), 1e-3)

  def test_material_from_field_keeps_nu_below_half(self):
    field = jnp.array([[2.0, 1.5, 1.0], [0.5, 0.1, 1.0]])
    E, nu, rho = model_lib.material_from_field(field, 1e6, 0.45, 1000.0)
    np.testing.assert_allclose(E, [2e6, 5e5])
    np.testing.assert_allclose(nu, [model_lib.NU_MAX, 0.045], rtol=1e-6)
    self.assertTrue(np.all(np.asarray(nu) < 0.5))
    np.testing.assert_allclose(rho, [1000.0, 1000.0])

  def test_bad_inputs_raise_clear_errors(self):
    with self.assertRaisesRegex(ValueError, 'nu must be in'):
      model_lib.encode_means(1e6, 0.5, 1000.0)
    with self.assertRaisesRegex(ValueError, 'E must be finite'):
      model_lib.encode_means(-1.0, 0.3, 1000.0)
    with self.assertRaisesRegex(ValueError, 'unknown constitutive model'):
      model_lib.encode_means(1e6, 0.3, 1000.0, 'jelly')
    with self.assertRaisesRegex(ValueError, 'means must have shape'):
      model_lib.predict(self.params, jnp.zeros((8, 3)), jnp.zeros((4,)))
    with self.assertRaisesRegex(ValueError, 'points must have shape'):
      model_lib.predict(self.params, jnp.zeros((8, 2)),
                        jnp.zeros((model_lib.MEANS_DIM,)))
    with self.assertRaisesRegex(ValueError, 'Unknown MPDP model config'):
      model_lib.ModelConfig.from_dict({'width': 3})

  def test_encode_means_batched(self):
    m = model_lib.encode_means([1e6, 1e4], [0.3, 0.2], [1e3, 2e3],
                               ['rigid', 'foam'])
    self.assertEqual(m.shape, (2, model_lib.MEANS_DIM))
    self.assertEqual(float(m[0, -1]), 1.0)   # rigid flag from the name
    self.assertEqual(float(m[1, -1]), 0.0)
    np.testing.assert_allclose(m[:, 0], [0.0, -1.0])

  def test_gradient_finite_and_matches_finite_differences(self):
    o, _, _, _ = _object(n=24)
    with jax.enable_x64(True):
      params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64),
                            _random_params(num_points=24))
      pts = jnp.asarray(o.points, jnp.float64)
      means = jnp.asarray(o.means, jnp.float64)
      mask = jnp.asarray(o.mask)
      target = jnp.asarray(o.field, jnp.float64)
      predict = model_lib.make_predict(_SMALL)

      def loss(p):
        f = predict(p, pts, means, mask)
        return train_lib.masked_log_errors(f[None], target[None],
                                           mask[None]).sum()

      loss = jax.jit(loss)
      grads = jax.jit(jax.grad(loss))(params)
      for g in jax.tree.leaves(grads):
        self.assertTrue(np.all(np.isfinite(np.asarray(g))))
      leaves, tree = jax.tree.flatten(params)
      keys = jax.random.split(jax.random.key(7), len(leaves))
      direction = jax.tree.unflatten(tree, [
        jax.random.normal(k, x.shape, x.dtype) for x, k in zip(leaves, keys)])
      analytic = sum(float(jnp.vdot(g, d)) for g, d in zip(
        jax.tree.leaves(grads), jax.tree.leaves(direction)))
      eps = 1e-5
      shift = lambda s: jax.tree.map(lambda x, d: x + s * d, params,
                                     direction)
      numeric = (float(loss(shift(eps))) - float(loss(shift(-eps)))) / (
        2 * eps)
      self.assertGreater(abs(analytic), 1e-6)
      np.testing.assert_allclose(analytic, numeric, rtol=_FD_RTOL)


class SyntheticTest(absltest.TestCase):

  def test_deterministic(self):
    a = synthetic.make_dataset(11, 4, 64)
    b = synthetic.make_dataset(11, 4, 64)
    c = synthetic.make_dataset(12, 4, 64)
    for k in ('points', 'mask', 'field', 'means'):
      np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    self.assertFalse(np.array_equal(a['points'], c['points']))

  def test_fields_have_mean_one_and_all_kinds_appear(self):
    kinds = set()
    for seed in range(24):
      o = synthetic.make_object(seed, 128)
      kinds.add(o.kind)
      np.testing.assert_allclose(o.field[o.mask].mean(0), 1.0, atol=_MEAN_TOL)
      self.assertTrue(np.all(o.field[o.mask] > 0))
      self.assertTrue(np.all(o.points[~o.mask] == 0))
    self.assertEqual(kinds, set(synthetic.KINDS))

  def test_rules_stiffer_near_support_and_in_thick_parts(self):
    for seed in range(6):
      o = synthetic.make_object(seed, 256, kind='beam', min_fill=1.0)
      if o.model == 'rigid' or o.model in synthetic.FLUIDS:
        continue
      d, f = o.dist, o.field[:, 0]
      near = f[d < np.quantile(d, 0.2)].mean()
      far = f[d > np.quantile(d, 0.8)].mean()
      self.assertGreater(near, 1.5 * far, msg=f'seed {seed}')
    # Thickness alone (equal distance): thicker is stiffer and denser.
    dist = np.zeros(4)
    thick = np.array([0.1, 0.2, 0.4, 0.8])
    f = synthetic.ground_truth_field(dist, thick, 1e6, 'neo_hookean')
    self.assertTrue(np.all(np.diff(f[:, 0]) > 0))
    self.assertTrue(np.all(np.diff(f[:, 2]) > 0))
    # Softer materials get stronger gradients.
    dist = np.linspace(0.0, 1.0, 8)
    thick = np.ones(8)
    soft = synthetic.ground_truth_field(dist, thick, 1e4, 'fixed_corotated')
    stiff = synthetic.ground_truth_field(dist, thick, 1e8, 'fixed_corotated')
    self.assertGreater(soft[0, 0] / soft[-1, 0], stiff[0, 0] / stiff[-1, 0])
    # Rigid bodies and fluids are homogeneous.
    for m in ('rigid', 'newtonian'):
      np.testing.assert_array_equal(
        synthetic.ground_truth_field(dist, thick, 1e6, m), 1.0)

  def test_bad_kind_raises(self):
    with self.assertRaisesRegex(ValueError, 'Unknown synthetic object kind'):
      synthetic.make_object(0, 64, kind='tree')


class TrainTest(absltest.TestCase):

  def test_optax_steps_lower_the_loss(self):
    data = synthetic.make_dataset(3, 4, 48)
    batch = {k: jnp.asarray(data[k]) for k in ('points', 'mask', 'field',
                                                'means')}
    params = model_lib.init_params(jax.random.key(0), _SMALL)
    loss_fn = train_lib.make_loss(_SMALL)
    tx = optax.adam(3e-3)
    state = {'step': jnp.asarray(0), 'params': params,
             'opt_state': tx.init(params)}
    step_fn = jax.jit(train_lib.make_train_step(loss_fn, tx))
    loss0 = float(loss_fn(params, batch)[0])
    for _ in range(3):
      state, _, _ = step_fn(state, batch)
    loss3 = float(loss_fn(state['params'], batch)[0])
    self.assertLess(loss3, loss0)
    self.assertEqual(int(state['step']), 3)

  def test_train_checkpoint_restore_and_resume(self):
    config = test_config.get_config()
    with tempfile.TemporaryDirectory() as workdir:
      r1 = train_lib.train_and_evaluate(config, workdir)
      self.assertEqual(r1['step'], config.train.num_steps)
      # Restore the saved state: identical predictions.
      mcfg = model_lib.ModelConfig.from_dict(config.model.to_dict())
      predict = jax.jit(model_lib.make_predict(mcfg))
      tx = train_lib.make_optimizer(config.train)
      fresh = model_lib.init_params(jax.random.key(1), mcfg)
      template = {'step': jnp.asarray(0, jnp.int32), 'params': fresh,
                  'opt_state': tx.init(fresh)}
      with ocp.CheckpointManager(os.path.join(workdir, 'checkpoints')) as m:
        self.assertEqual(m.latest_step(), config.train.num_steps)
        restored = train_lib.restore_latest(m, template)
      self.assertEqual(int(restored['step']), config.train.num_steps)
      # Placed as a new run's state is (uncommitted), so a jitted step
      # reuses the program compiled for the new run.
      self.assertFalse(any(a.committed for a in jax.tree.leaves(restored)))
      restored = restored['params']
      _, pts, means, mask = _object(n=32)
      np.testing.assert_array_equal(
        np.asarray(predict(restored, pts, means, mask)),
        np.asarray(predict(r1['params'], pts, means, mask)))
      predict(fresh, pts, means, mask)
      self.assertEqual(predict._cache_size(), 1)  # noqa: SLF001
      # Resume: a longer run continues from the saved step.
      config.unlock()
      config.train.num_steps = config.train.num_steps + 2
      r2 = train_lib.train_and_evaluate(config, workdir)
      self.assertEqual(r2['step'], config.train.num_steps)
      with open(os.path.join(workdir, 'metrics.jsonl')) as f:
        steps = [json.loads(line)['step'] for line in f]
      self.assertEqual(steps, [2, 4, 6])
      self.assertIn('baseline_rmse_log_E', r2)
      # npz export round trip is exact.
      pretrained.save_params(r2['params'], mcfg, workdir, 'exported')
      p, cfg, _ = pretrained.load_params(workdir, 'exported')
      self.assertEqual(cfg, mcfg)
      np.testing.assert_array_equal(
        np.asarray(predict(p, pts, means, mask)),
        np.asarray(predict(r2['params'], pts, means, mask)))

  def test_resume_under_another_config_is_refused(self):
    # A resume took a changed config silently (another learning rate, other
    # seeds); only logging, checkpointing and num_steps may change.
    config = test_config.get_config().to_dict()
    with tempfile.TemporaryDirectory() as w:
      train_lib.record_config(w, config)           # no checkpoints: any
      os.makedirs(os.path.join(w, 'checkpoints', '2'))
      other = copy.deepcopy(config)
      other['train']['learning_rate'] *= 2
      other['data']['seed'] = 7
      with self.assertRaisesRegex(
          model_lib.MPDPError, r"another config \(data.seed: .* -> 7; "
          r"train.learning_rate: .*\): resume with the same --config"):
        train_lib.record_config(w, other)
      same = copy.deepcopy(config)
      same['train']['log_every'] = 1
      same['train']['num_steps'] += 2
      with self.assertLogs(level='WARNING') as logs:
        train_lib.record_config(w, same)
      self.assertIn('num_steps', logs.output[0])
      with open(os.path.join(w, 'config.json')) as f:
        self.assertEqual(json.load(f)['train']['log_every'], 1)
      train_lib.record_config(w, same)  # the saved one is the new one

  def test_interrupted_run_resumes_exactly_and_logs_each_step_once(self):
    # A run interrupted after its last checkpoint (here: the checkpoint of
    # step 4 lost) resumes at step 2 and ends where an uninterrupted run
    # does; metrics.jsonl held steps 3 and 4 twice (and a cut line).
    config = test_config.get_config()
    config.train.log_every = 1
    with tempfile.TemporaryDirectory() as tmp:
      whole, cut = os.path.join(tmp, 'whole'), os.path.join(tmp, 'cut')
      r1 = train_lib.train_and_evaluate(config, whole)
      train_lib.train_and_evaluate(config, cut)
      shutil.rmtree(os.path.join(cut, 'checkpoints', '4'))
      with open(os.path.join(cut, 'metrics.jsonl'), 'a') as f:
        f.write('{"step": 5, "train_lo')  # cut short by the interruption
      r2 = train_lib.train_and_evaluate(config, cut)
      for a, b in zip(jax.tree.leaves(r1['params']),
                      jax.tree.leaves(r2['params'])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
      records = []
      for w in (whole, cut):
        with open(os.path.join(w, 'metrics.jsonl')) as f:
          records.append([json.loads(line) for line in f])
      self.assertEqual([r['step'] for r in records[1]], [1, 2, 3, 4])
      self.assertEqual([r['train_loss'] for r in records[0]],
                       [r['train_loss'] for r in records[1]])

  def test_interrupt_saves_the_step_reached(self):
    # Ctrl-C (or SIGTERM in the scripts) lost the steps since the last
    # periodic checkpoint; now the step reached is saved, and the resumed
    # run ends where an uninterrupted one does.
    config = test_config.get_config()
    config.train.log_every = 1
    batch = train_lib._batch  # noqa: SLF001

    def interrupt_at_3(data, seed, step, size):
      if step == 3:
        raise KeyboardInterrupt
      return batch(data, seed, step, size)

    with tempfile.TemporaryDirectory() as tmp:
      whole, cut = os.path.join(tmp, 'whole'), os.path.join(tmp, 'cut')
      r1 = train_lib.train_and_evaluate(config, whole)
      with absltest.mock.patch.object(train_lib, '_batch', interrupt_at_3), \
          self.assertLogs(level='WARNING') as logs, \
          self.assertRaises(KeyboardInterrupt):
        train_lib.train_and_evaluate(config, cut)
      self.assertIn('interrupted: step 3 saved', logs.output[-1])
      self.assertIn('3', os.listdir(os.path.join(cut, 'checkpoints')))
      r2 = train_lib.train_and_evaluate(config, cut)
      for a, b in zip(jax.tree.leaves(r1['params']),
                      jax.tree.leaves(r2['params'])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
      with open(os.path.join(cut, 'metrics.jsonl')) as f:
        self.assertEqual([json.loads(line)['step'] for line in f],
                         [1, 2, 3, 4])

      # Where a signal usually lands: after the 4th step's call returned,
      # before its result is assigned. The state of step 3 must still be
      # there to save (a donated state was deleted: nothing was saved).
      compile_step = train_lib._compile_step  # noqa: SLF001

      def cut_after_4th_call(step):
        jitted, calls = compile_step(step), []

        def call(*args):
          out = jitted(*args)
          calls.append(1)
          if len(calls) == 4:
            raise KeyboardInterrupt
          return out
        return call

      late = os.path.join(tmp, 'late')
      with absltest.mock.patch.object(train_lib, '_compile_step',
                                      cut_after_4th_call), \
          self.assertLogs(level='WARNING') as logs, \
          self.assertRaises(KeyboardInterrupt):
        train_lib.train_and_evaluate(config, late)
      self.assertIn('interrupted: step 3 saved', logs.output[-1])

  def test_bad_settings_and_a_diverging_run_stop_with_a_message(self):
    # A NaN learning rate used to train to a NaN checkpoint, exit 0.
    # A negative seed was NumPy's ValueError from inside the data or batch
    # generator.
    for field, value, want in (('learning_rate', float('nan'),
                                'learning_rate = nan; give a finite'),
                               ('batch_size', 0, 'batch_size = 0'),
                               ('seed', -1, r'train.seed = -1'),
                               ('data.seed', -2, r'data.seed = -2')):
      config = test_config.get_config()
      section, _, name = ('train.' + field).rpartition('.')
      config[section.rsplit('.', 1)[-1]][name] = value
      with self.subTest(field), tempfile.TemporaryDirectory() as workdir, \
          self.assertRaisesRegex(model_lib.MPDPError, want):
        train_lib.train_and_evaluate(config, workdir)
    config = test_config.get_config()
    config.train.learning_rate = 1e30
    config.train.grad_clip = 1e30
    with tempfile.TemporaryDirectory() as workdir:
      with self.assertRaisesRegex(model_lib.MPDPError,
                                  r'went non-finite by step (\d+).*nothing '
                                  'from it was saved.*learning_rate') as cm:
        train_lib.train_and_evaluate(config, workdir)
      bad = int(re.search(r'by step (\d+)', str(cm.exception)).group(1))
      ckpt = os.path.join(workdir, 'checkpoints')
      saved = [int(d) for d in (os.listdir(ckpt) if os.path.isdir(ckpt)
                                else ()) if d.isdigit()]
      self.assertTrue(all(s < bad for s in saved), (saved, bad))

  def test_resume_with_another_model_and_bad_weight_files_are_named(self):
    # Both were tracebacks from inside orbax / numpy.
    config = test_config.get_config()
    config.train.num_steps = 2
    with tempfile.TemporaryDirectory() as workdir:
      train_lib.train_and_evaluate(config, workdir)
      config.model.global_features = 8
      # Named from the config saved beside the checkpoints first.
      with self.assertRaisesRegex(
          model_lib.MPDPError, r'another config \(model.global_features: '
          r'16 -> 8\)'):
        train_lib.train_and_evaluate(config, workdir)
      # Without it (a workdir of an older version): named from the
      # checkpoint's metadata, before any restore starts (a restore failing
      # part-way left orbax's reads pending).
      os.remove(os.path.join(workdir, 'config.json'))
      with self.assertRaisesRegex(model_lib.MPDPError,
                                  'cannot resume from the checkpoint of step '
                                  r"2 .*\(params\['Dense_\d+'\]"
                                  r"\['(bias|kernel)'\] "
                                  r'is \((\d+, )?16,?\) float32 there and '
                                  r'\((\d+, )?8,?\) float32 in this config.*'
                                  'new --workdir'):
        train_lib.train_and_evaluate(config, workdir)
      # The optimiser state is compared as shapes (orbax saves its named
      # tuples as dicts).
      ckpt = os.path.join(workdir, 'checkpoints')
      with ocp.CheckpointManager(ckpt) as m:
        step = m.latest_step()
        with ocp.StandardCheckpointer() as c:
          saved = c.restore(os.path.join(ckpt, str(step), 'default'))
        # A live state: optax's named tuples, saved as dicts.
        live = {'step': saved['step'], 'params': saved['params'],
                'opt_state': train_lib.make_optimizer(config.train).init(
                  saved['params'])}
        fits = train_lib._checkpoint_misfit(m, step, live)
        live['opt_state'] = (live['opt_state'], np.zeros(2, np.float32))
        extra = train_lib._checkpoint_misfit(m, step, live)
      self.assertIsNone(fits)
      self.assertRegex(extra, r'optimiser state \(\d+ arrays in all\)')
      for name, body in (('a.json', '{"metadata": {}}'),
                         ('a.npz', 'not a zip')):
        with open(os.path.join(workdir, name), 'w') as fh:
          fh.write(body)
      with open(os.path.join(workdir, 'b.json'), 'w') as fh:
        fh.write('{"model_config": %s}' % json.dumps(
          model_lib.ModelConfig().__dict__ if hasattr(
            model_lib.ModelConfig(), '__dict__') else {}))
      with open(os.path.join(workdir, 'b.npz'), 'w') as fh:
        fh.write('not a zip')
      for name, want in (('a', r'a\.json: not a model description'),
                         ('b', r'b\.npz: not a weights file')):
        with self.subTest(name), self.assertRaisesRegex(model_lib.MPDPError,
                                                        want):
          pretrained.load_params(workdir, name)

  def test_same_eval_and_train_seed_rejected(self):
    config = test_config.get_config()
    config.data.eval_seed = config.data.seed
    with self.assertRaisesRegex(ValueError, 'must differ'):
      train_lib.make_datasets(config)


class ConfigChecksTest(absltest.TestCase):
  """Bad settings and weight files fail up front, naming the field (they
  were ZeroDivisionErrors after compiling, Flax/JAX/NumPy errors, or silent
  wrong runs); nothing here compiles or trains."""

  def test_bad_train_config_or_workdir_fails_before_any_work(self):
    cases = (
      ('train', 'log_every', 0, 'train.log_every = 0'),
      ('train', 'eval_every', 0, 'train.eval_every = 0'),
      ('train', 'checkpoint_every', 0, 'train.checkpoint_every = 0'),
      ('train', 'max_to_keep', 0, 'train.max_to_keep = 0'),
      ('train', 'grad_clip', 0.0, r'train.grad_clip = 0.0; give a finite '
       'number > 0'),
      ('train', 'grad_clip', -1.0, 'train.grad_clip = -1.0'),
      ('train', 'channel_weights', (-1.0, 1.0, 1.0), 'channel_weights = '
       r'\(-1.0.*weights >= 0'),
      ('train', 'channel_weights', (0.0, 0.0, 0.0), 'not all 0'),
      ('train', 'channel_weights', (1.0, 1.0), 'three finite weights'),
      ('train', 'weight_decay', float('nan'), 'weight_decay = nan'),
      ('train', 'warmup_steps', -1, 'warmup_steps = -1; give an integer'),
      ('data', 'num_eval', 0, 'data.num_eval = 0'),
      ('model', 'features', (0,), r'config.model: .*features\[0\] = 0'),
      ('model', 'features', (-4,), r'features\[0\] = -4'),
      ('model', 'log_range', (0.0, 0.4, 0.7), r'log_range\[0\] = 0.0'),
      ('model', 'log_range', (1.0, 1.0), 'log_range = .*three finite'),
      ('model', 'k_neighbors', 0, 'k_neighbors = 0.*edge_features = 0'),
      ('model', 'k_neighbors', -2, 'k_neighbors = -2'))
    with tempfile.TemporaryDirectory() as tmp:
      workdir = os.path.join(tmp, 'run')
      for section, field, value, want in cases:
        config = test_config.get_config()
        config[section][field] = value
        with self.subTest(f'{section}.{field}={value}'), \
            self.assertRaisesRegex(model_lib.MPDPError, want):
          train_lib.train_and_evaluate(config, workdir)
      self.assertFalse(os.path.exists(workdir))  # checked before any work
      afile = os.path.join(tmp, 'afile')
      open(afile, 'w').close()
      os.makedirs(workdir)
      open(os.path.join(workdir, 'checkpoints'), 'w').close()
      for path in (afile, workdir):
        with self.subTest(path), self.assertRaisesRegex(
            model_lib.MPDPError, r'--workdir.*is a file, not a folder'):
          train_lib.train_and_evaluate(test_config.get_config(), path)
    for bad, want in (({'features': '64'}, 'features = .64.; give a list'),
                      ({'edge_features': -1}, 'edge_features = -1'),
                      ({'global_features': 2.5}, 'global_features = 2.5'),
                      ({'log_range': (3.0, float('nan'), 1.0)},
                       r'log_range\[1\] = nan')):
      with self.subTest(bad), self.assertRaisesRegex(model_lib.MPDPError,
                                                     want):
        model_lib.ModelConfig.from_dict(bad)

  def test_weight_files_are_checked_against_their_model_config(self):
    # The shapes load_params checks against are the network's own (also
    # with EdgeConv off: edge_features = 0).
    for cfg in (_SMALL, model_lib.ModelConfig(features=(8,),
                                              edge_features=0)):
      abstract = jax.eval_shape(lambda c=cfg: model_lib.init_params(
        jax.random.key(0), c))
      self.assertEqual(jax.tree.map(lambda a: a.shape, abstract),
                       model_lib.param_shapes(cfg))
    params = jax.tree.map(
      lambda shape: np.full(shape, 0.01, np.float32),
      model_lib.param_shapes(_SMALL), is_leaf=lambda x: isinstance(x, tuple))
    with tempfile.TemporaryDirectory() as d:
      pretrained.save_params(params, _SMALL, d, 'good')
      loaded, cfg, _ = pretrained.load_params(d, 'good')
      self.assertEqual(cfg, _SMALL)
      nan = jax.tree.map(np.copy, params)
      nan['Dense_3']['kernel'][0, 0] = np.nan
      missing = {k: v for k, v in params.items() if k != 'Dense_1'}
      for name, tree, mcfg, want in (
          ('nan', nan, _SMALL, r'Dense_3/kernel holds 1 non-finite'),
          ('missing', missing, _SMALL, r"missing \['Dense_1/bias'"),
          ('other', params, dataclasses.replace(_SMALL, global_features=8),
           r'Dense_4/kernel has shape \(32, 16\).*global_features=8.*'
           r'needs \(32, 8\)')):
        pretrained.save_params(tree, mcfg, d, name)
        with self.subTest(name), self.assertRaisesRegex(model_lib.MPDPError,
                                                        want):
          pretrained.load_params(d, name)
      with open(os.path.join(d, 'good.npz'), 'rb') as f:
        body = f.read()
      with open(os.path.join(d, 'good.npz'), 'wb') as f:
        f.write(body[:len(body) // 2])  # a truncated download
      with self.assertRaisesRegex(model_lib.MPDPError,
                                  r'good\.npz: not a weights file.*damaged'):
        pretrained.load_params(d, 'good')
      with open(os.path.join(d, 'other.json'), 'w') as f:
        json.dump({'model_config': {'features': '64'}}, f)
      with self.assertRaisesRegex(model_lib.MPDPError,
                                  r'other\.json: not a model description.*'
                                  'features'):
        pretrained.load_params(d, 'other')


class PretrainedTest(absltest.TestCase):

  def test_shipped_checkpoint_beats_mean_only_baseline(self):
    params = pretrained.load_pretrained()
    # Seed 99 is neither the training (1) nor the evaluation (2) seed.
    data = synthetic.make_dataset(99, 16, 256)
    m = train_lib.evaluate(params, model_lib.ModelConfig(), data)
    self.assertLess(m['rmse_log_E'], 0.7 * m['baseline_rmse_log_E'])
    self.assertLess(m['rmse_log_rho'], m['baseline_rmse_log_rho'])
    self.assertLess(m['mare_E'], m['baseline_mare_E'])
    # Default predict with the shipped params: mean exactly one.
    f = model_lib.predict(params, data['points'][0], data['means'][0],
                          data['mask'][0])
    np.testing.assert_allclose(np.asarray(f)[data['mask'][0]].mean(0), 1.0,
                               atol=_MEAN_TOL)

  def test_shipped_checkpoint_is_small(self):
    size = sum(os.path.getsize(os.path.join(pretrained.PRETRAINED_DIR, f))
               for f in os.listdir(pretrained.PRETRAINED_DIR))
    self.assertLess(size, 2 * 1024 * 1024)


if __name__ == '__main__':
  absltest.main()
