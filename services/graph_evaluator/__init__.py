"""graph-evaluator: the method's graph estimators (CDL: CMI) on the latest weights and held-out episodes -> graph reports."""
