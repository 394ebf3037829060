"""What View-of-Delft and TJ4DRadSet share in OpenPCDet: a ``KittiDataset`` over a KITTI-style radar release.

Both releases keep KITTI's tree (``training/{velodyne,calib,image_2,label_2}``, ``ImageSets/<split>.txt``)
and KITTI's calibration and label files, and differ from KITTI (and from each other) in what
:class:`KittiStyleDataset`'s subclasses set:

* ``POINT_FEATURES``: the float32 columns of a ``velodyne/<id>.bin`` (KittiDataset reads 4), checked
  against ``POINT_FEATURE_ENCODING.src_feature_list`` and, per file, by ``check_points``;
* ``IMAGE_FILE_EXTENSION`` (config key; default ``DEFAULT_IMAGE_EXTENSION``): KittiDataset reads ``.png``;
* ``evaluation()``: the dataset's official protocol (``EVALUATE`` over ``REGIONS`` with ``IOU_THRESHOLDS``),
  not KITTI's;
* the info files (``INFO_PREFIX``): written by :meth:`KittiStyleDataset.create_infos`, without a
  ground-truth database (the paper's recipes do not sample ground truth).

A frame without annotations gets a ``DontCare`` placeholder (``KittiDataset.get_infos`` cannot stack an
empty list); a split that loads no frame is an error saying why. Importing this module imports OpenPCDet.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Sequence, Tuple

import numpy as np
from pcdet.datasets.kitti.kitti_dataset import KittiDataset

from mssf_blocks.errors import MSSFError

from ..evaluation.kitti import Objects

__all__ = ["KittiStyleDataset", "annos_to_objects", "check_feature_encoding"]

#: the placeholder object of a frame without annotations (KITTI's DontCare convention: sizes -1)
_EMPTY_FRAME_LINE = "DontCare -1 -1 -10 0 0 0 0 -1 -1 -1 -1000 -1000 -1000 -10"


def check_feature_encoding(dataset_cfg: Mapping, features: Sequence[str], dataset: str, what: str) -> None:
    """Raise :class:`MSSFError` naming the key when ``POINT_FEATURE_ENCODING`` cannot read ``features``
    (the float32 columns of ``dataset``'s ``what`` files)."""
    enc = dataset_cfg.get("POINT_FEATURE_ENCODING", None)
    if enc is None or "src_feature_list" not in enc or "used_feature_list" not in enc:
        raise MSSFError("DATA_CONFIG.POINT_FEATURE_ENCODING: expected src_feature_list and used_feature_list, "
                        f"got {enc!r}")
    src = list(enc["src_feature_list"])
    if len(src) != len(features):
        raise MSSFError(f"DATA_CONFIG.POINT_FEATURE_ENCODING.src_feature_list: {dataset} {what} have "
                        f"{len(features)} float32 features {list(features)}, the list names {len(src)}: {src}")
    missing = [f for f in enc["used_feature_list"] if f not in src]
    if missing:
        raise MSSFError(f"DATA_CONFIG.POINT_FEATURE_ENCODING.used_feature_list: {missing} not in src_feature_list {src}")


def _sibling_infos(root: Path, names: Sequence[str]) -> List[str]:
    """Folders beside ``root`` (e.g. VoD's other sensor folders) that hold these info files."""
    if not root.parent.is_dir():
        return []
    return sorted(str(d) for d in root.parent.iterdir()
                  if d.is_dir() and d != root and all((d / n).is_file() for n in names))


class KittiStyleDataset(KittiDataset):
    """OpenPCDet dataset over a KITTI-style radar release (``DATA_PATH`` holds ``training/`` and ``ImageSets/``).

    ``require_infos=False`` (used by :meth:`create_infos`) accepts a folder without info files."""

    DATASET_NAME = ""                 # in messages and the evaluation table
    POINT_FEATURES: Tuple[str, ...] = ()
    DEFAULT_IMAGE_EXTENSION = ".png"
    INFO_PREFIX = ""                  # <prefix>_infos_<split>.pkl
    INFOS_COMMAND = ""                # python -m mssf_examples.openpcdet <command>
    SENSOR_FOLDERS: Tuple[str, ...] = ()   # the release's sibling folders whose infos are told apart
    EVALUATE: Callable = None
    REGIONS: Tuple[str, ...] = ()
    IOU_THRESHOLDS: Mapping[str, float] = {}

    def __init__(self, dataset_cfg, class_names, training=True, root_path=None, logger=None, require_infos=True):
        self.check_dataset_cfg(dataset_cfg)
        self.image_extension = str(dataset_cfg.get("IMAGE_FILE_EXTENSION", self.DEFAULT_IMAGE_EXTENSION))
        self.require_infos = bool(require_infos)
        super().__init__(dataset_cfg=dataset_cfg, class_names=class_names, training=training,
                         root_path=root_path, logger=logger)

    @classmethod
    def check_dataset_cfg(cls, dataset_cfg: Mapping) -> None:
        check_feature_encoding(dataset_cfg, cls.POINT_FEATURES, cls.DATASET_NAME, "radar points")

    def check_points(self, points: np.ndarray, path: Any) -> np.ndarray:
        """``points (N, len(POINT_FEATURES))`` read from ``path``, or an error when they cannot be this dataset's."""
        return points

    def include_kitti_data(self, mode):
        super().include_kitti_data(mode)
        if self.require_infos:
            self._check_infos(mode)

    def _check_infos(self, mode: str) -> None:
        """Why a split has no frame, or infos written for another sensor folder than ``DATA_PATH``."""
        root = Path(self.root_path)
        names = [str(n) for n in self.dataset_cfg.INFO_PATH[mode]]
        where = f"DATA_PATH {self.dataset_cfg.DATA_PATH!r} (here {root.resolve()}, from the current folder {Path.cwd()})"
        command = f"python -m mssf_examples.openpcdet {self.INFOS_COMMAND} CFG --data_path {root}"
        if not self.kitti_infos:
            if not names:
                raise MSSFError(f"DATA_CONFIG.INFO_PATH[{mode!r}]: no info file listed, so the {mode} split has no frame")
            if not root.is_dir():
                raise MSSFError(f"{where}: no such folder, so the {mode} split has no frame (OpenPCDet's configs name "
                                "it relative to tools/: run from there)")
            missing = [n for n in names if not (root / n).is_file()]
            if missing:
                found = _sibling_infos(root, missing)
                hint = (f"; they are in {found}: the infos were built for that folder. Point DATA_PATH there, or build "
                        f"infos for this one") if found else ""
                raise MSSFError(f"DATA_CONFIG.INFO_PATH[{mode!r}]: {missing} not found in {where}{hint} ({command})")
            raise MSSFError(f"DATA_CONFIG.INFO_PATH[{mode!r}]: {names} in {where} hold no frame (written from an empty "
                            f"ImageSets/{self.dataset_cfg.DATA_SPLIT[mode]}.txt?); rebuild them with {self.INFOS_COMMAND}")
        built = sorted({str(i["point_cloud"].get("sensor_folder")) for i in self.kitti_infos
                        if i["point_cloud"].get("sensor_folder") is not None})
        # only between the release's own sensor folders: a renamed folder keeps valid infos
        if built and built != [root.name] and {root.name, *built} <= set(self.SENSOR_FOLDERS):
            raise MSSFError(f"DATA_CONFIG.INFO_PATH[{mode!r}]: {names} in {where} were built for the sensor folder "
                            f"{built} (recorded by {self.INFOS_COMMAND}), not {root.name!r}: their point counts and "
                            f"frames belong to that folder. Build infos for this one ({command}) or point DATA_PATH "
                            f"at {built[0]!r}")

    # ------------------------------------------------------------------ files
    def _file(self, folder: str, idx: str, ext: str) -> Path:
        path = self.root_split_path / folder / f"{idx}{ext}"
        if not path.is_file():
            raise MSSFError(f"{self.DATASET_NAME} frame {idx}: expected {path} (DATA_PATH {self.root_path}), not found")
        return path

    def get_lidar(self, idx):
        path = self._file("velodyne", idx, ".bin")
        raw = np.fromfile(str(path), dtype=np.float32)
        n = len(self.dataset_cfg.POINT_FEATURE_ENCODING.src_feature_list)
        if raw.size % n:
            raise MSSFError(f"{path}: {raw.size} float32 values, not a multiple of the {n} features of "
                            "DATA_CONFIG.POINT_FEATURE_ENCODING.src_feature_list")
        return self.check_points(raw.reshape(-1, n), path)

    def get_image(self, idx):
        """``(H, W, 3)`` float32 RGB in [0, 1], as ``KittiDataset.get_image``."""
        from PIL import Image

        with Image.open(self._file("image_2", idx, self.image_extension)) as img:
            return np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0

    def get_image_shape(self, idx):
        from PIL import Image

        with Image.open(self._file("image_2", idx, self.image_extension)) as img:
            w, h = img.size
        return np.array([h, w], dtype=np.int32)

    def get_label(self, idx):
        """KITTI objects; a frame without annotations gives one ``DontCare`` placeholder (never learned nor
        evaluated), because ``KittiDataset.get_infos`` cannot stack an empty list."""
        path = self._file("label_2", idx, ".txt")
        if not path.read_text().strip():
            from pcdet.utils.object3d_kitti import Object3d

            return [Object3d(_EMPTY_FRAME_LINE)]
        return super().get_label(idx)

    def get_calib(self, idx):
        self._file("calib", idx, ".txt")
        return super().get_calib(idx)

    def get_infos(self, num_workers=4, has_label=True, count_inside_pts=True, sample_id_list=None):
        infos = super().get_infos(num_workers, has_label, count_inside_pts, sample_id_list)
        for info in infos:
            info["point_cloud"]["num_features"] = len(self.dataset_cfg.POINT_FEATURE_ENCODING.src_feature_list)
            # the folder the point counts come from: a DATA_PATH naming another one is refused at load
            info["point_cloud"]["sensor_folder"] = Path(self.root_path).name
        return infos

    # ------------------------------------------------------------------ evaluation
    def evaluation(self, det_annos, class_names, **kwargs) -> Tuple[str, Dict[str, float]]:
        """The official protocol's AP of ``det_annos`` (``generate_prediction_dicts``) per region.

        Returns ``(table text, {"<region>/<Class>_<AP3D|APBEV>_<R11|R40>": AP in percent,
        "<region>/mAP3D_R40": their mean over class_names})``.
        """
        if not self.kitti_infos or "annos" not in self.kitti_infos[0]:
            return None, {}
        by_frame = {str(d["frame_id"]): d for d in det_annos}
        frames = [str(info["point_cloud"]["lidar_idx"]) for info in self.kitti_infos]
        missing = [f for f in frames if f not in by_frame]
        if missing:
            raise MSSFError(f"det_annos: no predictions for frames {missing[:5]} ({len(missing)} of {len(frames)})")
        unknown = [c for c in class_names if c not in self.IOU_THRESHOLDS]
        if unknown:
            raise MSSFError(f"CLASS_NAMES: the {self.DATASET_NAME} protocol evaluates {sorted(self.IOU_THRESHOLDS)}, "
                            f"got {unknown}")
        gts = [annos_to_objects(info["annos"], scored=False) for info in self.kitti_infos]
        dets = [annos_to_objects(by_frame[f], scored=True) for f in frames]
        thresholds = {c: self.IOU_THRESHOLDS[c] for c in class_names}
        results = type(self).EVALUATE(dets, gts, list(class_names), thresholds)
        ap_dict: Dict[str, float] = {}
        lines: List[str] = []
        for region in self.REGIONS:
            lines.append(f"{self.DATASET_NAME} {region}:")
            for cname in class_names:
                r = results[region][cname]
                lines.append(f"  {cname:<11} AP3D R40 {r['AP3D_R40']:6.2f}  APBEV R40 {r['APBEV_R40']:6.2f}  "
                             f"AP3D R11 {r['AP3D_R11']:6.2f}  (GT {r['num_gt']}, detections {r['num_pred']})")
                ap_dict.update({f"{region}/{cname}_{k}": v for k, v in r.items() if k.startswith("AP")})
            m = [results[region][c]["AP3D_R40"] for c in class_names]
            ap_dict[f"{region}/mAP3D_R40"] = float(np.mean(m))
            lines.append(f"  mAP3D R40 {float(np.mean(m)):6.2f}")
        return "\n".join(lines) + "\n", ap_dict

    # ------------------------------------------------------------------ infos
    @classmethod
    def create_infos(cls, dataset_cfg, class_names: Sequence[str], data_path, save_path,
                     workers: int = 4) -> Dict[str, Path]:
        """Write ``<INFO_PREFIX>_infos_{train,val,trainval}.pkl`` (and ``_test`` when ``ImageSets/test.txt`` and
        ``testing/`` exist) into ``save_path``, as OpenPCDet's ``create_kitti_infos`` does for KITTI."""
        data_path, save_path = Path(data_path), Path(save_path)
        dataset = cls(dataset_cfg=dataset_cfg, class_names=list(class_names), root_path=data_path, training=False,
                      require_infos=False)
        infos: Dict[str, list] = {}
        for split in ("train", "val"):
            if not (data_path / "ImageSets" / f"{split}.txt").is_file():
                raise MSSFError(f"data_path: expected {data_path / 'ImageSets' / (split + '.txt')} "
                                f"({cls.DATASET_NAME}'s split lists)")
            dataset.set_split(split)
            infos[split] = dataset.get_infos(num_workers=workers, has_label=True, count_inside_pts=True)
            if not infos[split]:
                raise MSSFError(f"data_path: {data_path / 'ImageSets' / (split + '.txt')} lists no frame")
        infos["trainval"] = infos["train"] + infos["val"]
        if (data_path / "ImageSets" / "test.txt").is_file() and (data_path / "testing").is_dir():
            dataset.set_split("test")
            infos["test"] = dataset.get_infos(num_workers=workers, has_label=False, count_inside_pts=False)
        save_path.mkdir(parents=True, exist_ok=True)
        written: Dict[str, Path] = {}
        for split, value in infos.items():
            written[split] = save_path / f"{cls.INFO_PREFIX}_infos_{split}.pkl"
            with open(written[split], "wb") as f:
                pickle.dump(value, f)
            print(f"{cls.DATASET_NAME} info {split} file is saved to {written[split]} ({len(value)} frames)")
        return written


def annos_to_objects(annos: Mapping[str, Any], scored: bool) -> Objects:
    """OpenPCDet's KITTI-style annos (``dimensions`` as ``(l, h, w)``) -> the kit's :class:`Objects`."""
    g = len(annos["name"])
    dims = np.asarray(annos["dimensions"], dtype=np.float64).reshape(g, 3)
    return Objects(
        names=np.array([str(n).lower() for n in annos["name"]], dtype=object),
        bbox=np.asarray(annos["bbox"], dtype=np.float64).reshape(g, 4),
        location=np.asarray(annos["location"], dtype=np.float64).reshape(g, 3),
        dimensions=dims[:, [1, 2, 0]],  # (l, h, w) -> (h, w, l)
        rotation_y=np.asarray(annos["rotation_y"], dtype=np.float64).reshape(g),
        occluded=np.asarray(annos["occluded"], dtype=np.float64).reshape(g),
        truncated=np.asarray(annos["truncated"], dtype=np.float64).reshape(g),
        score=np.asarray(annos["score"], dtype=np.float64).reshape(g) if scored else np.zeros(g),
        ignore=np.zeros(g, dtype=bool),
    )
