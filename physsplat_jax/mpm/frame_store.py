"""The frame program kept between processes, so that a run traces it once.

JAX's persistent compilation cache keys a compiled program by its lowered
module, so every process traces and lowers the frame before it can find
it there: for the tabletop at paper scale (64³, 768 substeps) 1.1-1.7 s of
Python on the 2-core VM, most of a warm run's compile stage on a GPU. The
first process to lower a frame now also stores it with ``jax.export``
(StableHLO, serialised), named by everything its lowering depends on; a
later process reads it back and lowers only a call to it (milliseconds),
then finds the compiled program in the compilation cache as before.

The stored program is the same module: it computes the same bits (a test
compares them). Nothing is stored, and the frame is traced as before,
without a compilation cache folder, without ``flatbuffers`` (``jax.export``'s
serialisation), for arguments spread over several devices, or when the
export fails; a stored file that cannot be read is traced and stored again,
and one that does not compile is compiled from a new trace, with a warning.
Deviceless, for an H100 (jax 0.10.2): the tabletop's stored frame compiles
to the same 20 kernels per substep, its Pallas stress kernel included.
"""

from __future__ import annotations

import functools
import hashlib
import os
import tempfile

from absl import logging
import jax

FOLDER = 'physsplat_frames'
# Pallas (Triton) kernels: JAX does not promise that a stored kernel loads
# in another JAX version; the name holds JAX's and jaxlib's versions, so a
# stored frame is only read back by the JAX that wrote it.
_TRITON = '__gpu$xla.gpu.triton'


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
  """The package's source (every module): any change to the code names
  new files."""
  h = hashlib.sha256()
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  for folder, dirs, files in os.walk(root):
    dirs.sort()
    for name in sorted(files):
      if name.endswith('.py'):
        path = os.path.join(folder, name)
        h.update(os.path.relpath(path, root).encode() + b'\0')
        with open(path, 'rb') as f:
          h.update(f.read())
  return h.hexdigest()


def _folder() -> str | None:
  """The persistent compilation cache's folder (None: off)."""
  return jax.config.jax_compilation_cache_dir or None


def _path(config, tree, leaves) -> str | None:
  """Where the frame for these is stored, or None (no compilation cache)."""
  folder = _folder()
  if not folder:
    return None
  import jaxlib  # noqa: PLC0415

  device = next(iter(leaves[0].devices())) if leaves and hasattr(
    leaves[0], 'devices') else jax.devices()[0]
  parts = [
    jax.__version__, jaxlib.__version__, device.platform,
    getattr(device, 'device_kind', ''), repr(config), str(tree),
    repr([(tuple(a.shape), str(a.dtype), bool(getattr(a, 'weak_type', 0)))
          for a in leaves]),
    str(jax.config.jax_enable_x64),
    str(jax.config.jax_default_matmul_precision), _source_digest()]
  h = hashlib.sha256('\0'.join(parts).encode())
  return os.path.join(folder, FOLDER, f'frame_{h.hexdigest()[:40]}.jaxexport')


def _single_device(leaves) -> bool:
  devices = set()
  for a in leaves:
    if not isinstance(a, jax.Array):
      return False
    devices |= set(a.sharding.device_set)
  return len(devices) <= 1


def compile_frame(frame_jit, state, materials, forces, config, compile_fn):
  """The frame compiled by ``compile_fn(lowered)``, from its stored form
  when there is one (see :func:`lower`), called as ``frame_jit`` is. A
  stored frame that fails to compile is compiled from a new trace instead,
  with a warning (it should not happen: the stored module is the one the
  trace gives)."""
  lowered, wrap = lower(frame_jit, state, materials, forces, config)
  if wrap is _same:
    return compile_fn(lowered)
  try:
    return wrap(compile_fn(lowered))
  except Exception as e:  # noqa: BLE001 - the traced frame instead
    logging.warning('frame store: the stored frame did not compile (%s: %s); '
                    'compiling it from a new trace.', type(e).__name__, e)
    return compile_fn(frame_jit.lower(state, materials, forces))


def _same(compiled):
  return compiled


def lower(frame_jit, state, materials, forces, config):
  """The frame lowered for these arguments, and how to call it compiled.

  Args:
    frame_jit: the jitted frame function ``(state, materials, forces) ->
      state``.
    state, materials, forces: its arguments (shapes and dtypes matter).
    config: the static ``SimConfig`` it was made from (part of the name).

  Returns:
    ``(lowered, wrap)``: ``wrap(lowered.compile())`` (or any compile of
    ``lowered``) is called as ``frame_jit`` is.
  """
  args = (state, materials, forces)
  leaves, tree = jax.tree.flatten(args)
  state_leaves, state_tree = jax.tree.flatten(state)
  path = _path(config, tree, leaves) if _single_device(leaves) else None
  if path is None:
    return frame_jit.lower(*args), _same
  try:
    from jax import export  # noqa: PLC0415
    from jax._src.export import serialization  # noqa: F401,PLC0415  (flatbuffers)
  except ImportError as e:
    logging.log_first_n(logging.INFO, 'frame store off: %s', 1, e)
    return frame_jit.lower(*args), _same

  def wrap(compiled):
    def call(state, materials, forces):
      out = compiled(*jax.tree.leaves((state, materials, forces)))
      return jax.tree.unflatten(state_tree, out)
    return call

  exported = None
  if os.path.exists(path):
    try:
      with open(path, 'rb') as f:
        exported = export.deserialize(bytearray(f.read()))
    except Exception as e:  # noqa: BLE001 - unreadable: trace it again
      logging.warning('frame store: cannot read %s (%s: %s); tracing the '
                      'frame again.', path, type(e).__name__, e)
      exported = None
  if exported is None:
    exported = _export(export, frame_jit, tree, args, state_leaves, path)
    if exported is None:
      return frame_jit.lower(*args), _same
  return jax.jit(exported.call).lower(*leaves), wrap


def _export(export, frame_jit, tree, args, state_leaves, path):
  """Exports and stores the frame (None when it cannot be: then the caller
  lowers it as before)."""

  def flat(*leaves):  # the frame on flat leaves: no pytree types stored
    return tuple(jax.tree.leaves(frame_jit(*jax.tree.unflatten(tree,
                                                                leaves))))

  try:
    exported = export.export(
      jax.jit(flat), disabled_checks=[
        export.DisabledSafetyCheck.custom_call(_TRITON)])(
          *jax.tree.leaves(args))
    same = [(a.shape, a.dtype) for a in exported.out_avals] == [
      (tuple(a.shape), a.dtype) for a in state_leaves]
    if not same:  # not a state -> state map: keep the usual path
      return None
    blob = exported.serialize()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), suffix='.tmp')
    with os.fdopen(fd, 'wb') as f:
      f.write(blob)
    os.replace(tmp, path)
  except Exception as e:  # noqa: BLE001 - any failure: the usual path
    logging.info('frame store: not stored (%s: %s)', type(e).__name__, e)
    return None
  return exported
