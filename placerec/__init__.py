"""placerec: LiDAR place recognition and loop-closure detection using intensity as well as geometry.

Import the pieces you need from their modules (``placerec.types``, ``placerec.io``, ``placerec.preprocess``, ...);
this package imports nothing heavy at import time.
"""

import logging

from placerec._version import __version__

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = ["__version__"]
