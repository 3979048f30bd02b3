"""benchmarks/remote/solo.sh: the queue of runs alone on the GPU, driven with a stand-in for python3 (no GPU here) that
logs what it was asked to do."""

import os
import shutil
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

FAKE_PYTHON = """#!/usr/bin/env bash
# a stand-in for python3: `-c` code runs in the real interpreter; benchmarks.long_run commands are logged and faked
if [ "$1" = "-c" ]; then
  case "$2" in *warm_gsplat*) exit 0;; esac
  exec {real} "$@"
fi
shift 2; cmd=$1; shift
echo "$cmd $*" >> "$SOLO_DIR/calls.log"
[ "$cmd" = train ] && echo "${{CUDA_VISIBLE_DEVICES:-none}}" >> "$SOLO_DIR/gpus.log"
while [ $# -gt 0 ]; do case $1 in --run-dir) d=$2;; --out) o=$2;; --milestones) ms=$2;; esac; shift; done
case $cmd in
  train) mkdir -p "$d"
         {real} -c "import json,sys; json.dump({{'milestone_train_s': {{m: 1.0 for m in sys.argv[2].split(',')}}}}, open(sys.argv[1], 'w'))" "$d/state.json" "$ms"
         echo "long_run: trained $ms";;
  eval) echo "long_run: scored $ms";;
  record) echo '[]' > "$o";;
esac
"""


@pytest.fixture()
def tree(tmp_path):
    if shutil.which("bash") is None or shutil.which("setsid") is None:
        pytest.skip("needs bash and setsid")
    root = tmp_path / "repo"
    (root / "benchmarks" / "remote").mkdir(parents=True)
    shutil.copy(REPO / "benchmarks" / "remote" / "solo.sh", root / "benchmarks" / "remote")
    for d in ("willags_ns", "configs"):
        (root / d).mkdir()
    (root / "pyproject.toml").write_text("")
    (root / ".data-a" / "reichstag").mkdir(parents=True)
    (root / ".data-a" / "reichstag" / "img.jpg").write_text("x")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "python3"
    fake.write_text(FAKE_PYTHON.format(real=sys.executable))
    fake.chmod(0o755)
    env = {
        **os.environ,
        "PATH": f"{bin_dir}:{os.environ['PATH']}",
        "SOLO_DIR": str(tmp_path / "solo"),
        "SOLO_POLL_S": "1",
        "SOLO_WAIT_S": "300",  # longer than any pause between two of the test's calls; a failing test leaves no queue for long
    }
    return root, env, tmp_path / "solo"


def _sh(root, env, *args, **extra):
    return subprocess.run(
        ["bash", "benchmarks/remote/solo.sh", *args],
        cwd=root,
        env={**env, **extra},
        capture_output=True,
        text=True,
        timeout=900,
    )


def _until_in_queue_log(solo: Path, line: str) -> None:
    """Until the detached queue has logged ``line`` (the deadline only guards against a hang)."""
    deadline = time.monotonic() + 600
    log = solo / "queue.log"
    while not (log.exists() and line in log.read_text()):
        assert time.monotonic() < deadline, log.read_text() if log.exists() else "no queue.log"
        time.sleep(0.1)


@pytest.mark.timing
def test_the_queue_trains_each_run_alone_in_order_and_a_scene_carried_later_waits_at_the_back(tree, tmp_path):
    root, env, solo = tree
    queue = "south-building:willags:15000 reichstag:peer:2000:43 reichstag:willags:30000:42:5"
    started = _sh(root, env, "start", queue, SOLO_DATA=".data-a")
    assert started.returncode == 0, started.stderr
    assert "scene reichstag ready" in started.stdout
    # a later device call carries the scene that did not fit in the first one, once both runs whose scene was
    # there have trained (the queue waits for the missing scene meanwhile)
    _until_in_queue_log(solo, "gpu_solo: done reichstag-willags-30000-s42-knob5")
    (root / ".data-b" / "south-building").mkdir(parents=True)
    waited = _sh(root, env, "wait", str(tmp_path / "out"), "600", SOLO_DATA=".data-b")
    assert waited.returncode == 0, waited.stderr
    assert "gpu_solo: all done" in waited.stdout
    trains = [ln.split() for ln in (solo / "calls.log").read_text().splitlines() if ln.startswith("train ")]

    def opt(call, name):
        return call[call.index(name) + 1] if name in call else None

    # one after another, each alone; the run whose scene came later last
    assert [opt(c, "--method") for c in trains] == ["peer", "willags", "willags"]
    assert [Path(opt(c, "--data")).name for c in trains] == ["reichstag", "reichstag", "south-building"]
    assert all(opt(c, "--concurrent") == "1" for c in trains)
    peer, knob, sb = trains
    assert (opt(peer, "--seed"), opt(peer, "--milestones")) == ("43", "1000,2000")
    assert (opt(knob, "--budget-minutes"), opt(knob, "--milestones")) == ("5", "30000")
    assert opt(peer, "--budget-minutes") is None
    assert opt(sb, "--milestones") == "1000,2000,5000,10000,15000"
    evals = [ln for ln in (solo / "calls.log").read_text().splitlines() if ln.startswith("eval ")]
    assert len(evals) == 2 + 1 + 5  # one process per milestone with a recorded time
    records = [ln.split() for ln in (solo / "calls.log").read_text().splitlines() if ln.startswith("record ")]
    assert [opt(r, "--tag") for r in records] == ["h200-curve-s43", "h200-curve-knob5", "h200-curve"]
    with tarfile.open(tmp_path / "out" / "solo-records.tgz") as tar:
        names = set(tar.getnames())
    assert {
        "rec/long-reichstag-peer-2000-s43.json",
        "rec/long-reichstag-willags-30000-s42-knob5.json",
        "rec/long-south-building-willags-15000-s42.json",
        "queue.log",
    } <= names


