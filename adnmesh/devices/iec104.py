"""IEC 60870-5-104 (c104): a device simulator's server (the plant's RTU) and the gateway's link.

c104 (lib60870) carries, encodes and decodes the protocol; nothing here handles a frame's bytes.

The station (:class:`IEC104Points`, one common address, default 1)
    ===========  =========  ==========================================================
    IOA          type       meaning
    ===========  =========  ==========================================================
    100 p_set    C_SE_NC_1  active power set-point, W (short float), direct execute
    101 q_set    C_SE_NC_1  reactive power set-point, var (generator convention)
    200 p_meas   M_ME_TF_1  measured active power, W, with a CP56Time2a time tag
    201 q_meas   M_ME_TF_1  measured reactive power, var, with a time tag
    300 status   M_SP_TB_1  on: connected to the grid and operating, with a time tag
    ===========  =========  ==========================================================

Measurement (:class:`IEC104Server`)
    Each monitoring point takes its value from :meth:`RealtimePlant.read` at the moment a
    client asks for it (c104's ``on_before_read``: a station interrogation or a read command),
    time-tagged with the server's wall clock, not the model time (UTC; CP56Time2a resolves
    1 ms). A set-point command applies :meth:`RealtimePlant.write` and is confirmed
    positively.

Faults (:class:`~adnmesh.devices.faults.DeviceFaults`, read at each request)
    ``refuse_writes``: set-point commands get a negative confirmation, nothing is taken;
    ``frozen``: P and Q keep their last value and time tag (the status goes on);
    ``disconnected``: the status point is off;
    ``silent``: a set-point command is neither taken nor confirmed (c104's
    ``ResponseState.NONE``); a request for a monitoring point holds the connection's thread
    of the server (the hook waits) until ``silent`` is cleared or the server stops, so the
    client gets at most the interrogation's activation confirmation and no data. Stopped
    (``down``): :meth:`IEC104Server.stop` closes the port and every connection.

The link (:class:`IEC104Link`)
    :meth:`~IEC104Link.connect` opens the connection (TCP, then its own STARTDT; no initial
    interrogation or clock synchronisation), then checks the station with a station
    interrogation: it must be confirmed and report all three monitoring points with their
    types. A read is one station interrogation (C_IC_NA_1) rather than three read commands
    (C_RD_NA_1): its activation termination comes after the points' data on the same
    connection, so every value has been taken when it arrives (c104 ends a read command before
    it stores the value). The reading's stamp is P's time tag, s since the epoch (UTC). A write
    is one direct set-point command per set-point (P, then Q if given), each waiting for its
    confirmation.

    The link waits for each command's final answer itself: c104's ``on_receive_raw`` hook,
    decoded by ``c104.explain_bytes_dict``, counts the answers per command. c104 2.2.1's own
    wait misses an answer that arrives before it starts waiting (false timeouts on a loaded
    host) and takes a negative confirmation followed by an UNKNOWN_CA reply as success; its
    verdict is not used, and its wait is cut to :data:`_C104_WAIT_MS`.

    Each wait for the device is bounded by ``timeout_s``: for the connection to open and for
    each answer; :meth:`~IEC104Link.connect` and a write of P and Q wait twice at most, and
    closing after an error adds c104's ending of its threads (about 0.1 s). Errors: no
    connection, or one lost -> ``unreachable``; no answer in time -> ``timeout``; a negative
    answer to a set-point -> ``refused``; a negative answer to the interrogation (no station
    of that common address), a monitoring point not reported with its type, a value that is
    not finite -> ``malformed``. After an error but ``refused`` the connection is closed:
    :meth:`IEC104Link.connect` opens it again. A set-point point the device does not have
    shows as ``refused`` (104 cannot ask for a command point without executing it).

Security profile
    None: plain TCP. IEC 62351-3 (TLS) is refused (``tls`` must be None): the c104 2.2.1
    client cannot complete a TLS handshake (its mbedtls 3.6 requires a host name to verify
    the server, which this c104 cannot set: -0x5D80), and its server writes lib60870's TLS
    debug lines to stderr. Keep the link on a trusted network (or a VPN) until c104 can.
"""

