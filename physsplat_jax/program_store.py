"""Programs kept traced between processes, so that a run traces them once.

JAX's persistent compilation cache keys a compiled program by its lowered
module, so every process traces and lowers a program before it can find
it there. For the largest programs of a run that is seconds of Python on
every start: the MPM frame of the tabletop at paper scale (64³, 768
substeps) 1.2-1.7 s on the 2-core VM, the MPDP network on the 63k-point
donut 1.2 s. :func:`compile_stored` stores such a program, the first time
it is lowered, with ``jax.export`` (StableHLO, serialised), named by
everything its lowering depends on; a later process reads it back and
lowers only a call to it (milliseconds), then finds the compiled program
in the compilation cache as before.

The stored program is the same module: it computes the same bits (tests
compare them). Nothing is stored, and the program is traced as before,
without a compilation cache folder, without ``flatbuffers`` (``jax.export``'s
serialisation), for arguments spread over several devices, or when the
export fails; a stored file that cannot be read is traced and stored again,
and one that does not compile is compiled from a new trace, with a warning.
Deviceless, for an H100 (jax 0.10.2), the tabletop's stored frame compiles
to the same 20 kernels per substep, its Pallas stress kernel included.

The stored files are pickles (the program and its result's tree): the
cache folder must be the user's own, as JAX's compilation cache, whose
compiled programs run as they are read, must be.

:func:`stored_jit` is ``jax.jit`` with the same storage, for the smaller
programs a run calls on concrete arrays (the host loop's deformation and
render): called inside a trace, or without a cache folder, it is the plain
``jax.jit``.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import os
import pickle
import re
import threading
import time
from typing import Any, Callable, Sequence

from absl import logging
import jax
import numpy as np

from physsplat_jax import atomic_files

FOLDER = 'physsplat_programs'
# Pallas (Triton) kernels: JAX does not promise that a stored kernel loads
# in another JAX version; the name holds JAX's and jaxlib's versions, so a
# stored program is only read back by the JAX that wrote it.
_TRITON = '__gpu$xla.gpu.triton'
# Stored programs kept per name (the oldest go first): each code change,
# scene size or config is a new file (0.1-1 MB).
KEEP = 32
# Programs compiled in this process, by name and arguments (the host loop
# compiles on two threads at once: the lock guards the dict).
_COMPILED: dict = {}
_LOCK = threading.Lock()


@functools.lru_cache(maxsize=1)
def source_digest() -> str:
  """The package's source (every module): any change to the code names
  new files."""
  h = hashlib.sha256()
  root = os.path.dirname(os.path.abspath(__file__))
  for folder, dirs, files in os.walk(root):
    dirs.sort()
    for name in sorted(files):
      if name.endswith('.py'):
        path = os.path.join(folder, name)
        h.update(os.path.relpath(path, root).encode() + b'\0')
        with open(path, 'rb') as f:
          h.update(f.read())
  return h.hexdigest()


def folder() -> str | None:
  """The persistent compilation cache's folder (None: off); the programs
  are stored in its ``physsplat_programs/``."""
  return jax.config.jax_compilation_cache_dir or None


def _avals(leaves) -> str:
  return repr([(tuple(np.shape(a)), str(getattr(a, 'dtype', type(a).__name__)),
                bool(getattr(a, 'weak_type', False))) for a in leaves])


def path_for(name: str, static_key: str, tree, leaves) -> str | None:
  """Where a program is stored, or None (no compilation cache)."""
  base = folder()
  if not base:
    return None
  import jaxlib  # noqa: PLC0415

  device = _device(leaves)
  parts = [
    name, static_key, jax.__version__, jaxlib.__version__, device.platform,
    getattr(device, 'device_kind', ''), str(tree), _avals(leaves),
    str(jax.config.jax_enable_x64),
    str(jax.config.jax_default_matmul_precision), source_digest()]
  h = hashlib.sha256('\0'.join(parts).encode())
  return os.path.join(base, FOLDER, f'{name}_{h.hexdigest()[:40]}.jaxexport')


def _device(leaves):
  """The device a program of these arguments runs on: the first committed
  array's, else the default device."""
  for a in leaves:
    if isinstance(a, jax.Array) and getattr(a, 'committed', True):
      return next(iter(a.devices()))
  return jax.config.jax_default_device or jax.devices()[0]


def _memo_key(leaves) -> tuple:
  """What a compiled program depends on beyond the trace: the devices of
  the committed arrays (a compiled program is bound to them), the default
  device (where uncommitted ones go), and the settings a trace reads."""
  committed = set()
  for a in leaves:
    if isinstance(a, jax.Array) and getattr(a, 'committed', True):
      committed |= {d.id for d in a.sharding.device_set}
  return (tuple(sorted(committed)), str(jax.config.jax_default_device),
          bool(jax.config.jax_enable_x64),
          str(jax.config.jax_default_matmul_precision))


