"""Transport security for the nodes' topics: a private certificate authority, one certificate
per participant, one Fast DDS XML profile per participant that carries all of its DDS traffic
over TLS on TCP (``orbit-tracking security``; :mod:`orbit_tracking.tools.security_check`
probes a running participant; docs/SECURITY.md has the why and the evidence).

The Fast DDS of the ROS 2 Jazzy wheels (``ros-jazzy-rmw-fastrtps-cpp``, Fast DDS 2.14) is built
without the DDS Security plugins, so sros2 enclaves cannot be used. It has TLS for its TCPv4
transport, with three traps this module works around:

* the profile file is read from ``FASTRTPS_DEFAULT_PROFILES_FILE`` (``FASTDDS_...`` is the 3.x
  name and is ignored), and a ``DEFAULT_FASTRTPS_PROFILES.xml`` in the working directory is
  loaded after it unless ``SKIP_DEFAULT_XML_FILE=1``;
* with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` rmw_fastrtps appends a shared-memory and a
  UDPv4 transport to whatever the profile says: secured processes need ``SYSTEM_DEFAULT``;
* the accepting end of a TLS connection never asks for a client certificate (Fast DDS sets the
  verify mode on an accepted socket only after its handshake), so anybody speaking TLS without
  a certificate gets in. An OpenSSL configuration (``OPENSSL_CONF``) whose ``system_default``
  section says ``VerifyMode = Peer,Require`` makes every TLS context of the bundled OpenSSL
  1.1.1 require and verify the peer's certificate.

Each profile turns the built-in transports off (UDPv4 and shared memory), adds one TCPv4
transport with ``<tls>`` (the private CA as the only trust anchor, the participant's
certificate and key, TLS 1.2+), listens on the participant's own address and port, and lists as
discovery peers the participants it connects to: Fast DDS 2.14 lets the end with the lower
port connect, and two participants that both list each other keep dropping each other's
connection.

Certificates and keys come from the ``cryptography`` package (ECDSA P-256, SHA-256, so no DH
parameter file is needed); keys are written with mode 0600. The CA key is not kept.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import re
import shutil
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

__all__ = [
    'ANNOUNCEMENT_PERIOD_S',
    'DEFAULT_BASE_PORT',
    'DEFAULT_HOST',
    'TLS_OPTIONS',
    'TLS_VERIFY_MODES',
    'UNSET_VARIABLES',
    'CertificateAuthority',
    'Participant',
    'SecurityLayout',
    'TlsFiles',
    'connects_to',
    'environment',
    'init_security',
    'issue_certificate',
    'load_layout',
    'make_ca',
    'openssl_conf',
    'parse_participants',
    'profile_xml',
    'write_certificate',
    'write_private_key',
]

DEFAULT_BASE_PORT = 17400
"""First TCP listening port handed out by ``security init`` (one port per participant)."""

DEFAULT_HOST = '127.0.0.1'
"""Address the participants listen on and reach each other at, unless given per participant."""

TLS_VERIFY_MODES = ('VERIFY_PEER', 'VERIFY_FAIL_IF_NO_PEER_CERT')
"""Fast DDS ``<verify_mode>`` of the profiles. Fast DDS 2.14 applies only the first of these
(an ``else if`` chain), and only on connections it opens; :func:`openssl_conf` does the rest."""

TLS_OPTIONS = ('NO_SSLV2', 'NO_SSLV3', 'NO_TLSV1', 'NO_TLSV1_1', 'NO_COMPRESSION')
"""Fast DDS ``<options>``: only TLS 1.2 and 1.3 are offered or accepted; no compression."""

ANNOUNCEMENT_PERIOD_S = 1
"""Discovery announcement period of the profiles. Over TCP a participant is reached only when
an announcement of it gets through, so it bounds how soon late starters find each other
(measured with three participants started 2 s apart: first messages after about 2.5 s
instead of 6.5 s with Fast DDS's default of 3 s)."""

UNSET_VARIABLES = ('ROS_LOCALHOST_ONLY',)
"""Variables a secured process must not have (``ROS_LOCALHOST_ONLY=1`` means LOCALHOST)."""

TRANSPORT_ID = 'orbit_tracking_tls'
PROFILE_FILE = 'profile.xml'
CA_CERT_FILE = 'ca.crt'
OPENSSL_CONF_FILE = 'openssl.cnf'
MARKER_FILE = '.orbit-tracking-security'
_XMLNS = '{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}'

_NAME = re.compile(r'^[A-Za-z][A-Za-z0-9_-]{0,62}$')


@dataclass(frozen=True)
class Participant:
    """One DDS participant (one process): its name, the address it listens on, its TCP port."""

    name: str
    host: str
    port: int

    def __post_init__(self) -> None:
        if not _NAME.match(self.name):
            raise ValueError(
                f'participant name {self.name!r} must start with a letter and hold only '
                'letters, digits, "_" and "-" (at most 63 characters)'
            )
        try:
            address = ipaddress.IPv4Address(self.host)
        except ValueError:
            raise ValueError(
                f'participant {self.name}: {self.host!r} is not an IPv4 address '
                '(Fast DDS TCPv4 locators need a numeric address)'
            ) from None
        if address.is_unspecified or address.is_multicast:
            raise ValueError(
                f'participant {self.name}: {self.host} cannot be listened on and connected to; '
                "give the host's own unicast address"
            )
        if not 1 <= self.port <= 65535:
            raise ValueError(f'participant {self.name}: port {self.port} is not in 1..65535')


@dataclass(frozen=True)
class TlsFiles:
    """The ``<tls>`` block of a profile: trust anchor, own certificate and key (PEM paths).

    ``verify=False`` writes ``VERIFY_NONE`` (the peer's certificate is not checked); the test
    suite uses it, and missing files, to play strangers. Give absolute paths: Fast DDS resolves
    relative ones against the working directory of the process.
    """

    ca_certificate: Path | None
    certificate: Path | None
    key: Path | None
    verify: bool = True


@dataclass(frozen=True)
class CertificateAuthority:
    """A CA certificate and its private key (``cryptography`` objects)."""

    certificate: Any
    key: Any


@dataclass(frozen=True)
class SecurityLayout:
    """A folder written by :func:`init_security`: the CA certificate, the OpenSSL
    configuration and, per participant, a folder with its certificate, key and profile."""

    directory: Path
    participants: tuple[Participant, ...]

    @property
    def ca_certificate(self) -> Path:
        return self.directory / CA_CERT_FILE

    @property
    def openssl_conf(self) -> Path:
        return self.directory / OPENSSL_CONF_FILE

    def participant(self, name: str) -> Participant:
        for p in self.participants:
            if p.name == name:
                return p
        known = ', '.join(p.name for p in self.participants)
        raise ValueError(f'no participant {name!r} in {self.directory} (it has: {known})')

    def folder(self, name: str) -> Path:
        return self.directory / name

    def certificate(self, name: str) -> Path:
        return self.folder(name) / f'{name}.crt'

    def key(self, name: str) -> Path:
        return self.folder(name) / f'{name}.key'

    def profile(self, name: str) -> Path:
        """The Fast DDS XML profile to start participant ``name`` with."""
        return self.folder(name) / PROFILE_FILE

    def tls_files(self, name: str) -> TlsFiles:
        return TlsFiles(self.ca_certificate, self.certificate(name), self.key(name))


def parse_participants(
    spec: str | Sequence[str], base_port: int = DEFAULT_BASE_PORT, host: str = DEFAULT_HOST
) -> tuple[Participant, ...]:
    """Participants from ``NAME[@HOST][:PORT]`` items (a comma-separated string or a list).

    A participant without ``@HOST`` listens on ``host``; one without ``:PORT`` gets
    ``base_port + i`` (``i`` its position in the list). Names and (host, port) pairs must be
    unique.
    """
    items = spec.split(',') if isinstance(spec, str) else list(spec)
    items = [item.strip() for item in items if item.strip()]
    if not items:
        raise ValueError('no participants given (e.g. --participants estimator,results)')
    out: list[Participant] = []
    for i, item in enumerate(items):
        m = re.fullmatch(r'([^@:]+)(?:@([^:]+))?(?::(\d+))?', item)
        if not m:
            raise ValueError(f'participant {item!r} is not NAME[@HOST][:PORT]')
        port = int(m.group(3)) if m.group(3) else base_port + i
        out.append(Participant(m.group(1), m.group(2) or host, port))
    names = [p.name for p in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f'participant names must be unique; repeated: {", ".join(dup)}')
    endpoints = [(p.host, p.port) for p in out]
    clash = sorted({f'{h}:{p}' for h, p in endpoints if endpoints.count((h, p)) > 1})
    if clash:
        raise ValueError(f'two participants would listen on the same port: {", ".join(clash)}')
    return tuple(out)


def connects_to(me: Participant, other: Participant) -> bool:
    """Whether ``me`` opens the TCP connection to ``other`` (and so lists it as a peer).

    Fast DDS 2.14 (``TCPTransportInterface::OpenOutputChannel``) connects when the remote port
    is higher than its own listening port, or equal with its own address lower; the other end
    waits. Listing a peer the other way round makes both ends connect, and the two
    connections keep replacing each other (no message gets through).
    """
    return (me.port, int(ipaddress.IPv4Address(me.host))) < (
        other.port,
        int(ipaddress.IPv4Address(other.host)),
    )


def _name(common_name: str) -> Any:
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, 'orbit_tracking'),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def _validity(days: int) -> tuple[datetime.datetime, datetime.datetime]:
    if days < 1:
        raise ValueError(f'certificate validity must be at least 1 day; got {days}')
    # back-dated a little: a peer whose clock is slightly behind still accepts the certificate
    now = datetime.datetime.now(datetime.UTC)
    return now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)


