"""A new user's path from photos to renders and exports, without traps (docs/reliability.md, "A user's path"): a run
loads from any working directory and only ever its own checkpoints, big photos, renders without ffmpeg, render
and export options that mean what they say, a readable start of ns-train. Each test names its row."""

import contextlib
import re
import shutil
from pathlib import Path

import pytest
import yaml

from benchmarks.scale import console_script
from tests.test_reliability_faults import _config, scene  # noqa: F401 - the module's 8+2-image scene fixture
from willags_ns.engine.checkpoints import CheckpointError, checkpoint_step, list_checkpoints

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def project(scene, tmp_path_factory):  # noqa: F811
    """A run as `ns-train willags --data scene` writes it from a project folder: output_dir `outputs` and the data
    `scene`, both relative to that folder; checkpoints of steps 2 and 3. Returns (project folder, config.yml)."""
    trained = _config(tmp_path_factory.mktemp("trained"), scene, steps=4, steps_per_save=2)
    trained.save_only_latest_checkpoint = False
    trainer = trained.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    proj = tmp_path_factory.mktemp("project")
    shutil.copytree(scene, proj / "scene")
    config = yaml.load((trained.get_base_dir() / "config.yml").read_text(), Loader=yaml.Loader)
    config.output_dir = Path("outputs")
    config.pipeline.datamanager.data = Path("scene")
    config.pipeline.datamanager.dataparser.data = Path("scene")
    run = proj / config.get_base_dir()
    shutil.copytree(trained.get_base_dir(), run)
    (run / "config.yml").write_text(yaml.dump(config), "utf8")
    assert [p.name for p in list_checkpoints(run / "nerfstudio_models")][:2] == [
        "step-000000003.ckpt",
        "step-000000002.ckpt",
    ]
    return proj, run / "config.yml"


def test_row_u1_a_run_loads_from_any_working_directory(project, tmp_path, monkeypatch):
    from nerfstudio.utils.eval_utils import eval_setup

    proj, cfg = project
    monkeypatch.chdir(tmp_path)  # neither outputs/ nor scene/ exist here
    config, pipeline, loaded, step = eval_setup(cfg, test_mode="test")
    assert loaded == cfg.parent / "nerfstudio_models" / "step-000000003.ckpt" and step == 3
    assert len(pipeline.datamanager.eval_dataset) == 2  # the scene found relative to where training ran
    assert config.get_base_dir().resolve() == cfg.parent.resolve()  # files written into the run folder land there
    assert not (tmp_path / "outputs").exists()


def _copy_of(project, dest: Path) -> Path:
    proj, cfg = project
    shutil.copytree(proj, dest)
    return dest / cfg.relative_to(proj)


def test_row_u2_a_copy_loads_its_own_checkpoints_never_the_originals(project, tmp_path, monkeypatch):
    from nerfstudio.utils.eval_utils import eval_setup

    proj, cfg = project
    copy_cfg = _copy_of(project, tmp_path / "copy")
    ckpts = copy_cfg.parent / "nerfstudio_models"
    monkeypatch.chdir(proj)  # from here the stored relative paths name the original run
    _, _, loaded, step = eval_setup(copy_cfg, test_mode="inference")
    assert loaded == ckpts / "step-000000003.ckpt" and step == 3

    # its newest checkpoint truncated: named, and the copy's older one loads (not the original's newest)
    newest = ckpts / "step-000000003.ckpt"
    newest.write_bytes(newest.read_bytes()[:5000])
    with pytest.warns(UserWarning, match=re.escape(str(newest))):
        _, _, loaded, step = eval_setup(copy_cfg, test_mode="inference")
    assert loaded == ckpts / "step-000000002.ckpt" and step == 2

    # every checkpoint of the copy damaged: an error naming them, never the original run's readable ones
    for p in list_checkpoints(ckpts):
        p.write_bytes(b"")
    with pytest.raises(CheckpointError, match=re.escape(str(ckpts))) as info:
        eval_setup(copy_cfg, test_mode="inference")
    assert "\n" not in str(info.value)

    # no checkpoint folder beside the copied config.yml: an error, not the folder its stored paths name
    shutil.rmtree(ckpts)
    with pytest.raises(CheckpointError, match=re.escape(str(ckpts))):
        eval_setup(copy_cfg, test_mode="inference")


