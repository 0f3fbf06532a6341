"""Pieces every trainer shares: checkpoints, resume, Ctrl-C, progress, schedules, data parallelism."""
