"""Image files as the parsers read them: a photo written at an integer fraction of its size."""

from pathlib import Path

from PIL import Image


def save_downscaled(src: Path, factor: int, dst: Path) -> None:
    """``src`` at floor(w / factor) x floor(h / factor) (nerfstudio's rounding of the cameras) with PIL's box (area)
    filter, written to ``dst``; JPEG at quality 95 without chroma subsampling, other formats as PIL writes them."""
    with Image.open(src) as im:
        small = im.resize((im.width // factor, im.height // factor), resample=Image.Resampling.BOX)
        if Path(src).suffix.lower() in (".jpg", ".jpeg"):
            small.convert("RGB").save(dst, quality=95, subsampling=0)
        else:
            small.save(dst)
