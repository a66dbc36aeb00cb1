"""intrinsic-reward: scores transitions with an intrinsic reward from the learned causal dynamics model."""
