"""`rig web`: the lab in a browser: the console, the history of trials, batch tables as maps."""
