"""Cross-validated evaluation: every registered photo of a collection is a test photo once.

A collection's test split holds 2 to 16 photos, so a method's score on it moves by up to half a decibel between runs
and a difference between two methods is mostly which photos happened to be tested. Here the registered photos are
dealt into K folds (sorted by name, photo i into fold i mod K); fold k trains on the other folds and is scored under
the unchanged NeRF-W protocol on its own photos. Each photo then has one score per method, from the one run that did
not train on it, and two methods are compared photo by photo: the mean of the paired differences with a 95 % interval
from a bootstrap over the photos.

A fold is a scene folder of its own, ``<scene>-cv<k>of<K>``: links to the collection's images, COLMAP model and
evaluation-only files, and a NeRF-W split file naming the fold's test photos. Every method reads its splits through
willags' data parser (the peer too: benchmarks/peer.py), so a fold is a scene to every tool: the GPU queues
(benchmarks/remote/solo.sh), long_run's records (its `scene` names the fold) and the region maps.

    python -m benchmarks cv folds --data ../shared/data/reichstag --folds 4 --out .gpu-cv   # the fold folders
    python -m benchmarks cv bundle --data ../shared/data/reichstag ../shared/data/sacre-coeur-mini --folds 4 7 \
        --out .gpu-xb                              # copies of the collections and their folds: one folder to carry
    python -m benchmarks cv plan --root .gpu-cv --methods willags peer --steps 5000 --queues 12  # solo.sh queues
    python -m benchmarks merge <records.json>       # fold runs go to benchmarks/records/cv.json
    python -m benchmarks cv report                  # the tables from benchmarks/records/cv.json
    python -m benchmarks cv bar --rule willags-prior-low-captransients --low willags --high willags-prior-low-cap1m \
        --bars 0.01 0.02 0.03                       # a rule's score at other bars, from its runs' measured shares
    python -m benchmarks cv readout --variant resmean --steps 15000   # the same runs under a variant vs their own
    python -m benchmarks cv photos --scene reichstag --a willags@15000 --b willags@5000 --inspect insp.json
                                                    # photo by photo: the ends, and r with the inspector's evidence
    python -m benchmarks cv photos --scene reichstag --a willags-prior-low-meanslr --b willags \
        --with willags-prior-low-mask-late willags  # and r with another pair's: two changes, the same photos?

The tables are docs/results.md's cross-validated section (benchmarks/results.py calls :func:`cv_rows`).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import shutil
import stat
import sys
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.records import tree_bytes

FOLD_RE = re.compile(r"^(?P<scene>.+)-cv(?P<fold>\d+)of(?P<folds>\d+)$")
"""A fold's scene name: <scene>-cv<k>of<K>, k counted from 1."""
NOT_LINKED = {"README.md", "sources.json", "split.json"}
"""Entries of a collection a fold does not link (its split files are replaced by the fold's own)."""
BOOTSTRAP_SAMPLES = 10000
"""Resamples of the photos behind each interval."""
BOOTSTRAP_SEED = 0
"""The bootstrap's generator seed: a table regenerates byte for byte."""


def fold_name(scene: str, fold: int, folds: int) -> str:
    return f"{scene}-cv{fold}of{folds}"


def parse_fold(name: str) -> tuple[str, int, int] | None:
    """(scene, k, K) of a fold's scene name, None for any other scene."""
    m = FOLD_RE.match(name)
    if m is None:
        return None
    fold, folds = int(m["fold"]), int(m["folds"])
    return (m["scene"], fold, folds) if 1 <= fold <= folds else None


def registered_photos(scene_dir: Path) -> list[str]:
    """The photos a fold can test: the COLMAP model's images whose file is in `images/`, sorted by name."""
    from willags_ns.data.colmap import find_colmap_model
    from willags_ns.data.sfm_tracks import read_observations

    model = find_colmap_model(scene_dir)
    if model is None:
        raise SystemExit(f"cv: {scene_dir} holds no COLMAP model (colmap/sparse/0, sparse/0, ...)")
    names = sorted(n for n in read_observations(model) if (scene_dir / "images" / n).is_file())
    if not names:
        raise SystemExit(f"cv: no image of the COLMAP model in {scene_dir} is in {scene_dir / 'images'}")
    return names


def assign_folds(names: Sequence[str], folds: int) -> dict[str, int]:
    """Photo -> fold (1..folds): sorted by name, photo i into fold i mod folds + 1 (every fold within one photo of
    the others' size; neighbours by name, often taken together, are spread over the folds)."""
    if folds < 2:
        raise ValueError(f"cv: at least 2 folds, got {folds}")
    if len(names) < folds:
        raise ValueError(f"cv: {len(names)} photos cannot fill {folds} folds")
    return {name: i % folds + 1 for i, name in enumerate(sorted(names))}


def write_fold_scenes(scene_dir: Path, folds: int, out: Path) -> list[Path]:
    """The K fold folders of the collection at `scene_dir` under `out`: relative links to its entries (images, the
    COLMAP model, evaluation-only files; not its own split files) and `<fold name>.tsv` with the fold's photos as
    test and the rest as train. Relative links keep a collection and its folds movable together (a GPU bundle)."""
    scene_dir = Path(scene_dir)
    assignment = assign_folds(registered_photos(scene_dir), folds)
    written = []
    for k in range(1, folds + 1):
        d = Path(out) / fold_name(scene_dir.name, k, folds)
        d.mkdir(parents=True, exist_ok=True)
        for entry in sorted(scene_dir.iterdir()):
            if entry.name in NOT_LINKED or entry.suffix == ".tsv" or entry.name.startswith("."):
                continue
            link = d / entry.name
            if link.is_symlink() or link.exists():
                link.unlink()
            link.symlink_to(os.path.relpath(entry.resolve(), d.resolve()))
        with open(d / f"{d.name}.tsv", "w", newline="") as f:
            w = csv.writer(f, delimiter="\t", lineterminator="\n")
            w.writerow(["filename", "id", "split", "dataset"])
            for i, (name, fold) in enumerate(sorted(assignment.items())):
                w.writerow([name, i + 1, "test" if fold == k else "train", scene_dir.name])
        written.append(d)
    return written


CARRY_LIMIT = 64 * 2**20
"""What one call to the lent GPU machine carries, the tracked tree included (the device tool's limit)."""


def write_bundle(collections: Sequence[Path], folds: Sequence[int], out: Path) -> list[Path]:
    """A folder to carry to a GPU machine: a copy of each collection (writable, its own split files kept) and its
    fold folders beside it (:func:`write_fold_scenes`, links relative to the copy). A collection already copied
    there is kept. Returns every scene folder written, the copies first."""
    if len(folds) not in (1, len(collections)):
        raise ValueError(f"cv: {len(folds)} fold counts for {len(collections)} collections (one, or one each)")
    counts = folds if len(folds) == len(collections) else [folds[0]] * len(collections)
    out = Path(out)
    written = []
    for scene_dir, k in zip(collections, counts, strict=True):
        scene_dir = Path(scene_dir)
        if not scene_dir.is_dir():
            raise ValueError(f"cv: no collection at {scene_dir}")
        copy = out / scene_dir.name
        if not copy.is_dir():
            shutil.copytree(scene_dir, copy, copy_function=shutil.copyfile)
            for d in (copy, *(q for q in copy.rglob("*") if q.is_dir())):  # a read-only source's folders stay editable
                d.chmod(d.stat().st_mode | stat.S_IWUSR)
        written += [copy, *write_fold_scenes(copy, k, out)]
    return written


def pin_lines(collections: Sequence[Path]) -> list[str]:
    """For each collection folder named as one of benchmarks/collections.py's: whether its SfM model is the one that
    collection pins (a bundle of another build would start its runs from another scene); other folders: nothing."""
    from benchmarks.collections import COLLECTIONS, CollectionError, model_digest, pin_verdict

    lines = []
    for scene_dir in map(Path, collections):
        coll = COLLECTIONS.get(scene_dir.name)
        if coll is None:
            continue
        try:
            lines.append(f"cv: {pin_verdict(coll, model_digest(scene_dir))}")
        except CollectionError as e:
            lines.append(f"cv: {e}")
    return lines


# --------------------------------------------------------------------------------------------------------------------
# the plan: the GPU queues of a cross-validation


@dataclass(frozen=True)
class PlannedRun:
    scene: str
    method: str
    steps: int
    seed: int
    cost: float
    priority: int

    def spec(self) -> str:
        """solo.sh's run spec: scene:method:steps:seed."""
        return f"{self.scene}:{self.method}:{self.steps}:{self.seed}"


RUN_COST = {"peer-full": 1.6}
"""Training cost of a method relative to the default's (the full peer trained ~1.5x as long on a shared GPU:
docs/design.md); unnamed methods count 1."""
PHOTO_COST = 0.03
"""Cost of scoring one test photo (128 Adam steps of the protocol) relative to a 5000-step training run."""


def plan_runs(
    test_photos: dict[str, int], methods: Sequence[str], steps: int, seeds: Sequence[int] = (42,)
) -> list[PlannedRun]:
    """Every (scene, method, seed) run with its estimated cost; `test_photos`: scene -> its test photos. Priority:
    the order of `methods`, where "a,b" is one group of equal priority (the first ones are compared first, so a lease
    that ends early leaves complete pairs)."""
    runs = []
    for p, group in enumerate(methods):
        for method, (scene, n_test) in ((m, sc) for sc in sorted(test_photos.items()) for m in group.split(",")):
            for seed in seeds:
                cost = RUN_COST.get(method, 1.0) * steps / 5000 + PHOTO_COST * n_test
                runs.append(PlannedRun(scene, method, steps, seed, cost, p))
    return runs


