"""Modbus TCP with the SunSpec DER information models: a device simulator's server and the
gateway's link. pymodbus carries Modbus (TCP, or TLS: Modbus/TCP Security); the register layout
(point offsets, types, scale-factor points, symbols) comes from pysunspec2's model definitions.

The map
    Holding registers from :data:`BASE_ADDRESS` (40000): the ``SunS`` marker, then each model as
    its ID, its length L and L registers, then the end model (ID 0xFFFF, L 0).
    :class:`SunSpecServer` serves :data:`SERVED_MODELS`: 1 (common: Mn ``adnmesh``, Md ``DER
    simulator``, SN the DER's id), 701 (DER AC measurement), 702 (capacity: the DER's ratings),
    704 (DER AC controls) and 122 (measurement status). Points not named here read as
    SunSpec's "not implemented" value.

Measurement (701, 122)
    Computed from :meth:`RealtimePlant.read` at the moment a request reads the map: 701's W,
    Var, VA, ConnSt and St, 122's PVConn and ECPConn (CONNECTED etc.) and Tms, the model time
    in whole seconds.

Controls (704)
    Only WSetEna, WSetMod, WSet, VarSetEna, VarSetMod and VarSet are writable; writing any
    other register is answered ILLEGAL DATA ADDRESS. The plant's active power set-point is
    WSet while WSetEna is ENABLED, else its available power (no limit); its reactive one is
    VarSet while VarSetEna is ENABLED, else 0 var (unity power factor). Only the absolute modes
    are supported: a write that leaves WSetMod other than WATTS or VarSetMod other than VARS,
    or an enable other than DISABLED/ENABLED, is answered ILLEGAL DATA VALUE and changes
    nothing. A write touching a function's points applies that function at once
    (:meth:`RealtimePlant.write`). The device starts with both functions enabled at the plant's
    set-points (its schedule) and keeps its controls over a restart (:meth:`SunSpecServer.stop`,
    :meth:`SunSpecServer.start`). VarSetPri (read-only) says the config's reactive priority.

Scale factors
    Each scale factor of the server is the finest (not below -3, mW) whose point type holds
    1.2 times the rating of every point it scales: P_inst for W, WSet, WMaxRtg;
    S_inst for Var, VA, VarSet and the var and VA ratings. The reference case's 2 MW WT gets
    W_SF = 2 (int16, 100 W steps) and WSet_SF = -2 (int32, 10 mW steps). A value beyond its
    type saturates. :attr:`SunSpecServer.scale_factors` lists them.

Faults (:class:`~adnmesh.devices.faults.DeviceFaults`, read at each request)
    ``refuse_writes``: every write is answered SERVER DEVICE FAILURE, nothing is taken;
    ``silent``: every request is read and dropped unanswered (pymodbus's ``trace_pdu`` hook
    hands the server no request); ``frozen``: W, Var, VA and Tms keep their last values;
    ``disconnected``: ConnSt DISCONNECTED, St OFF, PVConn 0, ECPConn DISCONNECTED.

The link
    :class:`SunSpecLink` scans the map from 40000 for the models of its :class:`SunSpecPoints`,
    reads their scale factors once (they are static) and enables the set-points' functions
    (the ``<point>Mod`` point to the absolute mode, then ``<point>Ena`` to ENABLED). A read is
    one request per model of the measured points (701 and 122 by default), a write one request
    per set-point. Every call is bounded by ``timeout_s``: pymodbus retries nothing and each
    request waits at most what is left of the call. Errors: no connection, or one refused,
    reset or closed -> ``unreachable`` (a failed TLS handshake too); no answer in time ->
    ``timeout``; an exception response to a write -> ``refused``; no marker, a missing or short
    model, an exception response to a read, a point "not implemented", an undecodable answer,
    a set-point beyond its point's type -> ``malformed``. After an error but ``refused`` the
    connection is closed: :meth:`SunSpecLink.connect` opens it again.
"""

from __future__ import annotations

import asyncio
import functools
import math
import socket
import ssl
import struct
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, fields

from pymodbus.client import ModbusTcpClient, ModbusTlsClient
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.server import ModbusTcpServer, ModbusTlsServer
from pymodbus.simulator import DataType, SimData, SimDevice
from sunspec2.device import Model
from sunspec2.mdef import END_MODEL_ID

