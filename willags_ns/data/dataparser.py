"""`willags-data`: one nerfstudio dataparser for the embedded synthetic scene, transforms.json scenes and COLMAP scenes.

What `data` points at decides the branch:

- nothing (`ns-train willags` without `--data`; `None`, `Path()` or `"."`): the embedded synthetic in-the-wild scene
  (`willags_ns.data.synthetic`), generated once into the cache and then read as a transforms.json scene;
- a directory with `transforms.json` (or the json file itself): nerfstudio's own `nerfstudio-data` parser, explicit
  `train_filenames` / `val_filenames` / `test_filenames` respected, `ply_file_path` loaded as seed points;
- a directory with a COLMAP model (`colmap/sparse/0`, `sparse/0`, `sparse` or `dense/sparse`): nerfstudio's
  `colmap` parser with the model's 3D points as seed points.

In both real-data branches a NeRF-W / Phototourism split file (`*.tsv` with columns `filename`, `id`, `split`,
`dataset`) in the directory gives the train/test split. Evaluation-only files found next to the images
(`masks_gt/`, `gt_clean/`) are exposed in `DataparserOutputs.metadata` ("masks_gt_dir", "gt_clean_dir"); training
never reads them. Input problems raise `WillagsDataError` naming the file or field, before nerfstudio's parsers run.
"""

import csv
import dataclasses
import functools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from nerfstudio.plugins.registry_dataparser import DataParserSpecification
from nerfstudio.process_data.colmap_utils import parse_colmap_camera_params
from nerfstudio.utils.rich_utils import CONSOLE

from willags_ns.data.colmap import (
    COLMAP_MODEL_DIRS,
    ColmapModelError,
    colmap_images_path,
    find_colmap_model,
    read_colmap_model,
)
from willags_ns.data.sfm_tracks import (
    SFM_DEPTHS_KEY,
    SFM_OBSERVATIONS_KEY,
    read_observations,
    train_observation_depths,
    train_observations,
)
from willags_ns.data.synthetic import SyntheticSceneConfig, ensure_default_scene

EVAL_ONLY_DIRS = {"masks_gt_dir": "masks_gt", "gt_clean_dir": "gt_clean"}
"""metadata key -> directory name of the evaluation-only files exposed when present."""

SPLITS = ("train", "val", "test")


class WillagsDataError(ValueError):
    """Bad input data; the message names the file or field at fault."""


class InputWarning(str):
    """A warning about input that trains but deserves a look: its text, with the kind of problem it reports (the
    same for every warning of one check: how a summary of many counts them) and the photo it names."""

    kind: str
    photo: str

    def __new__(cls, text: str, kind: str, photo: str = "") -> "InputWarning":
        self = super().__new__(cls, text)
        self.kind, self.photo = kind, photo
        return self


