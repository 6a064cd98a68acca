"""Where the instrument goes: measurement plans, the rig's kinematics, move ordering and
the holder's markers.
"""

from gonio.bench.plan import adaptive as _adaptive  # noqa: F401,E402  (registers the "adaptive" strategy)
from gonio.bench.plan import ndf_seeded as _ndf_seeded  # noqa: F401,E402  (registers the "ndf" strategy)