def _no_loading(monkeypatch):
    """Loading a checkpoint fails the test: what is refused must be refused before it."""
    from nerfstudio.scripts import render as ns_render

    def eval_setup(*args, **kwargs):
        raise AssertionError("the checkpoint was loaded")

    monkeypatch.setattr(ns_render, "eval_setup", eval_setup)


def test_row_u5_a_video_without_ffmpeg_is_refused_before_loading_and_images_need_none(
    appearance_run, tmp_path, monkeypatch
):
    from willags_ns.scripts import render

    cfg, _, _ = appearance_run
    monkeypatch.setattr(render.shutil, "which", lambda name: None)  # no ffmpeg on the PATH
    with monkeypatch.context() as m:
        _no_loading(m)
        with pytest.raises(SystemExit) as info:
            render.RenderInterpolated(load_config=cfg, output_path=tmp_path / "v.mp4").main()
        assert "\n" not in str(info.value.code) and "--output-format images" in str(info.value.code)
    render.RenderInterpolated(
        load_config=cfg, output_path=tmp_path / "v.mp4", output_format="images", interpolation_steps=2
    ).main()
    assert sorted((tmp_path / "v").glob("*.jpg"))


def test_row_u6_downscale_below_one_is_refused_and_interpolated_frames_all_differ(
    appearance_run, tmp_path, monkeypatch
):
    import numpy as np
    from PIL import Image

    from willags_ns.scripts import render

    cfg, _, _ = appearance_run
    with monkeypatch.context() as m:
        _no_loading(m)
        with pytest.raises(SystemExit):
            render.RenderInterpolated(load_config=cfg, output_path=tmp_path / "x.mp4", downscale_factor=0.5).main()
    out = tmp_path / "path.mp4"
    opts = dict(pose_source="train", interpolation_steps=3, output_format="images", image_format="png")
    render.RenderInterpolated(load_config=cfg, output_path=out, downscale_factor=2, **opts).main()
    frames = [np.asarray(Image.open(p)) for p in sorted((tmp_path / "path").glob("*.png"))]
    assert len(frames) >= 4
    for a, b in zip(frames, frames[1:], strict=False):
        assert not np.array_equal(a, b)  # each frame a new viewpoint: no repeated camera at the transitions
    full = render.RenderInterpolated(load_config=cfg, output_path=tmp_path / "full.mp4", **opts)
    full.main()
    big = np.asarray(Image.open(sorted((tmp_path / "full").glob("*.png"))[0]))
    assert frames[0].shape[0] == big.shape[0] // 2  # a factor of 2 renders at half the size