from adnmesh.config import SunSpecPointNames
from adnmesh.devices.faults import DeviceFaults
from adnmesh.devices.link import DeviceError, Reading

__all__ = ["BASE_ADDRESS", "SERVED_MODELS", "SunSpecLink", "SunSpecPoints", "SunSpecServer"]

BASE_ADDRESS = 40000
"""Modbus address of the SunSpec marker; the models follow it."""
SERVED_MODELS = (1, 701, 702, 704, 122)
"""The models :class:`SunSpecServer` serves by default, in map order."""

_MARKER = [0x5375, 0x6E53]    # "SunS"
_HEADROOM = 1.2               # a scale factor holds this many times its points' ratings
_FINEST_SF = -3
_RANGE = {"int16": (-32767, 32767), "uint16": (0, 65534),
          "int32": (-2**31 + 1, 2**31 - 1), "uint32": (0, 2**32 - 2)}
"""The integer types a power or time point may have, and their values (SunSpec's "not
implemented" values excluded)."""
_UNITS = {"p_set": "W", "q_set": "Var", "p_meas": "W", "q_meas": "Var", "stamp": "Secs"}
"""The units of each :class:`SunSpecPoints` point but ``status`` (as the definitions spell
them)."""
_ABSOLUTE_MODE = {"W": "WATTS", "Var": "VARS"}
"""The mode symbol of a set-point function in absolute units, by the set-point's units."""
_FUNCTIONS = {"p_w": "704.WSet", "q_var": "704.VarSet"}
"""The set-point functions the server implements, by their keyword of RealtimePlant.write."""


# -- the model definitions ------------------------------------------------------------------


@functools.cache
def _model(model_id: int) -> Model:
    """pysunspec2's model ``model_id`` without values: its points' offsets (registers from its
    ID point), lengths, types and definitions. Shared: never given values."""
    model = Model(model_id)
    if model.gdef is None:
        raise ValueError(f"no SunSpec model {model_id}")
    return model


def _point(text: str):
    """The pysunspec2 point of ``"model.point"`` (a point of the model's top-level group).

    Raises
    ------
    ValueError
        Not such a text, no such model or no such point.
    """
    model_id, _, name = text.partition(".")
    if not (model_id.isdigit() and name):
        raise ValueError("not 'model.point'")
    point = _model(int(model_id)).points.get(name)
    if point is None:
        raise ValueError(f"model {model_id} has no point {name!r}")
    return point


def _has(text: str) -> bool:
    """Whether the point ``"model.point"`` is defined (of a defined model)."""
    model_id, _, name = text.partition(".")
    return name in _model(int(model_id)).points


def _model_of(text: str) -> int:
    """The model id of ``"model.point"``."""
    return int(text.partition(".")[0])


def _symbol(text: str, name: str) -> int | None:
    """The value of the symbol ``name`` of the point ``text``; None if it has none."""
    return next((s["value"] for s in _point(text).pdef.get("symbols", ()) if s["name"] == name),
                None)


def _absolute_mode(text: str) -> int | None:
    """The value of the absolute mode (WATTS, VARS) of the ``<point>Mod`` of the set-point
    ``text``; None if it has none."""
    return _symbol(text + "Mod", _ABSOLUTE_MODE[_point(text).pdef["units"]])


def _bits(text: str, *names: str) -> int:
    """The bitfield ``text`` with the bits of the symbols ``names`` set."""
    return sum(1 << _symbol(text, name) for name in names)


def _decode(point, registers) -> int | str:
    """The raw value of ``point`` from its registers."""
    return point.info.data_to(struct.pack(f">{len(registers)}H", *registers))


def _encode(point, raw) -> list[int]:
    """The registers of ``point`` holding the raw value ``raw``."""
    return list(struct.unpack(f">{point.len}H", point.info.to_data(raw, point.len * 2)))


def _scaled(raw: int, sf: int) -> float:
    """``raw * 10**sf`` (dividing by an exact power of ten when ``sf < 0``)."""
    return float(raw * 10 ** sf) if sf >= 0 else raw / 10 ** -sf


def _unscaled(value: float, sf: int) -> int:
    """The raw value nearest to ``value / 10**sf``."""
    return round(value / 10 ** sf) if sf >= 0 else round(value * 10 ** -sf)


