"""What a user runs: one member's loop, the launcher, readers of pools (status, progress,
TensorBoard, plots, comparisons), evaluation, picking, replay, presets and the command line.
The only layer that brings learning and the protocol together."""
