"""Supervised MPDP training on synthetic objects (optax + orbax).

Loss: masked mean over valid points and the three channels of the squared
log error, ``w_c * (log m_pred - log m_true)^2`` (log space because the fields
are multiplicative; the mean-only baseline ``m = 1`` has loss
``mean(w_c log^2 m_true)``). Adam(W) with warmup + cosine decay and global-norm
clipping. Checkpoints are orbax ``CheckpointManager`` steps holding
``{'step', 'params', 'opt_state'}``; a run restarted in the same workdir
resumes from the latest step (batches are drawn from ``(seed, step)`` so a
resumed run sees the same batches). Metrics go to absl logging and
``workdir/metrics.jsonl`` (one JSON object per line).

Layout of ``config`` (an ``ml_collections.ConfigDict``; see
``experiments/configs/mpdp.py``): ``model`` (fields of
:class:`~physsplat_jax.mpdp.model.ModelConfig`), ``data`` (seed, eval_seed,
num_train, num_eval, num_points, min_fill), ``train`` (seed, learning_rate,
weight_decay, warmup_steps, num_steps, batch_size, grad_clip,
channel_weights, log_every, eval_every, checkpoint_every, max_to_keep).
:func:`validate_config` checks every field of them, and :func:`check_workdir`
the workdir, before any data, compilation or training.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from absl import logging

from physsplat_jax import atomic_files
from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp import synthetic
from physsplat_jax.mpdp.model import MPDPError


def masked_log_errors(pred, target, mask):
  """Per-channel masked mean squared log error.

  Args:
    pred, target: (B, N, 3) positive fields.
    mask: (B, N) bool.

  Returns:
    (3,) mean over valid points of ``(log pred - log target)^2``.
  """
  m = mask[..., None]
  lp = jnp.log(jnp.where(m, pred, 1.0))
  lt = jnp.log(jnp.where(m, target, 1.0))
  n = jnp.maximum(jnp.sum(mask), 1)
  return jnp.sum(jnp.where(m, (lp - lt) ** 2, 0.0), axis=(0, 1)) / n


def make_loss(model_config: model_lib.ModelConfig,
              channel_weights=(1.0, 1.0, 1.0)):
  """Returns ``loss_fn(params, batch) -> (loss, per-channel MSLE (3,))``."""
  predict_fn = model_lib.make_predict(model_config)
  w = jnp.asarray(channel_weights, jnp.float32)

  def loss_fn(params, batch):
    pred = predict_fn(params, batch['points'], batch['means'], batch['mask'])
    per = masked_log_errors(pred, batch['field'], batch['mask'])
    return jnp.sum(w * per) / jnp.sum(w), per

  return loss_fn


def make_optimizer(train_config):
  """AdamW + warmup-cosine schedule + global-norm clipping."""
  schedule = optax.warmup_cosine_decay_schedule(
    0.0, train_config.learning_rate, train_config.warmup_steps,
    max(train_config.num_steps, train_config.warmup_steps + 1),
    end_value=0.05 * train_config.learning_rate)
  return optax.chain(
    optax.clip_by_global_norm(train_config.grad_clip),
    optax.adamw(schedule, weight_decay=train_config.weight_decay))


def make_train_step(loss_fn, tx):
  """Returns ``step_fn(state, batch) -> (state, loss, per)`` (not jitted)."""

  def step_fn(state, batch):
    (loss, per), grads = jax.value_and_grad(loss_fn, has_aux=True)(
      state['params'], batch)
    updates, opt_state = tx.update(grads, state['opt_state'],
                                   state['params'])
    params = optax.apply_updates(state['params'], updates)
    return ({'step': state['step'] + 1, 'params': params,
             'opt_state': opt_state}, loss, per)

  return step_fn


def evaluate(params, model_config, data, batch_size: int = 64):
  """Held-out metrics of the network and of the mean-only baseline (m = 1).

  Args:
    params: params pytree.
    model_config: the network's :class:`ModelConfig`.
    data: dict from :func:`synthetic.make_dataset`.
    batch_size: evaluation batch size.

  Returns:
    dict of floats: ``rmse_log_{E,nu,rho}`` (RMS log error), ``mare_E``
    (mean |m_E pred - m_E true| / m_E true), and the ``baseline_*`` values.
  """
  predict_fn = jax.jit(model_lib.make_predict(model_config))
  num = data['points'].shape[0]
  sq = np.zeros(3)
  sq0 = np.zeros(3)
  are = are0 = 0.0
  count = 0
  for i in range(0, num, batch_size):
    sl = slice(i, i + batch_size)
    pred = np.asarray(predict_fn(params, data['points'][sl],
                                 data['means'][sl], data['mask'][sl]),
                      np.float64)
    mask = data['mask'][sl]
    tgt = data['field'][sl].astype(np.float64)[mask]
    pred = pred[mask]
    sq += np.sum((np.log(pred) - np.log(tgt)) ** 2, axis=0)
    sq0 += np.sum(np.log(tgt) ** 2, axis=0)
    are += np.sum(np.abs(pred[:, 0] - tgt[:, 0]) / tgt[:, 0])
    are0 += np.sum(np.abs(1.0 - tgt[:, 0]) / tgt[:, 0])
    count += int(mask.sum())
  out = {}
  for c, name in enumerate(model_lib.FIELD_CHANNELS):
    out[f'rmse_log_{name}'] = float(np.sqrt(sq[c] / count))
    out[f'baseline_rmse_log_{name}'] = float(np.sqrt(sq0[c] / count))
  out['mare_E'] = float(are / count)
  out['baseline_mare_E'] = float(are0 / count)
  return out


def _model_config(config) -> model_lib.ModelConfig:
  try:
    return model_lib.ModelConfig.from_dict(config.model.to_dict())
  except MPDPError as e:
    raise MPDPError(f'config.model: {e}') from None


def _is_weights(w) -> bool:
  return (isinstance(w, (tuple, list)) and len(w) == 3
          and all(model_lib.is_real(x) and x >= 0 for x in w)
          and sum(w) > 0)


def validate_config(config) -> model_lib.ModelConfig:
  """Checks ``config`` (see the module docstring) before any work.

  Returns:
    The :class:`ModelConfig` of ``config.model``.

  Raises:
    MPDPError: naming the first bad field (``config.<section>.<name>``), its
      value and what to give instead.
  """
  tc, d = config.train, config.data
  check = model_lib.check_values
  check('config.train', [
    ('learning_rate', tc.learning_rate, '>0'),
    ('batch_size', tc.batch_size, 'int>=1'),
    ('num_steps', tc.num_steps, 'int>=0'),
    ('seed', tc.seed, 'int>=0'),  # (NumPy's rule: _batch)
    ('weight_decay', tc.weight_decay, '>=0'),
    ('warmup_steps', tc.warmup_steps, 'int>=0'),
    ('grad_clip', tc.grad_clip, '>0'),
    ('channel_weights', tc.channel_weights, (
      _is_weights, 'three finite weights >= 0 (E, nu, rho), not all 0')),
    ('log_every', tc.log_every, 'int>=1'),
    ('eval_every', tc.eval_every, 'int>=1'),
    ('checkpoint_every', tc.checkpoint_every, 'int>=1'),
    ('max_to_keep', tc.max_to_keep, (
      lambda v: v is None or (model_lib.is_int(v) and v >= 1),
      'an integer >= 1 (or None: keep every checkpoint)'))])
  check('config.data', [
    ('seed', d.seed, 'int>=0'), ('eval_seed', d.eval_seed, 'int>=0'),
    ('num_train', d.num_train, 'int>=1'),
    ('num_eval', d.num_eval, 'int>=1'),
    ('num_points', d.num_points, (
      lambda v: model_lib.is_int(v) and v >= 8, 'an integer >= 8')),
    ('min_fill', d.min_fill, (
      lambda v: model_lib.is_real(v) and 0 < v <= 1,
      'a fraction in (0, 1]'))])
  if tc.batch_size > d.num_train:
    raise MPDPError(f'config.train.batch_size ({tc.batch_size}) exceeds '
                    f'config.data.num_train ({d.num_train}).')
  return _model_config(config)


def check_workdir(workdir, error: type = MPDPError) -> str:
  """``workdir`` as an absolute path, created if missing; checked before
  any work: it and its ``checkpoints`` entry (if there) must be writable
  folders, not files (orbax failed on them after the last step).

  Raises:
    error: naming the workdir (``--workdir``), what is wrong and the fix.
  """
  if not isinstance(workdir, str) or not workdir:
    raise error(f'workdir (--workdir) = {workdir!r}; give a folder path.')
  path = os.path.abspath(workdir)
  where = f'workdir {workdir!r} (--workdir)'
  for p in (path, os.path.join(path, 'checkpoints')):
    if os.path.exists(p) and not os.path.isdir(p):
      raise error(f'{where}: {p} is a file, not a folder; give another '
                  '--workdir or move the file away.')
  try:
    os.makedirs(path, exist_ok=True)
  except OSError as e:
    raise error(f'{where}: cannot create it ({e.strerror}); give a folder '
                'you can write to.') from None
  for p in (path, os.path.join(path, 'checkpoints')):
    if os.path.isdir(p) and not os.access(p, os.W_OK | os.X_OK):
      raise error(f'{where}: {p} is not writable; give a folder you can '
                  'write to.')
  return path


# Settings that may change between a run and its resume: how often it logs
# and saves, how many checkpoints it keeps, and (with a warning) how long it
# trains.
_RESUME_FREE = ('log_every', 'checkpoint_every', 'max_to_keep', 'num_steps')


def _flat(d, prefix=''):
  out = {}
  for k, v in d.items():
    if isinstance(v, dict):
      out.update(_flat(v, f'{prefix}{k}.'))
    else:
      out[prefix + k] = v
  return out


def record_config(workdir: str, config: dict, error: type = MPDPError,
                  flag: str = '--config') -> None:
  """Writes ``config`` to ``workdir/config.json``; refuses, before any
  work, to resume the checkpoints there under another config.

  A resumed run took the new settings silently: another learning rate or
  other seeds gave a run that neither config describes. Only
  ``log_every``, ``checkpoint_every``, ``max_to_keep`` and ``num_steps``
  may change; a longer (or shorter) ``num_steps`` is logged as a warning,
  as the learning-rate schedule, which spans ``num_steps``, then differs
  from the one the checkpoints were trained on.

  Raises:
    error: naming each changed field (old and new value) and the fix.
  """
  path = os.path.join(workdir, 'config.json')
  ckpt = os.path.join(workdir, 'checkpoints')
  resumes = os.path.isdir(ckpt) and any(n.isdigit() for n in os.listdir(ckpt))
  new = json.loads(json.dumps(config))  # tuples as lists, as in the file
  if resumes and os.path.exists(path):
    with open(path) as f:
      try:
        old = json.load(f)
      except ValueError:
        old = None
    if isinstance(old, dict):
      a, b = _flat(old), _flat(new)
      changed = [k for k in sorted(set(a) | set(b))
                 if a.get(k) != b.get(k)
                 and k.rsplit('.', 1)[-1] not in _RESUME_FREE]
      steps = [k for k in set(a) | set(b)
               if k.rsplit('.', 1)[-1] == 'num_steps' and a.get(k) != b.get(k)]
      for k in steps:
        logging.warning(
          '%s: %s -> %s on resume; the learning-rate schedule spans it, so '
          'the steps from here follow another schedule than a run of %s '
          'steps from the start would', k, a.get(k), b.get(k), b.get(k))
      if changed:
        what = '; '.join(f'{k}: {a.get(k)!r} -> {b.get(k)!r}'
                         for k in changed[:6])
        raise error(
          f'workdir {workdir!r} holds checkpoints trained under another '
          f'config ({what}{"; ..." if len(changed) > 6 else ""}): resume '
          f'with the same {flag} (saved in {path}) or train in a new '
          '--workdir.')
  atomic_files.write_data(path, json.dumps(new, indent=1), error,
                          what='training config')


def make_datasets(config):
  """(train, eval) datasets from ``config.data`` (disjoint seeds)."""
  d = config.data
  if d.seed == d.eval_seed:
    raise MPDPError(
      f'config.data.seed ({d.seed}) must differ from config.data.eval_seed '
      'so the held-out objects are not training objects.')
  train = synthetic.make_dataset(d.seed, d.num_train, d.num_points,
                                 d.min_fill)
  held = synthetic.make_dataset(d.eval_seed, d.num_eval, d.num_points,
                                d.min_fill)
  return train, held


def _batch(data, seed: int, step: int, batch_size: int):
  rng = np.random.default_rng([seed, step])
  idx = rng.choice(data['points'].shape[0], batch_size, replace=False)
  return {k: jnp.asarray(data[k][idx])
          for k in ('points', 'mask', 'field', 'means')}


def append_metrics(workdir: str, record: dict,
                   error: type = MPDPError) -> None:
  """Appends ``record`` as a line of ``workdir/metrics.jsonl`` (a line cut
  short by a full disk or an interruption is dropped on resume,
  :func:`trim_metrics`).

  Raises:
    error: it cannot be written, naming the file (Python's error on
      closing a file on a full disk names none) and the fix.
  """
  path = os.path.join(workdir, 'metrics.jsonl')
  try:
    with open(path, 'a') as f:
      f.write(json.dumps(record) + '\n')
  except OSError as e:
    raise error(_write_failure(os.path.join(workdir, 'checkpoints'),
                               OSError(e.errno, e.strerror, path))) from e


def trim_metrics(workdir: str, step: int) -> None:
  """Drops the records of ``workdir/metrics.jsonl`` past ``step``.

  A run resumed from the checkpoint of ``step`` logs the steps after it
  again: the records that an interrupted run wrote for them (after its last
  checkpoint) appeared twice. A line cut short by the interruption goes too.
  """
  path = os.path.join(workdir, 'metrics.jsonl')
  if not os.path.exists(path):
    return
  with open(path) as f:
    lines = f.readlines()

  def kept(line):
    try:
      return line.endswith('\n') and json.loads(line)['step'] <= step
    except (ValueError, KeyError, TypeError):
      return False

  keep = [line for line in lines if kept(line)]
  if len(keep) < len(lines):
    atomic_files.write_data(path, ''.join(keep), MPDPError, what='metrics')


@contextlib.contextmanager
def checkpoint_manager(workdir: str, max_to_keep: int,
                       error: type = MPDPError):
  """An orbax ``CheckpointManager`` over ``workdir/checkpoints`` (created;
  saves synchronously), closed on exit. A failed write while it is
  created or closed is raised as ``error`` naming the file
  (:func:`_named_write_errors`); :func:`save_checkpoint` does the same
  for each save.

  Orbax writes a step into a temporary folder and renames it when whole,
  and removes a temporary folder left behind when the next manager opens:
  the checkpoints finished before a failure stay good.
  """
  directory = os.path.join(workdir, 'checkpoints')
  options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep,
                                         create=True,
                                         enable_async_checkpointing=False)
  with _named_write_errors(directory, error):
    mngr = ocp.CheckpointManager(directory, options=options)
  try:
    yield mngr
  except BaseException:
    try:  # the body's error is the one raised
      mngr.close()
    except Exception as e:  # noqa: BLE001
      logging.warning('closing the checkpoints in %s: %s', directory, e)
    raise
  with _named_write_errors(directory, error):
    mngr.close()


@contextlib.contextmanager
def _named_write_errors(directory: str, error: type):
  """An OS error raised in the block (orbax's TensorStore ValueError
  carrying one included) raised as ``error``: the file, the fix and the
  step a rerun resumes from, instead of orbax's traceback."""
  try:
    yield
  except Exception as e:  # noqa: BLE001 (only OS errors are raised anew)
    os_error = atomic_files.os_error_of(e)
    if os_error is None:
      raise
    raise error(_write_failure(directory, os_error)) from e


