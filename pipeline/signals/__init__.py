"""Signal processing of ingested trials: units, clock alignment, resampling onto one grid and
phase labels, assembled per trial and per batch."""
