"""Build the GPU-check bundle: everything the GPU machine needs for ``gpu_check.py`` and lacks, in one folder.

Run here, on a machine with network (``make gpu-bundle``)::

    python benchmarks/gpu_bundle.py [--out .carry/gpu_bundle] [--cache ~/.cache/mssf-blocks/gpu_bundle]

The GPU machine (docs/gpus.md, "The device check") is Python 3.12 with torch 2.11 + CUDA 13.0, Triton 3.6,
numpy, pytest, einops, pybind11, ninja and nvcc, and has no network; a command carries at most 64 MiB of
working tree (the tracked files plus the carried folders). What it lacks, in the order of the check's
stages that need it (:data:`GROUPS`; a group that does not fit is left out whole, the less valuable first):

1. spconv for the CUDA detectors and spconv's tests (stages a and d): ``spconv-cu126`` 2.3.8 and the
   ``cumm-cu126`` it requires (``>=0.7.11,<0.8.0``: 0.7.11), both repacked as ``tar.xz`` (the wheels are
   70.5 and 26.6 MB; their files so are 26.0 and 18.6 MB), and the pure-Python ``pccm``, ``ccimport``,
   ``fire``, ``termcolor``, ``lark`` as wheels;
2. mmcv 2.1.0's source archive (stage b builds mmcv's deformable-attention CUDA op from it with the
   machine's nvcc, ``_mmcv_build.py``).

Every upstream file is pinned by its sha256 (a different file is refused), downloaded once into the cache
(wheels with ``pip download --no-deps --only-binary=:all: --python-version 3.12 --platform
manylinux_2_28_x86_64``, the source archive from the package index's simple page), and repacked
deterministically (sorted members, the wheel's own times), so a rerun reuses the cache and writes the same
bytes. ``manifest.json`` lists every file with its size and sha256, the groups left out and the total with
the tracked files; more than 64 MiB together is refused, naming the largest files. Without network and
without a cache the download fails with a message saying so.

Not bundled: numpy < 2.4 for Triton 3.6's interpreter (the device runs the compiled kernels, which do
not need the interpreter; docs/compatibility.md), mmdet3d / mmcv's compiled ops (stage e reports n/a).
"""

from __future__ import annotations

import argparse
import calendar
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import urllib.request
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bundle import MANIFEST, BundleError, sha256_of  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
LIMIT_BYTES = 64 * 2**20  # what one device call carries: tracked files + carried folders
DEFAULT_OUT = REPO / ".carry" / "gpu_bundle"
DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "mssf-blocks" / "gpu_bundle"
PLATFORM = ["--python-version", "3.12", "--implementation", "cp", "--platform", "manylinux_2_28_x86_64",
            "--platform", "manylinux_2_17_x86_64", "--platform", "manylinux2014_x86_64"]
INDEX = "https://pypi.org/simple"


@dataclass(frozen=True)
class Item:
    """One upstream file: ``spec`` for pip (or ``name==version`` of a source archive), its file name
    and sha256 as published, how it is carried (``wheel``, ``tar.xz`` or ``archive``), and the module
    it provides (checked after the install on the device)."""

    spec: str
    filename: str
    sha256: str
    kind: str
    provides: Optional[str] = None
    role: Optional[str] = None

    @property
    def version(self) -> str:
        return self.spec.split("==", 1)[1]

    @property
    def carried_name(self) -> str:
        return self.filename[: -len(".whl")] + ".tar.xz" if self.kind == "tar.xz" else self.filename


SPCONV = (
    Item("spconv-cu126==2.3.8", "spconv_cu126-2.3.8-cp312-cp312-manylinux_2_28_x86_64.whl",
         "88002b375d33561ac956e29e00dade16cad11d0e3413630a8ef35e92ddfda6e1", "tar.xz", "spconv"),
    Item("cumm-cu126==0.7.11", "cumm_cu126-0.7.11-cp312-cp312-manylinux_2_28_x86_64.whl",
         "569fadb2773acb1fdd49f5406352e4415407a1dedebe33e6fd7603414dee9775", "tar.xz", "cumm"),
    Item("pccm==0.4.16", "pccm-0.4.16-py3-none-any.whl",
         "97e97c341c50c40965bb8f9a8a1ad201868d64e8baa06f9581bedeb3bc223eec", "wheel", "pccm"),
    Item("ccimport==0.4.4", "ccimport-0.4.4-py3-none-any.whl",
         "7c78f1258d372de787b7ebe351fb56890f2141b8643c3a45b1842b23828d5245", "wheel", "ccimport"),
    Item("fire==0.7.1", "fire-0.7.1-py3-none-any.whl",
         "e43fd8a5033a9001e7e2973bab96070694b9f12f2e0ecf96d4683971b5ab1882", "wheel", "fire"),
    Item("termcolor==3.3.0", "termcolor-3.3.0-py3-none-any.whl",
         "cf642efadaf0a8ebbbf4bc7a31cec2f9b5f21a9f726f4ccbb08192c9c26f43a5", "wheel", "termcolor"),
    Item("lark==1.3.1", "lark-1.3.1-py3-none-any.whl",
         "c629b661023a014c37da873b4ff58a817398d12635d3bbb2c5a03be7fe5d1e12", "wheel", "lark"),
)
MMCV_SRC = (Item("mmcv==2.1.0", "mmcv-2.1.0.tar.gz",
                 "d387bcab66b467479b6660310e23746cfc79c6e57acf04094680adb499a5cd3f", "archive", role="mmcv_src"),)

