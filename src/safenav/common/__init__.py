"""Parts every trainer shares: run config, replay buffer, Lagrange multiplier, curricula, the
tensor view of any Gymnasium env, logging and checkpoints."""
