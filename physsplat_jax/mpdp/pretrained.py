"""Shipped MPDP weights: a flat ``.npz`` of params plus a JSON model config.

The shipped file ``physsplat_jax/data/mpdp/mpdp_params.npz`` (and
``mpdp_params.json``) is produced by ``experiments/train_mpdp.py
--export=...`` from an orbax training checkpoint; ``load_pretrained()``
returns its params pytree, which the pipeline uses by default with
:func:`physsplat_jax.mpdp.model.predict` (the default architecture).
A flat NumPy archive (not an orbax directory) keeps the package small and
loadable without orbax.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import zipfile
import zlib

import numpy as np

from physsplat_jax import atomic_files
from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp.model import MPDPError
from physsplat_jax.types import device_array

PRETRAINED_DIR = os.path.join(os.path.dirname(os.path.dirname(
  os.path.abspath(__file__))), 'data', 'mpdp')
PRETRAINED_NAME = 'mpdp_params'


def _flatten(tree, prefix=''):
  out = {}
  for k, v in tree.items():
    key = f'{prefix}/{k}' if prefix else str(k)
    if isinstance(v, dict):
      out.update(_flatten(v, key))
    else:
      out[key] = np.asarray(v)
  return out


def save_params(params, model_config: model_lib.ModelConfig, directory: str,
                name: str = PRETRAINED_NAME, metadata: dict | None = None):
  """Writes ``<directory>/<name>.npz`` and ``<name>.json``.

  Args:
    params: linen params pytree (nested dicts of arrays).
    model_config: the architecture the params belong to.
    directory: output directory (created if missing).
    name: file stem.
    metadata: extra JSON-serialisable info (e.g. held-out metrics).

  Both files are written whole before either replaces an earlier pair.

  Raises:
    MPDPError: a file cannot be written (a full disk: the earlier files
      are kept), naming it and the fix.
  """
  try:
    os.makedirs(directory, exist_ok=True)
  except OSError as e:
    raise MPDPError(f'{directory}: cannot create the folder '
                    f'({atomic_files.os_error_reason(e)})') from None
  flat = _flatten(dict(params))
  buf = io.BytesIO()
  np.savez_compressed(buf, **{k: v.astype(np.float32)
                              for k, v in flat.items()})
  blob = buf.getvalue()
  # The weights' digest in the description: a pair put together from two
  # exports of one architecture loaded silently.
  text = json.dumps({'model_config': model_config.to_dict(),
                     'npz_sha256': hashlib.sha256(blob).hexdigest(),
                     'metadata': metadata or {}}, indent=1)

  def write_both(tmp):  # both files complete before either is renamed
    with open(tmp, 'wb') as f:
      f.write(blob)
    atomic_files.write_data(os.path.join(directory, name + '.json'), text,
                            MPDPError, what='weights')

  atomic_files.write_atomically(os.path.join(directory, name + '.npz'),
                                write_both, MPDPError, what='weights')


def load_params(directory: str, name: str = PRETRAINED_NAME):
  """Reads params written by :func:`save_params`.

  Returns:
    (params pytree of float32 jax arrays, ModelConfig, metadata dict).

  Raises:
    MPDPError (a ValueError): if the files are missing or damaged, the
      weights are not the ones the JSON describes (its ``npz_sha256``,
      written since 2026-11-29; older files have none), or they do not fit
      its model config (a missing, extra or misshapen array; a non-float
      or non-finite value).
  """
  npz = os.path.join(directory, name + '.npz')
  js = os.path.join(directory, name + '.json')
  if not (os.path.exists(npz) and os.path.exists(js)):
    raise MPDPError(
      f'MPDP params not found: expected {npz} and {js}; train them with '
      'experiments/train_mpdp.py --export=<dir>.')
  fix = ('write both with experiments/train_mpdp.py --export=<dir> (or '
         'mpdp.save_params)')
  try:
    with open(js) as f:
      meta = json.load(f)
    cfg = model_lib.ModelConfig.from_dict(meta['model_config'])
  except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
    raise MPDPError(f'MPDP params {js}: not a model description '
                    f'({type(e).__name__}: {e}); {fix}.') from None
  try:
    with open(npz, 'rb') as f:
      blob = f.read()
    with np.load(io.BytesIO(blob), allow_pickle=False) as data:
      flat = {key: data[key] for key in data.files}
  except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile,
          zlib.error) as e:
    raise MPDPError(f'MPDP params {npz}: not a weights file written by '
                    f'save_params, or damaged ({type(e).__name__}); '
                    f'{fix}.') from None
  digest = meta.get('npz_sha256')
  if digest is not None and hashlib.sha256(blob).hexdigest() != digest:
    raise MPDPError(
      f'MPDP params {npz}: not the weights that {js} describes (their '
      'SHA-256 differs from its npz_sha256: the two files come from '
      f'different exports, or the weights were changed); {fix}.')
  _check_weights(flat, cfg, f'MPDP params {npz}', f'{js} ({cfg})', fix)
  params = {}
  for key, value in flat.items():
    node = params
    *parents, leaf = key.split('/')
    for p in parents:
      node = node.setdefault(p, {})
    node[leaf] = device_array(value)
  return params, cfg, meta.get('metadata', {})


def _check_weights(flat, cfg, where, config_of, fix):
  """Every array of ``cfg``'s network present with its shape, finite, and
  nothing else (:func:`model.param_shapes`: no Flax, no tracing)."""
  want = _flatten(model_lib.param_shapes(cfg))
  want = {k: tuple(int(n) for n in v) for k, v in want.items()}
  missing = sorted(set(want) - set(flat))
  extra = sorted(set(flat) - set(want))
  if missing or extra:
    raise MPDPError(
      f'{where}: the arrays do not fit the model config of {config_of} '
      f'(missing {missing[:4]}, unexpected {extra[:4]}); {fix}.')
  for k, shape in want.items():
    a = flat[k]
    if a.shape != shape:
      raise MPDPError(
        f'{where}: {k} has shape {a.shape}, the model config of '
        f'{config_of} needs {shape}; {fix}.')
    if not np.issubdtype(a.dtype, np.floating):
      raise MPDPError(f'{where}: {k} holds {a.dtype} values, not floats; '
                      f'{fix}.')
    if not np.all(np.isfinite(a)):
      raise MPDPError(
        f'{where}: {k} holds {int(np.sum(~np.isfinite(a)))} non-finite '
        f'values (NaN/inf weights give a NaN field); {fix} from a run '
        'that did not diverge.')


@functools.lru_cache(maxsize=1)
def _load_default():
  return load_params(PRETRAINED_DIR)


def load_pretrained():
  """Params of the shipped checkpoint (default architecture).

  Returns:
    The params pytree for :func:`physsplat_jax.mpdp.model.predict`.
  """
  params, cfg, _ = _load_default()
  if cfg != model_lib.ModelConfig():
    raise MPDPError(
      f'Shipped MPDP params were trained for {cfg}, not the default '
      'ModelConfig(); use make_predict(cfg) with load_params().')
  return params