def balance(runs: Sequence[PlannedRun], queues: int) -> list[list[PlannedRun]]:
    """Runs dealt into `queues` queues: by priority, then longest first, each to the least loaded queue; a queue runs
    its runs in that order."""
    load = [0.0] * queues
    out: list[list[PlannedRun]] = [[] for _ in range(queues)]
    for r in sorted(runs, key=lambda r: (r.priority, -r.cost, r.scene, r.method)):
        q = min(range(queues), key=lambda i: (load[i], i))
        out[q].append(r)
        load[q] += r.cost
    return [q for q in out if q]


def test_photo_counts(root: Path) -> dict[str, int]:
    """Scene folder name -> test photos of its split file, for every scene folder under `root` with one *.tsv."""
    from willags_ns.data.dataparser import read_split_tsv

    counts = {}
    for d in sorted(p for p in Path(root).iterdir() if p.is_dir()):
        tsvs = sorted(d.glob("*.tsv"))
        if len(tsvs) == 1:
            counts[d.name] = sum(s == "test" for s in read_split_tsv(tsvs[0]).values())
    return counts


# --------------------------------------------------------------------------------------------------------------------
# the analysis: per-photo scores, fold means, paired differences with intervals


def bootstrap_interval(diffs: Sequence[float], samples: int = BOOTSTRAP_SAMPLES, seed: int = BOOTSTRAP_SEED):
    """(mean, low, high): the mean of `diffs` and the 2.5th and 97.5th percentiles of the means of `samples`
    resamples of them with replacement (the percentile bootstrap)."""
    d = np.asarray(diffs, dtype=np.float64)
    if d.size == 0:
        raise ValueError("cv: no paired photo to compare")
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, d.size, size=(samples, d.size))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return float(d.mean()), float(low), float(high)


@dataclass
class MethodCV:
    """One method's cross-validation of one collection."""

    folds: int
    per_photo: dict[str, float]
    """Photo -> right-half PSNR from the run that held it out (mean over seeds where several ran)."""
    fold_means: dict[int, float]
    """Fold -> mean over its photos."""
    runs: int
    borrowed: tuple[int, ...] = ()
    """The folds whose scores are another method's runs of the same model (BORROWS), not the method's own."""

    @property
    def seeds(self) -> float:
        """Runs per fold (seeds): what the run noise of its mean is divided by."""
        return self.runs / max(len(self.fold_means), 1)

    @property
    def complete(self) -> bool:
        return len(self.fold_means) == self.folds

    @property
    def mean(self) -> float:
        return float(np.mean(list(self.per_photo.values())))


def _complete(by_method: dict[str, MethodCV], *methods: str) -> bool:
    """Whether every one of `methods` has every fold in `by_method` (one collection's MethodCVs)."""
    return all(m in by_method and by_method[m].complete for m in methods)


def milestone(rec: dict[str, Any], steps: int) -> dict[str, Any] | None:
    """A record's scores at `steps` (its milestone, or the record itself when it ran exactly that long)."""
    ms = (rec.get("milestones") or {}).get(str(steps))
    if ms is not None:
        return ms
    return rec if int(rec.get("steps", -1)) == steps and rec.get("per_image") else None


def variant_milestone(rec: dict[str, Any], steps: int, variant: str) -> dict[str, Any] | None:
    """A record's scores at `steps` under the protocol variant `variant` (`long_run eval --variant`), if scored."""
    return ((rec.get("protocol_variants") or {}).get(variant) or {}).get(str(steps))


def fold_runs(
    records: Sequence[dict[str, Any]], steps: int, tags: Sequence[str] | None = None, variant: str | None = None
):
    """(fold as parse_fold gives it, record, its scores at `steps`) of every fold run that ended well and was scored
    there: `tags`, only records whose tag starts with one of these; `variant`, the scores under that protocol variant
    instead of the protocol's own."""
    for rec in records:
        fold = parse_fold(str(rec.get("scene", "")))
        if fold is None or rec.get("status", "ok") != "ok":
            continue
        if tags is not None and not any(str(rec.get("tag") or "").startswith(t) for t in tags):
            continue
        ms = milestone(rec, steps) if variant is None else variant_milestone(rec, steps, variant)
        if ms is not None:
            yield fold, rec, ms


_MASK_OFF = ("mask_status", "mask_started")
"""A run whose record has neither field had the inspector's mask off: no mask scored (mask_status), and no start rule
measured (mask_started: the start rule measures only where the inspector turned the mask on, and keeps it off or
starts it then)."""

BORROWS: dict[str, tuple[str, tuple[str, ...], str]] = {
    "willags-prior-low-nomask": (
        "willags",
        _MASK_OFF,
        "the inspector kept the default's mask off there: the same model",
    ),
    "willags-prior-low-maskres": (
        "willags",
        _MASK_OFF,
        "the inspector kept the default's mask off there, so the mask's distance changes nothing: the same model",
    ),
    "willags-earlymask": (
        "willags",
        _MASK_OFF,
        "the inspector kept the mask off there, so when and whether it starts changes nothing: the same model",
    ),
    "willags-startrule-cap1m": (
        "willags-prior-low-cap1m",
        _MASK_OFF,
        "the inspector kept the mask off there, so when and whether it starts changes nothing: the same model",
    ),
    "willags-prior-low-mask5k": (
        "willags",
        _MASK_OFF,
        "the inspector kept the default's mask off there, so when the mask starts changes nothing: the same model",
    ),
}
"""Candidates that train another method's model wherever that method's run shows a switch off: candidate ->
(the method, the record fields whose absence shows the switch off, why the model is the same). On a fold the
candidate has no run of its own it takes that method's runs that lack every one of the fields, so a candidate that differs only
where the inspector turned a switch on runs only there and still counts on every collection (its difference there is
none, as the model is the same). Taken runs are never replicates (`replicate_differences` reads the records)."""


@dataclass
class FoldScores:
    """One method's fold runs of one collection, photo by photo, before runs are averaged (MethodCV)."""

    folds: int
    by_fold: dict[int, dict[str, list[float]]]
    """Fold -> photo -> right-half PSNR of each run of that fold."""
    runs: dict[int, int]
    """Fold -> how many runs scored it."""
    borrowed: tuple[int, ...] = ()
    """The folds whose runs are BORROWS' (another method's runs of the same model)."""

    def cv(self) -> MethodCV:
        """The method's MethodCV: its runs averaged photo by photo (method_cv)."""
        cv = method_cv(self.by_fold, self.folds, sum(self.runs.values()))
        cv.borrowed = self.borrowed
        return cv


def fold_scores(
    records: Sequence[dict[str, Any]],
    steps: int,
    tags: Sequence[str] | None = None,
    variant: str | None = None,
    borrowers: Sequence[str] | None = None,
) -> dict[str, dict[str, FoldScores]]:
    """{scene: {method: FoldScores}} of the fold runs scored at `steps` (records with per-photo scores; `tags`: only
    records whose tag starts with one of these; `variant`: their scores under that protocol variant instead of the
    protocol's own); one fold count per scene and method, the finer split where runs used two. `borrowers`: the
    BORROWS candidates that take runs (default: those with a run of their own among `records`)."""
    from benchmarks.methods import configuration

    if borrowers is None:
        borrowers = sorted({configuration(r) for r in records} & set(BORROWS))

    photos: dict[tuple[str, int, str], dict[int, dict[str, list[float]]]] = defaultdict(lambda: defaultdict(dict))
    runs: dict[tuple[str, int, str], dict[int, int]] = defaultdict(lambda: defaultdict(int))
    lent: dict[tuple[str, int, str], dict[int, list[list[tuple[str, float]]]]] = defaultdict(lambda: defaultdict(list))
    for fold, rec, ms in fold_runs(records, steps, tags, variant):
        if not ms.get("per_image"):
            continue
        scene, k, folds = fold
        method = configuration(rec)
        scores = [(p["image"], float(p["psnr"])) for p in ms["per_image"]]
        runs[(scene, folds, method)][k] += 1
        for name, psnr in scores:
            photos[(scene, folds, method)][k].setdefault(name, []).append(psnr)
        for borrower in borrowers:
            lender, fields, _ = BORROWS[borrower]
            if method == lender and not any(f in rec for f in fields):
                lent[(scene, folds, borrower)][k].append(scores)
    taken: dict[tuple[str, int, str], list[int]] = defaultdict(list)
    for key, by_fold in lent.items():
        for k, run_scores in sorted(by_fold.items()):
            if k in photos.get(key, {}):  # the candidate ran this fold itself
                continue
            for scores in run_scores:
                runs[key][k] += 1
                for name, psnr in scores:
                    photos[key][k].setdefault(name, []).append(psnr)
            taken[key].append(k)
    out: dict[str, dict[str, FoldScores]] = defaultdict(dict)
    for (scene, folds, method), by_fold in sorted(photos.items()):
        prev = out[scene].get(method)
        if prev is None or folds > prev.folds:
            key = (scene, folds, method)
            out[scene][method] = FoldScores(folds, dict(by_fold), dict(runs[key]), tuple(taken.get(key, ())))
    return dict(out)


