"""Built-in scenes: ``list_scenes()``, ``make_scene()``, and ``load_scene()``
(a built-in name or a scene file)."""

from __future__ import annotations

import difflib
import inspect
import os
from typing import Callable

from physsplat_jax.io import scene as scene_io
from physsplat_jax.scenes.donut import make_donut
from physsplat_jax.scenes.ficus import make_ficus
from physsplat_jax.scenes.tabletop import make_tabletop
from physsplat_jax.types import Scene

DEFAULT_SCENE = 'tabletop'

_BUILDERS: dict[str, Callable[..., Scene]] = {
  'donut': make_donut,
  'ficus': make_ficus,
  'tabletop': make_tabletop,
}


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
  return _BUILDERS[name]


def make_scene(name: str = DEFAULT_SCENE, **options) -> Scene:
  """Builds a built-in scene.

  Args:
    name: one of :func:`list_scenes` (``'donut'``, ``'ficus'``,
      ``'tabletop'``).
    **options: the builder's keywords; all accept ``seed`` (int or JAX PRNG
      key), ``detail`` (Gaussian density, spacings scale as ``1 / detail``),
      ``num_cameras``, ``width``, ``height`` and ``fov_deg``.

  Returns:
    The :class:`~physsplat_jax.types.Scene`.

  Raises:
    ValueError: unknown name (the message lists the built-in scenes) or a
      bad option value.
    TypeError: an option the scene does not take (the message lists them).
  """
  fn = _builder(name)
  allowed = scene_options(name)
  bad = sorted(set(options) - set(allowed))
  if bad:
    raise TypeError(
      f'make_scene({name!r}): unknown option(s) {bad}; this scene takes '
      f'{", ".join(allowed)}'
    )
  return fn(**options)


def load_scene(name_or_path, **options) -> Scene:
  """Loads a built-in scene by name, or a 3DGS file or folder.

  Args:
    name_or_path: a built-in name (:func:`list_scenes`: ``'tabletop'``,
      ``'ficus'``, ``'donut'``), a ``.ply`` / ``.splat`` path, or a 3DGS
      output folder.
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
      f'({", ".join(list_scenes())}){hint} nor an existing .ply/.splat file '
      'or 3DGS output folder.')
  return scene_io.load_scene(name_or_path, **options)