def test_row_u7_dataset_render_of_the_test_split_downscaled(appearance_run, tmp_path, capsys):
    from PIL import Image

    from willags_ns.scripts import render

    cfg, _, _ = appearance_run
    out = tmp_path / "ds"
    render.DatasetRender(
        load_config=cfg, output_path=out, split="test", downscale_factor=2, rendered_output_names=["rgb"]
    ).main()
    images = sorted(out.rglob("*.jpg")) + sorted(out.rglob("*.png"))
    assert images
    yml = yaml.load(cfg.read_text(), Loader=yaml.Loader)
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(cfg, test_mode="test")
    h = int(pipeline.datamanager.eval_dataset.cameras[0].height)
    with Image.open(images[0]) as im:
        assert im.height == h // 2
    assert yml.pipeline.datamanager.dataparser.downscale_factor is None  # the run's own config is left as it was
    captured = capsys.readouterr().out
    assert "{}" not in captured and "test" in captured

    # a run that trained at 1/2 of its photos' size (photos above 1600 px, or its own --downscale-factor 2): the
    # factor still counts from the training size, as for the trajectory renders (the photos are read at 1/4)
    copy = tmp_path / "run-at-half"
    shutil.copytree(cfg.parent, copy)
    yml.pipeline.datamanager.dataparser.downscale_factor = 2
    (copy / "config.yml").write_text(yaml.dump(yml), "utf8")
    for factor, want in ((None, h // 2), (2, h // 4)):
        out = tmp_path / f"half-{factor}"
        render.DatasetRender(
            load_config=copy / "config.yml",
            output_path=out,
            split="test",
            downscale_factor=factor,
            rendered_output_names=["rgb"],
        ).main()
        with Image.open(sorted(out.rglob("*.jpg"))[0]) as im:
            assert im.height == want, (factor, im.size, h)
    assert "1/2 of the training size (the run trained at 1/2 of its photos' size: they are read at 1/4)" in (
        capsys.readouterr().out
    )


def test_row_u8_export_needs_only_the_run_not_the_photos(project, tmp_path, monkeypatch):
    from nerfstudio.utils.eval_utils import eval_setup

    from willags_ns.data.dataparser import WillagsDataError
    from willags_ns.scripts.export import ExportGaussianSplat

    copy_cfg = _copy_of(project, tmp_path / "copy")
    shutil.rmtree(tmp_path / "copy" / "scene")  # the photos moved away
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "export"
    ExportGaussianSplat(load_config=copy_cfg, output_dir=out, appearance="image:1").main()
    from plyfile import PlyData

    assert len(PlyData.read(str(out / "splat.ply"))["vertex"]) > 0
    # what does read the photos says which are missing, in one line (the record names the photos where they were:
    # here, as if this copy had trained from its own scene folder)
    import torch

    record_path = copy_cfg.parent / "scene_cameras.pt"
    record = torch.load(record_path)
    for part in ("train", "test"):
        record[part]["names"] = [str(tmp_path / "copy" / "scene" / Path(n).name) for n in record[part]["names"]]
    torch.save(record, record_path)
    _, pipeline, _, _ = eval_setup(copy_cfg, test_mode="test")
    with pytest.raises(WillagsDataError, match="do not exist"):
        pipeline.get_average_eval_image_metrics()


def test_row_u9_a_missing_scene_is_one_line_without_an_auto_config_note(tmp_path):
    """`ns-train willags --data <a path that does not exist>`: the dataparser's line names the path; no line before it
    says that training goes on with the method's own configuration, or where the run that never starts would have
    written its checkpoints and config.yml: that line is all (beside nerfstudio's note on the --data alias)."""
    import os
    import subprocess

    from tests.test_reliability import _ns_train

    nowhere = tmp_path / "scenes" / "nowhere"
    bad = subprocess.run(
        _ns_train(["willags", "--data", str(nowhere), "--output-dir", str(tmp_path / "out")]),
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        timeout=600,
    )
    text = bad.stdout + bad.stderr
    assert bad.returncode == 1 and "Traceback" not in text
    assert f"{nowhere} does not exist" in text
    assert "auto-config" not in text and "training with the method's own configuration" not in text
    assert not (tmp_path / "out").exists()
    said = [ln for ln in text.splitlines() if ln.strip() and "Using --data alias" not in ln]
    assert len(said) == 1 and said[0].startswith("willags: ") and str(nowhere) in said[0], text


def test_row_u9_ns_train_starts_readably_and_a_bad_scene_leaves_no_run_folder(scene, tmp_path):  # noqa: F811
    import os
    import subprocess

    from tests.test_reliability import _ns_train

    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    bad = subprocess.run(
        _ns_train(["willags", "--data", str(tmp_path / "nowhere"), "--output-dir", str(tmp_path / "bad")]),
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert bad.returncode == 1 and "Traceback" not in bad.stderr
    assert not (tmp_path / "bad").exists()  # no run folder, no config.yml, for a run that never started

    out = tmp_path / "good"
    args = ["willags", "--data", str(scene), "--output-dir", str(out), "--vis", "tensorboard"]
    args += ["--max-num-iterations", "2", "--pipeline.model.mask.vgg-weights", "seeded"]
    good = subprocess.run(_ns_train(args), capture_output=True, text=True, env=env, timeout=600)
    assert good.returncode == 0, good.stderr[-3000:]
    text = good.stdout + good.stderr
    before = text.split("willags: checkpoints every")[0]  # printed as the first step starts
    assert len(before.splitlines()) <= 40, before
    assert "Warning:" not in text  # no FutureWarning / UserWarning a user cannot act on
    assert len(list(out.rglob("config.yml"))) == 1  # the full configuration is in the run folder


def _as_from_a_terminal(cmd: list[str], cwd: Path, stderr: int):
    """`cmd` started as from a terminal, for Ctrl-C: a suite started in the background (`make test &`, CI runners)
    hands its children SIGINT ignored, and Python then never raises KeyboardInterrupt; the child gets the terminal's
    default disposition. Unbuffered text output on a pipe; stderr: subprocess.PIPE or subprocess.STDOUT."""
    import os
    import signal
    import subprocess

    return subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        cwd=cwd,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


@pytest.mark.timing
def test_row_u9_ctrl_c_on_ns_viewer_stops_without_a_traceback(project, tmp_path):
    import signal
    import socket
    import subprocess
    import time

    proj, cfg = project
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    exe = console_script("ns-viewer")
    cmd = [str(exe), "--load-config", str(cfg), "--viewer.websocket-port", str(port)]
    proc = _as_from_a_terminal(cmd, tmp_path, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 300
        while True:  # serving: its port accepts connections
            assert proc.poll() is None and time.time() < deadline, proc.communicate()[1][-3000:]
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=600)  # bounds a hang only
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "Traceback" not in out + err, err[-3000:]
    assert proc.returncode == 130 and "willags: stopped (Ctrl-C)" in err, (proc.returncode, err[-3000:])


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.timing
def test_row_u9_ctrl_c_on_a_viewer_kept_after_training_closes_it_in_one_line(scene, tmp_path):  # noqa: F811
    """ns-train --viewer.quit-on-train-completion False keeps the viewer after training, saying so in one line with
    the way out; that Ctrl-C ends it with one line and exit status 0, the run complete, no traceback."""
    import signal
    import subprocess

    from tests.test_reliability import _ns_train

    out = tmp_path / "outputs"
    args = ["willags", "--data", str(scene), "--output-dir", str(out), "--viewer.websocket-port", str(_free_port())]
    args += ["--max-num-iterations", "2", "--pipeline.model.mask.vgg-weights", "seeded"]
    args += ["--viewer.quit-on-train-completion", "False"]
    proc = _as_from_a_terminal(_ns_train(args), tmp_path, stderr=subprocess.STDOUT)
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:  # the run ends, then the viewer waits
            lines.append(line)
            if line.startswith("willags: training is complete"):
                break
        assert "Ctrl-C ends ns-train" in lines[-1], "".join(lines)[-3000:]
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=600)  # bounds a hang only
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "".join(lines) + rest
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text[-3000:]
    assert proc.returncode == 0, (proc.returncode, text[-3000:])
    closed = [ln for ln in rest.splitlines() if ln.startswith("willags: viewer closed (Ctrl-C); the run is complete:")]
    assert len(closed) == 1, rest[-3000:]
    (cfg,) = out.rglob("config.yml")
    assert closed[0].endswith(str(cfg)) and list((cfg.parent / "nerfstudio_models").glob("step-000000001.ckpt"))


def test_row_u14_ns_train_ends_when_training_ends(scene, tmp_path):  # noqa: F811
    """ns-train with its viewer (the default --vis) and nobody connected to it: the process ends by itself once
    training is complete, exit status 0, the checkpoint written; it does not wait for a Ctrl-C."""
    import os
    import subprocess

    from tests.test_reliability import _ns_train

    out = tmp_path / "outputs"
    args = ["willags", "--data", str(scene), "--output-dir", str(out), "--viewer.websocket-port", str(_free_port())]
    args += ["--max-num-iterations", "2", "--pipeline.model.mask.vgg-weights", "seeded"]
    try:
        res = subprocess.run(
            _ns_train(args), capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}, timeout=600
        )
    except subprocess.TimeoutExpired as e:  # bounds a hang only: the process waited after training
        raise AssertionError(f"ns-train did not end after training: {str(e.stdout)[-3000:]}") from None
    text = res.stdout + res.stderr
    assert res.returncode == 0, text[-3000:]
    assert "Use ctrl+c to quit" not in text and "stays open" not in text, text[-3000:]
    (cfg,) = out.rglob("config.yml")
    assert list((cfg.parent / "nerfstudio_models").glob("step-000000001.ckpt"))


@pytest.mark.timing
def test_row_u14_a_browser_connected_at_the_end_keeps_the_viewer_until_it_leaves(scene, tmp_path):  # noqa: F811
    """A browser connected to the viewer when training ends: one line says the viewer stays open while it is
    connected and how to leave; when it disconnects, ns-train ends (status 0)."""
    import time

    import msgspec
    from websockets.sync.client import connect

    from tests._paused_ns_train import launch_paused, wait_until_paused

    port = _free_port()
    out = tmp_path / "outputs"
    args = ["willags", "--data", str(scene), "--output-dir", str(out), "--viewer.websocket-port", str(port)]
    args += ["--max-num-iterations", "3", "--pipeline.model.mask.vgg-weights", "seeded"]
    marker = tmp_path / "paused"
    proc = launch_paused(args, "viewer", 1, marker)  # waits in step 1 until a browser is connected
    log = marker.with_suffix(".log")
    # what a browser sends first: its camera (viser counts a client from then on)
    camera = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, 3.0]}
    camera |= {"fov": 1.0, "aspect": 1.5, "look_at": [0.0, 0.0, 0.0], "up_direction": [0.0, 0.0, 1.0]}
    try:
        wait_until_paused(proc, marker)
        with connect(f"ws://127.0.0.1:{port}", open_timeout=600, max_size=None) as browser:
            browser.send(msgspec.msgpack.encode(camera))  # training goes on and ends with the browser connected
            deadline = time.monotonic() + 600  # bounds a hang only
            while "willags: training is complete" not in log.read_text(errors="replace"):
                assert proc.poll() is None and time.monotonic() < deadline, log.read_text(errors="replace")[-3000:]
                with contextlib.suppress(TimeoutError):
                    browser.recv(timeout=0.2)
            assert proc.poll() is None  # still serving the browser
        proc.wait(timeout=600)  # the browser left: ns-train ends
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log.read_text(errors="replace")
    assert proc.returncode == 0, text[-3000:]
    (said,) = [ln for ln in text.splitlines() if ln.startswith("willags: training is complete")]
    assert "while a browser is connected" in said and "Ctrl-C" in said, said
    assert "Traceback" not in text, text[-3000:]