def collect(
    records: Sequence[dict[str, Any]],
    steps: int,
    tags: Sequence[str] | None = None,
    variant: str | None = None,
    borrowers: Sequence[str] | None = None,
):
    """{scene: {method: MethodCV}} from the fold runs scored at `steps` (fold_scores, runs averaged photo by
    photo)."""
    return {
        scene: {m: f.cv() for m, f in by_method.items()}
        for scene, by_method in fold_scores(records, steps, tags, variant, borrowers).items()
    }


def method_cv(by_fold: dict[int, dict[str, list[float]]], folds: int, runs: int) -> MethodCV:
    """A method's MethodCV from its scores {fold: {photo: [PSNR of each run]}}: runs averaged photo by photo."""
    per_photo = {name: float(np.mean(v)) for fold in by_fold.values() for name, v in fold.items()}
    fold_means = {k: float(np.mean([np.mean(v) for v in fold.values()])) for k, fold in sorted(by_fold.items())}
    return MethodCV(folds, per_photo, fold_means, runs)


EQUIVALENT = {
    ("willags-capscene", "willags-noprior"): "MCMC's cap not reached on any fold: the same model",
    ("willags-prior-low-captransients", "willags"): "the transients rule kept the cap on every fold: the same model",
    ("willags-prior-low-captransients25", "willags"): "the transients rule kept the cap on every fold: the same model",
}
"""Method pairs that train the same model where their runs end with the same number of Gaussians on every fold (the
pair's runs then differ only by the GPU's non-deterministic sums): replicates for the run noise."""


def _runs(records: Sequence[dict[str, Any]], steps: int):
    """{(scene, folds, build, configuration, seed): {fold: (per-photo PSNR, Gaussians)}} of the fold runs scored at
    `steps` (build: build_key's; runs on two builds of a collection are not replicates of one another)."""
    from benchmarks.methods import configuration

    build = build_key(records)
    out: dict[tuple[str, int, str, str, int], dict[int, tuple[dict[str, float], Any]]] = defaultdict(dict)
    for fold, rec, ms in fold_runs(records, steps):
        if not ms.get("per_image"):
            continue
        scene, k, folds = fold
        scores = {p["image"]: float(p["psnr"]) for p in ms["per_image"]}
        key = (scene, folds, build(rec), configuration(rec), int(rec.get("seed") or 42))
        out[key][k] = (scores, ms.get("num_gaussians"))
    return out


def replicate_differences(records: Sequence[dict[str, Any]], steps: int) -> list[tuple[str, str, float]]:
    """(scene, what, D): D is the difference of the cross-validated means of two runs of one model over every fold
    (the photos both scored): the same configuration at two seeds, or an EQUIVALENT pair at one seed whose runs ended
    with equal Gaussian counts on every fold. Only complete cross-validations count."""
    runs = {k: v for k, v in _runs(records, steps).items() if len(v) == k[1]}

    def d(a, b) -> float:
        pairs = [(a[k][0][p], b[k][0][p]) for k in a for p in a[k][0] if p in b[k][0]]
        return float(np.mean([x - y for x, y in pairs]))

    out = []
    keys = sorted(runs)
    for i, ka in enumerate(keys):
        for kb in keys[i + 1 :]:
            same_scene = ka[:3] == kb[:3]  # one collection, one fold count, one build
            if same_scene and ka[3] == kb[3]:
                out.append((ka[0], f"{ka[3]} seeds {kb[4]} - {ka[4]}", d(runs[kb], runs[ka])))
            elif same_scene and ka[4] == kb[4]:
                for (x, y), _ in EQUIVALENT.items():
                    a, b = {ka[3]: runs[ka], kb[3]: runs[kb]}.get(x), {ka[3]: runs[ka], kb[3]: runs[kb]}.get(y)
                    if a is None or b is None or a is b:
                        continue
                    if all(a[k][1] is not None and a[k][1] == b[k][1] for k in a):
                        out.append((ka[0], f"{x} - {y} (seed {ka[4]}, equal Gaussians)", d(a, b)))
    return out


def run_noise(records: Sequence[dict[str, Any]], steps: int) -> tuple[float | None, int]:
    """(sigma, pairs): the standard deviation of one run's cross-validated mean about its model's, from the
    replicate pairs (sigma^2 = mean of D^2 / 2), and how many pairs it rests on; (None, 0) without any. The photo
    bootstrap cannot see it: every photo of a fold shares that fold's run."""
    diffs = [x for _, _, x in replicate_differences(records, steps)]
    if not diffs:
        return None, 0
    return float(np.sqrt(np.mean(np.square(diffs)) / 2)), len(diffs)


def widened(mean: float, low: float, high: float, extra: float) -> tuple[float, float]:
    """(low, high) of an interval about `mean`, each side widened in quadrature by `extra` (the run noise)."""
    return mean - float(np.hypot(mean - low, extra)), mean + float(np.hypot(high - mean, extra))


def paired(a: MethodCV, b: MethodCV, sigma: float | None = None) -> tuple[float, float, float, int]:
    """(mean, low, high, photos) of a - b over the photos both scored: bootstrap_interval's, each side widened in
    quadrature by the run noise 1.96 sigma sqrt(1/seeds_a + 1/seeds_b) when `sigma` (run_noise) is known."""
    common = sorted(set(a.per_photo) & set(b.per_photo))
    mean, low, high = bootstrap_interval([a.per_photo[p] - b.per_photo[p] for p in common])
    if sigma:
        extra = 1.96 * sigma * float(np.sqrt(1 / a.seeds + 1 / b.seeds))
        low, high = widened(mean, low, high, extra)
    return mean, low, high, len(common)


def pooled(pairs: Sequence[tuple[MethodCV, MethodCV]], sigma: float | None = None) -> tuple[float, float, float, int]:
    """(mean, low, high, photos) of a - b over several collections at once, each `(a, b)` pair one collection and
    every collection weighing the same (a 128-photo collection does not outvote a 14-photo one): the mean of the
    collections' paired means, its 95 % interval from a bootstrap that resamples the photos within each collection,
    widened in quadrature by the run noise of that mean, 1.96 sigma sqrt(sum (1/seeds_a + 1/seeds_b)) / collections.
    """
    if not pairs:
        raise ValueError("cv: no collection to pool")
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    means, boots, var, photos = [], np.zeros(BOOTSTRAP_SAMPLES), 0.0, 0
    for a, b in pairs:
        common = sorted(set(a.per_photo) & set(b.per_photo))
        if not common:
            raise ValueError("cv: a pooled collection has no photo both methods scored")
        d = np.asarray([a.per_photo[p] - b.per_photo[p] for p in common], dtype=np.float64)
        means.append(d.mean())
        boots += d[rng.integers(0, d.size, size=(BOOTSTRAP_SAMPLES, d.size))].mean(axis=1)
        var += 1 / a.seeds + 1 / b.seeds
        photos += d.size
    n = len(pairs)
    mean = float(np.mean(means))
    low, high = (float(x) for x in np.percentile(boots / n, [2.5, 97.5]))
    if sigma:
        extra = 1.96 * sigma * float(np.sqrt(var)) / n
        low, high = widened(mean, low, high, extra)
    return mean, low, high, photos


def verdict(low: float, high: float) -> str:
    """What an interval of a difference says: above 0, below 0, or no change (a change inside it is none)."""
    return "better" if low > 0 else "worse" if high < 0 else "no change"


def _cell(cv: MethodCV | None, fold_means: bool = True) -> str:
    """The mean over every photo, then (`fold_means`) the mean of each fold; a note where folds are missing."""
    if cv is None:
        return "–"
    folds = " / ".join(f"{cv.fold_means[k]:.2f}" for k in sorted(cv.fold_means)) if fold_means else ""
    note = "" if cv.complete else f"{len(cv.fold_means)} of {cv.folds} folds"
    inside = "; ".join(x for x in (folds, note) if x)
    return f"{cv.mean:.2f} ({inside})" if inside else f"{cv.mean:.2f}"


def _diff(a: MethodCV | None, b: MethodCV | None, sigma: float | None = None) -> str:
    if a is None or b is None or not (set(a.per_photo) & set(b.per_photo)):
        return "–"
    mean, low, high, n = paired(a, b, sigma)
    return f"{mean:+.2f} [{low:+.2f}, {high:+.2f}] (n={n})"


GOAL_DB = 1.0
"""The goal: the default this much above the stronger peer by the cross-validated mean ..."""
GOAL_LOW_DB = 0.5
"""... with the 95 % interval of the difference above this."""


def goal_cell(a: MethodCV | None, b: MethodCV | None, sigma: float | None = None) -> str:
    """Whether `a` (the default) meets the goal against `b` (the stronger peer), or by how much it misses."""
    if a is None or b is None or not (a.complete and b.complete):
        return "–"
    mean, low, _, _ = paired(a, b, sigma)
    if mean >= GOAL_DB and low > GOAL_LOW_DB:
        return "met"
    return f"missed by {max(GOAL_DB - mean, GOAL_LOW_DB - low, 0.0):.2f}"


def stronger_peer(by_method: dict[str, MethodCV]) -> str | None:
    """The peer with the higher cross-validated mean among those with every fold scored (where neither has: among
    those with some, so a partial table still pairs the photos there are)."""
    peers = [m for m in ("peer", "peer-full") if m in by_method]
    complete = [m for m in peers if by_method[m].complete]
    return max(complete or peers, key=lambda m: by_method[m].mean) if peers else None


