"""The control loop and its safety: the trial's ticks, limits, moves, stopping, the estimator."""
