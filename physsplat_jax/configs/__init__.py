"""Scene configs: PhysGaussian JSON schema (``physgaussian``)."""

from physsplat_jax.configs.physgaussian import ConfigError as ConfigError
from physsplat_jax.configs.physgaussian import PhysGaussianConfig as PhysGaussianConfig
from physsplat_jax.configs.physgaussian import load_config as load_config
from physsplat_jax.configs.physgaussian import material_name as material_name
from physsplat_jax.configs.physgaussian import parse_config as parse_config