def compared_variants(records: Sequence[dict[str, Any]], steps: int, default: str = "willags") -> list[str]:
    """The protocol variants under which, on some collection, both the default and a peer have every fold scored at
    `steps`: the ones a table can compare the methods under."""
    names = sorted(
        {
            name
            for r in records
            if parse_fold(str(r.get("scene", ""))) is not None
            for name in (r.get("protocol_variants") or {})
        }
    )
    out = []
    for name in names:
        for by_method in collect(records, steps, variant=name).values():
            peer = stronger_peer(by_method)
            if peer and _complete(by_method, default, peer):
                out.append(name)
                break
    return out


def headline_table(
    by_scene: dict[str, dict[str, MethodCV]],
    sigma: float | None,
    steps: int,
    default: str = "willags",
    fold_means: bool = True,
) -> list[str]:
    """The markdown table of the collections: per collection its folds and photos, both peers' and the default's
    means (and, with `fold_means`, each fold's), the default against the stronger peer with its interval, and the
    goal."""
    from benchmarks.tables import md_table

    rows = []
    for scene, by_method in sorted(by_scene.items()):
        ref = by_method.get(default)
        peer_name = stronger_peer(by_method)
        peer = by_method.get(peer_name) if peer_name else None
        if ref is None and peer is None:  # only candidates scored here: nothing to set them against
            continue
        rows.append(
            [
                scene,
                f"{steps // 1000}k" if steps % 1000 == 0 else str(steps),
                str(max(cv.folds for cv in by_method.values())),
                str(max(len(cv.per_photo) for cv in by_method.values())),
                _cell(by_method.get("peer"), fold_means),
                _cell(by_method.get("peer-full"), fold_means),
                _cell(ref, fold_means),
                (f"{peer_name}: " if peer_name else "") + _diff(ref, peer, sigma),
                goal_cell(ref, peer, sigma),
            ]
        )
    head = [
        "scene",
        "steps",
        "folds",
        "photos",
        "peer",
        "peer-full",
        f"**{default}**",
        f"{default} − stronger peer [95 % CI] (photos)",
        f"goal (+{GOAL_DB:g} dB, CI above +{GOAL_LOW_DB:g})",
    ]
    return md_table(head, rows)


def cv_headline(records: Sequence[dict[str, Any]], steps: int, default: str = "willags") -> list[str]:
    """headline_table of the fold runs scored at `steps`, with the run noise of those runs, without the fold means,
    then the default against the light peer over every collection where both have every fold at once (README's
    table and the sentence under it)."""
    sigma, _ = run_noise(records, steps)
    by_scene = collect(records, steps)
    out = headline_table(by_scene, sigma, steps, default, fold_means=False)
    both = [(by[default], by["peer"]) for _, by in sorted(by_scene.items()) if _complete(by, default, "peer")]
    if len(both) >= 2:
        mean, low, high, n = pooled(both, sigma)
        at_once = f"{default} − peer {mean:+.2f} dB [{low:+.2f}, {high:+.2f}] ({n} photos)"
        out += ["", f"Over the {len(both)} collections at once: {at_once}."]
    return out


UNRECORDED = "not named"
"""scene_models' key for the runs whose records name no SfM model."""


def build_of(rec: dict[str, Any]) -> str:
    """The SfM model a record's run started from (its digest), UNRECORDED where the record names none."""
    return str(rec.get("scene_model_sha256") or UNRECORDED)


def build_key(records: Sequence[dict[str, Any]]) -> Callable[[dict[str, Any]], str]:
    """The build a record's run started from, read against every record: its digest where it names one; for a run
    that names none, on a collection nobody rebuilds (not in benchmarks.collections.COLLECTIONS: a fixed folder of
    data, one scene for every run) whose named runs all name one digest, that digest; otherwise UNRECORDED (a
    rebuilt collection's older runs may have started from any build)."""
    from benchmarks.collections import COLLECTIONS

    named: dict[str, set[str]] = defaultdict(set)
    for rec in records:
        fold = parse_fold(str(rec.get("scene", "")))
        if fold is not None and rec.get("scene_model_sha256"):
            named[fold[0]].add(build_of(rec))

    def key(rec: dict[str, Any]) -> str:
        fold = parse_fold(str(rec.get("scene", "")))
        if rec.get("scene_model_sha256") or fold is None or fold[0] in COLLECTIONS or len(named[fold[0]]) != 1:
            return build_of(rec)
        (only,) = named[fold[0]]
        return only

    return key


def method_builds(
    records: Sequence[dict[str, Any]],
    steps: int,
    tags=None,
    variant: str | None = None,
    key: Callable[[dict[str, Any]], str] | None = None,
) -> dict[tuple[str, str], set[str]]:
    """{(collection, method): the builds (`key`, build_key's of `records` when None) its fold runs scored at `steps`
    started from}."""
    from benchmarks.methods import configuration

    key = key or build_key(records)
    builds: dict[tuple[str, str], set[str]] = defaultdict(set)
    for (scene, _, _), rec, _ms in fold_runs(records, steps, tags, variant):
        builds[(scene, configuration(rec))].add(key(rec))
    return dict(builds)


def scene_models(
    records: Sequence[dict[str, Any]], steps: int, tags=None, key: Callable[[dict[str, Any]], str] | None = None
) -> dict[str, dict[str, set[str]]]:
    """{collection: {SfM model digest: methods}} of the fold runs scored at `steps` whose records name the model their
    scene held (`scene_model_sha256`, long_run.record). On a rebuilt collection where some record names one, the runs
    whose records name none are listed under UNRECORDED: a build that may be any (runs of a collection rebuilt with
    more than one thread start from another scene each time); on a fixed collection they join its one named build
    (build_key, or `key`); where no record names one, the collection is left out."""
    out: dict[str, dict[str, set[str]]] = defaultdict(lambda: defaultdict(set))
    key = key or build_key(records)
    for (scene, _, _), rec, _ms in fold_runs(records, steps, tags):
        out[scene][key(rec)].add(str(rec.get("method")))
    return {scene: dict(models) for scene, models in out.items() if set(models) != {UNRECORDED}}


def model_lines(
    records: Sequence[dict[str, Any]], steps: int, tags=None, default: str = "willags", sigma: float | None = None
) -> list[str]:
    """A line for each collection whose fold runs started from more than one SfM model: a rebuild of the collection
    that is not the same scene (benchmarks/collections.py, NUM_THREADS), so its methods' differences there mix the
    models' with the methods'. For each named model on which the default and a peer have every fold, the default
    against the stronger peer on that model's runs alone (`sigma`: the run noise, as in the tables)."""
    lines = []
    key = build_key(records)
    for scene, models in sorted(scene_models(records, steps, tags, key).items()):
        if len(models) < 2:
            continue
        each = "; ".join(f"{d[:12]}: {', '.join(sorted(m))}" for d, m in sorted(models.items()))
        lines.append(f"- **{scene}**: the fold runs started from {len(models)} SfM models ({each}).")
        for digest in sorted(d for d in models if d != UNRECORDED):
            alone = [r for r in records if key(r) == digest]
            by_method = collect(alone, steps, tags).get(scene, {})
            ref, peer_name = by_method.get(default), stronger_peer(by_method)
            peer = by_method.get(peer_name) if peer_name else None
            if ref is None or peer is None or not (ref.complete and peer.complete):
                continue
            lines.append(
                f"  On {digest[:12]} alone (runs a fold: {default} {ref.seeds:g}, {peer_name} {peer.seeds:g}): "
                f"{default} {ref.mean:.2f}, {peer_name} {peer.mean:.2f}, {default} − {peer_name} "
                f"{_diff(ref, peer, sigma)}, goal {goal_cell(ref, peer, sigma)}."
            )
    return lines


def same_build_refs(
    records: Sequence[dict[str, Any]], steps: int, tags=None, variant: str | None = None, default: str = "willags"
) -> dict[tuple[str, str], tuple[MethodCV, str]]:
    """{(collection, method): (the default's MethodCV from its runs on the one build every fold run of that method
    there started from, that build: a digest or UNRECORDED)}, on the collections where the default's runs span
    builds (benchmarks/collections.py: a rebuilt collection is another scene unless it is the pinned one) and it has
    every fold on that build. A method is then set against the default on its own scene; a method whose runs span
    builds, or whose build the default lacks, against every run of the default, as elsewhere."""
    key_of = build_key(records)
    builds = method_builds(records, steps, tags, variant, key_of)
    spanned = {scene for (scene, m), b in builds.items() if m == default and len(b) > 1}
    by_build: dict[str, dict[str, dict[str, MethodCV]]] = {}
    out = {}
    for (scene, method), b in sorted(builds.items()):
        if method == default or scene not in spanned or len(b) != 1:
            continue
        (key,) = b
        if key not in by_build:
            by_build[key] = collect([r for r in records if key_of(r) == key], steps, tags, variant)
        ref = by_build[key].get(scene, {}).get(default)
        if ref is not None and ref.complete:
            out[(scene, method)] = (ref, key)
    return out


