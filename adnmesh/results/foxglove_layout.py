"""A Foxglove layout for a run's recording: the main plots and the event log.

Foxglove opens an adnmesh recording as it is (JSON channels with JSON Schemas, the events as
``foxglove.Log``); :func:`foxglove_layout` arranges it as ``replay`` arranges Rerun: P_IP and
P_ref, the Log panel of the run's events, P_Y, the gains, every DER's infeed and the grid's
extremes. The layout is Foxglove's layout JSON as its app exports it (``configById`` with one
config per panel id ``<type>!<id>``, ``layout`` a tree of splits ``{first, second, direction,
splitPercentage}``, ``globalVariables``, ``userNodes``, ``playbackConfig``): Plot panels
(``paths`` of message paths with ``label``, ``color``, ``enabled``, ``timestampMethod``) and a
Log panel (type ``RosOut``, the legacy name Foxglove keeps: ``topicToRender``, ``minLogLevel``,
``searchTerms``).

Foxglove plots the fields as they are recorded (W, var, 1/W, p.u., %): a layout cannot scale
them. The topics are the bus keys ``adn/<grid>/...``; the message paths are written as
Foxglove writes them (:func:`message_path`: ``adn/g/measurement/p_ip.p_ip_w``). The x axis is
the receive time (the recording's ``log_time``: the delivery time, sim time from the run's
start).

``docs/foxglove-layout.json`` is this layout for the reference case (``configs/simbench.yaml``);
``adnmesh export RUN.mcap --foxglove-layout FILE`` writes the one of any recording.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable

from adnmesh.results.rules import COLORS, der_colors, natural_key
from adnmesh.wire.keys import Keys
from adnmesh.wire.protocol import KINDS

__all__ = ["foxglove_layout", "layout_json", "message_path"]


def _quoted(name: str, plain: str) -> str:
    if re.fullmatch(plain, name):
        return name
    return '"' + re.sub(r'[\\"]', lambda m: "\\" + m.group(0), name) + '"'


def message_path(topic: str, field: str) -> str:
    """Foxglove's message path of ``field`` on ``topic``, written as Foxglove writes it
    (``quoteTopicNameIfNeeded``, ``quoteFieldNameIfNeeded`` of its message-path package): a
    topic of letters, digits, ``_``, ``-`` and ``/`` as it is (``adn/g/measurement/p_ip.p_ip_w``),
    any other in double quotes."""
    return f"{_quoted(topic, r'[a-zA-Z0-9_/-]+')}.{_quoted(field, r'[a-zA-Z0-9_-]+')}"


def _hex(color: tuple[int, int, int]) -> str:
    return "#" + "".join(f"{c:02x}" for c in color)


def _field(kind: str, role: str) -> tuple[str, str, str]:
    """(field, series name, unit) of the series of ``role`` on messages of ``kind`` (the
    protocol table's)."""
    found = next(s for s in KINDS[kind].series if s.role == role)
    return found.field, found.name, found.unit


def _plot(title: str, lines: list[tuple[str, str, str | None]]) -> dict:
    """A Plot panel's config: ``lines`` are (message path, label, colour or None)."""
    paths = []
    for path, label, color in lines:
        line = {"value": path, "enabled": True, "timestampMethod": "receiveTime",
                "label": label}
        if color is not None:
            line["color"] = color
        paths.append(line)
    return {"paths": paths, "showXAxisLabels": True, "showYAxisLabels": True,
            "showLegend": True, "legendDisplay": "floating", "showPlotValuesInLegend": False,
            "isSynced": True, "xAxisVal": "timestamp", "sidebarDimension": 240,
            "foxglovePanelTitle": title}


def _line(keys: Keys, kind: str, role: str, who: str | None = None,
          color: tuple[int, int, int] | None = None,
          name: str | None = None) -> tuple[str, str, str | None]:
    field, series, unit = _field(kind, role)
    label = f"{name or series.format(der=who)} [{unit}]" if unit != "1" else (name or series)
    color = color or COLORS.get(role)
    return message_path(keys.of(kind, who), field), label, None if color is None else _hex(color)


def _split(direction: str, first, second, percentage: float = 50.0) -> dict:
    return {"first": first, "second": second, "direction": direction,
            "splitPercentage": percentage}


def foxglove_layout(grid: str, der_ids: Iterable[str], *, grid_model: bool = True,
                    events_topic: str | None = None, reactive: bool = False) -> dict:
    """The Foxglove layout of a run on grid ``grid`` with DERs ``der_ids`` (see the module
    doc); ``grid_model``: with the grid's extremes; ``events_topic``: the run's ``foxglove.Log``
    topic (default ``adn/<grid>/log``, as ``adnmesh up`` records it); ``reactive``: with the
    Q loop (Q_IP and Q_ref beside P_IP, Q_Y beside P_Y)."""
    keys = Keys(grid)
    ders = sorted(set(der_ids), key=natural_key)
    colors = der_colors(ders)
    config = {
        "Plot!p_ip": _plot("P_IP and P_ref [W]", [_line(keys, "p_ref", "p_ref"),
                                                  _line(keys, "p_ip", "p_ip")]),
        "RosOut!events": {"topicToRender": events_topic or f"{keys.root}/log",
                          "minLogLevel": 1, "searchTerms": []},
        "Plot!p_y": _plot("P_Y [p.u. of w·P_inst]", [_line(keys, "p_y", "p_y")]),
        "Plot!gains": _plot("gains: K_P [1/W], K_I [1/(W s)]", [_line(keys, "p_y", "kp"),
                                                               _line(keys, "p_y", "ki")]),
        "Plot!ders": _plot("DER infeed [W]", [
            _line(keys, "der_state", "der_infeed", der, colors[der]) for der in ders]),
    }
    top, outputs = "Plot!p_ip", "Plot!p_y"
    if reactive:
        config["Plot!q_ip"] = _plot("Q_IP and Q_ref [var]", [_line(keys, "q_ref", "q_ref"),
                                                             _line(keys, "p_ip", "q_ip")])
        config["Plot!q_y"] = _plot("Q_Y [p.u. of w·C^Q]", [_line(keys, "q_y", "q_y")])
        top = _split("column", "Plot!p_ip", "Plot!q_ip", 60.0)
        outputs = _split("column", "Plot!p_y", "Plot!q_y", 50.0)
    ders_and_grid: object = "Plot!ders"
    if grid_model:
        config["Plot!voltages"] = _plot("grid: bus voltage extremes [p.u.]", [
            _line(keys, "grid_state", "grid_v_min"), _line(keys, "grid_state", "grid_v_max")])
        config["Plot!loadings"] = _plot("grid: highest loadings [%]", [
            _line(keys, "grid_state", "grid_line_loading"),
            _line(keys, "grid_state", "grid_trafo_loading")])
        ders_and_grid = _split("row", "Plot!ders",
                               _split("column", "Plot!voltages", "Plot!loadings"), 55.0)
    layout = _split("column",
                    _split("row", top, "RosOut!events", 62.0),
                    _split("column", _split("row", outputs, "Plot!gains"), ders_and_grid,
                           40.0),
                    38.0)
    return {"configById": config, "globalVariables": {}, "userNodes": {},
            "playbackConfig": {"speed": 1}, "layout": layout}


def layout_json(layout: dict) -> str:
    """``layout`` as the text of a layout file (indented, ends with a newline)."""
    return json.dumps(layout, indent=2, ensure_ascii=False) + "\n"
