"""The rig description: camera, LCD, stage and fringe design as dataclasses, and ``rig.toml``
(``ptp-dataset/1`` and ``/2``) read with validation and written back.

The bottom layer: imports only :mod:`ptpcore.errors` and :mod:`ptpcore.atomic`.
"""

from . import rigfile
from .rigfile import *  # noqa: F401,F403  (the names of rigfile.__all__)
from . import naming
from .naming import *  # noqa: F401,F403  (the names of naming.__all__)

# One list of public names: each module's own __all__.
__all__ = list(rigfile.__all__) + list(naming.__all__)