def _write_failure(directory: str, e: OSError) -> str:
  """The message for a failed write under a training workdir."""
  what, where = 'write the file', e.filename or directory
  rel = os.path.relpath(os.path.abspath(where), directory)
  if not rel.startswith(os.pardir):  # inside checkpoints/: name the step
    step = rel.split(os.sep)[0].split('.')[0]
    what, where = f'write checkpoint {step}', directory
  return (f'{where}: cannot {what} ({atomic_files.os_error_reason(e)}); '
          f'{_resume_from(directory)}')


def _resume_from(directory: str) -> str:
  try:
    steps = sorted(int(n) for n in os.listdir(directory) if n.isdigit())
  except OSError:
    steps = []
  return (f'the checkpoints written before are kept: a rerun with the '
          f'same --workdir resumes from step {steps[-1]}' if steps else
          'no checkpoint was written yet: a rerun starts from step 0')


def checkpoint_bytes(state) -> int:
  """A bound on the disk space one orbax checkpoint of ``state`` takes:
  twice its arrays' bytes, 1 KiB of metadata per array, 128 KiB of files
  (measured: 68-93 kB for the test config's 35 kB in 57 arrays)."""
  leaves = jax.tree.leaves(state)
  return (2 * sum(np.dtype(getattr(a, 'dtype', np.float32)).itemsize
                  * int(np.prod(np.shape(a))) for a in leaves)
          + 1024 * len(leaves) + (128 << 10))


