"""The batched MJX closed loop: the plant of a batch, its rollouts, MJX's import."""
