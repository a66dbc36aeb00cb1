"""dashboard: the live causal-graph page, learned vs true graph, abstraction and learning curves, per run."""
