"""Parsing and validation of MLLM answers (pure functions).

Every parser either returns clean values plus a list of notes saying what it
repaired, or raises :class:`AnswerError` with a message that says what was
wrong. Nothing here trusts the model:

* JSON: code fences and prose around the object are stripped; a
  brace-balanced ``{...}`` is searched; Python-style literals (single quotes,
  True/False) are accepted as a last resort.
* Candidates: names are mapped to library keys (key, alias, phrase, fuzzy;
  see :meth:`MaterialLibrary.match`); unknown names are dropped with a note.
* Scores: clipped to [0, 1]; a 0-10 or 0-100 scale is detected and rescaled.
* Properties (:func:`validate_properties`): numbers are read from JSON
  numbers or from strings (``'70 GPa'``, ``'7.0 × 10^10 Pa'``, ``'7e10'``,
  ``'~2.7 g/cm³'``, ``'−70 GPa'`` with a Unicode minus, a decimal comma
  where it cannot be a thousands separator: ``'0,05 GPa'``; a range
  ``'5-10 GPa'``, ``'1.5-2.5 × 10^6 Pa'``, ``'1 MPa - 5 MPa'`` give their
  midpoint, as do ``'between 1 and 5 MPa'`` and ``'~1e6 - ~1e7 Pa'``; a
  tolerance ``'5 ± 1 MPa'`` is dropped); units from the
  string, from ``*_unit`` fields or from key suffixes
  (``youngs_modulus_gpa``). A string that does not read as one such
  quantity, or an unknown unit, makes the field unreadable (library
  value, with a note quoting the text): no number is ever taken from
  inside a unit or from a ``*_unit`` field. Then each
  value is checked against physics and against the chosen library entry:

  - E must be finite and > 0; it is accepted within a factor ``E_slack``
    (10) of the entry's real range. Otherwise a unit slip is assumed if a
    factor 1e±3, 1e±6, 1e±9 brings it into that band (``E = 70`` "Pa" for
    aluminium is 70 GPa; of several such factors, the one nearest the
    entry's geometric mid); failing that, the library's mid value is used.
  - nu must be finite and in [0, 0.5); values further than ``nu_slack``
    (0.1) from the entry's range are clipped into that band.
  - rho must be finite and > 0, accepted within a factor ``rho_slack`` (3)
    of the entry's range, repaired by a factor 1e±3 (g/cm^3 vs kg/m^3), else
    the library's mid value.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import math
import re
from collections.abc import Mapping

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.perception.checks import PerceptionError
from physsplat_jax.perception.library import MaterialEntry
from physsplat_jax.perception.library import MaterialLibrary

# Keys in the form of _unit_key (lower case; no spaces, ^, *, dots).
_PRESSURE_UNITS = {
  'pa': 1.0, 'pascal': 1.0, 'pascals': 1.0, 'n/m2': 1.0, 'nm-2': 1.0,
  'si': 1.0, 'kpa': 1e3, 'kilopascal': 1e3, 'kilopascals': 1e3,
  'mpa': 1e6, 'megapascal': 1e6, 'megapascals': 1e6, 'gpa': 1e9,
  'gigapascal': 1e9, 'gigapascals': 1e9, 'tpa': 1e12, 'n/mm2': 1e6,
  'nmm-2': 1e6, 'psi': 6894.757, 'ksi': 6.894757e6,
}
_DENSITY_UNITS = {
  'kg/m3': 1.0, 'kgm-3': 1.0, 'kgm3': 1.0, 'kg_m3': 1.0, 'si': 1.0,
  'kg/m-3': 1.0, 'g/cm-3': 1e3,  # (a common slip for kg/m^3, g/cm^3)
  'g/cm3': 1e3, 'gcm-3': 1e3, 'g_cm3': 1e3, 'g/cc': 1e3, 'g/ml': 1e3,
  'kg/l': 1e3, 'kg/dm3': 1e3, 'g/l': 1.0, 'lb/ft3': 16.0185,
}
_E_FIELDS = ('youngs_modulus', 'young_modulus', 'youngs_modulus_pa', 'e',
             'elastic_modulus', 'modulus', 'young', 'youngs')
_NU_FIELDS = ('poisson_ratio', 'poissons_ratio', 'nu', 'poisson')
_RHO_FIELDS = ('density', 'density_kg_m3', 'density_kg_per_m3', 'rho')
_UNIT_REPAIRS = (1e9, 1e6, 1e3, 1e-3, 1e-6, 1e-9)
# Minus signs and dashes read as '-'; superscripts as digits.
_DASHES = str.maketrans({c: '-' for c in '\u2212\u2012\u2013\u2014\ufe63'
                         '\uff0d'})
_SUPERSCRIPTS = str.maketrans('⁰¹²³⁴⁵⁶⁷⁸⁹⁻⁺', '0123456789-+')
# One number: 7, 2,700.5, 0,05, 7.0e10, 7.0 × 10^10, 7*10**10, 10^10.
_POWER = r'10\s*(?:\^|\*\*)\s*'
_NUMBER = re.compile(
  rf'(?P<sign>[-+]?)\s*(?:{_POWER}(?P<p0>[-+]?\d+)'
  r'|(?P<man>\d(?:[\d_]|,(?=\d))*(?:\.\d*)?|\.\d+)'
  rf'(?:e(?P<e>[-+]?\d+)|\s*[x×*·]\s*{_POWER}(?P<p>[-+]?\d+))?)', re.I)
_APPROX = re.compile(r'(?:~|≈|approx(?:imately|\.)?|about|around|roughly|'
                     r'circa|ca\.)\s*', re.I)
# A range's separator, and any '~' / 'about' before its second bound.
_RANGE = re.compile(r'\s*(?:-|to\b|and\b)\s*(?:' + _APPROX.pattern + ')?',
                    re.I)
_BETWEEN = re.compile(r'(?:between|from)\s+', re.I)
_TOLERANCE = re.compile(r'\s*(?:±|\+/-|\+-)\s*')


class AnswerError(PhysSplatError, ValueError):
  """An MLLM answer is unusable; the message says why (with an excerpt)."""


def _excerpt(text: str, n: int = 160) -> str:
  t = ' '.join(str(text).split())
  return repr(t if len(t) <= n else t[:n] + '...')


# -------------------------------------------------------------------- JSON


def _balanced_objects(text: str):
  """The brace-balanced ``{...}`` substrings (string-aware), in order; each
  search starts after the previous object (a non-JSON ``{name}`` in prose
  does not hide the object after it)."""
  start = text.find('{')
  while start >= 0:
    depth, quote, esc, end = 0, None, False, None
    for i in range(start, len(text)):
      ch = text[i]
      if quote:
        if esc:
          esc = False
        elif ch == '\\':
          esc = True
        elif ch == quote:
          quote = None
        continue
      if ch in ('"', "'"):
        quote = ch
      elif ch == '{':
        depth += 1
      elif ch == '}':
        depth -= 1
        if depth == 0:
          end = i + 1
          break
    if end is None:
      start = text.find('{', start + 1)
    else:
      yield text[start:end]
      start = text.find('{', end)


def _loads(cand: str):
  """JSON, else a Python literal; None when neither parses."""
  try:
    return json.loads(cand)
  except json.JSONDecodeError:
    try:
      return ast.literal_eval(cand)
    except (ValueError, SyntaxError, MemoryError, RecursionError):
      return None


def extract_json(text: str) -> dict:
  """The JSON object in an answer: the first code fence, or the text, or a
  brace-balanced object in it, that parses.

  Raises:
    AnswerError: no parseable object (the message quotes the answer).
  """
  if not isinstance(text, str) or not text.strip():
    raise AnswerError('empty answer where JSON was expected')
  t = text.strip()
  fences = [f.strip() for f in re.findall(r'```(?:json|JSON)?\s*(.*?)```', t,
                                         re.S)]
  for src in fences + [t]:
    for cand in (src, *_balanced_objects(src)):
      obj = _loads(cand)
      if obj is None:
        continue
      if isinstance(obj, dict):
        return obj
      raise AnswerError(f'expected a JSON object, got {type(obj).__name__}: '
                        f'{_excerpt(text)}')
  raise AnswerError(f'malformed JSON: {_excerpt(text)}')


# -------------------------------------------------------------- candidates


def _as_bool(v) -> bool | None:
  if isinstance(v, bool):
    return v
  if isinstance(v, (int, float)) and v in (0, 1):
    return bool(v)
  if isinstance(v, str):
    s = ' '.join(v.strip().lower().rstrip('.!').split())
    if s in ('true', 'yes', 'rigid', '1'):
      return True
    if s in ('false', 'no', 'deformable', 'soft', '0', 'not rigid',
             'non-rigid', 'nonrigid'):
      return False
  return None


@dataclasses.dataclass(frozen=True)
class Candidates:
  """Parsed answer (2).

  Attributes:
    keys: library keys, most likely first, unique.
    names: the model's names for them (same order).
    rigid: the model's rigid flag, or None if missing/unreadable.
    notes: what was repaired or dropped.
  """

  keys: tuple[str, ...]
  names: tuple[str, ...]
  rigid: bool | None
  notes: tuple[str, ...] = ()


def parse_candidates(text: str, library: MaterialLibrary,
                     num_candidates: int) -> Candidates:
  """Parses ``{"candidates": [...], "rigid": bool}``.

  Raises:
    AnswerError: malformed JSON, no candidate list, or no candidate that
      maps to a library material.
  """
  obj = extract_json(text)
  raw = obj.get('candidates', obj.get('materials'))
  if not isinstance(raw, list) or not raw:
    raise AnswerError(f'no "candidates" list in {_excerpt(text)}')
  notes = []
  keys, names = [], []
  for item in raw:
    name = item.get('material', item.get('name')) if isinstance(
      item, dict) else item
    if not isinstance(name, str) or not name.strip():
      notes.append(f'ignored candidate {item!r}')
      continue
    m = library.match(name)
    if m is None:
      notes.append(f'candidate {name!r} matches no library material')
      continue
    if m.key not in keys:
      keys.append(m.key)
      names.append(name)
  if not keys:
    raise AnswerError(
      'none of the candidates maps to a library material: '
      f'{_excerpt(text)}')
  keys, names = keys[:num_candidates], names[:num_candidates]
  rigid = _as_bool(obj.get('rigid'))
  if rigid is None:
    notes.append(f'rigid flag missing or unreadable ({obj.get("rigid")!r})')
  return Candidates(tuple(keys), tuple(names), rigid, tuple(notes))


# ------------------------------------------------------------------ scores


def parse_scores(text: str, library: MaterialLibrary,
                 candidate_keys) -> tuple[dict[str, float], list[str]]:
  """Parses ``{"scores": {name: s}}`` (or a list of {material, score}).

  Returns:
    (scores for the candidate keys that were rated, notes).

  Raises:
    AnswerError: malformed JSON or no usable score.
  """
  obj = extract_json(text)
  raw = obj.get('scores', obj)
  pairs = []
  if isinstance(raw, Mapping):
    pairs = list(raw.items())
  elif isinstance(raw, list):
    pairs = [(d.get('material', d.get('name')), d.get('score'))
             for d in raw if isinstance(d, dict)]
  notes = []
  vals = {}
  for name, s in pairs:
    if not isinstance(name, str):
      continue
    try:
      v = float(s)
    except (TypeError, ValueError):
      notes.append(f'score {s!r} for {name!r} is not a number')
      continue
    if not math.isfinite(v):
      notes.append(f'score {s!r} for {name!r} is not finite')
      continue
    m = library.match(name)
    if m is None or m.key not in candidate_keys:
      continue
    vals[m.key] = max(vals.get(m.key, -math.inf), v)
  if not vals:
    raise AnswerError(f'no usable candidate scores in {_excerpt(text)}')
  top = max(vals.values())
  if top > 1.0:
    scale = 10.0 if top <= 10.0 else 100.0
    notes.append(f'scores rescaled from a 0-{scale:g} scale')
    vals = {k: v / scale for k, v in vals.items()}
  out = {k: min(max(v, 0.0), 1.0) for k, v in vals.items()}
  return out, notes


# -------------------------------------------------------------- properties


def _field(obj: Mapping, names) -> tuple[str, str, object] | None:
  """(key, the field name it matched, value); ``*_unit`` keys are units,
  never values."""
  low = {str(k).lower(): k for k in obj
         if not str(k).lower().endswith(('_unit', '_units'))}
  for n in names:
    if n in low:
      return low[n], n, obj[low[n]]
  # Key with a unit suffix, e.g. youngs_modulus_gpa, density_g_cm3.
  for k_low, k in low.items():
    for n in names:
      if k_low.startswith(n + '_'):
        return k, n, obj[k]
  return None


def _unit_key(unit: str) -> str:
  u = str(unit).translate(_SUPERSCRIPTS).translate(_DASHES).lower()
  return re.sub(r'[\s^*·⋅.]', '', u)


def _unit_factor(unit: str, table: Mapping[str, float]) -> float | None:
  return table.get(_unit_key(unit))


def _plain(m: re.Match) -> float | None:
  """The value of a :data:`_NUMBER` match (None: an ambiguous comma)."""
  if m.group('p0') is not None:
    x = float(f'1e{m.group("p0")}')
  else:
    man = m.group('man').replace('_', '')
    if ',' in man:
      if re.fullmatch(r'[1-9]\d{0,2}(?:,\d{3})+(?:\.\d*)?', man):
        man = man.replace(',', '')  # thousands: 2,700 or 1,500.5
      elif re.fullmatch(r'\d+,\d+', man):
        man = man.replace(',', '.')  # decimal comma: 0,05 or 2,7
      else:
        return None
    exp = m.group('e') or m.group('p')
    x = float(f'{man}e{exp}' if exp is not None else man)
  return -x if m.group('sign') == '-' else x


def _has_exponent(m: re.Match) -> bool:
  return any(m.group(g) is not None for g in ('p0', 'e', 'p'))


def _exponent(m: re.Match) -> str:
  """The power of ten of a :data:`_NUMBER` match, as text ('0' if none)."""
  return m.group('p0') or m.group('e') or m.group('p') or '0'


def _quantity(text: str, table: Mapping[str, float] | None = None
              ) -> tuple[float, str, str] | str:
  """``(value, unit text, note)`` of a string such as ``'~7.0 × 10^10
  Pa'`` or ``'5-10 GPa'`` (midpoint), or why it does not read as one.

  A range's bounds share a power of ten written once (``'1.5-2.5 × 10^6'``
  is 1.5e6 to 2.5e6) and may each carry a unit (``'1 MPa - 5 MPa'``,
  ``'500 kPa to 5 MPa'``: with ``table``, unit -> SI factor, the second
  bound is converted to the first's unit). A tolerance (``'5 ± 1 MPa'``)
  is dropped; a fraction (``'1/3'``) is divided out.
  """
  t = re.sub(r'10([⁰¹²³⁴⁵⁶⁷⁸⁹⁻⁺]+)',
             lambda m: '10^' + m.group(1).translate(_SUPERSCRIPTS), text)
  t = t.translate(_SUPERSCRIPTS).translate(_DASHES).strip()
  start = 0
  for prefix in (_BETWEEN, _APPROX):  # 'between ~1 and 5 MPa'
    p = prefix.match(t, start)
    start = p.end() if p else start
  m = _NUMBER.match(t, start)
  if not m:
    return 'is not a number'
  x, note = _plain(m), ''
  if x is None:
    return 'has an ambiguous comma (write 0.05 or 2700)'
  rest = t[m.end():]
  frac = re.match(r'\s*/\s*', rest)
  m_den = _NUMBER.match(rest, frac.end()) if frac else None
  if m_den and not m_den.group('sign') and _plain(m_den):  # nu '1/3'
    x, rest = x / _plain(m_den), rest[m_den.end():]
  tol = _TOLERANCE.match(rest)
  if tol:
    m_tol = _NUMBER.match(rest, tol.end())
    if m_tol and not m_tol.group('sign'):
      note, rest = 'a value with a tolerance; the value used', rest[
        m_tol.end():]
  r = _RANGE.match(rest)
  m2 = _NUMBER.match(rest, r.end()) if r else None
  if m2 and not m2.group('sign'):
    y = _plain(m2)
    if y is None:
      return 'has an ambiguous comma (write 0.05 or 2700)'
    shared = 10.0 ** float(_exponent(m2))
    if not _has_exponent(m) and _has_exponent(m2) and x * shared <= y:
      x *= shared  # '1.5-2.5 x 10^6': one power for both ('500-1e6': not)
    x, note, rest = 0.5 * (x + y), 'a range; its midpoint used', rest[
      m2.end():]
  elif table:
    # '1 MPa - 5 MPa', '1e6 Pa to 1e7 Pa': a unit after each bound (the
    # second bound was dropped, so '1e6 Pa to 1e7 Pa' read as 1e6 Pa).
    for sep in _RANGE.finditer(rest):
      u1 = rest[:sep.start()].strip()
      f1 = _unit_factor(u1, table) if u1 else None
      m3 = _NUMBER.match(rest, sep.end())
      if f1 is None or not m3 or m3.group('sign'):
        continue
      tail = re.sub(r'\(.*?\)|\[.*?\]', ' ', rest[m3.end():]).strip(
        ' \t\n.,;:')
      u2 = re.split(r'[\s,;]+', tail)[0] if tail else ''
      f2 = _unit_factor(tail, table) or (
        _unit_factor(u2, table) if u2 else None)
      y = _plain(m3)
      if f2 is None or y is None:
        continue
      x = 0.5 * (x + y * f2 / f1)
      note, rest = 'a range; its midpoint used', u1
      break
  if re.match(r'\s*[.,]?\d', rest):  # '10^10.8', '1.2.3'
    return 'is not one number'
  rest = re.sub(r'\(.*?\)|\[.*?\]', ' ', rest).strip(' \t\n.,;:')
  return x, rest, note


def _number_with_unit(key: str, base: str, value, obj: Mapping,
                      table) -> tuple[float | None, str]:
  """(value in SI or None, note) from a number or a string with units.

  Args:
    key: the answer's key; base: the field name it matched.
    value: the answer's value (a number, a string, or {value, unit}).
    obj: the whole answer (``*_unit`` fields).
    table: unit -> SI factor; empty for a dimensionless field.
  """
  unit, notes = None, []
  if isinstance(value, Mapping) and 'value' in value:
    unit = value.get('unit', value.get('units'))
    unit = unit if isinstance(unit, str) and unit.strip() else None
    value = value['value']
  if isinstance(value, bool):
    return None, f'{key}={value!r} is not a number'
  if isinstance(value, (int, float)):
    x = float(value)
  elif isinstance(value, str):
    q = _quantity(value, table)
    if isinstance(q, str):
      return None, f'{key}={value!r} {q}; unreadable'
    x, rest, note = q
    if note:
      notes.append(f'{key}={value!r} is {note}')
    if rest and table:
      unit = rest
      if _unit_factor(rest, table) is None:  # '70 GPa, typical'
        first = re.split(r'[\s,;]+', rest)[0]
        unit = first if _unit_factor(first, table) is not None else rest
  else:
    return None, f'{key}={value!r} is not a number'
  low = {str(k).lower(): v for k, v in obj.items()}
  if unit is None:
    for uk in (f'{key.lower()}_unit', f'{key.lower()}_units', f'{base}_unit',
               f'{base}_units', 'unit', 'units'):
      if isinstance(low.get(uk), str) and low[uk].strip():
        unit = low[uk]
        break
  if unit is None:
    for suffix in table:
      if key.lower().endswith('_' + suffix.replace('/', '_')):
        unit = suffix
        break
  if unit is not None and table:
    f = _unit_factor(unit, table)
    if f is None:
      known = 'Pa, kPa, MPa, GPa' if 'gpa' in table else 'kg/m3, g/cm3'
      return None, (f'{key}={value!r}: unknown unit {unit!r} (use '
                    f'{known}); unreadable')
    if f != 1.0:
      x *= f
      notes.append(f'{key} given in {unit}')
  return x, '; '.join(notes)


@dataclasses.dataclass(frozen=True)
class Properties:
  """Validated real-world properties of one object's material.

  Attributes:
    E: Young's modulus [Pa].
    nu: Poisson's ratio in [0, 0.5).
    rho: density [kg/m^3].
    from_library: names of the fields that fell back to the library.
    notes: what was repaired or replaced, in words.
  """

  E: float
  nu: float
  rho: float
  from_library: tuple[str, ...] = ()
  notes: tuple[str, ...] = ()


def library_properties(entry: MaterialEntry) -> Properties:
  """The entry's real mid values (E, rho: geometric mid; nu: arithmetic)."""
  return Properties(E=entry.E_mid, nu=entry.poisson_ratio.mid,
                    rho=entry.density.geometric_mid,
                    from_library=('E', 'nu', 'rho'))


def _repair(x: float, ok, mid: float,
            factors=_UNIT_REPAIRS) -> float | None:
  """The unit-repair factor that makes ``ok(x * f)`` true, or None; when
  several do (a wide band: 10 for foam is 10 kPa or 10 MPa), the one that
  lands nearest ``mid`` in ratio (``x > 0``)."""
  fits = [f for f in factors if ok(x * f)]
  if not fits:
    return None
  return min(fits, key=lambda f: abs(math.log(x * f / mid)))


def validate_properties(text: str, entry: MaterialEntry,
                        E_slack: float = 10.0, rho_slack: float = 3.0,
                        nu_slack: float = 0.1) -> Properties:
  """Parses and validates answer (4) against physics and the entry.

  Args:
    text: the model's answer.
    entry: the chosen library material (plausibility bands, fallbacks).
    E_slack, rho_slack: accepted factor outside the entry's real range.
    nu_slack: accepted distance outside the entry's nu range.

  Returns:
    :class:`Properties`; invalid fields are replaced by library values and
    named in ``from_library`` and ``notes``.

  Raises:
    AnswerError: the answer has no JSON object at all.
    PerceptionError: a slack below 1 (``nu_slack`` below 0).
  """
  for arg, v in (('E_slack', E_slack), ('rho_slack', rho_slack),
                 ('nu_slack', nu_slack + 1.0)):
    if not v >= 1:  # NaN too (E_slack=0 divided by zero)
      raise PerceptionError(
        f'validate_properties: {arg}={v!r} must be a factor >= 1 '
        '(nu_slack: >= 0); see PerceptionOptions')
  obj = extract_json(text)
  lib = library_properties(entry)
  notes, from_lib = [], []
  name = entry.key

  # Young's modulus.
  E = None
  f = _field(obj, _E_FIELDS)
  if f is None:
    notes.append('E missing')
  else:
    E, note = _number_with_unit(str(f[0]), f[1], f[2], obj,
                                _PRESSURE_UNITS)
    if note:
      notes.append(note)
    if E is None:
      pass
    elif not math.isfinite(E) or E <= 0:
      notes.append(f'E={E:g} Pa is not positive and finite')
      E = None
    elif not entry.youngs_modulus.contains(E, E_slack):
      r = entry.youngs_modulus
      ok = lambda v: r.contains(v, E_slack)
      fac = _repair(E, ok, r.geometric_mid)
      if fac is not None:
        notes.append(
          f'E={E:g} Pa is implausible for {name} [{r.min:.2g}, {r.max:.2g}] '
          f'Pa; read as {E * fac:.3g} Pa (unit slip x{fac:g})')
        E *= fac
      else:
        notes.append(f'E={E:g} Pa is outside the plausible range of {name} '
                     f'[{r.min:.2g}, {r.max:.2g}] Pa (x{E_slack:g})')
        E = None
  if E is None:
    E = lib.E
    from_lib.append('E')

  # Poisson's ratio.
  nu = None
  f = _field(obj, _NU_FIELDS)
  if f is None:
    notes.append('nu missing')
  else:
    nu, note = _number_with_unit(str(f[0]), f[1], f[2], obj, {})
    if note:
      notes.append(note)
    if nu is not None and not (math.isfinite(nu) and 0.0 <= nu < 0.5):
      notes.append(f'nu={nu:g} is outside [0, 0.5)')
      nu = None
    elif nu is not None:
      lo = max(entry.poisson_ratio.min - nu_slack, 0.0)
      hi = min(entry.poisson_ratio.max + nu_slack, 0.499)
      if not lo <= nu <= hi:
        clipped = min(max(nu, lo), hi)
        notes.append(f'nu={nu:g} is far from {name} '
                     f'[{entry.poisson_ratio.min:g}, '
                     f'{entry.poisson_ratio.max:g}]; clipped to {clipped:g}')
        nu = clipped
  if nu is None:
    nu = lib.nu
    from_lib.append('nu')

  # Density.
  rho = None
  f = _field(obj, _RHO_FIELDS)
  if f is None:
    notes.append('density missing')
  else:
    rho, note = _number_with_unit(str(f[0]), f[1], f[2], obj,
                                  _DENSITY_UNITS)
    if note:
      notes.append(note)
    if rho is None:
      pass
    elif not math.isfinite(rho) or rho <= 0:
      notes.append(f'density={rho:g} is not positive and finite')
      rho = None
    elif not entry.density.contains(rho, rho_slack):
      r = entry.density
      fac = _repair(rho, lambda v: r.contains(v, rho_slack),
                    r.geometric_mid, (1e3, 1e-3))
      if fac is not None:
        notes.append(f'density={rho:g} kg/m^3 is implausible for {name}; '
                     f'read as {rho * fac:.4g} kg/m^3 (unit slip x{fac:g})')
        rho *= fac
      else:
        notes.append(f'density={rho:g} kg/m^3 is outside the plausible '
                     f'range of {name} [{r.min:g}, {r.max:g}] (x'
                     f'{rho_slack:g})')
        rho = None
  if rho is None:
    rho = lib.rho
    from_lib.append('rho')
  return Properties(E=float(E), nu=float(nu), rho=float(rho),
                    from_library=tuple(from_lib), notes=tuple(notes))
