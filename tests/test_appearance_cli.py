"""willags-render / willags-export / willags-latents on a small trained checkpoint (nerfstudio's own render and export
classes with --appearance). Runs are in-process (the commands' `main()`, small frames); one subprocess checks the
command line itself."""

import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

pytestmark = pytest.mark.slow


def _frames(out: Path) -> list[np.ndarray]:
    pngs = sorted(out.rglob("*.png"))
    assert pngs, f"nothing rendered under {out}"
    return [np.asarray(Image.open(p)).astype(np.float32) for p in pngs]


def _interpolate(cfg: Path, out: Path, **kw) -> list[np.ndarray]:
    """willags-render interpolate over the eval cameras, one step between each pair, frames at 1/4 size."""
    from willags_ns.scripts.render import RenderInterpolated

    RenderInterpolated(
        load_config=cfg,
        output_path=out,
        pose_source="eval",
        interpolation_steps=1,
        downscale_factor=4.0,
        output_format="images",  # no ffmpeg needed
        image_format="png",
        **kw,
    ).main()
    return _frames(out)


def _diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).mean())


def test_render_sweeps_interp_along_the_path_and_camera_idx_picks_the_image(appearance_run, tmp_path):
    cfg, names, seen = appearance_run
    i = seen[0]
    sweep = _interpolate(cfg, tmp_path / "sweep", appearance=f"interp:image:{i},sample:3")
    start = _interpolate(cfg, tmp_path / "image", appearance=f"image:{names[i]}")
    end = _interpolate(cfg, tmp_path / "sample", appearance="sample:3")
    assert len(sweep) == len(start) == len(end) >= 3
    assert _diff(sweep[0], start[0]) < 0.5 and _diff(sweep[-1], end[-1]) < 0.5  # T = 0 ... 1 along the path
    assert _diff(start[-1], end[-1]) > 1.0  # the two appearances differ visibly
    mid = len(sweep) // 2
    assert _diff(sweep[mid], start[mid]) > 0.2 and _diff(sweep[mid], end[mid]) > 0.2
    # ns-render's --camera-idx N: training image N's appearance
    by_idx = _interpolate(cfg, tmp_path / "camidx", camera_idx=i)
    assert _diff(by_idx[0], start[0]) < 0.5


