"""Step (3) of MLLM-P3: pick the best of the K candidate materials.

The paper ranks candidates by CLIP similarity between the rendered view and
each material name. CLIP weights cannot be downloaded here, so the pick
combines three signals, each in [0, 1]::

  score(k) = w_v * v(k) + w_t * t(k) + w_r * r(k)

* ``v(k)``: the MLLM's own visual match score for candidate k (answer to the
  'score' prompt: it sees the same image, so this plays CLIP's role);
* ``t(k)``: tf-idf cosine similarity between the caption and the library
  entry's key, description, aliases and keywords
  (:meth:`MaterialLibrary.similarity`), divided by the best candidate's
  value so it spans [0, 1];
* ``r(k) = 1 - i / K``: the MLLM's own ranking (position i in its list).

Default weights ``(w_v, w_t, w_r) = (0.6, 0.3, 0.1)``. When the scoring
answer is missing or unusable, ``w_v`` is dropped and the others are
renormalised ('text+rank'); ties go to the earlier candidate.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from physsplat_jax.perception.checks import PerceptionError
from physsplat_jax.perception.library import MaterialLibrary

DEFAULT_WEIGHTS = (0.6, 0.3, 0.1)


def select_candidate(
  candidate_keys: Sequence[str],
  caption: str,
  library: MaterialLibrary,
  visual_scores: Mapping[str, float] | None = None,
  weights: tuple[float, float, float] = DEFAULT_WEIGHTS,
) -> tuple[str, dict[str, float], str]:
  """Combines visual, text and rank evidence.

  Args:
    candidate_keys: library keys, the MLLM's most likely first.
    caption: the MLLM's caption of the object.
    library: the material library.
    visual_scores: key -> MLLM visual score in [0, 1] (missing keys count
      0), or None when unavailable.
    weights: ``(w_visual, w_text, w_rank)``, non-negative.

  Returns:
    ``(best key, combined score per key, method)``; method is
    'mllm_score+text+rank' or 'text+rank'.

  Raises:
    PerceptionError (a ValueError): no candidates, or bad weights.
  """
  keys = list(candidate_keys)
  if not keys:
    raise PerceptionError('select_candidate: no candidates')
  if len(weights) != 3 or min(weights) < 0 or sum(weights) <= 0:
    raise PerceptionError(f'select_candidate: weights {weights} must be '
                          'three non-negative numbers, not all zero')
  w_v, w_t, w_r = weights
  method = 'mllm_score+text+rank'
  if not visual_scores:
    w_v, method = 0.0, 'text+rank'
  total = w_v + w_t + w_r
  if total <= 0:  # only a visual weight was given and no visual scores
    w_t, w_r, total = 0.0, 1.0, 1.0
  sim = library.similarity(caption)
  t = {k: sim.get(k, 0.0) for k in keys}
  top = max(t.values())
  t = {k: (v / top if top > 0 else 0.0) for k, v in t.items()}
  n = len(keys)
  combined = {}
  for i, k in enumerate(keys):
    v = float(visual_scores.get(k, 0.0)) if visual_scores else 0.0
    combined[k] = (w_v * v + w_t * t[k] + w_r * (1.0 - i / n)) / total
  best = max(keys, key=lambda k: (combined[k], -keys.index(k)))
  return best, combined, method
