"""A self-signed certificate for the display server, made at first start: headsets reach the client over the LAN,
and WebXR needs a secure context (HTTPS, or http://localhost through `adb reverse`).

Checked at every start: both files are plain files, the private key is readable by its owner only (a key others can
read is refused: it may have been copied), the folder is its owner's only, and the pair loads (a corrupt, empty,
truncated or mismatched file is named with what to do)."""
from __future__ import annotations

import datetime
import ipaddress
import os
import socket
import ssl
import stat
from pathlib import Path

__all__ = ["CertificateError", "default_certificate_dir", "ensure_certificate", "server_context"]

PAIR = ("cert.pem", "key.pem")
OWNER_ONLY = 0o077  # mode bits of group and others


class CertificateError(ValueError):
    """The certificate or key cannot be used: the message names the file and says how to fix it."""


def default_certificate_dir() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config"
    return Path(base) / "agentdress" / "tls"


def _local_addresses() -> list[str]:
    addresses = {"127.0.0.1", "::1"}
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:  # no packet is sent: picks the LAN address
            probe.connect(("192.0.2.1", 9))
            addresses.add(probe.getsockname()[0])
    except OSError:
        pass
    return sorted(addresses)


def _remake_hint(directory: Path) -> str:
    return (f"delete {directory / PAIR[0]} and {directory / PAIR[1]} to have a new self-signed pair made at the next "
            "start (browsers then ask once more to accept it), or put a matching PEM certificate and key there")


def _secure_folder(directory: Path):
    """Make the folder (mode 0700), or take an existing one back to 0700 when it holds nothing but the pair: a
    folder shared with other files (say, --cert-dir /tmp) is left alone, the key's own mode protects it."""
    if not directory.exists():
        directory.mkdir(mode=0o700, parents=True)
        return
    if not directory.is_dir():
        raise CertificateError(f"{directory} is not a folder: give --cert-dir a folder for {PAIR[0]} and {PAIR[1]}")
    mode = stat.S_IMODE(directory.stat().st_mode)
    if mode & OWNER_ONLY and {p.name for p in directory.iterdir()} <= set(PAIR) \
            and directory.stat().st_uid == os.getuid():
        directory.chmod(0o700)


def _check_paths(*paths: Path):
    for path in paths:
        if (path.exists() or path.is_symlink()) and not path.is_file():
            raise CertificateError(f"{path} is not a file (a folder or a dangling link): remove it; "
                                   + _remake_hint(path.parent))


def _check_key_mode(key_path: Path):
    mode = stat.S_IMODE(key_path.stat().st_mode)
    if mode & OWNER_ONLY:
        raise CertificateError(
            f"the private key {key_path} is readable by other users (mode {mode:04o}): anyone on this machine may "
            f"have copied it. Run `chmod 600 {key_path}` to keep it, or " + _remake_hint(key_path.parent))


def ensure_certificate(directory=None) -> tuple[Path, Path, bool]:
    """(certificate path, key path, made now): reuses `directory`/cert.pem + key.pem, or makes a self-signed pair
    (EC P-256, 10 years) for localhost and this machine's addresses. The key file is readable by its owner only,
    the folder too; CertificateError (saying what to do) for a key others can read or a path that is not a file."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    directory = Path(directory) if directory is not None else default_certificate_dir()
    cert_path, key_path = directory / PAIR[0], directory / PAIR[1]
    _secure_folder(directory)
    _check_paths(cert_path, key_path)
    if cert_path.is_file() and key_path.is_file():
        _check_key_mode(key_path)
        return cert_path, key_path, False
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "agentdress view (self-signed)")])
    names = [x509.DNSName("localhost"), x509.DNSName(socket.gethostname())]
    names += [x509.IPAddress(ipaddress.ip_address(a)) for a in _local_addresses()]
    now = datetime.datetime.now(datetime.timezone.utc)
    certificate = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
                   .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(days=1))
                   .not_valid_after(now + datetime.timedelta(days=3650))
                   .add_extension(x509.SubjectAlternativeName(names), critical=False)
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                   .sign(key, hashes.SHA256()))
    descriptor = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(descriptor, 0o600)  # the mode of open() applies to a new file only: an existing one keeps its own
    with os.fdopen(descriptor, "wb") as handle:
        handle.write(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    cert_path.write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
    return cert_path, key_path, True


def server_context(cert_path, key_path) -> ssl.SSLContext:
    """The TLS context of the display server (TLS 1.2 or later) with this pair; CertificateError naming the file
    at fault - not a PEM certificate, not an unencrypted PEM key, or a key that is not the certificate's."""
    cert_path, key_path = Path(cert_path), Path(key_path)
    _check_paths(cert_path, key_path)
    if key_path.is_file():
        _check_key_mode(key_path)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        context.load_cert_chain(str(cert_path), str(key_path))
    except (ssl.SSLError, OSError) as error:
        raise CertificateError(_diagnosis(cert_path, key_path, error)) from None
    return context


def _diagnosis(cert_path: Path, key_path: Path, error: Exception) -> str:
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    hint = _remake_hint(cert_path.parent) if cert_path.parent == key_path.parent else \
        "give a matching PEM certificate and key"
    try:
        certificate = x509.load_pem_x509_certificate(cert_path.read_bytes())
    except (ValueError, OSError) as reason:
        return f"the certificate {cert_path} is not a PEM certificate (empty, truncated or corrupt: {reason}); {hint}"
    try:
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (ValueError, TypeError, OSError) as reason:
        return (f"the private key {key_path} is not an unencrypted PEM key (empty, truncated, corrupt or "
                f"password-protected: {reason}); {hint}")
    public = serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    if certificate.public_key().public_bytes(*public) != key.public_key().public_bytes(*public):
        return f"the private key {key_path} is not the key of the certificate {cert_path}; {hint}"
    return f"the certificate {cert_path} and key {key_path} do not load ({error}); {hint}"