def _key_usage(*, sign_certificates: bool) -> Any:
    from cryptography import x509

    return x509.KeyUsage(
        digital_signature=not sign_certificates,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=not sign_certificates,
        key_cert_sign=sign_certificates,
        crl_sign=sign_certificates,
        encipher_only=False,
        decipher_only=False,
    )


def make_ca(common_name: str = 'orbit_tracking CA', days: int = 365) -> CertificateAuthority:
    """A new self-signed CA (ECDSA P-256) that may sign participant certificates only."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec

    key = ec.generate_private_key(ec.SECP256R1())
    not_before, not_after = _validity(days)
    name = _name(common_name)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before)
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(sign_certificates=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), False)
        .sign(key, hashes.SHA256())
    )
    return CertificateAuthority(cert, key)


def issue_certificate(
    ca: CertificateAuthority, participant: Participant, days: int = 365
) -> tuple[Any, Any]:
    """A certificate signed by ``ca`` for ``participant`` and its key (ECDSA P-256).

    Good for both TLS roles (a participant accepts connections and opens them); it names the
    participant as CN and DNS name and carries its address as an IP name.
    """
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = ec.generate_private_key(ec.SECP256R1())
    not_before, not_after = _validity(days)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(participant.name))
        .issuer_name(ca.certificate.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before)
        .not_valid_after(min(not_after, ca.certificate.not_valid_after_utc))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(sign_certificates=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(
            x509.SubjectAlternativeName(
                [
                    x509.DNSName(participant.name),
                    x509.IPAddress(ipaddress.IPv4Address(participant.host)),
                ]
            ),
            critical=False,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca.key.public_key()), False
        )
        .sign(ca.key, hashes.SHA256())
    )
    return cert, key


def _write(path: Path, data: bytes, mode: int) -> None:
    # created with its final mode: a key is never readable by others, not even briefly
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.fchmod(fd, mode)
        os.write(fd, data)
    finally:
        os.close(fd)


def write_certificate(path: Path, cert: Any) -> None:
    """``cert`` as PEM, mode 0644."""
    from cryptography.hazmat.primitives import serialization

    _write(path, cert.public_bytes(serialization.Encoding.PEM), 0o644)


def write_private_key(path: Path, key: Any) -> None:
    """``key`` as unencrypted PKCS#8 PEM, mode 0600 (only its owner may read it)."""
    from cryptography.hazmat.primitives import serialization

    data = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    _write(path, data, 0o600)


