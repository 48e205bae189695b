"""Talking SMP to one device: where it is (a URI), a transport from smpclient, and one
checked request/answer exchange.

smpclient's transports move the bytes (UDP datagrams, the base64 console framing of a
serial line, that framing over a TCP socket for emulators); everything a device answers
is then checked here before it becomes a model of the ``smp`` package: the frame within
the SMP length field's bound, the header's op, group, command and *sequence number* those
of the request, the body bounded CBOR (:mod:`.cbor`), an SMP error (``rc``, ``err``)
turned into :class:`DeviceRefused`. ``SMPClient.request`` is not used: it decodes CBOR
without bounds.
"""

from __future__ import annotations

import asyncio
import re
from dataclasses import dataclass
from typing import Any, TypeVar, cast
from urllib.parse import parse_qs, urlsplit

from ..errors import InputError
from . import cbor

DEFAULT_UDP_PORT = 1337
DEFAULT_BAUD = 115200
MAX_FRAME = 8 + 0xFFFF  # SMP header + the largest body its 16-bit length field can announce
HCDF_GROUP = 100  # CogniPilot dendrite: command 0 reads {"url", "sha"} of the device's description
MGMT_ERR_ENOTSUP = 8

R = TypeVar("R")


class DeviceError(InputError):
    """A device could not be reached or said something we cannot interpret (exit 3)."""

    code = "device"


class DeviceUnreachable(DeviceError):
    code = "unreachable"


class DeviceMalformed(DeviceError):
    code = "malformed-answer"


class DeviceRefused(DeviceError):
    """The device answered the request with an SMP error code."""

    code = "device-refused"

    def __init__(self, message: str, *, rc: int, group: int | None, file: str) -> None:
        super().__init__(message, file=file, actual=f"rc={rc}" + (f" group={group}" if group is not None else ""))
        self.rc = rc
        self.group = group


@dataclass(frozen=True)
class Endpoint:
    """Where a device's SMP server is: ``udp://HOST[:PORT]``, ``serial:///dev/X?baud=N`` or
    ``socket://HOST:PORT`` (a serial console exposed as TCP, pyserial's URL form)."""

    uri: str
    kind: str  # udp | serial | socket
    host: str = ""
    port: int = 0
    path: str = ""
    baud: int = DEFAULT_BAUD


def parse_endpoint(text: str) -> Endpoint:
    """Parse a device URI; raises :class:`DeviceError` (exit 3) naming what is wrong."""
    parts = urlsplit(text)
    scheme = parts.scheme.lower()
    try:
        port = parts.port
    except ValueError:
        raise DeviceError(f"device URI {text!r}: bad port", file=text) from None
    if scheme == "udp" and parts.hostname:
        if parts.path not in ("", "/") or parts.query:
            raise DeviceError(f"device URI {text!r}: udp://HOST[:PORT] takes no path or query", file=text)
        return Endpoint(text, "udp", host=parts.hostname, port=port or DEFAULT_UDP_PORT)
    if scheme == "socket" and parts.hostname and port:
        return Endpoint(text, "socket", host=parts.hostname, port=port)
    if scheme == "serial" and parts.path and not parts.netloc:
        query = parse_qs(parts.query, strict_parsing=False)
        baud_text = query.pop("baud", [str(DEFAULT_BAUD)])
        if query or len(baud_text) != 1 or not re.fullmatch(r"[1-9][0-9]{2,7}", baud_text[0]):
            raise DeviceError(f"device URI {text!r}: serial:///dev/NAME[?baud=N] only", file=text)
        return Endpoint(text, "serial", path=parts.path, baud=int(baud_text[0]))
    raise DeviceError(
        f"device URI {text!r} is none of udp://HOST[:PORT], serial:///dev/NAME?baud=N, socket://HOST:PORT",
        file=text,
    )


async def open_transport(ep: Endpoint, timeout: float) -> Any:
    """A connected smpclient transport for ``ep``; raises :class:`DeviceUnreachable`."""
    try:
        if ep.kind == "udp":
            from smpclient.transport.udp import SMPUDPTransport

            udp = SMPUDPTransport()
            await udp.connect(ep.host, timeout, port=ep.port)
            return udp
        transport = _serial_transport_class()(baudrate=ep.baud)
        address = f"socket://{ep.host}:{ep.port}" if ep.kind == "socket" else ep.path
        await asyncio.wait_for(transport.connect(address, timeout), timeout + 1)
        return transport
    except (OSError, TimeoutError) as exc:
        raise DeviceUnreachable(f"cannot open {ep.uri}: {exc or type(exc).__name__}", file=ep.uri) from None
    except Exception as exc:  # pyserial raises SerialException (an OSError subclass) or ValueError
        raise DeviceUnreachable(f"cannot open {ep.uri}: {exc}", file=ep.uri) from None