# No ``from __future__ import annotations``: c104 checks a callback's annotations as objects.

import math
import socket
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, fields
from datetime import datetime, timezone

import c104

from adnmesh.devices.faults import DeviceFaults
from adnmesh.devices.link import DeviceError, Reading

__all__ = ["IEC104Link", "IEC104Points", "IEC104Server"]

_MAX_IOA = 16_777_215
_MEASURED_TYPES = (c104.Type.M_ME_TF_1, c104.Type.M_ME_TF_1, c104.Type.M_SP_TB_1)
"""Types of :attr:`IEC104Points.measured`."""
_SILENT_POLL_S = 0.01
_C104_WAIT_MS = 1
"""How long c104 itself waits for a command's answer, ms (the link then waits on by itself)."""
_COMPLETING = {c104.Type.C_SE_NC_1: c104.Cot.ACTIVATION_CON,
               c104.Type.C_IC_NA_1: c104.Cot.ACTIVATION_TERMINATION}
"""The cause of transmission that completes a command of each type the link sends."""
_SETTLED = (c104.ConnectionState.OPEN, c104.ConnectionState.CLOSED_AWAIT_RECONNECT)
"""States a connection being opened ends in: open (STARTDT confirmed) or failed."""
_NO_TLS = ("IEC 104 over TLS is not supported: the c104 2.2.1 client cannot verify a server "
           "(no host name for mbedtls); leave tls out")


@dataclass(frozen=True)
class IEC104Points:
    """The device's station: its common address and information object addresses (IOAs).

    Attributes
    ----------
    common_address : int
        The station's common address (ASDU address), 1..65534.
    p_set, q_set : int
        IOAs of the active (W) and reactive (var) power set-points, C_SE_NC_1.
    p_meas, q_meas : int
        IOAs of the measured active (W) and reactive (var) power, M_ME_TF_1.
    status : int
        IOA of the grid connection status, M_SP_TB_1 (on: connected and operating).

    Raises
    ------
    ValueError
        An address out of range (IOAs 1..16777215), or two IOAs alike.
    """

    common_address: int = 1
    p_set: int = 100
    q_set: int = 101
    p_meas: int = 200
    q_meas: int = 201
    status: int = 300

    def __post_init__(self) -> None:
        if not 1 <= self.common_address <= 65534:
            raise ValueError(f"IEC 104 common address {self.common_address} is not in 1..65534")
        ioas = {f.name: getattr(self, f.name) for f in fields(self)[1:]}
        for name, ioa in ioas.items():
            if not 1 <= ioa <= _MAX_IOA:
                raise ValueError(f"IEC 104 {name} address {ioa} is not in 1..{_MAX_IOA}")
        if len(set(ioas.values())) < len(ioas):
            raise ValueError(f"IEC 104 information object addresses are not distinct: {ioas}")

    @property
    def measured(self) -> tuple[int, int, int]:
        """IOAs of the monitoring points: ``(p_meas, q_meas, status)``."""
        return self.p_meas, self.q_meas, self.status


def _now() -> datetime:
    """The wall clock, UTC (a time tag)."""
    return datetime.now(timezone.utc)


