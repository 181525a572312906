"""Files written whole or not at all, and OS errors named with their fix.

Every writer of the package (outputs, scene stores, training checkpoints'
side files, exported weights) fills a temporary file beside the target and
renames it: a full disk or an interruption leaves the earlier file of that
name, never half a file, and no temporary file. Core: every layer may use it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import re
import secrets
import shutil
import socket
import stat
import threading
from typing import Callable

import numpy as np
from absl import logging

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


def free_bytes(path: str) -> int | None:
  """Free bytes on the disk of ``path`` (a folder that exists), or None
  where the system cannot say (the write that follows then decides):
  the one probe behind the output folder's warning
  (``io.outputs.check_free_space``) and the training's refusal
  (``mpdp.train.check_room``)."""
  try:
    return shutil.disk_usage(path).free
  except OSError:
    return None


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


def final_path(path) -> str | None:
  """The path a temporary name of :func:`partial_path` is renamed to, or
  None when ``path`` is not such a name."""
  head, tail = os.path.split(os.fspath(path))
  m = PARTIAL.fullmatch(tail)
  return os.path.join(head, m['stem'] + (m['ext'] or '')) if m else None


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
      _raise_named(e, p, error, what, (p, real))
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
      _raise_named(e, p, error, what, (p, real, tmp))
    if isinstance(e, PhysSplatError) and tmp in str(e):
      try:  # the message names the file the user asked for
        renamed = type(e)(str(e).replace(tmp, p))
      except Exception:  # noqa: BLE001 - another signature: as it is
        raise e from None
      raise renamed from None
    raise


def _raise_named(e: OSError, p: str, error: type[Exception], what: str,
                 ours=()):
  """``e`` again, or an OS error as ``error`` naming ``p`` and the fix.

  An error that names another file than ``ours`` (the output, its target,
  its temporary file: e.g. an input the block reads) is not this write's
  and passes as it is."""
  if isinstance(e, PhysSplatError):
    raise e
  other = getattr(e, 'filename', None)
  if isinstance(other, (str, bytes, os.PathLike)) and os.fsdecode(
      other) not in ours:
    raise e
  raise error(f'{p}: cannot write the {what} file ({os_error_reason(e)})'
              ) from None


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


def write_data(path, data: str | bytes, error: type[Exception], *,
               what: str = 'output') -> str:
  """``data`` (text, or bytes) as the file ``path``, through
  :func:`atomic_output`."""

  def write(tmp):
    with open(tmp, 'w' if isinstance(data, str) else 'wb') as f:
      f.write(data)

  return write_atomically(path, write, error, what=what)


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


# ---------------------------------------------------------- folder locks

LOCK = '.physsplat_run.lock'
# (folder, thread) -> nesting depth of this process's holds
_held: dict[tuple[str, int], int] = {}
_held_guard = threading.Lock()


def _lock_owner(path: str) -> tuple[int, str] | None:
  """(pid, host) written in a lock file, or None when unreadable."""
  try:
    with open(path) as f:
      pid, host = f.read().split()[:2]
    return int(pid), host
  except (OSError, ValueError):
    return None


def _write_owner(fd: int, text: str) -> None:
  os.ftruncate(fd, 0)
  os.write(fd, text.encode())


def _take_lock(folder: str, path: str, error: type[Exception], where: str,
               flag: str) -> int:
  """The open lock file of ``folder``, locked (``flock``) by this process.

  The kernel holds the lock for the open file and releases it when the
  process ends however it ends, so a lock file that a killed run left is
  taken over, and two runs starting at once cannot both hold the folder.
  The file holds the pid and host, for the message of a run refused.
  """
  for _ in range(5):
    try:
      fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
    except OSError as e:
      raise error(f'{where} cannot be written ({os_error_reason(e)})'
                  ) from None
    try:
      try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
      except BlockingIOError:
        owner = _lock_owner(path)
        who = (f'pid {owner[0]} on {owner[1]}' if owner
               else 'another process')
        raise error(f'{where} is in use by another run ({who}); give '
                    f'another {flag}, or wait for that run to end') from None
      except OSError as e:  # a file system without locks (some NFS mounts)
        logging.warning('%s: cannot lock %s (%s); a second run into this '
                        'folder would not be refused', folder, path, e)
      # Locked: but if the run before removed the file (it ended) between
      # our open and our lock, the lock is on a file no one else sees.
      try:
        here, now = os.fstat(fd), os.stat(path)
        current = (here.st_dev, here.st_ino) == (now.st_dev, now.st_ino)
      except FileNotFoundError:
        current = False
      if not current:
        os.close(fd)
        continue
      before = _lock_owner(path)
      if before is not None and before[0] != os.getpid():
        logging.info('%s: taking over the lock of an ended run (pid %d on '
                     '%s)', folder, *before)
      try:
        _write_owner(fd, f'{os.getpid()} {socket.gethostname()}\n')
      except OSError as e:
        with contextlib.suppress(OSError):
          os.remove(path)
        raise error(f'{where}: cannot write its lock file {path} '
                    f'({os_error_reason(e)})') from None
      return fd
    except BaseException:
      with contextlib.suppress(OSError):
        os.close(fd)
      raise
  raise error(f'{where}: cannot take its lock {path} (other runs keep '
              'replacing it); try again')


@contextlib.contextmanager
def hold_folder(folder: str, error: type[Exception], *,
                what: str = 'folder', flag: str = '--out',
                on_take: Callable[[str], object] | None = None):
  """Holds ``folder`` for this run (a lock file, :data:`LOCK`, locked with
  the kernel's ``flock``) while the block runs.

  A second run into the same folder (another process, or another thread
  of this one) fails at once naming the first; the kernel releases the
  lock when its process ends, so the file a killed run left is taken over
  and two runs starting at once cannot both hold it. Nested holds by one
  thread are allowed. ``on_take(folder)`` runs once the lock is taken (the
  outputs remove the temporary files a killed run left).

  Raises:
    error: another live run holds the folder (naming it, and ``flag`` for
      the fix), or the lock file cannot be written.
  """
  key = (os.path.realpath(folder), threading.get_ident())
  with _held_guard:
    nested = key in _held
    if nested:
      _held[key] += 1
  if nested:
    try:
      yield
    finally:
      with _held_guard:
        _held[key] -= 1
    return
  path = os.path.join(folder, LOCK)
  fd = _take_lock(folder, path, error, f'{what} {folder!r}', flag)
  with _held_guard:
    _held[key] = 1
  try:
    if on_take is not None:
      on_take(folder)
    yield
  finally:
    with _held_guard:
      del _held[key]
    with contextlib.suppress(OSError):
      os.remove(path)  # still locked: no run takes it meanwhile
    os.close(fd)
