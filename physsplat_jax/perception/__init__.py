"""Material perception: the material library and MLLM-P3 (pure functions).

The HTTP client lives in :mod:`physsplat_jax.io.mllm`; see docs/perception.md
and docs/materials.md.
"""

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
