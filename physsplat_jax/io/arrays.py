"""Pytrees of arrays in one ``.npz`` file: ``save_tree`` / ``load_tree``.

For ``pipeline.Params`` (MPDP weights, material scales, velocities,
forces) and any other tree of arrays: each leaf is stored under its tree
path (``.velocity``, ``.mpdp['params']['Dense_0']['kernel']``), empty
arrays included (orbax refuses a zero-size array, and ``init_params`` of a
scene without forces gives ``forces`` of shape (0, 3)). Loading takes a
template of the same structure, e.g. ``init_params(prepared, config)``,
and checks every path, shape and dtype against it, so a file saved for
another scene or config is named, not silently misassigned.
"""

from __future__ import annotations

import os

import jax
import numpy as np

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.io import paths
from physsplat_jax.io.paths import check_output_file


class TreeFileError(PhysSplatError, ValueError):
  """A tree file that cannot be written, read, or does not fit its
  template; the message names the file and the path in the tree."""


def _paths(tree) -> list[tuple[str, object]]:
  return [(jax.tree_util.keystr(p), leaf)
          for p, leaf in jax.tree_util.tree_leaves_with_path(tree)]


def save_tree(path, tree) -> str:
  """Writes every array leaf of ``tree`` to ``path`` (``.npz``, NumPy's
  format, uncompressed) under its tree path; returns the path.

  Raises:
    TreeFileError: a leaf that is not an array or number, or a path that
      cannot become a file.
  """
  path = check_output_file(path, TreeFileError, what='.npz', create=True)
  arrays = {}
  for key, leaf in _paths(tree):
    try:
      arrays[key] = np.asarray(leaf)
    except Exception as e:  # noqa: BLE001 - e.g. an abstract value
      raise TreeFileError(f'{path}: the leaf {key} is not an array '
                          f'({type(leaf).__name__}: {e})') from None
    kind = arrays[key].dtype.kind
    if kind == 'O':
      raise TreeFileError(f'{path}: the leaf {key} is not an array '
                          f'({type(leaf).__name__})')
    if kind not in 'biufc':  # e.g. bfloat16: NumPy's format has no such type
      raise TreeFileError(
        f'{path}: the leaf {key} is {arrays[key].dtype}, which .npz does '
        'not store; cast it to float32 first (params.astype(jnp.float32))')
  # Complete, then in place: never half a file.
  paths.write_npz(path, arrays, TreeFileError)
  return path


def load_tree(path, like):
  """The tree saved in ``path``, in the structure of ``like`` (a template
  with the same paths, shapes and dtypes, e.g. ``init_params(prepared,
  config)``), with JAX arrays as leaves.

  Raises:
    TreeFileError: the file is missing or not an ``.npz``, or its arrays do
      not fit the template (a path missing or extra, a shape or dtype that
      differs), each named.
  """
  path = os.fspath(path)
  try:
    data = np.load(path, allow_pickle=False)
  except FileNotFoundError:
    raise TreeFileError(f'{path}: no such file') from None
  except (OSError, ValueError) as e:
    raise TreeFileError(f'{path}: not a .npz tree file ({e})') from None
  if not isinstance(data, np.lib.npyio.NpzFile):
    raise TreeFileError(f'{path}: a single array (.npy), not a .npz tree '
                        'file written by save_tree')
  with data:
    want = _paths(like)
    keys = [k for k, _ in want]
    extra = sorted(set(data.files) - set(keys))
    missing = [k for k in keys if k not in data.files]
    if missing or extra:
      raise TreeFileError(
        f'{path}: does not fit the template: '
        + '; '.join(s for s in (
          f'missing {missing[:4]}' if missing else '',
          f'not in the template {extra[:4]}' if extra else '') if s)
        + ' (saved for another scene, config or MPDP network?)')
    leaves = []
    for key, ref in want:
      a = data[key]
      ref_shape = tuple(np.shape(ref))  # (arrays or ShapeDtypeStructs)
      ref_dtype = np.dtype(getattr(ref, 'dtype', None)
                           or np.asarray(ref).dtype)
      canon = jax.dtypes.canonicalize_dtype  # (float64 is float32 to JAX
      # without x64 mode: a Python float leaf is stored as float64)
      if a.shape != ref_shape or canon(a.dtype) != canon(ref_dtype):
        raise TreeFileError(
          f'{path}: {key} is {a.dtype} {a.shape} in the file, '
          f'{ref_dtype} {ref_shape} in the template (saved for another '
          'scene or config, or another float type?)')
      leaves.append(jax.numpy.asarray(a))
  return jax.tree.unflatten(jax.tree.structure(like), leaves)
