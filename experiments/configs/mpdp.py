"""MPDP supervised training: the config of the shipped checkpoint.

Usage: python experiments/train_mpdp.py --workdir=/tmp/mpdp \
  --config=experiments/configs/mpdp.py --export=physsplat_jax/data/mpdp
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
  return c
