"""What the NeRF-W protocol allows on a scene with `gt_clean/` test images (fox-wild, fox-appearance-only): a ceiling.

The protocol fits an appearance on the LEFT half of each test image and scores the RIGHT half. This script takes
the *clean* test image as a perfect reconstruction (no geometry error at all) and asks how well a given family of
colour transforms, fitted on the left half, predicts the right half of the real (appearance-changed) test image:

    raw            : no appearance model (the clean image as is)
    affine3        : 3x3 colour matrix + bias (any global linear colour change: exposure, white balance)
    loglin         : per channel  log I = g log C + o   (exposure, white balance and gamma: global ISP changes)
    loglin+xy      : loglin + a linear-in-(x, y) log term (a screen-space gradient), extrapolated to the right
    loglin+xy full : the same fitted on the WHOLE image (what the right half would score if the left half
                     determined the transform; an upper bound no protocol-respecting method reaches)

Any 3D appearance model is one such family (it cannot see the right half either), so the best of the left-half
rows bounds what a method can score under the protocol even with perfect geometry. fox-wild's generator adds a
screen-space gradient and an elliptical shadow per image (appearance.json): they are independent random draws
per image, so the left half says nothing about where the shadow falls on the right.

    python -m benchmarks ceiling --scene ../shared/data/fox-wild

Prints a table (per image and mean PSNR of the right half).
"""

import argparse
from pathlib import Path

import numpy as np
from PIL import Image


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(((a - b) ** 2).mean()))


def fit_predict(clean: np.ndarray, real: np.ndarray, kind: str, fit_cols: slice, score_cols: slice) -> np.ndarray:
    """Fit `kind` mapping clean -> real on `fit_cols`; return its prediction on `score_cols` ([H, w, 3] in [0, 1])."""
    h, w, _ = clean.shape
    if kind == "raw":
        return clean[:, score_cols]
    if kind == "affine3":
        x = np.concatenate([clean[:, fit_cols].reshape(-1, 3), np.ones((h * clean[:, fit_cols].shape[1], 1))], 1)
        a = np.linalg.lstsq(x, real[:, fit_cols].reshape(-1, 3), rcond=None)[0]
        xs = np.concatenate([clean[:, score_cols].reshape(-1, 3), np.ones((h * clean[:, score_cols].shape[1], 1))], 1)
        return np.clip(xs @ a, 0, 1).reshape(h, -1, 3)
    yy, xx = np.mgrid[0:h, 0:w]
    xx, yy = xx / w, yy / h
    out = np.zeros_like(clean[:, score_cols])
    for c in range(3):
        lc, lr = np.log(clean[..., c].clip(1e-3)), np.log(real[..., c].clip(1e-3))
        feats = [lc, np.ones_like(lc)] + ([xx, yy] if kind.startswith("loglin+xy") else [])
        f = np.stack([v[:, fit_cols].ravel() for v in feats], 1)
        ok = (clean[:, fit_cols, c].ravel() > 0.02) & (real[:, fit_cols, c].ravel() > 0.02)  # log of ~0 is noise
        wts = np.linalg.lstsq(f[ok], lr[:, fit_cols].ravel()[ok], rcond=None)[0]
        fs = np.stack([v[:, score_cols].ravel() for v in feats], 1)
        out[..., c] = np.exp(fs @ wts).reshape(h, -1)
    return np.clip(out, 0, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, default=Path("../shared/data/fox-wild"))
    args = ap.parse_args()
    clean_dir = args.scene / "gt_clean"
    if not clean_dir.is_dir():
        raise SystemExit(f"{clean_dir}: not found (this analysis needs a scene with clean test images)")
    names = sorted(p.name for p in clean_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    kinds = ["raw", "affine3", "loglin", "loglin+xy", "loglin+xy full"]
    table = {k: [] for k in kinds}
    for n in names:
        real = np.asarray(Image.open(args.scene / "images" / n).convert("RGB"), dtype=np.float64) / 255
        clean = np.asarray(Image.open(clean_dir / n).convert("RGB"), dtype=np.float64) / 255
        w = real.shape[1]
        left, right = slice(0, w // 2), slice(w // 2, w)
        for k in kinds:
            fit = slice(0, w) if k.endswith("full") else left
            pred = fit_predict(clean, real, k.replace(" full", ""), fit, right)
            table[k].append(psnr(pred, real[:, right]))
    print(f"{args.scene.name}: right-half PSNR with a perfect (clean) reconstruction, transform fitted as stated")
    print("| transform | " + " | ".join(Path(n).stem for n in names) + " | mean |")
    print("|---|" + "---|" * (len(names) + 1))
    for k in kinds:
        print(f"| {k} | " + " | ".join(f"{v:.2f}" for v in table[k]) + f" | **{np.mean(table[k]):.2f}** |")


if __name__ == "__main__":
    main()