def _fit(point_type: str, magnitude: float) -> int:
    """The finest scale factor (not below -3) at which ``point_type`` holds
    ``_HEADROOM * magnitude``."""
    sf = _FINEST_SF
    while _HEADROOM * abs(magnitude) > _RANGE[point_type][1] * 10.0 ** sf:
        sf += 1
    return sf


# -- the points -----------------------------------------------------------------------------

_CONFIG_DEFAULTS = SunSpecPointNames()
"""The points a DER's ``plant.points`` names unless it says otherwise: the defaults here too."""


@dataclass(frozen=True)
class SunSpecPoints:
    """The SunSpec points the gateway uses, as ``"model.point"`` of the model definitions.

    Attributes
    ----------
    p_set, q_set : str
        Active power set-point, W, and reactive one, var: writable integer points in W and var;
        a ``<point>Ena`` point of the model is enabled and a ``<point>Mod`` point set to its
        absolute mode (WATTS, VARS) at connect.
    p_meas, q_meas : str
        Measured active power, W, and reactive power, var: integer points in W and var.
    status : str
        The connection status: an enum16 point with a CONNECTED symbol.
    stamp : str or None
        The measurement's time stamp, s: an integer point in seconds (None: no staleness check).

    Raises
    ------
    ValueError
        One line naming the first point that is none of these. (Such points of one model are
        always within one Modbus read, 125 registers: a read is one request per model.)
    """

    p_set: str = _CONFIG_DEFAULTS.p_set
    q_set: str = _CONFIG_DEFAULTS.q_set
    p_meas: str = _CONFIG_DEFAULTS.p_meas
    q_meas: str = _CONFIG_DEFAULTS.q_meas
    status: str = _CONFIG_DEFAULTS.status
    stamp: str | None = _CONFIG_DEFAULTS.stamp

    def __post_init__(self) -> None:
        for field in fields(self):
            text = getattr(self, field.name)
            if text is None and field.name == "stamp":
                continue
            problem = _problem(field.name, text)
            if problem is not None:
                raise ValueError(f"SunSpecPoints.{field.name} {text!r}: {problem}")

    def measured(self) -> tuple[str, ...]:
        """The points :meth:`SunSpecLink.read` reads."""
        return tuple(t for t in (self.p_meas, self.q_meas, self.status, self.stamp)
                     if t is not None)

    def models(self) -> set[int]:
        """The models the points are in."""
        return {_model_of(t) for t in (self.p_set, self.q_set, *self.measured())}


def _problem(role: str, text: str) -> str | None:
    """Why ``text`` cannot be the point ``role`` of :class:`SunSpecPoints`; None if it can."""
    try:
        point = _point(text)
    except ValueError as exc:
        return str(exc)
    pdef = point.pdef
    if role == "status":
        if pdef["type"] != "enum16" or _symbol(text, "CONNECTED") is None:
            return "not an enum16 point with a CONNECTED value"
        return None
    units = _UNITS[role]
    if pdef["type"] not in _RANGE or pdef.get("units") != units:
        return f"not an integer point in {units}"
    if role in ("p_set", "q_set"):
        if pdef.get("access") != "RW":
            return "not writable"
        for suffix, symbol in (("Mod", _ABSOLUTE_MODE[units]), ("Ena", "ENABLED")):
            if _has(text + suffix) and _symbol(text + suffix, symbol) is None:
                return f"its {text + suffix} has no {symbol} value"
    return None


def _spans(texts) -> dict[int, tuple[int, int]]:
    """``{model: (first offset, end offset)}`` of the registers of the points ``texts``."""
    spans: dict[int, tuple[int, int]] = {}
    for text in texts:
        point = _point(text)
        first, end = spans.get(_model_of(text), (point.offset, point.offset + point.len))
        spans[_model_of(text)] = (min(first, point.offset), max(end, point.offset + point.len))
    return spans


# -- the server -----------------------------------------------------------------------------


