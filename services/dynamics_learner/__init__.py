"""dynamics-learner: trains the CDL causal dynamics model on streamed transitions and publishes weights."""
