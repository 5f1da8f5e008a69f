"""The simulated rig on real wires: a Modbus drive (TCP on loopback, RTU on a pseudo-terminal)
and an ASCII load cell on a pseudo-terminal, all in front of one `SimRig`.

The drive implements the register map of `rig.drivers.registers` (Oriental AZ style):
direct-data moves executed with the slider physics, STOP (level-sensitive, as on the
real drive: while the bit stays set, motion stops and every move is ignored), return-to-home, READY /
MOVE / IN-POS / ALM-A status bits, alarm codes and reset, and the communication
timeout: when a move is running and the master has been silent for longer than the
configured timeout the drive stops and raises alarm 0x85, like the real one.

RTU runs through a byte bridge between two pseudo-terminals (server side, client
side), TCP through a loopback proxy; the bridges are where line faults are injected:
lost replies, corrupted CRCs (RTU), late replies. Faults are fields of `FaultParams`
and can be changed while the devices run. The bridges and the load cell are also where
the wire gets its speed (`rig.sim.line`): with `sim.pace_wire` every byte takes its time on
the line at the configured baud rate and frame, and the USB adapter's latency on the way
back, so a loop rate proven here is one the lab's wire allows.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import pty
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass

from pymodbus import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from rig.drivers.registers import PROFILES, RegisterMap, from_words, to_words
from rig.sim.line import Framing, Line, PacedWriter
from rig.sim.params import SimParams
from rig.sim.physics import SimRig

ALARM_COMM_TIMEOUT = 0x85
N_REGISTERS = 0x400


@dataclass(frozen=True)
class Endpoints:
    modbus_tcp: str | None  # "host:port"
    modbus_rtu: str | None  # client-side pseudo-terminal path
    loadcell: str | None  # pseudo-terminal path

    def as_dict(self) -> dict[str, str | None]:
        return {"modbus_tcp": self.modbus_tcp, "modbus_rtu": self.modbus_rtu, "loadcell": self.loadcell}


class SimDrive:
    """Register semantics of the drive, in front of the shared physics."""

    def __init__(self, rig: SimRig, regs: RegisterMap, params: SimParams, origin_s: float) -> None:
        self.rig = rig
        self.regs = regs
        self.params = params
        self.origin_s = origin_s
        self.spm = params.slider.steps_per_mm
        self.comm_timeout_s = params.drive.comm_timeout_s
        self.last_request_s = time.monotonic()
        self.requests = 0
        self.moves = 0
        self.stops = 0
        self.ignored_moves = 0  # moves refused while STOP was held or an alarm was on
        self.input_bits = 0  # the input command register's lower word, as last written
        self.first_stop_s: float | None = None  # monotonic time the first STOP arrived

    @property
    def stop_held(self) -> bool:
        return bool(self.input_bits & (1 << self.regs.bit_stop))

    @property
    def alarm_code(self) -> int:
        return self.params.faults.alarm_code

    def sync(self) -> None:
        self.rig.advance(time.monotonic() - self.origin_s)
        if (self.alarm_code or self.stop_held) and self.rig.slider.moving and not self.rig.slider.stopping:
            self.rig.slider.stop()

    async def action(self, function_code: int, start_address: int, address: int, count: int,
                     current_registers: list[int], set_values: list[int] | None):
        self.requests += 1
        self.last_request_s = time.monotonic()
        with self.rig.lock:
            self.sync()
            if set_values is None:
                self._fill(current_registers, start_address, address, count)
            else:
                self._written(address, list(set_values))
        return None

    def _fill(self, regs: list[int], start: int, address: int, count: int) -> None:
        r = self.regs
        m = self.rig.slider
        code = self.alarm_code
        bits = 0
        if not m.moving and not code:
            bits |= 1 << r.bit_ready
        if code:
            bits |= 1 << r.bit_alarm
        if m.moving:
            bits |= 1 << r.bit_move
        if not m.moving and abs(m.position_mm - m.target_mm) < 0.5 / self.spm:
            bits |= 1 << r.bit_in_pos
        values = {
            r.feedback_position: to_words(round(self.rig.feedback_position_mm() * self.spm)),
            r.output_status: [0, bits],
            r.alarm: to_words(code),
            r.input_command: [0, self.input_bits],
        }
        if r.comm_timeout_ms is not None:
            values[r.comm_timeout_ms] = to_words(round(self.comm_timeout_s * 1000))
        for base, words in values.items():
            for i, w in enumerate(words):
                if address <= base + i < address + count:
                    regs[base + i - start] = w

    def _written(self, address: int, values: list[int]) -> None:
        r = self.regs
        end = address + len(values)

        def word32(base: int) -> int | None:
            if address <= base and base + 1 < end:
                return from_words(values[base - address], values[base + 1 - address])
            return None

        # trigger 1: apply all the direct data and start
        if address <= r.direct_data + 14 and r.direct_data + 15 < end and word32(r.direct_data + 14) == 1:
            self._start_move(word32(r.direct_data + 2), word32(r.direct_data + 4),
                             word32(r.direct_data + 6), word32(r.direct_data + 8))
        if address <= r.input_command + 1 < end:
            bits = values[r.input_command + 1 - address]
            rising = bits & ~self.input_bits
            self.input_bits = bits
            if bits & (1 << r.bit_stop) and self.params.faults.ignore_stops > 0:
                self.params.faults.ignore_stops -= 1
                self.input_bits &= ~(1 << r.bit_stop)  # lost inside the drive
            elif bits & (1 << r.bit_stop):
                self.stops += 1
                self.first_stop_s = self.first_stop_s or time.monotonic()
                self.rig.slider.stop()
            elif rising & (1 << r.bit_zhome) and not self.alarm_code:
                self.rig.slider.move_to(0.0, self.params.drive.home_speed_mm_s)
            if rising & (1 << r.bit_alarm_reset):
                self.params.faults.alarm_code = 0
        if word32(r.alarm_reset) == 1:
            self.params.faults.alarm_code = 0
        if r.comm_timeout_ms is not None and (ms := word32(r.comm_timeout_ms)) is not None:
            self.comm_timeout_s = max(ms, 0) / 1000.0

    def _start_move(self, op_type, position_steps, speed_hz, accel) -> None:
        if self.alarm_code or self.stop_held or self.params.faults.ignore_moves:
            self.ignored_moves += 1  # the real drive does not start, and no reply says so
            return
        if position_steps is None or not speed_hz:
            return
        target = position_steps / self.spm
        if op_type == 2:  # incremental from the command position
            target += self.rig.slider.target_mm
        accel_mm_s2 = accel / self.spm if accel else None
        self.rig.slider.move_to(target, abs(speed_hz) / self.spm, accel_mm_s2)
        self.moves += 1

    def watchdog(self) -> None:
        """The drive's own communication timeout: a silent master stops a running move."""
        with self.rig.lock:
            self.sync()
            silent = time.monotonic() - self.last_request_s
            if (self.comm_timeout_s > 0 and silent > self.comm_timeout_s and self.rig.slider.moving
                    and not self.alarm_code):
                self.params.faults.alarm_code = ALARM_COMM_TIMEOUT
                self.rig.slider.stop()


