"""Navigation: projection, the Constellation filter, the waypoint navigator, the sans-IO controller.

Imports only the core."""
