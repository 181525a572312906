"""Files written whole or not at all, and OS errors named with their fix.

Every writer of the package (outputs, scene stores, training checkpoints'
side files, exported weights) fills a temporary file beside the target and
renames it: a full disk or an interruption leaves the earlier file of that
name, never half a file, and no temporary file. Core: every layer may use it.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import stat
from typing import Callable

import numpy as np

from physsplat_jax.errors import PhysSplatError


def os_error_reason(e: OSError) -> str:
  """What an OS error means for an output, and its fix, in a few words."""
  why = e.strerror or str(e)
  if e.errno in (errno.ENOSPC, errno.EDQUOT):
    return f'{why}: free space on that disk, or write the output elsewhere'
  if e.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
    return f'{why}: choose a writable output path'
  return f'{why}; choose another output path'


PARTIAL = re.compile(
  r'\.(?P<stem>.+)\.\d+(-[0-9a-f]+)?\.partial(?P<ext>\.[^.]*)?')


def partial_path(path: str) -> str:
  """A new temporary name beside ``path`` for a writer to fill before
  renaming it to ``path``: hidden, with this process's id and a random
  token (two threads, two runs, or two hosts with equal pids writing one
  path never share one), the extension kept (writers pick the format by
  it). Names of this form match :data:`PARTIAL`."""
  head, tail = os.path.split(os.fspath(path))
  stem, ext = os.path.splitext(tail)
  token = secrets.token_hex(3)
  return os.path.join(head, f'.{stem}.{os.getpid()}-{token}.partial{ext}')


@contextlib.contextmanager
def atomic_output(path, error: type[Exception], *, what: str = 'output'):
  """The temporary path (:func:`partial_path`) to fill in the ``with``
  block; renamed to ``path`` when the block ends without an error.

  On any failure the temporary file is removed, so ``path`` holds either
  the earlier file or the complete new one, and nothing half-written is
  left; an ``OSError`` (a full disk) is raised as ``error`` naming
  ``path`` and the fix. Errors of the package's own classes pass (their
  message naming ``path`` where it named the temporary file).

  A ``path`` that is a symbolic link has the file it points to replaced
  (the link stays); the file keeps its permissions. A ``path`` that is not
  a regular file (``/dev/stdout``, a named pipe) is written directly.
  """
  p = os.fspath(path)
  real = os.path.realpath(p)
  try:
    mode = os.stat(real).st_mode
  except OSError:
    mode = None
  if mode is not None and not stat.S_ISREG(mode):
    try:
      yield p
    except OSError as e:
      if isinstance(e, PhysSplatError):
        raise
      raise error(f'{p}: cannot write the {what} file '
                  f'({os_error_reason(e)})') from None
    return
  tmp = partial_path(real)
  try:
    yield tmp
    if mode is not None:
      with contextlib.suppress(OSError):
        os.chmod(tmp, stat.S_IMODE(mode))
    os.replace(tmp, real)
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


def write_atomically(path, write: Callable[[str], object],
                     error: type[Exception], *, what: str = 'output') -> str:
  """``write(tmp)``, then ``tmp`` renamed to ``path``
  (:func:`atomic_output`).

  Returns:
    ``os.fspath(path)``.
  """
  with atomic_output(path, error, what=what) as tmp:
    write(tmp)
  return os.fspath(path)


def write_npz(path, arrays: dict, error: type[Exception], *,
              what: str = '.npz', compressed: bool = False) -> str:
  """NumPy's ``.npz`` of ``arrays`` at ``path`` exactly (``np.savez`` given
  a name adds '.npz' when it lacks one), through :func:`atomic_output`."""
  save = np.savez_compressed if compressed else np.savez

  def write(tmp):
    with open(tmp, 'wb') as f:
      save(f, **arrays)

  return write_atomically(path, write, error, what=what)


# TensorStore (orbax's array writer) raises ValueErrors whose text carries
# the OS error: 'Error writing "params.w/0" in OCDBT database at local file
# "PATH/": Failed writing: "PATH/d/..." ... [os_error_code='28']'.
_OS_ERROR_CODE = re.compile(r"os_error_code='?(\d+)")
_LOCAL_FILE = re.compile(r'(?:local file|Failed writing:) "([^"]+)"')


def os_error_of(e: BaseException) -> OSError | None:
  """The OS error behind ``e``: itself, the errors it was raised from
  (``__cause__``), or one that TensorStore put in its text as
  ``os_error_code`` (the file: the first 'local file "..."'); else None.
  The package's own errors are not OS errors."""
  seen = set()
  while e is not None and id(e) not in seen:
    seen.add(id(e))
    if isinstance(e, PhysSplatError):
      return None
    if isinstance(e, OSError) and e.errno is not None:
      return e
    m = _OS_ERROR_CODE.search(str(e))
    if m:
      code = int(m.group(1))
      f = _LOCAL_FILE.search(str(e))
      return OSError(code, os.strerror(code), f.group(1) if f else None)
    e = e.__cause__
  return None
