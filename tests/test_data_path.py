"""benchmarks/data_path.py: the stay counter and the tracer on hand-worked examples, then one real forward."""

import importlib
import inspect
import json
import os
import sys
import textwrap
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from data_path import PathTracer, count_stays, main, measure_variant  # noqa: E402


def test_count_stays_hand_worked():
    # a a | b | (left) | b | a | c | a | b: the exit ends b's stay, so 7 stays a b b a c a b in 3 files;
    # returns: the 2nd b, the 2nd and 3rd a, the 3rd b = 4
    c = count_stays(["a.py", "a.py", "b.py", None, "b.py", "a.py", "c.py", "a.py", "b.py"])
    assert c["stays"] == ["a.py", "b.py", "b.py", "a.py", "c.py", "a.py", "b.py"]
    assert (c["num_stays"], c["files_entered"], c["returns"]) == (7, 3, 4)
    assert c["visits"] == {"a.py": 3, "b.py": 3, "c.py": 1}
    assert count_stays([None, None])["num_stays"] == 0


_PKG = {
    "pkg/__init__.py": "",
    "pkg/a.py": """
        import outside
        from pkg import b

        def run(h):
            b.check(h.features)            # b, c (data: a tensor the holder carries)
            b.count(3)                     # b, c (not data)
            try:
                b.fails(h)                 # b, left by an exception
            except ValueError:
                pass
            outside.call_back(b.inner, h)  # outside code calls back into b
            return helper(h)               # same file: no new stay

        def helper(h):
            return b.done([h])             # data: a list holding the holder
    """,
    "pkg/b.py": """
        from pkg import c

        def check(t):
            return c.deep(t)

        def count(n):
            return c.plain(n)

        def fails(h):
            raise ValueError(h)

        def inner(h):
            return None

        def done(items):
            return len(items)
    """,
    "pkg/c.py": """
        def deep(t):
            return t

        def plain(n):
            return n
    """,
    "outside.py": """
        def call_back(fn, arg):
            return fn(arg)
    """,
}


class _Holder:
    def __init__(self):
        self.features = object()


def _holder(obj):
    return [obj.features] if isinstance(obj, _Holder) else None


@pytest.fixture
def pkg(tmp_path, monkeypatch):
    for name, text in _PKG.items():
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text(textwrap.dedent(text))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield importlib.import_module("pkg.a"), str(tmp_path / "pkg")
    for m in ("pkg", "pkg.a", "pkg.b", "pkg.c", "outside"):
        sys.modules.pop(m, None)


def test_tracer_all_frames_hand_worked(pkg):
    a, root = pkg
    with PathTracer(root) as tracer:
        a.run(_Holder())
    # a >check b >deep c >b >a >count b >plain c >b >a >fails b >a (exception) >inner b (from outside)
    # >a (through outside) >helper a >done b >a; then the call is left
    expected = ["a.py", "b.py", "c.py", "b.py", "a.py", "b.py", "c.py", "b.py", "a.py", "b.py", "a.py",
                "b.py", "a.py", "b.py", "a.py", None]
    assert tracer.sequence == expected
    c = count_stays(tracer.sequence)
    assert (c["num_stays"], c["files_entered"], c["returns"]) == (15, 3, 12)
    assert c["visits"] == {"a.py": 6, "b.py": 7, "c.py": 2}


def test_tracer_data_frames_hand_worked(pkg):
    a, root = pkg
    with PathTracer(root, _holder) as tracer:
        a.run(_Holder())
    # count(3) and plain(3) receive no voxel data: no stay in b or c for them
    assert tracer.sequence == ["a.py", "b.py", "c.py", "b.py", "a.py", "b.py", "a.py", "b.py", "a.py", "b.py",
                               "a.py", None]
    c = count_stays(tracer.sequence)
    assert (c["num_stays"], c["files_entered"], c["returns"]) == (11, 3, 8)
    assert c["visits"] == {"a.py": 5, "b.py": 5, "c.py": 1}


def test_tracer_data_follows_an_attribute_one_level_deep(pkg):
    a, root = pkg
    b = sys.modules["pkg.b"]

    class Box:
        def __init__(self, inner):
            self.inner = inner

    with PathTracer(root, _holder) as tracer:
        b.inner(Box(_Holder()))         # the holder one level down: data
        b.inner(Box(Box(_Holder())))    # two levels down: not followed
    assert tracer.sequence == ["b.py", None]


def test_a_real_forward(tmp_path):
    pytest.importorskip("spconv")
    from mssf_blocks import FusionBlock

    import mssf_blocks

    root = os.path.dirname(os.path.abspath(mssf_blocks.__file__))
    home = os.path.relpath(inspect.getsourcefile(FusionBlock), root).replace(os.sep, "/")
    counts = measure_variant("sff-voxels")
    for mode in ("all", "data"):
        c = counts[mode]
        # forward is entered and left in FusionBlock's file, and the counts agree with the stays
        assert c["stays"][0] == c["stays"][-1] == home
        assert c == count_stays(c["stays"])
    # following the data keeps a subset of the files and fewer stays
    assert set(counts["data"]["visits"]) < set(counts["all"]["visits"])
    assert counts["data"]["num_stays"] < counts["all"]["num_stays"]
    out = tmp_path / "path.json"
    assert main(["--variants", "sff-voxels", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["variants"]["sff-voxels"] == counts  # repeatable
