"""placerec: LiDAR place recognition and loop-closure detection using intensity as well as geometry.

Import the pieces you need from their modules (``placerec.types``, ``placerec.io``, ``placerec.preprocess``, ...);
this package imports nothing heavy at import time. A few names a user reaches for first are also here, imported
on first use: ``placerec.Localizer`` and ``placerec.MapArtifact`` (`placerec.maps`), ``placerec.LoopClosureDetector``
(`placerec.loop_closure`).
"""

import logging

from placerec._lazy import lazy_exports
from placerec._version import __version__

logging.getLogger(__name__).addHandler(logging.NullHandler())

_EXPORTS = {
    "Localizer": "placerec.maps.localizer",
    "MapArtifact": "placerec.maps.artifact",
    "LoopClosureDetector": "placerec.loop_closure",
}

__all__ = ["__version__", *sorted(_EXPORTS)]
__getattr__ = lazy_exports(__name__, _EXPORTS)
