"""What the simulator's client and the training pipeline share, and nothing else: the names and file
formats (vocab, documents), the estimator's front end and a model's inputs (frontend, features), the
params sections both read (params), a unit's calibration document (unit_calibration), the runtime cue
tracker (cues) and the registry's store (registry). numpy, pydantic, pyyaml and mlflow-skinny only."""