#: ``(group, stages that need it, items)`` in the order of value: the first group is kept first.
GROUPS: Tuple[Tuple[str, str, Tuple[Item, ...]], ...] = (
    ("spconv", "a (spconv's CUDA tests), d (SECOND, CenterPoint, VoxelNeXt)", SPCONV),
    ("mmcv_src", "b (mmcv's op built with nvcc, the comparison)", MMCV_SRC),
)


# --------------------------------------------------------------------------------------------------
# sizes
# --------------------------------------------------------------------------------------------------
def tracked_bytes(repo: Path = REPO) -> int:
    """Bytes of what a device call sends besides the carried folders: the tracked files and the untracked
    files git does not ignore (``git ls-files --cached --others --exclude-standard``)."""
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=repo,
                         capture_output=True, check=True).stdout
    total = 0
    for name in filter(None, out.split(b"\0")):
        path = Path(repo) / os.fsdecode(name)
        if path.is_symlink() or path.is_file():
            total += path.lstat().st_size
    return total


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def check_total(files: Dict[str, int], tracked: int, limit: int = LIMIT_BYTES) -> int:
    """``tracked + sum(files)``, or :class:`BundleError` naming the largest files when it is over ``limit``."""
    total = tracked + sum(files.values())
    if total > limit:
        largest = sorted(files.items(), key=lambda kv: -kv[1])[:5]
        raise BundleError(
            f"bundle: {_mb(total)} with the tracked files ({_mb(tracked)}) is over the {limit / 2**20:.0f} MiB a "
            f"device call carries by {_mb(total - limit)}; largest: " + ", ".join(f"{k} {_mb(v)}" for k, v in largest))
    return total


def choose(groups: Sequence[Tuple[str, Dict[str, int]]], tracked: int, limit: int = LIMIT_BYTES
           ) -> Tuple[List[str], List[str]]:
    """``(kept, left_out)`` group names: each group, in the order given (by value), kept when it still fits
    with the tracked files and the groups kept before it; ``left_out`` says by how much each did not.
    :class:`BundleError` when the first (most valuable) group does not fit."""
    kept, left, used = [], [], tracked
    for i, (name, files) in enumerate(groups):
        size = sum(files.values())
        if used + size <= limit:
            kept.append(name)
            used += size
            continue
        if i == 0:
            check_total(files, tracked, limit)  # raises, naming the files
        left.append(f"{name} ({_mb(size)}): over the {limit / 2**20:.0f} MiB limit by {_mb(used + size - limit)}")
    return kept, left


# --------------------------------------------------------------------------------------------------
# downloads (cached) and repacking
# --------------------------------------------------------------------------------------------------
def _pip_download(item: Item, dest: Path) -> None:
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", *PLATFORM, "-d", str(dest),
           item.spec]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    if r.returncode != 0:
        raise BundleError(f"bundle: `pip download {item.spec}` failed (exit {r.returncode}; no network? then run "
                          f"this where PyPI is reachable, or fill the cache {dest}): {r.stderr.strip()[-500:]}")


def _index_download(item: Item, dest: Path, index: str = INDEX) -> None:
    """A source archive from the index's simple page (pip download would build its metadata: mmcv's
    setup.py needs torch and a compiler)."""
    name = item.spec.split("==")[0]
    try:
        page = urllib.request.urlopen(f"{index}/{name}/", timeout=60).read().decode()
        links = re.findall(r'href="([^"]*/' + re.escape(item.filename) + r'[^"]*)"', page)
        if not links:
            raise BundleError(f"bundle: {item.filename} is not listed on {index}/{name}/")
        data = urllib.request.urlopen(links[0].split("#")[0], timeout=300).read()
    except OSError as exc:
        raise BundleError(f"bundle: downloading {item.filename} from {index} failed (no network? then run this "
                          f"where PyPI is reachable, or put the file in {dest}): {exc}") from exc
    (dest / item.filename).write_bytes(data)


