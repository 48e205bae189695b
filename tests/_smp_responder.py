"""An in-process SMP server on 127.0.0.1 (UDP), built from the ``smp`` package's models:
well-behaved devices of any image state, devices with the HCDF group (100), and hostile
ones. Neither smp nor smpclient ships a server; this one answers the requests fleet
sends: MCUmgr parameters, image state read/write, image upload, HCDF description.
"""

from __future__ import annotations

import asyncio
import hashlib
import struct
import threading
from dataclasses import dataclass, field
from typing import Any

import cbor2
from smp import header as smphdr
from smp import image_management as img
from smp import os_management as osm

HOSTILE_MODES = (
    "wrong-sequence",  # answers with another sequence number
    "oversized",  # a header announcing 65,535 body bytes, then only part of them: an answer that never ends
    "malformed-cbor",  # a body that is not CBOR
    "tagged-cbor",  # a CBOR tag (a bigfloat) inside the answer
    "duplicate-key",  # the image list twice in one map
    "deep-cbor",  # nested 200 deep
    "short-hash",  # an image hash of 20 bytes
    "silent",  # never answers
    "wrong-group",  # answers as another group
)
UPLOAD_MODES = (
    "lying-upload",  # after an upload, slot 1 reports another hash
    "stuck-upload",  # answers every chunk with offset 0
)


@dataclass
class SlotState:
    slot: int
    version: str
    hash: bytes
    active: bool = False
    confirmed: bool = False
    pending: bool = False
    permanent: bool = False
    bootable: bool = True


@dataclass
class FakeDevice:
    """One device's state and behaviour; the test changes it between runs."""

    slots: list[SlotState]
    description: tuple[str, str] | None = None  # (url, sha hex) of the HCDF group; None: no group 100 (rc 8)
    mode: str | None = None  # one of HOSTILE_MODES, or None
    latency: float = 0.0
    upload: bytearray = field(default_factory=bytearray)
    upload_len: int = 0
    upload_sha: bytes = b""
    requests: list[tuple[int, int, int]] = field(default_factory=list)  # (op, group, command) seen

    def answer(self, data: bytes) -> bytes | None:
        head = smphdr.Header.loads(data[:8])
        body = cbor2.loads(data[8:]) if len(data) > 8 else {}
        self.requests.append((int(head.op), int(head.group_id), int(head.command_id)))
        group, cmd, op = int(head.group_id), int(head.command_id), int(head.op)
        seq = head.sequence
        if self.mode == "silent":
            return None
        if (group, cmd) == (0, 6):
            return osm.MCUMgrParametersReadResponse(sequence=seq, buf_size=2048, buf_count=4).BYTES
        if (group, cmd, op) == (1, 0, 0):
            return self._hostile(seq) or self._states(seq)
        if (group, cmd, op) == (1, 0, 2):
            return self._mark(seq, body)
        if (group, cmd, op) == (1, 1, 2):
            return self._upload(seq, body)
        if (group, cmd) == (100, 0):
            if self.description is None:
                return raw_frame(smphdr.OP.READ_RSP, 100, 0, seq, cbor2.dumps({"rc": 8}))
            url, sha = self.description
            return raw_frame(smphdr.OP.READ_RSP, 100, 0, seq, cbor2.dumps({"url": url, "sha": sha}))
        return raw_frame(smphdr.OP(op + 1), group, cmd, seq, cbor2.dumps({"rc": 8}))

    def _images(self) -> list[img.ImageState]:
        return [
            img.ImageState(
                slot=s.slot,
                version=s.version,
                hash=s.hash,
                active=s.active,
                confirmed=s.confirmed,
                pending=s.pending,
                permanent=s.permanent,
                bootable=s.bootable,
            )
            for s in self.slots
        ]

    def _states(self, seq: int) -> bytes:
        return img.ImageStatesReadResponse(sequence=seq, images=self._images()).BYTES

    def _hostile(self, seq: int) -> bytes | None:
        m = self.mode
        body = {"images": [i.model_dump(exclude_none=True) for i in self._images()]}
        if m == "wrong-sequence":
            return img.ImageStatesReadResponse(sequence=(seq + 1) % 256, images=self._images()).BYTES
        if m == "oversized":
            return bytes(smphdr.Header(smphdr.OP.READ_RSP, smphdr.Version.V2, smphdr.Flag(0), 0xFFFF, 1, seq, 0)) + (
                cbor2.dumps(body)
            )
        if m == "malformed-cbor":
            return raw_frame(smphdr.OP.READ_RSP, 1, 0, seq, b"\xbf\x66images\x9f\xbf\x64slot")
        if m == "tagged-cbor":
            return raw_frame(
                smphdr.OP.READ_RSP, 1, 0, seq, b"\xa1\x66images\xc5\x82\x1b\x7f\xff\xff\xff\xff\xff\xff\xff\x01"
            )
        if m == "duplicate-key":
            enc = cbor2.dumps(body["images"])
            return raw_frame(smphdr.OP.READ_RSP, 1, 0, seq, b"\xa2\x66images" + enc + b"\x66images" + enc)
        if m == "deep-cbor":
            return raw_frame(smphdr.OP.READ_RSP, 1, 0, seq, b"\xa1\x66images" + b"\x81" * 200 + b"\x00")
        if m == "short-hash":
            images = [dict(i, hash=i["hash"][:20]) for i in body["images"]]
            return raw_frame(smphdr.OP.READ_RSP, 1, 0, seq, cbor2.dumps({"images": images}))
        if m == "wrong-group":
            return raw_frame(smphdr.OP.READ_RSP, 2, 0, seq, cbor2.dumps(body))
        return None

    def _mark(self, seq: int, body: dict[str, Any]) -> bytes:
        want = body.get("hash")
        confirm = bool(body.get("confirm"))
        target = (
            next((s for s in self.slots if s.hash == want), None) if want else next(s for s in self.slots if s.active)
        )
        if target is None:
            return raw_frame(smphdr.OP.WRITE_RSP, 1, 0, seq, cbor2.dumps({"rc": 3}))
        if target.active:
            target.confirmed = True
        else:
            target.pending = True
            target.permanent = confirm
        # smp's ImageStatesWriteResponse inherits the read response's op (READ_RSP); Zephyr
        # answers a write with WRITE_RSP, as fleet checks: the frame is built with that op
        images = img.ImageStatesWriteResponse(sequence=seq, images=self._images()).BYTES[8:]
        return raw_frame(smphdr.OP.WRITE_RSP, 1, 0, seq, images)

    def _upload(self, seq: int, body: dict[str, Any]) -> bytes:
        off = body["off"]
        if self.mode == "stuck-upload":
            return img.ImageUploadWriteResponse(sequence=seq, off=0).BYTES
        if off == 0:
            if body.get("sha") == self.upload_sha and 0 < len(self.upload) < self.upload_len:
                # Zephyr's resume: the same image again, continue where it stopped
                return img.ImageUploadWriteResponse(sequence=seq, off=len(self.upload)).BYTES
            self.upload = bytearray()
            self.upload_len = body["len"]
            self.upload_sha = body.get("sha", b"")
        if off != len(self.upload):
            return img.ImageUploadWriteResponse(sequence=seq, off=len(self.upload)).BYTES
        self.upload += body["data"]
        if len(self.upload) == self.upload_len:
            version, image_hash = mcuboot_identity(bytes(self.upload))
            if self.mode == "lying-upload":
                image_hash = hashlib.sha256(image_hash).digest()
            self.slots = [s for s in self.slots if s.slot != 1] + [SlotState(1, version, image_hash)]
            return img.ImageUploadWriteResponse(
                sequence=seq, off=len(self.upload), match=hashlib.sha256(self.upload).digest() == self.upload_sha
            ).BYTES
        return img.ImageUploadWriteResponse(sequence=seq, off=len(self.upload)).BYTES