def check_room(mngr: ocp.CheckpointManager, state,
               error: type = MPDPError, step: int | None = None) -> None:
  """Refuses when the disk of ``mngr``'s folder has no room for a
  checkpoint of ``state`` (:func:`checkpoint_bytes`); the training loops
  check before they start and before each save.

  On a full disk orbax fails part-way, and its worker threads print
  tracebacks after the error; checked first, the run stops cleanly with
  the last good checkpoint kept.

  Raises:
    error: naming the folder, the space free and needed, the fix and the
      step a rerun resumes from.
  """
  directory = os.fspath(mngr.directory)
  need = checkpoint_bytes(state)
  free = atomic_files.free_bytes(directory)
  if free is not None and free < need:  # (None: the save decides)
    which = 'the next checkpoint' if step is None else f'checkpoint {step}'
    raise error(
      f'{directory}: no room for {which}: {free / 1e6:.2f} MB free on that '
      f'disk, a checkpoint needs about {need / 1e6:.2f} MB (free space '
      f'there, or train in another --workdir); {_resume_from(directory)}')


def save_checkpoint(mngr: ocp.CheckpointManager, step: int, state,
                    error: type = MPDPError, force: bool = False) -> None:
  """Saves ``state`` as checkpoint ``step``, synchronously (the files are
  complete when it returns), after :func:`check_room`."""
  check_room(mngr, state, error, step)
  with _named_write_errors(os.fspath(mngr.directory), error):
    mngr.save(step, args=ocp.args.StandardSave(state), force=force)