# --------------------------------------------------------------------------------------------------------------------
# readers (pure functions)

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read the vertex positions [N, 3] float32 and colours [N, 3] uint8 of a point-cloud PLY (ascii or binary).

    Why not open3d (what nerfstudio uses): it is slow to import and, on machines without libusb, fails to import at
    all. Colours stored as floats are taken to be in [0, 1]; a cloud without colours gets grey.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise WillagsDataError(f"cannot read point cloud {path}: {e}") from None
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise WillagsDataError(f"{path} is not a PLY file (no 'ply' magic or no 'end_header')")
    body_start = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements = None, []  # elements: [name, count, [(prop, dtype)]]
    for line in header:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "ply"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property":
            if not elements:
                raise WillagsDataError(f"{path}: property before any element in the PLY header")
            if words[1] == "list":
                elements[-1][2].append((words[-1], None))
            elif words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise WillagsDataError(f"{path}: unknown PLY property type {words[1]!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise WillagsDataError(f"{path}: unsupported PLY format {fmt!r}")
    if not elements or elements[0][0] != "vertex":
        raise WillagsDataError(f"{path}: the first PLY element must be 'vertex'")
    _, count, props = elements[0]
    names = [p for p, _ in props]
    if any(t is None for _, t in props):
        raise WillagsDataError(f"{path}: list properties in the vertex element are not supported")
    if not {"x", "y", "z"} <= set(names):
        raise WillagsDataError(f"{path}: the vertex element lacks x, y or z")
    if fmt == "ascii":
        lines = raw[body_start:].decode("ascii").splitlines()[:count]
        try:
            table = np.array([[float(v) for v in ln.split()[: len(names)]] for ln in lines], dtype=np.float64)
        except ValueError as e:
            raise WillagsDataError(f"{path}: malformed ascii vertex data ({e})") from None
        if table.shape != (count, len(names)):
            raise WillagsDataError(f"{path}: expected {count} vertices with {len(names)} values, got {table.shape}")
        cols = {n: table[:, i] for i, n in enumerate(names)}
        kinds = {n: np.dtype(t).kind for n, t in props}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        if len(raw) - body_start < count * dtype.itemsize:
            raise WillagsDataError(f"{path}: truncated (needs {count} vertices of {dtype.itemsize} bytes)")
        arr = np.frombuffer(raw, dtype=dtype, count=count, offset=body_start)
        cols = {n: arr[n] for n in names}
        kinds = {n: dtype[n].kind for n in names}
    xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=-1).astype(np.float32)
    cnames = next((c for c in (("red", "green", "blue"), ("r", "g", "b")) if set(c) <= set(names)), None)
    if cnames is None:
        rgb = np.full((count, 3), 128, dtype=np.uint8)
    else:
        rgb = np.stack([np.asarray(cols[c], dtype=np.float64) for c in cnames], axis=-1)
        if kinds[cnames[0]] == "f":
            rgb = rgb * 255.0
        rgb = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
    return xyz, rgb


def read_split_tsv(path: Path) -> dict[str, str]:
    """Read a NeRF-W / Phototourism split file: tab-separated with a header holding at least `filename` and `split`
    (usually `filename id split dataset`). Returns {filename: "train" | "test"}; rows with an empty id ("nan": images
    the SfM did not register) are kept, since the COLMAP model decides which images exist."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise WillagsDataError(f"cannot read split file {path}: {e}") from None
    rows = list(csv.reader(text.splitlines(), delimiter="\t"))
    if not rows:
        raise WillagsDataError(f"split file {path} is empty")
    header = [h.strip().lower() for h in rows[0]]
    for col in ("filename", "split"):
        if col not in header:
            raise WillagsDataError(
                f"split file {path}: header {rows[0]} has no '{col}' column (expected tab-separated "
                "'filename id split dataset')"
            )
    fi, si = header.index("filename"), header.index("split")
    table: dict[str, str] = {}
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) <= max(fi, si):
            raise WillagsDataError(f"split file {path}, line {lineno}: expected {len(header)} tab-separated columns")
        name, split = row[fi].strip(), row[si].strip().lower()
        if not name:
            raise WillagsDataError(f"split file {path}, line {lineno}: empty filename")
        if split not in ("train", "test"):
            raise WillagsDataError(f"split file {path}, line {lineno}: split {row[si]!r} is neither 'train' nor 'test'")
        if table.get(name, split) != split:
            raise WillagsDataError(f"split file {path}, line {lineno}: {name} is listed in both splits")
        table[name] = split
    if not table:
        raise WillagsDataError(f"split file {path} lists no images")
    return table


def _tsv_split_of(image: Path, table: dict[str, str]) -> str | None:
    """Split of an image path: the tsv names files relative to the images folder (usually just the file name)."""
    parts = image.parts
    for k in range(1, len(parts) + 1):
        split = table.get("/".join(parts[-k:]))
        if split is not None:
            return split
    return None


# --------------------------------------------------------------------------------------------------------------------
# nerfstudio's transforms.json parser, minus open3d


class _NerfstudioParser(Nerfstudio):
    """nerfstudio's transforms.json parser reading `ply_file_path` with `read_ply_points` instead of open3d."""

    def _load_3D_points(self, ply_file_path: Path, transform_matrix: torch.Tensor, scale_factor: float):
        xyz, rgb = read_ply_points(ply_file_path)
        if len(xyz) == 0:
            return None
        points = torch.from_numpy(xyz)
        # same transform as nerfstudio: the ply is in the coordinates of transforms.json's poses
        points = torch.cat([points, torch.ones_like(points[:, :1])], -1) @ transform_matrix.T
        return {"points3D_xyz": points * scale_factor, "points3D_rgb": torch.from_numpy(rgb)}


