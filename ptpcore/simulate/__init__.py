"""A virtual rig with exact ground truth: lens, pose, pixelated LCD, blur, gamma, noise and
stage errors, rendering the same datasets a real capture writes, plus every pixel's true ray.

May import :mod:`ptpcore.fit` and everything below it (today it needs only
:mod:`ptpcore.pinhole`, :mod:`ptpcore.decode` and :mod:`ptpcore.rig`). :mod:`.scanner` adds the
scanner's projector, its height sweep and object scans (docs/method.md section 9).
"""

from . import virtual_rig
from .virtual_rig import *  # noqa: F401,F403  (the names of virtual_rig.__all__)
from . import draws, lens_models, scanner  # noqa: E402  (lens models beyond Brown; rigs drawn per seed; the scanner)
from .draws import *  # noqa: F401,F403,E402

# One list of public names: each module's own __all__.
__all__ = list(virtual_rig.__all__) + list(draws.__all__)