def cv_rows(
    records: Sequence[dict[str, Any]], steps: int, default: str = "willags", tags=None, variant: str | None = None
) -> list[str]:
    """The markdown tables of the cross-validated section: per collection the photos, each method's mean (fold
    means), the default against the stronger peer, then every other method against the default, and every method
    against the default over every collection at once. `variant`: each run's scores under that protocol variant
    (the run noise still the protocol's own)."""
    from benchmarks.tables import md_table

    by_scene = collect(records, steps, tags, variant)
    if not by_scene:
        return [f"No cross-validated run scored at {steps} steps yet."]
    sigma, pairs = run_noise(records, steps)
    refs = same_build_refs(records, steps, tags, variant, default)
    cand_rows = []
    for scene, by_method in sorted(by_scene.items()):
        ref = by_method.get(default)
        if ref is None and stronger_peer(by_method) is None:  # only candidates here: nothing to set them against
            continue
        for method, cv in sorted(by_method.items()):
            if method in (default, "peer", "peer-full"):
                continue
            own, key = refs.get((scene, method), (None, UNRECORDED))
            on = "that name no build" if key == UNRECORDED else f"on {key[:12]}"
            note = "" if own is None else f" (the default's runs {on})"
            if cv.borrowed:
                lender, _, why = BORROWS[method]
                folds = "/".join(str(k) for k in cv.borrowed)
                note += f" (folds {folds}: {lender}'s runs, {why})"
            cand_rows.append([scene, method, _cell(cv), _diff(cv, own or ref, sigma) + note])
    noise = (
        f"Run noise: sigma = {sigma:.2f} dB, the standard deviation of one run's cross-validated mean, from {pairs} "
        "replicate pair(s) (`cv.run_noise`); every interval below is the photo bootstrap's widened by it."
        if sigma is not None
        else "Run noise: no replicate pair yet; the intervals below are the photo bootstrap's alone and too narrow."
    )
    out = [noise, "", *headline_table(by_scene, sigma, steps, default)]
    mixed = model_lines(records, steps, tags, default, sigma)
    if mixed:
        out += [
            "",
            "Collections whose runs started from different builds of their scene (`cv.model_lines`):",
            "",
            *mixed,
        ]
    if cand_rows:
        out += ["", *md_table(["scene", "method", "mean (fold means)", f"− {default} [95 % CI] (photos)"], cand_rows)]
    pooled_rows = pooled_rows_of(by_scene, sigma, default, refs)
    if pooled_rows:
        out += [
            "",
            f"Every collection at once (each collection weighing the same; `cv.pooled`; a method with every fold of "
            f"only some of the collections where {default} has them is pooled over those, and its verdict waits for "
            f"the rest):",
            "",
            *md_table(["method", "collections", "photos", f"− {default} [95 % CI]", "verdict"], pooled_rows),
        ]
    switches = switch_rows(by_scene, sigma, default, method_builds(records, steps, tags, variant))
    if switches:
        head = ["method", "against", "the settings it adds", "collection", "method − against [95 % CI] (photos)",
                "verdict"]  # fmt: skip
        out += [
            "",
            "What a setting is worth: a method against the one whose settings it extends (`cv.switch_pairs`), on each "
            "collection where both have every fold, and at once over those. The settings are the methods' own: on a "
            "collection where the inspector already set one of them for the other method (the mask on "
            "sacre-coeur-mini), the pair differs by less than the column says:",
            "",
            *md_table(head, switches),
        ]
    fit_head, fits = capacity_rows(records, steps, tags)
    if fits and variant is None:
        out += [
            "",
            "What each method fits and keeps (`cv.capacity_rows`): the training photos' PSNR, each rendered with its own "
            'latent or embedding, and the Gaussians, means over the fold runs, "fit / thousands of Gaussians":',
            "",
            *md_table(fit_head, fits),
        ]
    return out


def capacity_rows(records: Sequence[dict[str, Any]], steps: int, tags=None) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of what each method fits and keeps at `steps`, from the fold runs' own records: per collection
    the mean over its runs of the training photos' PSNR (each rendered with its own latent or embedding,
    ``train_psnr``) and of the Gaussians at that step, "fit / thousands of Gaussians". A closer fit of the training
    photos is not a better score on new ones; the table shows where a method's capacity and fit differ. Only methods
    with at least one run that recorded both."""
    from benchmarks.methods import configuration

    vals: dict[tuple[str, str], list[tuple[float, float]]] = defaultdict(list)
    for fold, rec, ms in fold_runs(records, steps, tags):
        if ms.get("train_psnr") is None or ms.get("num_gaussians") is None:
            continue
        vals[(fold[0], configuration(rec))].append((float(ms["train_psnr"]), float(ms["num_gaussians"])))
    scenes = sorted({s for s, _ in vals})
    first = ("willags", "peer", "peer-full")  # the default and the peers first, then the candidates by name
    methods = sorted({m for _, m in vals}, key=lambda m: (first.index(m) if m in first else len(first), m))
    rows = []
    for m in methods:
        cells = []
        for sc in scenes:
            v = vals.get((sc, m))
            cells.append(
                "–" if not v else f"{np.mean([a for a, _ in v]):.1f} / {np.mean([g for _, g in v]) / 1e3:.0f}k"
            )
        rows.append([m, *cells])
    return ["method", *scenes], rows


def pooled_rows_of(
    by_scene: dict[str, dict[str, MethodCV]],
    sigma: float | None,
    default: str,
    refs: dict[tuple[str, str], tuple[MethodCV, str]] | None = None,
) -> list[list[str]]:
    """One row per method scored completely on at least two of the collections where `default` is complete: its
    pooled difference from the default over those collections and the verdict of that interval. A method missing
    some of them is pooled over the ones it has, its row naming how many and its verdict withheld: a default is
    decided on every collection at once. `refs` (same_build_refs): the default on a method's own build where it has
    one."""
    refs = refs or {}
    scenes = [s for s, by in sorted(by_scene.items()) if _complete(by, default)]
    if len(scenes) < 2:
        return []
    methods = sorted({m for s in scenes for m in by_scene[s]} - {default})
    out = []
    for m in methods:
        have = [s for s in scenes if _complete(by_scene[s], m)]
        if len(have) < 2:
            continue
        pairs = [(by_scene[s][m], refs[(s, m)][0] if (s, m) in refs else by_scene[s][default]) for s in have]
        mean, low, high, n = pooled(pairs, sigma)
        if len(have) == len(scenes):
            where, said = str(len(have)), verdict(low, high)
        else:
            where = f"{len(have)} of {len(scenes)} ({', '.join(have)})"
            said = f"none yet ({verdict(low, high)} on these)"
        taken = [s for s in have if len(by_scene[s][m].borrowed) == by_scene[s][m].folds]
        if taken:  # collections where it is the lender's model on every fold: a difference of none by construction
            where += f" ({len(taken)} wholly {BORROWS[m][0]}'s runs: cv.BORROWS)"
        out.append([m, where, str(n), f"{mean:+.2f} [{low:+.2f}, {high:+.2f}]", said])
    return out


def switch_pairs(methods: Sequence[str], default: str = "willags") -> list[tuple[str, str, list[str]]]:
    """(method, base, the settings it adds) for every two benchmarked methods where the one is the other with more
    settings (benchmarks.methods METHODS: the same base config, a strict superset of its overrides): what those
    settings are worth, measured as a pair. The default and the peers are left out (every method is set against the
    default already)."""
    from benchmarks.methods import METHODS

    names = sorted(m for m in set(methods) if m in METHODS and m != default and not m.startswith("peer"))
    out = []
    for b in names:
        for a in names:
            sa, sb = set(METHODS[a].overrides), set(METHODS[b].overrides)
            if a != b and METHODS[a].base == METHODS[b].base and sa < sb:
                out.append((b, a, [f"{k}={v}" for k, v in sorted(sb - sa, key=str)]))
    return out


def switch_rows(
    by_scene: dict[str, dict[str, MethodCV]],
    sigma: float | None,
    default: str,
    builds: dict[tuple[str, str], set[str]] | None = None,
) -> list[list[str]]:
    """Per pair of :func:`switch_pairs`, a row per collection where both have every fold, then, on two or more,
    the pair over those collections at once (:func:`pooled`) with its verdict. `builds` (method_builds): where each
    method's runs there all started from one build and the two builds differ, the row says so and stays out of the
    pooled row (two builds of a rebuilt collection are two scenes)."""
    methods = sorted({m for by in by_scene.values() for m in by})
    out = []
    for b, a, added in switch_pairs(methods, default):
        both = [s for s, by in sorted(by_scene.items()) if _complete(by, a, b)]
        scenes = []
        for s in both:
            ba, bb = (builds or {}).get((s, a), set()), (builds or {}).get((s, b), set())
            apart = len(ba) == 1 and len(bb) == 1 and ba != bb
            note = " (the two on different builds: left out of the pooled row)" if apart else ""
            out.append([b, a, ", ".join(added), s, _diff(by_scene[s][b], by_scene[s][a], sigma) + note, ""])
            if not apart:
                scenes.append(s)
        if len(scenes) >= 2:
            mean, low, high, n = pooled([(by_scene[s][b], by_scene[s][a]) for s in scenes], sigma)
            at_once = f"**{len(scenes)} at once**"
            out.append([b, a, ", ".join(added), at_once, f"{mean:+.2f} [{low:+.2f}, {high:+.2f}] (n={n})",
                        verdict(low, high)])  # fmt: skip
    return out


FIXED_SPLIT_STEPS = {"fox-clean": 5000, "fox-wild": 5000}
"""The synthetic scenes, scored on their own split (rendered: their test photos, transients and appearance changes are
known, so they are not dealt into folds), and the step count their runs are compared at."""


def scored_at(records: Sequence[dict[str, Any]], *steps: int) -> list[dict[str, Any]]:
    """The runs scored photo by photo at every one of `steps`: one run's checkpoints compared with each other."""
    return [r for r in records if all((milestone(r, n) or {}).get("per_image") for n in steps)]


