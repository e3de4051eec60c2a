#!/usr/bin/env python3
"""Make the secrets of an mcsm deployment from the shipped configs (nothing secret is committed).

::

    python deploy/make_secrets.py OUT [--variant usrpwd|mtls|both] [--server-host HOST]...

For each variant it copies ``deploy/<variant>/*.json5`` into ``OUT/<variant>/`` and:

* ``usrpwd``: writes ``users.txt`` (one ``user:password`` line per client identity, random
  passwords from :mod:`secrets`, mode 0600) and fills each client config's ``@PASSWORD@``;
* ``mtls``: makes a CA and, with ``openssl``, a server certificate (CN ``mcsm-server``, SAN
  ``localhost``, ``127.0.0.1`` and every ``--server-host``) and one client certificate per
  identity (CN = the identity: ``robot1``, ``viewer``, ...) in ``certs/`` (keys mode 0600).

Both variants also write the NATS users of the fleet's map servers (the maps' replicated
logs, ``docs/fleet.md``): ``nats-auth.conf`` for ``mcsm nats-cluster --auth`` and
``serverK.nats.json`` for ``mcsm serve --nats-auth``.

The identities are the connecting configs' file names (every ``*.json5`` but ``server.json5``
and ``router.json5``): the clients and a fleet's map servers (``server1``, ``server2``). One
``users.txt`` (one CA) serves both shapes of deployment: copy ``OUT/<variant>/server.json5``
(one server) or ``router.json5`` (a fleet's router) with ``users.txt`` or
``certs/{ca.pem,server.*}`` (the listening certificate of either) to that machine, and each
``<identity>.json5`` with its own password or ``certs/{ca.pem,<identity>.*}`` to that machine
only. Prints the directories it wrote. Exit 0 on success, 2 on a usage error
(``OUT/<variant>`` exists, no openssl), 1 if openssl fails.
"""

from __future__ import annotations

import argparse
import ipaddress
import secrets
import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
VARIANTS = ("usrpwd", "mtls")
DAYS = 365


LISTENERS = ("server.json5", "router.json5")
"""The configs that accept connections (a single server, a fleet's router); every other
``*.json5`` is an identity that connects: a client (robot, viewer, admin) or a fleet's map
server (``server1``, ``server2``)."""


def identities(variant_dir: Path) -> list[str]:
    return sorted(p.stem for p in variant_dir.glob("*.json5") if p.name not in LISTENERS)


def _copy(variant: str, out: Path) -> Path:
    dst = out / variant
    if dst.exists():
        raise FileExistsError(f"{dst} exists; refusing to overwrite secrets")
    dst.mkdir(parents=True)
    for p in sorted((HERE / variant).glob("*.json5")):
        shutil.copyfile(p, dst / p.name)
    return dst


def make_nats_auth(dst: Path) -> None:
    """The NATS users of a fleet's map servers (``server1``, ``server2``, ...): the cluster's
    ``nats-auth.conf`` (``mcsm nats-cluster --auth``) and each server's ``serverK.nats.json``
    (``mcsm serve --nats-auth``), random passwords, mode 0600. Clients (robots, viewers,
    admins) get no NATS user: only servers reach the maps' logs."""
    users = []
    for ident in identities(dst):
        if not ident.startswith("server"):
            continue
        password = secrets.token_urlsafe(24)
        users.append(f'    {{user: "{ident}", password: "{password}"}}')
        cred = dst / f"{ident}.nats.json"
        cred.write_text(f'{{"user": "{ident}", "password": "{password}"}}\n')
        cred.chmod(0o600)
    conf = dst / "nats-auth.conf"
    conf.write_text("# NATS users of the fleet's map servers (made by make_secrets.py)\n"
                    "authorization {\n  users = [\n" + ",\n".join(users) + "\n  ]\n}\n")
    conf.chmod(0o600)


def make_usrpwd(out: Path) -> Path:
    dst = _copy("usrpwd", out)
    make_nats_auth(dst)
    lines = []
    for ident in identities(dst):
        password = secrets.token_urlsafe(24)
        lines.append(f"{ident}:{password}")
        conf = dst / f"{ident}.json5"
        conf.write_text(conf.read_text().replace("@PASSWORD@", password))
        conf.chmod(0o600)
    users = dst / "users.txt"
    users.write_text("\n".join(lines) + "\n")
    users.chmod(0o600)
    return dst


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.PIPE, text=True)


def _sign(name: str, cn: str, ext: str, certs: Path) -> None:
    _openssl("req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
             "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={cn}",
             cwd=certs)
    (certs / f"{name}.ext").write_text(ext)
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", f"{name}.pem", "-days", str(DAYS), "-sha256",
             "-extfile", f"{name}.ext", cwd=certs)
    (certs / f"{name}.csr").unlink()
    (certs / f"{name}.ext").unlink()
    (certs / f"{name}.key").chmod(0o600)


def make_mtls(out: Path, server_hosts: list[str]) -> Path:
    if shutil.which("openssl") is None:
        raise FileNotFoundError("openssl is not installed (apt-get install openssl)")
    dst = _copy("mtls", out)
    make_nats_auth(dst)
    certs = dst / "certs"
    certs.mkdir()
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
             "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", str(DAYS), "-sha256",
             "-subj", "/CN=mcsm-deployment-ca", "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=certs)
    (certs / "ca.key").chmod(0o600)
    sans = []
    for host in ["localhost", "127.0.0.1", *server_hosts]:
        try:
            ipaddress.ip_address(host)
            sans.append(f"IP:{host}")
        except ValueError:
            sans.append(f"DNS:{host}")
    _sign("server", "mcsm-server",
          f"basicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n"
          f"subjectAltName={','.join(dict.fromkeys(sans))}\n", certs)
    for ident in identities(dst):
        _sign(ident, ident, "basicConstraints=CA:FALSE\nextendedKeyUsage=clientAuth\n", certs)
    (certs / "ca.srl").unlink(missing_ok=True)
    return dst


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="make_secrets.py", description=__doc__.split("\n")[0])
    p.add_argument("out", type=Path, help="directory to write (created)")
    p.add_argument("--variant", choices=(*VARIANTS, "both"), default="both")
    p.add_argument("--server-host", action="append", default=[], metavar="HOST",
                   help="extra host name or address the server certificate names (repeat)")
    args = p.parse_args(argv)
    variants = VARIANTS if args.variant == "both" else (args.variant,)
    try:
        for v in variants:
            dst = make_usrpwd(args.out) if v == "usrpwd" else make_mtls(args.out,
                                                                         args.server_host)
            print(dst)
    except (FileExistsError, FileNotFoundError) as exc:
        print(f"make_secrets.py: {exc}", file=sys.stderr)
        return 2
    except subprocess.CalledProcessError as exc:
        print(f"make_secrets.py: openssl failed: {(exc.stderr or '').strip()}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
