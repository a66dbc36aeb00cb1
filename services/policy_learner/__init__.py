"""policy-learner: trains PPO or SAC on streamed (scored) transitions and publishes versioned policy weights."""