def _locator(host: str, port: int, indent: str) -> str:
    return (
        f'{indent}<locator>\n'
        f'{indent}  <tcpv4>\n'
        f'{indent}    <address>{escape(host)}</address>\n'
        f'{indent}    <physical_port>{port}</physical_port>\n'
        f'{indent}  </tcpv4>\n'
        f'{indent}</locator>\n'
    )


def _tls_xml(tls: TlsFiles) -> str:
    lines = ['        <tls>']
    for tag, path in (
        ('verify_file', tls.ca_certificate),
        ('cert_chain_file', tls.certificate),
        ('private_key_file', tls.key),
    ):
        if path is not None:
            lines.append(f'          <{tag}>{escape(str(path))}</{tag}>')
    modes = TLS_VERIFY_MODES if tls.verify else ('VERIFY_NONE',)
    lines.append('          <verify_mode>')
    lines += [f'            <verify>{m}</verify>' for m in modes]
    lines.append('          </verify_mode>')
    lines.append('          <options>')
    lines += [f'            <option>{o}</option>' for o in TLS_OPTIONS]
    lines.append('          </options>')
    lines.append('        </tls>')
    return '\n'.join(lines) + '\n'


def profile_xml(me: Participant, peers: Sequence[Participant], tls: TlsFiles | None) -> str:
    """The Fast DDS XML profile (the default participant profile) of participant ``me``.

    TCPv4 only, listening on ``me.host:me.port``; ``peers`` are the discovery peers it
    connects to (see :func:`connects_to`). ``tls=None`` writes plain TCP: the test suite's
    control case, never for a node that needs protection.
    """
    peers_xml = ''.join(_locator(p.host, p.port, '            ') for p in peers)
    if peers_xml:
        peers_xml = f'          <initialPeersList>\n{peers_xml}          </initialPeersList>\n'
    kind = 'TLS over TCPv4' if tls is not None else 'plain TCPv4, NO TLS (test control only)'
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<!-- orbit-tracking security: participant {escape(me.name)}, {kind}.\n'
        '     Use it through `orbit-tracking security env` (FASTRTPS_DEFAULT_PROFILES_FILE,\n'
        '     OPENSSL_CONF, ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT, ...); one process per\n'
        '     profile. See docs/SECURITY.md. -->\n'
        '<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">\n'
        '  <profiles>\n'
        '    <transport_descriptors>\n'
        '      <transport_descriptor>\n'
        f'        <transport_id>{TRANSPORT_ID}</transport_id>\n'
        '        <type>TCPv4</type>\n'
        '        <interfaceWhiteList>\n'
        f'          <address>{escape(me.host)}</address>\n'
        '        </interfaceWhiteList>\n'
        '        <listening_ports>\n'
        f'          <port>{me.port}</port>\n'
        '        </listening_ports>\n'
        f'{_tls_xml(tls) if tls is not None else ""}'
        '      </transport_descriptor>\n'
        '    </transport_descriptors>\n'
        f'    <participant profile_name="orbit_tracking_{escape(me.name)}"'
        ' is_default_profile="true">\n'
        '      <rtps>\n'
        '        <!-- no UDPv4, no shared memory: this TCP transport is the only way in -->\n'
        '        <useBuiltinTransports>false</useBuiltinTransports>\n'
        '        <userTransports>\n'
        f'          <transport_id>{TRANSPORT_ID}</transport_id>\n'
        '        </userTransports>\n'
        '        <builtin>\n'
        '          <discovery_config>\n'
        '            <!-- announce every second (default 3 s): a peer that was not up yet when\n'
        '                 this one first tried to connect is reached sooner -->\n'
        '            <leaseAnnouncement>\n'
        f'              <sec>{ANNOUNCEMENT_PERIOD_S}</sec>\n'
        '            </leaseAnnouncement>\n'
        '          </discovery_config>\n'
        '          <metatrafficUnicastLocatorList>\n'
        f'{_locator(me.host, me.port, "            ")}'
        '          </metatrafficUnicastLocatorList>\n'
        f'{peers_xml}'
        '        </builtin>\n'
        '        <defaultUnicastLocatorList>\n'
        f'{_locator(me.host, me.port, "          ")}'
        '        </defaultUnicastLocatorList>\n'
        '      </rtps>\n'
        '    </participant>\n'
        '  </profiles>\n'
        '</dds>\n'
    )