def restore_latest(mngr: ocp.CheckpointManager, state,
                   error: type = MPDPError):
  """The latest checkpoint of ``mngr`` restored into ``state``'s structure.

  Returns ``state`` unchanged when there is no checkpoint yet (a new run).
  A checkpoint that does not fit ``state``, or is damaged, raises
  ``error`` (the caller's: MPDPError, or TrainingError for the simulator's
  training).
  """
  latest = mngr.latest_step()
  if latest is None:
    return state
  cannot = (f'cannot resume from the checkpoint of step {latest} in '
            f'{mngr.directory}: it does not fit this config\'s model and '
            'optimiser')
  misfit = _checkpoint_misfit(mngr, latest, state)
  if misfit:
    raise error(f'{cannot} ({misfit}); train in a new --workdir, or with '
                'the config that wrote it.')
  try:
    restored = mngr.restore(latest, args=ocp.args.StandardRestore(
      jax.tree.map(ocp.utils.to_shape_dtype_struct, state)))
  except Exception as e:  # noqa: BLE001 (orbax raises many kinds)
    raise error(
      f'{cannot}, or it is damaged ({type(e).__name__}: '
      f'{" ".join(str(e).split())[:200]}); train in a new --workdir, or '
      'with the config that wrote it.') from None
  logging.info('resumed from step %d', latest)
  return jax.tree.map(_placed_like, restored, state)


