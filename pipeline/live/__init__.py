"""The estimator live at the simulator: its serial wire format (`wire`), the stream's health
(`health`), insertions found in the signal (`insertions`), the session that runs the champion and the
cue tracker frame by frame (`session`), its recording (`recording`), the serial port (`port`), the
trainee's displays (`display`) and a rig emulated over a pseudo-terminal (`emulate`).
docs/live.md describes them."""