def _single_device(leaves) -> bool:
  """Arrays on one device at most, and no tracers (host values are put
  where the arrays are)."""
  devices = set()
  for a in leaves:
    if isinstance(a, jax.core.Tracer):
      return False
    if isinstance(a, jax.Array):
      devices |= set(a.sharding.device_set)
  return len(devices) <= 1


def compile_stored(jitted, args: Sequence[Any], *, name: str, out_tree,
                   static_key: str = '',
                   compile_fn: Callable | None = None) -> Callable:
  """``jitted`` compiled for ``args``, from its stored form when there is
  one; called as ``jitted`` is (positional arguments of these shapes).

  Args:
    jitted: a ``jax.jit`` function of positional arguments.
    args: its arguments (their shapes, dtypes and tree name the program).
    name: the program's name (the file's prefix).
    out_tree: the tree of its result (``jax.tree.structure``) if known
      without tracing it (e.g. the input state's for a frame; a program
      whose result has another tree is not stored), or None: the tree
      found when the program is traced, stored with it.
    static_key: what else its trace depends on (e.g. ``repr`` of a static
      config); the package's source, JAX's version and the device are in
      the name already.
    compile_fn: compiles a ``Lowered`` (default ``.compile()``).
  """
  compile_fn = compile_fn or (lambda lowered: lowered.compile())
  leaves, tree = jax.tree.flatten(tuple(args))
  memo = (jitted, name, static_key, tree, _avals(leaves), _memo_key(leaves))
  with _LOCK:
    if memo in _COMPILED:
      return _COMPILED[memo]
  lowered, wrap = _lower(jitted, args, leaves, tree, name, static_key,
                         out_tree)
  if wrap is None:
    compiled = compile_fn(lowered)
  else:
    try:
      compiled = wrap(compile_fn(lowered))
    except Exception as e:  # noqa: BLE001 - the traced program instead
      logging.warning('program store: the stored %s did not compile (%s: %s);'
                      ' compiling it from a new trace.', name,
                      type(e).__name__, e)
      compiled = compile_fn(jitted.lower(*args))
  with _LOCK:
    while len(_COMPILED) >= 32:
      _COMPILED.pop(next(iter(_COMPILED)), None)
    _COMPILED[memo] = compiled
  return compiled


def _lower(jitted, args, leaves, tree, name, static_key, out_tree):
  """``(lowered, wrap)``: ``wrap`` None when ``lowered`` is the usual
  trace's (nothing stored or read)."""
  path = (path_for(name, static_key, tree, leaves)
          if _single_device(leaves) else None)
  if path is None:
    return jitted.lower(*args), None
  try:
    from jax import export  # noqa: PLC0415
    from jax._src.export import serialization  # noqa: F401,PLC0415
  except ImportError as e:  # no flatbuffers: trace every time
    logging.log_first_n(logging.INFO, 'program store off: %s', 1, e)
    return jitted.lower(*args), None

  if os.path.exists(_not_stored(path)):
    return jitted.lower(*args), None
  exported = None
  if os.path.exists(path):
    try:
      stored = pickle.loads(read_file(path))
      exported = export.deserialize(bytearray(stored['exported']))
      if out_tree is not None and stored['out_tree'] != out_tree:
        raise ValueError('its result is not of the expected tree')
      out_tree = stored['out_tree']
    except Exception as e:  # noqa: BLE001 - unreadable: trace it again
      logging.warning('program store: cannot read %s (%s: %s); tracing the '
                      'program again.', path, type(e).__name__, e)
      exported = None
  if exported is None:
    exported, out_tree = _export(export, jitted, tree, leaves, out_tree, path)
    if exported is None:
      return jitted.lower(*args), None

  def wrap(compiled):
    def call(*args):
      return jax.tree.unflatten(out_tree, compiled(*jax.tree.leaves(args)))
    return call

  try:
    return jax.jit(exported.call).lower(*leaves), wrap
  except Exception as e:  # noqa: BLE001 - e.g. not these arguments' program
    logging.warning('program store: %s does not take these arguments (%s: '
                    '%s); tracing the program.', path, type(e).__name__, e)
    return jitted.lower(*args), None