_SERIAL_CLASS: Any = None


def _serial_transport_class() -> Any:
    """smpclient's serial transport, whose connection may also be a pyserial URL
    (``socket://``): then it is a :func:`_socket_line_class` line and, a socket having no
    transmit buffer, reports nothing waiting to be sent (as smpclient's own integration
    tests do against the same emulated devices)."""
    global _SERIAL_CLASS
    if _SERIAL_CLASS is None:
        from smpclient.transport.serial import SMPSerialTransport

        class UrlSerialTransport(SMPSerialTransport):
            async def connect(self, address: str, timeout_s: float) -> None:
                if "://" not in address:
                    await super().connect(address, timeout_s)
                    object.__setattr__(self, "_conn", _BoundedReads(self._conn, chunk=None))
                    return
                self._reset_state()
                conn = _socket_line_class()(None, timeout=0, write_timeout=0)
                conn.port = address  # what serial.serial_for_url does with the class it picks
                loop = asyncio.get_running_loop()
                await asyncio.wait_for(loop.run_in_executor(None, conn.open), timeout_s)
                conn.out_waiting = 0
                object.__setattr__(self, "_conn", _BoundedReads(conn, chunk=4096))

            async def send(self, data: bytes) -> None:
                # each request gets a fresh read budget; console output kept from earlier
                # answers is dropped (smpclient keeps it until read_serial, which fleet never calls)
                self._conn.left = MAX_SERIAL_BYTES
                self._serial_buffer.clear()
                await super().send(data)

        _SERIAL_CLASS = UrlSerialTransport
    return _SERIAL_CLASS


_SOCKET_LINE_CLASS: Any = None


def _socket_line_class() -> Any:
    """pyserial's ``socket://`` line with a bounded clean start. Its ``open`` discards what
    is waiting until nothing is: a peer that sends faster than that loop reads keeps
    ``open`` reading for as long as it sends (it did, on a loaded machine). This one
    discards at most :data:`MAX_SERIAL_BYTES`; what comes after counts against the first
    answer's budget, which calls the line malformed."""
    global _SOCKET_LINE_CLASS
    if _SOCKET_LINE_CLASS is None:
        from serial.urlhandler.protocol_socket import Serial as SocketSerial

        class SocketLine(SocketSerial):  # type: ignore[misc]
            def reset_input_buffer(self) -> None:
                left = MAX_SERIAL_BYTES
                while left > 0 and self.in_waiting:
                    left -= len(self.read(min(4096, left)))

        _SOCKET_LINE_CLASS = SocketLine
    return _SOCKET_LINE_CLASS


MAX_SERIAL_BYTES = 256 << 10  # bytes read from a serial line per answer: a whole SMP frame base64-encoded is ~90 KiB


class SerialFlood(ValueError):
    """A serial line that sends more than :data:`MAX_SERIAL_BYTES` for one answer."""


class _BoundedReads:
    """A pyserial connection whose reads are counted per request: smpclient's serial
    transport keeps everything it reads until a frame ends (console bytes and an unfinished
    frame alike), so a line that never stops sending would grow it until the timeout.
    ``chunk``: read up to that many bytes at once (a socket, opened with timeout 0, reports
    only whether something is waiting); None: exactly what a serial port says is waiting."""

    def __init__(self, conn: Any, *, chunk: int | None) -> None:
        self._conn = conn
        self._chunk = chunk
        self.left = MAX_SERIAL_BYTES

    def __getattr__(self, name: str) -> Any:
        return getattr(self._conn, name)

    def read_all(self) -> bytes:
        waiting = self._conn.in_waiting
        if not waiting:
            return b""
        data: bytes = self._conn.read(min(self._chunk or waiting, self.left + 1))
        self.left -= len(data)
        if self.left < 0:
            raise SerialFlood(f"more than {MAX_SERIAL_BYTES} bytes on the serial line for one answer")
        return data


