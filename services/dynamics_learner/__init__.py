"""dynamics-learner: trains the run's method's dynamics model on streamed transitions and publishes weights."""
