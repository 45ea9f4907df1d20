"""Recordings: the MCAP writer, the recorder role, the one reader, and the metrics scored from a run."""