def drive_line(params: SimParams, baudrate: int | None = None) -> Line | None:
    """The drive's RS-485 line as configured (None: not paced, bytes as fast as the pty)."""
    if not params.pace_wire:
        return None
    d = params.drive
    return Line(Framing(baudrate or d.baudrate, d.parity, d.stopbits), params.usb_latency_ms / 1000.0)


def loadcell_lines(params: SimParams) -> tuple[Line, Line] | None:
    """The load cell's two directions (RS-232 is full duplex): to the host (with the USB
    adapter's latency) and from it."""
    if not params.pace_wire:
        return None
    lc = params.loadcell
    framing = Framing(lc.baudrate, lc.parity, lc.stopbits)
    return Line(framing, params.usb_latency_ms / 1000.0), Line(framing)


def wire_note(params: SimParams, baudrate: int | None = None) -> str:
    """How fast the simulated drive's line is, for people: '115200 8N1, paced, USB latency 1 ms'."""
    d = params.drive
    frame = Framing(baudrate or d.baudrate, d.parity, d.stopbits).describe()
    if not params.pace_wire:
        return f"{frame}, not paced: bytes as fast as the pty"
    return f"{frame}, paced, USB latency {params.usb_latency_ms:g} ms"


def reply_faults(faults, data: bytes, *, corrupt: bool) -> bytes | None:
    """A reply on its way back to the master: lost (None), corrupted or late, as switched."""
    if faults.drop_replies > 0:
        faults.drop_replies -= 1
        return None
    if faults.garble_replies > 0:  # line noise: no frame at all, of any length
        faults.garble_replies -= 1
        return os.urandom(1 + data[-1] % 11)
    if corrupt and faults.corrupt_replies > 0:
        faults.corrupt_replies -= 1
        data = data[:-1] + bytes([data[-1] ^ 0xFF])  # the CRC no longer matches
    if faults.reply_delay_ms > 0:
        time.sleep(faults.reply_delay_ms / 1000.0)
    return data


