"""MPDP: per-point material property fields from a Flax point network.

``predict(params, points, means, mask, weights=None)`` -> (N, 3) multipliers
of (E, nu, rho) with masked (weighted) mean exactly 1; ``load_pretrained()``
gives the shipped params.
See docs/mpdp.md.
"""

from physsplat_jax.mpdp.model import MEANS_DIM as MEANS_DIM
from physsplat_jax.mpdp.model import MODEL_NAMES as MODEL_NAMES
from physsplat_jax.mpdp.model import NU_MAX as NU_MAX
from physsplat_jax.mpdp.model import MPDPError as MPDPError
from physsplat_jax.mpdp.model import ModelConfig as ModelConfig
from physsplat_jax.mpdp.model import encode_means as encode_means
from physsplat_jax.mpdp.model import init_params as init_params
from physsplat_jax.mpdp.model import make_predict as make_predict
from physsplat_jax.mpdp.model import material_from_field as material_from_field
from physsplat_jax.mpdp.model import predict as predict
from physsplat_jax.mpdp.pretrained import load_params as load_params
from physsplat_jax.mpdp.pretrained import load_pretrained as load_pretrained
from physsplat_jax.mpdp.pretrained import save_params as save_params


def __getattr__(name):
  # PointNet lives in mpdp.network, which imports Flax: loaded on first use.
  if name == 'PointNet':
    from physsplat_jax.mpdp.network import PointNet  # noqa: PLC0415
    return PointNet
  raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
