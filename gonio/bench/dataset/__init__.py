"""Exporting a session to ``dataset.nc``: the export, the per-point budget and CF-1.8
metadata.
"""
