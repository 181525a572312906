"""pytest configuration shared by all tests."""

import os
import pathlib

os.environ.setdefault('JAX_PLATFORMS', 'cpu')

import jax  # noqa: E402

# Tests that need float64 use ``with jax.enable_x64(True):`` locally, so the
# f32 default of the library is what the rest of the suite exercises.
del jax

REPO = pathlib.Path(__file__).resolve().parents[1]
