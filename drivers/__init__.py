"""Device drivers: one module per device, each a sans-IO decoder plus a thin I/O edge."""
