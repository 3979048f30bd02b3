"""A real scene's picture sheet: the right halves of up to 4 test views as ground truth | one row per run (default:
splatfacto, peer, willags), and the transient mask of 4 training images, from the sheets that runs with
WILLAGS_BENCH_RENDERS write (docs/real_scene_comparison.png: reichstag; docs/pictures_<scene>.png: every real scene).

    WILLAGS_BENCH_RENDERS=OUT/renders GRID=configs/benchmark_gpu_fidelity.json bash benchmarks/remote/grid.sh run OUT \\
        reichstag:splatfacto:h100-r3:42 reichstag:peer:h100-r3:42 reichstag:willags:h100-r4:43
    python -m benchmarks pictures OUT/renders --out docs/real_scene_comparison.png
    python -m benchmarks pictures OUT/renders --scene ../shared/data/south-building \\
        --rows "peer-h200-r1=peer,willags-h200-r1-wip=willags,willags-auto-h200-r1=willags-auto" \\
        --masks "{scene}-willags-h200-r1-wip-masks.png" --out docs/pictures_south-building.png

The test views' order is the parser's: the NeRF-W tsv's (COLMAP ids), or split.json's "test" list.
"""

import argparse
import sys
from pathlib import Path

from PIL import Image, ImageDraw

REPO = Path(__file__).resolve().parents[1]
ROWS = "splatfacto=splatfacto,peer=Splatfacto-W-light (peer),willags=willags"
"""--rows default: `<run name after the scene>=<label>` (a run's sheet is <scene>-<run name>*.png)."""


def _test_images(scene: Path) -> list[str]:
    """File names of the scene's test views in the parser's order."""
    tsv = scene / f"{scene.name}.tsv"
    if tsv.is_file():
        split = [ln.split("\t") for ln in tsv.read_text().splitlines()[1:] if ln.strip()]
        return [name for _, name in sorted((int(f[1]), f[0]) for f in split if f[2] == "test")]
    import json

    return [Path(p).name for p in json.loads((scene / "split.json").read_text())["test"]]


def _columns(sheet: Image.Image, test_sizes: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """x ranges of the sheet's columns: each test image's right half scaled to half the sheet's height."""
    h = sheet.height // 2
    xs, x = [], 0
    for w_full, h_full in test_sizes:
        w = max(1, round((w_full - w_full // 2) * h / h_full))
        xs.append((x, x + w))
        x += w
    return xs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("renders", type=Path, help="the WILLAGS_BENCH_RENDERS folder of the runs")
    ap.add_argument("--scene", type=Path, default=REPO.parent / "shared/data/reichstag")
    ap.add_argument("--views", default="0,1,3,5", help="test views to show (indices in the split's order)")
    ap.add_argument("--rows", default=ROWS, help="runs to show: comma-separated <run name>=<label>")
    ap.add_argument("--masks", default="{scene}-willags-*-masks.png", help="glob of the mask sheet ({scene}: its name)")
    ap.add_argument(
        "--masks-label", default="willags' transient mask", help="whose mask the mask sheet shows (its caption)"
    )
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "real_scene_comparison.png")
    args = ap.parse_args(argv)

    names = _test_images(args.scene)
    sizes = [Image.open(args.scene / "images" / name).size for name in names]
    views = [int(v) for v in args.views.split(",") if int(v) < len(names)]
    rows_spec = [tuple(item.split("=", 1)) for item in args.rows.split(",")]

    sheets = {}
    for key, _ in rows_spec:
        found = sorted(args.renders.glob(f"{args.scene.name}-{key}*.png"))
        found = [p for p in found if not p.name.endswith("-masks.png")]
        if not found:
            print(f"no sheet for {key} in {args.renders}", file=sys.stderr)
            return 1
        sheets[key] = Image.open(found[0]).convert("RGB")
    first = sheets[rows_spec[0][0]]
    cols = _columns(first, sizes)
    h = first.height // 2
    label_w = 150
    tiles_w = sum(cols[v][1] - cols[v][0] for v in views)
    rows = [("ground truth (right half)", first, 0)] + [(label, sheets[k], h) for k, label in rows_spec]
    masks = sorted(args.renders.glob(args.masks.format(scene=args.scene.name)))
    mask_sheet = Image.open(masks[0]).convert("RGB") if masks else None
    mask_h = 0
    if mask_sheet is not None:
        scale = (label_w + tiles_w) / mask_sheet.width
        mask_sheet = mask_sheet.resize((label_w + tiles_w, round(mask_sheet.height * scale)))
        mask_h = mask_sheet.height + 24
    out = Image.new("RGB", (label_w + tiles_w, h * len(rows) + mask_h), "white")
    draw = ImageDraw.Draw(out)
    for r, (label, sheet, y0) in enumerate(rows):
        x = label_w
        draw.text((6, r * h + h // 2 - 6), label, fill=(0, 0, 0))
        for v in views:
            a, b = cols[v]
            out.paste(sheet.crop((a, y0, b, y0 + h)), (x, r * h))
            x += b - a
    if mask_sheet is not None:
        y = h * len(rows)
        draw.text((6, y + 6), f"{args.masks_label} on 4 training images (red: not supervised)", fill=(0, 0, 0))
        out.paste(mask_sheet, (0, y + 24))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    out.save(args.out)
    print(f"wrote {args.out} ({out.width}x{out.height})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
