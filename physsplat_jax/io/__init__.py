"""File I/O: 3DGS scenes (PLY, compressed PLY, .splat) and camera files.

The only package modules that touch the filesystem live here (and in
``experiments/``). Render outputs (video, frames) are in ``io.video`` and
``io.frames``, imported from there directly.
"""

from physsplat_jax.io.ply import PlyError as PlyError
from physsplat_jax.io.ply import load_ply as load_ply
from physsplat_jax.io.ply import read_ply as read_ply
from physsplat_jax.io.ply import read_ply_header as read_ply_header
from physsplat_jax.io.ply import save_ply as save_ply
from physsplat_jax.io.ply import write_ply as write_ply