def _arrays(tree) -> list[tuple[str, tuple, np.dtype]]:
  """(key path, shape, dtype) of each array leaf of ``tree``."""
  return [(jax.tree_util.keystr(k), tuple(np.shape(v)), np.dtype(v.dtype))
          for k, v in jax.tree_util.tree_leaves_with_path(tree)]


def _checkpoint_misfit(mngr, step, state) -> str | None:
  """How the checkpoint of ``step`` differs from ``state``'s arrays, or None.

  Read from the checkpoint's metadata before restoring: a restore that
  fails part-way leaves orbax's reads pending, and they warn at exit.
  The params are compared by name (flax keeps them in plain dicts, saved
  as they are); the optimiser state as a multiset of shapes, since orbax
  saves its named tuples as dicts, in an order that need not be theirs.
  None also when the metadata cannot be read: the restore then decides.
  """
  # (The default step folder and item name: with others the check finds
  # no folder and leaves it to the restore.)
  path = mngr.directory / str(step) / 'default'  # an etils Path
  if not os.path.isdir(path):
    return None
  handler = None
  try:
    handler = ocp.StandardCheckpointHandler()
    meta = handler.metadata(path)
    saved = _arrays(getattr(meta, 'tree', meta))
    want = _arrays(state)
  except Exception:  # noqa: BLE001 (orbax versions differ; restore decides)
    return None
  finally:
    if handler is not None:
      handler.close()
  there = {k: (s, d) for k, s, d in saved}
  here = {k: (s, d) for k, s, d in want}
  for key in sorted(set(there) | set(here)):
    if not key.startswith("['params']") or there.get(key) == here.get(key):
      continue
    name = key[len("['params']"):]
    if key not in there:
      return f'its params have no {name}, which this config\'s model has'
    if key not in here:
      return f'its params have {name}, which this config\'s model has not'
    (s0, d0), (s1, d1) = there[key], here[key]
    return (f'params{name} is {s0} {d0} there and {s1} {d1} in this '
            'config\'s model')
  def shapes(arrays):
    return sorted((s, str(d)) for _, s, d in arrays)
  if shapes(saved) != shapes(want):
    return (f'its optimiser state ({len(saved)} arrays in all) differs '
            f'from this config\'s ({len(want)})')
  return None