class TcpBridge:
    """A loopback TCP proxy in front of the Modbus TCP server: where TCP replies get lost or late."""

    def __init__(self, faults, listen_port: int, target_port: int, latency_s: float = 0.0) -> None:
        self.faults = faults
        self.target_port = target_port
        # TCP has no baud rate; a latency only, when asked for
        self.line = Line(None, latency_s) if latency_s > 0 else None
        self._writer = PacedWriter("tcp-paced") if self.line is not None else None
        self._listener = socket.create_server(("127.0.0.1", listen_port))
        self.port = self._listener.getsockname()[1]  # the kernel's choice when listen_port is 0
        self._listener.settimeout(0.05)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._accept = threading.Thread(target=self._run, name="tcp-bridge", daemon=True)
        self._accept.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except (TimeoutError, OSError):
                continue
            try:
                upstream = socket.create_connection(("127.0.0.1", self.target_port), timeout=2)
            except OSError:
                client.close()
                continue
            t = threading.Thread(target=self._pump, args=(client, upstream), name="tcp-pump", daemon=True)
            self._threads.append(t)
            t.start()

    def _pump(self, client: socket.socket, upstream: socket.socket) -> None:
        for sock in (client, upstream):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with client, upstream:
            while not self._stop.is_set():
                ready, _, _ = select.select([client, upstream], [], [], 0.05)
                for sock in ready:
                    try:
                        data = sock.recv(4096)
                    except OSError:
                        return
                    if not data:
                        return
                    if sock is client:
                        upstream.sendall(data)
                        continue
                    data = reply_faults(self.faults, data, corrupt=False)
                    if data is None:
                        continue
                    if self._writer is not None:
                        self._writer.put(_socket_writer(client), self.line.pieces(data, time.monotonic()))
                    else:
                        client.sendall(data)

    def close(self) -> None:
        self._stop.set()
        self._accept.join(2.0)
        for t in self._threads:
            t.join(2.0)
        if self._writer is not None:
            self._writer.close()
        self._listener.close()


def _socket_writer(sock: socket.socket):
    def write(data: bytes) -> None:
        with contextlib.suppress(OSError):  # the master hung up while its reply was on the way
            sock.sendall(data)
    return write


def _raw_pty() -> tuple[int, int, str]:
    master, slave = pty.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


