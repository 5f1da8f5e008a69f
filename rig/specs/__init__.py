"""What a trial is told to do: the rig's config, protocols and their YAML binding, the moves."""
