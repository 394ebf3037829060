"""``benchmarks/gpu_bundle.py`` (the bundle built here) and ``benchmarks/_bundle.py`` (installed offline on the
GPU machine): the 64 MiB limit with the tracked files, the choice by value, the pinned hashes, the cache,
the manifest, the refusal of an altered bundle, the offline install. A stand-in bundle of two tiny
generated packages (``tests/helpers/gpu_bundle_stand_in.py``) stands for the real one (spconv, 45 MB)."""

import os
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_bundle_stand_in import PROBES, build_stand_in, make_wheel, stand_in_groups  # noqa: E402

import _bundle  # noqa: E402  (benchmarks/, put on the path by gpu_bundle_stand_in)
import gpu_bundle as gb  # noqa: E402

MiB = 2**20
#: pip and urllib pointed at nothing: what "no network" looks like to them
OFFLINE = dict(http_proxy="http://127.0.0.1:9", https_proxy="http://127.0.0.1:9", HTTP_PROXY="http://127.0.0.1:9",
               HTTPS_PROXY="http://127.0.0.1:9", no_proxy="", NO_PROXY="", PIP_CONFIG_FILE=os.devnull,
               PIP_RETRIES="0", PIP_TIMEOUT="2", PIP_FIND_LINKS="")


def test_the_limit_counts_the_tracked_files_and_names_the_largest():
    assert gb.check_total({"a.whl": 10 * MiB}, tracked=4 * MiB) == 14 * MiB
    assert gb.check_total({"a.whl": 60 * MiB}, tracked=4 * MiB) == 64 * MiB  # exactly the limit fits
    with pytest.raises(gb.BundleError) as info:
        gb.check_total({"small.whl": 1000, "spconv.tar.xz": 60 * MiB, "cumm.tar.xz": 3 * MiB}, tracked=4 * MiB)
    msg = str(info.value)
    assert "over the 64 MiB" in msg and "tracked files (4.2 MB)" in msg
    assert msg.index("spconv.tar.xz 62.9 MB") < msg.index("cumm.tar.xz 3.1 MB")  # the largest first


def test_groups_are_kept_by_value_and_the_first_must_fit():
    groups = [("spconv", {"spconv.tar.xz": 45 * MiB}), ("mmcv_src", {"mmcv.tar.gz": 10 * MiB}),
              ("small", {"x.whl": 1 * MiB})]
    assert gb.choose(groups, tracked=3 * MiB) == (["spconv", "mmcv_src", "small"], [])
    kept, left = gb.choose(groups, tracked=10 * MiB)  # 45 + 10 + 10 > 64: mmcv_src goes, the smaller one stays
    assert kept == ["spconv", "small"] and len(left) == 1 and left[0].startswith("mmcv_src (10.5 MB): over")
    with pytest.raises(gb.BundleError, match="spconv.tar.xz"):
        gb.choose(groups, tracked=20 * MiB)


def test_the_tracked_size_is_what_git_sends(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("git not installed")
    repo = tmp_path / "r"
    repo.mkdir()
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / ".gitignore").write_text(".carry/\n")
    (repo / "tracked.txt").write_bytes(b"x" * 1000)
    (repo / "new.txt").write_bytes(b"y" * 300)  # untracked, not ignored: it travels too
    (repo / ".carry").mkdir()
    (repo / ".carry" / "big.bin").write_bytes(b"z" * 5000)  # ignored: carried only when named
    subprocess.run(["git", "-C", str(repo), "add", "tracked.txt", ".gitignore"], check=True)
    assert gb.tracked_bytes(repo) == 1000 + 300 + len(".carry/\n")


def test_build_writes_a_verified_manifest_reuses_its_cache_and_refuses_too_much(tmp_path):
    out, cache = tmp_path / "bundle", tmp_path / "cache"
    out.mkdir()
    (out / "stale.whl").write_bytes(b"old")  # the folder is carried whole: anything else goes
    manifest = build_stand_in(out, cache, tracked=123)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(["manifest.json", "mssf_probe_wheel-0.0.1-py3-none-any.whl",
                            "mssf_probe_xz-0.0.2-py3-none-any.tar.xz", "mmcv-0.0.0.tar.gz"])
    assert manifest["tracked_bytes"] == 123 and manifest["left_out"] == []
    assert manifest["total_bytes"] == 123 + sum(e["bytes"] for e in manifest["entries"])
    for e in manifest["entries"]:
        assert _bundle.sha256_of(out / e["file"]) == e["sha256"]
    packed = out / "mssf_probe_xz-0.0.2-py3-none-any.tar.xz"
    with tarfile.open(packed) as tar:  # the wheel's files as they are
        assert sorted(tar.getnames())[0] == "mssf_probe_xz-0.0.2.dist-info/METADATA"
        assert tar.extractfile("mssf_probe_xz/__init__.py").read() == b"__version__ = '0.0.2'\n"
    first = packed.read_bytes()
    # a rerun: nothing downloaded (build_stand_in's download raises), the repack reused; and deterministic
    (cache / packed.name).unlink()
    build_stand_in(out, cache, tracked=123)
    assert packed.read_bytes() == first
    with pytest.raises(gb.BundleError, match="over the 64 MiB .*mssf_probe"):
        build_stand_in(out, cache, tracked=64 * MiB - 10)