class RtuBridge:
    """Copies bytes between the server's and the client's pseudo-terminals, injecting line faults.

    The client's side can vanish (`vanish()`: its pseudo-terminal closed under the master, like a
    USB adapter pulled mid-trial) and come back (`restore()`: a new one, its path behind the
    same `link_path` when one was given, as udev's by-id names do).
    """

    def __init__(self, faults, link_path: str | None = None, line: Line | None = None) -> None:
        self.faults = faults
        self.link_path = link_path
        self.line = line if line is not None and line.paced else None
        self._writer = PacedWriter("rtu-paced") if self.line is not None else None
        self._generation = 0  # a reply still on the line when the port vanished is not for its successor
        self._lock = threading.Lock()
        self.server_master, self._server_slave, self.server_path = _raw_pty()
        self.client_master, self._client_slave, self.client_path = _raw_pty()
        self._link()
        self._stop = threading.Event()
        # vanish() asks, the bridge's own thread closes: a descriptor closed under its select
        # could be reused by any file the process opens next and read from as the port
        self._vanish = threading.Event()
        self._vanished = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rtu-bridge", daemon=True)
        self._thread.start()

    @property
    def path(self) -> str:
        """Where the master opens the port: the stable link if there is one."""
        return self.link_path or self.client_path

    def _link(self) -> None:
        if self.link_path:
            tmp = f"{self.link_path}.new"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            os.symlink(self.client_path, tmp)
            os.replace(tmp, self.link_path)

    def vanish(self) -> None:
        """The port goes away under whoever has it open: both ends of its pseudo-terminal closed
        (by the bridge's thread, between two of its reads; at once if it no longer runs)."""
        self._vanished.clear()
        self._vanish.set()
        if self._thread.is_alive() and self._vanished.wait(2.0):
            return
        self._close_client()

    def _close_client(self) -> None:
        with self._lock:
            for fd in (self.client_master, self._client_slave):
                if fd >= 0:
                    with contextlib.suppress(OSError):
                        os.close(fd)
            self.client_master = self._client_slave = -1
            if self.link_path:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(self.link_path)
        self._vanish.clear()
        self._vanished.set()

    def restore(self) -> str:
        """The port is back (a new pseudo-terminal); returns the path to open."""
        with self._lock:
            if self.client_master < 0:
                self.client_master, self._client_slave, self.client_path = _raw_pty()
                self._generation += 1
                self._link()
        return self.path

    def _run(self) -> None:
        sm = self.server_master
        while not self._stop.is_set():
            if self._vanish.is_set():
                self._close_client()
            cm = self.client_master
            fds = [sm] if cm < 0 else [sm, cm]
            try:
                ready, _, _ = select.select(fds, [], [], 0.05)
            except (OSError, ValueError):
                return
            # No later than the bytes were written: the pacing counts from here, so a reply is
            # never early
            arrived = time.monotonic()
            for fd in ready:
                try:
                    data = _read_all(fd)
                except OSError:  # the client side closed under us
                    continue
                if not data:
                    continue
                if fd == cm:
                    if self._writer is not None:
                        # the drive acts on a whole frame: it gets the request once its last byte is in
                        self._writer.put(self._to_server,
                                         self.line.pieces(data, arrived, latency=False, trickle=False))
                    else:
                        _write_all(sm, data)
                    continue
                data = reply_faults(self.faults, data, corrupt=True)
                if data is None:
                    continue
                if self._writer is not None:
                    # a delayed reply (reply_delay_ms) starts on the line when it is sent
                    ready_s = max(arrived, time.monotonic()) if self.faults.reply_delay_ms > 0 else arrived
                    self._writer.put(self._to_client(self._generation), self.line.pieces(data, ready_s))
                    continue
                with self._lock:
                    if self.client_master >= 0:
                        _write_all(self.client_master, data)

    def _to_server(self, data: bytes) -> None:
        _write_now(self.server_master, data)

    def _to_client(self, generation: int):
        def write(data: bytes) -> None:
            with self._lock:
                if self.client_master >= 0 and self._generation == generation:
                    _write_now(self.client_master, data)
        return write

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        if self._writer is not None:
            self._writer.close()
        for fd in (self.server_master, self._server_slave, self.client_master, self._client_slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        if self.link_path:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.link_path)


def _read_all(fd: int) -> bytes:
    out = bytearray()
    while True:
        try:
            chunk = os.read(fd, 4096)
        except BlockingIOError:
            break
        except OSError as exc:
            if exc.errno == errno.EIO:  # the other side is closed for now
                break
            raise
        if not chunk:
            break
        out += chunk
    return bytes(out)


