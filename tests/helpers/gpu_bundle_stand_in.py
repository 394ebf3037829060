"""A stand-in GPU-check bundle for the tests: two tiny generated packages, one carried as a wheel and one
as a ``tar.xz`` repack of a wheel, and a stand-in source archive, built by ``benchmarks/gpu_bundle.py``'s
own :func:`build` from a cache filled here (no network). The real bundle (spconv, 45 MB) is not needed
to prove the offline install path."""

from __future__ import annotations

import hashlib
import sys
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
import gpu_bundle as gb  # noqa: E402

#: (module, version, kind) of the stand-in packages.
PROBES = (("mssf_probe_wheel", "0.0.1", "wheel"), ("mssf_probe_xz", "0.0.2", "tar.xz"))


def make_wheel(folder: Path, module: str, version: str) -> Path:
    """A minimal pure-Python wheel of ``module`` (``__version__ = version``), byte-for-byte reproducible."""
    name = f"{module}-{version}-py3-none-any.whl"
    dist = f"{module}-{version}.dist-info"
    files = {
        f"{module}/__init__.py": f"__version__ = {version!r}\n",
        f"{dist}/METADATA": f"Metadata-Version: 2.1\nName: {module}\nVersion: {version}\n",
        f"{dist}/WHEEL": "Wheel-Version: 1.0\nGenerator: mssf-tests\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
    }
    record = "".join(f"{k},sha256={_b64(v.encode())},{len(v.encode())}\n" for k, v in files.items())
    files[f"{dist}/RECORD"] = record + f"{dist}/RECORD,,\n"
    path = Path(folder) / name
    with zipfile.ZipFile(path, "w") as zf:
        for k, v in files.items():
            info = zipfile.ZipInfo(k, date_time=(2026, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            zf.writestr(info, v)
    return path


def _b64(data: bytes) -> str:
    import base64

    return base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def stand_in_groups(cache: Path):
    """``gpu_bundle.GROUPS``-shaped groups whose upstream files are generated into ``cache`` and pinned."""
    cache.mkdir(parents=True, exist_ok=True)
    items = []
    for module, version, kind in PROBES:
        wheel = make_wheel(cache, module, version)
        items.append(gb.Item(f"{module}=={version}", wheel.name, gb.sha256_of(wheel), kind, module))
    archive = cache / "mmcv-0.0.0.tar.gz"
    archive.write_bytes(b"not a real archive: the CPU dry run never builds mmcv's op\n")
    src = gb.Item("mmcv==0.0.0", archive.name, gb.sha256_of(archive), "archive", role="mmcv_src")
    return (("probes", "a", tuple(items)), ("mmcv_src", "b", (src,)))


def build_stand_in(out: Path, cache: Path, tracked: int = 0):
    """The stand-in bundle in ``out``; its manifest."""
    return gb.build(out, cache, groups=stand_in_groups(cache), tracked=tracked,
                    download=lambda item, dest: (_ for _ in ()).throw(AssertionError(f"downloaded {item}")))
