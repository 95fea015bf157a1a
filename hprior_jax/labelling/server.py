"""Serving a query folder: where (address, port, access token) and how (uvicorn in the
foreground for `hprior label`, or in a background thread while a run waits for answers)."""
from __future__ import annotations

import secrets
import socket
import threading
import time
from dataclasses import dataclass, replace

from hprior_jax.labelling.app import make_app
from hprior_jax.labelling.store import QueryFolder

LOOPBACK = ("127.0.0.1", "localhost", "::1")


@dataclass(frozen=True)
class ServerOptions:
    host: str = "127.0.0.1"
    port: int = 8765  # 0: any free port (tests)
    token: str | None = None

    def resolved(self) -> "ServerOptions":
        """With an access token made up where the address is not loopback and none was
        given: a page served beyond this machine answers only those who have the token."""
        if self.token is None and self.host not in LOOPBACK:
            return replace(self, token=secrets.token_urlsafe(16))
        return self

    def check(self, host_flag: str = "--host", port_flag: str = "--port") -> "ServerOptions":
        """Refuses, before anything is written or served, a port out of range and an address
        this machine cannot serve on (naming the flag)."""
        if not 0 <= self.port <= 65535:
            raise ValueError(f"{port_flag} {self.port}: a port is 1-65535 (0: any free one)")
        try:
            family = socket.getaddrinfo(self.host, None)[0][0]
            with socket.socket(family, socket.SOCK_STREAM) as probe:
                probe.bind((self.host, 0))  # any free port: only the address is checked
        except (OSError, UnicodeError) as e:
            reason = getattr(e, "strerror", None) or str(e)
            raise ValueError(f"{host_flag} {self.host}: this machine cannot serve on it "
                             f"({reason}); give one of its addresses, e.g. 127.0.0.1 or "
                             "0.0.0.0 (every interface)") from None
        return self

    def url(self, port: int | None = None) -> str:
        shown = "127.0.0.1" if self.host in ("0.0.0.0", "::") else self.host
        return (f"http://{shown}:{self.port if port is None else port}/"
                + (f"?token={self.token}" if self.token else ""))


def _app(folder: QueryFolder, options: ServerOptions):
    return make_app(folder, options.token)


def serve(folder: QueryFolder, options: ServerOptions) -> None:
    """Serves until Ctrl-C (uvicorn handles it)."""
    import uvicorn

    uvicorn.run(_app(folder, options), host=options.host, port=options.port,
                log_level="warning")


class BackgroundServer:
    """The app served from a daemon thread of this process (a run that waits for a person's
    answers): the socket is bound here, so a port in use fails at once and port 0 works."""

    def __init__(self, folder: QueryFolder, options: ServerOptions):
        import uvicorn

        family = socket.AF_INET6 if ":" in options.host else socket.AF_INET
        self._socket = socket.socket(family, socket.SOCK_STREAM)
        self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._socket.bind((options.host, options.port))
        except OSError as e:
            self._socket.close()
            raise OSError(f"cannot serve the labelling page on {options.host}:{options.port} "
                          f"({e.strerror}); choose another with --label-port") from None
        self.url = options.url(self._socket.getsockname()[1])
        self._server = uvicorn.Server(uvicorn.Config(_app(folder, options), log_level="warning"))
        self._thread = threading.Thread(target=self._server.run,
                                        kwargs={"sockets": [self._socket]}, daemon=True)
        self._thread.start()
        deadline = time.monotonic() + 30
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"the labelling server did not start on {self.url}")
            time.sleep(0.02)

    def close(self) -> None:
        self._server.should_exit = True
        self._thread.join(timeout=10)
        self._socket.close()
