"""The recorder: every message on the ``adn/**`` keys into one MCAP file.

An adnmesh recording is an ordinary MCAP file (https://mcap.dev) that Foxglove opens as it is:

- one **schema** record per message type (schema encoding ``jsonschema``, the JSON Schema as
  UTF-8 text, name = the message type),
- one **channel** per key (topic = the Zenoh key, message encoding ``json``),
- one **message** record per message: the JSON payload exactly as it was on the bus,
  ``log_time`` = delivery time, ``publish_time`` = send time (both ns, sim time in sim mode) and
  ``sequence`` = 1, 2, 3, … per channel, in the order the recorder wrote them,
- a **metadata** record :data:`RUN_METADATA` (``"adnmesh.run"``) written first, with the run's
  description (see :data:`RUN_METADATA_KEYS`), and any further records the runtime adds with
  :meth:`Recorder.add_metadata` (e.g. :data:`PUBLISHED_METADATA`, the agents' own counts).

Schema and channel records are written lazily, on the first message of their type or key.
Messages are grouped in zstd-compressed chunks; every ``flush_interval_s`` of wall time the
chunk in progress is closed and written, and the file is flushed and fsync'ed, so that a
recorder killed at any moment (even by SIGKILL) leaves a file whose complete chunks
:func:`adnmesh.recording.read_recording` recovers: all messages written more than about one
flush interval before the kill.
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Mapping
from pathlib import Path

from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from adnmesh import __version__

__all__ = [
    "FORMAT_VERSION",
    "MESSAGE_ENCODING",
    "PUBLISHED_METADATA",
    "RECOVERY_METADATA",
    "RUN_METADATA",
    "RUN_METADATA_KEYS",
    "Recorder",
    "SCHEMA_ENCODING",
]

FORMAT_VERSION = "1"
"""Version of the recording layout described in this module (metadata key ``recording_format``)."""

MESSAGE_ENCODING = "json"
"""MCAP message encoding of every channel."""

SCHEMA_ENCODING = "jsonschema"
"""MCAP schema encoding of every schema."""

RUN_METADATA = "adnmesh.run"
"""Name of the metadata record that describes the run (written when the recorder opens)."""

PUBLISHED_METADATA = "adnmesh.published"
"""Name of the optional metadata record ``{topic: count}`` with what the agents say they
published; ``adnmesh inspect`` compares it with the recording."""

RECOVERY_METADATA = "adnmesh.recovery"
"""Name of the metadata record that :func:`adnmesh.recording.recover` adds to a recovered file."""

RUN_METADATA_KEYS = {
    "run_id": "identifier of the run, also the default file name logs/<run_id>.mcap",
    "config": "the config file's text (YAML), verbatim",
    "config_path": "where the config was read from",
    "config_sha256": "sha256 of the config file, hex",
    "table_sha256": "sha256 of the scheduling table file used, hex",
    "adnmesh_version": "version of adnmesh that recorded (filled in if missing)",
    "seed": "seed of the random streams (ICT channel model)",
    "clock": "'sim' or 'realtime'",
    "t0_ns": "time of the run's start on the recorded time axis, ns (default 0)",
    "recording_format": "FORMAT_VERSION (filled in)",
    "flush_interval_s": "the recorder's flush interval, s (filled in)",
}
"""The keys of the :data:`RUN_METADATA` record and what they hold; all values are strings.
The recorder requires none of them but fills in the ones marked *filled in*."""

_CHUNK_SIZE = 4 * 1024 * 1024  # bytes; chunks are normally closed by the flush timer first


class Recorder:
    """Write bus messages to an MCAP file; thread-safe.

    Parameters
    ----------
    path : str or Path
        The file to create (parent directories are made; an existing file is replaced).
    metadata : dict of str to str
        The run's description, written as the :data:`RUN_METADATA` record (keys: see
        :data:`RUN_METADATA_KEYS`).
    schemas : dict of str to dict
        Message type name -> JSON Schema (draft 2020-12) of its payload. Only types that are
        written get a schema record.
    flush_interval_s : float
        Wall-clock seconds between flushes to disk (> 0). Bounds what a killed run loses.

    Examples
    --------
    >>> rec = Recorder("logs/run.mcap", metadata={"clock": "sim"}, schemas=SCHEMAS)
    >>> rec.write("adn/g/measurement/p_ip", "p_ip", b'{"p_ip_w": 1.0e6}',
    ...           log_time_ns=200_000_000, publish_time_ns=100_000_000)
    >>> rec.close()
    """

    def __init__(
        self,
        path: str | Path,
        *,
        metadata: Mapping[str, str],
        schemas: Mapping[str, Mapping],
        flush_interval_s: float = 1.0,
    ) -> None:
        if not flush_interval_s > 0:
            raise ValueError(f"flush_interval_s must be > 0, got {flush_interval_s!r}")
        bad = {k: v for k, v in metadata.items() if not (isinstance(k, str) and isinstance(v, str))}
        if bad:
            raise TypeError(f"metadata keys and values must be str, got {bad!r}")
        self.path = Path(path)
        self._schemas = {name: json.dumps(schema, sort_keys=True).encode() for name, schema in
                         schemas.items()}
        self._flush_interval_s = float(flush_interval_s)
        run = dict(metadata)
        run.setdefault("adnmesh_version", __version__)
        run.setdefault("recording_format", FORMAT_VERSION)
        run.setdefault("flush_interval_s", f"{self._flush_interval_s:g}")

        self._lock = threading.Lock()
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, schema name)
        self._counts: dict[str, int] = {}
        self._dirty = False
        self._closed = False
        self._failure: BaseException | None = None

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 -- closed in close()
        try:
            self._writer = Writer(self._file, chunk_size=_CHUNK_SIZE,
                                  compression=CompressionType.ZSTD)
            self._writer.start(profile="", library=f"adnmesh {__version__}; {LIBRARY_IDENTIFIER}")
            self._writer.add_metadata(RUN_METADATA, run)
            self._sync()
        except BaseException:
            self._file.close()
            raise
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name="adnmesh-recorder-flush",
                                         daemon=True)
        self._flusher.start()

    # -- writing ---------------------------------------------------------------------------

    def write(self, topic: str, schema_name: str, payload: bytes, *, log_time_ns: int,
              publish_time_ns: int) -> None:
        """Record one message.

        Parameters
        ----------
        topic : str
            The key it was published on, e.g. ``adn/<grid>/der/<id>/state``.
        schema_name : str
            Its message type, a key of ``schemas``. All messages of one topic must share it.
        payload : bytes
            The JSON payload as it was on the bus (recorded unchanged).
        log_time_ns, publish_time_ns : int
            Delivery and send time, ns (>= 0; sim time in sim mode).

        Raises
        ------
        ValueError
            Unknown ``schema_name``, a second type on one topic, or a negative time.
        RuntimeError
            The recorder is closed, or an earlier flush failed (the cause is chained).
        """
        if schema_name not in self._schemas:
            raise ValueError(f"{topic}: unknown message type {schema_name!r}")
        if log_time_ns < 0 or publish_time_ns < 0:
            raise ValueError(f"{topic}: times must be >= 0 ns, got log_time_ns={log_time_ns}, "
                             f"publish_time_ns={publish_time_ns}")
        with self._lock:
            self._check_open()
            channel = self._channels.get(topic)
            if channel is None:
                channel = (self._register(topic, schema_name), schema_name)
                self._channels[topic] = channel
            elif channel[1] != schema_name:
                raise ValueError(f"{topic}: message type {schema_name!r}, but the topic is "
                                 f"recorded as {channel[1]!r}")
            sequence = self._counts.get(topic, 0) + 1
            self._writer.add_message(channel[0], log_time=int(log_time_ns), data=bytes(payload),
                                     publish_time=int(publish_time_ns), sequence=sequence)
            self._counts[topic] = sequence
            self._dirty = True

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Add a metadata record ``name`` (e.g. :data:`PUBLISHED_METADATA`) and flush."""
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise TypeError(f"metadata {name!r}: keys and values must be str")
        with self._lock:
            self._check_open()
            self._writer.add_metadata(name, dict(data))
            self._sync()

    def counts(self) -> dict[str, int]:
        """Return the number of messages written so far, per topic."""
        with self._lock:
            return dict(self._counts)

    def flush(self) -> None:
        """Write everything recorded so far to disk now (the timer does this periodically)."""
        with self._lock:
            self._check_open()
            self._sync()

    def close(self) -> None:
        """Stop the flush timer and finish the file (summary section, indexes, footer).

        Calling it again does nothing. Raises RuntimeError if a periodic flush had failed.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._stop.set()
        self._flusher.join()
        with self._lock:
            try:
                if self._failure is None:
                    self._writer.finish()
                    self._file.flush()
                    os.fsync(self._file.fileno())
            finally:
                self._file.close()
            if self._failure is not None:
                raise RuntimeError(f"{self.path}: recording failed") from self._failure

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # -- internals (called with the lock held) ---------------------------------------------

    def _check_open(self) -> None:
        if self._failure is not None:
            raise RuntimeError(f"{self.path}: recording failed") from self._failure
        if self._closed:
            raise RuntimeError(f"{self.path}: recorder is closed")

    def _register(self, topic: str, schema_name: str) -> int:
        schema_id = self._schema_ids.get(schema_name)
        if schema_id is None:
            schema_id = self._writer.register_schema(schema_name, SCHEMA_ENCODING,
                                                     self._schemas[schema_name])
            self._schema_ids[schema_name] = schema_id
        return self._writer.register_channel(topic, MESSAGE_ENCODING, schema_id)

    def _sync(self) -> None:
        """Close the chunk in progress and push the file to disk."""
        self._writer.flush()
        os.fsync(self._file.fileno())
        self._dirty = False

    def _flush_loop(self) -> None:
        # the fsync happens outside the lock, so that writers are not held up by the disk;
        # close() stops this thread before it closes the file
        while not self._stop.wait(self._flush_interval_s):
            with self._lock:
                if self._closed or self._failure is not None or not self._dirty:
                    continue
                try:
                    self._writer.flush()
                    self._dirty = False
                except BaseException as exc:  # noqa: BLE001 -- reported by write()/close()
                    self._failure = exc
                    continue
            try:
                os.fsync(self._file.fileno())
            except OSError as exc:
                with self._lock:
                    self._failure = exc