# --------------------------------------------------------------------------------------------------------------------
# the dataparser


@dataclass
class WillagsDataParserConfig(DataParserConfig):
    """willags-data: the embedded synthetic scene (no --data), a transforms.json scene or a COLMAP scene."""

    _target: type = field(default_factory=lambda: WillagsDataParser)
    """target class to instantiate"""
    data: Path | None = None  # pyright: ignore[reportIncompatibleVariableOverride]
    """Scene directory (transforms.json scene, or COLMAP scene with colmap/sparse/0, sparse/0, sparse or dense/sparse,
    optionally with a NeRF-W *.tsv split) or a transforms json file. None, '' or '.': the embedded synthetic scene
    (the parser then sets data to the generated scene's directory, for `datamanager.get_datapath()`)."""
    synthetic: SyntheticSceneConfig = field(default_factory=SyntheticSceneConfig)
    """Parameters of the embedded synthetic scene (used only when data is not given)."""
    cache_dir: Path | None = None
    """Where synthetic scenes are generated; default $WILLAGS_CACHE/scenes or ~/.cache/willags/scenes."""
    split_tsv: Path | None = None
    """NeRF-W / Phototourism split file (relative to data or absolute). Default: the one *.tsv in data, if any."""
    colmap_path: Path | None = None
    """COLMAP model directory relative to data. Default: the first of colmap/sparse/0, sparse/0, sparse, dense/sparse."""
    images_path: Path = Path("images")
    """COLMAP scenes: image directory relative to data (dense/images is tried when this is absent)."""
    load_3D_points: bool = True
    """Seed the Gaussians with the scene's points (transforms.json's ply_file_path, or the COLMAP points3D)."""
    downscale_factor: int | None = None
    """Image downscale factor N: images read at 1/N of their size (COLMAP scenes: from images_N/, written from images/
    when it is missing). None: nerfstudio's rule (largest side <= 1600 px, using existing images_N folders)."""
    scale_factor: float = 1.0
    """How much to scale the camera origins by (after auto-scaling)."""
    scene_scale: float = 1.0
    """How much to scale the region of interest (scene box) by."""
    orientation_method: Literal["pca", "up", "vertical", "none"] = "up"
    """How nerfstudio orients the poses."""
    center_method: Literal["poses", "focus", "none"] = "poses"
    """How nerfstudio centres the poses."""
    auto_scale_poses: bool = True
    """Scale the poses to fit in the +/- 1 box."""
    eval_mode: Literal["fraction", "filename", "interval", "all"] = "interval"
    """Train/eval split when the scene gives none (no *_filenames in transforms.json, no tsv, no *_list.txt)."""
    eval_interval: int = 8
    """eval_mode=interval: every eval_interval-th image (sorted by name / COLMAP id) is held out."""
    train_split_fraction: float = 0.9
    """eval_mode=fraction: fraction of the images used for training."""


