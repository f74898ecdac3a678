"""Mutual-TLS credentials of one cloud and its edges: a private certificate authority, the cloud's
server certificate and one client certificate per edge, and the ``ssl`` contexts built from them.

The CA's key stays at the cloud (it issues edge certificates); an edge receives the CA certificate
(to check it talks to its own cloud, not an impostor) and its own certificate and key (to prove which
edge it is). The cloud accepts only clients whose certificate this CA signed; the edge accepts only
a server whose certificate this CA signed for :data:`CLOUD_NAME`. Keys are ECDSA P-256; TLS 1.3 only.
"""

from __future__ import annotations

import datetime
import os
import ssl
from dataclasses import dataclass
from pathlib import Path

from infinirl.utils import atomic_open

__all__ = ["CLOUD_NAME", "TlsFiles", "certificate_name", "client_context", "issue_credentials", "server_context"]

#: the name the cloud's certificate is issued for and the edge checks (independent of its address,
#: which differs behind NAT, proxies and the link emulator)
CLOUD_NAME = "infinirl-cloud"
_VALID_DAYS = 3650


@dataclass(frozen=True, kw_only=True)
class TlsFiles:
    """One party's files: the CA certificate it trusts, its own certificate chain and key."""

    ca: str
    cert: str
    key: str

    @classmethod
    def in_folder(cls, folder: str | os.PathLike, name: str) -> TlsFiles:
        """``<folder>/ca.pem``, ``<folder>/<name>.pem``, ``<folder>/<name>.key`` (the layout
        :func:`issue_credentials` writes)."""
        folder = Path(folder)
        return cls(ca=str(folder / "ca.pem"), cert=str(folder / f"{name}.pem"), key=str(folder / f"{name}.key"))

    def check(self) -> None:
        for what, path in (("CA certificate", self.ca), ("certificate", self.cert), ("key", self.key)):
            if not os.path.isfile(path):
                raise FileNotFoundError(f"TLS {what} {path} does not exist; create the files with "
                                        "`python -m infinirl.edge certs <folder> --edges <names>`")


def _write_pem(path: Path, data: bytes, private: bool) -> None:
    with atomic_open(path, "wb", permissions=0o600 if private else None) as handle:  # a key is never readable by others
        handle.write(data)


def _new_key():
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _certificate(*, subject: str, public_key, issuer: str, issuer_key, ca: bool, server: bool):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.timezone.utc)
    builder = (x509.CertificateBuilder()
               .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
               .issuer_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, issuer)]))
               .public_key(public_key).serial_number(x509.random_serial_number())
               .not_valid_before(now - datetime.timedelta(minutes=5))
               .not_valid_after(now + datetime.timedelta(days=_VALID_DAYS))
               .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
    if ca:
        builder = builder.add_extension(x509.KeyUsage(
            digital_signature=True, content_commitment=False, key_encipherment=False, data_encipherment=False,
            key_agreement=False, key_cert_sign=True, crl_sign=True, encipher_only=False, decipher_only=False),
            critical=True)
    else:
        usage = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
        builder = builder.add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
        if server:
            builder = builder.add_extension(x509.SubjectAlternativeName([x509.DNSName(subject)]), critical=False)
    return builder.sign(issuer_key, hashes.SHA256())


def issue_credentials(folder: str | os.PathLike, *, edges: tuple[str, ...] = ("edge-0",),
                      ca_name: str = "infinirl-edge-ca") -> dict[str, TlsFiles]:
    """Write a new CA, the cloud's certificate and one per edge into ``folder``; returns
    ``{"cloud": TlsFiles, <edge>: TlsFiles, ...}``. An existing CA in ``folder`` is reused, so more
    edges can be issued later for the same cloud."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    bad = [name for name in edges if not name or name == "cloud" or name == "ca" or "/" in name]
    if bad:
        raise ValueError(f"edge names {bad} cannot be used: names must be non-empty, not 'cloud' or 'ca', no '/'")

    def private_bytes(key) -> bytes:
        return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                 serialization.NoEncryption())

    ca_cert_path, ca_key_path = folder / "ca.pem", folder / "ca.key"
    if ca_cert_path.exists() and ca_key_path.exists():
        ca_key = serialization.load_pem_private_key(ca_key_path.read_bytes(), password=None)
        ca_name = x509.load_pem_x509_certificate(ca_cert_path.read_bytes()).subject.rfc4514_string()[3:]
    else:
        ca_key = _new_key()
        ca_cert = _certificate(subject=ca_name, public_key=ca_key.public_key(), issuer=ca_name, issuer_key=ca_key,
                               ca=True, server=False)
        _write_pem(ca_key_path, private_bytes(ca_key), private=True)
        _write_pem(ca_cert_path, ca_cert.public_bytes(serialization.Encoding.PEM), private=False)
    issued = {}
    for name, subject, server in (("cloud", CLOUD_NAME, True), *((edge, edge, False) for edge in edges)):
        key = _new_key()
        cert = _certificate(subject=subject, public_key=key.public_key(), issuer=ca_name, issuer_key=ca_key,
                            ca=False, server=server)
        files = TlsFiles.in_folder(folder, name)
        _write_pem(Path(files.key), private_bytes(key), private=True)
        _write_pem(Path(files.cert), cert.public_bytes(serialization.Encoding.PEM), private=False)
        issued[name] = files
    return issued


def certificate_name(path: str | os.PathLike) -> str:
    """The common name in the PEM certificate at ``path`` (an edge's identity at the cloud)."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not names:
        raise ValueError(f"certificate {path} has no common name; issue it with issue_credentials")
    return str(names[0].value)


def _context(purpose: ssl.Purpose, files: TlsFiles) -> ssl.SSLContext:
    files.check()
    context = ssl.create_default_context(purpose, cafile=files.ca)
    context.minimum_version = ssl.TLSVersion.TLSv1_3
    context.load_cert_chain(files.cert, files.key)
    context.verify_mode = ssl.CERT_REQUIRED
    return context


def server_context(files: TlsFiles) -> ssl.SSLContext:
    """The cloud's context: its certificate, and every client must present one the CA signed."""
    return _context(ssl.Purpose.CLIENT_AUTH, files)


def client_context(files: TlsFiles) -> ssl.SSLContext:
    """An edge's context: its certificate, and the server must be the CA's :data:`CLOUD_NAME`."""
    context = _context(ssl.Purpose.SERVER_AUTH, files)
    context.check_hostname = True
    return context
