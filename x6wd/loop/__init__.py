"""The one control loop (``runner``): devices -> controller -> motors, telemetry, recorder,
with an injected clock; the daemon, hardware in the loop and fast time are its edges."""
