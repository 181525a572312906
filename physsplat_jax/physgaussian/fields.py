"""Field checks shared by the PhysGaussian config parser.

``ConfigError`` and the helpers that check one JSON field (type, length,
physical range); each error names the config file, the field, the value
and the fix. :mod:`physsplat_jax.physgaussian.schema` re-exports them.
"""

from __future__ import annotations

import difflib
import math
from typing import Any

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.mpm.models import PARAM_RANGES
from physsplat_jax.values import is_number


class ConfigError(PhysSplatError, ValueError):
  """A config field has a bad value or type; the message names the fix."""


def _where(source: str, field: str) -> str:
  return f'{source}: field {field!r}'


def _type_error(source, field, value, expected):
  return ConfigError(
    f'{_where(source, field)} has value {value!r} of type '
    f'{type(value).__name__}; expected {expected}. Fix the value in the '
    'JSON file.'
  )


def _float(source, field, value):
  if not is_number(value):
    raise _type_error(source, field, value, 'a number')
  value = float(value)
  if not math.isfinite(value):
    raise _type_error(source, field, value, 'a finite number')
  return value


def _int(source, field, value):
  if isinstance(value, bool):
    raise _type_error(source, field, value, 'an integer')
  if isinstance(value, float) and value.is_integer():
    value = int(value)
  if not isinstance(value, int):
    raise _type_error(source, field, value, 'an integer')
  return value


def _vec(source, field, value, n=None):
  if not isinstance(value, (list, tuple)):
    want = f'a list of {n} numbers' if n else 'a list of numbers'
    raise _type_error(source, field, value, want)
  if n is not None and len(value) != n:
    raise ConfigError(
      f'{_where(source, field)} has {len(value)} entries {value!r}; '
      f'expected {n} numbers.'
    )
  return tuple(_float(source, f'{field}[{i}]', v) for i, v in enumerate(value))


def _bool(source, field, value):
  if isinstance(value, bool):
    return value
  if isinstance(value, int) and value in (0, 1):
    return bool(value)
  raise _type_error(source, field, value, 'true/false')


def _freeze(value):
  if isinstance(value, (list, tuple)):
    return tuple(_freeze(v) for v in value)
  if isinstance(value, dict):
    return tuple(sorted((k, _freeze(v)) for k, v in value.items()))
  return value


def _check_kind(source, field, value, kind):
  if kind == 'vec3':
    return _vec(source, field, value, 3)
  if kind == 'vec2':
    return _vec(source, field, value, 2)
  if kind == 'float':
    return _float(source, field, value)
  if kind == 'int':
    return _int(source, field, value)
  if kind == 'str':
    if not isinstance(value, str):
      raise _type_error(source, field, value, 'a string')
    return value
  return _freeze(value)


def check_range(source: str, field: str, value: float) -> None:
  """Raises ``ConfigError`` if ``value`` is outside the physical range of
  the model parameter ``field`` (``mpm.models.PARAM_RANGES``, the ranges
  perception's overrides are checked against too)."""
  ok, want = PARAM_RANGES[field]
  if not ok(value):
    raise ConfigError(f'{_where(source, field)} = {value:g}: use {want}.')


def check_keys(source: str, field: str, keys: Any, known: Any,
               what: str) -> None:
  """Raises ``ConfigError`` naming the first of ``keys`` not in ``known``.

  Args:
    source: config path.
    field: the object's field name, e.g. ``'boundary_conditions[1]'``.
    keys: the object's keys.
    known: the accepted keys.
    what: the object's kind, for the message (e.g. ``'particle_impulse'``).
  """
  for k in keys:
    if k in known:
      continue
    close = difflib.get_close_matches(str(k), sorted(known), n=1)
    hint = f' (did you mean {close[0]!r}?)' if close else ''
    raise ConfigError(
      f'{_where(source, field)} ({what}): unknown key {k!r}{hint}; '
      f'{what} takes {sorted(known)}. Fix the spelling or remove the key.'
    )
