"""The GPU-check bundle on the device side: verify it and install it offline into a target folder.

A bundle (built by ``benchmarks/gpu_bundle.py`` on a machine with network) is one folder holding
``manifest.json`` and the files it lists, each with its size and sha256:

* ``kind = "wheel"``: a wheel, installed with ``pip install --no-index --no-deps --target`` (pip never
  looks at an index or the network: ``--no-index``, and the machine's pip configuration is not read);
* ``kind = "tar.xz"``: a wheel's files repacked as ``tar.xz`` (spconv's 70.5 MB wheel is 26 MB so),
  unpacked into the target folder as they are (a wheel is a site-packages tree plus its ``.dist-info``);
* ``kind = "archive"``: a file a stage reads as it is (mmcv's source archive, for ``_mmcv_build.py``);
  nothing is installed, :func:`install` returns its path under the entry's ``role``.

Stdlib only: this runs before anything the bundle brings is importable.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from typing import Dict, List, Optional

__all__ = ["MANIFEST", "KINDS", "BundleError", "sha256_of", "read_manifest", "verify", "install", "activate"]

MANIFEST = "manifest.json"
KINDS = ("wheel", "tar.xz", "archive")


class BundleError(RuntimeError):
    """A bundle that cannot be used (missing, altered, or an install that failed); the message says which file."""


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_manifest(bundle: Path) -> Dict[str, object]:
    """The bundle's manifest; :class:`BundleError` naming what is wrong with it."""
    path = Path(bundle) / MANIFEST
    if not path.is_file():
        raise BundleError(f"bundle: no {MANIFEST} in {bundle} (build one with `make gpu-bundle` on a machine "
                          "with network, then carry the folder)")
    try:
        manifest = json.loads(path.read_text())
        entries = manifest["entries"]
    except (ValueError, KeyError, TypeError) as exc:
        raise BundleError(f"bundle: {path} is not a bundle manifest ({type(exc).__name__}: {exc})") from exc
    for e in entries:
        missing = [k for k in ("file", "kind", "sha256", "bytes") if k not in e]
        if missing or e["kind"] not in KINDS:
            raise BundleError(f"bundle: {path}: entry {e!r}: expected keys file, kind (one of {KINDS}), sha256, "
                              f"bytes; missing {missing}")
    return manifest


def verify(bundle: Path, manifest: Dict[str, object]) -> None:
    """Every listed file is there with its recorded size and sha256 (a partial copy or a stale file is
    refused before anything is installed)."""
    for e in manifest["entries"]:
        path = Path(bundle) / e["file"]
        if not path.is_file():
            raise BundleError(f"bundle: {e['file']} is listed in {MANIFEST} but missing from {bundle}")
        size = path.stat().st_size
        if size != e["bytes"]:
            raise BundleError(f"bundle: {e['file']}: expected {e['bytes']} bytes, found {size} (a partial copy?)")
        digest = sha256_of(path)
        if digest != e["sha256"]:
            raise BundleError(f"bundle: {e['file']}: sha256 {digest} does not match the manifest's {e['sha256']}")


def _offline_env() -> Dict[str, str]:
    """pip's environment: no index, no configuration files (an image's pip.conf may name one)."""
    env = dict(os.environ, PIP_NO_INDEX="1", PIP_CONFIG_FILE=os.devnull, PIP_DISABLE_PIP_VERSION_CHECK="1")
    env.pop("PIP_FIND_LINKS", None)
    env.pop("PIP_INDEX_URL", None)
    env.pop("PIP_EXTRA_INDEX_URL", None)
    return env


def _untar(path: Path, target: Path) -> None:
    with tarfile.open(path, "r:xz") as tar:
        if hasattr(tarfile, "data_filter"):  # Python >= 3.11.4 / 3.12: refuse paths leaving the target
            tar.extractall(target, filter="data")
        else:
            for member in tar.getmembers():
                if member.name.startswith("/") or ".." in Path(member.name).parts:
                    raise BundleError(f"bundle: {path.name}: member {member.name!r} leaves the target folder")
            tar.extractall(target)


def install(bundle: Path, target: Path, python: Optional[str] = None, timeout_s: float = 180.0) -> Dict[str, object]:
    """Verify ``bundle`` and install it into ``target`` with no step that needs the network.

    Returns ``dict(target, seconds, installed=[{file, kind, provides, version}], archives={role: path},
    left_out=[...])``. Raises :class:`BundleError` (naming the file) when the bundle is altered or pip fails.
    """
    bundle, target = Path(bundle).resolve(), Path(target).resolve()
    t0 = time.perf_counter()
    manifest = read_manifest(bundle)
    verify(bundle, manifest)
    target.mkdir(parents=True, exist_ok=True)
    entries: List[Dict[str, object]] = manifest["entries"]
    wheels = [bundle / e["file"] for e in entries if e["kind"] == "wheel"]
    if wheels:
        cmd = [python or sys.executable, "-m", "pip", "install", "--no-index", "--no-deps", "--no-compile",
               "--no-cache-dir", "--disable-pip-version-check", "--quiet", "--upgrade", "--target", str(target),
               *map(str, wheels)]
        try:
            r = subprocess.run(cmd, env=_offline_env(), capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired as exc:
            raise BundleError(f"bundle: pip install --no-index of {len(wheels)} wheels took over {timeout_s:.0f} s") from exc
        if r.returncode != 0:
            raise BundleError(f"bundle: pip install --no-index --target {target} failed (exit {r.returncode}): "
                              f"{(r.stderr or r.stdout).strip()[-800:]}")
    archives: Dict[str, str] = {}
    for e in entries:
        if e["kind"] == "tar.xz":
            _untar(bundle / e["file"], target)
        elif e["kind"] == "archive":
            archives[e.get("role") or e["file"]] = str(bundle / e["file"])
    installed = [dict(file=e["file"], kind=e["kind"], provides=e.get("provides"), version=e.get("version"))
                 for e in entries if e["kind"] != "archive"]
    return dict(bundle=str(bundle), target=str(target), seconds=round(time.perf_counter() - t0, 2),
                installed=installed, archives=archives, left_out=manifest.get("left_out", []))


def activate(target: Path) -> None:
    """Put ``target`` first on this process's ``sys.path`` and on ``PYTHONPATH`` (the stages' subprocesses)."""
    target = str(Path(target).resolve())
    if target not in sys.path:
        sys.path.insert(0, target)
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (target, os.environ.get("PYTHONPATH", "")) if p)
    importlib.invalidate_caches()
