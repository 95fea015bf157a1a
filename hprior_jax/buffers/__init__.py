"""Replay and preference buffers: pytree state plus pure ops."""