class IEC104Server:
    """A simulated RTU: a c104 server of ``plant`` (see the module docstring).

    Parameters
    ----------
    plant : RealtimePlant
        The plant it serves.
    host : str
        Address to listen on.
    port : int
        TCP port (0: a free one, chosen at the first :meth:`start` and kept over restarts).
    points : IEC104Points
        Its station.
    tls : None
        Must be None (see the module docstring's security profile).
    faults : DeviceFaults, optional
        The faults it plays (default: none, a new :class:`DeviceFaults`).

    Raises
    ------
    ValueError
        ``tls`` given.
    """

    def __init__(self, plant, host: str = "127.0.0.1", port: int = 0,
                 points: IEC104Points = IEC104Points(), tls=None,
                 faults: DeviceFaults | None = None) -> None:
        if tls is not None:
            raise ValueError(_NO_TLS)
        self.plant = plant
        self.host = host
        self.points = points
        self.faults = DeviceFaults() if faults is None else faults
        self._port = port
        self._server: c104.Server | None = None
        self._stopping = threading.Event()

    @property
    def port(self) -> int:
        """The TCP port (the one chosen once started with port 0)."""
        return self._port

    def start(self) -> None:
        """Listen (c104's threads); return once it does.

        Raises
        ------
        OSError
            It cannot listen on host:port.
        RuntimeError
            It is already running.
        """
        if self._server is not None:
            raise RuntimeError("the IEC 104 server is already running")
        if self._port == 0:     # lib60870 would bind port 0 but not tell which port it got
            with socket.create_server((self.host, 0)) as probe:
                self._port = probe.getsockname()[1]
        server = c104.Server(ip=self.host, port=self._port)
        self._add_station(server)
        self._stopping.clear()
        try:
            server.start()
        except RuntimeError:
            raise OSError(f"cannot listen on {self.host}:{self._port}") from None
        self._server = server

    def stop(self) -> None:
        """Close the port and every connection, end c104's threads (nothing if not running)."""
        if self._server is None:
            return
        self._stopping.set()            # releases the requests a silent device holds
        self._server.stop()
        self._server = None

    def __enter__(self) -> "IEC104Server":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _add_station(self, server: c104.Server) -> None:
        """The station, its points, their hooks and the plant's values now."""
        points = self.points
        station = server.add_station(common_address=points.common_address)
        for ioa in (points.p_set, points.q_set):
            station.add_point(io_address=ioa, type=c104.Type.C_SE_NC_1).on_receive(
                callable=self._on_set_point)
        for ioa, kind in zip(points.measured, _MEASURED_TYPES):
            point = station.add_point(io_address=ioa, type=kind)
            self._measure(point)
            point.on_before_read(callable=self._on_before_read)

    def _measure(self, point: c104.Point) -> None:
        """Give ``point`` the plant's value now, time-tagged now."""
        if point.io_address == self.points.status:
            point.info = c104.SingleInfo(on=not self.faults.disconnected, recorded_at=_now())
            return
        p_w, q_var, _ = self.plant.read()
        value = p_w if point.io_address == self.points.p_meas else q_var
        point.info = c104.ShortInfo(actual=value, recorded_at=_now())

    def _on_before_read(self, point: c104.Point) -> None:
        """c104's hook before it reports ``point`` to a client (interrogation, read)."""
        while self.faults.silent and not self._stopping.wait(_SILENT_POLL_S):
            pass
        if point.io_address == self.points.status or not self.faults.frozen:
            self._measure(point)

    def _on_set_point(self, point: c104.Point, previous_info: c104.Information,
                      message: c104.IncomingMessage) -> c104.ResponseState:
        """c104's hook on a set-point command: its confirmation (NONE: none at all)."""
        if self.faults.silent:
            return c104.ResponseState.NONE
        value = point.value
        if self.faults.refuse_writes or not math.isfinite(value):
            return c104.ResponseState.FAILURE
        if point.io_address == self.points.p_set:
            self.plant.write(p_w=value)
        else:
            self.plant.write(q_var=value)
        return c104.ResponseState.SUCCESS


