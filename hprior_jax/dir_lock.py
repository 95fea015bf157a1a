"""One writer per directory: a run directory, a grid's results directory, a labelling query
folder. An advisory `fcntl.flock` on DIR/.lock held for the life of the process: the kernel
drops it when the holder exits or is killed, so a lock left by a dead process is simply
taken over; the file's text (PID, start time, command) only names the holder in the error."""
from __future__ import annotations

import fcntl
import os
import sys
import time
from pathlib import Path

LOCK_NAME = ".lock"


class DirInUse(RuntimeError):
    """Another live process holds the directory; the message names it."""


class DirLock:
    def __init__(self, directory: Path):
        self.directory = Path(directory)
        self.path = self.directory / LOCK_NAME
        self._fd: int | None = None

    def acquire(self) -> "DirLock":
        self.directory.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 4096).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise DirInUse(f"{self.directory} is in use by {holder}") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"PID {os.getpid()} (started {time.strftime('%Y-%m-%d %H:%M:%S')}: "
                     f"{' '.join(Path(sys.argv[0]).name.split()[:1] + sys.argv[1:3])})\n"
                 .encode())
        os.fsync(fd)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock; the file stays (harmless)
            self._fd = None

    def __enter__(self) -> "DirLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def hold(directory: Path) -> DirLock:
    """Locks `directory` for this process (until `release` or exit) or raises DirInUse."""
    return DirLock(directory).acquire()
