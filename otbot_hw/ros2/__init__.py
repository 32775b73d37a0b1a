"""ROS 2 bags in and out (rosbag2: MCAP storage, CDR messages, ``metadata.yaml``).

* ``bag_import.import_bag``: a ROS 2 bag (folder or single ``.mcap``) → a project ``Recording``
  (``otbot import``), by a mapping (``mapping.BagMap``; the common layout by default); its parts
  ``bag_open`` (opening, decoding), ``bag_series`` (topics to series), ``bag_time`` (stamps, grid);
* ``bag_export.export_recording``: a project recording → a rosbag2 folder (``otbot export --ros2``);
* ``writer.BagWriter``: the streaming, append-safe bag writer both use (and the daemon's session
  recordings with ``daemon.recording.format: ros2``).

Messages are serialized and deserialized by ``rosbags`` (the ``ros2`` pip extra) (no hand-written CDR) with the standard
ROS 2 Jazzy definitions; the MCAP container is written with the ``mcap`` package, unchunked and
flushed, so that a process killed mid-run leaves a bag that loads up to the cut.
Frames and the conversion between REP-103 and the project's conventions: docs/recording-format.md §9.
"""
from otbot_hw.recording import RecordingError


def rosbags(module: str = "rosbags"):
    """``rosbags`` (or a submodule), the ``ros2`` pip extra: ``MissingExtraError`` (exit 2, one line
    naming ``pip install 'otbot-hw[ros2]'``) when it is not installed."""
    from otbot_hw.extras import require

    return require(module)


class BagError(RecordingError):
    """A ROS 2 bag or its mapping cannot give a correct recording (bad input: exit 2); the message
    names the bag, topic and field."""


__all__ = ["BagError", "rosbags"]
