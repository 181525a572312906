"""Output paths checked before the work, for every writer of the package.

A writer that fails only at its end (a folder where the file should be, a
file where a folder should be, a folder that cannot be written) loses the
work done before it; these checks cost a few ``stat`` calls, so writers make
them up front, each raising its own module's error class.
"""

from __future__ import annotations

import contextlib
import os

from physsplat_jax.atomic_files import PARTIAL as PARTIAL
from physsplat_jax.atomic_files import atomic_output as atomic_output
from physsplat_jax.atomic_files import os_error_reason as os_error_reason
from physsplat_jax.atomic_files import partial_path as partial_path
from physsplat_jax.atomic_files import final_path as final_path
from physsplat_jax.atomic_files import write_atomically as write_atomically
from physsplat_jax.atomic_files import write_data as write_data
from physsplat_jax.atomic_files import write_npz as write_npz


def check_output_file(path, error: type[Exception], *, what: str = 'output',
                      create: bool = False) -> str:
  """Checks, without writing anything, that ``path`` can become a file.

  Refuses a path that is not a path, is a folder (or ends in a separator),
  whose folder cannot be created because an existing part of it is a file,
  or whose nearest existing folder is not writable.

  Args:
    path: the output file.
    error: the exception class raised (the calling module's own).
    what: what the file is, for the message (``'PLY'``, ``'scene
      sidecar'``).
    create: also create the missing folders.

  Returns:
    ``os.fspath(path)``.

  Raises:
    error: naming the path, what is in the way and the fix.
  """
  if not isinstance(path, (str, os.PathLike)):
    raise error(
      f'expected a {what} file path, got {type(path).__name__} {path!r}')
  p = os.fspath(path)
  if os.path.isdir(p) or p.endswith(('/', os.sep)):
    raise error(f'{p}: is a directory; give the {what} file\'s path (a new '
                'or existing file, not a folder)')
  folder = os.path.dirname(os.path.abspath(p))
  existing = folder
  while not os.path.exists(existing):  # the part of the folder that exists
    existing = os.path.dirname(existing)
  if not os.path.isdir(existing):
    raise error(f'{p}: cannot create the folder of the {what} file: '
                f'{existing} is a file, not a folder; choose another output '
                'path')
  if not os.access(existing, os.W_OK | os.X_OK):
    raise error(f'{p}: the folder {existing} is not writable; choose a '
                'writable output path')
  if create:
    try:
      os.makedirs(folder, exist_ok=True)
    except OSError as e:
      raise error(f'{p}: cannot create its folder ({e.strerror or e}); '
                  'choose a writable output path') from None
  return p


@contextlib.contextmanager
def open_output(path, error: type[Exception], *, what: str = 'output'):
  """:func:`check_output_file` (folders created), then the file open for
  writing (binary) in the ``with`` block: a temporary file, renamed to
  ``path`` when the block ends (:func:`atomic_output`), so a full disk or
  an error part-way leaves the earlier file and raises ``error`` naming
  ``path``."""
  p = check_output_file(path, error, what=what, create=True)
  with atomic_output(p, error, what=what) as tmp, open(tmp, 'wb') as f:
    yield f