def _placed_like(restored, template):
  """``restored`` placed the way a new run's ``template`` leaf is.

  Orbax hands back arrays committed to a device, where a new run's state is
  uncommitted: jitted steps would compile a second program for the resumed
  run (same shapes, other argument placement). Leaves the template placed
  on purpose (committed, or sharded) keep the placement orbax restored.
  """
  if isinstance(template, jax.Array) and not template.committed:
    return jnp.asarray(np.asarray(restored))
  return restored


def _compile_step(step):
  return jax.jit(step)


def save_interrupted(mngr: ocp.CheckpointManager, state,
                     error: type = MPDPError) -> int | None:
  """On an interruption (Ctrl-C, or the experiment scripts' SIGTERM), the
  state of the last finished step saved as a checkpoint, so that a rerun in
  the same workdir resumes there instead of at the last periodic
  checkpoint (up to ``checkpoint_every - 1`` steps earlier).

  Nothing is saved when that step is saved already or the state is not
  finite (nor when a step that donated its state was cut off: the training
  loops here do not donate, so that an interruption between a step's
  return and its assignment leaves the step before). Returns the step
  saved, or None.
  """
  leaves = jax.tree.leaves(state)
  if any(getattr(a, 'is_deleted', lambda: False)() for a in leaves):
    logging.warning('interrupted inside a step: the latest checkpoint in %s '
                    'stays the one to resume from', mngr.directory)
    return None
  step = int(state['step'])
  if step == 0 or step == mngr.latest_step():
    return None
  if not _finite(jnp.zeros(()), state['params']):
    logging.warning('interrupted at step %d with non-finite weights: not '
                    'saved', step)
    return None
  try:
    save_checkpoint(mngr, step, state, error, force=True)
  except error as e:  # no room: the interruption goes on
    logging.warning('interrupted at step %d, not saved: %s', step, e)
    return None
  logging.warning('interrupted: step %d saved in %s; run again with the '
                  'same workdir to resume', step, mngr.directory)
  return step


def _finite(loss, params) -> bool:
  """Whether the loss and every weight are finite (one host sync)."""
  leaves = [jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(params)]
  return bool(jnp.isfinite(loss) & jnp.all(jnp.stack(leaves)))


def holds_workdir(validate, error: type = MPDPError):
  """Decorator of a training ``fn(config, workdir)``: ``validate(config)``
  first (a bad config fails before the workdir is made), then the workdir
  checked (:func:`check_workdir`) and held (``atomic_files.hold_folder``)
  while it trains, so that a second training into it (a job submitted
  twice, a requeue while the first still runs) stops at once, naming the
  first, instead of both writing the same checkpoints."""

  def decorate(fn):
    @functools.wraps(fn)
    def held(config, workdir, *args, **kwargs):
      validate(config)
      path = check_workdir(workdir, error)
      with atomic_files.hold_folder(path, error, what='workdir',
                                    flag='--workdir'):
        return fn(config, workdir, *args, **kwargs)

    return held

  return decorate


