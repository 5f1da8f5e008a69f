"""The rig checked: do the devices answer (`rig probe`), which ports exist, timing benchmarks."""