def _write_now(fd: int, data: bytes) -> None:
    """What the pty takes now; the rest is lost, as bytes sent to a port nobody reads are. The
    paced writer must not wait here: every piece behind this one would be late."""
    with contextlib.suppress(BlockingIOError, OSError):
        os.write(fd, data)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    deadline = time.monotonic() + 0.5
    while view:
        try:
            n = os.write(fd, view)
            view = view[n:]
        except BlockingIOError:
            if time.monotonic() > deadline:  # nobody reads: drop rather than block the bridge
                return
            time.sleep(0.0005)


class LoadCellPort:
    """An ASCII load cell on a pseudo-terminal: streams lines, or answers requests."""

    def __init__(self, rig: SimRig, params: SimParams, origin_s: float) -> None:
        self.rig = rig
        self.params = params
        self.origin_s = origin_s
        self.master, self._slave, self.path = _raw_pty()
        self.lines = 0
        lines = loadcell_lines(params)
        self.tx, self.rx = lines if lines is not None else (None, None)
        self._writer = PacedWriter("loadcell-paced") if self.tx is not None else None
        self._fd_lock = threading.Lock()  # the paced writer must not write to a descriptor closed under it
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="loadcell-pty", daemon=True)
        self._thread.start()

    def _line(self) -> bytes:
        f = self.params.faults
        self.lines += 1
        if f.garbage_lines > 0:
            f.garbage_lines -= 1
            return b"#\x07garb@ge%%\r\n"
        self.rig.advance(time.monotonic() - self.origin_s)
        force = self.rig.read_force_N()
        return (self.params.loadcell.line_format.format(force_N=force) + "\r\n").encode()

    def _send(self, data: bytes) -> None:
        if self._writer is None:
            _write_all(self.master, data)
            return
        self._writer.put(self._write, self.tx.pieces(data, time.monotonic()))

    def _write(self, data: bytes) -> None:
        with self._fd_lock:
            if self.master >= 0:
                _write_now(self.master, data)

    def _wait_until(self, t: float) -> None:
        delay = t - time.monotonic()
        if delay > 0:
            self._stop.wait(delay)

    def _run(self) -> None:
        lc = self.params.loadcell
        period = 1.0 / lc.rate_Hz
        next_t = time.monotonic()
        pending = bytearray()
        while not self._stop.is_set():
            f = self.params.faults
            if f.loadcell_disconnect:
                self._disconnect()
                return
            if lc.mode == "poll":
                ready, _, _ = select.select([self.master], [], [], 0.02)
                if ready:
                    arrived = time.monotonic()
                    pending += _read_all(self.master)
                    while b"\n" in pending or b"\r" in pending:
                        cut = min(i for i in (pending.find(b"\n"), pending.find(b"\r")) if i >= 0)
                        req = bytes(pending[:cut]).strip()
                        del pending[: cut + 1]
                        # the request's bytes take their time to arrive before the cell can answer
                        heard = self.rx.carry(cut + 1, arrived)[1] if self.rx is not None else arrived
                        if req and not f.loadcell_silent:
                            # conversion time of a real cell (its reply's transmit time is the line's)
                            self._wait_until(heard + lc.reply_ms / 1000.0)
                            self._send(self._line())
                continue
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_t = time.monotonic()
            if self.tx is not None and self.tx.free_at() > time.monotonic():
                # a line too slow for the rate: the cell sends its next reading when the last
                # one is out, so the rate the host sees is the line's
                self._wait_until(self.tx.free_at())
                next_t = time.monotonic()
            if not f.loadcell_silent:
                self._send(self._line())

    def _disconnect(self) -> None:
        with self._fd_lock:
            for fd in (self.master, self._slave):
                if fd >= 0:
                    with contextlib.suppress(OSError):
                        os.close(fd)
            self.master = self._slave = -1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        if self._writer is not None:
            self._writer.close()
        self._disconnect()


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class WireSim:
    """The simulated drive and load cell on real wires, run by an asyncio loop in a thread."""

    def __init__(self, params: SimParams | None = None, *, tcp: bool = True, rtu: bool = True,
                 loadcell: bool = True, tcp_port: int = 0, profile: str = "oriental_az_sim",
                 baudrate: int | None = None, rtu_link: str | None = None) -> None:
        self.params = params or SimParams()
        self.rig = SimRig(self.params)
        self.origin_s = time.monotonic()
        self.drive = SimDrive(self.rig, PROFILES[profile], self.params, self.origin_s)
        self.want = {"tcp": tcp, "rtu": rtu, "loadcell": loadcell}
        # 0: the port the kernel gives the listener when it binds. A port found free beforehand
        # can be taken before the bind (by the inner server's own pick, or a connection's
        # ephemeral port): seen once in a suite run as "Address already in use"
        self.tcp_port = tcp_port
        self.baudrate = baudrate or self.params.drive.baudrate
        self.rtu_link = rtu_link  # a stable path (symlink) to the RTU port, kept across vanish/restore
        self.bridge: RtuBridge | None = None
        self.tcp_bridge: TcpBridge | None = None
        self.loadcell: LoadCellPort | None = None
        self.endpoints: Endpoints | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_async: asyncio.Event | None = None

    def start(self, timeout_s: float = 10.0) -> Endpoints:
        self._thread = threading.Thread(target=self._thread_main, name="wire-sim", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise RuntimeError("simulated devices did not start in time")
        if self._error is not None:
            raise RuntimeError(f"simulated devices failed to start: {self._error}")
        return self.endpoints

    def __enter__(self) -> WireSim:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _thread_main(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._error = exc
            self._ready.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop_async = asyncio.Event()
        def device(action) -> SimDevice:
            return SimDevice(id=self.params.drive.device_id,
                             simdata=[SimData(address=0, count=N_REGISTERS, values=0,
                                              datatype=DataType.REGISTERS)],
                             action=action)

        servers = []
        rtu_path = tcp = None
        if self.want["tcp"]:
            server = ModbusTcpServer(device(self.drive.action), address=("127.0.0.1", 0))
            await server.serve_forever(background=True)
            servers.append(server)
            inner_port = server.transport.sockets[0].getsockname()[1]
            self.tcp_bridge = TcpBridge(self.params.faults, self.tcp_port, inner_port,
                                        self.params.tcp_latency_ms / 1000.0)
            self.tcp_port = self.tcp_bridge.port
            tcp = f"127.0.0.1:{self.tcp_port}"
        if self.want["rtu"]:
            self.bridge = RtuBridge(self.params.faults, self.rtu_link, drive_line(self.params, self.baudrate))
            # 8N1 on the pty whatever the drive's frame: ptys do not emulate parity (and refuse
            # even parity on some kernels); the frame's length is the paced line's business
            server = ModbusSerialServer(device(self.drive.action), framer=FramerType.RTU,
                                        port=self.bridge.server_path,
                                        baudrate=self.baudrate, bytesize=8, parity="N", stopbits=1)
            await server.serve_forever(background=True)
            servers.append(server)
            rtu_path = self.bridge.path
        if self.want["loadcell"]:
            self.loadcell = LoadCellPort(self.rig, self.params, self.origin_s)
        self.endpoints = Endpoints(tcp, rtu_path, self.loadcell.path if self.loadcell else None)
        self._ready.set()
        try:
            while not self._stop_async.is_set():
                self.drive.watchdog()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._stop_async.wait(), 0.005)
        finally:
            for server in servers:
                with contextlib.suppress(Exception):
                    await server.shutdown()
            if self.bridge:
                self.bridge.close()
            if self.tcp_bridge:
                self.tcp_bridge.close()
            if self.loadcell:
                self.loadcell.close()

    def stop(self) -> None:
        if self._loop is not None and self._stop_async is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop_async.set)
        if self._thread is not None:
            self._thread.join(5.0)