def length_rows(records: Sequence[dict[str, Any]], short: int, long: int, default: str = "willags") -> list[str]:
    """What the steps from `short` to `long` are worth: per collection, each method whose fold runs were scored at
    both counts on every fold (only the runs scored at both: one run's two checkpoints), its mean at each and the
    paired difference long - short with the photo bootstrap's interval widened by the run noise at `long` (as
    `paired`: conservative, the two checkpoints of one run share most of its noise), then each method over the
    collections at once."""
    from benchmarks.tables import md_table

    both = scored_at(records, short, long)
    a, b = collect(both, short), collect(both, long)
    sigma, _ = run_noise(records, long)
    rows, pools = [], defaultdict(list)
    for scene in sorted(set(a) & set(b)):
        for method in sorted(set(a[scene]) & set(b[scene]), key=lambda m: (m != default, m)):
            lo, hi = a[scene][method], b[scene][method]
            if not (lo.complete and hi.complete):
                continue
            mean, low, high, n = paired(hi, lo, sigma)
            rows.append(
                [scene, method, f"{lo.mean:.2f}", f"{hi.mean:.2f}", f"{mean:+.2f} [{low:+.2f}, {high:+.2f}] (n={n})"]
            )
            pools[method].append((hi, lo))
    for method, pairs in sorted(pools.items(), key=lambda kv: (kv[0] != default, kv[0])):
        if len(pairs) >= 2:
            mean, low, high, n = pooled(pairs, sigma)
            rows.append([f"**{len(pairs)} at once**", method, "", "", f"{mean:+.2f} [{low:+.2f}, {high:+.2f}] (n={n})"])
    head = ["scene", "method", f"{short} steps", f"{long} steps", f"{long} − {short} [95 % CI] (photos)"]
    return md_table(head, rows) if rows else []


def parse_side(text: str, steps: int) -> tuple[str, int]:
    """A side of `cv photos`, METHOD or METHOD@STEPS -> (method, step count; `steps` where none is named)."""
    method, _, n = text.partition("@")
    if not method or (n and not n.isdigit()):
        raise ValueError(f"cv: {text!r} is not METHOD or METHOD@STEPS")
    return method, int(n) if n else steps


def photo_differences(
    records: Sequence[dict[str, Any]], scene: str, a: tuple[str, int], b: tuple[str, int]
) -> dict[str, float]:
    """Photo -> a's score minus b's on `scene`'s cross-validation, each side a (configuration, step count); where both
    sides are one method at two counts, only the runs scored at both (one run's two checkpoints, as `length_rows`)."""
    if a[0] == b[0]:
        records = scored_at(records, a[1], b[1])
    sides = []
    for method, n in (a, b):
        cv = collect(records, n).get(scene, {}).get(method)
        if cv is None:
            raise ValueError(f"cv: no fold run of {method} on {scene} scored at {n} steps")
        sides.append(cv.per_photo)
    return {p: sides[0][p] - sides[1][p] for p in sorted(set(sides[0]) & set(sides[1]))}


def evidence_correlations(diffs: dict[str, float], report: dict[str, Any]) -> dict[str, tuple[float, int]]:
    """Per-image array of a `willags-inspect --split all --output` report -> (Pearson r with the photos' differences,
    photos both hold); arrays that do not vary over those photos are left out."""
    per = report.get("per_image") or {}
    names = per.get("names") or []
    out = {}
    for key, values in per.items():
        if key == "names" or len(values) != len(names):
            continue
        pairs = [(float(v), diffs[n]) for n, v in zip(names, values, strict=True) if n in diffs and v is not None]
        if len(pairs) < 3:
            continue
        x, y = np.asarray(pairs).T
        if x.std() > 0 and y.std() > 0:
            out[key] = (float(np.corrcoef(x, y)[0, 1]), len(pairs))
    return out


def pair_correlation(diffs: dict[str, float], other: dict[str, float]) -> tuple[float, int] | None:
    """(Pearson r of two sets of photo differences over the photos both hold, those photos); None under 3 photos or
    where either does not vary. Do two changes gain on the same photos (one failure), or on others?"""
    common = sorted(set(diffs) & set(other))
    if len(common) < 3:
        return None
    x, y = np.array([diffs[p] for p in common]), np.array([other[p] for p in common])
    if x.std() == 0 or y.std() == 0:
        return None
    return float(np.corrcoef(x, y)[0, 1]), len(common)


def photo_lines(
    diffs: dict[str, float], top: int, correlations: dict[str, tuple[float, int]] | None = None
) -> list[str]:
    """What `cv photos` prints: the spread of the differences, the photos at each end, the correlations."""
    if not diffs:
        return ["cv: the two sides share no photo"]
    d = np.asarray(list(diffs.values()))
    order = sorted(diffs.items(), key=lambda kv: kv[1])
    lines = [
        f"{d.size} photos: mean {d.mean():+.2f}, median {np.median(d):+.2f}, below -1 dB {(d < -1).sum()}, "
        f"above +1 dB {(d > 1).sum()}",
        "lowest: " + ", ".join(f"{p} {v:+.2f}" for p, v in order[:top]),
        "highest: " + ", ".join(f"{p} {v:+.2f}" for p, v in reversed(order[-top:])),
    ]
    for key, (r, n) in sorted((correlations or {}).items(), key=lambda kv: -abs(kv[1][0])):
        lines.append(f"r with {key}: {r:+.2f} ({n} photos)")
    return lines


def fixed_split(records: Sequence[dict[str, Any]], scene: str, steps: int) -> dict[str, MethodCV]:
    """{configuration: MethodCV} of the GPU runs of `scene` on its own split scored at `steps` photo by photo (one
    fold: every test photo; seeds averaged photo by photo)."""
    from benchmarks.methods import configuration

    scores: dict[str, dict[str, list[float]]] = defaultdict(dict)
    runs: dict[str, int] = defaultdict(int)
    for rec in records:
        if rec.get("scene") != scene or rec.get("device") != "cuda" or rec.get("status", "ok") != "ok":
            continue
        ms = milestone(rec, steps)
        if ms is None or not ms.get("per_image"):
            continue
        method = configuration(rec)
        runs[method] += 1
        for p in ms["per_image"]:
            scores[method].setdefault(p["image"], []).append(float(p["psnr"]))
    return {method: method_cv({1: by_photo}, 1, runs[method]) for method, by_photo in scores.items()}


def fixed_split_rows(
    records: Sequence[dict[str, Any]], methods: Sequence[str], sigma: dict[int, float | None], default: str = "willags"
) -> list[str]:
    """The synthetic scenes' table: per scene (FIXED_SPLIT_STEPS) the default's mean and runs, then each of `methods`
    and the peers scored there against it, photo by photo, the interval widened by the run noise of that step count
    (`sigma`: steps -> sigma, as `paired`)."""
    from benchmarks.tables import md_table

    rows = []
    for scene, steps in FIXED_SPLIT_STEPS.items():
        by_method = fixed_split(records, scene, steps)
        ref = by_method.get(default)
        if ref is None:
            continue
        rows.append(
            [scene, str(steps), str(len(ref.per_photo)), f"**{default}**", str(ref.runs), f"{ref.mean:.2f}", ""]
        )
        for m in dict.fromkeys([*methods, "peer", "peer-full"]):
            cv = by_method.get(m)
            if m == default or cv is None:
                continue
            mean, low, high, n = paired(cv, ref, sigma.get(steps))
            rows.append([scene, str(steps), str(n), m, str(cv.runs), f"{cv.mean:.2f}",
                         f"{mean:+.2f} [{low:+.2f}, {high:+.2f}]"])  # fmt: skip
    head = ["scene", "steps", "photos", "method", "runs", "mean", f"− {default} [95 % CI]"]
    return md_table(head, rows) if rows else []