def test_row_u11_an_export_of_a_damaged_only_checkpoint_writes_nothing(project, tmp_path):
    """willags-export whose only checkpoint is truncated: one line naming it, and no output folder left behind (the
    folder it made, empty); a folder that existed before is kept."""
    from willags_ns.scripts.export import ExportGaussianSplat

    copy_cfg = _copy_of(project, tmp_path / "copy")
    ckpts = list_checkpoints(copy_cfg.parent / "nerfstudio_models")
    for p in ckpts[1:]:
        p.unlink()
    ckpts[0].write_bytes(ckpts[0].read_bytes()[:5000])
    out = tmp_path / "exports" / "trunc"
    with pytest.raises(CheckpointError, match=re.escape(str(ckpts[0]))):
        ExportGaussianSplat(load_config=copy_cfg, output_dir=out).main()
    assert not (tmp_path / "exports").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    with pytest.raises(CheckpointError):
        ExportGaussianSplat(load_config=copy_cfg, output_dir=mine).main()
    assert mine.is_dir()


def test_row_u11_an_export_past_a_damaged_newest_checkpoint_warns_once_and_names_the_step(project, tmp_path):
    """willags-export whose newer of two checkpoints is truncated: the real command says so in one line (not also
    as a Python UserWarning with its source line) and the line naming the PLY names the step exported."""
    import os
    import subprocess

    copy_cfg = _copy_of(project, tmp_path / "copy")
    newest, older = list_checkpoints(copy_cfg.parent / "nerfstudio_models")[:2]
    newest.write_bytes(newest.read_bytes()[:5000])
    exe = console_script("willags-export")
    out = tmp_path / "exports"
    res = subprocess.run(
        [str(exe), "--load-config", str(copy_cfg), "--output-dir", str(out)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "400"},
        timeout=600,
    )
    text = res.stdout + res.stderr
    assert res.returncode == 0, text[-3000:]
    assert len([ln for ln in text.splitlines() if newest.name in ln]) == 1, text
    assert "Warning" not in text, text
    (wrote,) = [ln for ln in text.splitlines() if "wrote" in ln and "splat.ply" in ln]
    assert f"step {checkpoint_step(older)}" in wrote, wrote


