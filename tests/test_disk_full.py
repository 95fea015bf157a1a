"""A disk that fills during a run, on a real small filesystem (a tmpfs mounted in a mount
namespace of the training process: as root, or in a user namespace where the kernel allows
one; skipped elsewhere): one line naming the path and the cause, exit 1, nothing else on
stderr; the run directory, copied elsewhere, resumes to the rows of a run that never failed."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_life_cycle import TOY, _rows, _train

ROOT = Path(__file__).resolve().parent.parent
# `tasks` first: it sets XLA_FLAGS before jax is imported
CODE = ("import sys, tasks; from tests.toy_task import ensure_registered; ensure_registered(); "
        "from hprior_jax import cli; sys.exit(cli.main(sys.argv[1:]))")
# mount the small disk, train onto it, keep a copy of what it left, exit with training's status
SCRIPT = 'mount -t tmpfs -o size=256k tmpfs "$0" || exit 99; "$@"; rc=$?; cp -a "$0/run" "$COPY"; exit $rc'


def _in_mount_namespace() -> list[str]:
    command = ["unshare", "--mount"] + ([] if os.geteuid() == 0 else ["--map-root-user"])
    try:
        ok = subprocess.run([*command, "sh", "-c", "mount -t tmpfs tmpfs /mnt"],
                            capture_output=True).returncode == 0
    except FileNotFoundError:
        ok = False
    if not ok:
        pytest.skip("no mount namespace here (unshare): a full disk needs a real small one")
    return command


def test_a_full_disk_ends_with_one_line_and_the_run_resumes_elsewhere(tmp_path):
    disk, copy = tmp_path / "disk", tmp_path / "copy"
    disk.mkdir()
    args = [*TOY, "--steps", "4000", "--checkpoint-every", "40", "--no-progress",
            "--out", str(disk / "run")]
    proc = subprocess.run([*_in_mount_namespace(), "sh", "-c", SCRIPT, str(disk),
                           sys.executable, "-c", CODE, "train", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "COPY": str(copy)})
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 1, proc.stderr
    assert len(err) == 1 and err[0].startswith(f"error: {disk / 'run'}"), proc.stderr
    assert "no space left on device" in err[0].lower(), proc.stderr

    step = max(int(p.name) for p in (copy / "checkpoints").iterdir() if p.name.isdigit())
    target = step + 40  # past where the disk filled
    assert _train("--resume", str(copy), "--steps", str(target)) == 0
    clean = tmp_path / "clean"
    assert _train("--steps", str(target), "--replay-capacity", "4000", "--checkpoint-every",
                  "40", "--out", str(clean)) == 0
    assert _rows(copy / "eval.csv") == _rows(clean / "eval.csv")
    shutil.rmtree(copy)
