"""Shrink the GPU wheels of ../shared/gpu/prepare_wheels.sh so that they and the scenes fit one device call's 64 MiB.

Drops data no run needs: tensorly's example datasets (7 MB; nerfstudio imports tensorly only for TensoRF's
decompositions) and jedi's bundled typeshed stubs (3 MB; IPython's completion only). Rewrites the wheels in place:

    bash ../shared/gpu/prepare_wheels.sh && python3 benchmarks/slim_wheels.py .whl-gpu
"""

import sys
import zipfile
from pathlib import Path

DROP = {"tensorly-": ("tensorly/datasets/data/",), "jedi-": ("jedi/third_party/typeshed/", "jedi/third_party/django")}


def slim(wheel: Path, prefixes: tuple[str, ...]) -> int:
    """Rewrite `wheel` without members under `prefixes` (their RECORD lines go too). Returns bytes saved."""
    before = wheel.stat().st_size
    tmp = wheel.with_suffix(".tmp")
    with zipfile.ZipFile(wheel) as src, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            if info.filename.startswith(prefixes):
                continue
            data = src.read(info)
            if info.filename.endswith(".dist-info/RECORD"):
                keep = [ln for ln in data.decode().splitlines() if not ln.startswith(prefixes)]
                data = ("\n".join(keep) + "\n").encode()
            dst.writestr(info, data)
    tmp.replace(wheel)
    return before - wheel.stat().st_size


def main(folder: str) -> int:
    saved = 0
    for w in sorted(Path(folder).glob("*.whl")):
        for stem, prefixes in DROP.items():
            if w.name.startswith(stem):
                saved += slim(w, prefixes)
    print(f"slim_wheels: {saved / 2**20:.1f} MiB saved in {folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else ".whl-gpu"))
