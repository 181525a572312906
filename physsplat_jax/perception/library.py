"""The material library: real-world property ranges and simulation presets.

The data live in ``physsplat_jax/data/materials.json`` (docs/materials.md
explains every column and lists the sources). Each entry has

* real-world ranges ``density`` [kg/m^3], ``youngs_modulus`` E [Pa] and
  ``poisson_ratio`` nu, with source ids;
* a simulation preset ``sim = {E, nu, rho}``: the values used at video-rate
  time steps. Real solids are GPa-stiff and would need dt ~ 1e-6 s, so the
  preset follows one documented compression law (``preset_rule`` in the
  file)::

    E_sim = clip(sqrt(E_mid * E_ref), 1e3, 1e7) Pa,  E_mid = sqrt(E_min E_max),
    E_ref = 1e5 Pa,  nu_sim = min(mean(nu), 0.45),
    rho_sim = sqrt(rho_min rho_max)

  which keeps the stiffness ORDER of the real materials (softer real ->
  softer simulated) while landing in the 1e4-1e7 Pa band where peers
  simulate. Rigid materials are flagged ``rigid``; their E_sim only matters
  for contacts.
* the constitutive model (``CANONICAL_MODELS``), model parameters in
  simulation units, a rigid flag, aliases and keywords for name matching.

Name lookup (:meth:`MaterialLibrary.match`): exact key, exact alias, then a
phrase/keyword score over the name's words (material words -- keys and
aliases -- weigh 3 per word, object and appearance keywords 1/df, df being
the number of entries sharing the keyword), then a fuzzy (typo) match.
So ``'metal can'`` -> aluminum (alias), ``'rubber ball'`` -> rubber,
``'jelly cube'`` -> jelly, ``'ficus leaves'`` -> leaf, ``'alumnium'`` ->
aluminum (fuzzy).

Everything here is pure except :func:`default_library`, which reads the
package's own data file once (package data, not user files).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import importlib.resources
import json
import math
import os
import re
from collections.abc import Mapping
from typing import Any

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.mpm.models import CANONICAL_MODELS

# Parameters each model needs (simulation units; see the file's 'units').
# Each is a field the solver's update reads for that model
# (mpm.models.MODEL_PARAMS): snow's hardening is ``xi`` and a Bingham
# fluid's viscosity ``viscosity`` (named otherwise they were ignored).
MODEL_PARAMS = {
  'fixed_corotated': (),
  'neo_hookean': (),
  'stvk': (),
  'rigid': (),
  'von_mises': ('yield_stress', 'hardening', 'xi'),
  'drucker_prager': ('friction_angle',),
  'snow': ('theta_c', 'theta_s', 'xi'),
  'foam': ('yield_stress', 'plastic_viscosity'),
  'plasticine': ('yield_stress', 'softening'),
  'newtonian': ('viscosity',),
  'bingham': ('yield_stress', 'viscosity'),
}
# Models whose yield stress is a yield strain times E_sim (so it scales
# with E_sim when perception rescales the preset).
STRAIN_YIELD_MODELS = ('von_mises', 'foam', 'plasticine')
# Models that can never be rigid bodies (granular media and fluids).
NEVER_RIGID_MODELS = ('drucker_prager', 'snow', 'newtonian', 'bingham')

_MATERIAL_WEIGHT = 3.0  # score per word of a matched key or alias
_FUZZY_CUTOFF = 0.8  # difflib ratio for a typo match

_IRREGULAR = {
  'leaves': 'leaf', 'knives': 'knife', 'loaves': 'loaf', 'shelves': 'shelf',
  'potatoes': 'potato', 'tomatoes': 'tomato', 'glasses': 'glass',
  'pebbles': 'pebble', 'tires': 'tire', 'tyres': 'tyre', 'dice': 'die',
}


class LibraryError(PhysSplatError, ValueError):
  """The library data file is malformed; the message names file and field."""


class MaterialNotFoundError(PhysSplatError, LookupError):
  """No library entry matches a name; the message lists close keys."""


@dataclasses.dataclass(frozen=True)
class Range:
  """A closed physical range ``[min, max]``."""

  min: float
  max: float

  @property
  def mid(self) -> float:
    """Arithmetic midpoint."""
    return 0.5 * (self.min + self.max)

  @property
  def geometric_mid(self) -> float:
    """``sqrt(min * max)`` (for quantities spanning decades, e.g. E)."""
    return math.sqrt(self.min * self.max)

  def contains(self, x: float, factor: float = 1.0) -> bool:
    """Whether ``min / factor <= x <= max * factor``."""
    return self.min / factor <= x <= self.max * factor


@dataclasses.dataclass(frozen=True)
class MaterialEntry:
  """One library material (all values are plain Python floats).

  Attributes:
    key: library key, e.g. ``'aluminum'``.
    category: e.g. ``'metal'``, ``'plant'``, ``'fluid'``.
    description: one line used for text similarity and prompts.
    aliases: material names and synonyms (matched as whole phrases).
    keywords: object and appearance words (weak evidence).
    density: real range [kg/m^3].
    youngs_modulus: real range [Pa] (fluids: ``3 K (1 - 2 nu)``).
    poisson_ratio: real range, within [0, 0.5).
    model: constitutive model (one of ``CANONICAL_MODELS``).
    rigid: simulated as a rigid body by default.
    params: model parameters in simulation units, sorted ``(name, value)``.
    E_sim, nu_sim, rho_sim: the simulation preset [Pa, 1, kg/m^3].
    yield_strain: yield_stress / E_sim for strain-yield models, else None.
    sources: ids into :attr:`MaterialLibrary.sources`.
    bulk_modulus: real bulk modulus range of fluids [Pa], else None.
    note: free text.
  """

  key: str
  category: str
  description: str
  aliases: tuple[str, ...]
  keywords: tuple[str, ...]
  density: Range
  youngs_modulus: Range
  poisson_ratio: Range
  model: str
  rigid: bool
  params: tuple[tuple[str, float], ...]
  E_sim: float
  nu_sim: float
  rho_sim: float
  yield_strain: float | None = None
  sources: tuple[str, ...] = ()
  bulk_modulus: Range | None = None
  note: str = ''

  @property
  def params_dict(self) -> dict[str, float]:
    return dict(self.params)

  @property
  def E_mid(self) -> float:
    """Geometric midpoint of the real E range [Pa]."""
    return self.youngs_modulus.geometric_mid

  @property
  def name(self) -> str:
    """The key with spaces, for prompts and logs."""
    return self.key.replace('_', ' ')


@dataclasses.dataclass(frozen=True)
class Match:
  """The result of a name lookup.

  Attributes:
    key: the library key.
    how: 'key', 'alias', 'phrase', 'keyword', 'fuzzy' or 'default'.
    term: the library term that matched (e.g. the alias).
    score: the phrase/keyword score (0 for exact and default matches).
  """

  key: str
  how: str
  term: str
  score: float = 0.0

  def describe(self, name: str) -> str:
    """A short human-readable account, e.g. for log lines."""
    if self.how == 'key':
      return f'name {name!r} is the library key'
    if self.how == 'default':
      return f'name {name!r} matched nothing; default {self.key!r}'
    return f'name {name!r} matched {self.how} {self.term!r}'


# ------------------------------------------------------------------- text


def normalize(text: str) -> str:
  """Lower-case words separated by single spaces (punctuation dropped)."""
  text = str(text).lower().replace("'", '')
  return ' '.join(re.sub(r'[^a-z0-9]+', ' ', text).split())


def singular(word: str) -> str:
  """A crude English singular, applied alike to names and library terms."""
  if word in _IRREGULAR:
    return _IRREGULAR[word]
  if len(word) > 4 and word.endswith('ies'):
    return word[:-3] + 'y'
  if len(word) > 4 and word.endswith(('sses', 'ches', 'shes', 'xes')):
    return word[:-2]
  if (len(word) > 3 and word.endswith('s')
      and not word.endswith(('ss', 'us', 'is'))):
    return word[:-1]
  return word


def tokens(text: str) -> tuple[str, ...]:
  """Normalised, singularised words of ``text``."""
  return tuple(singular(w) for w in normalize(text).split())


def _contains(hay: tuple[str, ...], needle: tuple[str, ...]) -> bool:
  n = len(needle)
  return n > 0 and any(hay[i:i + n] == needle
                       for i in range(len(hay) - n + 1))


# ---------------------------------------------------------------- library


@dataclasses.dataclass(frozen=True)
class MaterialLibrary:
  """An immutable set of :class:`MaterialEntry` with name matching.

  Attributes:
    entries: the materials, in file order (ties in matching go to the
      earlier entry).
    sources: source id -> full citation.
    rule: the file's ``preset_rule`` (constants of the preset law).
    origin: where the data came from (for messages).
  """

  entries: tuple[MaterialEntry, ...]
  sources: tuple[tuple[str, str], ...] = ()
  rule: tuple[tuple[str, Any], ...] = ()
  origin: str = '<dict>'

  # Access -----------------------------------------------------------------
  @functools.cached_property
  def _by_key(self) -> dict[str, MaterialEntry]:
    return {e.key: e for e in self.entries}

  @property
  def keys(self) -> tuple[str, ...]:
    return tuple(e.key for e in self.entries)

  def __len__(self) -> int:
    return len(self.entries)

  def __contains__(self, key: str) -> bool:
    return key in self._by_key

  def __getitem__(self, key: str) -> MaterialEntry:
    try:
      return self._by_key[key]
    except KeyError:
      raise MaterialNotFoundError(
        f'no material key {key!r} in the library ({self.origin}); close '
        f'keys: {self.suggest(key)}; all keys: {list(self.keys)}'
      ) from None

  def get(self, key: str, default=None):
    return self._by_key.get(key, default)

  @property
  def sources_dict(self) -> dict[str, str]:
    return dict(self.sources)

  @property
  def rule_dict(self) -> dict[str, Any]:
    return dict(self.rule)

  @property
  def E_sim_bounds(self) -> tuple[float, float]:
    """``(E_sim_min, E_sim_max)`` of the preset law [Pa]."""
    r = self.rule_dict
    return float(r.get('E_sim_min_pa', 1e3)), float(r.get('E_sim_max_pa', 1e7))

  @property
  def nu_sim_max(self) -> float:
    return float(self.rule_dict.get('nu_sim_max', 0.45))

  @property
  def E_reference(self) -> float:
    return float(self.rule_dict.get('E_reference_pa', 1e5))

  # Matching ---------------------------------------------------------------
  @functools.cached_property
  def _terms(self) -> list[tuple[tuple[str, ...], str, str, float, str]]:
    """(tokens, key, kind, weight per word, original term) for all terms."""
    df: dict[tuple[str, ...], int] = {}
    for e in self.entries:
      for kw in set(tokens(k) for k in e.keywords):
        df[kw] = df.get(kw, 0) + 1
    out = []
    for e in self.entries:
      out.append((tokens(e.key), e.key, 'key', _MATERIAL_WEIGHT, e.key))
      for a in e.aliases:
        out.append((tokens(a), e.key, 'alias', _MATERIAL_WEIGHT, a))
      for k in e.keywords:
        t = tokens(k)
        out.append((t, e.key, 'keyword', 1.0 / df[t], k))
    return out

  def mentioned(self, text: str) -> tuple[str, ...]:
    """Keys whose key or an alias appears as a phrase in ``text``.

    Strong evidence only (material words such as 'aluminium', 'rubber
    ball'); keywords ('can', 'shiny') are not counted. Used by the
    plausibility check of MLLM answers.
    """
    toks = tokens(text)
    out = []
    for t, k, kind, _, _ in self._terms:
      if kind in ('key', 'alias') and k not in out and _contains(toks, t):
        out.append(k)
    return tuple(out)

  def suggest(self, name: str, n: int = 5) -> list[str]:
    """Keys whose key/aliases are closest to ``name`` (for messages)."""
    words = {' '.join(t): key for t, key, kind, _, _ in self._terms
             if kind != 'keyword'}
    close = difflib.get_close_matches(' '.join(tokens(name)), list(words),
                                      n=3 * n, cutoff=0.5)
    out = []
    for c in close:
      if words[c] not in out:
        out.append(words[c])
    return out[:n]

  def match(self, name: str) -> Match | None:
    """Best library entry for a free-text object or material name.

    Args:
      name: e.g. ``'metal can'``, ``'Ficus leaves'``, ``'rubber_ball'``.

    Returns:
      A :class:`Match`, or None when nothing matches.
    """
    norm = normalize(name)
    if not norm:
      return None
    key = norm.replace(' ', '_')
    if key in self._by_key:
      return Match(key, 'key', key)
    toks = tokens(name)
    if '_'.join(toks) in self._by_key:
      return Match('_'.join(toks), 'key', '_'.join(toks))
    for t, k, kind, _, term in self._terms:
      if kind == 'alias' and t == toks:
        return Match(k, 'alias', term)
    # Phrase and keyword scores.
    score: dict[str, float] = {}
    best_term: dict[str, tuple[float, str, str]] = {}
    for t, k, kind, w, term in self._terms:
      if _contains(toks, t):
        s = w * len(t)
        score[k] = score.get(k, 0.0) + s
        how = 'phrase' if kind in ('key', 'alias') else 'keyword'
        if s > best_term.get(k, (-1.0, '', ''))[0]:
          best_term[k] = (s, term, how)
    if score:
      order = {e.key: i for i, e in enumerate(self.entries)}
      k = max(score, key=lambda c: (score[c], -order[c]))
      return Match(k, best_term[k][2], best_term[k][1], score[k])
    # Typos: each word against single-word keys/aliases, then the whole name.
    vocab = {}
    for t, k, kind, _, term in self._terms:
      if kind != 'keyword':
        vocab.setdefault(' '.join(t), (k, term))
    for cand in [' '.join(toks)] + list(toks):
      close = difflib.get_close_matches(cand, list(vocab), n=1,
                                        cutoff=_FUZZY_CUTOFF)
      if close:
        k, term = vocab[close[0]]
        return Match(k, 'fuzzy', term)
    return None

  def lookup(self, name: str, default: str | None = None) -> Match:
    """Like :meth:`match`, but never returns None.

    Args:
      name: a free-text name.
      default: key to use when nothing matches; None raises.

    Returns:
      A :class:`Match` (``how='default'`` when the default was used).

    Raises:
      MaterialNotFoundError: no match and no default (the message lists
        close keys and how to fix it).
    """
    m = self.match(name)
    if m is not None:
      return m
    if default is not None:
      self[default]  # validates the default key
      return Match(default, 'default', default)
    raise MaterialNotFoundError(
      f'no library material matches {name!r}; close keys: '
      f'{self.suggest(name)}. Give the object a library key (ObjectInfo.'
      f'material), an override (name=key), or add an alias to '
      f'{self.origin}. Keys: {list(self.keys)}'
    )

  # Text similarity --------------------------------------------------------
  @functools.cached_property
  def _corpus(self) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    """(idf per word, per-entry unit tf-idf vectors) over key, description,
    aliases and keywords."""
    raw = {}
    for e in self.entries:
      words = list(tokens(e.key)) + list(tokens(e.description))
      for a in e.aliases + e.keywords:
        words += list(tokens(a))
      raw[e.key] = words
    n = len(raw)
    df: dict[str, int] = {}
    for words in raw.values():
      for w in set(words):
        df[w] = df.get(w, 0) + 1
    idf = {w: math.log((1 + n) / (1 + c)) + 1.0 for w, c in df.items()}
    docs = {}
    for k, words in raw.items():
      vec: dict[str, float] = {}
      for w in words:
        vec[w] = vec.get(w, 0.0) + idf[w]
      norm = math.sqrt(sum(v * v for v in vec.values())) or 1.0
      docs[k] = {w: v / norm for w, v in vec.items()}
    return idf, docs

  def similarity(self, text: str) -> dict[str, float]:
    """Cosine similarity in [0, 1] between ``text`` and every entry.

    Bag-of-words tf-idf over each entry's key, description, aliases and
    keywords (the library is the corpus); words unknown to the library are
    ignored.
    """
    idf, docs = self._corpus
    vec: dict[str, float] = {}
    for w in tokens(text):
      if w in idf:
        vec[w] = vec.get(w, 0.0) + idf[w]
    norm = math.sqrt(sum(v * v for v in vec.values()))
    if norm == 0:
      return {k: 0.0 for k in docs}
    return {
      k: sum(v * d.get(w, 0.0) for w, v in vec.items()) / norm
      for k, d in docs.items()
    }


# ---------------------------------------------------------------- parsing


def _range(origin, key, field, raw) -> Range:
  where = f'{origin}: materials.{key}.{field}'
  if not isinstance(raw, Mapping) or set(raw) != {'min', 'max'}:
    raise LibraryError(f'{where} must be {{"min": x, "max": y}}, got {raw!r}')
  try:
    lo, hi = float(raw['min']), float(raw['max'])
  except (TypeError, ValueError):
    raise LibraryError(f'{where} has non-numeric bounds {raw!r}') from None
  if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
    raise LibraryError(f'{where} = [{lo}, {hi}] must be finite with min <= '
                       'max')
  return Range(lo, hi)


def _strings(origin, key, field, raw) -> tuple[str, ...]:
  if not isinstance(raw, (list, tuple)) or not all(
      isinstance(s, str) for s in raw):
    raise LibraryError(f'{origin}: materials.{key}.{field} must be a list of '
                       f'strings, got {raw!r}')
  return tuple(raw)


def parse_entry(key: str, raw: Mapping, origin: str = '<dict>',
                known_sources=None) -> MaterialEntry:
  """Validates and converts one JSON entry (see docs/materials.md).

  Raises:
    LibraryError: naming the file, key and field.
  """
  where = f'{origin}: materials.{key}'
  if not isinstance(raw, Mapping):
    raise LibraryError(f'{where} must be an object, got {type(raw).__name__}')
  if not re.fullmatch(r'[a-z][a-z0-9_]*', key):
    raise LibraryError(f'{where}: keys are lower_snake_case, got {key!r}')
  required = ('description', 'density', 'youngs_modulus', 'poisson_ratio',
              'model', 'rigid', 'sim', 'sources')
  missing = [f for f in required if f not in raw]
  if missing:
    raise LibraryError(f'{where} lacks field(s) {missing}')
  model = raw['model']
  if model not in CANONICAL_MODELS:
    raise LibraryError(f'{where}.model = {model!r} is not one of '
                       f'{list(CANONICAL_MODELS)}')
  if not isinstance(raw['rigid'], bool):
    raise LibraryError(f'{where}.rigid must be true or false')
  params = raw.get('params', {})
  if not isinstance(params, Mapping):
    raise LibraryError(f'{where}.params must be an object')
  need = [p for p in MODEL_PARAMS[model] if p not in params]
  if need:
    raise LibraryError(f'{where}.params lacks {need} required by model '
                       f'{model!r}')
  try:
    params = tuple(sorted((str(k), float(v)) for k, v in params.items()))
  except (TypeError, ValueError):
    raise LibraryError(f'{where}.params has non-numeric values') from None
  sim = raw['sim']
  if not isinstance(sim, Mapping) or set(sim) != {'E', 'nu', 'rho'}:
    raise LibraryError(f'{where}.sim must be {{"E", "nu", "rho"}}, got '
                       f'{sim!r}')
  sources = _strings(origin, key, 'sources', raw['sources'])
  if not sources:
    raise LibraryError(f'{where}.sources is empty; cite at least one source')
  if known_sources is not None:
    unknown = [s for s in sources if s not in known_sources]
    if unknown:
      raise LibraryError(f'{where}.sources {unknown} are not in the file\'s '
                         '"sources" table')
  nu = _range(origin, key, 'poisson_ratio', raw['poisson_ratio'])
  if not (0.0 <= nu.min and nu.max < 0.5):
    raise LibraryError(f'{where}.poisson_ratio [{nu.min}, {nu.max}] must lie '
                       'in [0, 0.5)')
  E = _range(origin, key, 'youngs_modulus', raw['youngs_modulus'])
  rho = _range(origin, key, 'density', raw['density'])
  if E.min <= 0 or rho.min <= 0:
    raise LibraryError(f'{where}: youngs_modulus and density must be > 0')
  E_sim, nu_sim, rho_sim = (float(sim['E']), float(sim['nu']),
                            float(sim['rho']))
  if not (E_sim > 0 and rho_sim > 0 and 0.0 <= nu_sim < 0.5):
    raise LibraryError(f'{where}.sim = {dict(sim)} must have E > 0, rho > 0, '
                       '0 <= nu < 0.5')
  ys = raw.get('yield_strain')
  bulk = raw.get('bulk_modulus')
  return MaterialEntry(
    key=key,
    category=str(raw.get('category', '')),
    description=str(raw['description']),
    aliases=_strings(origin, key, 'aliases', raw.get('aliases', [])),
    keywords=_strings(origin, key, 'keywords', raw.get('keywords', [])),
    density=rho,
    youngs_modulus=E,
    poisson_ratio=nu,
    model=model,
    rigid=raw['rigid'],
    params=params,
    E_sim=E_sim,
    nu_sim=nu_sim,
    rho_sim=rho_sim,
    yield_strain=None if ys is None else float(ys),
    sources=sources,
    bulk_modulus=None if bulk is None else _range(origin, key,
                                                  'bulk_modulus', bulk),
    note=str(raw.get('note', '')),
  )


def parse_library(data: Mapping, origin: str = '<dict>') -> MaterialLibrary:
  """Builds a :class:`MaterialLibrary` from the decoded JSON document.

  Args:
    data: ``{"materials": {key: entry}, "sources": {...},
      "preset_rule": {...}}``.
    origin: file name or label for error messages.

  Raises:
    LibraryError: on any schema problem (naming the field), duplicate
      aliases across entries, or an empty library.
  """
  if not isinstance(data, Mapping) or not isinstance(
      data.get('materials'), Mapping):
    raise LibraryError(f'{origin}: expected an object with a "materials" '
                       'object')
  sources = data.get('sources', {})
  if not isinstance(sources, Mapping):
    raise LibraryError(f'{origin}: "sources" must map ids to citations')
  entries = tuple(
    parse_entry(k, v, origin, known_sources=sources if sources else None)
    for k, v in data['materials'].items()
  )
  if not entries:
    raise LibraryError(f'{origin}: the library has no materials')
  seen: dict[tuple[str, ...], str] = {}
  for e in entries:
    for term in (e.key,) + e.aliases:
      t = tokens(term)
      if t in seen and seen[t] != e.key:
        raise LibraryError(
          f'{origin}: {term!r} of materials.{e.key} is already a key or '
          f'alias of materials.{seen[t]}; names must be unambiguous'
        )
      seen[t] = e.key
  rule = data.get('preset_rule', {})
  return MaterialLibrary(
    entries=entries,
    sources=tuple((str(k), str(v)) for k, v in sources.items()),
    rule=tuple(sorted((str(k), v) for k, v in rule.items())),
    origin=origin,
  )


def load_library(path: str | os.PathLike) -> MaterialLibrary:
  """Reads a library JSON file (same schema as the shipped one).

  Raises:
    LibraryError: unreadable file, bad JSON or bad schema (names the file).
  """
  path = os.fspath(path)
  try:
    with open(path, encoding='utf-8') as f:
      data = json.load(f)
  except OSError as e:
    raise LibraryError(f'{path}: cannot read the material library: {e}'
                       ) from None
  except json.JSONDecodeError as e:
    raise LibraryError(f'{path}: invalid JSON at line {e.lineno} column '
                       f'{e.colno}: {e.msg}') from None
  return parse_library(data, origin=path)


@functools.lru_cache(maxsize=1)
def default_library() -> MaterialLibrary:
  """The library shipped in ``physsplat_jax/data/materials.json`` (cached)."""
  res = importlib.resources.files('physsplat_jax') / 'data' / 'materials.json'
  data = json.loads(res.read_text(encoding='utf-8'))
  return parse_library(data, origin='physsplat_jax/data/materials.json')
