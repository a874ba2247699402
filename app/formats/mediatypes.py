"""Media types the service reads and writes, each spelled once.

Types tied to one message (the CDR types of ``app.ros.messages_in.media_type`` and
``app.ros.messages_out.CDR_MEDIA_TYPE``) stay with the code that reads or writes that message.
"""

from __future__ import annotations

#: Bytes with no more specific type: what generic HTTP clients and generated clients send and accept for a file.
OCTET_STREAM = "application/octet-stream"
#: A NumPy ``.npy`` file.
NPY = "application/x-npy"
#: An MCAP file: the type the MCAP project names (``application/mcap``; none is registered).
MCAP = "application/mcap"
#: An MCAP file by the older ``x-`` name, still sent by some tools: accepted as ``MCAP`` is.
X_MCAP = "application/x-mcap"
#: A ROS 1 bag (``.bag``, format 2.0).
ROSBAG = "application/x-rosbag"
