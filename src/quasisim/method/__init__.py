"""Control methods that turn a demonstration into PD-target trajectories for the target simulators."""
