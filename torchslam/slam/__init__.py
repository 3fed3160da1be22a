"""Old home of the systems and the application, kept for one release.

``torchslam.slam.X`` now lives in :mod:`torchslam.systems` (base, registry, lockstep, monitor,
memory, nislam, gcslam) or :mod:`torchslam.app` (run, outputs, progress, report, runfolder, batch,
calibrate_time, the old ``time_offset``). Each old path still imports, as the very same module,
and warns once.
"""

import warnings

from ..systems import *  # noqa: F401,F403
from ..systems import __all__  # noqa: F401

warnings.warn("torchslam.slam moved to torchslam.systems and torchslam.app; the old path goes in the next release",
              FutureWarning, stacklevel=2)
