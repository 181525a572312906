"""Output paths checked before the work, for every writer of the package.

A writer that fails only at its end (a folder where the file should be, a
file where a folder should be, a folder that cannot be written) loses the
work done before it; these checks cost a few ``stat`` calls, so writers make
them up front, each raising its own module's error class.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
from typing import Callable

from physsplat_jax.errors import PhysSplatError


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


def open_output(path, error: type[Exception], *, what: str = 'output'):
  """:func:`check_output_file` (folders created), then ``open(path, 'wb')``,
  an OS error raised as ``error`` naming the file."""
  p = check_output_file(path, error, what=what, create=True)
  try:
    return open(p, 'wb')
  except OSError as e:
    raise error(f'{p}: cannot write the {what} file ({e.strerror or e}); '
                'choose a writable output path') from None


def os_error_reason(e: OSError) -> str:
  """What an OS error means for an output, and its fix, in a few words."""
  why = e.strerror or str(e)
  if e.errno in (errno.ENOSPC, errno.EDQUOT):
    return f'{why}: free space on that disk, or write the output elsewhere'
  if e.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
    return f'{why}: choose a writable output path'
  return f'{why}; choose another output path'


PARTIAL = re.compile(r'\..+\.\d+\.partial(\.[^.]*)?')


def partial_path(path: str) -> str:
  """The temporary name beside ``path`` that a writer fills before renaming
  it to ``path``: hidden, with this process's id (two runs into one folder
  never share one), the extension kept (writers pick the format by it).
  Names of this form match :data:`PARTIAL`."""
  head, tail = os.path.split(os.fspath(path))
  stem, ext = os.path.splitext(tail)
  return os.path.join(head, f'.{stem}.{os.getpid()}.partial{ext}')


def write_atomically(path, write: Callable[[str], object],
                     error: type[Exception], *, what: str = 'output') -> str:
  """``write(tmp)`` to :func:`partial_path`, then renamed to ``path``.

  On any failure the temporary file is removed, so ``path`` holds either
  the earlier file or the complete new one, and nothing half-written is
  left; an ``OSError`` (a full disk) is raised as ``error`` naming
  ``path`` and the fix. Errors of the package's own classes pass (their
  message naming ``path`` where it named the temporary file).

  Returns:
    ``os.fspath(path)``.
  """
  p = os.fspath(path)
  tmp = partial_path(p)
  try:
    write(tmp)
    os.replace(tmp, p)
  except BaseException as e:
    with contextlib.suppress(OSError):
      os.remove(tmp)
    if isinstance(e, OSError) and not isinstance(e, PhysSplatError):
      raise error(f'{p}: cannot write the {what} file '
                  f'({os_error_reason(e)})') from None
    if isinstance(e, PhysSplatError) and tmp in str(e):
      try:  # the message names the file the user asked for
        renamed = type(e)(str(e).replace(tmp, p))
      except Exception:  # noqa: BLE001 - another signature: as it is
        raise e from None
      raise renamed from None
    raise
  return p