@holds_workdir(validate_config)
def train_and_evaluate(config, workdir: str) -> dict:
  """Trains MPDP on synthetic objects, checkpointing and resuming in workdir.

  Args:
    config: ConfigDict (see module docstring).
    workdir: directory for ``checkpoints/``, ``metrics.jsonl`` and
      ``config.json``; created if missing. If it holds checkpoints, training
      resumes from the latest step.

  Returns:
    dict: final held-out metrics (see :func:`evaluate`) plus ``step``,
    ``train_loss`` and ``params`` (the trained params pytree).

  Raises:
    MPDPError: a bad config field or workdir (:func:`validate_config`,
      :func:`check_workdir`), or a workdir that another training holds
      (:func:`holds_workdir`), before any data is made or code compiled;
      a disk without room for a checkpoint (:func:`check_room`).
  """
  tc = config.train
  mcfg = validate_config(config)
  workdir = check_workdir(workdir)
  logging.info('MPDP training on %s; workdir %s', jax.devices(), workdir)
  # (The sections this training reads; config.sim is the simulator's.)
  record_config(workdir, {k: v for k, v in config.to_dict().items()
                          if k in ('model', 'data', 'train')})

  seconds = collections.Counter()
  t0 = time.perf_counter()
  train_data, eval_data = make_datasets(config)
  seconds['data'] = time.perf_counter() - t0
  logging.info('generated %d train / %d held-out objects in %.1f s',
               config.data.num_train, config.data.num_eval, seconds['data'])

  params = model_lib.init_params(jax.random.key(tc.seed), mcfg,
                                 config.data.num_points)
  tx = make_optimizer(tc)
  state = {'step': jnp.asarray(0, jnp.int32), 'params': params,
           'opt_state': tx.init(params)}
  loss_fn = make_loss(mcfg, tuple(tc.channel_weights))
  # (Not donated: an interruption between the step's return and the
  # assignment would leave `state` deleted and nothing to save.)
  step_fn = _compile_step(make_train_step(loss_fn, tx))

  loss = per = None
  t0 = time.perf_counter()
  with checkpoint_manager(workdir, tc.max_to_keep) as mngr:
    state = restore_latest(mngr, state)
    check_room(mngr, state)
    start = int(state['step'])
    trim_metrics(workdir, start)
    seconds['checkpoints'] += time.perf_counter() - t0
    t_start = time.time()
    try:
      for step in range(start, tc.num_steps):
        t0, aside = time.perf_counter(), 0.0  # (aside: evaluation, saves)
        batch = _batch(train_data, tc.seed, step, tc.batch_size)
        state, loss, per = step_fn(state, batch)
        if step == start:
          jax.block_until_ready(loss)
        done = step + 1
        log = done % tc.log_every == 0 or done == tc.num_steps
        save = done % tc.checkpoint_every == 0 or done == tc.num_steps
        if (log or save) and not _finite(loss, state['params']):
          raise MPDPError(
            f'MPDP training went non-finite by step {done} (train loss '
            f'{float(loss)}); nothing from it was saved (the last checkpoint '
            f'in {workdir} is from before). Lower config.train.learning_rate '
            f'(now {tc.learning_rate}) or config.train.grad_clip.')
        if log:
          rec = {'step': done, 'train_loss': float(loss),
                 'train_msle': [float(x) for x in per],
                 'elapsed_s': time.time() - t_start}
          if done % tc.eval_every == 0 or done == tc.num_steps:
            t1 = time.perf_counter()
            rec.update(evaluate(state['params'], mcfg, eval_data))
            dt = time.perf_counter() - t1
            aside += dt
            seconds['evaluate'] += dt
          logging.info('step %d: %s', done, rec)
          append_metrics(workdir, rec)
        if save:
          t1 = time.perf_counter()
          save_checkpoint(mngr, done, state)
          dt = time.perf_counter() - t1
          aside += dt
          seconds['checkpoints'] += dt
        seconds['first step (compiles)' if step == start else 'steps'] += (
          time.perf_counter() - t0 - aside)
    except KeyboardInterrupt:  # (Ctrl-C, or SIGTERM in the scripts)
      save_interrupted(mngr, state)
      raise
    mngr.wait_until_finished()
  t0 = time.perf_counter()
  result = evaluate(state['params'], mcfg, eval_data)
  seconds['evaluate'] += time.perf_counter() - t0
  result.update(step=int(state['step']),
                train_loss=None if loss is None else float(loss),
                seconds={k: round(v, 3) for k, v in seconds.items()},
                params=state['params'])
  logging.info('time: %s', ', '.join(f'{k} {v:.1f} s'
                                     for k, v in seconds.items()))
  return result
