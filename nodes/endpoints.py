"""Where the bus is: the forwarder's well-known endpoints and, for TCP, CURVE keys.

One forwarder per host. Locally it binds IPC sockets under the runtime directory, so no
node needs another node's address. `FV_BUS` overrides the location:

- ``ipc:///path/base`` (default ``ipc://$XDG_RUNTIME_DIR/fv/bus`` or ``/tmp/fv-<uid>/bus``):
  publishers connect to ``base.pub``, subscribers to ``base.sub``, control to ``base.ctl``.
- ``tcp://host:port``: publishers connect to port, subscribers to port+1, control to
  port+2, always with CURVE encryption and authentication (`FV_CURVE_DIR`).

`FV_CURVE_DIR` holds ``server.key`` (public), ``client.key`` + ``client.key_secret`` for
clients, ``server.key_secret`` and ``authorized/*.key`` (allowed client keys) for the
forwarder; `fv keys DIR` creates them.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.auth

BUS_ENV = "FV_BUS"
CURVE_ENV = "FV_CURVE_DIR"


def default_bus_url() -> str:
    runtime = os.environ.get("XDG_RUNTIME_DIR") or f"/tmp/fv-{os.getuid()}"
    return f"ipc://{runtime}/fv/bus"


@dataclass(frozen=True)
class BusAddress:
    """The three forwarder endpoints of one bus."""

    url: str
    pub: str
    sub: str
    ctl: str

    @property
    def is_tcp(self) -> bool:
        return self.url.startswith("tcp://")

    @property
    def ipc_dir(self) -> Path | None:
        """Folder holding the IPC socket files (None for TCP)."""
        return Path(self.url[len("ipc://"):]).parent if self.url.startswith("ipc://") else None

    @property
    def ipc_files(self) -> tuple[Path, ...]:
        """The IPC socket files of the pub, sub and ctl endpoints (none for TCP)."""
        return () if self.is_tcp else tuple(Path(e[len("ipc://"):]) for e in (self.pub, self.sub, self.ctl))


def bus_address(url: str | None = None) -> BusAddress:
    """Endpoints for `url` (default: `FV_BUS`, else the per-user IPC path)."""
    url = url or os.environ.get(BUS_ENV) or default_bus_url()
    if url.startswith("ipc://"):
        return BusAddress(url, url + ".pub", url + ".sub", url + ".ctl")
    if url.startswith("tcp://"):
        host, _, port = url[len("tcp://"):].rpartition(":")
        if not host or not port.isdigit():
            raise ValueError(f"{BUS_ENV}={url!r}: expected tcp://HOST:PORT")
        p = int(port)
        return BusAddress(url, f"tcp://{host}:{p}", f"tcp://{host}:{p + 1}", f"tcp://{host}:{p + 2}")
    raise ValueError(f"{BUS_ENV}={url!r}: expected ipc://PATH or tcp://HOST:PORT")


def curve_dir() -> Path | None:
    value = os.environ.get(CURVE_ENV)
    return Path(value) if value else None


def _load(path: Path) -> tuple[bytes, bytes | None]:
    if not path.is_file():
        raise FileNotFoundError(f"CURVE key file {path} not found ({CURVE_ENV} must hold the keys made by `fv keys`)")
    return zmq.auth.load_certificate(str(path))


def secure_client(sock: zmq.Socket, address: BusAddress) -> None:
    """Configure `sock` as a CURVE client when the bus is TCP (IPC needs no keys)."""
    if not address.is_tcp:
        return
    keys = curve_dir()
    if keys is None:
        raise RuntimeError(f"bus {address.url} is TCP: set {CURVE_ENV} to a folder made by `fv keys`")
    server_public, _ = _load(keys / "server.key")
    client_public, client_secret = _load(keys / "client.key_secret")
    sock.curve_serverkey = server_public
    sock.curve_publickey = client_public
    sock.curve_secretkey = client_secret


def secure_server(sock: zmq.Socket, keys: Path) -> None:
    """Configure `sock` as a CURVE server with the forwarder's secret key."""
    public, secret = _load(keys / "server.key_secret")
    sock.curve_server = True
    sock.curve_publickey = public
    sock.curve_secretkey = secret


def make_keys(folder: Path) -> list[Path]:
    """Create server and client key pairs and authorise the client; returns the files. The secret
    keys are readable by their owner alone (0600); a folder that holds keys already is refused, so
    that the keys copied to the other hosts stay valid."""
    folder = Path(folder)
    existing = sorted(p.name for p in folder.glob("*.key*")) if folder.is_dir() else []
    if existing:
        raise ValueError(f"{folder} holds keys already ({', '.join(existing)}): remove them to make new ones "
                         "(the other hosts then need the new client keys)")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "authorized").mkdir(exist_ok=True)
    umask = os.umask(0o077)  # the secret keys are never readable by others, not even for a moment
    try:
        server_pub, server_sec = zmq.auth.create_certificates(str(folder), "server")
        client_pub, client_sec = zmq.auth.create_certificates(str(folder), "client")
    finally:
        os.umask(umask)
    for public in (server_pub, client_pub):
        os.chmod(public, 0o644)
    authorized = folder / "authorized" / "client.key"
    authorized.write_bytes(Path(client_pub).read_bytes())
    return [Path(p) for p in (server_pub, server_sec, client_pub, client_sec)] + [authorized]
