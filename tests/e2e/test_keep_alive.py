"""`locus serve` keeps an idle HTTP connection open for ``LOCUS_KEEP_ALIVE_S``, not for
uvicorn's own 5 s."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tests.conftest import LiveServer

REQUEST = b"GET /healthz HTTP/1.1\r\nHost: locus\r\n\r\n"


def _answered(conn: socket.socket) -> bool:
    """Send one request on ``conn`` and read its whole answer; True when it is a 200, False
    when the server has closed the connection."""
    try:
        conn.sendall(REQUEST)
        answer = b""
        while b"\r\n\r\n" not in answer:
            chunk = conn.recv(4096)
            if not chunk:
                return False
            answer += chunk
        head, body = answer.split(b"\r\n\r\n", 1)
        length = next(
            int(line.split(b":")[1])
            for line in head.split(b"\r\n")
            if line.lower().startswith(b"content-length:")
        )
        while len(body) < length:
            chunk = conn.recv(4096)
            if not chunk:
                return False
            body += chunk
        return head.startswith(b"HTTP/1.1 200")
    except (BrokenPipeError, ConnectionResetError):
        return False


def test_idle_connection_lives_as_long_as_the_setting_says(
    new_database: Callable[[], Any], tmp_path: Path
) -> None:
    server = LiveServer(
        database_url=new_database(), home=tmp_path, workers=1, env={"LOCUS_KEEP_ALIVE_S": "2"}
    )
    try:
        port = int(server.url.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=10) as conn:
            assert _answered(conn)
            time.sleep(1.0)
            # idle for less than the setting: the same connection answers
            assert _answered(conn)
            time.sleep(3.5)
            # idle for longer than the setting (and less than uvicorn's 5 s): closed
            conn.settimeout(2)
            assert not _answered(conn)
    finally:
        server.stop()