class WillagsDataParser(DataParser):
    """Resolves `config.data` once (see the module docstring), then delegates to nerfstudio's parser for it."""

    config: WillagsDataParserConfig  # pyright: ignore[reportIncompatibleVariableOverride]

    def __init__(self, config: WillagsDataParserConfig):
        super().__init__(config)
        self._delegate: DataParser | None = None
        self._tsv: dict[str, str] | None = None
        self._root: Path | None = None
        self._colmap_model: Path | None = None  # the COLMAP branch's model: its tracks feed the mask's safeguard

    # ---- resolution

    def _resolve(self) -> DataParser:
        if self._delegate is not None:
            return self._delegate
        self.config.downscale_factor = checked_downscale_factor(self.config.downscale_factor)
        data = self.config.data
        if data is None or Path(data) == Path():
            scene_dir = ensure_default_scene(self.config.synthetic, self.config.cache_dir)
            CONSOLE.log(f"willags-data: embedded synthetic in-the-wild scene at {scene_dir}")
            # Point the (shared) config at the generated scene, so `datamanager.get_datapath()` (ns-viewer, exports)
            # names a real directory; the saved config.yml keeps data unset and regenerates/reuses the scene.
            self.config.data = scene_dir
            self._delegate = self._transforms_parser(scene_dir, scene_dir / "transforms.json")
            return self._delegate
        data = Path(data).expanduser()
        if not data.exists():
            raise WillagsDataError(f"data path {data} does not exist")
        if data.is_file():
            if data.suffix != ".json":
                raise WillagsDataError(f"data path {data} is a file but not a transforms .json file")
            self._delegate = self._transforms_parser(data.parent, data)
        elif (data / "transforms.json").is_file():
            self._delegate = self._transforms_parser(data, data / "transforms.json")
        else:
            model = find_colmap_model(data, self.config.colmap_path)
            if model is None:
                looked = [str(self.config.colmap_path)] if self.config.colmap_path else list(COLMAP_MODEL_DIRS)
                raise WillagsDataError(
                    f"{data} has neither transforms.json nor a COLMAP model (cameras + images .bin/.txt) in "
                    f"{', '.join(looked)}"
                )
            self._delegate = self._colmap_parser(data, model)
        return self._delegate

    def image_downscale_factor(self) -> int:
        """The factor N at which this parser reads the scene's images (1/N of their width and height): the configured
        one, else the one resolved for the scene as training resolves it (COLMAP: MAX_AUTO_SIDE; transforms.json:
        nerfstudio's own rule, known once the scene is parsed)."""
        delegate = self._resolve()
        own = getattr(delegate.config, "downscale_factor", None)
        if own:
            return int(own)
        if isinstance(delegate, Nerfstudio):
            if getattr(delegate, "downscale_factor", None) is None:
                delegate.get_dataparser_outputs("train")
            return int(delegate.downscale_factor or 1)
        return 1

    def _find_tsv(self, root: Path) -> Path | None:
        if self.config.split_tsv is not None:
            tsv = self.config.split_tsv if self.config.split_tsv.is_absolute() else root / self.config.split_tsv
            if not tsv.is_file():
                raise WillagsDataError(f"split_tsv {tsv} does not exist")
            return tsv
        found = sorted(root.glob("*.tsv"))
        if len(found) > 1:
            raise WillagsDataError(
                f"{root} holds several split files ({', '.join(p.name for p in found)}): choose one with --split-tsv"
            )
        return found[0] if found else None

    def _split_kwargs(self) -> dict[str, Any]:
        # With a tsv, nerfstudio's parser is asked for every image (fraction 1.0 keeps all in "train", with no
        # warning) and the tsv then picks each split: the poses are oriented and scaled over all images, as usual.
        if self._tsv is not None:
            return {"eval_mode": "fraction", "train_split_fraction": 1.0}
        return {
            "eval_mode": self.config.eval_mode,
            "eval_interval": self.config.eval_interval,
            "train_split_fraction": self.config.train_split_fraction,
        }

    def _common_kwargs(self) -> dict[str, Any]:
        c = self.config
        return {
            "downscale_factor": c.downscale_factor,
            "scale_factor": c.scale_factor,
            "scene_scale": c.scene_scale,
            "orientation_method": c.orientation_method,
            "center_method": c.center_method,
            "auto_scale_poses": c.auto_scale_poses,
        }

    def _transforms_parser(self, root: Path, json_path: Path) -> DataParser:
        factor = self.config.downscale_factor
        small = root / f"images_{factor}"
        if factor is not None and factor > 1 and not small.is_dir():  # nerfstudio reads images_N/<name>
            frames = check_transforms(json_path)["frames"]
            write_downscaled_images([root / f["file_path"] for f in frames], factor, small)
        meta = check_transforms(json_path, self.config.downscale_factor)
        self._root = root
        tsv = self._find_tsv(root)
        has_split_keys = any(f"{s}_filenames" in meta for s in SPLITS)
        if tsv is not None and has_split_keys:
            if self.config.split_tsv is not None:
                raise WillagsDataError(
                    f"{json_path} has explicit *_filenames splits and split_tsv {tsv} was given: keep only one"
                )
            CONSOLE.log(f"willags-data: {json_path.name} lists its splits; ignoring {tsv.name}")
            tsv = None
        if tsv is not None:
            self._tsv = read_split_tsv(tsv)
            CONSOLE.log(f"willags-data: train/test split from {tsv}")
        load_points = self.config.load_3D_points and "ply_file_path" in meta
        if self.config.load_3D_points and not load_points:
            # (also keeps nerfstudio from asking interactively to convert a colmap/ folder into a ply)
            CONSOLE.log(f"willags-data: {json_path} has no ply_file_path; no seed points (random initialisation)")
        if load_points and not (root / meta["ply_file_path"]).is_file():
            raise WillagsDataError(f"{json_path}: ply_file_path {meta['ply_file_path']!r} does not exist")
        cfg = NerfstudioDataParserConfig(
            data=json_path if json_path.name != "transforms.json" else root,
            load_3D_points=load_points,
            **self._common_kwargs(),
            **self._split_kwargs(),
        )
        return _NerfstudioParser(cfg)

    def _colmap_parser(self, root: Path, model: Path) -> DataParser:
        self._root = root
        self._colmap_model = model
        images_path = colmap_images_path(root, self.config.images_path)
        images_dir = root / images_path
        factor = self.config.downscale_factor
        if factor is None and images_dir.is_dir():  # nerfstudio's rule, without its interactive question
            factor = auto_downscale_factor(images_dir)
            if factor > 1:
                CONSOLE.log(f"willags-data: images read at 1/{factor} size (largest side <= {MAX_AUTO_SIDE} px)")
        if factor is not None and factor > 1:
            full_dir, images_dir = images_dir, images_dir.parent / f"{images_dir.name}_{factor}"
            if not images_dir.is_dir() and full_dir.is_dir():
                check_colmap(root, model, full_dir, self.config.load_3D_points)
                write_downscaled_images(sorted(p for p in full_dir.iterdir() if p.is_file()), factor, images_dir)
        check_colmap(root, model, images_dir, self.config.load_3D_points)
        tsv = self._find_tsv(root)
        if tsv is not None:
            lists = [p.name for p in root.glob("*_list.txt")]
            if lists:
                raise WillagsDataError(f"{root} has both a tsv split ({tsv.name}) and {', '.join(lists)}: keep one")
            self._tsv = read_split_tsv(tsv)
            CONSOLE.log(f"willags-data: train/test split from {tsv}")
        cfg = ColmapDataParserConfig(
            data=root,
            colmap_path=model.relative_to(root),
            images_path=images_path,
            load_3D_points=self.config.load_3D_points,
            **{**self._common_kwargs(), "downscale_factor": factor},
            **self._split_kwargs(),
        )
        return cfg.setup()

    # ---- outputs

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs: Any) -> DataparserOutputs:
        if split not in SPLITS:
            raise WillagsDataError(f"unknown split {split!r}; expected one of {SPLITS}")
        delegate = self._resolve()
        if self._tsv is None:
            outputs = delegate.get_dataparser_outputs(split)
        else:
            outputs = _select_tsv_split(delegate.get_dataparser_outputs("train"), self._tsv, split)
        assert self._root is not None
        if split == "train" and len(outputs.image_filenames) == 0:
            raise WillagsDataError(
                f"{self._root}: the training split has no images: check train_filenames / the *.tsv split / "
                "the dataparser's eval-mode (`ns-train ... willags-data --eval-mode all` trains on every image)"
            )
        metadata = dict(outputs.metadata)
        metadata["data_dir"] = self._root
        for key, name in EVAL_ONLY_DIRS.items():
            if (self._root / name).is_dir():
                metadata[key] = self._root / name
        if split == "train" and self._colmap_model is not None:
            names = [Path(p).name for p in outputs.image_filenames]
            try:
                metadata[SFM_OBSERVATIONS_KEY] = train_observations(read_observations(self._colmap_model), names)
            except Exception as e:  # the mask then runs without its safeguard; training itself needs no tracks
                CONSOLE.log(f"willags-data: SfM observations of {self._colmap_model} unreadable ({e!r}): no safeguard")
            if SFM_OBSERVATIONS_KEY in metadata:  # read when the SfM depth loss asks (the points file: its cost)
                scale = float(outputs.dataparser_scale)
                metadata[SFM_DEPTHS_KEY] = functools.partial(train_observation_depths, self._colmap_model, names, scale)
        return dataclasses.replace(outputs, metadata=metadata)


