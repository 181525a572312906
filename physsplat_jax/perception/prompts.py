"""Prompts of MLLM-P3 (PhysSplat, ICCV 2025, Sec. 3.1): four questions.

Every prompt starts with a ``TASK: <name>`` line (caption, candidates,
score, properties) so answers are easy to audit in the cache and servers can
be scripted in tests. JSON answers are requested in an exact form; the
parsers in :mod:`physsplat_jax.perception.parsing` still accept common
deviations (code fences, prose around the JSON, units in strings).
"""

from __future__ import annotations

from collections.abc import Sequence

SYSTEM = (
  'You are a materials scientist helping a physics simulator. You look at '
  'a rendered object and answer precisely. When asked for JSON, answer with '
  'a single JSON object and nothing else.'
)

TASKS = ('caption', 'candidates', 'score', 'properties')
# Part of every cache key: bump when a prompt's wording changes.
# 2: several views of the object per question.
PROMPT_VERSION = 2


def caption_prompt(name_hint: str | None = None) -> str:
  """(1) Caption the object."""
  hint = f' (the scene labels it {name_hint!r})' if name_hint else ''
  return (
    'TASK: caption\n'
    f'The images show one object cut out of a 3D scene{hint}, seen from '
    'several sides. Describe it in one or two sentences: what it is, what '
    'it is most likely made of, its colour and its surface (shiny, matte, '
    'translucent, rough, soft). '
    'Answer with plain text only.'
  )


def candidates_prompt(caption: str, num_candidates: int,
                      library_names: Sequence[str]) -> str:
  """(2) K candidate materials and the rigid flag, as JSON."""
  names = ', '.join(library_names)
  return (
    'TASK: candidates\n'
    f'Object description: {caption}\n'
    f'List the {num_candidates} most likely materials of this object, most '
    'likely first, and say whether the object moves as a rigid body (it '
    'does not visibly bend, squash, break apart or flow under everyday '
    f'forces). Prefer names from this list: {names}.\n'
    'Answer with JSON only, exactly in this form:\n'
    '{"candidates": [{"material": "<name>", "reason": "<a few words>"}], '
    '"rigid": true}'
  )


def score_prompt(caption: str, candidates: Sequence[str]) -> str:
  """(3) Visual match score of every candidate, as JSON."""
  names = ', '.join(candidates)
  example = ', '.join(f'"{c}": 0.5' for c in candidates[:2])
  return (
    'TASK: score\n'
    f'Object description: {caption}\n'
    f'Candidate materials: {names}.\n'
    'For each candidate, rate from 0 (impossible) to 1 (certain) how well it '
    'matches the object in the images.\n'
    'Answer with JSON only, exactly in this form:\n'
    f'{{"scores": {{{example}}}}}'
  )


def properties_prompt(caption: str, material: str, description: str) -> str:
  """(4) Density, Young's modulus and Poisson's ratio, as JSON (SI)."""
  return (
    'TASK: properties\n'
    f'Object description: {caption}\n'
    f'Material: {material} ({description}).\n'
    'Estimate the real-world physical properties of this material as it '
    'is in this object. Use SI units: density in kg/m^3, Young\'s modulus '
    'in pascals (Pa, not GPa or MPa), Poisson\'s ratio between 0 and 0.5.\n'
    'Answer with JSON only, exactly in this form:\n'
    '{"density_kg_m3": 1000.0, "youngs_modulus_pa": 1.0e6, '
    '"poisson_ratio": 0.3}'
  )


def json_repair_prompt(original_prompt: str, bad_answer: str,
                       problem: str) -> str:
  """Asks again after an answer that could not be parsed."""
  excerpt = bad_answer.strip().replace('\n', ' ')[:300]
  return (
    f'{original_prompt}\n\n'
    f'Your previous answer could not be used ({problem}): {excerpt!r}\n'
    'Answer again with one valid JSON object only, no prose, no code fence.'
  )


def task_of(prompt: str) -> str | None:
  """The ``TASK:`` name of a prompt, or None."""
  first = prompt.split('\n', 1)[0].strip()
  if first.startswith('TASK:'):
    return first[len('TASK:'):].strip()
  return None
