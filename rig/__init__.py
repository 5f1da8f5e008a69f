"""indentation-rig: controller and model lab for a soft-tissue indentation rig."""

__version__ = "0.1.0"
