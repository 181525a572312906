"""MPDP training configs: supervised (the shipped checkpoint) and through
the simulator (``sim``).

Usage:
  python experiments/train_mpdp.py --workdir=/tmp/mpdp \
    --config=experiments/configs/mpdp.py --export=physsplat_jax/data/mpdp
  python experiments/train_mpdp.py --workdir=/tmp/mpdp_sim \
    --config=experiments/configs/mpdp.py --mode=simulator
"""

import ml_collections


def get_config():
  """Default MPDP training config (a few minutes on 2 CPU cores)."""
  c = ml_collections.ConfigDict()
  c.model = ml_collections.ConfigDict(dict(
    features=(64, 64), edge_features=64, k_neighbors=8, global_features=128,
    cond_features=32, head_features=(64, 64), log_range=(3.0, 0.405, 0.693)))
  c.data = ml_collections.ConfigDict(dict(
    seed=1, eval_seed=2, num_train=1024, num_eval=128, num_points=256,
    min_fill=0.75))
  c.train = ml_collections.ConfigDict(dict(
    seed=0, learning_rate=2e-3, weight_decay=1e-4, warmup_steps=100,
    num_steps=2000, batch_size=16, grad_clip=1.0,
    channel_weights=(1.0, 1.0, 1.0), log_every=100, eval_every=500,
    checkpoint_every=500, max_to_keep=2))
  # Through physsplat_jax.pipeline.simulate (physsplat_jax.training.simtrain):
  # synthetic cantilevers anchored in a wall, trajectory loss against
  # targets simulated from the ground-truth fields.
  c.sim = ml_collections.ConfigDict(dict(
    task=dict(
      num_gaussians=384, num_particles=192, length=0.5, E=3e5, nu=0.3,
      rho=1000.0, model='fixed_corotated', num_frames=10, fps=24.0,
      substeps_per_frame=50, grid_res=20, margin=0.75, gaussian_scale=0.024,
      width=64, height=48, wall_seed=1234, dtype='float64'),
    train_seeds=(0, 1, 2, 3), eval_seeds=(10, 11, 12, 13), init='zero',
    num_steps=30, learning_rate=3e-3, grad_clip=1.0, log_every=1,
    checkpoint_every=10, max_to_keep=2))
  return c