def test_row_u12_a_test_photo_as_image_spec_is_named_with_the_spec_that_fits(appearance_run, tmp_path):
    """willags-render --appearance image:NAME where NAME is one of the run's test photos: refused in one line that
    says it is a test photo and gives photo:PATH, which renders."""
    from nerfstudio.utils.eval_utils import eval_setup

    from willags_ns.scripts import render

    cfg, names, _ = appearance_run
    _, pipeline, _, _ = eval_setup(cfg, test_mode="inference")
    test_photo = Path(pipeline.datamanager.eval_dataset.image_filenames[0])
    assert test_photo.name not in names
    opts = dict(split="test", rendered_output_names=["rgb"])
    with pytest.raises(SystemExit) as info:
        render.DatasetRender(
            load_config=cfg, output_path=tmp_path / "r", appearance=f"image:{test_photo.name}", **opts
        ).main()
    message = str(info.value.code)
    assert "\n" not in message and "test photo" in message, message
    (spec,) = re.findall(r"photo:\S+", message)
    assert Path(spec.removeprefix("photo:")).resolve() == test_photo.resolve()
    render.DatasetRender(load_config=cfg, output_path=tmp_path / "ok", appearance=spec, refine_steps=2, **opts).main()
    assert sorted((tmp_path / "ok").rglob("*.jpg")) + sorted((tmp_path / "ok").rglob("*.png"))


