"""Applications: the daemon, the servers, the operator client, the command line.

The top layer: may import every layer below it."""
