"""Where a method's remaining error lives: the right half of each test photo split into regions, PSNR per region.

The regions of a test photo come from one trained model's geometry (willags' run of the scene: its Gaussians are the
same for every appearance), and every method of the scene is scored on the same regions:

- ``covisible``: the surface the pixel shows is seen by at least 3 training photos. The rendered depth of the test
  view is lifted to 3D and projected into every training camera; a camera sees the point when it lands inside its
  image, in front of it, and no nearer than that camera's own rendered depth there (an occlusion test, ``tol``
  relative). What a static model can learn best.
- ``few``: seen by 1 or 2 training photos; ``unseen``: by none (the model can only guess there).
- ``sky``: open sky and far background: the Gaussians cover less than half of the pixel (accumulation < 0.5), or
  the rendered surface lies beyond every photographed one (deeper than the 99th percentile of the depths of the SfM
  points in front of the test camera: Gaussians a model placed in the sky).
- ``outlier``: every method's squared error above ``OUTLIER_MSE`` over a 3x3 neighbourhood: content no static model
  of the scene explains (people and other transients of the test photo, found without a detector; also any static
  content that every method misses). It takes precedence over the regions above.

The error maps and the geometry are written while a run is scored (`benchmarks.child.protocol_scores` with
``$WILLAGS_BENCH_REGIONS`` set to a folder): one ``<scene>-<method>[-<tag>].npz`` per scored run, on the block grid
(``BLOCK`` x ``BLOCK`` pixels of the right half: mean squared errors average exactly over blocks). ``report`` turns
a folder of them into the table and one picture per scene:

    python -m benchmarks regions report DUMPS --out docs/regions.md --pictures docs/regions
"""

from __future__ import annotations

import argparse
import json
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.tables import md_table

REGIONS_ENV = "WILLAGS_BENCH_REGIONS"
"""Folder where each scored run writes its error maps and geometry (unset: nothing is written)."""

BLOCK = 2
"""Side of the square pixel blocks the maps are stored on."""

REGIONS = ("covisible", "few", "unseen", "sky", "outlier")
"""The regions, in the table's order."""

OUTLIER_MSE = 0.04
"""Squared error (colours in [0, 1]; ~14 dB) above which every method must err, over a 3x3 neighbourhood of blocks,
for a block to count as an outlier."""

COVISIBLE_VIEWS = 3
"""Training photos that must see a surface for it to be co-visible."""


# ------------------------------------------------------------------------------------------------ on the grid