class _PipeReader:
    """The read end of a pipe a child process writes to, read in a thread (so the child never blocks on a full pipe)
    until :meth:`close` closes it, as `tee` does when a Ctrl-C ends it: the child's next write to the pipe fails."""

    def __init__(self):
        import os
        import threading

        self.r, self.w = os.pipe()
        self.data = bytearray()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        import os
        import select

        while not self._stop.is_set():
            if select.select([self.r], [], [], 0.05)[0]:
                chunk = os.read(self.r, 1 << 16)
                if not chunk:  # the writer ended
                    break
                self.data += chunk
        os.close(self.r)

    def started(self) -> None:
        """The child has its copy of the write end: drop ours, so the pipe ends when the child does."""
        import os

        os.close(self.w)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()

    def text(self, timeout: float = 600) -> str:
        """Everything read, once the writer has ended (the timeout bounds a hang only)."""
        self._thread.join(timeout)
        return self.data.decode(errors="replace")


@pytest.mark.timing
@pytest.mark.parametrize("how", ["ctrl-c through a pipe", "hang-up", "closed stdout"])
def test_row_u15_a_stop_through_a_closed_pipe_still_writes_the_checkpoint_and_the_resume_command(
    how,
    scene,  # noqa: F811
    tmp_path,
):
    """`ns-train ... | tee log` then Ctrl-C (tee ends with it: the output's reader is gone when the interrupt
    writes), a closed terminal (SIGHUP, and nothing reads stdout or stderr any more), and a stdout closed while
    training (`| head`): each stops after the step with its checkpoint and resume_command.txt naming it; the resume
    line reaches stderr when it is still read."""
    import signal

    from tests._paused_ns_train import launch_paused, wait_until_paused

    out = tmp_path / "outputs"
    args = ["willags", "--data", str(scene), "--output-dir", str(out), "--vis", "tensorboard", "--timestamp", "t"]
    args += ["--max-num-iterations", "1000", "--logging.steps-per-log", "1"]
    args += ["--pipeline.model.mask.vgg-weights", "seeded"]
    stdout, stderr = _PipeReader(), _PipeReader()
    marker = tmp_path / "paused"
    proc = launch_paused(args, "step", 3, marker, stdout=stdout.w, stderr=stderr.w)
    stdout.started()
    stderr.started()
    try:
        wait_until_paused(proc, marker)
        stdout.close()
        if how == "hang-up":
            stderr.close()
        signal_of = {"ctrl-c through a pipe": signal.SIGINT, "hang-up": signal.SIGHUP, "closed stdout": signal.SIGUSR1}
        proc.send_signal(signal_of[how])  # SIGUSR1: go on training, with nobody reading stdout
        proc.wait(timeout=600)  # bounds a hang only
    finally:
        if proc.poll() is None:
            proc.kill()
    err = stderr.text() if how != "hang-up" else ""
    assert proc.returncode == {"ctrl-c through a pipe": 130, "hang-up": 129, "closed stdout": 141}[how], err[-3000:]
    run = out / "scene" / "willags" / "t"
    ckpts = list_checkpoints(run / "nerfstudio_models")
    assert len(ckpts) == 1, (ckpts, err[-3000:])
    step = checkpoint_step(ckpts[0])
    assert step is not None and (step == 3 if how != "closed stdout" else step >= 3)
    resume = (run / "resume_command.txt").read_text()
    assert str(ckpts[0]) in resume and f"--max-num-iterations {999 - step}" in resume, resume
    if how != "hang-up":
        assert "Traceback" not in err, err[-3000:]
        assert resume.strip() in err, err[-3000:]  # the resume line, on the terminal


