"""Which column layout a float32 point file holds, decided from its values, not from its size alone.

A ``velodyne/<id>.bin`` file is a bare run of float32 values: its size only says which row widths divide
it. 224 bytes are 8 View-of-Delft rows of 7 floats and 7 TJ4DRadSet rows of 8 alike (one VoD frame in
eight has such a size: 8 * k points), and the real VoD frame 01047 (352 points) is one. So a reading is
accepted only when the columns look like what they are named, tested on every row:

* ``time`` (VoD: which radar scan, ``0`` for the current one, ``-1`` for the one before, ..., as the VoD
  devkit's SENSORS_AND_DATA.md defines it): an integer in ``[-MAX_SCANS, 0]``;
* ``range`` (TJ4DRadSet: the distance the radar measured): ``|x, y, z|`` within ``RANGE_REL_TOL`` of
  itself plus ``RANGE_ABS_TOL`` (the coordinates are that range along the measured angles: on the 41
  frames of TJ4DRadSet's public sample, 108,222 points, they agree to 3.1e-5 m, 1.9e-7 of the range);
* ``reflectance`` (KITTI LiDAR): in ``[0, 1]``;
* every column: finite.

Read the wrong way, a file puts every other column in these places (row ``i`` of a width-8 reading of a
width-7 file starts at value ``8 i``, i.e. column ``i mod 7``), so a wrong reading fails them on most
rows. Columns without a test are not checked; a layout without a tested column is never evidence for
itself (:attr:`Reading.evidence` is empty) and decides nothing.

:func:`read_layouts` reads one file every way; :func:`plausible_layouts` keeps the readings that pass.
Used by the CLI (``python -m mssf_examples``: ``cli/loading.py``) to tell ``--dataset vod`` from ``tj4d``, and
by :func:`~mssf_examples.data.kitti_points.read_points` when a file fits another known format by size.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np

from .kitti_points import PointFormat

__all__ = ["MAX_SCANS", "RANGE_REL_TOL", "RANGE_ABS_TOL", "Reading", "column_problem", "read_layouts",
           "plausible_layouts"]

#: Most radar scans a VoD-style ``time`` column may go back (VoD itself: 4, in ``radar_5frames``).
MAX_SCANS = 64
#: ``range`` must equal ``|x, y, z|`` within ``RANGE_REL_TOL * range + RANGE_ABS_TOL`` metres on every row.
RANGE_REL_TOL = 1e-3
RANGE_ABS_TOL = 1e-2


def _share(bad: np.ndarray) -> str:
    return f"{int(bad.sum())} of {bad.size} rows"


def _time_problem(t: np.ndarray, xyz: np.ndarray) -> Optional[str]:
    bad = ~((t == np.round(t)) & (t <= 0) & (t >= -MAX_SCANS))
    if bad.any():
        return (f"column 'time' is not a scan offset (an integer in [-{MAX_SCANS}, 0]) on {_share(bad)}, "
                f"e.g. {float(t[bad][0]):.6g}")
    return None


def _range_problem(r: np.ndarray, xyz: np.ndarray) -> Optional[str]:
    norm = np.sqrt((xyz.astype(np.float64) ** 2).sum(1))
    off = np.abs(r.astype(np.float64) - norm)
    bad = ~(off <= RANGE_REL_TOL * np.abs(norm) + RANGE_ABS_TOL)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        return (f"column 'range' differs from |x, y, z| on {_share(bad)}, e.g. {float(r[i]):.6g} against "
                f"{norm[i]:.6g}")
    return None


def _reflectance_problem(v: np.ndarray, xyz: np.ndarray) -> Optional[str]:
    bad = ~((v >= 0) & (v <= 1))
    if bad.any():
        return f"column 'reflectance' is outside [0, 1] on {_share(bad)}, e.g. {float(v[bad][0]):.6g}"
    return None


#: The tested columns, by name (:class:`~mssf_examples.data.kitti_points.PointFormat` channel names).
_COLUMN_TESTS = {"time": _time_problem, "range": _range_problem, "reflectance": _reflectance_problem}


def column_problem(rows: np.ndarray, point_format: PointFormat) -> Tuple[Optional[str], Tuple[str, ...]]:
    """``(problem, evidence)`` for ``(P, C)`` rows read as ``point_format``: why they are not its columns
    (``None`` when they pass) and the tested column names that passed."""
    if not np.isfinite(rows).all():
        bad = ~np.isfinite(rows).all(1)
        return f"non-finite values on {_share(bad)}", ()
    xyz = rows[:, :3]
    evidence = []
    for i, name in enumerate(point_format.channels):
        test = _COLUMN_TESTS.get(name)
        if test is None:
            continue
        problem = test(rows[:, i], xyz)
        if problem:
            return problem, ()
        evidence.append(name)
    return None, tuple(evidence)


@dataclass(frozen=True)
class Reading:
    """One way of reading a file: its rows as ``point_format``'s columns.

    Attributes:
        point_format: the layout tried.
        values: float32 values in the file.
        problem: why the values are not this layout (size or columns), ``None`` when they pass.
        evidence: the tested columns that passed (empty: nothing speaks for this layout).
    """

    point_format: PointFormat
    values: int
    problem: Optional[str]
    evidence: Tuple[str, ...] = ()

    @property
    def fits(self) -> bool:
        """The values make whole rows of this layout."""
        return self.values % self.point_format.num_channels == 0

    @property
    def plausible(self) -> bool:
        """Whole rows whose tested columns pass, and at least one tested column (or no rows at all)."""
        return self.problem is None and (bool(self.evidence) or self.values == 0)

    def describe(self) -> str:
        """E.g. ``rows of 7 (vod_radar): column 'time' is not a scan offset ...``."""
        c, name = self.point_format.num_channels, self.point_format.name
        if not self.fits:
            return f"not rows of {c} ({name}: {self.values} values)"
        if self.problem:
            return f"rows of {c} ({name}): {self.problem}"
        if not self.evidence:
            return f"rows of {c} ({name}): no tested column"
        return f"rows of {c} ({name}): plausible ({', '.join(self.evidence)} as expected)"


def _values(source: Union[str, Path, np.ndarray]) -> np.ndarray:
    if isinstance(source, np.ndarray):
        return np.asarray(source, dtype="<f4").reshape(-1)
    return np.fromfile(Path(source), dtype="<f4")


def read_layouts(source: Union[str, Path, np.ndarray], formats: Sequence[PointFormat]) -> List[Reading]:
    """Read ``source`` (a float32 little-endian file, or its values) as each of ``formats``.

    The caller checks first that the file holds whole float32 values (its size a multiple of 4).
    """
    data = _values(source)
    out = []
    for fmt in formats:
        c = fmt.num_channels
        if data.size % c:
            out.append(Reading(fmt, int(data.size), f"{data.size} values are not rows of {c}"))
            continue
        problem, evidence = column_problem(data.reshape(-1, c), fmt)
        out.append(Reading(fmt, int(data.size), problem, evidence))
    return out


def plausible_layouts(readings: Sequence[Reading]) -> List[Reading]:
    """The readings that pass (:attr:`Reading.plausible`)."""
    return [r for r in readings if r.plausible]
