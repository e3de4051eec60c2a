"""``deploy/make_secrets.py`` keeps what docs/deploy.md says: every secret file (passwords,
keys, the configs holding them, NATS credentials) is mode 0600; passwords are 24 random bytes;
the server certificate names localhost, 127.0.0.1 and every --server-host; certificates last
365 days."""

from __future__ import annotations

import re
import stat
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_secret_files_modes_passwords_and_certificates(tmp_path: Path) -> None:
    out = tmp_path / "secrets"
    r = subprocess.run([sys.executable, str(REPO / "deploy" / "make_secrets.py"), str(out),
                        "--server-host", "mapserver.test"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    users = out / "usrpwd" / "users.txt"
    files = [f for f in out.rglob("*") if f.is_file()]
    secret = [f for f in files if f == users or f.suffix == ".key"
              or "password" in f.read_text(errors="replace").lower()]
    assert len(secret) > 12 and users in secret
    for f in secret:  # a password or a key inside: mode 0600
        assert stat.S_IMODE(f.stat().st_mode) == 0o600, f
    passwords = [ln.split(":", 1)[1] for ln in users.read_text().split()]
    # 24 random bytes each, URL-safe base64 (32 characters), no two alike
    assert all(re.fullmatch(r"[A-Za-z0-9_-]{32}", pw) for pw in passwords)
    assert len(passwords) >= 5 and len(set(passwords)) == len(passwords)
    cert = out / "mtls" / "certs" / "server.pem"
    text = subprocess.run(["openssl", "x509", "-in", str(cert), "-noout", "-text"],
                          capture_output=True, text=True, timeout=60, check=True).stdout
    sans = re.search(r"Subject Alternative Name:\s*\n\s*(.+)", text)
    assert sans is not None
    names = {n.strip() for n in sans.group(1).split(",")}
    assert {"DNS:localhost", "IP Address:127.0.0.1", "DNS:mapserver.test"} <= names, names
    dates = subprocess.run(["openssl", "x509", "-in", str(cert), "-noout", "-startdate",
                            "-enddate"], capture_output=True, text=True, timeout=60,
                           check=True).stdout
    from datetime import datetime

    start, end = (datetime.strptime(v.split("=", 1)[1].strip(), "%b %d %H:%M:%S %Y %Z")
                  for v in dates.splitlines())
    assert (end - start).days == 365
