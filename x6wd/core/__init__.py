"""Shared core: records, errors, configuration types, health, recording, mission files.

Imports nothing above it; every other layer may import it."""
