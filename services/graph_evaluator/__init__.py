"""graph-evaluator: CMI of the latest dynamics weights on held-out episodes -> causal graph reports."""
