"""absl flags for perception in experiment scripts (defined on request only).

``define_flags()`` defines the ``--mllm_*`` flags of
:func:`physsplat_jax.io.mllm.define_flags` plus:

* ``--material_override`` (repeatable): ``'name=key'`` or
  ``'name={"material": "rubber", "E": 3e5}'``; several pairs may be joined
  with ``;`` (``'ball=rubber;can=aluminum'``; a JSON value ends its item).
  Values are simulation values; each object may be given once.
* ``--default_material``: library key for names that match nothing
  (empty: error instead).
* ``--perception_candidates``, ``--perception_image_size``,
  ``--perception_views``, ``--perception_selection``.

``options_from_flags()`` turns them into :class:`PerceptionOptions`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

from physsplat_jax.io import mllm
from physsplat_jax.perception.choice import MaterialChoiceError
from physsplat_jax.perception.p3 import SELECTION_METHODS
from physsplat_jax.perception.p3 import PerceptionOptions


def parse_overrides(items: Sequence[str] | str | None) -> dict[str, Any]:
  """Parses ``name=value`` strings into an overrides dict.

  Args:
    items: strings like ``'ball=rubber'``, ``'a=wood;b=sand'`` or
      ``'cube={"material": "jelly", "E": 2e4}'``.

  Returns:
    name -> library key/name or dict of values.

  Raises:
    MaterialChoiceError: a malformed item (the message quotes it and shows
      the form), a pair after a JSON value in the same item, or an object
      given twice.
  """
  if items is None:
    return {}
  if isinstance(items, str):
    items = [items]
  out: dict[str, Any] = {}
  for item in items:
    for name, value, part in _override_parts(item):
      if name in out:
        raise MaterialChoiceError(
          f'material override {part!r}: object {name!r} is already given '
          f'({name}={_show(out[name])}); give each object once')
      out[name] = value
  return out


def _show(value) -> str:
  return json.dumps(value) if isinstance(value, Mapping) else str(value)


def _override_parts(item: str):
  """Yields ``(name, value, text)`` of one --material_override string."""
  rest = item
  while rest.strip():
    if '=' not in rest.split(';', 1)[0]:
      part = rest.split(';', 1)[0]
      if not part.strip():
        rest = rest.split(';', 1)[1] if ';' in rest else ''
        continue
      raise MaterialChoiceError(
        f'material override {part!r}: expected name=key or '
        'name={"material": ..., "E": ...}')
    name, rest = rest.split('=', 1)
    name, rest = name.strip(), rest.lstrip()
    if rest.startswith('{'):
      try:
        value, end = json.JSONDecoder().raw_decode(rest)
      except json.JSONDecodeError as e:
        raise MaterialChoiceError(
          f'material override {item!r}: invalid JSON for {name!r} ({e})'
        ) from None
      part, after = f'{name}={rest[:end]}', rest[end:].strip()
      if after and not after.startswith(';'):
        raise MaterialChoiceError(
          f'material override {item!r}: unexpected {after!r} after the '
          f'JSON of {name!r}')
      if after.strip('; '):
        raise MaterialChoiceError(
          f'material override {item!r}: after a JSON value, pass '
          f'{after.lstrip("; ")!r} as a separate --material_override '
          '(";" joins name=key pairs only)')
      rest = ''
    else:
      value, _, rest = rest.partition(';')
      value = value.strip()
      part = f'{name}={value}'
    if not name or (isinstance(value, str) and not value):
      raise MaterialChoiceError(
        f'material override {part!r}: empty name or value')
    yield name, value, part


def define_flags(flag_values=None) -> None:
  """Defines the MLLM and perception flags (idempotent)."""
  from absl import flags

  fv = flags.FLAGS if flag_values is None else flag_values
  mllm.define_flags(fv)
  d = PerceptionOptions()
  specs = [
    (flags.DEFINE_multi_string, 'material_override', [],
     'Object material: name=key, name={"material": k, "E": ..}, or several '
     'joined with ";". Beats the MLLM and the library.'),
    (flags.DEFINE_string, 'default_material', d.default_material,
     'Library key for object names that match nothing (empty: error).'),
    (flags.DEFINE_integer, 'perception_candidates', d.num_candidates,
     'Candidate materials asked of the MLLM (K).'),
    (flags.DEFINE_integer, 'perception_image_size', d.image_size,
     'Side of the rendered object view sent to the MLLM [pixels].'),
    (flags.DEFINE_integer, 'perception_views', d.num_views,
     'Views of each object sent with every MLLM question (around it).'),
  ]
  for define, name, default, help_ in specs:
    if name not in fv:
      define(name, default, help_, flag_values=fv)
  if 'perception_selection' not in fv:
    flags.DEFINE_enum('perception_selection', d.selection,
                      list(SELECTION_METHODS),
                      'How to pick among candidates: MLLM score + text + '
                      'rank, text + rank, or the first.', flag_values=fv)


def options_from_flags(flag_values=None,
                       config_materials: Mapping[str, Any] | None = None
                       ) -> PerceptionOptions:
  """:class:`PerceptionOptions` from the flags of :func:`define_flags`."""
  from absl import flags

  fv = flags.FLAGS if flag_values is None else flag_values
  return PerceptionOptions(
    mllm=mllm.config_from_flags(fv),
    overrides=parse_overrides(fv.material_override),
    config_materials=dict(config_materials or {}),
    default_material=fv.default_material or None,
    num_candidates=int(fv.perception_candidates),
    image_size=int(fv.perception_image_size),
    num_views=int(fv.perception_views),
    selection=fv.perception_selection,
  ).validate()
