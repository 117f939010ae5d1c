"""Calibration tools: estimate configuration sections from recordings of calibration runs.

:mod:`x6wd.calibrate.odometry` (``x6wd calibrate odometry``): wheel diameters, effective
track and the non-systematic odometry error from a straight and a circular track (seed 003).
:mod:`x6wd.calibrate.gnss` (``x6wd calibrate gnss``): the seed-003 GPS error terms RE and ASE
from a static recording at a known position, and the LCE map from drives with a reference
trajectory (:mod:`x6wd.calibrate.rtklib` reads RTKLIB ``.pos`` files).
"""
