"""Registry of the built-in scenes: ``list_scenes()`` and ``make_scene()``."""

from __future__ import annotations

import inspect
from typing import Callable

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
    raise ValueError(
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
