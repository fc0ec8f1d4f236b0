"""triswarm's MAVLink dialect, shipped generated: ``triswarm_v20`` (MAVLink 2, a module like pymavlink's
``pymavlink.dialects.v20.common``, with our commands). Importing it reads no environment and writes
nothing.

The folder holds the wire definitions it is made from: ``triswarm.xml`` (ours: common.xml plus the
plan and leader commands) and ``common.xml``, ``standard.xml`` and ``minimal.xml``, pinned copies of
pymavlink 2.4.50's (``pymavlink/dialects/v20/``), so that the frames triswarm speaks do not change
with the pymavlink installed. ``triswarm_v20.py`` is pymavlink's own generator's output for them,
made by ``tools/gen_dialect.py`` (``make dialect``), which replaces only its read of MAV_IGNORE_CRC
from the environment (triswarm never ignores CRCs); do not edit it. tests/test_dialect.py checks,
message by message and enum by enum, that it is what the generator makes of these files.
"""

from . import triswarm_v20

__all__ = ["triswarm_v20"]
