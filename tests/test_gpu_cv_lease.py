"""benchmarks/remote/cv_lease.sh: which runs a cross-validated lease starts from the bundles it is given (its dry run;
the queues themselves are solo.sh's, tests/test_gpu_solo.py)."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "benchmarks" / "remote" / "cv_lease.sh"


def _lease(*args, cwd, **env):
    return subprocess.run(
        ["bash", str(SCRIPT), *args], cwd=cwd, env={**os.environ, **env}, capture_output=True, text=True, timeout=60
    )


@pytest.fixture()
def bundles(tmp_path):
    if shutil.which("bash") is None:
        pytest.skip("needs bash")
    folds = tmp_path / ".gpu-a"
    for name in ("lund", "lund-cv1of2", "lund-cv2of2", "sacre-coeur-mini-cv1of7"):
        (folds / name).mkdir(parents=True)
    (folds / "notes-cv.txt").write_text("a file, not a fold")
    extra = tmp_path / ".gpu-fox"
    (extra / "fox-clean").mkdir(parents=True)
    return tmp_path


def test_every_fold_folder_is_a_run_and_a_bundle_without_folds_gives_none(bundles):
    r = _lease("runs", ".gpu-a", ".gpu-fox", cwd=bundles, CV_METHOD="m", CV_STEPS="5000", CV_SEED="43")
    assert r.returncode == 0
    assert r.stdout.split() == ["lund-cv1of2:m:5000:43", "lund-cv2of2:m:5000:43", "sacre-coeur-mini-cv1of7:m:5000:43"]
    assert "*" not in r.stdout  # no pattern taken for a scene
    assert ".gpu-fox holds no fold folder" in r.stderr


def test_start_queues_the_folds_then_the_extra_runs_and_add_carries_scenes_alone(bundles):
    start = _lease("start", ".gpu-a", cwd=bundles, CV_DRY_RUN="1", CV_EXTRA="fox-clean:willags:5000:42")
    assert start.returncode == 0
    assert start.stdout.strip() == (
        'solo.sh queues start "lund-cv1of2:willags:15000:42" "lund-cv2of2:willags:15000:42" '
        '"sacre-coeur-mini-cv1of7:willags:15000:42" "fox-clean:willags:5000:42"'
    )
    added = _lease("add", ".gpu-fox", cwd=bundles, CV_DRY_RUN="1", CV_EXTRA="fox-clean:willags:5000:42")
    assert added.returncode == 0 and added.stdout.strip() == "copy only: .gpu-fox"  # CV_EXTRA starts once, with start
    nothing = _lease("start", ".gpu-fox", cwd=bundles, CV_DRY_RUN="1")
    assert nothing.returncode == 2 and "no run to start" in nothing.stderr
    usage = _lease(cwd=bundles)
    assert usage.returncode == 2 and usage.stderr.startswith("usage: cv_lease.sh")


def test_several_methods_run_every_fold_each_in_an_order_that_turns_from_fold_to_fold(bundles):
    """Queues go round the GPUs in order: with two methods on two GPUs, a fixed order would put every run of the
    first method on the first GPU; the order turns by one at each fold, so each method's runs alternate."""
    r = _lease("runs", ".gpu-a", cwd=bundles, CV_METHOD="willags peer-full", CV_STEPS="15000")
    assert r.returncode == 0
    runs = r.stdout.split()
    assert runs == [
        "lund-cv1of2:willags:15000:42",
        "lund-cv1of2:peer-full:15000:42",
        "lund-cv2of2:peer-full:15000:42",
        "lund-cv2of2:willags:15000:42",
        "sacre-coeur-mini-cv1of7:willags:15000:42",
        "sacre-coeur-mini-cv1of7:peer-full:15000:42",
    ]
    gpu_of_peer_full = [i % 2 for i, run in enumerate(runs) if ":peer-full:" in run]
    assert gpu_of_peer_full == [1, 0, 1]


def test_cv_folds_keeps_only_the_named_fold_folders(bundles):
    """A lease that ran out leaves some folds unscored: CV_FOLDS (what `cv missing` prints, newline- or
    space-separated) runs only those, and a bundle none of whose folds it names adds no run."""
    r = _lease("runs", ".gpu-a", cwd=bundles, CV_METHOD="m", CV_FOLDS="lund-cv2of2\nsacre-coeur-mini-cv1of7")
    assert r.returncode == 0 and r.stdout.split() == ["lund-cv2of2:m:15000:42", "sacre-coeur-mini-cv1of7:m:15000:42"]
    assert "holds no fold folder" not in r.stderr  # it holds them; none was asked for
    spaced = _lease("runs", ".gpu-a", cwd=bundles, CV_METHOD="m", CV_FOLDS="lund-cv1of2 lund-cv2")
    assert spaced.stdout.split() == ["lund-cv1of2:m:15000:42"]  # whole names only, not a prefix
    none = _lease("add", ".gpu-a", cwd=bundles, CV_DRY_RUN="1", CV_FOLDS="liberty-cv1of4")
    assert none.returncode == 0 and none.stdout.strip() == "copy only: .gpu-a"
