"""Packs what a lent GPU machine lacks to run this project under its own jax, into `.gpu/`.

    python -m benchmarks.tooling.gpu_carry            # here, once; then carry `.gpu` to the machine

The lent machine (one H200 on 2026-12-04) has Python 3.12 with its own CUDA build of jax,
flax, optax, chex, orbax and torch, and no package registry. This writes:
- `.gpu/whl/`: cp312 manylinux wheels of the packages it lacks, at the versions of
  requirements.lock (mujoco, mujoco-mjx, tyro, ...);
- `.gpu/site/dm_control`: the installed dm_control without its largest folders (its 56 MB
  wheel and mujoco's 27 MB do not fit the 64 MiB a call can carry together); the suite's
  cheetah, walker and quadruped load from what is left;
- `.gpu/run.sh`: sourced at the start of the command there, it installs the wheels and sets
  PYTHONPATH and MUJOCO_GL.
Then, there: `source .gpu/run.sh && python3 -m benchmarks.runs.gpu_suite --parts ... --out $OUT`.

    python -m benchmarks.tooling.gpu_carry --warp       # also MJX-Warp's warp-lang, in two halves

MJX-Warp (`benchmarks/ports/mjx_warp.py`) needs warp-lang, whose wheel (149 MB) no call can carry.
Without its CPU compiler, examples and tests it packs into a 75 MiB tar.xz, split into
`.gpu_warp/a/` and `.gpu_warp/b/`; three calls in a row on the warm machine (it is given
back 30 s after a call) bring it there: carry `.gpu_warp/a` with
`mkdir -p /tmp/wp && cp .gpu_warp/a/* /tmp/wp/`, then `.gpu_warp/b` with
`cat /tmp/wp/* .gpu_warp/b/* | python3 -m benchmarks.tooling.gpu_carry --unpack /tmp/wsite`, then
`.gpu` as above (run.sh puts /tmp/wsite on PYTHONPATH). `.gpu/` and `.gpu_warp/` are
git-ignored.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
WHEELS = ("mujoco", "mujoco-mjx", "dm-env", "dm-tree", "PyOpenGL", "tyro", "docstring_parser",
          "typeguard", "trimesh", "tensorboardX")
# dm_control's parts that the suite's tasks never import (locomotion alone is 83 MB)
DROP = ("locomotion", "manipulation", "suite/dog_assets", "mujoco/testing", "viewer", "blender",
        "suite/all_domains.png")
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64",
             "manylinux_2_17_x86_64", "manylinux2014_x86_64")
RUN_SH = """\
# sourced on the GPU machine, from the repository root (benchmarks/tooling/gpu_carry.py wrote it)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \\
    --target /tmp/site .gpu/whl/*.whl || return 1
export PYTHONPATH=$PWD:$PWD/.gpu/site:/tmp/site:/tmp/wsite MUJOCO_GL=disable PYTHONUNBUFFERED=1
"""
WARP_VERSION = "1.19.0"  # not a project dependency: MJX-Warp's benchmark only
# what a GPU machine does not need: the CPU backend's compiler (69 MB), examples, tests
WARP_DROP = ("warp/bin/warp-clang.so", "warp/examples", "warp/tests")


def locked_version(name: str) -> str:
    key = name.lower().replace("_", "-")
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        pkg, _, version = line.partition("==")
        if pkg.strip().lower().replace("_", "-") == key:
            return version.strip()
    raise KeyError(f"{name} is not in requirements.lock")


def download_wheels(dest: Path, python: str = "3.12") -> None:
    dest.mkdir(parents=True, exist_ok=True)
    platforms = [a for p in PLATFORMS for a in ("--platform", p)]
    subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps",
                    "--only-binary=:all:", "--python-version", python, "--implementation", "cp",
                    *platforms, "-d", str(dest),
                    *(f"{name}=={locked_version(name)}" for name in WHEELS)], check=True)


def slim_dm_control(dest: Path) -> None:
    import dm_control

    source = Path(dm_control.__file__).parent
    target = dest / "dm_control"
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(source, target, ignore=shutil.ignore_patterns("__pycache__", "*_test.py"))
    for part in DROP:
        path = target / part
        shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)


def pack_warp(dest: Path) -> None:
    """warp-lang's wheel, less WARP_DROP, as a tar.xz in two halves: dest/a/part, dest/b/part."""
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps",
                        "--only-binary=:all:", "--python-version", "3.12", "--implementation",
                        "cp", *[a for p in PLATFORMS for a in ("--platform", p)], "-d", tmp,
                        f"warp-lang=={WARP_VERSION}"], check=True)
        pack_wheel(next(Path(tmp).glob("warp_lang-*.whl")), dest, WARP_DROP)


def pack_wheel(wheel_path: Path, dest: Path, drop: tuple[str, ...]) -> None:
    """The files of a wheel (a zip), less those under `drop`, as a tar.xz split in two
    halves: dest/a/part and dest/b/part (`cat` them back together)."""
    import io
    import zipfile

    packed = io.BytesIO()
    with zipfile.ZipFile(wheel_path) as wheel, \
            tarfile.open(fileobj=packed, mode="w:xz", preset=9) as tar:
        for info in wheel.infolist():
            if info.is_dir() or any(info.filename.startswith(d) for d in drop):
                continue
            member = tarfile.TarInfo(info.filename)
            member.size, member.mode = info.file_size, 0o755
            with wheel.open(info) as f:
                tar.addfile(member, f)
    data = packed.getvalue()
    half = (len(data) + 1) // 2
    for name, part in (("a", data[:half]), ("b", data[half:])):
        (dest / name).mkdir(parents=True, exist_ok=True)
        (dest / name / "part").write_bytes(part)


def unpack_warp(target: Path, stream=None) -> None:
    """The halves, concatenated on stdin (or `stream`), unpacked into `target` (on the GPU
    machine)."""
    with tarfile.open(fileobj=stream or sys.stdin.buffer, mode="r|xz") as tar:
        tar.extractall(target, filter="data")


def size_mib(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2**20


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--dest", type=Path, default=ROOT / ".gpu")
    p.add_argument("--warp", action="store_true", help="also pack warp-lang into .gpu_warp/")
    p.add_argument("--unpack", type=Path, default=None,
                   help="on the GPU machine: unpack warp-lang from stdin into this folder")
    args = p.parse_args(argv)
    if args.unpack:
        unpack_warp(args.unpack)
        return 0
    if args.warp:
        pack_warp(ROOT / ".gpu_warp")
        print(f".gpu_warp: {size_mib(ROOT / '.gpu_warp'):.1f} MiB in two halves")
    download_wheels(args.dest / "whl")
    slim_dm_control(args.dest / "site")
    (args.dest / "run.sh").write_text(RUN_SH)
    print(f"{args.dest}: {size_mib(args.dest):.1f} MiB (a call carries at most 64 MiB with "
          "the working tree)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
