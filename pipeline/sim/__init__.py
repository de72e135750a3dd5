"""The built-in rig simulator: the rig's physics and writing simulated rig-log/1 batches
(see `docs/physics.md`)."""
