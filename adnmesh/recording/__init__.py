"""Recording runs to MCAP and reading them back.

- :class:`Recorder` writes every bus message of a run to an MCAP file (JSON payloads with their
  JSON Schemas, so Foxglove opens it), flushing periodically so a killed run stays readable.
- :func:`read_recording` reads a recording, complete or truncated; :func:`recover` turns a
  truncated one into a complete file.
- :func:`validate_recording` checks messages against their schemas; :func:`check_counts`
  compares what agents published with what was recorded.
- :mod:`~adnmesh.recording.foxglove_log`: the ``foxglove.Log`` format of the events topic.
- :mod:`~adnmesh.recording.mcap_records`: the file's records as both readers take them, and
  the one set of words (:class:`RecordingError`) for a file that is no readable recording.

This package is the file format only; what a run's messages mean (series, events, figures)
is :mod:`adnmesh.results`, which reads recordings through it.
"""

from adnmesh.recording.reader import (
    ChannelInfo,
    RecordedMessage,
    Recording,
    RecordingError,
    read_recording,
    recover,
)
from adnmesh.recording.validate import (
    CountDifference,
    RecordingLossError,
    check_counts,
    count_differences,
    validate_recording,
)
from adnmesh.recording.writer import (
    PUBLISHED_METADATA,
    RECOVERY_METADATA,
    RUN_METADATA,
    RUN_METADATA_KEYS,
    UNCOUNTED_METADATA,
    Recorder,
)

__all__ = [
    "ChannelInfo",
    "CountDifference",
    "PUBLISHED_METADATA",
    "RECOVERY_METADATA",
    "RUN_METADATA",
    "RUN_METADATA_KEYS",
    "RecordedMessage",
    "Recorder",
    "Recording",
    "RecordingError",
    "RecordingLossError",
    "UNCOUNTED_METADATA",
    "check_counts",
    "count_differences",
    "read_recording",
    "recover",
    "validate_recording",
]
