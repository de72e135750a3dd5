"""How much data a lab needs (issue 39): force and cue figures against the training insertions per
angle, and a new unit's cues against its calibration insertions per angle, by subsampling the lab's
own processed data (`curves`), and what to record next, in words computed from them (`advice`)."""