def openssl_conf() -> str:
    """The OpenSSL configuration every secured process loads (``OPENSSL_CONF``).

    Its ``system_default`` section applies to every TLS context OpenSSL creates in the process:
    ``VerifyMode = Peer,Require`` makes the accepting end of a connection require a client
    certificate that chains to the profile's CA (Fast DDS 2.14 never asks for one there), and
    ``MinProtocol`` repeats the profile's TLS 1.2 floor.
    """
    return (
        '# orbit-tracking security: OpenSSL settings of the secured DDS processes\n'
        '# (OPENSSL_CONF=<this file>). Without it Fast DDS accepts TLS clients that present\n'
        '# no certificate at all; see docs/SECURITY.md.\n'
        'openssl_conf = orbit_tracking_openssl\n'
        '\n'
        '[orbit_tracking_openssl]\n'
        'ssl_conf = orbit_tracking_ssl\n'
        '\n'
        '[orbit_tracking_ssl]\n'
        'system_default = orbit_tracking_tls\n'
        '\n'
        '[orbit_tracking_tls]\n'
        'MinProtocol = TLSv1.2\n'
        'VerifyMode = Peer,Require\n'
    )


def environment(layout: SecurityLayout, name: str) -> dict[str, str]:
    """The environment variables that make a process participant ``name`` (set them all, and
    unset :data:`UNSET_VARIABLES`)."""
    layout.participant(name)
    return {
        'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp',
        'FASTRTPS_DEFAULT_PROFILES_FILE': str(layout.profile(name)),
        'SKIP_DEFAULT_XML_FILE': '1',
        'OPENSSL_CONF': str(layout.openssl_conf),
        'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SYSTEM_DEFAULT',
    }


