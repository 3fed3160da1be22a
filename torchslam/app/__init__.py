"""The application around the SLAM systems: run folders, batches, reports, progress and calibration.

Only this layer (with ``data/`` and ``cli.py``) touches the disk; it imports the systems through
:mod:`torchslam.systems` and never the other way round.
"""