@pytest.mark.timing
def test_row_u16_the_resume_command_goes_on_in_the_same_run_folder_counting_to_its_end(scene, tmp_path):  # noqa: F811
    """Ctrl-C after step 2 of 8, then the written resume command: training goes on in the same run folder (one
    config.yml, the checkpoints of both parts side by side, resume_command.txt gone at the end), and the step
    table's progress counts to the run's end (step s of 8 reads s/8, never above 100 %)."""
    import os
    import shlex
    import signal
    import subprocess

    from tests._paused_ns_train import launch_paused, wait_until_paused

    out = tmp_path / "outputs"
    args = ["willags", "--data", str(scene), "--output-dir", str(out), "--vis", "tensorboard"]
    args += ["--max-num-iterations", "8", "--logging.steps-per-log", "1"]
    args += ["--pipeline.model.mask.vgg-weights", "seeded", "--save-only-latest-checkpoint", "False"]
    marker = tmp_path / "paused"
    proc = launch_paused(args, "step", 2, marker)
    try:
        wait_until_paused(proc, marker)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=600)  # bounds a hang only
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, marker.with_suffix(".log").read_text(errors="replace")[-3000:]
    (run,) = [p.parent for p in out.rglob("config.yml")]
    command = shlex.split((run / "resume_command.txt").read_text())
    assert command[0] == "ns-train"
    exe = console_script("ns-train")
    res = subprocess.run(
        [exe, *command[1:]], capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}, timeout=600
    )
    text = res.stdout + res.stderr
    assert res.returncode == 0, text[-3000:]
    assert [p.parent for p in out.rglob("config.yml")] == [run], text[-3000:]  # the same folder, no second one
    steps = sorted(checkpoint_step(p) for p in list_checkpoints(run / "nerfstudio_models"))
    assert steps == [2, 7], steps
    assert not (run / "resume_command.txt").exists()  # the run is complete
    rows = [(int(m[1]), float(m[2])) for m in re.finditer(r"^(\d+) \(([\d.]+)%\)", res.stdout, re.M)]
    assert sorted({s for s, _ in rows}) == list(range(3, 8)), res.stdout[-3000:]  # the last one again at the end
    for s, pct in rows:
        assert pct == pytest.approx(100 * s / 8, abs=0.01), (s, pct)


def test_the_end_of_a_run_waits_for_the_viewers_render_threads():
    """A browser that leaves mid-frame: nerfstudio's render thread (a daemon) still draws that frame; the run's end
    stops and joins it, so the interpreter never exits under a thread inside torch (status -6)."""
    import threading

    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    from willags_ns.engine.trainer import join_render_threads

    class Drawing(RenderStateMachine):
        def __init__(self):  # no viewer: only the thread and its loop flag
            threading.Thread.__init__(self, daemon=True)
            self.running = True
            self.in_frame = threading.Event()

        def run(self):
            while self.running:
                self.in_frame.set()
                threading.Event().wait(0.05)  # a frame being drawn

    thread = Drawing()
    thread.start()
    assert thread.in_frame.wait(30)
    join_render_threads(timeout_s=30)
    assert not thread.is_alive() and thread.running is False
