"""benchmarks/data_path.py: the stay counter and the tracer on hand-worked examples, then one real forward."""

import importlib
import inspect
import json
import os
import sys
import textwrap
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

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
        import functools

        import outside
        from pkg import b, c

        def run(h):
            b.check(h.features)            # b, c (data: a tensor the holder carries)
            b.count(3)                     # b, c (not data)
            try:
                b.fails(h)                 # b, left by an exception
            except ValueError:
                pass
            c.via(functools.partial(b.check, h.features))  # c (not data) calls b with data
            outside.call_back(b.inner, h)  # outside code calls back into b
            h.centre()                     # c: a method of the holder (data: self)
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
        class Holder:
            def __init__(self):
                self.features = object()

            def centre(self):
                return plain(0)

        def deep(t):
            return t

        def plain(n):
            return n

        def via(fn):
            return fn()
    """,
    "outside.py": """
        def call_back(fn, arg):
            return fn(arg)
    """,
}


def _holder(obj):
    return [obj.features] if type(obj).__name__ == "Holder" else None


def _new_holder():
    return sys.modules["pkg.c"].Holder()  # (build it before tracing: its __init__ is in c.py)


@pytest.fixture
def pkg(tmp_path, monkeypatch):
    for name, text in _PKG.items():
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text(textwrap.dedent(text))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield importlib.import_module("pkg.a"), str(tmp_path / "pkg")
    for m in ("pkg", "pkg.a", "pkg.b", "pkg.c", "outside"):  # (the next test imports its own copy)
        sys.modules.pop(m, None)


def test_tracer_all_frames_hand_worked(pkg):
    a, root = pkg
    h = _new_holder()
    with PathTracer(root) as tracer:
        a.run(h)
    # a >check b >deep c >b >a >count b >plain c >b >a >fails b >a (exception) >via c >check b >deep c >b >c
    # >a >inner b (from outside) >a (through outside) >centre c (>plain c) >a >helper a >done b >a; then the
    # call is left
    expected = ["a.py", "b.py", "c.py", "b.py", "a.py", "b.py", "c.py", "b.py", "a.py", "b.py", "a.py",
                "c.py", "b.py", "c.py", "b.py", "c.py", "a.py", "b.py", "a.py", "c.py", "a.py", "b.py", "a.py", None]
    assert tracer.sequence == expected
    c = count_stays(tracer.sequence)
    assert (c["num_stays"], c["files_entered"], c["returns"]) == (23, 3, 20)
    assert c["visits"] == {"a.py": 8, "b.py": 9, "c.py": 6}


def test_tracer_data_frames_hand_worked(pkg):
    a, root = pkg
    h = _new_holder()
    with PathTracer(root, _holder) as tracer:
        a.run(h)
    # count(3), plain(3) and via(partial) receive no voxel data: no stay for them, and check's return
    # goes back to run's file, not via's
    assert tracer.sequence == ["a.py", "b.py", "c.py", "b.py", "a.py", "b.py", "a.py", "b.py", "c.py", "b.py",
                               "a.py", "b.py", "a.py", "c.py", "a.py", "b.py", "a.py", None]
    c = count_stays(tracer.sequence)
    assert (c["num_stays"], c["files_entered"], c["returns"]) == (17, 3, 14)
    assert c["visits"] == {"a.py": 7, "b.py": 7, "c.py": 3}


def test_tracer_data_follows_an_attribute_one_level_deep(pkg):
    _, root = pkg
    b = sys.modules["pkg.b"]

    class Box:
        def __init__(self, inner):
            self.inner = inner

    one, two = Box(_new_holder()), Box(Box(_new_holder()))
    with PathTracer(root, _holder) as tracer:
        b.inner(one)  # the holder one level down: data
        b.inner(two)  # two levels down: not followed
    assert tracer.sequence == ["b.py", None]


def test_a_real_forward(tmp_path):
    pytest.importorskip("spconv")
    import mssf_blocks
    from mssf_blocks import FusionBlock, SparseVoxels

    root = os.path.dirname(os.path.abspath(mssf_blocks.__file__))
    home, voxels_home = (os.path.relpath(inspect.getsourcefile(c), root).replace(os.sep, "/")
                         for c in (FusionBlock, SparseVoxels))
    counts = measure_variant("sff-voxels")
    for mode in ("all", "data"):
        c = counts[mode]
        # forward is entered and left in FusionBlock's file, and the counts agree with the stays
        assert c["stays"][0] == c["stays"][-1] == home
        assert c == count_stays(c["stays"])
    # following the data keeps a subset of the files and fewer stays
    assert set(counts["data"]["visits"]) < set(counts["all"]["visits"])
    assert counts["data"]["num_stays"] < counts["all"]["num_stays"]
    assert voxels_home in counts["data"]["visits"]  # the voxels' own methods (self) are on the data's way
    out = tmp_path / "path.json"
    assert main(["--variants", "sff-voxels", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["variants"]["sff-voxels"] == counts  # repeatable
