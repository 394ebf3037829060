"""Reading and running the shell commands of README.md and docs/*.md (``test_docs_commands.py`` classifies
and runs them; the ```python blocks are ``doc_blocks.py``'s).

A command is one logical line of a fenced ```bash / ```sh / ```shell block (backslash continuations
joined, ``#`` comments dropped) or a ``$ `` line of a ```console block, keyed by ``(file, text)``. A
block right after an HTML comment ``<!-- commands: not run: REASON -->`` is marked not runnable as a
whole, with that reason (for pages whose commands another test runs, or that need what CI lacks).

Running: :func:`make_clone` copies the repository into a temporary folder (a fresh-clone stand-in,
``../shared`` linked beside it as in CI) and writes the generated datasets the docs' placeholder paths
stand for; :func:`run_command` runs one command there with ``bash``, as printed apart from the
placeholder paths (:data:`PLACEHOLDERS`) and the listed shortenings, with this interpreter's ``bin/``
first on ``PATH`` (``python``, ``pip`` and ``mssf`` are the environment's).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

REPO = Path(__file__).resolve().parents[2]
DOC_FILES = [REPO / "README.md"] + sorted((REPO / "docs").glob("*.md"))
SHELL_LANGS = ("bash", "sh", "shell", "console", "shell-session")
_FENCE = re.compile(r"^(\s*)(```+)\s*([\w+-]*)")
_MARKER = re.compile(r"<!--\s*commands:\s*not run:\s*(?P<reason>.+?)\s*-->")

#: Paths the docs use for the reader's own data; each stands for a generated tree in the test's clone.
#: (``/tmp/`` is the reader's scratch folder: the test writes there inside its own temporary folder.)
PLACEHOLDERS = {
    "/data/view_of_delft": "data/view_of_delft",  # a View-of-Delft release tree (radar_5frames, ImageSets)
    "/data/TJ4DRadSet": "data/TJ4DRadSet",  # a TJ4DRadSet tree (training/, ImageSets/)
    "/tmp/": "scratch/",
}


@dataclass(frozen=True)
class Command:
    file: str  # relative to the repository, e.g. "docs/real-data.md"
    line: int  # 1-based line of the command's first line
    text: str  # continuations joined with single spaces, comment dropped
    not_run: Optional[str] = None  # the reason of a `<!-- commands: not run: ... -->` marker

    @property
    def key(self) -> Tuple[str, str]:
        return (self.file, self.text)

    @property
    def where(self) -> str:
        return f"{self.file}:{self.line}"


def strip_comment(line: str) -> str:
    """``line`` without a ``#`` comment (a ``#`` at the start or after whitespace, outside quotes)."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip()
    return line.rstrip()


def _block_commands(rel: str, start: int, lang: str, body: Sequence[str], not_run: Optional[str]) -> List[Command]:
    out, pending, first = [], [], 0
    for i, raw in enumerate(body):
        line = raw.strip()
        if lang == "console":
            if pending:
                pass  # a continuation of a `$ ` line
            elif line.startswith("$ "):
                line = line[2:]
            else:
                continue  # output
        line = strip_comment(line) if not line.endswith("\\") else line
        if not pending and not line:
            continue
        if not pending:
            first = start + 1 + i + 1
        if line.endswith("\\"):
            pending.append(line[:-1].strip())
            continue
        pending.append(line)
        out.append(Command(rel, first, " ".join(p for p in pending if p), not_run))
        pending = []
    if pending:
        raise ValueError(f"{rel}:{first}: a command ends with a line continuation and no next line")
    return out


