"""Sim-to-real gap diagnosis."""
