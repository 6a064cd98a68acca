"""Where the instrument goes: measurement plans, the rig's kinematics, move ordering and
the holder's markers.
"""

from gonio.bench.plan import adaptive as _adaptive  # noqa: F401,E402  (registers the "adaptive" strategy)
