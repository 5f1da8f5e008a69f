"""Trial logs: the message types, the MCAP writer, the reader, and recovery after a crash."""