def fetch(item: Item, cache: Path, download: Optional[Callable[[Item, Path], None]] = None) -> Path:
    """The upstream file in ``cache`` (downloaded once), its sha256 checked against the pinned one."""
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / item.filename
    if not path.is_file():
        (download or (_index_download if item.kind == "archive" else _pip_download))(item, cache)
        if not path.is_file():
            raise BundleError(f"bundle: downloading {item.spec} gave no {item.filename} in {cache}")
    digest = sha256_of(path)
    if digest != item.sha256:
        raise BundleError(f"bundle: {path}: sha256 {digest}, expected {item.sha256} (pinned for {item.spec}); "
                          "delete it to download again")
    return path


def repack(wheel: Path, out: Path, preset: int = 6) -> Path:
    """The wheel's files as a deterministic ``tar.xz`` (members sorted, the wheel's own times and modes,
    owner 0): its unpacked tree is what ``pip install --target`` would write, minus script wrappers."""
    tmp = out.with_suffix(".partial")
    with zipfile.ZipFile(wheel) as zf, tarfile.open(tmp, "w:xz", preset=preset) as tar:
        for info in sorted(zf.infolist(), key=lambda i: i.filename):
            if info.is_dir():
                continue
            ti = tarfile.TarInfo(info.filename)
            ti.size = info.file_size
            ti.mtime = calendar.timegm(info.date_time + (0, 0, 0))  # (UTC: the same bytes in any time zone)
            ti.mode = (info.external_attr >> 16) & 0o777 or 0o644
            with zf.open(info) as f:
                tar.addfile(ti, f)
    tmp.replace(out)
    return out


def carried(item: Item, cache: Path, download=None) -> Path:
    """The file carried for ``item``: the upstream file, or its ``tar.xz`` repack (cached beside it)."""
    src = fetch(item, cache, download)
    if item.kind != "tar.xz":
        return src
    packed = cache / item.carried_name
    stamp = cache / (item.carried_name + ".from")
    if not (packed.is_file() and stamp.is_file() and stamp.read_text().strip() == item.sha256):
        print(f"  repacking {item.filename} as {packed.name} (a minute or two, once)", flush=True)
        repack(src, packed)
        stamp.write_text(item.sha256 + "\n")
    return packed


# --------------------------------------------------------------------------------------------------
# the bundle
# --------------------------------------------------------------------------------------------------
def build(out: Path = DEFAULT_OUT, cache: Path = DEFAULT_CACHE, groups=GROUPS, tracked: Optional[int] = None,
          limit: int = LIMIT_BYTES, download=None) -> Dict[str, object]:
    """Write the bundle into ``out`` (emptied of anything else) and return its manifest."""
    tracked = tracked_bytes() if tracked is None else tracked
    files = {name: [(item, carried(item, cache, download)) for item in items] for name, _, items in groups}
    kept, left_out = choose([(name, {p.name: p.stat().st_size for _, p in files[name]}) for name, _, _ in groups],
                            tracked, limit)
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for name, stages, _ in groups:
        if name not in kept:
            continue
        for item, path in files[name]:
            dest = out / path.name
            if not (dest.is_file() and dest.stat().st_size == path.stat().st_size and sha256_of(dest) == sha256_of(path)):
                shutil.copyfile(path, dest)
            entries.append(dict(file=path.name, kind=item.kind, bytes=dest.stat().st_size, sha256=sha256_of(dest),
                                provides=item.provides, version=item.version, role=item.role, group=name,
                                stages=stages, upstream=item.filename, upstream_sha256=item.sha256))
    wanted = {e["file"] for e in entries} | {MANIFEST}
    for stale in out.iterdir():  # the folder holds the bundle and nothing else (it is carried whole)
        if stale.name not in wanted:
            shutil.rmtree(stale) if stale.is_dir() else stale.unlink()
    sizes = {e["file"]: e["bytes"] for e in entries}
    total = check_total(sizes, tracked, limit)
    manifest = dict(python="3.12", platform="manylinux_2_28_x86_64", entries=entries, left_out=left_out,
                    bundle_bytes=sum(sizes.values()), tracked_bytes=tracked, total_bytes=total, limit_bytes=limit)
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="the bundle folder (carried whole; default %(default)s)")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="downloads and repacks (default %(default)s)")
    args = ap.parse_args(argv)
    try:
        manifest = build(args.out, args.cache)
    except BundleError as exc:
        print(f"gpu_bundle: {exc}", file=sys.stderr)
        return 1
    for e in manifest["entries"]:
        print(f"  {e['file']:70s} {_mb(e['bytes']):>9s}  {e['kind']}")
    for line in manifest["left_out"]:
        print(f"  LEFT OUT: {line}")
    print(f"bundle {_mb(manifest['bundle_bytes'])} + tracked files {_mb(manifest['tracked_bytes'])} = "
          f"{_mb(manifest['total_bytes'])} of {manifest['limit_bytes'] / 2**20:.0f} MiB; written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
