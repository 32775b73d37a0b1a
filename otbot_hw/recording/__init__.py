"""Recordings of Otbot runs in MCAP (the container ROS 2 bags and Foxglove use).

One file holds one run: a metadata record ``otbot`` and, for every sample k, one
JSON message on each recorded topic, all stamped with the same time t_k. The
layout is specified in ``docs/recording-format.md``; in short:

==================  ===============================================  ==========
topic               payload (JSON)                                   required
==================  ===============================================  ==========
/otbot/command      t (s), torque [tau_r, tau_l, tau_p] (N m)        yes
/otbot/joints       t, position [phi_r, phi_l, phi_p] (rad),         no
                    velocity (rad/s)
/otbot/imu          t, accel [x, y, z] (m/s^2), gyro [x, y, z]       no
                    (rad/s), platform frame B''
/otbot/truth        t, q (6), qd (6), force [f_x, f_y] (N, ground)   no (sim)
/otbot/estimate     t, pose [x, y, alpha] (m, rad), twist (m/s,      no (loop)
                    rad/s), std (6) of pose and twist, gyro_bias
/otbot/reference    t, p [x, y, alpha], pd, pdd (desired motion)     no (loop)
/otbot/events       t, kind, text: sparse (mode changes, faults,     no (loop)
                    saturation), not one per sample
==================  ===============================================  ==========

Messages are written unchunked and uncompressed and flushed every few samples,
so a file cut short (process killed mid-write) still loads every complete sample.
Floats are written with Python's shortest round-trip repr: loading gives back the
exact float64 values.

Its parts: ``format`` (topics and their JSON schemas, units, frames, the ``source`` metadata,
``Recording``, ``RecordingError``), ``writer`` (``RecordingWriter``: streaming; ``write_recording``),
``reader`` (``read_recording``: a file cut short yields its complete samples). This package's names
are the public interface (57 modules import them from ``otbot_hw.recording``).
"""
from otbot_hw.recording.format import (
    FORMAT_NAME, FORMAT_VERSION, FRAMES, MCAP_MAGIC, PROFILE, SAMPLE_TOPICS, SOURCE_BUS_SIMULATION, SOURCE_ROBOT,
    SOURCE_SIMULATION, TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_EVENTS, TOPIC_IMU, TOPIC_JOINTS, TOPIC_PAYLOAD,
    TOPIC_REFERENCE, TOPIC_TRUTH, TOPICS, UNITS, Recording, RecordingError, source_metadata)
from otbot_hw.recording.reader import read_recording
from otbot_hw.recording.writer import RecordingWriter, write_recording, write_samples_and_events

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "FRAMES", "MCAP_MAGIC", "PROFILE", "SAMPLE_TOPICS",
           "SOURCE_BUS_SIMULATION", "SOURCE_ROBOT", "SOURCE_SIMULATION", "TOPIC_COMMAND", "TOPIC_ESTIMATE",
           "TOPIC_EVENTS", "TOPIC_IMU", "TOPIC_JOINTS", "TOPIC_PAYLOAD", "TOPIC_REFERENCE", "TOPIC_TRUTH", "TOPICS",
           "UNITS", "Recording", "RecordingError", "source_metadata", "read_recording", "RecordingWriter",
           "write_recording", "write_samples_and_events"]