def fit_rows(records: Sequence[dict[str, Any]]) -> list[str]:
    """The table of the protocol variants (`long_run eval --variant`): per run and milestone, the protocol's own
    right-half PSNR, each variant's, the oracle's (the fit on the whole photo), and how many photos the variant moves
    by more than 1 dB either way: whether the protocol's fit reaches a photo's appearance or stops short of it."""
    from benchmarks.tables import md_table

    rows = []
    for r in sorted(records, key=lambda r: (str(r.get("scene")), str(r.get("method")), r.get("seed") or 0)):
        for name, by_step in sorted((r.get("protocol_variants") or {}).items()):
            for step, v in sorted(by_step.items(), key=lambda kv: int(kv[0])):
                own = (r.get("milestones") or {}).get(step) or {}
                if "psnr" not in own or "psnr" not in v:
                    continue
                mine = {p["image"]: p["psnr"] for p in own.get("per_image", [])}
                moved = [p["psnr"] - mine[p["image"]] for p in v.get("per_image", []) if p.get("image") in mine]
                proto = v.get("protocol") or {}
                what = (
                    f"{proto.get('steps')} steps, lr {proto.get('lr')}"
                    + (f", best of {proto['start_candidates']} + 1 starts" if proto.get("start_candidates") else "")
                    + (" + oracle" if proto.get("oracle") else "")
                    + (f", residual at the {proto['residual_latent']} latent" if proto.get("residual_latent") else "")
                )
                rows.append(
                    [
                        str(r["scene"]),
                        str(r["method"]),
                        str(r.get("seed")),
                        step,
                        f"{name} ({what})",
                        f"{own['psnr']:.2f}",
                        f"{v['psnr']:.2f} ({v['psnr'] - own['psnr']:+.2f})",
                        f"{v['oracle_psnr']:.2f}" if "oracle_psnr" in v else "–",
                        f"{sum(d > 1 for d in moved)} / {sum(d < -1 for d in moved)} of {len(moved)}",
                    ]
                )
    if not rows:
        return ["No run scored under a protocol variant yet."]
    head = [
        "scene",
        "method",
        "seed",
        "step",
        "variant",
        "protocol (128 steps, lr 0.01)",
        "variant (− protocol)",
        "oracle",
        "photos +1 dB / −1 dB",
    ]
    return md_table(head, rows)


# --------------------------------------------------------------------------------------------------------------------
# the command line


def run_milestone_photos(
    records: Sequence[dict[str, Any]], method: str, short: int, long: int
) -> dict[str, list[list[tuple[float, float]]]]:
    """{collection: one list per fold run of `method` (a configuration) of its test photos' (PSNR at `short`, PSNR at
    `long`)}: the runs scored at both step counts."""
    from benchmarks.methods import configuration

    out: dict[str, list[list[tuple[float, float]]]] = defaultdict(list)
    for rec in scored_at(records, short, long):
        fold = parse_fold(str(rec.get("scene", "")))
        if fold is None or rec.get("status", "ok") != "ok" or configuration(rec) != method:
            continue
        early, late = (
            {p["image"]: float(p["psnr"]) for p in milestone(rec, n)["per_image"]}  # type: ignore[index]
            for n in (short, long)
        )
        out[fold[0]].append([(score, late[name]) for name, score in early.items() if name in late])
    return dict(out)


