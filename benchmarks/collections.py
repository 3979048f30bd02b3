"""Real photo collections rebuilt from public repositories: photos in, a scene for ``ns-train willags`` out.

The photos are never committed here. Each collection names its source (a public GitHub repository pinned to a
commit, a folder in it, and which photos to take); ``build`` fetches them, resizes them to at most ``MAX_SIDE``
pixels on the long side (JPEG quality ``JPEG_QUALITY``: small scenes that travel to a GPU machine), runs
``willags-process`` on them (the split is its own: every 8th registered photo is a test photo) and writes a
README.md and a sources.json (each photo's origin, original size and whether it registered) into the scene:

    python -m benchmarks collections list
    python -m benchmarks collections build lund --out /scenes/lund [--source MIRROR] [--num-threads 1]

``--source`` is a local copy of the repository: a clone or a bare mirror (the photos are read at the pinned commit)
or a plain folder holding the repository's files. Without it the repository is cloned over https at the pinned
commit (only the named folder is checked out). The built folder holds ``images/``, ``colmap/sparse/0``,
``<name>.tsv``, ``process_summary.json``, README.md and sources.json; the SfM database and the distorted model
that ``willags-process`` keeps for resuming are removed at the end (nerfstudio reads neither). SfM runs on one
thread (``NUM_THREADS``) so that a rebuild is the same scene byte for byte: the README gives the model's digest, and
the build says whether it is the one the collection pins (``Collection.model_sha256``).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from PIL import Image, ImageOps

from benchmarks.records import tree_bytes

MAX_SIDE = 800
"""Long side of the photos given to SfM and training, in pixels (the shared real scenes' size)."""

JPEG_QUALITY = 90
"""Quality of the resized photos (4:2:0 chroma): ~100 KB per 800 px photo."""

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
"""Files taken from a source folder when a collection lists no photos."""

NUM_THREADS = 1
"""willags-process's CPU threads for a build. With one, a build gives the same SfM model byte for byte every time
(``model_digest``); with more, the matcher's and mapper's threads finish in an order that changes from run to run,
and so do the model's points, and a collection rebuilt elsewhere is then not the scene the records were made on
(docs/process.md, "The same scene every time"). It costs about twice the build's time."""

MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin")
"""The SfM model a scene holds in ``colmap/sparse/0``: what ``model_digest`` hashes."""

LEFT_BEHIND = ("colmap/database.db", "colmap/distorted", "colmap/inputs", "colmap/vocab_tree.bin")
"""What willags-process keeps for resuming and nerfstudio never reads: removed from a finished scene."""


class CollectionError(RuntimeError):
    """A bad collection name, source or photo list: one line saying which and why."""


@dataclass(frozen=True)
class Collection:
    name: str
    """Scene name: the built folder's ``<name>.tsv`` and the README's title."""
    repo: str
    """Public GitHub repository, ``owner/name``."""
    commit: str
    """The pinned commit (40 hex digits): the photos are read at this commit."""
    folder: str
    """Folder of the photos inside the repository."""
    photos: tuple[str, ...] = ()
    """Paths to take, relative to ``folder`` (a file name, or ``sub/name`` for a photo in a subfolder: a source that
    splits one landmark's photos over several folders); empty: every photo there, subfolders included
    (``PHOTO_SUFFIXES``)."""
    single_camera: bool = False
    """All photos from one camera and zoom: willags-process shares one set of intrinsics between them."""
    mapper: str = "auto"
    """willags-process's ``--mapper`` (auto, incremental or global)."""
    about: str = ""
    """What the photos show and why the collection is here (the README's first paragraph)."""
    licence: str = ""
    """Under what terms the photos are published (the README says it)."""
    model_sha256: str = ""
    """``model_digest`` of the scene that a build at ``NUM_THREADS`` threads gives: a build says whether it made that
    scene (``pin_verdict``), so runs made on scenes built in different places are known to compare. Empty: not
    pinned."""

    @property
    def url(self) -> str:
        return f"https://github.com/{self.repo}.git"


COLLECTIONS: dict[str, Collection] = {
    c.name: c
    for c in (
        Collection(
            name="lund",
            repo="mapillary/OpenSfM",
            commit="238744cdf3b5d50149c50d136a87f7fea25ad5cd",
            folder="data/lund/images",
            photos=tuple(f"{i:02d}.jpg" for i in range(1, 30)),
            single_camera=True,
            mapper="global",
            about=(
                "A walk through the cobbled streets of old Lund (Sweden) on a sunny day: 29 phone photos, 1024 x 768, "
                "one camera, with hard shadows, parked cars, bicycles and people walking through (faces and number "
                "plates blurred by the source). A street scene rather than one landmark: the camera moves along "
                "several streets, so most of each photo is seen by only a few others. One shared camera (one phone); "
                "the global mapper, because the incremental one finds no initial pair on this forward-moving walk "
                "(it registers 2 of 29). The global model agrees with the photos' own GPS tags (not used by SfM): "
                "after a similarity alignment the camera centres are a median 4 m (at most 11 m) from them over a "
                "179 m walk, within a phone's GPS error."
            ),
            licence="part of OpenSfM's example data (the repository is BSD-2-Clause licensed)",
            model_sha256="fca888203f845057fdec2bdd9bff337ed74f3e33ca30f738fc5af57563b5836c",
        ),
        Collection(
            name="westminster-abbey",
            repo="zym1010/photo_tourism_ZJU",
            commit="f889eba0ceaf4424befd3106dd4818144ed4ae97",
            folder="img/regular",
            photos=(
                "10.jpg",
                "20.jpg",
                "29.jpg",
                "30.jpg",
                "35.jpg",
                "37.jpg",
                "40.jpg",
                "50.jpg",
                "67.jpg",
                "68.jpg",
                "78.jpg",
                "79.JPG",
                "80.jpg",
                "90.jpg",
                "DSC00796.JPG",
                "DSC01851.jpg",
                "DSCN0142.JPG",
                "DSCN1055.JPG",
                "DSC_0182.JPG",
                "DSC_0355.JPG",
                "DSC_1372.JPG",
                "IMG_0161.JPG",
                "IMG_1716.jpg",
                "IMG_2249.jpg",
                "IMG_2251a.jpg",
                "IMG_4081.JPG",
                "London Part 4 095.JPG",
                "London Westminster Abbey.JPG",
                "OJ077898_942long.jpg",
                "Street Art, London - April 2011 594.jpg",
                "Westminster Abbey 2.JPG",
                "Westminster Abbey.JPG",
                "Westminster-Abbey-3.jpg",
                "Westminster-Abbey-UK-1050x1680.jpg",
                "Westminster-Abbey-UK-2048x2048.jpg",
                "Westminster-Abbey.jpg",
                "Westminster-Abbey_1.jpg",
                "figurebig-3149.jpg",
                "img_0732.jpg",
                "img_0774.jpg",
                "img_5906.jpg",
                "london 151.JPG",
                "london-westminster-abbey.jpg",
                "london_d2_westminster_abbey2.JPG",
                "london_photography_westminster_abbey.jpg",
                "west-abbey-04.jpg",
                "westminster-abbey-side-entrance.jpg",
                "westminster_abbey2.JPG",
                "westminster_abbey__london___hdr.jpg",
            ),
            about=(
                "Westminster Abbey's north front (London) as visitors photograph it: 49 photos gathered from the web "
                "for a Photo Tourism course project, from many cameras (the 18 that keep their EXIF name 18 different "
                "models: Canon, Nikon, Sony, Panasonic, Olympus, Kodak, Casio; 17 different days, 2005-2013) and "
                "viewpoints near and far, in blue sky, overcast and evening light, a few processed (HDR, warm "
                "tones), with crowds on the lawn and people posing in front. The landmark collection of the kind the "
                "method is for. Two files of the folder are byte-identical to two others under other names "
                "(60.jpg = DSC01851.jpg, 70.jpg = IMG_0161.JPG) and two are left out because some mirrors of the "
                "repository do not carry files over 4 MB (WestminsterAbbey-north-facade001m.jpg, img_0409.jpg)."
            ),
            licence=(
                "no licence stated: the photos were gathered from the web (photo-sharing, wallpaper and stock "
                "sites, judging by their file names), their copyright stays with their photographers; never "
                "redistribute them"
            ),
            model_sha256="3acaa97df5d16dcb52723aa07ce4242e48fc7ceeca08f42c2645bd304fb523cf",
        ),
        Collection(
            name="hochiminh-mausoleum",
            repo="huynhtiennhat0403/vietnamese-landmark-classifier",
            commit="2b4896fa32dd88b4d83d8344440b3efb1e90145e",
            folder="data",
            photos=(
                "train/hochiminh_mausoleum/hochiminh_mausoleum (10).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (11).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (12).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (13).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (14).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (15).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (16).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (17).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (18).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (19).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (2).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (20).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (21).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (22).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (23).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (24).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (25).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (26).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (27).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (29).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (3).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (30).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (31).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (32).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (33).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (34).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (35).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (36).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (37).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (38).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (39).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (4).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (40).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (41).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (5).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (6).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (7).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (8).jpg",
                "train/hochiminh_mausoleum/hochiminh_mausoleum (9).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (1).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (10).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (2).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (3).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (4).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (5).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (6).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (7).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (8).jpg",
                "test/hochiminh_mausoleum/hochiminh_mausoleum (9).jpg",
            ),
            about=(
                "The Ho Chi Minh Mausoleum (Hanoi) and Ba Dinh Square in front of it, as visitors and web pages show "
                "it: 49 photos gathered from the web for a landmark classifier (its train and test folders of the "
                "mausoleum), mostly of the front facade from near and far, in clear, overcast, sunset and night "
                "light, with queues of visitors, the honour guard, flags and flower beds that change from photo to "
                "photo; some are HDR-processed or watermarked, a few are small (about 160-400 px). Most carry no "
                "EXIF; the few that do name different cameras and years (2007-2020). One file is left out: "
                "train/hochiminh_mausoleum/hochiminh_mausoleum (28).jpg is byte-identical to (24).jpg."
            ),
            licence=(
                "no licence stated: the photos were gathered from the web, their copyright stays with their "
                "photographers; never redistribute them"
            ),
            model_sha256="66e17407a44bb87c63a0d126f5da1f5153f621566d40a229835ff75ec56cdc98",
        ),
        Collection(
            name="porto-city-hall",
            repo="franciscapessanha/Porto-landmarks-recognition",
            commit="c937199327fc15c5cde99a3ef9a325f50819d5a0",
            folder="images/camara",
            photos=(
                "camara-0000.jpg",
                "camara-0001.jpg",
                "camara-0002.jpg",
                "camara-0003.jpg",
                "camara-0004.jpg",
                "camara-0005.jpg",
                "camara-0006.jpg",
                "camara-0007.jpg",
                "camara-0008.jpg",
                "camara-0009.jpg",
                "camara-0010.jpg",
                "camara-0011.jpg",
                "camara-0012.jpg",
                "camara-0013.jpg",
                "camara-0014.jpg",
                "camara-0015.jpg",
                "camara-0016.jpg",
                "camara-0017.png",
                "camara-0018.jpg",
                "camara-0019.jpg",
                "camara-0020.jpg",
                "camara-0021.jpg",
                "camara-0022.jpg",
                "camara-0023.jpg",
                "camara-0024.jpg",
                "camara-0025.jpg",
                "camara-0026.jpg",
                "camara-0027.jpg",
                "camara-0028.jpg",
                "camara-0029.jpg",
                "camara-0030.jpg",
                "camara-0031.jpg",
                "camara-0032.jpg",
                "camara-0033.jpg",
                "camara-0035.jpg",
                "camara-0036.jpg",
                "camara-0037.jpg",
                "camara-0038.jpg",
                "camara-0039.jpg",
                "camara-0040.jpg",
                "camara-0041.jpg",
                "camara-0042.jpg",
                "camara-0043.jpg",
                "camara-0044.jpg",
                "camara-0045.jpg",
                "camara-0046.jpg",
                "camara-0047.jpg",
                "camara-0048.jpg",
                "camara-0049.jpg",
                "camara-0050.jpg",
                "camara-0051.jpg",
                "camara-0052.jpg",
                "camara-0053.jpg",
                "camara-0054.jpg",
                "camara-0055.jpg",
                "camara-0056.jpg",
                "camara-0057.jpg",
                "camara-0059.jpg",
                "camara-0060.jpg",
                "camara-0061.jpg",
                "camara-0062.jpg",
                "camara-0063.jpg",
                "camara-0064.jpg",
                "camara-0065.jpg",
                "camara-0066.jpg",
                "camara-0067.jpg",
                "camara-0068.jpg",
                "camara-0069.jpg",
                "camara-0070.jpg",
                "camara-0071.jpg",
                "camara-0072.jpg",
                "camara-0073.jpg",
                "camara-0074.jpg",
                "camara-0075.jpg",
                "camara-0076.jpg",
                "camara-0077.jpg",
                "camara-0078.jpg",
                "camara-0080.jpg",
                "camara-0083.jpg",
                "camara-0084.jpg",
                "camara-0086.jpg",
                "camara-0087.jpg",
                "camara-0088.jpg",
                "camara-0089.jpg",
                "camara-0090.jpg",
                "camara-0091.jpg",
                "camara-0092.jpg",
                "camara-0093.jpg",
                "camara-0094.jpg",
                "camara-0095.jpg",
                "camara-0096.jpg",
                "camara-0097.jpg",
                "camara-0098.jpeg",
            ),
            about=(
                "Porto's City Hall (Camara Municipal do Porto) at the top of the Avenida dos Aliados: 93 photos "
                "gathered from the web for a landmark recognition project, nearly all of the main facade and its "
                "clock tower from the avenue, near and far, straight on and from either side, in blue sky, overcast, "
                "dusk and night light, one in black and white, with the pool, trees and passers-by in front; about a "
                "fifth carry a stock photo site's watermark, a few are small (from 220 px) and one is a night crowd "
                "with flags. Almost none keep their EXIF. Left out: five files byte-identical to others "
                "(camara-0079, -0081, -0082, -0085 and -0099 repeat -0021, -0025, -0014, -0008 and -0069) and two whose "
                "contents some mirrors of the repository do not carry (camara-0034, camara-0058). The photos are in "
                "the repository's history only (this commit), not in its latest tree."
            ),
            licence=(
                "no licence stated: the photos were gathered from the web (several from stock photo sites), their "
                "copyright stays with their photographers; never redistribute them"
            ),
            model_sha256="d08341d59c0da771f3cb1da94451af487fb2e4f9a42b782274c9d41280a200ea",
        ),
        Collection(
            name="porto-clerigos",
            repo="franciscapessanha/Porto-landmarks-recognition",
            commit="c937199327fc15c5cde99a3ef9a325f50819d5a0",
            folder="images/clerigos",
            photos=(
                "clerigos-0000.jpg",
                "clerigos-0001.jpg",
                "clerigos-0002.jpg",
                "clerigos-0003.jpg",
                "clerigos-0004.jpg",
                "clerigos-0005.jpg",
                "clerigos-0006.jpg",
                "clerigos-0007.jpg",
                "clerigos-0008.jpg",
                "clerigos-0009.jpg",
                "clerigos-0010.jpg",
                "clerigos-0011.jpg",
                "clerigos-0012.jpg",
                "clerigos-0013.jpg",
                "clerigos-0014.jpg",
                "clerigos-0015.jpg",
                "clerigos-0016.jpg",
                "clerigos-0017.jpg",
                "clerigos-0018.jpg",
                "clerigos-0019.jpg",
                "clerigos-0020.jpg",
                "clerigos-0021.jpg",
                "clerigos-0022.jpg",
                "clerigos-0023.jpg",
                "clerigos-0024.jpg",
                "clerigos-0025.jpg",
                "clerigos-0026.jpg",
                "clerigos-0027.jpg",
                "clerigos-0028.jpg",
                "clerigos-0029.jpg",
                "clerigos-0030.jpg",
                "clerigos-0031.jpg",
                "clerigos-0032.jpg",
                "clerigos-0033.jpg",
                "clerigos-0034.jpg",
                "clerigos-0035.jpg",
                "clerigos-0036.jpg",
                "clerigos-0037.jpg",
                "clerigos-0038.jpg",
                "clerigos-0039.jpg",
                "clerigos-0040.jpg",
                "clerigos-0041.jpg",
                "clerigos-0042.jpg",
                "clerigos-0043.jpg",
                "clerigos-0044.jpg",
                "clerigos-0045.jpg",
                "clerigos-0046.jpg",
                "clerigos-0047.jpg",
                "clerigos-0048.jpg",
                "clerigos-0049.jpg",
                "clerigos-0050.jpg",
                "clerigos-0051.jpg",
                "clerigos-0052.jpg",
                "clerigos-0053.jpg",
                "clerigos-0054.jpg",
                "clerigos-0055.jpg",
                "clerigos-0056.jpg",
                "clerigos-0057.jpg",
                "clerigos-0058.jpg",
                "clerigos-0059.jpg",
                "clerigos-0060.jpg",
                "clerigos-0061.jpg",
                "clerigos-0062.jpg",
                "clerigos-0063.jpg",
                "clerigos-0064.png",
                "clerigos-0065.jpg",
                "clerigos-0066.jpg",
                "clerigos-0067.jpg",
                "clerigos-0069.jpg",
                "clerigos-0070.jpg",
                "clerigos-0071.jpg",
                "clerigos-0073.jpg",
                "clerigos-0074.jpg",
                "clerigos-0075.jpg",
                "clerigos-0076.jpg",
                "clerigos-0077.jpg",
                "clerigos-0078.jpg",
                "clerigos-0079.jpg",
                "clerigos-0080.jpg",
                "clerigos-0081.jpg",
                "clerigos-0082.jpg",
                "clerigos-0083.jpg",
                "clerigos-0084.jpg",
                "clerigos-0085.jpg",
                "clerigos-0086.jpg",
                "clerigos-0087.jpg",
                "clerigos-0088.jpg",
                "clerigos-0089.jpg",
                "clerigos-0090.jpg",
                "clerigos-0091.jpg",
                "clerigos-0092.jpg",
                "clerigos-0093.jpg",
                "clerigos-0094.jpg",
                "clerigos-0095.jpg",
                "clerigos-0096.jpg",
                "clerigos-0097.jpg",
                "clerigos-0098.jpg",
                "clerigos-0099.jpg",
            ),
            about=(
                "The Clerigos Tower (Torre dos Clerigos) in Porto's old town: 98 photos gathered from the web for a "
                "landmark recognition project, the baroque granite tower from the streets and squares around it, near "
                "and far, from below and from above the roofs, with the church beside it, trees, trams, cars and "
                "passers-by, in blue sky, cloud, dusk and night light; a few are panoramas of the city with the tower "
                "small on the skyline, and a few are not photos of the site (a book cover, a postcard, an information "
                "board, a drawing, a souvenir held up). Some carry a stock photo site's "
                "watermark, some are small (from 150 px). Left out: clerigos-0072, a smaller copy of clerigos-0097, "
                "and clerigos-0068, a GIF. Built to be scored, not tuned on: no setting was chosen by it. The "
                "photos are in the repository's history only (this commit), not in its latest tree."
            ),
            licence=(
                "no licence stated: the photos were gathered from the web (several from stock photo sites), their "
                "copyright stays with their photographers; never redistribute them"
            ),
            model_sha256="468ea26a74b048a2f843736ce2b56020b508b32846fb0a4d2f960cdbe8223c0d",
        ),
    )
}
"""Every collection ``build`` knows, by name."""


def collection(name: str) -> Collection:
    if name not in COLLECTIONS:
        raise CollectionError(f"unknown collection {name!r}; known: {', '.join(COLLECTIONS)}")
    return COLLECTIONS[name]


def select_photos(available: Sequence[str], coll: Collection) -> list[str]:
    """The photos to take, sorted: ``coll.photos`` (each must be in ``available``) or every photo file there."""
    have = set(available)
    if coll.photos:
        missing = [p for p in coll.photos if p not in have]
        if missing:
            more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
            raise CollectionError(
                f"{coll.name}: {coll.repo} {coll.folder} lacks {', '.join(missing[:3])}{more} at {coll.commit[:8]}"
            )
        return sorted(coll.photos)
    picked = sorted(n for n in have if Path(n).suffix.lower() in PHOTO_SUFFIXES)
    if not picked:
        raise CollectionError(f"{coll.name}: no photos ({', '.join(PHOTO_SUFFIXES)}) in {coll.repo} {coll.folder}")
    return picked


def scene_name(name: str) -> str:
    """The photo's file name in the scene: its path below the collection's folder without the suffix (the stem alone
    for a photo directly in it; the subfolders' names first for one below, so that two subfolders' photos of one
    name stay apart), every run of characters other than letters, digits, ``.``, ``_`` and ``-`` turned into one
    ``_`` (web photos carry spaces and commas, which some tools split on; ``/`` too), then ``.jpg``
    (``resize_photo`` writes JPEG); ``photo.jpg`` when nothing of it is left."""
    stem = Path(name).with_suffix("").as_posix()
    return (re.sub(r"[^A-Za-z0-9._-]+", "_", stem).strip("_.") or "photo") + ".jpg"


def resize_photo(data: bytes, dst: Path, max_side: int = MAX_SIDE, quality: int = JPEG_QUALITY) -> dict[str, Any]:
    """Write the photo ``data`` to ``dst`` as a JPEG with a long side of at most ``max_side`` (area filter; EXIF
    orientation applied to the pixels, the rest of the EXIF kept for SfM's focal-length prior). Returns its original
    and written sizes, ``{"orig_size": [w, h], "size": [w, h]}``."""
    with Image.open(io.BytesIO(data)) as im:
        orig = list(im.size)
        exif = im.getexif()
        upright = ImageOps.exif_transpose(im)
        w, h = upright.size
        scale = min(1.0, max_side / max(w, h))
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        small = upright.resize(size, resample=Image.Resampling.BOX) if scale < 1.0 else upright
        exif.pop(0x0112, None)  # orientation: now in the pixels
        dst.parent.mkdir(parents=True, exist_ok=True)
        small.convert("RGB").save(dst, format="JPEG", quality=quality, exif=exif.tobytes())
    return {"orig_size": orig, "size": list(size)}


class Source:
    """The photos of a collection's folder at its pinned commit: from a git repository (a clone or a bare mirror)
    or from a plain folder holding the repository's files."""

    def __init__(self, coll: Collection, root: Path):
        self.coll, self.root = coll, root
        self.git = _is_git(root)
        if self.git:
            rc = _git(root, "cat-file", "-e", f"{coll.commit}^{{commit}}", check=False)
            if rc.returncode != 0:
                raise CollectionError(f"{coll.name}: {root} has no commit {coll.commit} of {coll.repo}")
        elif not (root / coll.folder).is_dir():
            raise CollectionError(f"{coll.name}: {root} has no folder {coll.folder} ({coll.repo}) and is no git repo")

    def names(self) -> list[str]:
        """Every file below the folder, as a path relative to it (``sub/name`` in a subfolder)."""
        if self.git:
            # -z: names as they are (without it git quotes a name with non-ASCII letters)
            out = _git(self.root, "ls-tree", "-r", "-z", "--name-only", f"{self.coll.commit}:{self.coll.folder}").stdout
            return sorted(n for n in out.decode().split("\0") if n)
        top = self.root / self.coll.folder
        return sorted(p.relative_to(top).as_posix() for p in top.rglob("*") if p.is_file())

    def read(self, name: str) -> bytes:
        if self.git:
            return _git(self.root, "cat-file", "blob", f"{self.coll.commit}:{self.coll.folder}/{name}").stdout
        return (self.root / self.coll.folder / name).read_bytes()


def _git(repo: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    """``git -C repo args`` (works on bare repositories too); a failure raises CollectionError with git's message."""
    r = subprocess.run(["git", "-C", str(repo), *args], capture_output=True)
    if check and r.returncode != 0:
        raise CollectionError(f"git {' '.join(args)} in {repo}: {r.stderr.decode().strip() or r.returncode}")
    return r


def _is_git(path: Path) -> bool:
    if not path.is_dir():
        return False
    r = subprocess.run(["git", "-C", str(path), "rev-parse", "--absolute-git-dir"], capture_output=True)
    return r.returncode == 0 and Path(r.stdout.decode().strip()).resolve() in (
        (path / ".git").resolve(),
        path.resolve(),
    )


def clone(coll: Collection, dst: Path) -> Path:
    """A partial clone of ``coll.repo`` in ``dst`` holding only ``coll.folder`` at ``coll.commit`` (network)."""
    _git(dst.parent, "clone", "--filter=blob:none", "--no-checkout", coll.url, str(dst))
    _git(dst, "checkout", coll.commit, "--", coll.folder)
    return dst


def scene_readme(coll: Collection, rows: Sequence[dict[str, Any]], summary: dict[str, Any]) -> str:
    """The built scene's README.md: what the photos are, where from, how they were processed, the SfM numbers."""
    reg = sum(r["registered"] for r in rows)
    sides = [max(r["undistorted_size"]) for r in rows if r["registered"]]
    stages = ", ".join(f"{k} {v:.0f} s" for k, v in summary.get("stage_s", {}).items())
    unreg = [r["name"] for r in rows if not r["registered"]]
    lines = [
        f"# {coll.name}",
        "",
        coll.about,
        "",
        f"Source: the public repository {coll.repo} (commit {coll.commit[:8]}, `{coll.folder}`): {len(rows)} photos "
        f"({coll.licence}; use them for research and testing only). `sources.json` lists every photo with its origin, "
        "original size, size here and whether it registered.",
        "",
        f"Built by `python -m benchmarks collections build {coll.name} --out DIR` (willags-ns): each photo resized "
        f"to a long side of at most {MAX_SIDE} px (area filter, JPEG quality {JPEG_QUALITY}), then `willags-process`"
        + (" --single-camera" if coll.single_camera else "")
        + (f" --mapper {coll.mapper}" if coll.mapper != "auto" else "")
        + ".",
        "",
        "Layout (nerfstudio's colmap dataparser defaults; the willags dataparser also reads the split):",
        "",
        "```",
        f"images/                 {reg} registered photos, undistorted (PINHOLE), JPEG quality {JPEG_QUALITY}, long side "
        f"{min(sides, default=0)}-{max(sides, default=0)} px (sizes differ per photo)",
        "colmap/sparse/0/        cameras.bin images.bin points3D.bin",
        f"{summary.get('split_file', coll.name + '.tsv'):<24}NeRF-W split (filename, id, split, dataset): "
        f"{summary.get('num_train', '?')} train, {summary.get('num_test', '?')} test (every 8th registered photo)",
        "process_summary.json    willags-process's summary: options, timings, why photos did not register",
        "sources.json            per photo: origin, sizes, registered",
        "```",
        "",
        f"## SfM (willags-process, pycolmap {summary.get('pycolmap', '?')}, CPU)",
        "",
        "| | |",
        "|---|---|",
        f"| photos / registered | {len(rows)} / {reg} |",
        f"| camera model | {summary.get('camera_model', '?')} |",
        f"| matching | {summary.get('matching', '?')} ({summary.get('num_pairs', 0):,} pairs) |",
        f"| 3D points | {summary.get('points3D', 0):,} |",
        f"| mean reprojection error | {summary.get('mean_reprojection_error_px', float('nan')):.3f} px |",
        f"| mean track length | {summary.get('mean_track_length', float('nan')):.2f} |",
        f"| wall time | {summary.get('wall_s', 0):.0f} s ({stages}) |",
        f"| SfM model (sha256 of colmap/sparse/0) | `{summary.get('model_sha256', '?')}` |",
    ]
    if unreg:
        lines += ["", f"Not registered ({len(unreg)}): {', '.join(unreg)} (why: process_summary.json)."]
    return "\n".join(lines) + "\n"


def model_digest(scene: Path) -> str:
    """sha256 over the SfM model of ``scene`` (``MODEL_FILES`` in ``colmap/sparse/0``, each file's name and bytes):
    two scenes with one digest hold the same cameras, poses and points."""
    h = hashlib.sha256()
    for name in MODEL_FILES:
        f = scene / "colmap" / "sparse" / "0" / name
        if not f.is_file():
            raise CollectionError(f"{scene}: no SfM model file {f.relative_to(scene)}")
        h.update(name.encode() + b"\0")
        h.update(f.read_bytes())
    return h.hexdigest()


def pin_verdict(coll: Collection, digest: str) -> str:
    """One line: whether ``digest`` is the SfM model ``coll`` pins (``Collection.model_sha256``)."""
    if not coll.model_sha256:
        return f"{coll.name}: SfM model {digest[:12]} (no model pinned for this collection)"
    if digest == coll.model_sha256:
        return f"{coll.name}: SfM model {digest[:12]}, the pinned one: the same scene as every build that matches it"
    return (
        f"{coll.name}: SfM model {digest[:12]} differs from the pinned {coll.model_sha256[:12]} (another pycolmap, or "
        f"more than {NUM_THREADS} thread): runs on it do not compare with runs on the pinned scene"
    )


def build(
    coll: Collection, out: Path, source: Path | None = None, num_threads: int = NUM_THREADS, log=print
) -> dict[str, Any]:
    """Fetch, resize and process ``coll`` into the scene folder ``out``; returns the SfM summary plus the sources."""
    out = out.resolve()
    with tempfile.TemporaryDirectory(prefix=f"willags-{coll.name}-") as tmp:
        tmp_path = Path(tmp)
        if source is None:
            log(f"cloning {coll.url} at {coll.commit[:8]} ({coll.folder} only)")
            source = clone(coll, tmp_path / "repo")
        src = Source(coll, source.resolve())
        names = select_photos(src.names(), coll)
        photos = tmp_path / "photos"
        rows = []
        for name in names:
            dst = photos / scene_name(name)
            sizes = resize_photo(src.read(name), dst)
            rows.append({"name": dst.name, "repo": f"{coll.repo} @ {coll.commit}", "path": f"{coll.folder}/{name}"})
            rows[-1].update(sizes)
        if len({r["name"] for r in rows}) != len(rows):
            raise CollectionError(f"{coll.name}: two photos of {coll.folder} share a name in the scene")
        log(f"{len(rows)} photos resized to <= {MAX_SIDE} px in {photos}; running willags-process")
        cmd = [
            sys.executable, "-m", "willags_ns.scripts.process", "--images", str(photos), "--output", str(out),
            "--num-threads", str(num_threads), "--num-downscales", "0",
        ]  # fmt: skip
        if coll.single_camera:
            cmd.append("--single-camera")
        if coll.mapper != "auto":
            cmd += ["--mapper", coll.mapper]
        r = subprocess.run(cmd)
        if r.returncode != 0:
            raise CollectionError(f"{coll.name}: willags-process failed (exit status {r.returncode}); see above")
    return finish_scene(coll, out, rows)


def reencode(images: Path, quality: int = JPEG_QUALITY) -> None:
    """Re-save every JPEG in ``images`` at ``quality`` (same pixels and size): COLMAP's undistorter writes near
    lossless JPEGs, about three times the bytes of the photos it was given."""
    for f in sorted(images.iterdir()):
        if f.suffix.lower() in (".jpg", ".jpeg"):
            tmp = f.with_name(f".{f.name}.partial")
            with Image.open(f) as im:
                im.convert("RGB").save(tmp, format="JPEG", quality=quality, exif=im.getexif().tobytes())
            tmp.replace(f)


def finish_scene(coll: Collection, out: Path, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Drop what nerfstudio does not read, re-encode the images, mark which photos registered, write README.md and
    sources.json."""
    summary = json.loads((out / "process_summary.json").read_text())
    reencode(out / "images")
    registered = {p.name: p for p in (out / "images").iterdir()}
    for r in rows:
        r["registered"] = r["name"] in registered
        if r["registered"]:
            with Image.open(registered[r["name"]]) as im:
                r["undistorted_size"] = list(im.size)
    for rel in LEFT_BEHIND:
        p = out / rel
        shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True)
    summary["model_sha256"] = model_digest(out)
    (out / "sources.json").write_text(json.dumps(rows, indent=1) + "\n")
    (out / "README.md").write_text(scene_readme(coll, rows, summary))
    return {**summary, "sources": rows}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="benchmarks collections", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="the collections: name, source, photos")
    b = sub.add_parser("build", help="fetch a collection's photos, resize them, run willags-process")
    b.add_argument("name", help=f"one of {', '.join(COLLECTIONS)}")
    b.add_argument("--out", type=Path, required=True, help="scene folder to write (outside any git tree)")
    b.add_argument("--source", type=Path, default=None, help="local clone, bare mirror or copy of the repository")
    b.add_argument(
        "--num-threads", type=int, default=NUM_THREADS,
        help=f"willags-process's CPU threads (default {NUM_THREADS}: the same SfM model on every build)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    try:
        if args.cmd == "list":
            for c in COLLECTIONS.values():
                n = f"{len(c.photos)} photos" if c.photos else "every photo"
                print(f"{c.name:<16} {c.repo} @ {c.commit[:8]}  {c.folder}  ({n})")
            return 0
        res = build(collection(args.name), args.out, args.source, args.num_threads)
    except CollectionError as e:
        print(f"benchmarks collections: {e}", file=sys.stderr)
        return 1
    reg = sum(r["registered"] for r in res["sources"])
    print(
        f"{args.name}: {reg} / {len(res['sources'])} registered, mean reprojection error "
        f"{res['mean_reprojection_error_px']:.3f} px, {res['wall_s']:.0f} s, {tree_bytes(args.out) / 1e6:.1f} MB in {args.out}"
    )
    print(pin_verdict(collection(args.name), res["model_sha256"]))
    return 0
