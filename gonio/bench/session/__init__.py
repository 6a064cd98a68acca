"""A capture session that survives being killed: the run, its journal, its integrity
checks, the point pipeline, signals, calibration frames and operator shots.
"""
