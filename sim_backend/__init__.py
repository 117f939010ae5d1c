"""The simulated world: emits the real devices' bytes and register values."""
