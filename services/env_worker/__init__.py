"""env-worker: steps one environment with the current collection policy and publishes transition batches."""