def _export(export, jitted, tree, leaves, out_tree, path):
  """Exports and stores the program with its result's tree: ``(exported,
  out_tree)``, or ``(None, None)`` when it cannot be (then the caller
  lowers it as before)."""
  got = []

  def flat(*leaves):  # on flat leaves: no pytree types to store
    out = jitted(*jax.tree.unflatten(tree, leaves))
    outs = jax.tree.leaves(out)
    got.append((jax.tree.structure(out),
                any(getattr(getattr(x, 'aval', None), 'weak_type', False)
                    for x in outs)))
    return tuple(outs)

  # Arrays on the CPU of a GPU host (a render device of its own): a CPU
  # program, not one for the default backend.
  platform = _device(leaves).platform
  platforms = (['cpu'] if platform == 'cpu' and jax.default_backend() != 'cpu'
               else None)
  try:
    exported = export.export(
      jax.jit(flat), platforms=platforms, disabled_checks=[
        export.DisabledSafetyCheck.custom_call(_TRITON)])(*leaves)
    tree_out, weak = got[-1]
    if weak:  # a stored program's results would lose their weak types
      raise TypeError('a result is weakly typed (computed from Python '
                      'scalars only)')
    if out_tree is None:
      out_tree = tree_out
    elif tree_out != out_tree:  # the caller's result tree is not this one
      return None, None
    blob = pickle.dumps(dict(exported=bytes(exported.serialize()),
                             out_tree=out_tree),
                        protocol=pickle.HIGHEST_PROTOCOL)
  except Exception as e:  # noqa: BLE001 - cannot be stored: the usual path
    if not got:  # the function itself failed: its error comes from the
      return None, None  # caller's own trace, and nothing is recorded
    logging.info('program store: %s cannot be stored (%s: %s); it is traced '
                 'in every process.', path, type(e).__name__, e)
    # Recorded, so that later processes trace it at once instead of
    # trying again (a new code or JAX version is a new name).
    write_file(_not_stored(path), f'{type(e).__name__}: {e}'.encode())
    return None, None
  write_file(path, blob)
  return exported, out_tree


def _not_stored(path: str) -> str:
  """The record that the program of ``path`` cannot be stored."""
  return path[:-len('.jaxexport')] + '.notstored'


# A stored file: this tag, the SHA-256 of the content, the content. A file
# damaged on disk (a bit flipped, a copy cut short) fails the check and is
# built again; without it a scene read back with wrong positions, silently.
_TAG = b'PSJSTOR1'


def write_file(path: str, blob: bytes) -> bool:
  """Writes ``blob`` to ``path`` whole (a temporary file renamed; its
  digest first, see :func:`read_file`) and keeps the :data:`KEEP` newest
  files of its name (``{name}_{hash}{suffix}``); a failure (a full disk, a
  read-only folder) is logged and returns False, leaving no temporary file:
  it costs only the next process a trace or a build."""
  where = os.path.dirname(path)
  try:
    os.makedirs(where, exist_ok=True)
    atomic_files.write_data(path, _TAG + hashlib.sha256(blob).digest() + blob,
                            OSError, what='stored')
    name, suffix = os.path.splitext(os.path.basename(path))
    prune(where, name.rsplit('_', 1)[0], suffix)
  except OSError as e:
    logging.info('program store: cannot write %s (%s)', path, e)
    return False
  return True


def read_file(path: str) -> bytes:
  """The content :func:`write_file` stored at ``path``.

  Raises:
    OSError: it cannot be read.
    ValueError: it is damaged (its digest does not match) or was not
      written by :func:`write_file`.
  """
  with open(path, 'rb') as f:
    data = f.read()
  head = len(_TAG) + 32
  if len(data) < head or not data.startswith(_TAG):
    raise ValueError('not a stored file of this version')
  blob = data[head:]
  if hashlib.sha256(blob).digest() != data[len(_TAG):head]:
    raise ValueError('damaged: its content does not match its digest')
  return blob


# A temporary file older than this was left by a killed writer [s].
_STALE_S = 3600.0


def prune(where: str, name: str, suffix: str = '.jaxexport') -> None:
  """Keeps the :data:`KEEP` newest files ``{name}_*{suffix}`` of ``where``
  (stored programs, or what else is stored beside them), and removes the
  temporary files of its family that killed writers left (older than an
  hour: a live writer's is seconds old)."""
  family = re.compile(re.escape(name) + r'_[0-9a-f]{40}' + re.escape(suffix)
                      + '$')
  names = os.listdir(where)
  files = [os.path.join(where, f) for f in names if family.match(f)]
  files.sort(key=os.path.getmtime)
  stale = []
  for f in names:
    final = atomic_files.final_path(f)
    if final is not None and family.match(final):
      stale.append(os.path.join(where, f))
  now = time.time()
  for old in files[:-KEEP] + stale:
    try:
      if old in stale and now - os.path.getmtime(old) < _STALE_S:
        continue
      os.remove(old)
    except OSError:  # another process removed it
      pass