class SunSpecServer:
    """A DER's plant as a SunSpec device on Modbus TCP (see the module docstring).

    Parameters
    ----------
    plant : RealtimePlant
        The plant it serves.
    host : str
        Address to listen on.
    port : int
        TCP port (0: a free one, kept over restarts; see :attr:`port`).
    unit_id : int
        Its Modbus unit id.
    tls : (certfile, keyfile), optional
        Serve Modbus/TCP Security (TLS 1.2+) with this certificate and key (PEM).
    faults : DeviceFaults, optional
        The faults it plays (default: none, a new :class:`DeviceFaults`).
    models : tuple of int
        The models it serves, in map order (default :data:`SERVED_MODELS`; tests leave some
        out).

    Attributes
    ----------
    scale_factors : dict of str to int
        ``{"model.X_SF": exponent}`` of the scale-factor points it serves.
    """

    def __init__(self, plant, host: str = "127.0.0.1", port: int = 0, unit_id: int = 1,
                 tls: tuple[str, str] | None = None, faults: DeviceFaults | None = None,
                 models: tuple[int, ...] = SERVED_MODELS) -> None:
        self.plant = plant
        self.host = host
        self.unit_id = unit_id
        self.tls = tls
        self.faults = DeviceFaults() if faults is None else faults
        self._port = port
        self._starts: dict[int, int] = {}
        address = BASE_ADDRESS + len(_MARKER)
        for model_id in models:
            self._starts[model_id] = address
            address += _model(model_id).len
        self.scale_factors = self._fit_scale_factors()
        setpoints = {"p_w": plant.p_setpoint_w, "q_var": plant.q_setpoint_var}
        self._controls = {}
        for keyword, text in _FUNCTIONS.items():
            self._controls |= {text + "Ena": _symbol(text + "Ena", "ENABLED"),
                               text + "Mod": _absolute_mode(text),
                               text: self._raw(text, setpoints[keyword])}
        self._measured: dict[str, int] = {}
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping: asyncio.Event | None = None

    @property
    def port(self) -> int:
        """The TCP port (the one bound once started with port 0)."""
        return self._port

    def start(self) -> None:
        """Listen, on a thread of its own; return once it does.

        Raises
        ------
        OSError
            It cannot listen on host:port (or read its certificate).
        RuntimeError
            It is already running.
        """
        if self._thread is not None:
            raise RuntimeError("the SunSpec server is already running")
        sslctx = None
        if self.tls is not None:
            sslctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            sslctx.minimum_version = ssl.TLSVersion.TLSv1_2
            sslctx.load_cert_chain(*self.tls)
        device = SimDevice(self.unit_id, simdata=self._simdata(), action=self._on_request)
        listening = threading.Event()
        self._thread = threading.Thread(target=asyncio.run,
                                        args=(self._serve(device, sslctx, listening),),
                                        name=f"sunspec-{self.plant.der.id}", daemon=True)
        self._thread.start()
        listening.wait()
        if self._loop is None:
            self._thread.join()
            self._thread = None
            with socket.create_server((self.host, self._port)):   # raises what stopped pymodbus
                pass
            raise OSError(f"cannot listen on {self.host}:{self._port}")

    def stop(self) -> None:
        """Close the listener and every connection, end its thread (nothing if not running)."""
        if self._thread is None:
            return
        self._loop.call_soon_threadsafe(self._stopping.set)
        self._thread.join()
        self._thread = self._loop = self._stopping = None

    def __enter__(self) -> SunSpecServer:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    async def _serve(self, device: SimDevice, sslctx, listening: threading.Event) -> None:
        """Serve until :meth:`stop`; set ``listening`` once it listens (or failed to)."""
        try:
            server = await self._listen(device, sslctx)
        finally:
            listening.set()
        if server is None:
            return
        await self._stopping.wait()
        for connection in server.active_connections.values():
            if connection.transport is not None:   # None: its TLS handshake failed
                connection.transport.abort()       # at once: TLS would await the client's goodbye
        await server.shutdown()

    async def _listen(self, device: SimDevice, sslctx) -> ModbusTcpServer | None:
        """A pymodbus server of ``device`` listening on host:port; None if it cannot."""
        where = {"address": (self.host, self._port), "trace_pdu": self._on_pdu}
        server = ModbusTcpServer(device, **where) if sslctx is None else \
            ModbusTlsServer(device, sslctx=sslctx, **where)
        try:
            await server.serve_forever(background=True)
        except RuntimeError:                    # pymodbus could not listen (it logs why)
            return None
        self._port = server.transport.sockets[0].getsockname()[1]
        self._stopping = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        return server

    def _on_pdu(self, sending: bool, pdu):
        """pymodbus's hook on every PDU: a silent device hands the server no request."""
        return None if self.faults.silent and not sending else pdu

    async def _on_request(self, function_code: int, start: int, address: int, count: int,
                          registers: list[int], values: list[int] | None) -> ExcCodes | None:
        """pymodbus's action on every request (before it answers from ``registers``, which
        begin at address ``start``): a read refreshes the measurement, a write applies 704."""
        if values is None:
            for text, raw in self._refresh().items():
                self._put(registers, start, text, raw)
            return None
        if self.faults.refuse_writes:
            return ExcCodes.DEVICE_FAILURE
        after = registers.copy()
        after[address - start:address - start + len(values)] = values
        return self._apply(after, start, range(address, address + len(values)))

    def _apply(self, registers: list[int], start: int, written: range) -> ExcCodes | None:
        """Take the set-point functions whose points ``written`` touches from ``registers``
        (the map after the write) to the plant; ILLEGAL_VALUE for an unsupported state."""
        released = {"p_w": self.plant.p_avail_w, "q_var": 0.0}
        controls, targets = dict(self._controls), {}
        for keyword, text in _FUNCTIONS.items():
            texts = (text + "Ena", text + "Mod", text)
            if not any(a in written for t in texts for a in self._addresses(t)):
                continue
            controls |= {t: self._get(registers, start, t) for t in texts}
            enable, mode, setpoint = (controls[t] for t in texts)
            enabled = _symbol(texts[0], "ENABLED")
            if enable not in (enabled, _symbol(texts[0], "DISABLED")) or \
                    mode != _absolute_mode(text):
                return ExcCodes.ILLEGAL_VALUE
            targets[keyword] = self._value(text, setpoint) if enable == enabled else \
                released[keyword]
        self.plant.write(**targets)
        self._controls = controls
        return None

    def _refresh(self) -> dict[str, int]:
        """The raw values of the live points now (see the module docstring), kept for the next
        start."""
        on = not self.faults.disconnected
        self._measured |= {
            "701.ConnSt": _symbol("701.ConnSt", "CONNECTED" if on else "DISCONNECTED"),
            "701.St": _symbol("701.St", "ON" if on else "OFF"),
            "122.PVConn": _bits("122.PVConn", "CONNECTED", "AVAILABLE", "OPERATING") if on else 0,
            "122.ECPConn": _bits("122.ECPConn", "CONNECTED" if on else "DISCONNECTED")}
        if not self.faults.frozen or "701.W" not in self._measured:
            p_w, q_var, t_s = self.plant.read()
            self._measured |= {"701.W": self._raw("701.W", p_w),
                               "701.Var": self._raw("701.Var", q_var),
                               "701.VA": self._raw("701.VA", math.hypot(p_w, q_var)),
                               "122.Tms": int(t_s)}
        return self._measured

    def _static(self) -> dict[str, int | str]:
        """The raw values of the points that do not change."""
        der = self.plant.der
        return {"1.Mn": "adnmesh", "1.Md": "DER simulator", "1.SN": der.id,
                "1.DA": self.unit_id,
                "701.ACType": _symbol("701.ACType", "THREE_PHASE"),
                "702.CtrlModes": _bits("702.CtrlModes", "FIXED_W", "FIXED_VAR"),
                "704.VarSetPri": _symbol("704.VarSetPri",
                                         "ACTIVE" if self.plant.priority == "p" else "REACTIVE"),
                "122.StorConn": 0,
                **{text: self._raw(text, value) for text, value in self._ratings().items()},
                **self.scale_factors}

    def _ratings(self) -> dict[str, float]:
        """702's ratings (and settings, equal to them) of the DER, W, VA, var."""
        der, cap = self.plant.der, self.plant.capability
        return {f"702.{name}{suffix}": value for suffix in ("Rtg", "")
                for name, value in (("WMax", der.p_inst_w), ("VAMax", cap.s_va),
                                    ("VarMaxInj", cap.q_max_var),
                                    ("VarMaxAbs", -cap.q_min_var))}

    def _fit_scale_factors(self) -> dict[str, int]:
        """The exponent of every scale-factor point of the served points (module docstring)."""
        der = self.plant.der
        p_w, s_va = der.p_inst_w, self.plant.capability.s_va
        magnitudes = {"701.W": p_w, "701.Var": s_va, "701.VA": s_va,
                      "704.WSet": p_w, "704.VarSet": s_va, **self._ratings()}
        factors: dict[str, int] = {}
        for text, magnitude in magnitudes.items():
            point = _point(text)
            sf_text = f"{_model_of(text)}.{point.sf}"
            factors[sf_text] = max(factors.get(sf_text, _FINEST_SF),
                                   _fit(point.pdef["type"], magnitude))
        return factors

    def _raw(self, text: str, value: float) -> int:
        """The raw value of the scaled point ``text`` for ``value`` (W, var, VA), saturated."""
        point = _point(text)
        low, high = _RANGE[point.pdef["type"]]
        sf = self.scale_factors[f"{_model_of(text)}.{point.sf}"]
        return min(max(_unscaled(value, sf), low), high)

    def _value(self, text: str, raw: int) -> float:
        """The value (W, var) of the raw value of the scaled point ``text``."""
        return _scaled(raw, self.scale_factors[f"{_model_of(text)}.{_point(text).sf}"])

    def _addresses(self, text: str) -> range:
        """The Modbus addresses of the point ``text`` (empty if its model is not served)."""
        if _model_of(text) not in self._starts:
            return range(0)
        point = _point(text)
        first = self._starts[_model_of(text)] + point.offset
        return range(first, first + point.len)

    def _put(self, registers: list[int], start: int, text: str, raw) -> None:
        """Write the raw value of ``text`` into ``registers`` (which begin at ``start``)."""
        where = self._addresses(text)
        if where:
            registers[where.start - start:where.stop - start] = _encode(_point(text), raw)

    def _get(self, registers: list[int], start: int, text: str) -> int:
        """The raw value of ``text`` in ``registers`` (which begin at ``start``)."""
        where = self._addresses(text)
        return _decode(_point(text), registers[where.start - start:where.stop - start])

    def _simdata(self) -> list[SimData]:
        """The map as pymodbus register blocks: the control points writable, the rest not."""
        image = list(_MARKER)
        for model_id in self._starts:
            image += _encode_model(model_id)
        image += [END_MODEL_ID, 0]
        for text, raw in (self._static() | self._controls | self._refresh()).items():
            self._put(image, BASE_ADDRESS, text, raw)
        writable = {a - BASE_ADDRESS for t in self._controls for a in self._addresses(t)}
        blocks, first = [], 0
        for i in range(1, len(image) + 1):
            if i == len(image) or (i in writable) != (first in writable):
                blocks.append(SimData(BASE_ADDRESS + first, values=image[first:i],
                                      datatype=DataType.REGISTERS, readonly=first not in writable))
                first = i
        return blocks


