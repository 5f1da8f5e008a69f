"""Running trials: the daemon and its clients, a trial in the foreground, the live view."""