class Session:
    """One connected device: checked request/answer exchanges, one at a time."""

    def __init__(self, ep: Endpoint, transport: Any, timeout: float) -> None:
        self.endpoint = ep
        self.transport = transport
        self.timeout = timeout

    async def close(self) -> None:
        try:
            await self.transport.disconnect()
        except Exception:  # noqa: S110 - closing a connection that may already be gone
            pass

    async def request(self, req: Any, response_type: type[R], *, timeout: float | None = None) -> R:
        """Send ``req`` (an ``smp`` request model) and return its answer as ``response_type``.

        Raises:
            DeviceUnreachable: no complete answer within the timeout, or the line dropped.
            DeviceMalformed: an answer that is not the answer to this request.
            DeviceRefused: an SMP error answer.
        """
        from pydantic import ValidationError
        from smp import header as smphdr
        from smp.exceptions import SMPException

        uri = self.endpoint.uri
        wait = self.timeout if timeout is None else timeout
        try:
            frame = bytes(await asyncio.wait_for(self.transport.send_and_receive(req.BYTES), wait))
        except TimeoutError:
            raise DeviceUnreachable(f"no complete answer within {wait:g} s", file=uri) from None
        except (SMPException, ValueError, AssertionError) as exc:  # bad framing, CRC, base64, header
            raise DeviceMalformed(f"broken answer ({exc})", file=uri) from None
        except Exception as exc:  # smpclient's own transport errors (disconnected, more data than announced)
            raise DeviceUnreachable(f"{type(exc).__name__}: {exc}", file=uri) from None
        if not smphdr.Header.SIZE <= len(frame) <= MAX_FRAME:
            raise DeviceMalformed(f"answer of {len(frame)} bytes", file=uri)
        try:
            head = smphdr.Header.loads(frame[: smphdr.Header.SIZE])
        except (ValueError, AssertionError) as exc:
            raise DeviceMalformed(f"bad SMP header ({exc})", file=uri) from None
        want = req.header
        if head.sequence != want.sequence:
            raise DeviceMalformed(
                "answer to another request (sequence number)",
                file=uri,
                expected=str(want.sequence),
                actual=str(head.sequence),
            )
        if (int(head.group_id), int(head.command_id)) != (int(want.group_id), int(want.command_id)) or int(
            head.op
        ) != int(want.op) + 1:
            raise DeviceMalformed(
                "answer is not for this request (op/group/command)",
                file=uri,
                expected=f"{int(want.op) + 1}/{int(want.group_id)}/{int(want.command_id)}",
                actual=f"{int(head.op)}/{int(head.group_id)}/{int(head.command_id)}",
            )
        if head.length != len(frame) - smphdr.Header.SIZE:
            raise DeviceMalformed(
                f"header announces {head.length} body bytes, {len(frame) - smphdr.Header.SIZE} came", file=uri
            )
        try:
            body = cbor.loads(frame[smphdr.Header.SIZE :])
        except cbor.CborError as exc:
            raise DeviceMalformed(f"malformed CBOR ({exc})", file=uri) from None
        if not isinstance(body, dict) or not all(isinstance(k, str) for k in body):
            raise DeviceMalformed("answer body is not a map of text keys", file=uri)
        _raise_smp_error(body, uri)
        if body.get("rc") == 0 and "rc" not in getattr(response_type, "model_fields", {}):
            del body["rc"]
        try:
            # smp_data given: the model keeps the frame as received instead of re-encoding it
            return cast(Any, response_type)(header=head, smp_data=frame, **body)  # type: ignore[no-any-return]
        except (ValidationError, SMPException, TypeError, ValueError) as exc:
            first = str(exc).splitlines()[:3]
            raise DeviceMalformed(f"unexpected answer ({' / '.join(first)})", file=uri) from None


def _raise_smp_error(body: dict[str, Any], uri: str) -> None:
    """SMP v1 errors are ``{"rc": N}``, v2 ``{"err": {"group": G, "rc": N}}`` (rc 0: success)."""
    rc = body.get("rc")
    err = body.get("err")
    if isinstance(err, dict):
        group, code = err.get("group"), err.get("rc")
        if not isinstance(code, int) or isinstance(code, bool) or not isinstance(group, int):
            raise DeviceMalformed(f"malformed SMP error {err!r}", file=uri)
        if code != 0:
            raise DeviceRefused("the device refused the request", rc=code, group=group, file=uri)
    if rc is not None:
        if not isinstance(rc, int) or isinstance(rc, bool):
            raise DeviceMalformed(f"malformed SMP rc {rc!r}", file=uri)
        if rc != 0:
            raise DeviceRefused("the device refused the request", rc=rc, group=None, file=uri)


def hcdf_models() -> tuple[type[Any], type[Any]]:
    """The HCDF group's read request and response (group 100, command 0), built on the
    ``smp`` package's message models like its own groups."""
    global _HCDF
    if _HCDF is None:
        from smp import message

        class HcdfDescriptionReadRequest(message.ReadRequest):
            _GROUP_ID = HCDF_GROUP
            _COMMAND_ID = 0

        class HcdfDescriptionReadResponse(message.ReadResponse):
            _GROUP_ID = HCDF_GROUP
            _COMMAND_ID = 0
            url: str
            sha: str

        _HCDF = (HcdfDescriptionReadRequest, HcdfDescriptionReadResponse)
    return _HCDF


_HCDF: tuple[type[Any], type[Any]] | None = None


async def connect(ep: Endpoint, timeout: float) -> Session:
    return Session(ep, await open_transport(ep, timeout), timeout)
