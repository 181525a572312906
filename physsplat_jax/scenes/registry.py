"""Built-in scenes: ``list_scenes()``, ``make_scene()``, and ``load_scene()``
(a built-in name or a scene file).

A built-in scene is built from meshes (trimesh) in 0.2-0.3 s on the 2-core
VM, with 0.1 s more to import trimesh. With a compilation cache folder
(``jax_compilation_cache_dir``, on by default in the experiment scripts)
``make_scene`` stores the scene it built there (``physsplat_scenes/``, named
by the scene, its options, the package's source and the shipped scene
files) and a later process reads it back in milliseconds: the same arrays.
"""

from __future__ import annotations

import difflib
import functools
import hashlib
import importlib
import importlib.metadata
import inspect
import os
import pickle
from typing import Callable

from absl import logging
import jax
import numpy as np

from physsplat_jax import program_store
from physsplat_jax.io import scene as scene_io
from physsplat_jax.types import Scene
from physsplat_jax.types import device_array

DEFAULT_SCENE = 'tabletop'

# name -> (module, builder): imported when a scene is first built (the
# builders import trimesh).
_BUILDERS: dict[str, tuple[str, str]] = {
  'donut': ('physsplat_jax.scenes.donut', 'make_donut'),
  'ficus': ('physsplat_jax.scenes.ficus', 'make_ficus'),
  'tabletop': ('physsplat_jax.scenes.tabletop', 'make_tabletop'),
}
FOLDER = 'physsplat_scenes'


def list_scenes() -> tuple[str, ...]:
  """Names of the built-in scenes, sorted."""
  return tuple(sorted(_BUILDERS))


def scene_options(name: str) -> tuple[str, ...]:
  """The keyword options a built-in scene accepts."""
  return tuple(inspect.signature(_builder(name)).parameters)


def _builder(name: str) -> Callable[..., Scene]:
  if not isinstance(name, str) or name not in _BUILDERS:
    raise scene_io.SceneFileError(
      f'unknown built-in scene {name!r}; built-in scenes: '
      f'{", ".join(list_scenes())}'
    )
  module, fn = _BUILDERS[name]
  return getattr(importlib.import_module(module), fn)


def make_scene(name: str = DEFAULT_SCENE, **options) -> Scene:
  """Builds a built-in scene.

  Args:
    name: one of :func:`list_scenes` (``'donut'``, ``'ficus'``,
      ``'tabletop'``).
    **options: the builder's keywords; all accept ``seed`` (int or JAX PRNG
      key), ``detail`` (Gaussian density, spacings scale as ``1 / detail``),
      ``num_cameras``, ``width``, ``height`` and ``fov_deg``.

  With a compilation cache folder (``jax_compilation_cache_dir``) the scene
  is stored there once built and read back by later calls, in any process
  (the module's docstring); options that cannot name a file (Gaussians
  passed in) build it every time.

  Returns:
    The :class:`~physsplat_jax.types.Scene`.

  Raises:
    ValueError: unknown name (the message lists the built-in scenes) or a
      bad option value.
    TypeError: an option the scene does not take (the message lists them).
  """
  if not isinstance(name, str) or name not in _BUILDERS:
    _builder(name)  # the error that lists the scenes
  path = _stored_path(name, options)
  if path is not None and os.path.exists(path):
    scene = _read(path)
    if scene is not None:
      return scene
  fn = _builder(name)
  allowed = scene_options(name)
  bad = sorted(set(options) - set(allowed))
  if bad:
    raise TypeError(
      f'make_scene({name!r}): unknown option(s) {bad}; this scene takes '
      f'{", ".join(allowed)}'
    )
  scene = fn(**options)
  if path is not None:
    _write(path, scene)
  return scene


def _option_key(value):
  """A stable text for an option value, or None (not storable: e.g. a
  scene's own Gaussians passed in)."""
  if value is None or isinstance(value, (bool, int, float, str)):
    return repr(value)
  if isinstance(value, (tuple, list)):
    parts = [_option_key(v) for v in value]
    return None if None in parts else f'({",".join(parts)})'
  if isinstance(value, (jax.Array, np.ndarray)):  # a PRNG key as seed
    if jax.dtypes.issubdtype(value.dtype, jax.dtypes.prng_key):
      value = jax.random.key_data(value)
    a = np.asarray(value)
    if a.size > 16:
      return None
    return f'{a.dtype}{a.shape}{a.tolist()}'
  return None


