"""Faults a long run meets, with nothing lost (docs/reliability.md rows 22-28): a full disk at a save, a damaged
checkpoint given to the loaders, a killed training process, the exact resume command, saves by wall time, the
viewer's banner in a log, and progress output of long commands. Each test names its row."""

import errno
import os
import re
import shlex
import signal
import socket
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.scale import console_script
from tests._paused_ns_train import launch_paused, wait_until_paused
from willags_ns.engine import checkpoints as ck
from willags_ns.engine.checkpoints import (
    CheckpointError,
    CheckpointSpaceError,
    SaveTimer,
    checkpoint_path,
    list_checkpoints,
    load_file,
    load_latest,
    read_checkpoint,
    resume_command,
    save_atomic,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """8 training + 2 test images of 32x24 (tests/test_reliability.py's tiny scene)."""
    from willags_ns.data.synthetic import SyntheticSceneConfig, make_scene, write_scene

    cfg = SyntheticSceneConfig(num_train=8, num_test=2, width=32, height=24, num_points=400, supersample=1)
    return write_scene(make_scene(cfg), tmp_path_factory.mktemp("faults") / "scene")


def _config(out: Path, data: Path, steps: int, **trainer):
    from tests.test_reliability import _tiny_config

    config = _tiny_config(out, data, steps=steps)
    for k, v in trainer.items():
        setattr(config, k, v)
    config.save_config()
    return config


def _state(n: int = 3) -> dict:
    g = torch.Generator().manual_seed(n)
    return {"step": n, "pipeline": {"w": torch.randn(64, 64, generator=g)}, "optimizers": {}}


# ---- row 22: a full disk at a save


class FillingDisk:
    """Opens partial checkpoint files on a disk that fills up at the ``full_at``-th file: that file takes
    ``room`` bytes, then every write raises ENOSPC (what a real full disk does under the checkpoint writer)."""

    def __init__(self, full_at: int, room: int = 1000):
        self.full_at, self.room, self.opened = full_at, room, 0

    def __call__(self, path: Path):
        self.opened += 1
        f = open(path, "wb")
        if self.opened < self.full_at:
            return f
        room = [self.room]
        real_write = f.write

        class Full:
            def write(self, data):
                if len(data) > room[0]:
                    real_write(bytes(data)[: room[0]])
                    room[0] = 0
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                room[0] -= len(data)
                return real_write(data)

            def __getattr__(self, name):
                return getattr(f, name)

        return Full()


def test_row22_a_save_is_atomic_and_a_full_disk_removes_its_partial_file(tmp_path, monkeypatch):
    d = tmp_path / "ckpts"
    good = save_atomic(_state(2), checkpoint_path(d, 2))
    assert list_checkpoints(d) == [good] and read_checkpoint(good)["step"] == 2
    stale = d / ".step-000000003.ckpt.999.partial"  # left by a process killed mid-save
    stale.write_bytes(b"half a checkpoint")
    assert list_checkpoints(d) == [good]  # never read
    monkeypatch.setattr(ck, "_open_partial", FillingDisk(full_at=1))
    with pytest.raises(CheckpointSpaceError, match=rf"^no space left on {re.escape(str(d))}: the checkpoint needs "):
        save_atomic(_state(4), checkpoint_path(d, 4))
    assert sorted(p.name for p in d.iterdir()) == [good.name], "the partial files were not removed"
    torch.testing.assert_close(read_checkpoint(good)["pipeline"]["w"], _state(2)["pipeline"]["w"])

    # any other write error: one line naming the file
    def read_only(path):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(ck, "_open_partial", read_only)
    with pytest.raises(CheckpointError, match=r"cannot write checkpoint .*step-000000005.ckpt: Permission denied"):
        save_atomic(_state(5), checkpoint_path(d, 5))


def test_row22_a_config_write_that_fails_midway_leaves_the_previous_config_yml_whole(scene, tmp_path, monkeypatch):
    config = _config(tmp_path / "out", scene, steps=5)
    path = config.get_base_dir() / "config.yml"
    before = path.read_text()
    write_text = Path.write_text

    def half_then_disk_full(self, data, *args, **kwargs):
        write_text(self, data[: len(data) // 2], *args, **kwargs)
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    monkeypatch.setattr(Path, "write_text", half_then_disk_full)
    config.max_num_iterations = 7
    with pytest.raises(OSError, match="No space left"):
        config.save_config()
    monkeypatch.undo()
    assert path.read_text() == before
    assert [p.name for p in path.parent.iterdir() if p.name.endswith(ck.PARTIAL_SUFFIX)] == []
    config.save_config()
    assert "max_num_iterations: 7" in path.read_text()


def _mount_tmpfs(path: Path, size: str) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    try:
        res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    except FileNotFoundError:
        return False
    return res.returncode == 0


def test_row22_a_full_disk_on_a_real_small_filesystem(tmp_path):
    """The issue's case: a 3 MB tmpfs, two 2 MB checkpoints (the second needs the first to stay until it is
    complete). Needs permission to mount (root); otherwise the FillingDisk tests above stand in for it."""
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, "3m"):
        pytest.skip("cannot mount a tmpfs here (needs root); the ENOSPC writer tests cover the same path")
    try:
        big = {"step": 1, "pipeline": {"w": torch.randn(512, 1024)}}  # 2 MB
        first = save_atomic(big, checkpoint_path(disk / "ckpts", 1))
        with pytest.raises(CheckpointSpaceError) as info:
            save_atomic({**big, "step": 2}, checkpoint_path(disk / "ckpts", 2))
        msg = str(info.value)
        assert re.match(
            rf"no space left on {re.escape(str(disk / 'ckpts'))}: the checkpoint needs about 2\.0 MB, ", msg
        )
        assert "inline_container" not in msg and "\n" not in msg
        assert [p.name for p in (disk / "ckpts").iterdir()] == [first.name]  # the partial file is gone
        assert read_checkpoint(first)["step"] == 1
    finally:
        subprocess.run(["umount", str(disk)], check=False)


def test_row22_a_full_disk_stops_training_naming_the_last_good_checkpoint_and_the_resume_command(
    scene, tmp_path, monkeypatch, capsys
):
    from willags_ns.engine.checks import _excepthook

    config = _config(tmp_path, scene, steps=8, steps_per_save=2, save_every_minutes=0.0)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    monkeypatch.setattr(ck, "_open_partial", FillingDisk(full_at=2))  # step 2 saves, step 4 meets a full disk
    with pytest.raises(CheckpointSpaceError) as info:
        trainer.train()
    d = config.get_checkpoint_dir()
    msg = str(info.value)
    assert re.match(rf"no space left on {re.escape(str(d))}: the checkpoint needs about \d+\.\d MB, ", msg), msg
    assert f"Training stopped at step 4; the last good checkpoint is {d / 'step-000000002.ckpt'} (step 2)" in msg
    # 8 planned steps, the last good save after step 2: 5 steps left (nerfstudio counts them from step 3)
    good = d / "step-000000002.ckpt"
    assert f"resume with:\n  ns-train willags --load-checkpoint {good} --max-num-iterations 5" in msg
    assert trainer.step == 4  # no step trained after the failed save
    assert sorted(p.name for p in d.iterdir()) == ["step-000000002.ckpt"]
    assert read_checkpoint(d / "step-000000002.ckpt")["step"] == 2
    # from the command line: that message, no traceback
    capsys.readouterr()
    _excepthook(lambda *a: pytest.fail("fell through to Python's traceback"))(type(info.value), info.value, None)
    err = capsys.readouterr().err
    assert err.strip().startswith("willags: no space left on") and "Traceback" not in err


# ---- row 23: a truncated / corrupt checkpoint given to --load-dir, ns-eval, willags-render ...


def test_row23_the_reason_is_torchs_first_sentence_not_cut_at_a_colon(tmp_path):
    """A checkpoint cut short of its zip directory: torch says `... failed reading zip archive: failed finding central
    directory. This is an internal miniz error. ...`; the line quotes the first sentence whole."""
    path = tmp_path / "step-000000001.ckpt"
    torch.save({"step": 1, "pipeline": {"x": torch.zeros(300000)}}, path)
    path.write_bytes(path.read_bytes()[:100000])
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(path)
    msg = str(info.value)
    assert "failed reading zip archive: failed finding central directory.)" in msg and "miniz" not in msg, msg


@pytest.mark.parametrize("damage", ["half", "tail", "empty", "garbage", "not-a-checkpoint"])
def test_row23_every_kind_of_damage_is_one_line_naming_the_file(tmp_path, damage):
    path = save_atomic(_state(7), checkpoint_path(tmp_path, 7))
    data = path.read_bytes()
    damaged = {
        "half": data[: len(data) // 2],
        "tail": data[:-10],
        "empty": b"",
        "garbage": b"hello world" * 50,
    }
    if damage == "not-a-checkpoint":
        torch.save({"weights": torch.zeros(2)}, path)
    else:
        path.write_bytes(damaged[damage])
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(path)
    msg = str(info.value)
    assert msg.startswith(f"checkpoint {path} ") and "\n" not in msg, msg
    assert ("truncated or corrupt" in msg) if damage != "not-a-checkpoint" else ("not a nerfstudio checkpoint" in msg)
    assert not msg.endswith(":)"), msg  # torch's reason to the end of its first sentence, not cut at a colon


@pytest.fixture(scope="module")
def two_checkpoints(scene, tmp_path_factory):
    """A 4-step run keeping every checkpoint: steps 2 and 3; (config.yml, checkpoint directory)."""
    config = _config(
        tmp_path_factory.mktemp("two"), scene, steps=4, steps_per_save=2, save_only_latest_checkpoint=False
    )
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    d = config.get_checkpoint_dir()
    assert [p.name for p in list_checkpoints(d)] == ["step-000000003.ckpt", "step-000000002.ckpt"]
    return config.get_base_dir() / "config.yml", d


def _damaged_copy(two_checkpoints, tmp_path) -> tuple[Path, Path]:
    """A copy of the run whose newest checkpoint (step 3) is truncated: (config.yml, checkpoint directory)."""
    import shutil

    import yaml

    cfg_path, _ = two_checkpoints
    config = yaml.load(cfg_path.read_text(), Loader=yaml.Loader)
    config.output_dir = tmp_path / "out"
    shutil.copytree(cfg_path.parent, config.get_base_dir())
    config.save_config()
    newest = config.get_checkpoint_dir() / "step-000000003.ckpt"
    newest.write_bytes(newest.read_bytes()[:5000])
    return config.get_base_dir() / "config.yml", config.get_checkpoint_dir()


def test_row23_loaders_skip_a_damaged_newest_checkpoint_naming_it(two_checkpoints, tmp_path, scene):
    from nerfstudio.utils.eval_utils import eval_setup

    cfg, d = _damaged_copy(two_checkpoints, tmp_path)
    newest, older = d / "step-000000003.ckpt", d / "step-000000002.ckpt"
    warned: list[str] = []
    path, state = load_latest(d, warn=warned.append)
    assert path == older and state["step"] == 2
    assert len(warned) == 1 and str(newest) in warned[0] and "truncated or corrupt" in warned[0]
    assert "using step-000000002.ckpt" in warned[0]

    # --load-dir (willags' trainer): resumes after step 2, with the warning
    config = _config(tmp_path / "resume", scene, steps=1)
    config.load_dir = d
    trainer = config.setup(local_rank=0, world_size=1)
    with pytest.warns(UserWarning, match=re.escape(str(newest))):
        trainer.setup()
    assert trainer._start_step == 3

    # nerfstudio's eval_setup (ns-eval, ns-render, ns-viewer, willags-render, willags-export, willags-latents)
    with pytest.warns(UserWarning, match=re.escape(str(newest))):
        _, _, loaded, step = eval_setup(cfg, test_mode="inference")
    assert loaded == older and step == 2

    # chosen by name (--load-step, --load-checkpoint): an error naming it and the one that can be used instead
    hint = f"{older} (step 2) is readable: load it instead"
    with pytest.raises(CheckpointError, match=re.escape(hint)) as info:
        load_latest(d, step=3)
    assert str(info.value).startswith(f"checkpoint {newest} ")
    with pytest.raises(CheckpointError, match=re.escape(hint)):
        load_file(newest)
    with pytest.raises(CheckpointError, match=r"no checkpoint of step 9 in .*\(steps there: 3, 2\)"):
        load_latest(d, step=9)


def test_row23_ns_eval_on_a_damaged_checkpoint_prints_one_line(two_checkpoints, tmp_path):
    """The command line: ns-eval with every checkpoint damaged stops with one line naming them, no traceback."""
    cfg, d = _damaged_copy(two_checkpoints, tmp_path)
    older = d / "step-000000002.ckpt"
    older.write_bytes(b"")
    exe = console_script("ns-eval")
    res = subprocess.run(
        [str(exe), "--load-config", str(cfg), "--output-path", str(tmp_path / "eval.json")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 1, (res.stdout[-2000:], res.stderr[-2000:])
    last = [ln for ln in res.stderr.strip().splitlines() if ln.strip()][-1]
    assert last.startswith(f"willags: no readable checkpoint in {d}: checkpoint "), res.stderr[-2000:]
    assert "step-000000003.ckpt" in last and "step-000000002.ckpt" in last
    assert "Traceback" not in res.stderr + res.stdout


# ---- row 24: the exact resume command


def test_row24_resume_command_parses_to_the_resumed_run():
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    argv = ["/venv/bin/ns-train", "willags", "--data", "/d", "--max-num-iterations", "400", "--load-dir", "/old"]
    argv += ["--pipeline.model.num-downscales", "0", "nerfstudio-data", "--downscale-factor", "2"]
    ckpt = Path("/out/run dir/nerfstudio_models/step-000000100.ckpt")
    cmd = resume_command(argv, "willags", ckpt, 299)
    assert cmd == (
        "ns-train willags --load-checkpoint '/out/run dir/nerfstudio_models/step-000000100.ckpt' "
        "--max-num-iterations 299 --data /d --pipeline.model.num-downscales 0 nerfstudio-data --downscale-factor 2"
    )
    config = tyro.cli(AnnotatedBaseConfigUnion, args=shlex.split(cmd)[1:])
    assert config.load_checkpoint == ckpt and config.load_dir is None and config.max_num_iterations == 299
    assert config.pipeline.model.num_downscales == 0 and config.pipeline.datamanager.dataparser.downscale_factor == 2
    # --a=b and --a_b spellings are replaced too; a command line that is not ns-train's gets the plain form
    argv = ["ns-train", "willags", "--max_num_iterations=400", "--load-step=3", "--load-dir", "/a"]
    assert (
        resume_command(argv, "willags", Path("/c"), 9) == "ns-train willags --load-checkpoint /c --max-num-iterations 9"
    )
    assert resume_command(["pytest"], "willags", Path("/c"), 9).startswith(
        "ns-train willags --load-checkpoint /c --max-num-iterations 9  (plus this run's other ns-train options)"
    )


def test_row24_a_budgeted_run_resumes_with_what_is_left_of_its_budget():
    """Stopped 42 s into a 2-minute budget: the resume command asks for the 78 s left, not a new 2 minutes, so the
    two parts train within the budget asked for."""
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    argv = ["ns-train", "willags", "--data", "/d", "--pipeline.time-budget-minutes", "2"]
    cmd = resume_command(argv, "willags", Path("/c"), 500, budget_minutes_left=(120 - 42) / 60)
    assert cmd == (
        "ns-train willags --load-checkpoint /c --max-num-iterations 500 --pipeline.time-budget-minutes 1.30 --data /d"
    )
    config = tyro.cli(AnnotatedBaseConfigUnion, args=shlex.split(cmd)[1:])
    assert config.pipeline.time_budget_minutes == 1.3
    argv = ["ns-train", "willags", "--pipeline.time_budget_minutes=2"]  # the other spelling is replaced too
    assert resume_command(argv, "willags", Path("/c"), 5, budget_minutes_left=0.0).endswith(
        "--max-num-iterations 5 --pipeline.time-budget-minutes 0.01"
    )
    # a run without a budget keeps its options as they were
    assert "--pipeline.time-budget-minutes" not in resume_command(["ns-train", "willags"], "willags", Path("/c"), 5)


# ---- row 25: kill -9 during training -> the last save is intact; the written command resumes it to the planned end


def _cli_config(args: list[str]):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    return tyro.cli(AnnotatedBaseConfigUnion, args=args)


def _ns_train_in_process(args: list[str]) -> None:
    """What `ns-train ARGS` does (nerfstudio.scripts.train.main), in this process."""
    from nerfstudio.scripts.train import main

    main(_cli_config(args))


@pytest.mark.timing
@pytest.mark.parametrize(
    ("where", "step", "saved"),
    [("step", 7, 6), ("save", 10, 8)],
    ids=["killed-inside-a-step", "killed-inside-a-save"],
)
def test_row25_sigkill_loses_nothing_beyond_the_last_save_and_the_written_command_resumes_to_the_planned_step(
    scene, tmp_path, where, step, saved
):
    """SIGKILL where the test chose, whatever the machine's speed: inside a training step (the parameters in memory
    one step ahead of the last save) or inside the write of a checkpoint (its partial file on disk)."""
    plan = 16
    args = ["willags", "--data", str(scene), "--output-dir", str(tmp_path / "run"), "--timestamp", "t"]
    args += ["--vis", "tensorboard", "--max-num-iterations", str(plan), "--steps-per-save", "2"]
    args += ["--pipeline.model.num-downscales", "0", "--pipeline.model.mask.vgg-weights", "seeded"]
    args += ["--pipeline.model.mask.warmup-steps", "1000"]  # no VGG in these few steps: the test stays fast
    marker = tmp_path / "paused"
    proc = launch_paused(args, where, step, marker)
    d = tmp_path / "run" / scene.name / "willags" / "t" / "nerfstudio_models"
    try:
        wait_until_paused(proc, marker)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    partial = [p for p in d.iterdir() if p.name.endswith(ck.PARTIAL_SUFFIX)]
    assert len(partial) == (where == "save"), partial  # killed mid-write: the partial file stays on disk
    found = list_checkpoints(d)
    assert found == [checkpoint_path(d, saved)], found  # partial files are never step-*.ckpt
    killed = read_checkpoint(found[0])
    assert int(killed["step"]) == saved

    # nothing lost beyond the save: the same run, uninterrupted, has the same state after that step
    _ns_train_in_process([*args[:4], str(tmp_path / "ref"), *args[5:], "--max-num-iterations", str(saved + 1)])
    ref = read_checkpoint(checkpoint_path(tmp_path / "ref" / scene.name / "willags" / "t" / "nerfstudio_models", saved))
    from tests.test_reliability import _state_equal

    _state_equal(ref["pipeline"], killed["pipeline"], "pipeline")
    _state_equal(ref["optimizers"], killed["optimizers"], "optimizers")

    # the written command resumes after that step and ends the run at its planned step
    command = (d.parent / ck.RESUME_FILE).read_text().strip()
    assert f"--load-checkpoint {found[0]} --max-num-iterations {plan - saved - 1}" in command, command
    words = shlex.split(command)
    assert words[0] == "ns-train"
    _ns_train_in_process(words[1:])
    assert list_checkpoints(d) == [checkpoint_path(d, plan - 1)], list_checkpoints(d)
    assert not [p for p in d.iterdir() if p.name.endswith(ck.PARTIAL_SUFFIX)]
    assert not (d.parent / ck.RESUME_FILE).exists()  # the run is complete: nothing left to resume


# ---- row 26: saves by wall time (an injected clock, no sleeping); row 28: the viewer's address once in a log


@pytest.mark.timing
def test_row26_saves_by_wall_time_and_row28_the_viewer_banner_prints_once(scene, tmp_path, capsys):
    assert not SaveTimer(0.0, clock=lambda: 1e9).due()  # 0 minutes: off
    config = _config(
        tmp_path, scene, steps=8, steps_per_save=10**6, save_every_minutes=2.5, save_only_latest_checkpoint=False
    )
    config.vis = "viewer+tensorboard"  # the viewer's address is the local writer's banner
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        config.viewer.websocket_port = s.getsockname()[1]
    config.viewer.quit_on_train_completion = True
    config.logging.steps_per_log = 1
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    minutes = [0.0]
    trainer.clock = lambda: 60.0 * minutes[0]
    orig = trainer.train_iteration

    def one_minute_per_step(step):
        out = orig(step)
        minutes[0] += 1.0
        return out

    trainer.train_iteration = one_minute_per_step
    try:
        trainer.train()
    finally:
        trainer.shutdown()
    # a save once 2.5 minutes passed since the last: after steps 2 (3 min) and 5 (6 min); the last step at the end
    steps = sorted(ck.checkpoint_step(p) for p in list_checkpoints(config.get_checkpoint_dir()))
    assert steps == [2, 5, 7]
    out = capsys.readouterr().out
    assert out.count("Viewer running locally") == 1, out[-3000:]
    assert "every 2.5 min" in out


# ---- row 27: progress output of long commands


def test_row27_progress_lines_in_a_log():
    import io

    from rich.console import Console

    from willags_ns.tools.progress import Progress, progress_line

    assert progress_line("x", 3, 10, 12.0) == "x: 3/10 (30%), 12 s, ~28 s left"
    assert progress_line("x", 10, 10, 200.0) == "x: 10/10 (100%), 3.3 min"
    buf = io.StringIO()
    t = [0.0]
    with Progress(console=Console(file=buf), clock=lambda: t[0], every_s=20.0, label="frames") as p:
        task = p.add_task("", total=60)
        for _ in range(60):
            t[0] += 1.0
            p.advance(task)
    # the first step (with the time left), then every 20 s, then the end
    assert buf.getvalue().splitlines() == [
        "frames: 1/60 (2%), 1 s, ~59 s left",
        "frames: 21/60 (35%), 21 s, ~39 s left",
        "frames: 41/60 (68%), 41 s, ~19 s left",
        "frames: 60/60 (100%), 60 s",
    ]
    # rich's track (nerfstudio's renders), whose updater thread reports nothing without a display
    buf = io.StringIO()
    t[0] = 0.0
    with Progress(console=Console(file=buf), clock=lambda: t[0], every_s=20.0, label="frames") as p:
        for _ in p.track(range(3)):
            t[0] += 5.0
    assert buf.getvalue().splitlines() == ["frames: 1/3 (33%), 5 s, ~10 s left", "frames: 3/3 (100%), 15 s"]


def test_row27_ns_eval_says_what_it_does_and_shows_progress_per_image_and_step(appearance_run, capsys):
    from nerfstudio.utils.eval_utils import eval_setup

    cfg, _, _ = appearance_run
    _, pipeline, _, _ = eval_setup(cfg, test_mode="test")
    pipeline.config.eval_protocol.max_images = 2
    capsys.readouterr()
    metrics = pipeline.get_average_eval_image_metrics()
    out = capsys.readouterr().out
    steps = pipeline.config.eval_protocol.steps
    assert "ns-eval: NeRF-W protocol on 2 test images: per image, " in out and f"{steps} Adam steps" in out
    for i in (1, 2):
        assert re.search(rf"image {i}/2 \S+ \(latent fit, left half at \d+x\d+ px\): 1/{steps} ", out), out
        assert re.search(rf"image {i}/2 .*: {steps}/{steps} \(100%\)", out), out
    # and the whole protocol's time left, from its first step
    assert re.search(rf"all 2 test images: 1/{2 * steps} \(\d+%\), \d+ s, ~[\d.]+ (s|min) left", out), out
    assert metrics["num_images"] == 2 and np.isfinite(metrics["psnr"])


def test_row27_render_and_export_print_the_appearance_and_the_written_path(appearance_run, tmp_path, capsys):
    from willags_ns.scripts.export import ExportGaussianSplat
    from willags_ns.scripts.render import DatasetRender

    cfg, names, seen = appearance_run
    i = seen[0]
    ExportGaussianSplat(load_config=cfg, output_dir=tmp_path / "ply", appearance=f"image:{i}").main()
    out = capsys.readouterr().out
    ply = tmp_path / "ply" / "splat.ply"
    assert ply.is_file()
    assert f"willags-export: appearance: image:{i} = training image {i} ({names[i]}), |z| = " in out
    assert re.search(
        rf"willags-export: wrote {re.escape(str(ply))}, \d+\.\d MB, from the checkpoint of step \d+ \(appearance: image:{i} ",
        out,
    ), out
    assert re.search(r"willags-export: writing [\d,]+ Gaussians to splat.ply: \d+/\d+ \(100%\)", out), out

    DatasetRender(load_config=cfg, output_path=tmp_path / "renders", split="test", rendered_output_names=["rgb"]).main()
    out = capsys.readouterr().out
    assert "willags-render: appearance: mean (the mean of the training images' latents)" in out
    assert re.search(r"^willags-render: frames: (\d+)/\1 \(100%\)", out, re.M), out  # progress, in a log too
    assert re.search(
        rf"willags-render: wrote {re.escape(str(tmp_path / 'renders'))}, from the checkpoint of step \d+ \(appearance: mean",
        out,
    ), out


def test_row27_the_ply_writer_writes_nerfstudios_bytes(tmp_path):
    from collections import OrderedDict

    from nerfstudio.scripts.exporter import ExportGaussianSplat as NsExport

    from willags_ns.scripts.export import write_ply

    rng = np.random.default_rng(0)
    n = 1000
    m = OrderedDict()
    for k in ("x", "y", "z"):
        m[k] = rng.standard_normal(n).astype(np.float32)
    m["red"] = rng.integers(0, 255, n).astype(np.uint8)
    m["f_dc_0"] = rng.standard_normal((n, 1))  # float64 [N, 1], written as float32 as nerfstudio does
    m["opacity"] = rng.standard_normal((n, 1)).astype(np.float32)
    NsExport.write_ply(str(tmp_path / "ns.ply"), n, m)
    write_ply(str(tmp_path / "ours.ply"), n, m)
    assert (tmp_path / "ours.ply").read_bytes() == (tmp_path / "ns.ply").read_bytes()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    with pytest.raises(ValueError, match="Count does not match"):
        write_ply(str(tmp_path / "bad.ply"), n + 1, m)
