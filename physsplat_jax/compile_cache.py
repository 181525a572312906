"""JAX's persistent compilation cache in a user cache folder.

Compiling the MPM frame, the deformation and the rasterizer takes seconds
to tens of seconds per shape; with the cache on, a second run of the same
shapes (same scene size, grid, image size) loads the compiled code from
disk instead. The experiment scripts turn it on by default
(``experiments/lib/cli.py``); library users call
:func:`enable_compilation_cache` once.

Where: ``$PHYSSPLAT_JAX_CACHE`` if set (``off``, ``0`` or ``none``
disables it), else ``$XDG_CACHE_HOME/physsplat_jax/jax`` (default
``~/.cache/physsplat_jax/jax``).
"""

from __future__ import annotations

import os
import tempfile

import jax
from absl import logging

ENV = 'PHYSSPLAT_JAX_CACHE'
_OFF = ('off', '0', 'none', 'false', 'no')


def default_cache_dir() -> str | None:
  """The cache folder from the environment, or None when disabled."""
  env = os.environ.get(ENV)
  if env is not None:
    return None if env.strip().lower() in _OFF else os.path.expanduser(env)
  base = os.environ.get('XDG_CACHE_HOME') or os.path.join(
    os.path.expanduser('~'), '.cache')
  return os.path.join(base, 'physsplat_jax', 'jax')


def enable_compilation_cache(path: str | None = None,
                             min_compile_time_s: float = 0.0) -> str | None:
  """Turns the persistent compilation cache on; returns its folder.

  Args:
    path: cache folder; None uses :func:`default_cache_dir` ('off' there
      disables the cache and returns None).
    min_compile_time_s: only programs that took at least this long to
      compile are stored. The default 0 stores every program: preparing a
      scene compiles ~160 small host-side programs (~30 ms each, below
      JAX's usual threshold of 1 s), and storing them took the
      tabletop's warm preparation from 6.7-7.3 s to 3.0 s on a 2-core CPU.
  """
  path = default_cache_dir() if path is None else path
  if path is None or str(path).strip().lower() in _OFF:
    logging.info('compilation cache: off')
    return None
  try:
    os.makedirs(path, exist_ok=True)
    # A folder that cannot take a file (read-only, a full disk) made JAX
    # warn once per program (23 warnings in a small run): one here instead.
    with tempfile.NamedTemporaryFile(dir=path, prefix='.write_test_') as f:
      f.write(b'x' * 4096)
      f.flush()
  except OSError as e:
    logging.warning('compilation cache: cannot write to %s (%s); running '
                    'without it (every program compiles again in each run; '
                    'free space there, or choose another folder with '
                    '--compile_cache or PHYSSPLAT_JAX_CACHE)', path,
                    e.strerror or e)
    return None
  jax.config.update('jax_compilation_cache_dir', path)
  jax.config.update('jax_persistent_cache_min_compile_time_secs',
                    float(min_compile_time_s))
  jax.config.update('jax_persistent_cache_min_entry_size_bytes', 0)
  logging.info('compilation cache: %s', path)
  return path