def test_a_cached_file_that_differs_from_the_pinned_hash_is_refused(tmp_path):
    cache = tmp_path / "cache"
    (_, _, (item, _)), _ = stand_in_groups(cache)
    (cache / item.filename).write_bytes(b"tampered")
    with pytest.raises(gb.BundleError, match=f"{item.filename}: sha256 .* expected {item.sha256}"):
        gb.fetch(item, cache)


def test_downloads_fail_clearly_without_network(tmp_path, monkeypatch):
    for k, v in OFFLINE.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setenv("PIP_NO_INDEX", "1")
    wheel = gb.Item("mssf-no-such-package==0.0.1", "mssf_no_such_package-0.0.1-py3-none-any.whl", "0" * 64, "wheel")
    with pytest.raises(gb.BundleError, match=r"pip download mssf-no-such-package==0.0.1` failed .*no network\?"):
        gb.fetch(wheel, tmp_path)
    archive = gb.Item("mmcv==2.1.0", "mmcv-2.1.0.tar.gz", "0" * 64, "archive")
    with pytest.raises(gb.BundleError, match="downloading mmcv-2.1.0.tar.gz from .* failed \\(no network\\?"):
        gb._index_download(archive, tmp_path, index="http://127.0.0.1:9/simple")


def test_the_bundle_installs_offline_and_an_altered_one_is_refused(tmp_path):
    bundle = tmp_path / "bundle"
    build_stand_in(bundle, tmp_path / "cache")
    env = dict(os.environ, **OFFLINE, PIP_INDEX_URL="http://127.0.0.1:9/simple")
    site = tmp_path / "site"
    code = ("import sys, _bundle; info = _bundle.install(sys.argv[1], sys.argv[2]); _bundle.activate(sys.argv[2]); "
            "import mssf_probe_wheel, mssf_probe_xz, os, json; "
            "print(json.dumps([info['archives'], mssf_probe_wheel.__version__, mssf_probe_xz.__version__, "
            "os.environ['PYTHONPATH'].split(os.pathsep)[0]]))")
    r = subprocess.run([sys.executable, "-c", code, str(bundle), str(site)], env=dict(env, PYTHONPATH=str(gb.REPO / "benchmarks")),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    import json

    archives, v_wheel, v_xz, first_path = json.loads(r.stdout.strip().splitlines()[-1])
    assert (v_wheel, v_xz) == tuple(v for _, v, _ in PROBES)
    assert archives == {"mmcv_src": str((bundle / "mmcv-0.0.0.tar.gz").resolve())}
    assert first_path == str(site.resolve())  # the stages' subprocesses see the site first
    assert (site / "mssf_probe_xz-0.0.2.dist-info" / "METADATA").is_file()
    # altered after the build: refused before anything is installed, naming the file
    wheel = bundle / "mssf_probe_wheel-0.0.1-py3-none-any.whl"
    data = bytearray(wheel.read_bytes())
    data[-1] ^= 1
    wheel.write_bytes(bytes(data))
    with pytest.raises(_bundle.BundleError, match="mssf_probe_wheel-0.0.1-py3-none-any.whl: sha256"):
        _bundle.install(bundle, tmp_path / "site2")
    assert not (tmp_path / "site2").exists()
    wheel.write_bytes(b"short")
    with pytest.raises(_bundle.BundleError, match="a partial copy"):
        _bundle.install(bundle, tmp_path / "site2")
    with pytest.raises(_bundle.BundleError, match="no manifest.json .*`make gpu-bundle`"):
        _bundle.install(tmp_path / "cache", tmp_path / "site2")


def test_a_failing_offline_pip_is_reported_with_its_message(tmp_path):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    broken = make_wheel(bundle, "mssf_probe_wheel", "0.0.1")
    broken.write_bytes(b"not a zip")
    (bundle / "manifest.json").write_text(
        '{"entries": [{"file": "%s", "kind": "wheel", "bytes": %d, "sha256": "%s"}]}'
        % (broken.name, broken.stat().st_size, _bundle.sha256_of(broken)))
    with pytest.raises(_bundle.BundleError, match="pip install --no-index --target .* failed"):
        _bundle.install(bundle, tmp_path / "site")
