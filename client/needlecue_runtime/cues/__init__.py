"""The angle cues at run time: the cue pack as a typed document (pack), a frame's evidence (evidence),
the paper's standard profile (profile), a unit's reading (reading, units), the cue states (states) and
the tracker that steps them every frame (tracker). The pipeline fits the packs (`pipeline.cues`)."""