@pytest.mark.timing
def test_no_run_starts_after_the_deadline(tree, tmp_path):
    root, env, solo = tree
    assert _sh(root, env, "start", "reichstag:peer:2000", SOLO_DATA=".data-a", SOLO_DEADLINE_S="-1").returncode == 0
    waited = _sh(root, env, "wait", str(tmp_path / "out"), "600")
    assert "deadline passed; not started: reichstag:peer:2000" in waited.stdout
    assert not (solo / "calls.log").exists()


@pytest.mark.timing
def test_a_long_run_past_its_deadline_is_dropped_and_shorter_runs_still_start(tree, tmp_path):
    root, env, solo = tree
    started = _sh(
        root,
        env,
        "start",
        "reichstag:peer:15000 reichstag:willags:5000",
        SOLO_DATA=".data-a",
        SOLO_LONG_DEADLINE_S="-1",
    )
    assert started.returncode == 0
    waited = _sh(root, env, "wait", str(tmp_path / "out"), "600")
    assert "long-run deadline passed; not started: reichstag:peer:15000" in waited.stdout
    trained = [ln.split()[2] for ln in (solo / "calls.log").read_text().splitlines() if ln.startswith("train ")]
    assert trained == ["willags"]


@pytest.mark.timing
def test_a_queue_started_under_a_lock_does_not_keep_it(tree, tmp_path):
    root, env, solo = tree
    if shutil.which("flock") is None:
        pytest.skip("needs flock")
    lock = tmp_path / "lock"
    started = subprocess.run(
        ["flock", str(lock), "bash", "benchmarks/remote/solo.sh", "start", "reichstag:peer:2000"],
        cwd=root,
        env={**env, "SOLO_DATA": ".no-data"},  # the queue waits for its scene, alive
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert started.returncode == 0, started.stderr
    # the running queue gives the lock's descriptor up as it starts (a guard against a hang, not a speed bound)
    deadline = time.monotonic() + 300
    while subprocess.run(["flock", "-n", str(lock), "true"], timeout=60).returncode != 0:
        assert time.monotonic() < deadline, "the queue still holds its starter's lock"
        time.sleep(0.2)
    assert not (solo / "done").exists()  # and it is still running, waiting for its scene
    waited = _sh(root, env, "wait", str(tmp_path / "out"), "600", SOLO_DATA=".data-a")  # its scene comes; it ends
    assert "gpu_solo: done reichstag-peer-2000-s42" in waited.stdout


@pytest.mark.timing
def test_queues_run_side_by_side_and_one_archive_brings_back_every_queue(tree, tmp_path):
    root, env, solo = tree
    queues = tmp_path / "queues"
    qenv = {**env, "QUEUES_DIR": str(queues), "SOLO_DATA": ".data-a"}
    started = _sh(
        root, qenv, "queues", "start", "reichstag:peer:2000", "reichstag:willags:1000 reichstag:splatfacto:1000"
    )
    assert started.returncode == 0, started.stderr
    waited = _sh(root, qenv, "queues", "wait", str(tmp_path / "out"), "600")
    assert waited.returncode == 0, waited.stderr
    assert "gpu_queues: 0 queue(s) still running" in waited.stdout
    calls = {q: (queues / q / "calls.log").read_text() for q in ("q1", "q2")}
    assert [ln.split()[2] for ln in calls["q1"].splitlines() if ln.startswith("train ")] == ["peer"]
    assert [ln.split()[2] for ln in calls["q2"].splitlines() if ln.startswith("train ")] == ["willags", "splatfacto"]
    with tarfile.open(tmp_path / "out" / "queues.tgz") as tar:
        names = set(tar.getnames())
    prefix = str(queues).lstrip("/")
    assert {f"{prefix}/q1/rec/long-reichstag-peer-2000-s42.json", f"{prefix}/q2/queue.log"} <= names


@pytest.mark.timing
def test_queues_are_spread_over_the_gpus_and_added_queues_go_on_round_the_list(tree, tmp_path):
    root, env, _ = tree
    queues = tmp_path / "queues"
    qenv = {**env, "QUEUES_DIR": str(queues), "SOLO_DATA": ".data-a", "QUEUE_GPUS": "0 1"}
    runs = ("reichstag:peer:1000", "reichstag:willags:1000", "reichstag:splatfacto:1000")
    assert _sh(root, qenv, "queues", "start", *runs).returncode == 0
    assert _sh(root, qenv, "queues", "add", "reichstag:peer-full:1000").returncode == 0
    waited = _sh(root, qenv, "queues", "wait", str(tmp_path / "out"), "600")
    assert "gpu_queues: 0 queue(s) still running" in waited.stdout
    gpus = {q: (queues / q / "gpus.log").read_text().split() for q in ("q1", "q2", "q3", "q4")}
    assert gpus == {"q1": ["0"], "q2": ["1"], "q3": ["0"], "q4": ["1"]}
    assert "== q4 (GPU 1): reichstag:peer-full:1000" in waited.stdout
    # each record says the GPU was shared by the two queues pinned to it
    for q in ("q1", "q2", "q3", "q4"):
        records = [ln.split() for ln in (queues / q / "calls.log").read_text().splitlines() if ln.startswith("record ")]
        assert [r[r.index("--concurrent") + 1] for r in records] == ["2"], q


@pytest.mark.timing
def test_a_run_shorter_than_every_milestone_is_scored_where_it_ends(tree, tmp_path):
    root, env, solo = tree
    assert _sh(root, env, "start", "reichstag:willags:500", SOLO_DATA=".data-a").returncode == 0
    waited = _sh(root, env, "wait", str(tmp_path / "out"), "600")
    assert "gpu_solo: all done" in waited.stdout
    (train,) = [ln.split() for ln in (solo / "calls.log").read_text().splitlines() if ln.startswith("train ")]
    assert train[train.index("--milestones") + 1] == "500"


def test_variants_score_the_last_milestone_again_under_their_fit_settings_before_the_record(tree, tmp_path):
    root, env, solo = tree
    variants = "fit512:512:0.01 orc:128:0.03:oracle st:128:0.01:start16 both:128:0.01:oracle:start8 rm:128:0.01:resmean"
    started = _sh(root, env, "start", "reichstag:willags:2000", SOLO_DATA=".data-a", SOLO_VARIANTS=variants)
    assert started.returncode == 0, started.stderr
    _until_in_queue_log(solo, "gpu_solo: queue finished")
    calls = (solo / "calls.log").read_text().splitlines()
    evals = [c for c in calls if c.startswith("eval ")]
    assert sorted(c.split("--milestones ")[1].split()[0] for c in evals if "--variant" not in c) == ["1000", "2000"]
    both, fit, orc, rm, st = sorted((c for c in evals if "--variant" in c), key=lambda c: c.split("--variant ")[1])
    assert "--variant rm --protocol-steps 128 --protocol-lr 0.01 --residual-latent mean --train-views 0" in rm
    assert "--milestones 2000 --variant fit512 --protocol-steps 512 --protocol-lr 0.01 --train-views 0" in fit
    assert "--variant orc --protocol-steps 128 --protocol-lr 0.03 --oracle --train-views 0" in orc
    assert "--variant st --protocol-steps 128 --protocol-lr 0.01 --protocol-start-candidates 16 --train-views" in st
    assert "--protocol-lr 0.01 --oracle --protocol-start-candidates 8 --train-views 0" in both
    assert calls[-1].startswith("record ")  # the record is made after every score, the variants' too


def test_an_unknown_command_prints_the_usage(tree):
    root, env, _ = tree
    bad = _sh(root, env, "queues", "bogus")
    assert bad.returncode == 2 and "usage: solo.sh queues start" in bad.stderr
