"""Material perception: the material library and MLLM-P3 (pure functions).

The HTTP client lives in :mod:`physsplat_jax.io.mllm`; see docs/perception.md
and docs/materials.md.
"""

from physsplat_jax.perception.choice import MaterialChoice as MaterialChoice
from physsplat_jax.perception.choice import (
  MaterialChoiceError as MaterialChoiceError,
)
from physsplat_jax.perception.choice import ObjectMaterial as ObjectMaterial
from physsplat_jax.perception.choice import apply_spec as apply_spec
from physsplat_jax.perception.choice import (
  simulation_values as simulation_values,
)
from physsplat_jax.perception.choice import (
  spec_from_physgaussian as spec_from_physgaussian,
)
from physsplat_jax.perception.flags import define_flags as define_flags
from physsplat_jax.perception.flags import (
  options_from_flags as options_from_flags,
)
from physsplat_jax.perception.flags import parse_overrides as parse_overrides
from physsplat_jax.perception.library import LibraryError as LibraryError
from physsplat_jax.perception.library import Match as Match
from physsplat_jax.perception.library import MaterialEntry as MaterialEntry
from physsplat_jax.perception.library import MaterialLibrary as MaterialLibrary
from physsplat_jax.perception.library import (
  MaterialNotFoundError as MaterialNotFoundError,
)
from physsplat_jax.perception.library import default_library as default_library
from physsplat_jax.perception.library import load_library as load_library
from physsplat_jax.perception.library import parse_library as parse_library
from physsplat_jax.perception.p3 import PerceptionError as PerceptionError
from physsplat_jax.perception.p3 import PerceptionOptions as PerceptionOptions
from physsplat_jax.perception.p3 import perceive_object as perceive_object
from physsplat_jax.perception.p3 import perceive_scene as perceive_scene
from physsplat_jax.perception.p3 import object_cache_id as object_cache_id
from physsplat_jax.perception.p3 import plausibility as plausibility
from physsplat_jax.perception.p3 import (
  render_object_view as render_object_view,
)
from physsplat_jax.perception.p3 import (
  render_object_views as render_object_views,
)
from physsplat_jax.perception.parsing import AnswerError as AnswerError
from physsplat_jax.perception.selection import (
  select_candidate as select_candidate,
)