class IEC104Link:
    """The gateway's link to an RTU over IEC 104 (a :class:`~adnmesh.devices.link.DeviceLink`;
    see the module docstring).

    Parameters
    ----------
    host : str
        The device's address.
    port : int
        Its TCP port.
    points : IEC104Points
        Its station.
    timeout_s : float
        Longest wait for the connection and for each answer, s (> 0).
    tls : None
        Must be None (see the module docstring's security profile).

    Raises
    ------
    ValueError
        ``tls`` given, or ``timeout_s`` not positive.
    """

    def __init__(self, host: str, port: int, points: IEC104Points = IEC104Points(),
                 timeout_s: float = 1.0, tls=None) -> None:
        if tls is not None:
            raise ValueError(_NO_TLS)
        if not timeout_s > 0:
            raise ValueError(f"IEC 104 timeout must be positive, got {timeout_s} s")
        self.host = host
        self.port = port
        self.points = points
        self.timeout_s = timeout_s
        self._client: c104.Client | None = None
        self._connection: c104.Connection | None = None
        self._setpoints: dict[int, c104.Point] = {}
        self._changed = threading.Condition()   # an answer came or the connection's state changed
        self._answers: dict[tuple[c104.Type, int], list[bool]] = {}   # final answers, positive?
        self._sent: dict[tuple[c104.Type, int], int] = {}             # commands sent
        self._received: dict[int, c104.Information] = {}              # monitoring IOA -> info

    def connect(self) -> None:
        """Connect (again) and check the station (see the module docstring). Raises
        :class:`DeviceError`."""
        self.close()
        self._answers, self._sent = {}, {}
        self._client = c104.Client(command_timeout_ms=_C104_WAIT_MS)
        try:    # MUTED: c104's own STARTDT may race the connection's state and never be sent
            connection = self._client.add_connection(ip=self.host, port=self.port,
                                                     init=c104.Init.MUTED)
        except ValueError as exc:       # c104 resolves the host at once
            self.close()
            raise DeviceError("unreachable", f"{self.host}:{self.port}: {exc}") from None
        connection.protocol_parameters.connection_timeout = math.ceil(self.timeout_s)
        connection.on_state_change(callable=self._on_state_change)
        connection.on_receive_raw(callable=self._on_receive_raw)
        self._connection = connection
        self._add_station()
        self._client.start()
        with self._changed:
            self._changed.wait_for(lambda: connection.state in _SETTLED, self.timeout_s)
        if connection.state != c104.ConnectionState.OPEN:
            self.close()
            raise DeviceError("unreachable", f"no connection to {self.host}:{self.port} "
                                             f"within {self.timeout_s} s")
        with self._call():
            self._interrogate()

    def write(self, p_w: float, q_var: float | None) -> None:
        """Write the active power set-point, W, and, if not None, the reactive one, var.
        Raises :class:`DeviceError`."""
        with self._call():
            self._set(self.points.p_set, p_w)
            if q_var is not None:
                self._set(self.points.q_set, q_var)

    def read(self) -> Reading:
        """Read P (W), Q (var), the status and P's time tag (s since the epoch) with one
        station interrogation. Raises :class:`DeviceError`."""
        with self._call():
            p, q, status = self._interrogate()
        return Reading(p_w=p.value, q_var=q.value, connected=status.value,
                       stamp=p.recorded_at.timestamp())

    def close(self) -> None:
        """Close the connection and end c104's threads (never raises)."""
        if self._client is not None:
            self._client.stop()
        self._client = self._connection = None
        self._setpoints = {}

    def _add_station(self) -> None:
        """The client's copy of the station: the set-points, the monitoring points' hooks."""
        points = self.points
        station = self._connection.add_station(common_address=points.common_address)
        self._setpoints = {ioa: station.add_point(io_address=ioa, type=c104.Type.C_SE_NC_1)
                           for ioa in (points.p_set, points.q_set)}
        for ioa, kind in zip(points.measured, _MEASURED_TYPES):
            station.add_point(io_address=ioa, type=kind).on_receive(callable=self._on_measured)

    def _on_state_change(self, connection: c104.Connection,
                         state: c104.ConnectionState) -> None:
        """c104's hook on the connection's state (its client thread)."""
        if state == c104.ConnectionState.OPEN_MUTED:
            connection.unmute()         # STARTDT; then OPEN
        with self._changed:
            self._changed.notify_all()

    def _on_receive_raw(self, connection: c104.Connection, data: bytes) -> None:
        """c104's hook on every frame received (its client thread, in order): keeps the final
        answers to the link's commands."""
        apdu = c104.explain_bytes_dict(apdu=data)
        kind = apdu.get("type")
        if kind not in _COMPLETING:
            return
        cot = apdu["cot"]
        if apdu["negative"] or cot.name.startswith("UNKNOWN_"):
            positive = False
        elif cot == _COMPLETING[kind]:
            positive = True
        else:
            return
        with self._changed:
            self._answers.setdefault((kind, apdu["firstInformationObjectAddress"]),
                                     []).append(positive)
            self._changed.notify_all()

    def _on_measured(self, point: c104.Point, previous_info: c104.Information,
                     message: c104.IncomingMessage) -> c104.ResponseState:
        """c104's hook on a monitoring point's value received (its receiving thread, before
        the frames that follow are received)."""
        self._received[point.io_address] = point.info
        return c104.ResponseState.SUCCESS

    @contextmanager
    def _call(self):
        """One call on the open connection; after an error but a refusal, it is closed."""
        if self._connection is None:
            raise DeviceError("unreachable", f"not connected to {self.host}:{self.port}")
        try:
            if self._connection.state != c104.ConnectionState.OPEN:
                raise DeviceError("unreachable", f"connection to {self.host}:{self.port} lost")
            yield
        except DeviceError as exc:
            if exc.reason != "refused":
                self.close()
            raise

    def _interrogate(self) -> tuple[c104.Information, c104.Information, c104.Information]:
        """A station interrogation: the infos of P, Q and the status it reported."""
        ca = self.points.common_address
        self._received = {}
        self._command(c104.Type.C_IC_NA_1, 0, f"the interrogation of station {ca}", "malformed",
                      lambda: self._connection.interrogation(common_address=ca,
                                                             wait_for_response=False))
        infos = []
        for ioa, kind in zip(self.points.measured, _MEASURED_TYPES):
            info = self._received.get(ioa)
            if info is None:
                raise DeviceError("malformed", f"station {ca} reported no {kind.name} at IOA "
                                               f"{ioa}")
            infos.append(info)
        p, q, _ = infos
        if not (math.isfinite(p.value) and math.isfinite(q.value)):
            raise DeviceError("malformed", f"station {ca} reported P {p.value} W, "
                                           f"Q {q.value} var")
        return tuple(infos)

    def _set(self, ioa: int, value: float) -> None:
        """A direct set-point command to ``ioa``, confirmed."""
        point = self._setpoints[ioa]
        point.value = float(value)
        self._command(c104.Type.C_SE_NC_1, ioa, f"the set-point {value} at IOA {ioa}",
                      "refused", lambda: point.transmit(cause=c104.Cot.ACTIVATION))

    def _command(self, kind: c104.Type, ioa: int, what: str, negative: str, send) -> None:
        """Send a command with ``send()`` and wait for its final answer; raise a DeviceError
        (reason ``negative`` for a negative answer)."""
        key = (kind, ioa)
        sent = self._sent[key] = self._sent.get(key, 0) + 1
        connection = self._connection
        send()      # c104's verdict is not kept: its own wait may miss the answer
        with self._changed:
            self._changed.wait_for(lambda: len(self._answers.get(key, ())) >= sent
                                   or connection.state != c104.ConnectionState.OPEN,
                                   self.timeout_s)
            answers = self._answers.get(key, [])
        if len(answers) >= sent:
            if answers[sent - 1]:
                return
            raise DeviceError(negative, f"negative answer to {what}")
        if connection.state != c104.ConnectionState.OPEN:
            raise DeviceError("unreachable", f"connection to {self.host}:{self.port} lost "
                                             f"during {what}")
        raise DeviceError("timeout", f"no answer to {what} within {self.timeout_s} s")
