"""needlecue: the pipeline from raw rig logs to registered needle-force models and angle cues
(README.md; docs/layout.md maps the packages)."""
