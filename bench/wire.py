"""Bare HTTP/1.1 and WebSocket clients for the benchmarks.

The load generator shares the machine with the server it measures, so it must
cost far less per message than the server does; a general-purpose client costs
about as much per request as the server's handling of it.
"""

from __future__ import annotations

import asyncio
import struct

_MASK = b"\x00\x00\x00\x00"
"""A client frame must be masked; a zero key leaves the payload as it is, so none is copied."""


class Connection:
    """A keep-alive HTTP/1.1 connection, opened at the first request and again after a failure."""

    def __init__(self, host: str, port: int, key: str) -> None:
        self.host, self.port, self.key = host, port, key
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def request(self, method: str, path: str, body: bytes = b"") -> tuple[int, bytes]:
        """Send one request; return the status code and the body of the answer."""
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        head = (
            f"{method} {path} HTTP/1.1\r\nHost: {self.host}\r\nAuthorization: Bearer {self.key}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
        )
        self.writer.write(head.encode() + body)
        assert self.reader is not None
        header = await self.reader.readuntil(b"\r\n\r\n")
        status = int(header[9:12])
        length = 0
        for line in header.split(b"\r\n"):
            if line.lower().startswith(b"content-length:"):
                length = int(line.split(b":")[1])
        return status, await self.reader.readexactly(length)

    async def post(self, path: str, body: bytes) -> int:
        """Send one POST and return the status code."""
        return (await self.request("POST", path, body))[0]

    def close(self) -> None:
        """Drop the connection; the next request opens a new one."""
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None


class Socket:
    """A WebSocket client for text messages: answers pings, ends at the server's close."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    @classmethod
    async def open(cls, host: str, port: int, path: str) -> Socket:
        """Connect and upgrade; raise ConnectionError when the server refuses the upgrade."""
        reader, writer = await asyncio.open_connection(host, port)
        writer.write(
            f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
            "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n".encode()
        )
        header = await reader.readuntil(b"\r\n\r\n")
        if header[9:12] != b"101":
            writer.close()
            raise ConnectionError(f"upgrade refused: {header[:12].decode(errors='replace')}")
        return cls(reader, writer)

    def _frame(self, opcode: int, payload: bytes) -> None:
        n = len(payload)
        if n < 126:
            head = struct.pack("!BB", 0x80 | opcode, 0x80 | n)
        elif n < 65536:
            head = struct.pack("!BBH", 0x80 | opcode, 0x80 | 126, n)
        else:
            head = struct.pack("!BBQ", 0x80 | opcode, 0x80 | 127, n)
        self.writer.write(head + _MASK + payload)

    def send(self, text: bytes) -> None:
        """Queue one text message (UTF-8 bytes)."""
        self._frame(0x1, text)

    async def receive(self) -> bytes:
        """Return the next text message; raise EOFError when the server closes."""
        while True:
            first, second = await self.reader.readexactly(2)
            n = second & 0x7F
            if n == 126:
                (n,) = struct.unpack("!H", await self.reader.readexactly(2))
            elif n == 127:
                (n,) = struct.unpack("!Q", await self.reader.readexactly(8))
            payload = await self.reader.readexactly(n)
            opcode = first & 0x0F
            if opcode == 0x9:
                self._frame(0xA, payload)
            elif opcode == 0x8:
                raise EOFError("the server closed the socket")
            elif opcode in (0x1, 0x2):
                return payload

    def close(self) -> None:
        """Close without the closing handshake: the benchmark is done with it."""
        self.writer.close()
