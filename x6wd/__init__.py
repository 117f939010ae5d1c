"""x6wd: onboard software of the X6WD six-wheeled GPS robot."""

__version__ = "0.1.0"