class StoredJit:
  """``jax.jit(fun, static_argnames=...)`` whose programs are stored
  traced (:func:`compile_stored`, named ``name``).

  Called on concrete arrays with a cache folder, it compiles (once per
  static values and argument shapes) from the stored program; inside a
  trace (``jit``, ``grad``, ``vmap``), under ``jax.disable_jit``, for
  arrays on several devices, with unhashable static values, or without a
  cache folder it is the plain ``jax.jit`` (the same program). The stored
  program computes the same values; unlike ``jax.jit``'s, its results are
  committed to the device it ran on, and a program with weakly typed
  results is not stored. The stored name holds the function's module,
  name and code and the static values' ``repr``, not values the function
  closes over: give each program its own ``name``. Static arguments are
  bound by name (no ``*args`` or positional-only parameters with
  ``static_argnames``).
  """

  def __init__(self, fun: Callable, name: str,
               static_argnames: Sequence[str] = ()):
    self._fun = fun
    self._name = name
    self._static = tuple(static_argnames)
    self._jit = jax.jit(fun, static_argnames=self._static)
    self._by_static: dict = {}
    self._signature = inspect.signature(fun) if self._static else None
    self._identity = _code_identity(fun)
    functools.update_wrapper(self, fun)

  def __call__(self, *args, **kwargs):
    if self._signature is not None:  # static values, given by name or not
      bound = self._signature.bind(*args, **kwargs).arguments
      static = {k: bound.pop(k) for k in self._static if k in bound}
      args, kwargs = (), bound
    else:
      static = {}
    dynamic = (args, kwargs)
    try:  # static values are hashed, as jax.jit does
      statics = tuple(sorted(static.items()))
      hash(statics)
    except TypeError:
      statics = None
    if (statics is None or folder() is None or jax.config.jax_disable_jit
        or not _trace_state_clean()
        or not _single_device(jax.tree.leaves(dynamic))):
      return self._jit(*args, **kwargs, **static)
    jitted = self._by_static.get(statics)
    if jitted is None:
      fun = self._fun
      jitted = jax.jit(lambda args, kwargs: fun(*args, **kwargs, **static))
      with _LOCK:
        jitted = self._by_static.setdefault(statics, jitted)
    compiled = compile_stored(jitted, dynamic, name=self._name,
                              out_tree=None,
                              static_key=self._identity + repr(statics))
    return compiled(*dynamic)

  def clear_cache(self) -> None:
    """Forgets the compiled programs (this process's; the stored files
    stay)."""
    self._jit.clear_cache()
    with _LOCK:
      mine = set(map(id, self._by_static.values()))
      for memo in [m for m in _COMPILED if id(m[0]) in mine]:
        _COMPILED.pop(memo, None)
      self._by_static.clear()

  def __getattr__(self, name):  # lower, _cache_size...: the plain jit's
    if name == '_jit':
      raise AttributeError(name)
    return getattr(self._jit, name)


def _trace_state_clean() -> bool:
  """No transformation is tracing (then a call with concrete arguments is
  staged into the trace, as ``jax.jit``'s is, not run at once)."""
  try:
    from jax._src import core  # noqa: PLC0415
    return core.trace_state_clean()
  except (ImportError, AttributeError):  # another JAX: trust the tracers
    return True


def _code_identity(fun) -> str:
  """The function in the stored program's name: its module, qualified name
  and code (two functions of one name, or an edited function outside the
  package, are other programs; values it closes over are not seen)."""
  code = getattr(fun, '__code__', None)
  digest = ''
  if code is not None:
    h = hashlib.sha256()
    stack = [code]
    while stack:
      c = stack.pop()
      h.update(c.co_code)
      h.update(repr([k for k in c.co_consts if not hasattr(k, 'co_code')]
                    ).encode())
      h.update(repr(c.co_names).encode())
      stack += [k for k in c.co_consts if hasattr(k, 'co_code')]
    digest = h.hexdigest()[:16]
  return (f'{getattr(fun, "__module__", "")}.'
          f'{getattr(fun, "__qualname__", repr(fun))}:{digest}:')


def stored_jit(fun: Callable | None = None, *, name: str | None = None,
               static_argnames: Sequence[str] = ()):
  """:class:`StoredJit` of ``fun`` (a decorator without ``fun``); ``name``
  defaults to the function's."""
  if fun is None:
    return lambda f: stored_jit(f, name=name, static_argnames=static_argnames)
  return StoredJit(fun, name or getattr(fun, '__name__', 'program'),
                   static_argnames)