def shell_commands(path: Path, root: Path = REPO) -> List[Command]:
    """The commands of the fenced shell blocks of a Markdown file (see the module docstring)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    rel = path.relative_to(root).as_posix()
    commands, i = [], 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, lang, start = m.group(2), m.group(3).lower(), i
        i += 1
        body = []
        while i < len(lines) and not lines[i].strip().startswith(fence):
            body.append(lines[i])
            i += 1
        i += 1
        if lang in SHELL_LANGS:
            prev = next((lines[j] for j in range(start - 1, -1, -1) if lines[j].strip()), "")
            marker = _MARKER.search(prev)
            commands += _block_commands(rel, start, "console" if lang in ("console", "shell-session") else "sh",
                                        body, marker.group("reason") if marker else None)
    return commands


ALL_COMMANDS = [c for f in DOC_FILES for c in shell_commands(f)]


# ---------------------------------------------------------------------------------------------------
# the clone and its generated data
# ---------------------------------------------------------------------------------------------------
_IGNORE = shutil.ignore_patterns(".git", ".venv", "__pycache__", "*.egg-info", ".pytest_cache", ".hypothesis",
                                 "build", "dist", "outputs", "*.pt", "*.pyc", "site", "results", "*.onnx")


def write_vod_and_tj4d_trees(data: Path) -> Dict[str, List[str]]:
    """``data/view_of_delft`` (VoD layout: ``radar_5frames/{training,testing}``, ``ImageSets/{train,val,test}``;
    frame ids from 00100, the one the docs' ``real_frame.py`` line names) and ``data/TJ4DRadSet`` (the same
    scenes in TJ4DRadSet's layout and 8-channel point files), all from generated scenes."""
    import numpy as np

    from mssf_examples.data.kitti_export import write_vod_tree
    from mssf_examples.scenes.synthetic import SceneConfig, SyntheticDataset

    cfg = SceneConfig(image_size=(64, 104))
    splits = {"train": [SyntheticDataset("train", 4, cfg, seed=3)[i] for i in range(4)],
              "val": [SyntheticDataset("val", 2, cfg, seed=3)[i] for i in range(2)]}
    vod = data / "view_of_delft"
    ids = write_vod_tree(vod, splits, first_id=100)
    base = vod / "radar_5frames"
    for sub in ("velodyne", "calib", "image_2"):  # the unlabelled test split: testing/ without label_2
        (base / "testing" / sub).mkdir(parents=True)
        for i in ids["val"]:
            f = next((base / "training" / sub).glob(f"{i}.*"))
            shutil.copyfile(f, base / "testing" / sub / f.name)
    (base / "ImageSets" / "test.txt").write_text("\n".join(ids["val"]) + "\n")
    tj = data / "TJ4DRadSet"
    for sub in ("calib", "image_2", "label_2"):
        shutil.copytree(base / "training" / sub, tj / "training" / sub)
    (tj / "training" / "velodyne").mkdir()
    for f in (base / "training" / "velodyne").iterdir():  # x, y, z, V_r, Range, Power, Alpha, Beta
        p = np.fromfile(f, dtype="<f4").reshape(-1, 7)
        cols = [p[:, 0], p[:, 1], p[:, 2], p[:, 4], np.linalg.norm(p[:, :3], axis=1), p[:, 3],
                np.arctan2(p[:, 1], p[:, 0]), np.zeros(len(p))]
        np.stack(cols, 1).astype("<f4").tofile(tj / "training" / "velodyne" / f.name)
    (tj / "ImageSets").mkdir()
    for split in ("train", "val"):
        (tj / "ImageSets" / f"{split}.txt").write_text("\n".join(ids[split]) + "\n")
    return ids


def make_clone(tmp: Path) -> Path:
    """A copy of the repository's files at ``tmp/clone`` with ``tmp/shared`` -> ``../shared`` (when it
    exists) and the generated data of :data:`PLACEHOLDERS` under ``tmp``; returns the clone."""
    clone = tmp / "clone"
    shutil.copytree(REPO, clone, ignore=_IGNORE)
    shared = REPO.parent / "shared"
    if shared.exists():
        (tmp / "shared").symlink_to(shared.resolve())
    write_vod_and_tj4d_trees(tmp / "data")
    (tmp / "scratch").mkdir()
    return clone


def substitute(text: str, tmp: Path, replace: Optional[Dict[str, str]] = None) -> str:
    """``text`` with the listed shortenings (each must occur) and then the placeholder paths replaced."""
    for old, new in (replace or {}).items():
        if old not in text:
            raise AssertionError(f"shortening {old!r} does not occur in the command {text!r}")
        text = text.replace(old, new)
    pattern = "|".join(re.escape(p) for p in PLACEHOLDERS)  # one pass, each at the start of a path
    return re.sub(rf"(?<![\w/.~-])({pattern})",
                  lambda m: str(tmp / PLACEHOLDERS[m.group(1)]) + ("/" if m.group(1).endswith("/") else ""), text)


def run_command(command: Command, clone: Path, replace: Optional[Dict[str, str]] = None,
                timeout: float = 300, path_first: Sequence[Path] = (), pythonpath: Optional[Path] = None
                ) -> subprocess.CompletedProcess:
    """Run ``command`` in ``clone`` (see the module docstring; the placeholders' trees are expected beside
    it, ``path_first`` goes before this interpreter's ``bin/`` on ``PATH``, ``pythonpath`` is the only
    ``PYTHONPATH``); raises ``AssertionError`` naming the doc line, the command as run and its output's
    tail when it exits non-zero."""
    text = substitute(command.text, clone.parent, replace)
    bindirs = [str(p) for p in path_first] + [str(Path(sys.executable).parent)]
    env = dict(os.environ, PATH=os.pathsep.join(bindirs + [os.environ.get("PATH", "")]), OMP_NUM_THREADS="1")
    env.pop("PYTHONPATH", None)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    r = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", text], cwd=clone, env=env, capture_output=True,
                       text=True, timeout=timeout)
    if r.returncode != 0:
        raise AssertionError(f"{command.where}: the documented command failed (exit {r.returncode}):\n  {text}\n"
                             f"--- stdout (tail) ---\n{r.stdout[-2000:]}\n--- stderr (tail) ---\n{r.stderr[-3000:]}")
    return r
