"""Driving particles: internal filling, PGAS, Poisson disk, K-means."""

from physsplat_jax.sampling.curvature import gaussian_curvature
from physsplat_jax.sampling.curvature import local_curvature
from physsplat_jax.sampling.curvature import normalize_curvature
from physsplat_jax.sampling.filling import FillConfig
from physsplat_jax.sampling.filling import FillResult
from physsplat_jax.sampling.filling import fill_gaussians
from physsplat_jax.sampling.filling import fill_mesh
from physsplat_jax.sampling.filling import fill_objects
from physsplat_jax.sampling.filling import interior_cells
from physsplat_jax.sampling.filling import occupancy_grid
from physsplat_jax.sampling.clustering import KMeansResult
from physsplat_jax.sampling.clustering import kmeans
from physsplat_jax.sampling.pgas import PGASConfig
from physsplat_jax.sampling.pgas import adaptive_radius
from physsplat_jax.sampling.pgas import pgas_curvature
from physsplat_jax.sampling.pgas import pgas_sample
from physsplat_jax.sampling.pgas import scale_for_budget
from physsplat_jax.sampling.poisson import PoissonResult
from physsplat_jax.sampling.poisson import check_overflow
from physsplat_jax.sampling.poisson import poisson_disk
from physsplat_jax.sampling.driving import Candidates
from physsplat_jax.sampling.driving import Drivers
from physsplat_jax.sampling.driving import make_candidates
from physsplat_jax.sampling.driving import select_drivers