def test_latents_are_written_at_the_named_path_and_a_failed_write_keeps_the_previous_file(tmp_path, monkeypatch):
    import errno

    from willags_ns.engine.checks import WillagsIOError
    from willags_ns.scripts import latents as lt

    lat, seen = np.arange(6, dtype=np.float32).reshape(3, 2), np.array([True, False, True])
    path = lt.write_latents(tmp_path / "z", lat, ["a.jpg", "b.jpg", "c.jpg"], seen)  # no ".npz" added
    assert path == tmp_path / "z" and sorted(p.name for p in tmp_path.iterdir()) == ["z"]
    before = path.read_bytes()
    savez = np.savez

    def half_then_disk_full(f, **arrays):
        savez(f, **arrays)
        f.truncate(f.tell() // 2)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(lt.np, "savez", half_then_disk_full)
    with pytest.raises(WillagsIOError, match=rf"^no space left on {re.escape(str(tmp_path))}: z needs about "):
        lt.write_latents(path, lat * 2, ["a.jpg", "b.jpg", "c.jpg"], seen)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["z"]
    monkeypatch.undo()
    with pytest.raises(WillagsIOError, match=rf"^cannot write {re.escape(str(tmp_path / 'none' / 'z.npz'))}: "):
        lt.write_latents(tmp_path / "none" / "z.npz", lat, ["a.jpg", "b.jpg", "c.jpg"], seen)


def test_latents_export_and_latent_file_spec(appearance_run, tmp_path):
    from willags_ns.scripts.latents import ExportLatents, main

    cfg, names, seen = appearance_run
    data = np.load(main(ExportLatents(load_config=cfg, output=tmp_path / "latents.npz")))
    assert list(data["names"]) == names and data["latents"].shape[0] == len(names)
    assert data["seen"][seen].all() and np.isfinite(data["latents"]).all()
    i = seen[-1]
    np.save(tmp_path / "z.npy", data["latents"][i])
    # a saved row is a latent: SPEC giving exactly that image's appearance (checked on the latent: rendering it
    # is the same code path as every other SPEC, exercised above)
    from nerfstudio.utils.eval_utils import eval_setup

    from willags_ns.appearance_spec import resolve_latent

    _, pipeline, _, _ = eval_setup(cfg, test_mode="inference")
    z_file = resolve_latent(f"latent:{tmp_path / 'z.npy'}", pipeline.model)
    assert torch.equal(z_file, resolve_latent(f"image:{names[i]}", pipeline.model))


def test_willags_export_bakes_the_chosen_appearance(appearance_run, tmp_path):
    from plyfile import PlyData

    from willags_ns.scripts.export import ExportGaussianSplat

    cfg, _, seen = appearance_run
    dc = []
    for spec in (f"image:{seen[0]}", "sample:4"):
        out = tmp_path / spec.replace(":", "_")
        ExportGaussianSplat(load_config=cfg, output_dir=out, appearance=spec).main()
        v = PlyData.read(str(out / "splat.ply"))["vertex"]
        dc.append(np.stack([v["f_dc_0"], v["f_dc_1"], v["f_dc_2"]], 1))
        assert np.isfinite(dc[-1]).all()
    assert dc[0].shape == dc[1].shape and not np.allclose(dc[0], dc[1])


def test_cli_photo_with_refinement_and_bad_specs_name_the_bad_part(appearance_run, tmp_path):
    from nerfstudio.utils.eval_utils import eval_setup

    from willags_ns.scripts.render import DatasetRender, choose_appearance

    cfg, _, _ = appearance_run
    photo = tmp_path / "photo.png"
    Image.fromarray((np.random.default_rng(2).random((40, 60, 3)) * 255).astype(np.uint8)).save(photo)
    cmd = [sys.executable, "-m", "willags_ns.scripts.render", "dataset", "--load-config", str(cfg), "--split", "test"]
    cmd += ["--rendered-output-names", "rgb", "--image-format", "png", "--output-path", str(tmp_path / "photo")]
    cmd += ["--appearance", f"photo:{photo}", "--refine-steps", "3", "--refine-view", "0", "--refine-starts", "4"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, (res.stdout[-2000:], res.stderr[-2000:])
    assert _frames(tmp_path / "photo")
    assert "and 4 training latents" in res.stdout + res.stderr  # --refine-starts reached the fit's description

    # syntax errors fail before the checkpoint loads; resolution errors name the bad part too
    with pytest.raises(SystemExit, match="seed must be an integer, got '1.5'"):
        DatasetRender(load_config=cfg, output_path=tmp_path / "bad", appearance="sample:1.5").main()
    with pytest.raises(SystemExit, match="a still needs the weight"):
        DatasetRender(load_config=cfg, output_path=tmp_path / "bad", appearance="interp:image:0,sample:1").main()
    _, pipeline, _, _ = eval_setup(cfg, test_mode="inference")
    d = int(pipeline.model.train_latents.shape[1])
    np.save(tmp_path / "nan.npy", np.full(d, np.nan, np.float32))
    (tmp_path / "junk.jpg").write_bytes(b"not a jpeg")
    bad = {
        "image:nope": "unknown training image 'nope'",
        f"photo:{tmp_path / 'missing.jpg'}": "missing.jpg': no such file",
        f"photo:{tmp_path / 'junk.jpg'}": "junk.jpg' as an image",
        f"latent:{tmp_path / 'nan.npy'}": "nan.npy' holds NaN or Inf",
    }
    for spec, msg in bad.items():
        opts = SimpleNamespace(appearance=spec, refine_steps=0, refine_view=None, camera_idx=None)
        with pytest.raises(ValueError, match=msg):
            choose_appearance(pipeline, opts)


def test_demo_appearance_grid_is_labelled_and_large(appearance_run, tmp_path):
    """The demo's picture: rows of labelled tiles (training photos, their appearances, a new photo's, two samples,
    an interpolation), tiles upscaled 2x."""
    from nerfstudio.utils.eval_utils import eval_setup

    from willags_ns.scripts.demo import appearance_grid, labelled_grid

    # the layout, known answer: 2 rows of 10x8 tiles at 2x, white background, dark label text under each tile
    tiles = [("a", np.zeros((8, 10, 3), np.uint8)), ("b", np.full((8, 10, 3), 200, np.uint8))]
    g = labelled_grid([("row one", tiles), ("row two", tiles[:1])], scale=2, pad=6)
    assert g.shape == (6 + 2 * (24 + 16 + 20 + 6), 6 + 2 * (20 + 6), 3)
    assert (g[30:46, 6:26] == 0).all() and (g[30:46, 32:52] == 200).all()  # first row's tiles, upscaled
    assert (g[46:66, 6:26] < 128).any() and (g[46:66, 6:26] == 255).any()  # a label under the first tile

    cfg, _, _ = appearance_run
    _, pipeline, _, _ = eval_setup(cfg, test_mode="test")
    grid = appearance_grid(pipeline, tmp_path)
    h, w = (
        pipeline.datamanager.eval_dataset.cameras[0].height.item(),
        pipeline.datamanager.eval_dataset.cameras[0].width.item(),
    )
    assert grid.shape[0] == 6 + 4 * (24 + 2 * h + 20 + 6)  # photos, appearances, new photo + samples, interpolation
    assert grid.shape[1] == 6 + 5 * (2 * w + 6)  # the widest row: 5 interpolation steps
    assert (tmp_path / "new_photo.png").exists()


def test_demo_views_label_the_photo_and_the_render(appearance_run, tmp_path):
    """views_gt_vs_render.png: a row per test view, the photo on the left and the render on the right, each tile
    labelled with what it is (and the render with the appearance it used)."""
    from nerfstudio.utils.eval_utils import eval_setup

    from willags_ns.scripts.demo import labelled_grid, views_rows

    cfg, _, _ = appearance_run
    _, pipeline, _, _ = eval_setup(cfg, test_mode="test")
    pipeline.model.eval()
    test = pipeline.datamanager.eval_dataset
    rows = views_rows(pipeline)
    assert len(rows) == min(4, len(test))
    for i, (title, tiles) in enumerate(rows):
        assert Path(test.image_filenames[i]).name in title
        (photo_label, photo), (render_label, rendered) = tiles
        assert np.array_equal(photo, (test.get_image_float32(i)[..., :3].numpy() * 255).round().astype(np.uint8))
        assert not np.array_equal(photo, rendered)
        assert "photo" in photo_label and "render" not in photo_label
        assert "render" in render_label and "appearance" in render_label
    grid = labelled_grid(rows)
    h, w = photo.shape[:2]
    assert grid.shape == (6 + len(rows) * (24 + 2 * h + 20 + 6), 6 + 2 * (2 * w + 6), 3)
    label = grid[6 + 24 + 2 * h : 6 + 24 + 2 * h + 20, 6 : 6 + 2 * w]  # under the first photo
    assert (label < 128).any()  # its label is drawn
