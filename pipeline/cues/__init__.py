"""The simulator's angle cues: the runtime tracker (numpy only, imported by the client), fitting
the cue packs from training splits, and scoring the cues on held-out trials."""
