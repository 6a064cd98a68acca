"""Fitting many datasets: the Dask batch, the in-memory handoff to workers, the allocator
settings of processes that fit.
"""
