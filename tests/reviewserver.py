"""A real `kbbatch review` server on an ephemeral port in a thread, and a raw HTTP client."""

from __future__ import annotations

import http.client
import json
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kbbatch.pipeline import ClipOptions
from kbbatch.presets import Preset
from kbbatch.web.app import TOKEN_HEADER, ReviewServer, ReviewSession


@dataclass
class Reply:
    status: int
    headers: dict[str, str]
    body: bytes

    def json(self) -> Any:
        return json.loads(self.body)


@dataclass
class Served:
    url: str
    port: int
    session: ReviewSession
    address: str = "127.0.0.1"

    def request(self, method: str, path: str, body: bytes | None = None,
                headers: dict[str, str | None] | None = None) -> Reply:
        """Send the path exactly as given (no client-side normalisation of '..' or '%2f'),
        with the session's token in its header unless headers name it (None: none sent)."""
        headers = {TOKEN_HEADER: self.session.token} | (headers or {})
        headers = {k: v for k, v in headers.items() if v is not None}
        connection = http.client.HTTPConnection(self.address, self.port, timeout=120)
        try:
            connection.request(method, path, body=body, headers=headers)
            response = connection.getresponse()
            return Reply(response.status, {k.lower(): v for k, v in response.getheaders()},
                         response.read())
        finally:
            connection.close()

    def get(self, path: str, **headers: str) -> Reply:
        return self.request("GET", path, headers=headers)

    def post(self, path: str, data: Any, token: str | None = "session") -> Reply:
        headers = {"Content-Type": "application/json",
                   TOKEN_HEADER: self.session.token if token == "session" else token}
        return self.request("POST", path, json.dumps(data).encode(), headers)

    def wait_planned(self, timeout_s: float = 120) -> dict[str, Any]:
        """/api/photos once every photo is planned (or failed)."""
        deadline = time.monotonic() + timeout_s
        while True:
            overview = self.get("/api/photos").json()
            progress = overview["progress"]
            if progress["done"] == progress["total"]:
                return overview
            if time.monotonic() > deadline:
                raise TimeoutError(f"planning did not finish: {progress}")
            time.sleep(0.2)


@contextmanager
def running_server(folder: Path, manifest: Path, preset: Preset, options: ClipOptions,
                   host: str = "127.0.0.1") -> Iterator[Served]:
    session = ReviewSession(folder, manifest, preset, options, ())
    server = ReviewServer(session, host, 0)
    thread = threading.Thread(target=server.serve, daemon=True)
    thread.start()
    try:
        yield Served(server.url, server.port, session, host.strip("[]"))
    finally:
        server.shutdown()
        thread.join(timeout=10)