def _select_tsv_split(outputs: DataparserOutputs, table: dict[str, str], split: str) -> DataparserOutputs:
    """The images of `outputs` (all the scene's images) that the tsv puts in `split` (val and test: 'test')."""
    want = "train" if split == "train" else "test"
    splits = [_tsv_split_of(p, table) for p in outputs.image_filenames]
    idx = [i for i, s in enumerate(splits) if s == want]
    if not idx:
        raise WillagsDataError(f"the tsv split lists no '{want}' image that is in the scene")
    missing = sum(s is None for s in splits)
    if missing and split == "train":
        CONSOLE.log(f"willags-data: {missing} image(s) of the scene are not in the tsv and are left out of both splits")
    index = torch.tensor(idx, dtype=torch.long)
    metadata = dict(outputs.metadata)
    depth = metadata.get("depth_filenames")
    if depth is not None:
        metadata["depth_filenames"] = [depth[i] for i in idx]
    masks = outputs.mask_filenames
    return dataclasses.replace(
        outputs,
        image_filenames=[outputs.image_filenames[i] for i in idx],
        cameras=outputs.cameras[index],
        mask_filenames=[masks[i] for i in idx] if masks is not None else None,
        metadata=metadata,
    )


MAX_AUTO_SIDE = 1600
"""Without a downscale factor, images are read at 1/2**k of their size, the smallest k that brings the first image's
largest side to at most this (nerfstudio's rule for COLMAP scenes)."""


