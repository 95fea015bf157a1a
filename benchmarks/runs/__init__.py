"""Whole runs and start-up: end to end, against BPref, replay, devices, compiling, GPU suite."""