def mcuboot_identity(data: bytes) -> tuple[str, bytes]:
    """What MCUboot (and so the img group) reports for an image: the header's version and
    SHA-256 over header + payload + protected TLVs; read with struct from MCUboot's
    ``struct image_header``, independently of imgtool and of hcdf_trust."""
    magic, _load, hdr_size, prot_tlv_size, img_size, _flags = struct.unpack_from("<IIHHII", data)
    assert magic == 0x96F3B83D
    major, minor, revision, build = struct.unpack_from("<BBHI", data, 20)
    version = f"{major}.{minor}.{revision}" + (f".{build}" if build else "")
    return version, hashlib.sha256(data[: hdr_size + img_size + prot_tlv_size]).digest()


def raw_frame(op: smphdr.OP, group: int, command: int, seq: int, body: bytes) -> bytes:
    head = smphdr.Header(op, smphdr.Version.V2, smphdr.Flag(0), len(body), group, seq, command)
    return bytes(head) + body


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, device: FakeDevice) -> None:
        self.device = device

    def connection_made(self, transport: Any) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr: Any) -> None:
        answer = self.device.answer(data)
        if answer is None:
            return
        if self.device.latency:
            asyncio.get_running_loop().call_later(self.device.latency, self.transport.sendto, answer, addr)
        else:
            self.transport.sendto(answer, addr)


class Responder:
    """Fake devices on 127.0.0.1, served by one event loop in a background thread."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.transports: list[Any] = []

    def add(self, device: FakeDevice) -> str:
        async def start() -> Any:
            transport, _ = await self.loop.create_datagram_endpoint(
                lambda: _Protocol(device), local_addr=("127.0.0.1", 0)
            )
            return transport

        transport = asyncio.run_coroutine_threadsafe(start(), self.loop).result(10)
        self.transports.append(transport)
        port = transport.get_extra_info("sockname")[1]
        return f"udp://127.0.0.1:{port}"

    def close(self) -> None:
        for t in self.transports:
            self.loop.call_soon_threadsafe(t.close)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()