def auto_downscale_factor(images_dir: Path) -> int:
    """nerfstudio's automatic downscale factor of a COLMAP scene's images (see MAX_AUTO_SIDE): the first image by
    name decides; 1 when there is none or it cannot be read (the checks name it)."""
    from PIL import Image

    first = next(iter(sorted(p for p in images_dir.iterdir() if p.is_file())), None)
    if first is None:
        return 1
    try:
        with Image.open(first) as im:
            side = max(im.size)
    except OSError:
        return 1
    return downscale_for_side(side)


def downscale_for_side(side: int) -> int:
    """The automatic downscale factor of a photo whose largest side is `side` px: the smallest power of 2 that brings
    it to at most MAX_AUTO_SIDE."""
    factor = 1
    while side / factor > MAX_AUTO_SIDE:
        factor *= 2
    return factor


def checked_downscale_factor(factor: float | None) -> int | None:
    """The image downscale factor as nerfstudio's parsers need it: a whole number >= 1 (``willags-render dataset
    --downscale-factor 2`` passes 2.0), or None. Anything else is a WillagsDataError naming the value."""
    if factor is None:
        return None
    try:
        value = float(factor)
    except (TypeError, ValueError):
        value = float("nan")
    if not (value >= 1 and value.is_integer()):
        raise WillagsDataError(
            f"downscale_factor {factor!r}: images are read at 1/factor of their size, so it must be a whole number "
            ">= 1 (2: half the width and height)"
        )
    return int(value)


def write_downscaled_images(files: list[Path], factor: int, dst: Path) -> None:
    """Each of ``files`` at floor(w / factor) x floor(h / factor) (nerfstudio's rounding of the cameras), with PIL's
    area filter, into ``dst`` under its own name: the ``images_N`` folder nerfstudio's parsers read for
    ``downscale_factor N``. Written to a hidden sibling and renamed when complete; a folder that cannot be written is
    one line."""
    import os
    import shutil

    from willags_ns.data.images import save_downscaled
    from willags_ns.files import partial_path

    tmp = partial_path(dst)
    CONSOLE.log(f"willags-data: writing {dst} ({len(files)} images at 1/{factor} size) for downscale_factor {factor}")
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for f in files:
            try:
                save_downscaled(f, factor, tmp / f.name)
            except OSError as e:
                if isinstance(e, PermissionError) or e.errno is not None:
                    raise
                shutil.copy2(f, tmp / f.name)  # not an image (a stray file): kept as it is, as the checks see it
        os.rename(tmp, dst)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise WillagsDataError(
            f"cannot write the downscaled images {dst} ({e.strerror or e}): make {dst.parent} writable, or run "
            f"willags-process with --num-downscales to write them"
        ) from None


