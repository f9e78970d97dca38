"""Probe a running participant's TLS port (``orbit-tracking security check``): a client with
a certificate of the participant's CA must be let in; a client without a certificate, or with
one of another CA, must be turned away, even when it does not check the participant's own
certificate (as an intruder would not). See :mod:`orbit_tracking.tools.security`."""

from __future__ import annotations

import socket
import ssl
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from orbit_tracking.tools.security import (
    Participant,
    SecurityLayout,
    issue_certificate,
    make_ca,
    write_certificate,
    write_private_key,
)

__all__ = ['Probe', 'check_participant', 'probe_tls']


@dataclass(frozen=True)
class Probe:
    """What happened when a TLS client knocked on a participant's port."""

    accepted: bool
    detail: str


def probe_tls(
    host: str,
    port: int,
    ca_certificate: Path | None = None,
    certificate: Path | None = None,
    key: Path | None = None,
    wait_s: float = 1.0,
) -> Probe:
    """Open a TLS connection to ``host:port`` and report whether the far end kept it.

    The client checks the server's certificate against ``ca_certificate`` when given (and not
    at all otherwise, as an intruder would) and presents ``certificate``/``key`` when given. A
    Fast DDS participant says nothing after the handshake, so a connection still open after
    ``wait_s`` seconds counts as accepted; an alert or a close counts as refused.
    """
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    if ca_certificate is not None:
        ctx.load_verify_locations(cafile=str(ca_certificate))
        ctx.verify_mode = ssl.CERT_REQUIRED
    else:
        ctx.verify_mode = ssl.CERT_NONE
    if certificate is not None:
        ctx.load_cert_chain(str(certificate), str(key) if key is not None else None)
    try:
        raw = socket.create_connection((host, port), timeout=5.0)
    except OSError as exc:
        return Probe(False, f'no TCP connection: {exc}')
    with raw:
        try:
            with ctx.wrap_socket(raw) as tls:
                session = f'{tls.version()} {tls.cipher()[0]}'  # type: ignore[index]
                tls.settimeout(wait_s)
                try:
                    data = tls.recv(1)
                except TimeoutError:
                    return Probe(True, f'{session}: connection kept open')
                if not data:
                    return Probe(False, f'{session}: closed by the participant')
                return Probe(True, f'{session}: the participant sent data')
        except ssl.SSLError as exc:
            return Probe(False, f'TLS refused: {exc.reason or exc}')
        except OSError as exc:
            return Probe(False, f'connection dropped: {exc}')


def check_participant(
    layout: SecurityLayout, name: str, attempts: int = 3
) -> list[tuple[str, bool, Probe]]:
    """Probe the running participant ``name``: ``(what, expected accepted, probe)`` per case.

    Cases: its own credentials (must be accepted over TLS 1.2+, with a server certificate of
    the CA), no client certificate, and a certificate of a throwaway CA (both must be refused,
    even though these clients do not check the server at all). The first case is tried up to
    ``attempts`` times, a second apart: Fast DDS handles one handshake at a time on a port, so
    a peer or stranger connecting at the same moment can make one attempt fail.
    """
    me = layout.participant(name)
    own = (layout.ca_certificate, layout.certificate(name), layout.key(name))
    probe = probe_tls(me.host, me.port, *own)
    for _ in range(attempts - 1):
        if probe.accepted:
            break
        time.sleep(1.0)
        probe = probe_tls(me.host, me.port, *own)
    results = [
        ('a certificate of this CA', True, probe),
        ('no client certificate', False, probe_tls(me.host, me.port)),
    ]
    with tempfile.TemporaryDirectory(prefix='orbit-tracking-probe-') as tmp:
        stranger = Participant('stranger', me.host, me.port)
        cert, key = issue_certificate(make_ca('throwaway CA', 1), stranger, 1)
        write_certificate(Path(tmp) / 'stranger.crt', cert)
        write_private_key(Path(tmp) / 'stranger.key', key)
        probe = probe_tls(
            me.host, me.port, None, Path(tmp) / 'stranger.crt', Path(tmp) / 'stranger.key'
        )
        results.append(('a certificate of another CA', False, probe))
    return results