def stopping_gain(
    runs: Sequence[Sequence[tuple[float, float]]], photos: int, margin: float, draws: int = 300, seed: int = 0
) -> tuple[float, float]:
    """What ending each run at its earlier milestone when `photos` of its test photos score better there by more than
    `margin` dB (a stand-in for held-out halves: eval/holdout.py's rule between two steps) gains on the run's other
    test photos, against always the later one; averaged over `draws` random choices of those photos. Returns (mean
    gain in dB per scored photo, share of runs that end early). A run lends at most half its photos, at least one."""
    rng = np.random.default_rng(seed)
    gains, early = [], []
    for _ in range(draws):
        diffs, stops = [], 0
        for run in runs:
            d = np.array([a - b for a, b in run])
            if len(d) < 2:
                continue
            order = rng.permutation(len(d))
            k = max(1, min(photos, len(d) // 2))
            stop = float(d[order[:k]].mean()) > margin
            stops += stop
            diffs.extend(d[order[k:]] if stop else np.zeros(len(d) - k))
        gains.append(float(np.mean(diffs)) if diffs else 0.0)
        early.append(stops / max(1, sum(len(r) >= 2 for r in runs)))
    return float(np.mean(gains)), float(np.mean(early))


def missing_folds(records: Sequence[dict[str, Any]], method: str, steps: int, default: str = "willags") -> list[str]:
    """The fold scenes (`<collection>-cv<k>of<K>`) that `method` has no run of scored at `steps`, on every collection
    where the default has every fold there: what a lease must still run before the method counts on all of them (a
    lease that ran out leaves some folds unscored; `cv_lease.sh` takes the list as CV_FOLDS). A BORROWS candidate
    lacks only the folds where the method it borrows from had the switch on."""
    by_scene = collect(records, steps, borrowers=[method] if method in BORROWS else [])
    out = []
    for scene, by_method in sorted(by_scene.items()):
        ref = by_method.get(default)
        if ref is None or not ref.complete:
            continue
        have = by_method[method].fold_means if method in by_method else {}
        out += [fold_name(scene, k, ref.folds) for k in range(1, ref.folds + 1) if k not in have]
    return out


def bar_rows(
    records: Sequence[dict[str, Any]],
    steps: int,
    rule: str,
    low: str,
    high: str,
    bars: Sequence[float],
    field: str = "cap_rule_share",
) -> list[str]:
    """What a rule that chooses between two methods by a share it measures would have scored at other bars: for each
    fold where `rule`'s run recorded `field` at `steps`, `high`'s run of that fold where the share is below the bar and
    `low`'s elsewhere, against `low` photo by photo (a composition: up to the moment the rule decides, its run is the
    other two's, so the composed score differs from its own runs by the run noise). Each collection on the one build
    the rule's runs started from; a collection lacking a fold of any of the three is left out, and named."""
    from benchmarks.methods import configuration

    key = build_key(records)
    sigma, _ = run_noise(records, steps)
    shares: dict[str, dict[int, float]] = defaultdict(dict)
    builds: dict[str, set[str]] = defaultdict(set)
    for (scene, k, _n), rec, ms in fold_runs(records, steps):
        if configuration(rec) == rule and ms.get(field) is not None:
            shares[scene][k] = float(ms[field])
            builds[scene].add(key(rec))
    if not shares:
        return [f"cv: no fold run of {rule} recorded {field} at {steps} steps"]
    lines = [f"| bar | {' | '.join(sorted(shares))} | at once |", "|---|" + "---|" * (len(shares) + 1)]
    # scene -> (low's runs, high's runs, low's MethodCV: the reference of every bar) on the rule's build
    ready: dict[str, tuple[FoldScores, FoldScores, MethodCV] | None] = {}
    skipped = []
    for scene in sorted(shares):
        ready[scene] = None
        if len(builds[scene]) != 1:
            skipped.append(f"{scene}: the rule's runs started from {len(builds[scene])} builds")
            continue
        (build,) = builds[scene]
        by_method = fold_scores([r for r in records if key(r) == build], steps).get(scene, {})
        lo, hi = by_method.get(low), by_method.get(high)
        whole = (
            lo is not None
            and hi is not None
            and lo.folds == hi.folds
            and all(k in lo.by_fold and k in hi.by_fold and k in shares[scene] for k in range(1, lo.folds + 1))
        )
        if not whole:
            skipped.append(f"{scene}: a fold lacks a run of {rule}, {low} or {high}")
            continue
        ready[scene] = (lo, hi, lo.cv())
    for bar in bars:
        cells, pairs = [], []
        for scene in sorted(shares):
            if ready[scene] is None:
                cells.append("–")
                continue
            lo, hi, b = ready[scene]
            folds = range(1, lo.folds + 1)
            below = {k: shares[scene][k] < bar for k in folds}
            pick = {k: hi if below[k] else lo for k in folds}
            a = FoldScores(lo.folds, {k: pick[k].by_fold[k] for k in folds}, {k: pick[k].runs[k] for k in folds}).cv()
            mean, low_ci, high_ci, _ = paired(a, b, sigma)
            cells.append(f"{mean:+.2f} [{low_ci:+.2f}, {high_ci:+.2f}] ({sum(below.values())}/{lo.folds} {high})")
            pairs.append((a, b))
        at_once = ""
        if pairs:
            mean, low_ci, high_ci, _ = pooled(pairs, sigma)
            at_once = f"{mean:+.2f} [{low_ci:+.2f}, {high_ci:+.2f}] over {len(pairs)}: {verdict(low_ci, high_ci)}"
        lines.append(f"| {bar:g} | {' | '.join(cells)} | {at_once} |")
    lines += [f"- left out: {s}" for s in skipped]
    return lines


def readout_variants(records: Sequence[dict[str, Any]], steps: int, method: str = "willags") -> list[str]:
    """The protocol variants some fold run of `method` was scored under at `steps` that no table compares with a
    peer (compared_variants): readouts of the method's own runs (`cv readout`)."""
    from benchmarks.methods import configuration

    names = {
        name
        for r in records
        if parse_fold(str(r.get("scene", ""))) is not None and configuration(r) == method
        for name in (r.get("protocol_variants") or {})
        if variant_milestone(r, steps, name) is not None
    }
    return sorted(names - set(compared_variants(records, steps, method)))


def readout_rows(records: Sequence[dict[str, Any]], steps: int, variant: str, method: str = "willags") -> list[str]:
    """`method`'s fold runs scored under the protocol variant `variant` against the same runs' own scores, photo by
    photo, per collection and over the collections whose every fold has both (two or more, each weighing the same): a readout
    that changes only how a trained model is scored (the residual's latent, the fit's settings) compared on one set of
    runs, so the run noise cancels and the interval is the photos' alone."""
    from benchmarks.methods import configuration

    runs = [
        r
        for r in records
        if configuration(r) == method and variant_milestone(r, steps, variant) is not None
        and milestone(r, steps) is not None
    ]  # fmt: skip
    if not runs:
        return [f"cv: no fold run of {method} scored under the variant {variant!r} at {steps} steps"]
    own, other = fold_scores(runs, steps), fold_scores(runs, steps, variant=variant)
    lines = [
        f"| collection | folds | {method} | under {variant} | {variant} − own [95 % CI] (photos) |",
        "|---|---|---|---|---|",
    ]
    pairs = []
    for scene in sorted(own):
        a_runs, b_runs = other.get(scene, {}).get(method), own[scene].get(method)
        if a_runs is None or b_runs is None:
            continue
        a, b = a_runs.cv(), b_runs.cv()
        mean, low, high, n = paired(a, b)
        whole = all(k in a_runs.by_fold for k in range(1, a_runs.folds + 1))
        folds = f"{len(a_runs.by_fold)} of {a_runs.folds}"
        lines.append(
            f"| {scene} | {folds} | {b.mean:.2f} | {a.mean:.2f} | {mean:+.2f} [{low:+.2f}, {high:+.2f}] (n={n}) |"
        )
        if whole:
            pairs.append((a, b))
    if len(pairs) > 1:
        mean, low, high, n = pooled(pairs)
        lines.append(
            f"| **{len(pairs)} at once** | | | | {mean:+.2f} [{low:+.2f}, {high:+.2f}] (n={n}): {verdict(low, high)} |"
        )
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("folds", help="write the fold folders of a collection")
    f.add_argument("--data", type=Path, required=True, help="the collection (a COLMAP scene)")
    f.add_argument("--folds", type=int, default=4)
    f.add_argument("--out", type=Path, required=True, help="where the fold folders go (beside the collection's copy)")
    b = sub.add_parser("bundle", help="copy collections and write their folds into one folder to carry to a GPU")
    b.add_argument("--data", type=Path, nargs="+", required=True, help="the collections (COLMAP scenes)")
    b.add_argument("--folds", type=int, nargs="+", default=[4], help="fold counts: one for all, or one each")
    b.add_argument("--out", type=Path, required=True, help="the bundle (an ignored folder of the repository)")
    p = sub.add_parser("plan", help="print balanced solo.sh queues for the fold folders (and other scenes) of a root")
    p.add_argument("--root", type=Path, nargs="+", required=True, help="folders holding the scenes to plan")
    p.add_argument(
        "--methods", nargs="+", required=True, help='benchmarks.methods names, first = compared first; "a,b": equal'
    )
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--seeds", type=int, nargs="+", default=[42])
    p.add_argument("--queues", type=int, default=12)
    p.add_argument("--only", nargs="*", default=None, help="plan only these scenes (folder names or collections)")
    ph = sub.add_parser("photos", help="one collection's photo-by-photo differences between two runs' scores")
    ph.add_argument("--scene", required=True, help="the collection (its fold runs' scene name without -cvKofN)")
    ph.add_argument("--a", required=True, help="METHOD or METHOD@STEPS (a configuration, as the tables name it)")
    ph.add_argument("--b", required=True, help="METHOD or METHOD@STEPS, subtracted from a")
    ph.add_argument("--steps", type=int, default=15000, help="the step count of a side that names none")
    ph.add_argument("--inspect", type=Path, help="a `willags-inspect --split all --output` report: r per image array")
    ph.add_argument(
        "--with",
        dest="pairs",
        nargs=2,
        action="append",
        default=[],
        metavar=("A2", "B2"),
        help="another pair of sides (A2 minus B2, each METHOD or METHOD@STEPS): r of its photo differences with a - b's"
        " (repeatable)",
    )
    ph.add_argument("--top", type=int, default=5, help="photos shown at each end")
    ph.add_argument("--records", type=Path, default=None)
    st = sub.add_parser(
        "stop", help="what ending a run at its earlier milestone, chosen on some of its photos, gains on the others"
    )
    st.add_argument("--method", default="willags", help="the configuration whose fold runs are read")
    st.add_argument("--short", type=int, default=5000)
    st.add_argument("--long", type=int, default=15000)
    st.add_argument("--photos", type=int, default=8, help="photos of a run that choose (at most half of them)")
    st.add_argument("--margin", type=float, default=0.1, help="dB the earlier step must lead by on them")
    st.add_argument("--records", type=Path, default=None)
    mi = sub.add_parser("missing", help="the fold scenes a method has no run of yet, one a line (cv_lease.sh CV_FOLDS)")
    mi.add_argument("--method", required=True, help="the configuration, as the tables name it")
    mi.add_argument("--steps", type=int, default=15000)
    mi.add_argument("--records", type=Path, default=None)
    ba = sub.add_parser("bar", help="what a rule choosing between two methods by a measured share scores at other bars")
    ba.add_argument("--rule", required=True, help="the rule's configuration (its runs record the share)")
    ba.add_argument("--low", required=True, help="the method the rule keeps at or above the bar (the reference)")
    ba.add_argument("--high", required=True, help="the method the rule turns to below the bar")
    ba.add_argument("--bars", type=float, nargs="+", required=True)
    ba.add_argument("--field", default="cap_rule_share", help="the share the rule's records carry at --steps")
    ba.add_argument("--steps", type=int, default=15000)
    ba.add_argument("--records", type=Path, default=None)
    ro = sub.add_parser("readout", help="a method's runs under a protocol variant against their own scores")
    ro.add_argument("--variant", required=True, help="the variant's name (`long_run eval --variant`)")
    ro.add_argument("--method", default="willags")
    ro.add_argument("--steps", type=int, default=15000)
    ro.add_argument("--records", type=Path, default=None)
    r = sub.add_parser("report", help="print the cross-validated tables from the records")
    r.add_argument("--records", type=Path, default=None)
    r.add_argument("--steps", type=int, default=5000)
    args = ap.parse_args(argv)
    if args.cmd == "folds":
        try:
            written = write_fold_scenes(args.data, args.folds, args.out)
        except ValueError as e:
            raise SystemExit(str(e)) from None
        for d in written:
            print(f"cv: wrote {d}")
        return 0
    if args.cmd == "bundle":
        try:
            written = write_bundle(args.data, args.folds, args.out)
        except ValueError as e:
            raise SystemExit(str(e)) from None
        size = tree_bytes(args.out)
        print(
            f"cv: {args.out}: {len(written)} scenes, {size / 2**20:.1f} MiB to carry (a call carries {CARRY_LIMIT // 2**20} "
            "MiB with the tracked tree and the wheels)"
        )
        for line in pin_lines(args.data):
            print(line)
        return 0
    if args.cmd == "plan":
        counts: dict[str, int] = {}
        for root in args.root:
            counts.update(test_photo_counts(root))
        if args.only is not None:
            keep = set(args.only)
            counts = {s: n for s, n in counts.items() if s in keep or (parse_fold(s) or ("",))[0] in keep}
        if not counts:
            raise SystemExit(f"cv: no scene folder with one split file under {', '.join(map(str, args.root))}")
        qs = balance(plan_runs(counts, args.methods, args.steps, args.seeds), args.queues)
        for q in qs:
            print(" ".join(r.spec() for r in q))
        total = sum(r.cost for q in qs for r in q)
        print(f"# {sum(map(len, qs))} runs in {len(qs)} queues, {total:.1f} run-units", file=sys.stderr)
        return 0
    from benchmarks.records import CV_RECORDS, load_records

    records = load_records(args.records or CV_RECORDS)
    if args.cmd == "photos":
        try:
            diffs = photo_differences(
                records, args.scene, parse_side(args.a, args.steps), parse_side(args.b, args.steps)
            )
        except ValueError as e:
            raise SystemExit(str(e)) from None
        corr = None
        if args.inspect is not None:
            try:
                corr = evidence_correlations(diffs, json.loads(args.inspect.read_text()))
            except (OSError, ValueError) as e:
                raise SystemExit(f"cv: {args.inspect}: not a willags-inspect report ({e})") from None
        for a2, b2 in args.pairs:
            try:
                other = photo_differences(records, args.scene, parse_side(a2, args.steps), parse_side(b2, args.steps))
            except ValueError as e:
                raise SystemExit(str(e)) from None
            r = pair_correlation(diffs, other)
            if r is not None:
                corr = {**(corr or {}), f"{a2} - {b2}": r}
        print("\n".join(photo_lines(diffs, args.top, corr)))
        return 0
    if args.cmd == "readout":
        print("\n".join(readout_rows(records, args.steps, args.variant, args.method)))
        return 0
    if args.cmd == "bar":
        print("\n".join(bar_rows(records, args.steps, args.rule, args.low, args.high, args.bars, args.field)))
        return 0
    if args.cmd == "missing":
        folds = missing_folds(records, args.method, args.steps)
        for name in folds:
            print(name)
        print(f"cv: {args.method} lacks {len(folds)} fold run(s) scored at {args.steps} steps", file=sys.stderr)
        return 0
    if args.cmd == "stop":
        by_scene = run_milestone_photos(records, args.method, args.short, args.long)
        if not by_scene:
            raise SystemExit(f"cv: no fold run of {args.method} scored at both {args.short} and {args.long} steps")
        print(
            f"| collection | runs | {args.long} -> {args.short} steps (all photos) | the rule's gain | runs ended early |"
        )
        print("|---|---|---|---|---|")
        for scene, runs in sorted(by_scene.items()):
            gain, early = stopping_gain(runs, args.photos, args.margin)
            whole = float(np.mean([a - b for run in runs for a, b in run]))
            print(f"| {scene} | {len(runs)} | {whole:+.2f} | {gain:+.2f} | {early:.2f} |")
        return 0
    print("\n".join(cv_rows(records, args.steps)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