@functools.lru_cache(maxsize=1)
def _data_digest() -> str:
  """The shipped scene files (their contents, 3 ms) and the libraries the
  builders use: a new file or version names new stored scenes (read once
  per process, as the package's source digest is)."""
  here = os.path.join(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__))), 'data', 'scenes')
  h = hashlib.sha256()
  if os.path.isdir(here):
    for f in sorted(os.listdir(here)):
      h.update(f.encode() + b'\0')
      with open(os.path.join(here, f), 'rb') as fh:
        h.update(fh.read())
  for lib in ('trimesh', 'scipy', 'numpy'):
    try:
      h.update(f'{lib}={importlib.metadata.version(lib)}'.encode())
    except importlib.metadata.PackageNotFoundError:
      pass
  return h.hexdigest()


def _stored_path(name: str, options: dict) -> str | None:
  """Where the built scene is stored, or None (no cache folder, or an
  option that cannot name it)."""
  base = program_store.folder()
  if not base:
    return None
  keys = {k: _option_key(v) for k, v in sorted(options.items())}
  if None in keys.values():
    return None
  h = hashlib.sha256('\0'.join(
    [name, *(f'{k}={v}' for k, v in keys.items()),
     program_store.source_digest(), _data_digest(),
     str(jax.config.jax_enable_x64)]).encode())
  return os.path.join(base, FOLDER, f'{name}_{h.hexdigest()[:40]}.pkl')


def _write(path: str, scene: Scene) -> None:
  """Stores the scene (NumPy leaves); a failure only costs the next
  process a build."""
  try:
    host = jax.tree.map(
      lambda a: np.asarray(a) if isinstance(a, jax.Array) else a, scene)
    blob = pickle.dumps(host, protocol=pickle.HIGHEST_PROTOCOL)
  except Exception as e:  # noqa: BLE001 - the scene is built each time
    logging.info('scene store: %s not stored (%s: %s)', path,
                 type(e).__name__, e)
    return
  program_store.write_file(path, blob)


def _read(path: str) -> Scene | None:
  """The stored scene with its arrays on the default device, or None."""
  try:
    host = pickle.loads(program_store.read_file(path))
    if not isinstance(host, Scene):
      raise TypeError(f'not a Scene: {type(host).__name__}')
  except Exception as e:  # noqa: BLE001 - unreadable: build it again
    logging.warning('scene store: cannot read %s (%s: %s); building the '
                    'scene again.', path, type(e).__name__, e)
    return None
  return jax.tree.map(
    lambda a: device_array(a) if isinstance(a, np.ndarray) else a, host)


def load_scene(name_or_path, **options) -> Scene:
  """Loads a built-in scene by name, or a 3DGS file or folder.

  Args:
    name_or_path: a built-in name (:func:`list_scenes`: ``'tabletop'``,
      ``'ficus'``, ``'donut'``), a ``.ply`` / ``.splat`` / ``.spz`` path, or
      a 3DGS output folder.
    **options: for a built-in scene, the options of :func:`make_scene`; for
      a file, those of :func:`physsplat_jax.io.scene.load_scene`.

  Returns:
    A :class:`~physsplat_jax.types.Scene`.

  Raises:
    SceneFileError: neither a built-in name nor an existing path (the
      message lists the built-in scenes and the closest name), or a bad
      file.
  """
  if isinstance(name_or_path, str) and name_or_path in list_scenes():
    return make_scene(name_or_path, **options)
  if isinstance(name_or_path, (str, os.PathLike)) and not os.path.exists(
      name_or_path):
    close = difflib.get_close_matches(str(name_or_path), list_scenes(), n=1)
    hint = f' (did you mean {close[0]!r}?)' if close else ''
    raise scene_io.SceneFileError(
      f'scene {os.fspath(name_or_path)!r} is neither a built-in scene '
      f'({", ".join(list_scenes())}){hint} nor an existing .ply/.splat/.spz '
      'file or 3DGS output folder.')
  return scene_io.load_scene(name_or_path, **options)
