"""Agents: pure state, losses and updates."""
