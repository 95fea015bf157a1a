"""Flax modules (no losses, no optimizers)."""
