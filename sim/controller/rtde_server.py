"""The RTDE server (port 30004): protocol-version and controller-version handshakes, output and input recipes per
connection, start/pause, input packages applied to the shared registers, and output packages streamed by the tick.

What the stock ur_rtde 1.6.5 client needs (see the protocol note, sections 1.2-1.5):
- one reply message to every ``V``, ``v``, ``O``, ``I``, ``S`` and ``P``; the ``S`` reply goes out before the first
  ``U``, and ``P`` is always answered (``RTDEIOInterface.disconnect`` blocks on it);
- input recipe ids 1, 2, 3, ... per connection in arrival order; input packages from connections that were never
  started are applied too;
- input packages longer than their recipe are parsed by their prefix (``getForwardKinematics(q, tcp)`` sends 12
  doubles under a 6-double recipe), shorter ones are dropped; both are logged once per connection and recipe.

Malformed messages are answered, never raised: a setup that cannot be parsed, or an output recipe whose package
would not fit in one message, gets a failed setup reply (recipe id 0); a header that announces less than itself loses
the framing, so it is answered with an error text message (``M``) and the connection is closed. A client that
never reads its replies is dropped by ``tcp_service.Connection.send`` once they pass its queue limit.
"""

from __future__ import annotations

import logging
import struct
import threading
from collections.abc import Callable

from sim.controller import rtde_wire as wire
from sim.controller.rtde_names import INPUT_TYPES, NOT_FOUND, input_types, output_types, recipe_struct, type_width
from sim.controller.rtde_outputs import OutputRecipe
from sim.controller.state import StateSnapshot
from sim.controller.tcp_service import Connection, TcpService

log = logging.getLogger(__name__)

CONTROLLER_TICK_HZ = 500.0
InputSink = Callable[[dict[str, object]], None]


class InputRecipe:
    """A validated input recipe: decodes one ``U`` body into ``{name: value}``."""

    def __init__(self, recipe_id: int, names: list[str]) -> None:
        self.recipe_id = recipe_id
        self.names = names
        types = [INPUT_TYPES[n] for n in names]
        self._struct = recipe_struct(types)
        self._widths = [type_width(t) for t in types]

    @property
    def size(self) -> int:
        return self._struct.size

    def decode(self, body: bytes) -> dict[str, object]:
        flat = self._struct.unpack_from(body)
        fields: dict[str, object] = {}
        i = 0
        for name, width in zip(self.names, self._widths, strict=True):
            fields[name] = flat[i] if width == 1 else flat[i : i + width]
            i += width
        return fields


