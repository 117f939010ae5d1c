"""Calibration tools: estimate configuration sections from recordings of calibration runs.

:mod:`x6wd.calibrate.odometry` (``x6wd calibrate odometry``): wheel diameters, effective
track and the non-systematic odometry error from a straight and a circular track (seed 003).
"""
