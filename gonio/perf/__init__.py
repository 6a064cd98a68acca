"""Every benchmark, run as ``gonio perf ...`` (alias ``gonio bench ...``): each prints its
figures as ratios against a peer or a physical limit measured in the same run.
"""