class RtdeSession:
    """Per-connection RTDE state."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.output: OutputRecipe | None = None
        self.decimation = 1
        self.inputs: dict[int, InputRecipe] = {}
        self.next_output_id = 1
        self.next_input_id = 1
        self.started = False
        self.warned: set[tuple[str, int]] = set()

    def warn_once(self, kind: str, recipe_id: int, message: str, *args: object) -> None:
        if (kind, recipe_id) not in self.warned:
            self.warned.add((kind, recipe_id))
            log.warning(message, *args)


class RtdeServer:
    """RTDE protocol version 2 on ``host:port``; ``apply_inputs`` is called (from socket threads) for every input
    package, and ``broadcast`` (from the tick) streams one snapshot to every started connection."""

    def __init__(
        self,
        host: str,
        port: int,
        apply_inputs: InputSink,
        controller_version: tuple[int, int, int, int] = (5, 15, 0, 106767),
    ) -> None:
        self._apply_inputs = apply_inputs
        self._version = controller_version
        self._sessions: list[RtdeSession] = []
        self._lock = threading.Lock()
        self.service = TcpService("rtde", host, port, self._serve)
        self.packages_sent = 0

    def start(self) -> None:
        self.service.start()

    def stop(self) -> None:
        self.service.stop()

    @property
    def session_count(self) -> int:
        with self._lock:
            return len(self._sessions)

    def broadcast(self, snapshot: StateSnapshot, tick_index: int) -> None:
        """Sends ``snapshot`` to every started session whose frequency is due at this tick. Never blocks."""
        with self._lock:
            sessions = list(self._sessions)
        for session in sessions:
            recipe = session.output
            if not session.started or recipe is None or tick_index % session.decimation:
                if session.conn.has_pending:
                    session.conn.flush()
                continue
            if session.conn.send(wire.frame(wire.DATA_PACKAGE, recipe.pack(snapshot)), droppable=True):
                self.packages_sent += 1

    def _serve(self, conn: Connection) -> None:
        session = RtdeSession(conn)
        with self._lock:
            self._sessions.append(session)
        reader = wire.FrameReader()
        try:
            while not self.service.stopping:
                data = conn.recv()
                if data is None:
                    continue
                if not data:
                    return
                for msg_type, payload in reader.feed(data):
                    try:
                        self._handle(session, msg_type, payload)
                    except (ValueError, struct.error, KeyError, IndexError) as exc:
                        log.warning("%r: RTDE message %r could not be handled: %s", conn, chr(msg_type), exc)
                        conn.send(wire.text_message(f"RTDE message {chr(msg_type)!r} could not be handled: {exc}"))
        except ValueError as exc:  # the framing is lost: nothing after this can be read
            log.warning("%r: closing after a malformed message: %s", conn, exc)
            conn.close_after_reply(wire.text_message(f"malformed RTDE message: {exc}; closing"))
        finally:
            with self._lock:
                self._sessions.remove(session)

    def _handle(self, session: RtdeSession, msg_type: int, payload: bytes) -> None:
        conn = session.conn
        if msg_type == wire.DATA_PACKAGE:
            self._handle_input(session, payload)
        elif msg_type == wire.REQUEST_PROTOCOL_VERSION:
            version = struct.unpack_from(">H", payload)[0] if len(payload) >= 2 else -1
            if version != wire.PROTOCOL_VERSION:
                log.warning("%r asked for RTDE protocol version %d; only version 2 is served", conn, version)
            conn.send(wire.success_reply(wire.REQUEST_PROTOCOL_VERSION, version == wire.PROTOCOL_VERSION))
        elif msg_type == wire.GET_URCONTROL_VERSION:
            conn.send(wire.version_reply(*self._version))
        elif msg_type == wire.SETUP_OUTPUTS:
            self._setup_outputs(session, payload)
        elif msg_type == wire.SETUP_INPUTS:
            self._setup_inputs(session, payload)
        elif msg_type == wire.START:
            conn.send(wire.success_reply(wire.START))
            session.started = True  # after the reply is queued: the S reply always precedes the first U
            log.debug("%r started (%s)", conn, "no outputs" if session.output is None else session.output.names)
        elif msg_type == wire.PAUSE:
            session.started = False
            conn.send(wire.success_reply(wire.PAUSE))
        elif msg_type == wire.TEXT_MESSAGE:
            log.info("%r text message: %r", conn, payload)
        else:
            session.warn_once("type", msg_type, "%r: ignoring RTDE message type %d (%r)", conn, msg_type, chr(msg_type))

    def _setup_outputs(self, session: RtdeSession, payload: bytes) -> None:
        try:
            frequency_hz, names = wire.parse_output_setup(payload)
        except ValueError as exc:
            log.warning("%r: malformed output setup (%s); answered with recipe id 0", session.conn, exc)
            _send_setup_reply(session.conn, wire.SETUP_OUTPUTS, 0, [])
            return
        types = output_types(names)
        recipe_id = session.next_output_id
        session.next_output_id += 1
        if NOT_FOUND in types or not names:
            missing = [n for n, t in zip(names, types, strict=True) if t == NOT_FOUND]
            log.warning("%r asked for unknown RTDE outputs %s; answered NOT_FOUND", session.conn, missing)
            _send_setup_reply(session.conn, wire.SETUP_OUTPUTS, 0, types)
            return
        package_bytes = wire.HEADER.size + 1 + recipe_struct(types).size
        if package_bytes > wire.MAX_MESSAGE_BYTES:
            log.warning(
                "%r asked for %d RTDE outputs, a %d-byte package (at most %d fit in one message); answered with "
                "recipe id 0",
                session.conn,
                len(names),
                package_bytes,
                wire.MAX_MESSAGE_BYTES,
            )
            _send_setup_reply(session.conn, wire.SETUP_OUTPUTS, 0, types)
            return
        if not 0.0 < frequency_hz <= CONTROLLER_TICK_HZ:
            log.warning("%r asked for %.1f Hz; streaming at 500 Hz instead", session.conn, frequency_hz)
            frequency_hz = CONTROLLER_TICK_HZ
        session.output = OutputRecipe(recipe_id, names, frequency_hz)
        session.decimation = max(1, round(CONTROLLER_TICK_HZ / frequency_hz))
        _send_setup_reply(session.conn, wire.SETUP_OUTPUTS, recipe_id, types)

    def _setup_inputs(self, session: RtdeSession, payload: bytes) -> None:
        names = wire.parse_names(payload)
        types = input_types(names)
        if NOT_FOUND in types or not names:
            missing = [n for n, t in zip(names, types, strict=True) if t == NOT_FOUND]
            log.warning("%r asked for unknown RTDE inputs %s; answered NOT_FOUND", session.conn, missing)
            _send_setup_reply(session.conn, wire.SETUP_INPUTS, 0, types)
            return
        recipe_id = session.next_input_id
        session.next_input_id += 1
        session.inputs[recipe_id] = InputRecipe(recipe_id, names)
        _send_setup_reply(session.conn, wire.SETUP_INPUTS, recipe_id, types)

    def _handle_input(self, session: RtdeSession, payload: bytes) -> None:
        if not payload:
            return
        recipe_id, body = payload[0], payload[1:]
        recipe = session.inputs.get(recipe_id)
        if recipe is None:
            session.warn_once(
                "id",
                recipe_id,
                "%r sent an input package for unknown recipe %d (known: %s); ignored",
                session.conn,
                recipe_id,
                sorted(session.inputs),
            )
            return
        if len(body) < recipe.size:
            session.warn_once(
                "short",
                recipe_id,
                "%r: input package for recipe %d has %d bytes, the recipe needs %d; dropped",
                session.conn,
                recipe_id,
                len(body),
                recipe.size,
            )
            return
        if len(body) > recipe.size:
            session.warn_once(
                "long",
                recipe_id,
                "%r: input package for recipe %d has %d bytes, the recipe needs %d; "
                "applying the first %d (seen with getForwardKinematics(q, tcp))",
                session.conn,
                recipe_id,
                len(body),
                recipe.size,
                recipe.size,
            )
        self._apply_inputs(recipe.decode(body))


def _send_setup_reply(conn: Connection, msg_type: int, recipe_id: int, types: list[str]) -> None:
    """A setup reply; one whose type list would not fit in one message goes out as a failure without the list."""
    if wire.HEADER.size + 1 + len(",".join(types)) > wire.MAX_MESSAGE_BYTES:
        recipe_id, types = 0, []
    conn.send(wire.setup_reply(msg_type, recipe_id, types))