def check_transforms(json_path: Path, downscale_factor: int | None = None) -> dict[str, Any]:
    """Validate a transforms.json enough that nerfstudio's parser cannot fail deep inside. Returns its content.
    With an explicit downscale factor N > 1 the images are looked for where nerfstudio reads them: images_N/<name>."""
    try:
        meta = json.loads(json_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as e:
        raise WillagsDataError(f"cannot read {json_path}: {e}") from None
    except json.JSONDecodeError as e:
        raise WillagsDataError(f"{json_path} is not valid JSON: {e}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise WillagsDataError(f"{json_path}: no 'frames' list (or it is empty)")
    root = json_path.parent
    names, centres = set(), []
    for i, frame in enumerate(meta["frames"]):
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise WillagsDataError(f"{json_path}: frames[{i}] has no 'file_path'")
        try:
            pose = np.asarray(frame.get("transform_matrix"), dtype=np.float64)
        except (TypeError, ValueError):
            pose = np.zeros(0)
        if pose.shape not in ((4, 4), (3, 4)) or not np.isfinite(pose).all():
            raise WillagsDataError(
                f"{json_path}: frames[{i}] ({frame['file_path']}) needs a finite 4x4 transform_matrix "
                "(it has NaN / Inf or the wrong shape): fix or remove that frame"
            )
        _check_rotation(pose[:3, :3], f"{json_path}: frames[{i}] ({frame['file_path']})")
        for key in ("fl_x", "fl_y", "w", "h"):
            value = frame.get(key, meta.get(key))
            try:
                ok = value is None or (np.isfinite(float(value)) and float(value) > 0)
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise WillagsDataError(
                    f"{json_path}: frames[{i}] ({frame['file_path']}) has {key} = {value!r}; it must be a number > 0: "
                    f"fix '{key}' (in the frame or at the top level of {json_path.name})"
                )
        for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
            if key not in meta and key not in frame:
                raise WillagsDataError(
                    f"{json_path}: '{key}' is neither global nor in frames[{i}] ({frame['file_path']})"
                )
        image = root / frame["file_path"]
        if downscale_factor is not None and downscale_factor > 1:
            image = root / f"images_{downscale_factor}" / image.name
        if not image.is_file():
            raise WillagsDataError(f"{json_path}: frames[{i}] image {image} does not exist")
        names.add(Path(frame["file_path"]).as_posix())
        centres.append(pose[:3, 3])
    if np.ptp(np.stack(centres), axis=0).max() == 0:  # nerfstudio's auto-scale would divide by zero
        raise WillagsDataError(f"{json_path}: all {len(centres)} cameras sit at the same position; need a baseline")
    for s in SPLITS:
        listed = meta.get(f"{s}_filenames")
        if listed is None:
            continue
        unknown = [f for f in listed if Path(f).as_posix() not in names]
        if unknown:
            raise WillagsDataError(f"{json_path}: {s}_filenames lists files with no frame: {unknown[:5]}")
    return meta


ROTATION_TOL = 1e-3
"""Largest |R^T R - I| entry and |det R - 1| accepted for a pose's rotation block (see willags_ns.engine.checks)."""


def _check_rotation(R: np.ndarray, where: str) -> None:
    """Raise WillagsDataError unless R (3x3) is a proper rotation: R^T R = I and det R = +1 (within ROTATION_TOL)."""
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
        raise WillagsDataError(
            f"{where}: the 3x3 block of transform_matrix is not a rotation (max |R^T R - I| = {err:.3g}, "
            f"det = {det:.4g}; want 0 and +1): remove any scale, shear or mirroring (scale belongs in the translation)"
        )


def check_colmap(root: Path, model: Path, images_dir: Path, need_points: bool) -> None:
    """Validate a COLMAP scene: image folder, readable model, one camera type, image files, points."""
    if not images_dir.is_dir():
        raise WillagsDataError(f"COLMAP scene {root}: image directory {images_dir} does not exist")
    try:
        colmap = read_colmap_model(model)
    except ColmapModelError as e:
        raise WillagsDataError(str(e)) from None
    cameras, images = colmap.cameras, colmap.images
    if not images:
        raise WillagsDataError(f"the COLMAP model in {model} has no registered images")
    try:
        models = {parse_colmap_camera_params(cam)["camera_model"] for cam in cameras.values()}
    except Exception as e:
        raise WillagsDataError(f"{model}: unsupported COLMAP camera model ({e})") from None
    if len(models) > 1:
        raise WillagsDataError(f"{model}: cameras of several types {sorted(models)}; nerfstudio supports one")
    missing = [im.name for im in images.values() if not (images_dir / im.name).is_file()]
    if missing:
        raise WillagsDataError(
            f"{len(missing)} image(s) of the COLMAP model are missing in {images_dir}: {missing[:5]}"
        )
    if need_points and not ((model / "points3D.bin").is_file() or (model / "points3D.txt").is_file()):
        raise WillagsDataError(f"{model} has no points3D.bin/.txt (pass --load-3D-points False to start from random)")


SCENE_RECORD = "scene_cameras.pt"
"""Beside a run's config.yml: its scene without the photos (cameras, image names, scene box, whether it had SfM
keypoints), written when training starts, so that commands that need only the trained model (willags-export,
renders of trajectories) work when the photos have moved."""


def scene_record(train: DataparserOutputs, test: DataparserOutputs | None, has_keypoints: bool) -> dict[str, Any]:
    """What :class:`SavedSceneDataParser` rebuilds a scene from: tensors, strings and flags only (loads with
    ``torch.load(weights_only=True)``)."""

    def split(outputs: DataparserOutputs) -> dict[str, Any]:
        c = outputs.cameras
        out = {
            "names": [str(p) for p in outputs.image_filenames],
            "camera_to_worlds": c.camera_to_worlds.detach().cpu(),
            "fx": c.fx.cpu(),
            "fy": c.fy.cpu(),
            "cx": c.cx.cpu(),
            "cy": c.cy.cpu(),
            "width": c.width.cpu(),
            "height": c.height.cpu(),
            "camera_type": c.camera_type.cpu(),
        }
        if c.distortion_params is not None:
            out["distortion_params"] = c.distortion_params.cpu()
        return out

    return {
        "train": split(train),
        "test": split(test) if test is not None else None,
        "scene_box": train.scene_box.aabb.cpu(),
        "dataparser_transform": train.dataparser_transform.cpu(),
        "dataparser_scale": float(train.dataparser_scale),
        "has_keypoints": bool(has_keypoints),
    }


@dataclass
class SavedSceneDataParserConfig(DataParserConfig):
    """A run's scene rebuilt from its SCENE_RECORD, without the photos: for loading a trained model whose scene
    folder is gone (willags-export, trajectory renders). Images are never read through it."""

    _target: type = field(default_factory=lambda: SavedSceneDataParser)
    record: Path = Path(SCENE_RECORD)
    """The run's scene_cameras.pt."""
    data: Path | None = None  # pyright: ignore[reportIncompatibleVariableOverride]
    """Where the photos were (kept for messages; it does not exist)."""


class SavedSceneDataParser(DataParser):
    config: SavedSceneDataParserConfig  # pyright: ignore[reportIncompatibleVariableOverride]

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs: Any) -> DataparserOutputs:
        from nerfstudio.cameras.cameras import Cameras
        from nerfstudio.data.scene_box import SceneBox

        rec = torch.load(self.config.record, map_location="cpu")
        part = rec["train"] if split == "train" or rec.get("test") is None else rec["test"]
        cams = Cameras(
            camera_to_worlds=part["camera_to_worlds"],
            fx=part["fx"],
            fy=part["fy"],
            cx=part["cx"],
            cy=part["cy"],
            width=part["width"],
            height=part["height"],
            camera_type=part["camera_type"],
            distortion_params=part.get("distortion_params"),
        )
        metadata: dict[str, Any] = {}
        if rec["has_keypoints"] and split == "train":  # the model's sky follows whether there were keypoints
            metadata[SFM_OBSERVATIONS_KEY] = [np.zeros((0, 3), np.float32) for _ in part["names"]]
        return DataparserOutputs(
            image_filenames=[Path(n) for n in part["names"]],
            cameras=cams,
            scene_box=SceneBox(aabb=rec["scene_box"]),
            dataparser_transform=rec["dataparser_transform"],
            dataparser_scale=rec["dataparser_scale"],
            metadata=metadata,
        )


willags_dataparser = DataParserSpecification(
    config=WillagsDataParserConfig(),
    description="WilLaGS data: the embedded synthetic in-the-wild scene (no --data), a transforms.json scene or a "
    "COLMAP scene (NeRF-W .tsv split honoured); eval-only masks_gt/ and gt_clean/ exposed in metadata",
)
