"""A new estimator unit's calibration: from its short calibration batch, the input transform that lets
the frozen shared models read it as they read the training units (`fit`), and the per-unit document
that the pipeline applies, the registry stores and the client fetches (`unit`)."""
