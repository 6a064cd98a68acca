"""The registered models, one file a model: its parameters, its numpy formula, its Dr.Jit
kernel and its Mitsuba 3 twin.
"""

# The transmission models register here (gonio.models imports the reflection ones by name).
from gonio.models.catalogue import roughdielectric as _roughdielectric  # noqa: F401,E402
from gonio.models.catalogue import dielectric as _dielectric  # noqa: F401,E402
from gonio.models.catalogue import thindielectric as _thindielectric  # noqa: F401,E402
from gonio.models.catalogue import difftrans as _difftrans  # noqa: F401,E402
from gonio.models.catalogue import roughslab as _roughslab  # noqa: F401,E402
