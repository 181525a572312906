"""Named settings of the benchmarks (config fields over
experiments/configs/simulate.py's defaults).

- ``paper``: the paper's setting for a GPU: 64^3 grid, 768 substeps per
  frame at 30 fps, 150 frames (a 5 s video), 800x800, up to 200k particles
  (issue 17's targets are stated at it);
- ``cpu``: sized for a 2-core CPU (the ``make demo`` settings).

``benchmark_pipeline --preset`` runs ``experiments.simulate`` with them;
``benchmark_substep --preset`` and ``gpu_kernels --preset`` prepare a
scene's substep with them (``demo``, those scripts' default, is
experiments/configs/demo.py with its scene motions instead).
"""

PRESETS = {
  'paper': dict(grid_res=64, num_frames=150, fps=30.0, substeps_per_frame=768,
                width=800, height=800, max_particles=200_000),
  'cpu': dict(grid_res=32, num_frames=36, fps=24.0, width=480, height=360,
              max_particles=6_000),
}
