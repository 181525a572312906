"""MLLM-P3 perception of a scene's objects, with an offline default.

For every object of a :class:`~physsplat_jax.types.Scene` the material is
chosen by the first path that applies (one absl log line per object says
which, and why):

1. ``override``: ``options.overrides[object name]`` (a library key or name,
   or a mapping of simulation values; see :func:`choice.apply_spec`).
2. ``config``: ``options.config_materials[object name]`` (or its ``'*'``
   entry), e.g. from a PhysGaussian config.
3. ``mllm`` (when an endpoint is configured): PhysSplat's MLLM-P3 on
   ``num_views`` rendered views of the object alone (around it, every
   ``360 / num_views`` degrees of azimuth), all sent together with each
   question (OpenAI multi-image content):

   (1) caption the object; (2) ask for K candidate materials and whether it
   is rigid (JSON); (3) pick the best candidate (MLLM visual score + caption
   text similarity + rank; :mod:`physsplat_jax.perception.selection`);
   (4) ask for density, E and nu of the chosen material given the image and
   caption (JSON). Every answer is validated
   (:mod:`physsplat_jax.perception.parsing`); a malformed JSON answer is
   asked again once (``json_retries``). The real-world values are mapped to
   the simulation preset (:func:`choice.simulation_values`).

   The picked material must be plausible (:func:`plausibility`): when the
   object's name states a material ('metal can', 'rubber ball'), the pick
   must be of the same library category; when it does not, the same holds
   for the materials the caption names (the MLLM's account of the
   object's appearance). The property answers must lie in the picked
   material's library ranges (widened by the ``*_slack`` factors). An
   implausible pick sends the object to path 4 with a one-line warning
   saying why ("'jelly' (food) contradicts the name 'metal can', which
   says aluminum (metal)").

   Any failure falls back to the library with a warning: a failed caption
   or candidate step (network error, timeout, deadline, unusable answer)
   sends the whole object to path 4; a failed score step drops the visual
   score; a failed or out-of-range property answer uses library values for
   the fields concerned. Each question has a total deadline
   (``mllm.request_deadline_s``) and the scene one
   (``mllm.scene_deadline_s``): objects reached after it use the library.

   Caching: every question's cache key is computed from what needs no
   render: a hash of the object's Gaussians, its name, the view settings,
   ``prompts.PROMPT_VERSION``, the prompt text, the model and its settings.
   The views are rendered on the first cache miss only, so a fully cached
   run renders nothing. An answer that turns out unusable (empty, no JSON,
   cut at ``max_tokens``) is deleted from the cache (the next run asks
   again) and the message says so; options and ``images`` are checked
   before any question (:mod:`physsplat_jax.perception.checks`).
4. ``library`` (offline default): the scene's ``ObjectInfo.material`` key
   if set, else the object's name matched against the library (key, alias,
   phrase, keyword, fuzzy), else ``options.default_material`` with a
   warning (or an error when that is None).

Only rendering (``render_image``) and the injected client touch anything
outside plain Python; the client is :class:`physsplat_jax.io.mllm.MLLMClient`
unless one is passed in.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import jax.numpy as jnp
import numpy as np
from absl import logging

from physsplat_jax.io.mllm import MLLMConfig
from physsplat_jax.io.mllm import MLLMError
from physsplat_jax.io.mllm import encode_png
from physsplat_jax.perception import checks
from physsplat_jax.perception import choice as choice_lib
from physsplat_jax.perception import parsing
from physsplat_jax.perception import prompts
from physsplat_jax.perception.checks import PerceptionError
from physsplat_jax.perception.choice import MaterialChoice
from physsplat_jax.perception.library import MaterialEntry
from physsplat_jax.perception.library import MaterialLibrary
from physsplat_jax.perception.library import MaterialNotFoundError
from physsplat_jax.perception.library import default_library
from physsplat_jax.perception.selection import DEFAULT_WEIGHTS
from physsplat_jax.perception.selection import select_candidate
from physsplat_jax.types import Gaussians
from physsplat_jax.types import ObjectInfo
from physsplat_jax.types import Scene
from physsplat_jax.types import concatenate_gaussians
from physsplat_jax.values import is_int

SELECTION_METHODS = ('score', 'text', 'first')


class ChatClient(Protocol):
  """What perception needs from a client (``MLLMClient`` has it)."""

  def complete(self, prompt: str,
               images: Sequence[bytes] | Callable[[], Sequence[bytes]] = (),
               system: str | None = None, *, cache_id: str | None = None,
               deadline: float | None = None) -> Any:
    """Returns an object with a ``text`` attribute (``images`` may be a
    callable that renders them, called only when a request is made)."""


@dataclasses.dataclass(frozen=True)
class PerceptionOptions:
  """Settings of :func:`perceive_scene`.

  Attributes:
    mllm: endpoint settings; disabled (no ``base_url``) means offline.
    overrides: object name -> library key/name or mapping of simulation
      values (``{'material': 'rubber', 'E': 3e5}``); beats everything.
    config_materials: object name (or ``'*'`` for all) -> same, from a
      scene config; beats the MLLM and the library.
    default_material: library key used when an object's name matches
      nothing (with a warning); None raises instead.
    num_candidates: K, candidate materials asked for.
    image_size: side of each rendered view [pixels].
    num_views: views per object, ``360 / num_views`` degrees apart in
      azimuth, sent together with every question.
    azimuth_deg, elevation_deg: viewing direction of the first view.
    background: RGB background of the view.
    name_hint: tell the MLLM the object's scene name in the caption prompt.
    selection: 'score' (visual score + text + rank), 'text' (text + rank,
      no score request) or 'first' (the MLLM's first candidate).
    score_weights: ``(visual, text, rank)`` weights of 'score'.
    json_retries: re-asks after an answer without usable JSON.
    max_E_ratio: largest honoured factor between the MLLM's E and the
      library's mid value (see :mod:`physsplat_jax.perception.choice`).
    E_slack, rho_slack, nu_slack: plausibility bands of the validation.
    scene_material_first: use ``ObjectInfo.material`` (when set) even when
      an MLLM is configured.
  """

  mllm: MLLMConfig = MLLMConfig()
  overrides: Mapping[str, Any] = dataclasses.field(default_factory=dict)
  config_materials: Mapping[str, Any] = dataclasses.field(
    default_factory=dict)
  default_material: str | None = 'jelly'
  num_candidates: int = 5
  image_size: int = 224
  num_views: int = 4
  azimuth_deg: float = 30.0
  elevation_deg: float = 20.0
  background: tuple[float, float, float] = (1.0, 1.0, 1.0)
  name_hint: bool = True
  selection: str = 'score'
  score_weights: tuple[float, float, float] = DEFAULT_WEIGHTS
  json_retries: int = 1
  max_E_ratio: float = 100.0
  E_slack: float = 10.0
  rho_slack: float = 3.0
  nu_slack: float = 0.1
  scene_material_first: bool = False

  def validate(self) -> PerceptionOptions:
    """Returns ``self``; raises :class:`PerceptionError` naming a bad field
    and its allowed range (``mllm``: :class:`MLLMError`)."""
    if self.selection not in SELECTION_METHODS:
      raise PerceptionError(
        f'PerceptionOptions.selection={self.selection!r} is not one of '
        f'{SELECTION_METHODS}')
    # (field, lowest, highest or None): integers.
    for f, lo, hi in (('num_candidates', 1, None), ('num_views', 1, 8),
                      ('image_size', 8, None), ('json_retries', 0, 10)):
      v = getattr(self, f)
      if not (is_int(v) and lo <= v and (hi is None or v <= hi)):
        checks.bad_option(f, v, f'an integer in {lo}..{hi}'
                          if hi is not None else f'an integer >= {lo}')
    # (field, test, allowed): numbers; inf is "no limit" for the factors.
    for f, ok, want in (
        ('max_E_ratio', lambda x: x >= 1, 'a factor >= 1'),
        ('E_slack', lambda x: x >= 1, 'a factor >= 1'),
        ('rho_slack', lambda x: x >= 1, 'a factor >= 1'),
        ('nu_slack', lambda x: 0 <= x <= 0.5, 'a number in [0, 0.5]'),
        ('azimuth_deg', math.isfinite, 'a finite angle [deg]'),
        ('elevation_deg', math.isfinite, 'a finite angle [deg]')):
      v = getattr(self, f)
      if checks.number(v) is None or not ok(v):
        checks.bad_option(f, v, want)
    w = checks.numbers(self.score_weights, 3)
    if w is None or min(w) < 0 or not math.isfinite(sum(w)) or sum(w) <= 0:
      checks.bad_option('score_weights', self.score_weights,
                        '(visual, text, rank): three finite numbers >= 0, '
                        f'not all zero (default {DEFAULT_WEIGHTS})')
    b = checks.numbers(self.background, 3)
    if b is None or not all(0.0 <= x <= 1.0 for x in b):
      checks.bad_option('background', self.background,
                        'an RGB triple with values in [0, 1]')
    for f in ('overrides', 'config_materials'):
      if not isinstance(getattr(self, f), Mapping):
        checks.bad_option(f, getattr(self, f),
                          'a mapping object name -> spec')
    if not isinstance(self.default_material, (str, type(None))):
      checks.bad_option('default_material', self.default_material,
                        'a library key or None')
    self.mllm.validate()
    return self


# --------------------------------------------------------------- rendering


def _pad_pow2(g: Gaussians) -> Gaussians:
  """Pads with invisible Gaussians to a power of two (fewer recompiles)."""
  g = g.replace(normals=None, extras={})
  k = g.num
  n = 1 << max(int(k - 1).bit_length(), 6)
  if n == k:
    return g
  p = n - k
  dt = g.means.dtype
  pad = Gaussians(
    means=jnp.broadcast_to(jnp.mean(g.means, axis=0), (p, 3)).astype(dt),
    log_scales=jnp.full((p, 3), -12.0, dt),
    quats=jnp.tile(jnp.asarray([[1.0, 0.0, 0.0, 0.0]], dt), (p, 1)),
    opacity_logits=jnp.full((p,), -40.0, dt),
    sh=jnp.zeros((p,) + g.sh.shape[1:], dt),
  )
  return concatenate_gaussians([g, pad])


def render_object_view(
  scene: Scene,
  index: int,
  size: int = 224,
  azimuth_deg: float = 30.0,
  elevation_deg: float = 20.0,
  background=(1.0, 1.0, 1.0),
) -> np.ndarray:
  """Renders one object alone from a camera fitted to it.

  The camera (:func:`physsplat_jax.cameras.fit_camera`) frames the 0.5-99.5
  percentile box of the object's centres (robust to floaters), with the
  scene's up axis. The object's Gaussians are padded with invisible ones to
  a power of two (at least 64) so objects of similar size share one
  compiled renderer.

  Args:
    scene: the scene.
    index: object index into ``scene.objects``.
    size: image side [pixels].
    azimuth_deg, elevation_deg: viewing direction.
    background: RGB.

  Returns:
    (size, size, 3) float32 image in [0, 1].

  Raises:
    PerceptionError: the object has no Gaussians.
  """
  from physsplat_jax.cameras import fit_camera
  from physsplat_jax.render import render_image

  mask = np.asarray(scene.object_ids) == index
  if not mask.any():
    raise PerceptionError(f'object {index} ({scene.objects[index].name!r}) '
                          'has no Gaussians to render')
  g = scene.gaussians.subset(mask)
  means = np.asarray(g.means, np.float64)
  lo = np.percentile(means, 0.5, axis=0)
  hi = np.percentile(means, 99.5, axis=0)
  pad = 0.05 * max(float(np.linalg.norm(hi - lo)), 1e-6)
  # Fixed near/far (static camera fields): one compile serves all objects
  # of a padded size; the camera is outside the object's bounding sphere.
  cam = fit_camera(lo - pad, hi + pad, up=scene.up_vector, width=size,
                   height=size, azimuth=azimuth_deg,
                   elevation=elevation_deg, near=1e-3, far=1e10)
  out = render_image(_pad_pow2(g), cam, background=tuple(background))
  return np.clip(np.asarray(out.image, np.float32), 0.0, 1.0)


def view_azimuths(options: PerceptionOptions) -> tuple[float, ...]:
  """Azimuths [deg] of the object views (evenly around it)."""
  n = options.num_views
  return tuple(options.azimuth_deg + 360.0 * i / n for i in range(n))


def render_object_views(scene: Scene, index: int,
                        options: PerceptionOptions) -> list[np.ndarray]:
  """The ``options.num_views`` views of one object sent to the MLLM."""
  return [render_object_view(scene, index, options.image_size, az,
                             options.elevation_deg, options.background)
          for az in view_azimuths(options)]


def object_cache_id(scene: Scene, index: int,
                    options: PerceptionOptions) -> str:
  """What the views of an object depend on, hashed (no render).

  sha256 of the object's Gaussians (means, scales, rotations, opacities,
  SH as float32 bytes), its name, the view settings and the prompt
  version; the client adds the prompt, the model and its settings.
  """
  mask = np.asarray(scene.object_ids) == index
  g = scene.gaussians
  h = hashlib.sha256()
  for a in (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh):
    h.update(np.ascontiguousarray(np.asarray(a)[mask], np.float32).tobytes())
  h.update(json.dumps({
    'name': scene.objects[index].name, 'size': options.image_size,
    'azimuths': view_azimuths(options), 'elevation': options.elevation_deg,
    'background': list(options.background),
    'prompt_version': prompts.PROMPT_VERSION,
  }, sort_keys=True).encode('utf-8'))
  return 'gaussians:' + h.hexdigest()


def plausibility(name: str, caption: str, entry: MaterialEntry,
                 library: MaterialLibrary) -> str | None:
  """Why a picked material is implausible for the object, or None.

  The object's name is the strongest evidence: when it names materials
  (library keys or aliases as phrases, e.g. 'metal can', 'rubber ball'),
  the pick must share the category of one of them. Otherwise the caption
  (the MLLM's own description of the views) is checked the same way. A
  name or caption that names no material accepts any pick.

  Args:
    name: the object's scene name.
    caption: the MLLM's caption of the object.
    entry: the picked library entry.
    library: the material library.

  Returns:
    A one-line reason, or None when plausible.
  """
  for what, text in (('name', name), ('caption', caption)):
    keys = library.mentioned(text or '')
    if not keys:
      continue
    cats = {library[k].category for k in keys}
    if entry.category in cats:
      return None
    says = ', '.join(f'{k} ({library[k].category})' for k in keys[:3])
    return (f'{entry.key!r} ({entry.category}) contradicts the {what} '
            f'{_short(text, 60)!r}, which says {says}')
  return None


# ---------------------------------------------------------------- helpers


class _StepFailed(Exception):
  """One P3 step failed for good (message says which and why)."""


class _Implausible(_StepFailed):
  """The MLLM's pick contradicts the object's name or appearance."""


def _entry_offline(info: ObjectInfo, library: MaterialLibrary,
                   default: str | None
                   ) -> tuple[MaterialEntry | None, str, list[str]]:
  """(entry or None, reason, warnings) of the offline path."""
  warnings = []
  if info.material:
    if info.material in library:
      return (library[info.material],
              f'scene material key {info.material!r}', warnings)
    m = library.match(info.material)
    if m is not None:
      return (library[m.key],
              f'scene material {info.material!r} matched {m.how} '
              f'{m.term!r}', warnings)
    warnings.append(f'scene material {info.material!r} is not in the '
                    'library')
  m = library.match(info.name)
  if m is not None:
    return library[m.key], m.describe(info.name), warnings
  if default is not None:
    warnings.append(f'name {info.name!r} matched no library material; '
                    f'default {default!r} used. '
                    + material_hint(info.name, library))
    return library[default], f'default material {default!r}', warnings
  return None, '', warnings


def material_hint(name: str, library: MaterialLibrary) -> str:
  """How to choose a material for object ``name``, with a few library keys
  (the closest to the name first)."""
  keys = library.suggest(name, n=4)
  for k in ('steel', 'wood', 'rubber', 'jelly', 'sand', 'plasticine'):
    if k in library and k not in keys and len(keys) < 8:
      keys.append(k)
  return (f'Choose one with --material_override="{name}=KEY" (scripts) or '
          'PerceptionOptions.overrides / ObjectInfo.material (API), KEY a '
          f'library key such as {", ".join(keys)} ({len(library.keys)} in '
          'all, docs/materials.md).')


def _offline_choice(info, library, options, warnings=(),
                    prefix='') -> MaterialChoice:
  entry, reason, w = _entry_offline(info, library, options.default_material)
  if entry is None:
    raise MaterialNotFoundError(
      f'object {info.name!r}: no library material matches its name and no '
      'default_material is set. ' + material_hint(info.name, library))
  return choice_lib.choice_from_entry(
    info.name, entry, 'library', prefix + reason, tuple(warnings) + tuple(w))


def _lookup_spec(specs: Mapping[str, Any], info: ObjectInfo, index: int):
  for k in (info.name, str(index)):
    if k in specs:
      return specs[k]
  return specs.get('*')


def _check_spec_keys(scene: Scene, options: PerceptionOptions) -> None:
  """Refuses override / config keys that match no object of ``scene`` (a
  misspelt name was silently ignored: the object got another material)."""
  names = scene.object_names
  known = set(names) | {str(i) for i in range(len(names))} | {'*'}
  for field in ('overrides', 'config_materials'):
    bad = [k for k in getattr(options, field) if k not in known]
    if bad:
      raise choice_lib.MaterialChoiceError(
        f'PerceptionOptions.{field} names {bad} but scene {scene.name!r} '
        f'has no such object; its objects are {list(names)}. Use an '
        f"object's name, its index as a string ('0'..'{len(names) - 1}') "
        "or '*' (every object)")


def _short(text: str, n: int = 80) -> str:
  t = ' '.join(text.split())
  return t if len(t) <= n else t[:n - 3] + '...'


# ---------------------------------------------------------------- MLLM-P3


def _mllm_choice(info: ObjectInfo, views: Callable[[], list[bytes]],
                 cache_id: str, client: ChatClient, library: MaterialLibrary,
                 options: PerceptionOptions, deadline: float | None = None
                 ) -> MaterialChoice:
  warnings: list[str] = []

  def ask(task: str, prompt: str):
    try:
      return client.complete(prompt, views, system=prompts.SYSTEM,
                             cache_id=cache_id, deadline=deadline)
    except MLLMError as e:
      raise _StepFailed(f'{task} request failed: {e}') from None

  def unusable(reply) -> str:
    """Drops an unusable answer from the cache (the next run asks
    again); what to add to the message (the cut, the cache file)."""
    cut = getattr(reply, 'cut', '')
    note = f'; {cut}' if cut else ''
    key, evict = getattr(reply, 'key', None), getattr(client, 'evict', None)
    gone = evict(key) if key and callable(evict) else None
    if getattr(reply, 'cached', False):
      path = getattr(reply, 'cache_path', None) or 'the MLLM cache'
      note += (f'; replayed from cache {path}, now deleted (the next run '
               'asks again; --mllm_cache_dir= disables the cache)' if gone
               else f'; replayed from cache {path}; delete it or pass '
               '--mllm_cache_dir=')
    return note

  def ask_json(task: str, prompt: str, parse: Callable[[str], Any]):
    reply = ask(task, prompt)
    attempt = 0
    while True:
      try:
        out = parse(reply.text)
      except parsing.AnswerError as e:
        why = f'{e}{unusable(reply)}'
        if attempt >= options.json_retries:
          raise _StepFailed(f'{task} answer unusable: {why}') from None
        attempt += 1
        warnings.append(f'{task} answer unusable ({why}); asked again')
        reply = ask(task, prompts.json_repair_prompt(prompt, reply.text,
                                                     str(e)))
        continue
      if getattr(reply, 'cut', ''):
        warnings.append(f'{task} {reply.cut}')
      return out

  # (1) caption.
  reply = ask('caption', prompts.caption_prompt(
    info.name if options.name_hint else None))
  caption = reply.text.strip()
  if not caption:
    raise _StepFailed('caption answer is empty' + unusable(reply))
  if getattr(reply, 'cut', ''):
    warnings.append(f'caption {reply.cut}')
  # (2) candidates + rigid.
  cands = ask_json(
    'candidates',
    prompts.candidates_prompt(caption, options.num_candidates,
                              [library[k].name for k in library.keys]),
    lambda t: parsing.parse_candidates(t, library, options.num_candidates))
  warnings.extend(cands.notes)
  # (3) pick the best.
  visual = None
  if options.selection == 'first':
    key, combined, method = cands.keys[0], {cands.keys[0]: 1.0}, 'first'
  else:
    if options.selection == 'score' and len(cands.keys) > 1:
      try:
        visual, notes = ask_json(
          'score',
          prompts.score_prompt(caption,
                               [library[k].name for k in cands.keys]),
          lambda t: parsing.parse_scores(t, library, cands.keys))
        warnings.extend(notes)
      except _StepFailed as e:
        warnings.append(f'{e}; picked by text similarity and rank only')
    key, combined, method = select_candidate(
      cands.keys, caption, library, visual, options.score_weights)
  entry = library[key]
  why = plausibility(info.name, caption, entry, library)
  if why is not None:
    raise _Implausible(why)
  # (4) properties.
  try:
    props = ask_json(
      'properties',
      prompts.properties_prompt(caption, entry.name, entry.description),
      lambda t: parsing.validate_properties(
        t, entry, options.E_slack, options.rho_slack, options.nu_slack))
  except _StepFailed as e:
    warnings.append(f'{e}; library values used')
    props = parsing.library_properties(entry)
  warnings.extend(props.notes)
  if props.from_library:
    warnings.append(f'{"/".join(props.from_library)} from the library '
                    f'({entry.key})')
  rigid, note = choice_lib.rigid_for(entry, cands.rigid, info.name)
  if note:
    warnings.append(note)
  E, nu, rho, params = choice_lib.simulation_values(
    entry, library, props.E, props.nu, props.rho, options.max_E_ratio)
  got = [f for f in ('E', 'nu', 'rho') if f not in props.from_library]
  reason = (
    f'MLLM-P3: caption {_short(caption)!r}; candidates {list(cands.keys)}; '
    f'picked {key} by {method} ({combined[key]:.2f}); '
    + (f'{"/".join(got)} from the MLLM (E_real={props.E:.3g} Pa)'
       if got else 'values from the library')
  )
  return choice_lib.check_choice(MaterialChoice(
    object_name=info.name, material_key=key, model=entry.model, E=E, nu=nu,
    rho=rho, rigid=rigid, params=params, source='mllm', reason=reason,
    E_real=props.E, caption=caption, candidates=cands.keys,
    warnings=tuple(warnings),
  ))


def _given_choice(info: ObjectInfo, index: int, options: PerceptionOptions,
                  library: MaterialLibrary) -> MaterialChoice | None:
  """The object's material from an override or config value, or None when
  neither names it (raises MaterialChoiceError on a bad one)."""
  spec = _lookup_spec(options.overrides, info, index)
  source = 'override'
  if spec is None:
    spec, source = _lookup_spec(options.config_materials, info, index), \
      'config'
  if spec is None:
    return None
  base, _, _ = _entry_offline(info, library, None)
  return choice_lib.apply_spec(info.name, spec, library, base, source)


def perceive_object(
  scene: Scene,
  index: int,
  options: PerceptionOptions,
  library: MaterialLibrary,
  client: ChatClient | None = None,
  image: np.ndarray | Sequence[np.ndarray] | None = None,
  deadline: float | None = None,
) -> MaterialChoice:
  """The material of one object (see the module docstring for the paths).

  Args:
    scene: the scene.
    index: object index into ``scene.objects``.
    options: settings.
    library: the material library.
    client: chat client, or None for offline.
    image: an (H, W, 3) view, or a sequence of them, to send instead of
      rendering ``options.num_views``.
    deadline: optional absolute ``time.monotonic()`` time (the scene's
      deadline) after which no more questions are asked.

  Returns:
    A validated :class:`MaterialChoice`.

  Raises:
    MaterialChoiceError: a bad override/config value (names the object and
      field).
    MaterialNotFoundError: offline, no match and no default material.
  """
  info = scene.objects[index]
  given = _given_choice(info, index, options, library)
  if given is not None:
    return given
  if client is None or (options.scene_material_first and info.material):
    return _offline_choice(info, library, options)
  if deadline is not None and time.monotonic() >= deadline:
    why = (f'the scene deadline ({options.mllm.scene_deadline_s:g} s) has '
           'passed')
    return _offline_choice(info, library, options,
                           warnings=(f'MLLM-P3 skipped: {why}',),
                           prefix=f'MLLM-P3 skipped ({why}): ')
  if image is not None:
    pngs = [encode_png(v) for v in checks.views_of(image, 'image')]
    cache_id = 'images:' + hashlib.sha256(b''.join(
      hashlib.sha256(p).digest() for p in pngs)).hexdigest()
    views = lambda: pngs
  else:
    cache_id = object_cache_id(scene, index, options)
    rendered: list[bytes] = []

    def views() -> list[bytes]:
      if not rendered:  # once per object, on the first cache miss
        rendered.extend(encode_png(v) for v in
                        render_object_views(scene, index, options))
      return rendered

  try:
    return _mllm_choice(info, views, cache_id, client, library, options,
                        deadline)
  except _Implausible as e:
    return _offline_choice(
      info, library, options,
      warnings=(f'MLLM-P3 answer rejected as implausible: {e}',),
      prefix='MLLM-P3 answer implausible, fell back to the library: ')
  except (_StepFailed, ValueError) as e:
    return _offline_choice(info, library, options,
                           warnings=(f'MLLM-P3 failed: {e}',),
                           prefix='MLLM-P3 failed, fell back to the library: ')


def perceive_scene(
  scene: Scene,
  options: PerceptionOptions | None = None,
  *,
  client: ChatClient | None = None,
  library: MaterialLibrary | None = None,
  images: Mapping[int, np.ndarray] | None = None,
) -> tuple[MaterialChoice, ...]:
  """Chooses a material for every object of ``scene``.

  Args:
    scene: a scene with ``objects`` (background Gaussians, id -1, are not
      perceived).
    options: :class:`PerceptionOptions` (default: offline, library by name).
    client: a chat client; default: an ``MLLMClient`` when
      ``options.mllm`` has an endpoint, else None (offline).
    library: the material library (default: the shipped one).
    images: object index -> (H, W, 3) view, or a sequence of views, to use
      instead of rendering (checked up front: a bad index or shape raises
      :class:`PerceptionError` naming ``images[i]``).

  Returns:
    One :class:`MaterialChoice` per object, in ``scene.objects`` order.
    Each is logged in one absl line naming its path and reason (WARNING
    level when something fell back, INFO otherwise).

  Raises:
    MaterialChoiceError: a bad override/config value, or a key of
      ``options.overrides`` / ``config_materials`` that names no object of
      the scene (the message lists the scene's objects).
    PerceptionError: a bad option or ``images`` entry.
  """
  options = (options or PerceptionOptions()).validate()
  images = checks.check_images(images, scene.object_names, scene.name)
  library = library or default_library()
  if options.default_material is not None:
    library[options.default_material]  # fail early on a bad default
  # Every override and config value is checked before any question is
  # asked: a bad one fails at once, not after the MLLM answered others.
  _check_spec_keys(scene, options)
  given = [_given_choice(info, i, options, library)
           for i, info in enumerate(scene.objects)]
  if client is None and options.mllm.enabled:
    from physsplat_jax.io.mllm import MLLMClient

    client = MLLMClient(options.mllm)
  mode = 'MLLM-P3 via ' + options.mllm.model if client is not None else (
    'offline (library)')
  logging.info('perception: %d object(s), %s', len(scene.objects), mode)
  deadline = (time.monotonic() + options.mllm.scene_deadline_s
              if client is not None else None)
  out = []
  for i, info in enumerate(scene.objects):
    c = given[i] or perceive_object(
      scene, i, options, library, client,
      images.get(i), deadline)
    level = logging.WARNING if c.warnings else logging.INFO
    logging.log(level, 'perception: object %d %r -> %s via %s: %s%s', i,
                info.name, c.summary(), c.source, c.reason,
                (' | warnings: ' + '; '.join(c.warnings)) if c.warnings
                else '')
    out.append(c)
  return tuple(out)
