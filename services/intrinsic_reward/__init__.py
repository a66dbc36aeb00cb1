"""intrinsic-reward: scores transitions with an intrinsic reward from the method's learned dynamics model (or its own ensemble)."""