def block_mean(x: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """[H, W, ...] -> [H // block, W // block, ...]: the mean over each block (the edge rows/columns cut)."""
    h, w = (x.shape[0] // block) * block, (x.shape[1] // block) * block
    x = x[:h, :w]
    return x.reshape(h // block, block, w // block, block, *x.shape[2:]).mean(axis=(1, 3))


def right_half(x: np.ndarray) -> np.ndarray:
    return x[:, x.shape[1] // 2 :]


def error_map(pred: np.ndarray, gt: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """Squared error of the right half, averaged over the colour channels and over blocks: [h, w] float32."""
    err = ((right_half(pred).astype(np.float64) - right_half(gt).astype(np.float64)) ** 2).mean(axis=-1)
    return block_mean(err, block).astype(np.float32)


def psnr_of(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


# ------------------------------------------------------------------------------------------------ geometry


def lift(depth: np.ndarray, c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, us, vs) -> np.ndarray:
    """World points [N, 3] of pixel positions (us, vs) (pixel units, centres at +0.5) at ``depth`` [N] (camera z),
    for a nerfstudio camera (OpenGL axes: x right, y up, looking down -z; ``c2w`` [3, 4])."""
    x = (us - cx) / fx * depth
    y = -(vs - cy) / fy * depth
    cam = np.stack([x, y, -depth], axis=-1)
    return cam @ c2w[:, :3].T + c2w[:, 3]


def project(points: np.ndarray, c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float):
    """Pixel positions (u, v) and camera depth z of world ``points`` [N, 3] in a nerfstudio camera."""
    cam = (points - c2w[:, 3]) @ c2w[:, :3]
    z = -cam[:, 2]
    safe = np.where(np.abs(z) > 1e-9, z, 1e-9)
    return fx * cam[:, 0] / safe + cx, -fy * cam[:, 1] / safe + cy, z


def visible_counts(points: np.ndarray, views: Sequence[dict[str, Any]], tol: float = 0.05) -> np.ndarray:
    """How many of ``views`` see each world point [N, 3]. A view: ``c2w`` [3, 4], ``fx fy cx cy`` at the resolution
    of its rendered ``depth`` [h, w]. Seen: in front, inside the image, not behind the view's own surface there
    (z <= depth * (1 + tol))."""
    counts = np.zeros(len(points), dtype=np.int32)
    for v in views:
        d = v["depth"]
        h, w = d.shape
        u, vv, z = project(points, v["c2w"], v["fx"], v["fy"], v["cx"], v["cy"])
        inside = (z > 0) & (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
        iu = np.clip(u.astype(np.int64), 0, w - 1)
        iv = np.clip(vv.astype(np.int64), 0, h - 1)
        counts += inside & (z <= d[iv, iu] * (1.0 + tol))
    return counts


def covisibility(
    depth: np.ndarray, c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, views, block: int = BLOCK
) -> np.ndarray:
    """For the right half of a test view with rendered ``depth`` [H, W] (full resolution): the number of training
    ``views`` that see the surface of each block's centre [h, w]."""
    H, W = depth.shape
    d = block_mean(right_half(depth), block)
    h, w = d.shape
    vs, us = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    us = W // 2 + (us + 0.5) * block
    vs = (vs + 0.5) * block
    pts = lift(d.reshape(-1), c2w, fx, fy, cx, cy, us.reshape(-1), vs.reshape(-1))
    return visible_counts(pts, views).reshape(h, w)


# ------------------------------------------------------------------------------------------------ regions


def _dilate_min(errs: np.ndarray) -> np.ndarray:
    """3x3 minimum filter of a [h, w] map (edges replicated)."""
    p = np.pad(errs, 1, mode="edge")
    h, w = errs.shape
    return np.min([p[i : i + h, j : j + w] for i in range(3) for j in range(3)], axis=0)


def far_depth(points: np.ndarray, c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, w: int, h: int):
    """The 99th percentile of the depths of the SfM ``points`` [N, 3] that project into a camera (inf: none do)."""
    u, v, z = project(points, c2w, fx, fy, cx, cy)
    z = z[(z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)]
    return float(np.percentile(z, 99)) if len(z) else float("inf")


def region_labels(
    covis: np.ndarray,
    acc: np.ndarray,
    errors: Sequence[np.ndarray] = (),
    depth: np.ndarray | None = None,
    far: float = float("inf"),
) -> np.ndarray:
    """Each block's region index (into :data:`REGIONS`) from the reference geometry (``covis`` counts, ``acc``
    accumulation, ``depth`` beyond ``far``) and, for ``outlier``, the error maps of every method of the scene."""
    lab = np.where(covis >= COVISIBLE_VIEWS, 0, np.where(covis >= 1, 1, 2)).astype(np.int8)
    lab[acc < 0.5] = 3
    if depth is not None:
        lab[depth > far] = 3
    if len(errors):
        every = np.min(np.stack(errors), axis=0)
        lab[_dilate_min(every) > OUTLIER_MSE] = 4
    return lab


def region_scores(errors: Sequence[np.ndarray], labels: Sequence[np.ndarray]) -> dict[str, dict[str, float]]:
    """PSNR and pixel share of each region, over all test images (their blocks pooled, as a PSNR over the pooled
    right halves), and ``all`` (the whole right halves)."""
    e = np.concatenate([x.reshape(-1) for x in errors]).astype(np.float64)
    lab = np.concatenate([x.reshape(-1) for x in labels])
    out = {"all": {"share": 1.0, "psnr": psnr_of(float(e.mean()))}}
    for k, name in enumerate(REGIONS):
        sel = lab == k
        out[name] = {"share": float(sel.mean()), "psnr": psnr_of(float(e[sel].mean())) if sel.any() else float("nan")}
    return out


# ------------------------------------------------------------------------------------------------ while scoring


def _camera_params(cameras, i: int) -> dict[str, Any]:
    """c2w [3, 4], fx, fy, cx, cy, w, h of camera ``i`` as numpy and Python numbers."""
    p = {k: float(getattr(cameras, k)[i]) for k in ("fx", "fy", "cx", "cy")}
    p.update(w=int(cameras.width[i]), h=int(cameras.height[i]))
    return {"c2w": cameras.camera_to_worlds[i].detach().cpu().numpy().astype(np.float64), **p}


def _render_geometry(model, cameras, i: int, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Rendered depth and accumulation [h, w] of camera ``i`` at ``scale`` of its resolution."""
    import torch

    cam = cameras[i : i + 1].to(model.device)
    if scale != 1.0:
        cam.rescale_output_resolution(scale)
    with torch.no_grad():
        out = model.get_outputs(cam)
    depth = out["depth"].detach().float().cpu().numpy()[..., 0]
    acc = out["accumulation"].detach().float().cpu().numpy()[..., 0]
    return depth, acc


def training_views(model, cameras, max_side: int = 200) -> list[dict[str, Any]]:
    """Every training camera's parameters at a reduced resolution and its rendered depth there."""
    views = []
    for i in range(len(cameras)):
        p = _camera_params(cameras, i)
        scale = min(1.0, max_side / max(p["w"], p["h"]))
        depth, _ = _render_geometry(model, cameras, i, scale)
        sy, sx = depth.shape[0] / p["h"], depth.shape[1] / p["w"]
        scaled = {"fx": p["fx"] * sx, "fy": p["fy"] * sy, "cx": p["cx"] * sx, "cy": p["cy"] * sy}
        views.append({"c2w": p["c2w"], **scaled, "depth": depth})
    return views


class RegionDump:
    """Collects a scored run's error maps (``on_prediction`` of the protocol) and, with ``geometry``, the
    co-visibility and accumulation of each test view; :meth:`save` writes them as one npz."""

    def __init__(self):
        self.errors: list[np.ndarray] = []
        self.thumbs: list[np.ndarray] = []

    def on_prediction(self, i: int, pred, gt) -> None:
        p = pred.detach().float().cpu().numpy()
        g = gt.detach().float().cpu().numpy()
        self.errors.append(error_map(p, g))
        self.thumbs.append((block_mean(right_half(np.clip(g, 0, 1))) * 255).astype(np.uint8))

    def save(self, path: Path, names: Sequence[str], trainer=None) -> Path:
        """Writes the error maps (as root mean squares in float16); with the reference run's ``trainer`` also the
        geometry of its model and the photos' right halves (the picture's), and with the scene's SfM points each test
        view's far depth."""
        arrays: dict[str, Any] = {"names": np.array(list(names)[: len(self.errors)])}
        for i, e in enumerate(self.errors):
            arrays[f"rms_{i}"] = np.sqrt(e).astype(np.float16)
        if trainer is not None:
            model, dm = trainer.pipeline.model, trainer.pipeline.datamanager
            test_cameras, points = dm.eval_dataset.cameras, dm.train_dataparser_outputs.metadata.get("points3D_xyz")
            for i, t in enumerate(self.thumbs):
                arrays[f"gt_{i}"] = t
            views = training_views(model, dm.train_dataset.cameras)
            for i in range(len(self.errors)):
                p = _camera_params(test_cameras, i)
                depth, acc = _render_geometry(model, test_cameras, i)
                arrays[f"covis_{i}"] = covisibility(depth, p["c2w"], p["fx"], p["fy"], p["cx"], p["cy"], views)
                arrays[f"acc_{i}"] = block_mean(right_half(acc)).astype(np.float32)
                arrays[f"depth_{i}"] = block_mean(right_half(depth)).astype(np.float32)
                if points is not None:
                    arrays[f"far_{i}"] = np.float64(far_depth(points.cpu().numpy().astype(np.float64), **p))
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **arrays)
        return path


# ------------------------------------------------------------------------------------------------ the report


def dump_name(filename: str) -> tuple[str, str] | None:
    """(scene, method) of a dump named <scene>-<method>[-<tag>].npz, the method one of benchmarks/methods.py's (the
    longest that fits: `willags-mcmc` is not `willags` with a tag); None for any other file."""
    from benchmarks.methods import METHODS

    if not filename.endswith(".npz"):
        return None
    stem = filename[: -len(".npz")]
    for method in sorted(METHODS, key=len, reverse=True):
        m = re.match(rf"^(?P<scene>.+?)-{re.escape(method)}(?:-(?P<tag>.+))?$", stem)
        if m:
            return m["scene"], method
    return None


REFERENCE = "willags"
"""The method whose geometry defines the regions of a scene."""


def load_dumps(folder: Path) -> dict[str, dict[str, list[dict[str, np.ndarray]]]]:
    """scene -> method -> the runs' arrays (one dict per npz; several seeds or tags each)."""
    out: dict[str, dict[str, list[dict[str, np.ndarray]]]] = {}
    for f in sorted(Path(folder).glob("*.npz")):
        named = dump_name(f.name)
        if named is None:
            continue
        scene, method = named
        with np.load(f) as z:
            out.setdefault(scene, {}).setdefault(method, []).append({k: z[k] for k in z.files})
    return out


def _images(run: dict[str, np.ndarray], key: str) -> list[np.ndarray]:
    """A dump's maps of one kind, in test-image order; "err": the squared errors (stored as their square roots)."""
    if key == "err":
        return [x.astype(np.float64) ** 2 for x in _images(run, "rms")]
    return [run[f"{key}_{i}"] for i in range(len(run["names"])) if f"{key}_{i}" in run]


def reference_run(runs: dict[str, list[dict[str, np.ndarray]]]) -> dict[str, np.ndarray] | None:
    """The run whose geometry defines a scene's regions: REFERENCE's first run with geometry, else the first run of
    any method that has it (a `willags` run scored under another name, e.g. a candidate that became the default)."""
    ordered = [*runs.get(REFERENCE, []), *(r for m, rs in sorted(runs.items()) if m != REFERENCE for r in rs)]
    return next((r for r in ordered if "covis_0" in r), None)


def scene_regions(runs: dict[str, list[dict[str, np.ndarray]]]) -> tuple[list[np.ndarray], dict[str, Any]] | None:
    """The labels of a scene's test images (the reference run's geometry, every method's errors for outliers) and
    each method's region scores (its runs averaged: PSNR of the mean of their per-region PSNRs)."""
    ref = reference_run(runs)
    if ref is None:
        return None
    covis, acc = _images(ref, "covis"), _images(ref, "acc")
    n = len(covis)
    firsts = [_images(rs[0], "err") for rs in runs.values() if rs and len(_images(rs[0], "rms")) >= n]
    labels = []
    for i in range(n):
        depth, far = ref.get(f"depth_{i}"), float(ref.get(f"far_{i}", np.inf))
        labels.append(region_labels(covis[i], acc[i], [errs[i] for errs in firsts], depth, far))
    scores: dict[str, Any] = {}
    for method, rs in runs.items():
        per_run = [region_scores(_images(r, "err")[:n], labels) for r in rs if len(_images(r, "err")) >= n]
        if not per_run:
            continue
        psnr = {k: float(np.mean([p[k]["psnr"] for p in per_run])) for k in per_run[0]}
        scores[method] = {
            k: {"share": s["share"], "psnr": psnr[k], "runs": len(per_run)} for k, s in per_run[0].items()
        }
    return labels, scores


COLOURS = np.array([[40, 160, 60], [230, 200, 40], [200, 60, 200], [70, 130, 230], [230, 40, 40]], dtype=np.float32)
"""Overlay colour of each region (green co-visible, yellow few, magenta unseen, blue sky, red outlier)."""


def region_picture(path: Path, thumbs: Sequence[np.ndarray], labels: Sequence[np.ndarray]) -> Path:
    """Each test image's right half above its regions (overlaid at half strength), side by side."""
    from PIL import Image

    cols, height = [], 160
    for t, lab in zip(thumbs, labels, strict=False):
        img = t[: lab.shape[0], : lab.shape[1]].astype(np.float32)
        im = Image.fromarray(np.concatenate([img, 0.5 * img + 0.5 * COLOURS[lab]], axis=0).astype(np.uint8))
        cols.append(im.resize((max(1, round(im.width * 2 * height / im.height)), 2 * height)))
    sheet, x = Image.new("RGB", (sum(c.width for c in cols), 2 * height), "white"), 0
    for c in cols:
        sheet.paste(c, (x, 0))
        x += c.width
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)
    return path


TABLE_ORDER = ("willags", "peer-full", "peer", "splatfacto")
"""Methods listed first in the table, in this order; the others (candidates of the default) follow by name."""


def _table_order(method: str) -> tuple[int, str]:
    return (TABLE_ORDER.index(method) if method in TABLE_ORDER else len(TABLE_ORDER), method)


def report(folder: Path, out: Path | None, pictures: Path | None, json_out: Path | None = None) -> str:
    """The markdown table of every scene's regions (a picture per scene when ``pictures`` is given; the scores as
    JSON, scene -> method -> region -> share / psnr / runs, when ``json_out`` is)."""
    rows = []
    every: dict[str, Any] = {}
    for scene, runs in sorted(load_dumps(folder).items()):
        got = scene_regions(runs)
        if got is None:
            continue
        labels, scores = got
        every[scene] = scores
        for method in sorted(scores, key=_table_order):
            s = scores[method]
            cells = [f"{s[k]['psnr']:.2f} ({100 * s[k]['share']:.0f} %)" for k in ("all", *REGIONS)]
            rows.append([scene, method, str(s["all"]["runs"]), *cells])
        if pictures is not None:
            ref = reference_run(runs)
            assert ref is not None
            region_picture(pictures / f"{scene}.png", _images(ref, "gt"), labels)
    head = ["scene", "method", "runs", *(f"{r} PSNR (share)" for r in ("all", *REGIONS))]
    text = "\n".join(md_table(head, rows)) + "\n"
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(every, indent=1))
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("report", help="the region table (and pictures) of a folder of dumps")
    r.add_argument("dumps", type=Path)
    r.add_argument("--out", type=Path, default=None)
    r.add_argument("--pictures", type=Path, default=None)
    r.add_argument("--json", type=Path, default=None, help="the scores as JSON (a record of the table)")
    args = ap.parse_args(argv)
    print(report(args.dumps, args.out, args.pictures, args.json), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