def _encode_model(model_id: int) -> list[int]:
    """The registers of model ``model_id`` with its ID and L and every other point "not
    implemented"."""
    data = _model(model_id).get_mb()
    return list(struct.unpack(f">{len(data) // 2}H", data))


# -- the link -------------------------------------------------------------------------------


class _TlsClient(ModbusTlsClient):
    """pymodbus's TLS client, checking the device's certificate against the host it dials
    (pymodbus 3.16 wraps its socket without a server name, which a checking context
    refuses)."""

    def connect(self) -> bool:
        """Connect and shake hands; False if either fails."""
        if self.socket is None:
            params = self.comm_params
            try:
                sock = socket.create_connection((params.host, params.port),
                                                timeout=params.timeout_connect)
                self.socket = params.sslctx.wrap_socket(sock, server_hostname=params.host)
            except OSError:
                self.close()
        return self.socket is not None


class SunSpecLink:
    """A SunSpec device on Modbus TCP as a :class:`~adnmesh.devices.link.DeviceLink` (see the
    module docstring).

    Parameters
    ----------
    host : str
        The device's host name or address.
    port : int
        Its TCP port.
    unit_id : int
        Its Modbus unit id.
    timeout_s : float
        Longest duration of one call (connect, write, read), s.
    points : SunSpecPoints
        The points used.
    tls : (cafile, certfile or None, keyfile or None), optional
        Modbus/TCP Security: the CA the device's certificate must chain to (and name the host
        dialled), and the link's own certificate and key if the device asks for one (PEM).

    Attributes
    ----------
    model_addresses : dict of int to int
        ``{model id: Modbus address of its ID point}`` of the models used, found by
        :meth:`connect`.
    """

    def __init__(self, host: str, port: int, unit_id: int = 1, timeout_s: float = 1.0,
                 points: SunSpecPoints = SunSpecPoints(),
                 tls: tuple[str, str | None, str | None] | None = None) -> None:
        self.host = host
        self.port = port
        self.unit_id = unit_id
        self.timeout_s = timeout_s
        self.points = points
        self.tls = tls
        self.model_addresses: dict[int, int] = {}
        self._scale: dict[str, int] = {}
        self._client: ModbusTcpClient | None = None
        self._deadline = 0.0

    def connect(self) -> None:
        """Connect (again), scan the map, read the scale factors, enable the set-points.
        Raises :class:`DeviceError` (OSError if the TLS files cannot be read)."""
        self.close()
        self._client = self._new_client()
        with self._call():
            if not self._client.connect():
                raise DeviceError("unreachable", f"no connection to {self.host}:{self.port}")
            self.model_addresses = self._scan()
            self._scale = self._read_scale_factors()
            for text in (self.points.p_set, self.points.q_set):
                self._enable(text)

    def write(self, p_w: float, q_var: float | None) -> None:
        """Write the active power set-point, W, and, if not None, the reactive one, var.
        Raises :class:`DeviceError`."""
        with self._call():
            self._write_value(self.points.p_set, p_w)
            if q_var is not None:
                self._write_value(self.points.q_set, q_var)

    def read(self) -> Reading:
        """Read the measured infeed, the connection status and the time stamp. Raises
        :class:`DeviceError`."""
        points = self.points
        with self._call():
            raw = self._read_points(points.measured())
        return Reading(p_w=self._value(points.p_meas, raw), q_var=self._value(points.q_meas, raw),
                       connected=raw[points.status] == _symbol(points.status, "CONNECTED"),
                       stamp=None if points.stamp is None else self._value(points.stamp, raw))

    def close(self) -> None:
        """Close the connection (never raises)."""
        if self._client is not None:
            self._client.close()
            self._client = None

    def _new_client(self) -> ModbusTcpClient:
        """A pymodbus client that retries nothing."""
        if self.tls is None:
            return ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0)
        cafile, certfile, keyfile = self.tls
        sslctx = ssl.create_default_context(cafile=cafile)
        sslctx.minimum_version = ssl.TLSVersion.TLSv1_2
        if certfile is not None:
            sslctx.load_cert_chain(certfile, keyfile)
        return _TlsClient(self.host, port=self.port, sslctx=sslctx, timeout=self.timeout_s,
                          retries=0)

    @contextmanager
    def _call(self):
        """One call: its deadline; after an error but a refusal, the connection is closed."""
        if self._client is None:
            raise DeviceError("unreachable", f"not connected to {self.host}:{self.port}")
        self._deadline = time.monotonic() + self.timeout_s
        try:
            yield
        except DeviceError as exc:
            if exc.reason != "refused":
                self.close()
            raise

    def _request(self, what: str, send):
        """``send(client)``'s response, waiting at most what is left of the call."""
        left_s = self._deadline - time.monotonic()
        if left_s <= 0:
            raise DeviceError("timeout", f"{what}: the call took its {self.timeout_s:g} s")
        self._client.comm_params.timeout_connect = left_s     # the wait for this answer
        try:
            return send(self._client)
        except ConnectionException as exc:
            raise DeviceError("unreachable", f"{what}: {exc.string}") from None
        except ModbusIOException as exc:
            if exc.fcode is None:                # an answer pymodbus could not decode
                raise DeviceError("malformed", f"{what}: {exc.string}") from None
            raise DeviceError("timeout", f"{what}: no answer within {self.timeout_s:g} s") \
                from None
        except ModbusException as exc:
            raise DeviceError("malformed", f"{what}: {exc.string}") from None
        except TimeoutError:
            raise DeviceError("timeout", f"{what}: no answer within {self.timeout_s:g} s") \
                from None
        except OSError as exc:
            raise DeviceError("unreachable", f"{what}: {exc}") from None

    def _read(self, address: int, count: int, what: str) -> list[int]:
        """``count`` holding registers from ``address``."""
        response = self._request(what, lambda c: c.read_holding_registers(
            address, count=count, device_id=self.unit_id))
        if response.isError() or len(response.registers) != count:
            raise DeviceError("malformed", f"{what}: {response}")
        return response.registers

    def _write_point(self, text: str, raw: int) -> None:
        """Write the raw value of ``text``; "refused" if the device answers an exception."""
        point = _point(text)
        address = self.model_addresses[_model_of(text)] + point.offset
        response = self._request(f"write {text}", lambda c: c.write_registers(
            address, _encode(point, raw), device_id=self.unit_id))
        if response.isError():
            raise DeviceError("refused", f"write {text}: exception code "
                                         f"{response.exception_code}")

    def _scan(self) -> dict[int, int]:
        """Walk the map from the marker until every model used is found."""
        needed, found = self.points.models(), {}
        first = self._read(BASE_ADDRESS, 4, f"the SunSpec marker at {BASE_ADDRESS}")
        if first[:2] != _MARKER:
            raise DeviceError("malformed", f"no SunSpec marker at {BASE_ADDRESS}")
        (model_id, length), address = first[2:], BASE_ADDRESS + 2
        while model_id != END_MODEL_ID and not needed <= found.keys():
            if model_id in needed:
                found[model_id] = address
                self._check_length(model_id, length)
            address += 2 + length
            if address > 0xFFFF - 1:
                raise DeviceError("malformed", "the SunSpec model chain leaves the address space")
            model_id, length = self._read(address, 2, f"the model header at {address}")
        missing = sorted(needed - found.keys())
        if missing:
            raise DeviceError("malformed", f"no SunSpec model {', '.join(map(str, missing))} "
                                           f"in the map of {self.host}:{self.port}")
        return found

    def _check_length(self, model_id: int, length: int) -> None:
        """Raise "malformed" if model ``model_id`` of length ``length`` lacks a point used."""
        for text in (self.points.p_set, self.points.q_set, *self.points.measured()):
            point = _point(text)
            if _model_of(text) == model_id and point.offset + point.len > 2 + length:
                raise DeviceError("malformed", f"model {model_id} of length {length} has no "
                                               f"{text}")

    def _read_scale_factors(self) -> dict[str, int]:
        """``{"model.point": exponent}`` of the points used (0: no scale factor)."""
        texts = (self.points.p_set, self.points.q_set, *self.points.measured())
        sf_of = {t: f"{_model_of(t)}.{_point(t).sf}" for t in texts if _point(t).sf is not None}
        raw = self._read_points(set(sf_of.values()))
        for sf_text, sf in raw.items():
            if not -10 <= sf <= 10:
                raise DeviceError("malformed", f"{sf_text} = {sf}: not a scale factor")
        return {t: raw[sf_of[t]] if t in sf_of else _point(t).sf_value or 0 for t in texts}

    def _read_points(self, texts) -> dict[str, int]:
        """The raw values of the points ``texts``: one read per model."""
        raw = {}
        for model_id, (first, end) in _spans(texts).items():
            registers = self._read(self.model_addresses[model_id] + first, end - first,
                                   f"model {model_id}")
            for text in texts:
                point = _point(text)
                if _model_of(text) == model_id:
                    at = point.offset - first
                    raw[text] = _decode(point, registers[at:at + point.len])
                    if not point.info.is_impl(raw[text]):
                        raise DeviceError("malformed", f"{text} is not implemented")
        return raw

    def _enable(self, text: str) -> None:
        """Set the function of the set-point ``text`` to its absolute mode and enable it."""
        if _has(text + "Mod"):
            self._write_point(text + "Mod", _absolute_mode(text))
        if _has(text + "Ena"):
            self._write_point(text + "Ena", _symbol(text + "Ena", "ENABLED"))

    def _write_value(self, text: str, value: float) -> None:
        """Write ``value`` (W, var) to the set-point ``text`` at its scale factor."""
        sf = self._scale[text]
        raw = _unscaled(value, sf)
        low, high = _RANGE[_point(text).pdef["type"]]
        if not low <= raw <= high:
            raise DeviceError("malformed", f"{text}: {value:g} does not fit its type at scale "
                                           f"factor {sf}")
        self._write_point(text, raw)

    def _value(self, text: str, raw: dict[str, int]) -> float:
        """The value of the point ``text`` (W, var, s) from the raw values ``raw``."""
        return _scaled(raw[text], self._scale[text])
