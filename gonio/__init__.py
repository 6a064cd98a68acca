"""gonio: a physically based BRDF/BSDF measurement and validation bench.

Sub-packages, bottom to top (each imports only those below it; pyproject.toml
``[tool.importlinter]`` checks it): ``core`` (geometry, errors, files), ``models``,
``sim`` and ``fitting`` (side by side), ``bench`` (the instrument), ``perf``
(benchmarks) and ``cli`` (argument parsing). docs/architecture.md draws the tree.
"""
