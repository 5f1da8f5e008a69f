"""The simulated rig: tissue physics, a simulated slider and load cell."""
