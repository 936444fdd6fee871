"""Test helper: a Rerun .rrd file read back with rerun's own reader, as columns."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

__all__ = ["rrd_columns"]


def rrd_columns(path: Path, reader=None) -> dict[str, dict[str, list]]:
    """Entity path -> column -> values of the data recording in ``path`` (durations as int
    ns); ``reader``: an ``RrdReader`` of it already open."""
    from rerun.chunk import RrdReader

    columns: dict[str, dict[str, list]] = {}
    for chunk in (reader or RrdReader(path)).stream():
        batch = chunk.to_record_batch()
        entity = columns.setdefault(chunk.entity_path, {})
        for name in batch.schema.names:
            column = batch.column(name)
            if pa.types.is_duration(column.type):
                column = column.cast(pa.int64())
            entity.setdefault(name, []).extend(column.to_pylist())
    return columns
