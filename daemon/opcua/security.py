"""Who may talk to `millsense opcua`: the server's certificate, the trust list, the sessions allowed.

- The only endpoint is Basic256Sha256 with Sign & Encrypt: the channel proves the server (its
  certificate and RSA key) and the client (its application certificate) to each other.
- A client's application certificate must be in the trust list, a directory of DER or PEM files,
  compared byte for byte. The directory is read again at every new session, so a certificate
  copied there is trusted, and one removed is refused, without a restart. A refusal says which
  certificate (subject, SHA-256 thumbprint) so the administrator can trust it on purpose.
- The session's user is the client's X.509 certificate (again one in the trust list); the
  anonymous user only with `--allow-anonymous`, and still over the encrypted, trusted channel.
  There are no user names and passwords: nothing to store, nothing to guess.

Errors here are one line for a user (`OpcuaSetupError`), never a traceback.
"""

from __future__ import annotations

import datetime as dt
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa

log = structlog.get_logger("millsense.opcua")

CERT_SUFFIXES = (".der", ".pem", ".crt", ".cer")
MAX_CERT_BYTES = 65536


class OpcuaSetupError(ValueError):
    """The server cannot start as configured; the message names the option and says why."""


@dataclass(frozen=True)
class ServerIdentity:
    certificate_der: bytes
    private_key_pem: bytes
    application_uri: str


def _read(path: Path, option: str) -> bytes:
    if not path.is_file():
        raise OpcuaSetupError(f"{option} {path}: does not exist (make one: see docs/opcua.md, Certificates)")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise OpcuaSetupError(f"{option} {path}: cannot be read: {exc.strerror or exc}") from None
    if len(data) > MAX_CERT_BYTES:
        raise OpcuaSetupError(f"{option} {path}: over {MAX_CERT_BYTES} bytes: not a certificate or key")
    return data


def parse_certificate(data: bytes) -> x509.Certificate:
    """A certificate from PEM or DER bytes; ValueError when it is neither."""
    if data.lstrip().startswith(b"-----BEGIN"):
        return x509.load_pem_x509_certificate(data)
    return x509.load_der_x509_certificate(data)


def thumbprint(cert_der: bytes) -> str:
    return hashlib.sha256(cert_der).hexdigest()


def application_uri_of(cert: x509.Certificate) -> str | None:
    """The URI in the certificate's subjectAltName: OPC UA's application instance URI."""
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return None
    uris = san.get_values_for_type(x509.UniformResourceIdentifier)
    return uris[0] if uris else None


def load_server_identity(cert_path: Path, key_path: Path) -> ServerIdentity:
    """The server certificate and key, checked to belong together. Raises OpcuaSetupError."""
    cert_data = _read(cert_path, "--cert")
    key_data = _read(key_path, "--key")
    try:
        cert = parse_certificate(cert_data)
    except ValueError:
        raise OpcuaSetupError(f"--cert {cert_path}: not an X.509 certificate (PEM or DER)") from None
    try:
        if key_data.lstrip().startswith(b"-----BEGIN"):
            key = serialization.load_pem_private_key(key_data, password=None)
        else:
            key = serialization.load_der_private_key(key_data, password=None)
    except (ValueError, TypeError) as exc:
        why = "encrypted with a password (give an unencrypted key, readable by this user only)" if "password" in str(
            exc).lower() else "not a private key (PEM or DER)"
        raise OpcuaSetupError(f"--key {key_path}: {why}") from None
    if not isinstance(key, rsa.RSAPrivateKey) or not 2048 <= key.key_size <= 4096:
        raise OpcuaSetupError(f"--key {key_path}: the security policies (Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss) need an RSA key of 2048 to 4096 bits")
    if key.public_key().public_numbers() != cert.public_key().public_numbers():
        raise OpcuaSetupError(f"--key {key_path}: does not belong to the certificate --cert {cert_path}")
    now = dt.datetime.now(dt.timezone.utc)
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        raise OpcuaSetupError(f"--cert {cert_path}: not valid now (valid {cert.not_valid_before_utc:%Y-%m-%d} "
                              f"to {cert.not_valid_after_utc:%Y-%m-%d})")
    uri = application_uri_of(cert)
    if uri is None:
        raise OpcuaSetupError(f"--cert {cert_path}: has no URI in its subjectAltName (OPC UA clients check the "
                              "server's application URI against it)")
    return ServerIdentity(
        certificate_der=cert.public_bytes(serialization.Encoding.DER),
        private_key_pem=key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                          serialization.NoEncryption()),
        application_uri=uri,
    )