def _prepare_directory(directory: Path, force: bool) -> None:
    if directory.exists() or directory.is_symlink():
        if not force:
            raise FileExistsError(f'{directory} exists; pass --force to replace it')
        if not directory.is_dir() or directory.is_symlink():
            raise FileExistsError(f'{directory} exists and is not a folder')
        if any(directory.iterdir()) and not (directory / MARKER_FILE).is_file():
            # --force never deletes a folder this command did not make
            raise FileExistsError(
                f'{directory} is not empty and was not made by `orbit-tracking security init`;'
                ' not replacing it, even with --force'
            )
        shutil.rmtree(directory)
    directory.mkdir(parents=True, mode=0o700)
    os.chmod(directory, 0o700)


def init_security(
    directory: str | Path,
    participants: Sequence[Participant],
    days: int = 365,
    force: bool = False,
) -> SecurityLayout:
    """Write a new CA certificate, one certificate, key and profile per participant, and the
    OpenSSL configuration, into ``directory`` (made with mode 0700)::

        directory/ca.crt  openssl.cnf
        directory/<name>/<name>.crt  <name>.key (0600)  profile.xml

    The CA's key is thrown away once the certificates are signed: nobody can issue another
    certificate from this folder; to add a participant, run it again (``force``) and hand out
    the new files. Refuses an existing ``directory`` unless ``force`` (then it is replaced, if
    this function made it).
    """
    if not participants:
        raise ValueError('at least one participant is needed')
    directory = Path(directory).absolute()
    _validity(days)
    _prepare_directory(directory, force)
    layout = SecurityLayout(directory, tuple(participants))
    ca = make_ca(days=days)
    write_certificate(layout.ca_certificate, ca.certificate)
    _write(layout.openssl_conf, openssl_conf().encode(), 0o644)
    for p in participants:
        layout.folder(p.name).mkdir(mode=0o700)
        cert, key = issue_certificate(ca, p, days)
        write_certificate(layout.certificate(p.name), cert)
        write_private_key(layout.key(p.name), key)
        peers = [q for q in participants if connects_to(p, q)]
        xml = profile_xml(p, peers, layout.tls_files(p.name))
        _write(layout.profile(p.name), xml.encode(), 0o644)
    _write(directory / MARKER_FILE, b'made by orbit-tracking security init\n', 0o644)
    return layout


def load_layout(directory: str | Path) -> SecurityLayout:
    """The layout of a folder written by :func:`init_security` (participants read back from
    their profiles)."""
    directory = Path(directory).absolute()
    if not (directory / MARKER_FILE).is_file():
        raise FileNotFoundError(
            f'{directory} is not a folder made by `orbit-tracking security init`'
        )
    participants = []
    for profile in sorted(directory.glob(f'*/{PROFILE_FILE}')):
        root = ET.parse(profile).getroot()
        host = root.find(f'.//{_XMLNS}interfaceWhiteList/{_XMLNS}address')
        port = root.find(f'.//{_XMLNS}listening_ports/{_XMLNS}port')
        if host is None or port is None or not host.text or not port.text:
            raise ValueError(f'{profile}: no listening address and port')
        participants.append(Participant(profile.parent.name, host.text, int(port.text)))
    return SecurityLayout(directory, tuple(participants))
