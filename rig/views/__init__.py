"""What a person reads: progress lines, status and watch views, replays, figures, decoded wire spies."""