class TrustList:
    """The client certificates in a directory, read afresh at each question."""

    def __init__(self, directory: Path, option: str = "--trust-dir") -> None:
        self.directory = directory
        self.option = option  # what an error names

    def check(self) -> int:
        """How many certificates the directory holds now. Raises OpcuaSetupError when it is not a directory."""
        if not self.directory.is_dir():
            raise OpcuaSetupError(f"{self.option} {self.directory}: not a directory (put the client certificates "
                                  "you trust there, one file each)")
        return len(self.trusted())

    def trusted(self) -> dict[bytes, str]:
        """DER bytes → file name of every certificate in the directory; unreadable files are logged and skipped."""
        out: dict[bytes, str] = {}
        try:
            entries = sorted(self.directory.iterdir())
        except OSError as exc:
            log.warning("opcua.trust_list_unreadable", directory=str(self.directory), error=str(exc))
            return out
        for path in entries:
            if path.suffix.lower() not in CERT_SUFFIXES or not path.is_file():
                continue
            try:
                data = path.read_bytes()[:MAX_CERT_BYTES]
                cert = parse_certificate(data)
            except (OSError, ValueError):
                log.warning("opcua.trust_list_bad_file", file=str(path))
                continue
            out[cert.public_bytes(serialization.Encoding.DER)] = path.name
        return out

    def contains(self, cert_der: bytes) -> bool:
        return cert_der in self.trusted()


def client_validator(trust: TrustList, refused: list[str]) -> Any:
    """The asyncua certificate validator: time range, then membership in the trust list.

    Called by asyncua at CreateSession with the client's application certificate; a refusal is a
    ServiceError that the client receives as BadCertificateUntrusted (or TimeInvalid).
    """
    from asyncua import ua
    from asyncua.common.utils import ServiceError

    async def validate(cert: x509.Certificate, app_description: Any) -> None:
        der = cert.public_bytes(serialization.Encoding.DER)
        subject = cert.subject.rfc4514_string() or "(no subject)"
        now = dt.datetime.now(dt.timezone.utc)
        if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
            refused.append(f"client certificate {subject} is not valid now")
            log.warning("opcua.client_refused", reason="certificate not valid now", subject=subject,
                        sha256=thumbprint(der))
            raise ServiceError(ua.StatusCodes.BadCertificateTimeInvalid)
        if not trust.contains(der):
            refused.append(f"client certificate {subject} is not in the trust list")
            log.warning("opcua.client_refused", reason="certificate not in the trust list", subject=subject,
                        sha256=thumbprint(der), hint=f"copy it into {trust.directory} to trust it")
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)

    return validate


class SessionUsers:
    """asyncua's user manager: every session's certificate must be in the trust list; those also in the
    operators' folder may acknowledge and confirm alarms (acknowledge.py)."""

    def __init__(self, trust: TrustList, operators: TrustList | None = None) -> None:
        self.trust = trust
        self.operators = operators

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> Any:
        """The session's user, or None to refuse it (the client gets BadUserAccessDenied).

        asyncua passes the X.509 user token's certificate, or for any other token the certificate
        of the secure channel: either way it must be in the trust list. An anonymous token reaches
        here only with --allow-anonymous (`identity_tokens`), and a channel without a certificate
        (security None, offered by no endpoint but open for discovery) never gets a session.
        """
        from asyncua.crypto.permission_rules import UserRole

        from millsense.daemon.opcua.acknowledge import SessionUser

        if username is not None:
            log.warning("opcua.user_refused", reason="user names and passwords are not accepted")
            return None
        if not certificate:
            log.warning("opcua.user_refused", reason="no certificate: a session needs the signed and encrypted channel")
            return None
        der = certificate if isinstance(certificate, bytes) else certificate.public_bytes(serialization.Encoding.DER)
        name = self.trust.trusted().get(der)
        if name is None:
            log.warning("opcua.user_refused", reason="certificate not in the trust list", sha256=thumbprint(der))
            return None
        operator = self.operators is not None and self.operators.contains(der)
        return SessionUser(role=UserRole.User, name=name, operator=operator, sha256=thumbprint(der))


def identity_tokens(allow_anonymous: bool) -> list[Any]:
    from asyncua import ua

    return [ua.X509IdentityToken, ua.AnonymousIdentityToken] if allow_anonymous else [ua.X509IdentityToken]
