"""``make wheel-check`` (run by ``.ci/run`` after ``make test``): README's install, done as a new
user would, checked end to end.

1. Builds the wheel from this clone (``pip wheel . --no-deps``: the C kernel is compiled into
   it; pip's cache serves the build requirements).
2. Creates a fresh virtual environment outside the clone and installs the wheel there with its
   ``viz`` extra (dependencies from pip's cache or index, as for any user).
3. From a folder outside the clone (so that nothing is imported from the source tree): the
   compiled kernel is loaded from the installed package; ``mcsm --version``, ``mcsm-client
   --version`` and ``mcsm view --help`` (a command the client package adds through the
   ``mcsm.commands`` entry point) work; a real ``mcsm serve`` takes an ``mcsm-client update``
   and answers ``info``; ``mcsm replay`` of its recording says ``identical``.

Exits 0 when everything holds, 1 with the failing step otherwise. Prints each step's time.
Not part of ``make test`` (building the kernel twice takes 10-30 s on a shared 2-core VM).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def step(what: str, cmd: list[str], cwd: Path, timeout: float = 600, **kw: object) -> str:
    t0 = time.monotonic()
    p = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout,
                       **kw)  # type: ignore[call-overload]
    dt = time.monotonic() - t0
    if p.returncode != 0:
        print(f"FAILED: {what} (exit {p.returncode}, {dt:.1f} s)\n{p.stdout}\n{p.stderr}",
              file=sys.stderr)
        raise SystemExit(1)
    print(f"ok  {dt:6.1f} s  {what}", flush=True)
    return str(p.stdout)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="mcsm-wheel-") as tmp:
        work = Path(tmp)
        dist = work / "dist"
        step("build the wheel (pip wheel . --no-deps)",
             [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q", "-w",
              str(dist)], cwd=work)
        (wheel,) = dist.glob("mcsm-*.whl")
        names = zipfile.ZipFile(wheel).namelist()
        kernels = [n for n in names if n.startswith("mcsm/core/_kernel") and ".so" in n]
        if not kernels:
            print(f"FAILED: no compiled kernel in {wheel.name}", file=sys.stderr)
            return 1
        print(f"ok          {wheel.name}: {', '.join(sorted(kernels))}")
        venv = work / "venv"
        step("fresh venv", [sys.executable, "-m", "venv", str(venv)], cwd=work)
        bindir = venv / "bin"
        step("pip install the wheel with its viz extra",
             [str(bindir / "python"), "-m", "pip", "install", "-q", f"{wheel}[viz]"], cwd=work)
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
        env["PATH"] = f"{bindir}{os.pathsep}{env.get('PATH', '')}"
        out = step("the kernel loads from the installed package",
                   [str(bindir / "python"), "-c",
                    "import mcsm, mcsm.core.kernel as k, numpy as np; "
                    "from mcsm import StochasticMap; m = StochasticMap(8); "
                    "x = np.zeros((8, 7)); x[:, 3] = 1; x[:, 0] = np.linspace(0.9, 1.1, 8); "
                    "m.update('a', 'b', x); print(mcsm.__file__); print(k.__file__)"],
                   cwd=work, env=env)
        if str(ROOT) in out or str(venv) not in out:
            print(f"FAILED: mcsm imported from outside the fresh venv:\n{out}", file=sys.stderr)
            return 1
        step("mcsm --version", ["mcsm", "--version"], cwd=work, env=env)
        step("mcsm-client --version", ["mcsm-client", "--version"], cwd=work, env=env)
        step("mcsm view --help (entry point mcsm.commands)", ["mcsm", "view", "--help"],
             cwd=work, env=env)
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        rec = work / "tour.mcap"
        serve = subprocess.Popen(["mcsm", "serve", "--samples", "64", "--listen", endpoint,
                                  "--record", str(rec)], cwd=work, env=env,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert serve.stdout is not None
            line = serve.stdout.readline()
            if not line.startswith("listening on"):
                print(f"FAILED: mcsm serve: {line}{serve.stderr.read() if serve.stderr else ''}",
                      file=sys.stderr)
                return 1
            step("mcsm-client update", ["mcsm-client", "--connect", endpoint, "update", "world",
                                        "r1", "--planar", "1", "0", "0.1", "--sigma", "0.05",
                                        "0.05", "0.01"], cwd=work, env=env, timeout=60)
            step("mcsm-client info", ["mcsm-client", "--connect", endpoint, "info"], cwd=work,
                 env=env, timeout=60)
        finally:
            serve.send_signal(2)
            serve.wait(timeout=60)
        out = step("mcsm replay of its recording", ["mcsm", "replay", str(rec)], cwd=work,
                   env=env)
        if not out.strip().endswith("identical"):
            print(f"FAILED: replay said:\n{out}", file=sys.stderr)
            return 1
    print("wheel check passed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
