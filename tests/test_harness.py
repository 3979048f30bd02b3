"""Benchmark harness: grid parsing, schedules, record merging, markdown and goals; one tiny end-to-end run."""

import json

import numpy as np
import pytest
from PIL import Image

from benchmarks import harness
from benchmarks.harness import (
    apply_schedule,
    build_config,
    goal_rows,
    merge_records,
    pareto_rows,
    parse_grid,
    render_markdown,
)

# ---------------------------------------------------------------- grid


def test_parse_grid_defaults_overrides_and_tags():
    grid = {
        "steps": [100, 200],
        "downscale": 2,
        "protocol_steps": 16,
        "runs": [
            {"scene": "default", "methods": ["willags", "willags-3dgs"]},
            {"scene": "../shared/data/fox-wild", "methods": ["willags"], "steps": [50], "protocol_steps": 4},
            {"scene": "sacre-coeur-mini", "methods": ["willags-lite"], "downscale": 4, "tag": "x"},
        ],
    }
    settings, specs = parse_grid(grid)
    assert settings["device"] == "auto"
    keys = [(s.scene_name, s.method, s.steps) for s in specs]
    assert keys == [
        ("default", "willags", 100), ("default", "willags", 200),
        ("default", "willags-3dgs", 100), ("default", "willags-3dgs", 200),
        ("fox-wild", "willags", 50), ("sacre-coeur-mini", "willags-lite", 100), ("sacre-coeur-mini", "willags-lite", 200),
    ]  # fmt: skip
    default, fox, sacre = specs[0], specs[4], specs[5]
    assert default.downscale == 1 and default.tag == ""  # the synthetic scene is never downscaled
    assert fox.downscale == 2 and fox.tag == "ds2" and fox.protocol_steps == 4
    assert default.protocol_steps == 16
    assert sacre.downscale == 4 and sacre.tag == "x"


@pytest.mark.parametrize(
    "grid",
    [
        {"runs": []},
        {"stepz": [1], "runs": [{"scene": "default", "methods": ["willags"]}]},
        {"runs": [{"scene": "default", "methods": ["nerfacto"]}]},
        {"runs": [{"scene": "default", "methods": ["willags"], "step": 3}]},
        {"runs": [{"methods": ["willags"]}]},
        {"runs": [{"scene": "default", "methods": ["willags"], "steps": [0]}]},
        {"device": "tpu", "runs": [{"scene": "default", "methods": ["willags"]}]},
    ],
)
def test_parse_grid_rejects_bad_grids(grid):
    with pytest.raises(ValueError):
        parse_grid(grid)


def test_shipped_grids_parse():
    for name in ("benchmark_cpu.json", "benchmark_gpu.json"):
        settings, specs = parse_grid(json.loads((harness.REPO / "configs" / name).read_text()))
        assert specs, name
        methods = {s.method for s in specs}
        assert {"willags", "willags-lite", "willags-novae", "willags-nofield", "willags-nomask"} <= methods
    _, gpu = parse_grid(json.loads((harness.REPO / "configs" / "benchmark_gpu.json").read_text()))
    assert any(s.method == "splatfacto" for s in gpu)


def test_resolve_scene(tmp_path):
    assert harness.resolve_scene("default") is None
    (tmp_path / "data" / "sc").mkdir(parents=True)
    assert harness.resolve_scene("sc", [str(tmp_path / "data")]) == (tmp_path / "data" / "sc").resolve()
    assert harness.resolve_scene(str(tmp_path / "data" / "sc")) == (tmp_path / "data" / "sc").resolve()
    with pytest.raises(FileNotFoundError):
        harness.resolve_scene("no-such-scene", [str(tmp_path)])


def test_downscaled_scene_mirror(tmp_path):
    src = tmp_path / "scene"
    (src / "images").mkdir(parents=True)
    (src / "transforms.json").write_text("{}")
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (7, 9, 3), dtype=np.uint8)).save(src / "images" / "a.png")
    Image.fromarray(np.full((6, 10, 3), 200, np.uint8)).save(src / "images" / "b.jpg")
    dst = harness.downscaled_scene(src, 2, cache_root=tmp_path / "cache")
    assert (dst / "transforms.json").is_symlink() and (dst / "images").is_symlink()
    assert Image.open(dst / "images_2" / "a.png").size == (4, 3)  # floor(9/2) x floor(7/2)
    small_b = np.asarray(Image.open(dst / "images_2" / "b.jpg"))
    assert small_b.shape == (3, 5, 3) and abs(int(small_b.mean()) - 200) <= 2
    mtime = (dst / "images_2" / "a.png").stat().st_mtime_ns
    assert harness.downscaled_scene(src, 2, cache_root=tmp_path / "cache") == dst
    assert (dst / "images_2" / "a.png").stat().st_mtime_ns == mtime  # reused, not rewritten
    assert not list(src.glob("images_*"))  # the source is never written
    assert harness.downscaled_scene(src, 1, cache_root=tmp_path / "cache") == src.resolve()


# ---------------------------------------------------------------- schedules


@pytest.mark.parametrize("method", ["willags", "willags-lite", "willags-3dgs", "willags-novae"])
def test_short_schedule_is_the_same_for_every_method(method, tmp_path):
    cfg = build_config(method, 300, "cpu", None, None, "short", tmp_path)
    m = cfg.pipeline.model
    assert cfg.max_num_iterations == 300
    assert (m.num_downscales, m.warmup_length, m.refine_every, m.stop_split_at) == (0, 50, 50, 240)
    assert m.reset_alpha_every * m.refine_every > 300  # no opacity reset inside the run
    if hasattr(m, "mask"):
        assert m.mask.warmup_steps == 75
    scheds = [g["scheduler"] for g in cfg.optimizers.values() if g.get("scheduler") is not None]
    assert scheds and all(s.max_steps == 300 for s in scheds)
    assert all(getattr(s, "warmup_steps", 0) < 300 for s in scheds)
    assert cfg.steps_per_eval_image == 0 and cfg.steps_per_eval_all_images == 0  # train_s is training only
    assert m.log_images_every == 0
    if method == "willags-novae":
        assert m.latent.kind == "embedding"


METHODS_USED = ("willags", "willags-auto", "willags-full", "willags-nomask")


def test_the_default_inspects_and_its_ablations_change_the_full_model(tmp_path):
    """METHODS' `willags` is the default (auto_config); `willags-full` and every ablation of the default start
    from the full model without inspection (benchmarks/methods.py base_trainer_config)."""
    built = {m: build_config(m, 300, "cpu", None, None, "short", tmp_path).pipeline.model for m in METHODS_USED}
    assert built["willags"].auto_config is True and built["willags-auto"].auto_config is True
    assert built["willags-full"].auto_config is False
    assert built["willags-nomask"].auto_config is False and built["willags-nomask"].mask.enabled is False
    assert vars(built["willags-full"]) == {**vars(built["willags"]), "auto_config": False}


@pytest.mark.parametrize(
    "rec, name",
    [
        ({"method": "willags", "date": "2026-11-25T19:00:00"}, "willags-full"),  # before the default inspected
        ({"method": "willags", "date": "2026-11-26T09:00:00"}, "willags-splitclone"),  # before it densified by MCMC
        ({"method": "willags", "date": "2026-11-28T09:00:00"}, "willags"),
        ({"method": "willags-mcmc", "date": "2026-11-27T16:00:00"}, "willags"),  # the default named in full
        ({"method": "willags"}, "willags"),  # undated: its own name
        ({"method": "willags-auto", "date": "2026-11-25T16:00:00"}, "willags-splitclone"),  # the default of its time
        ({"method": "willags-auto", "date": "2026-11-24T16:00:00"}, "willags-auto"),  # an older full model under it
        ({"method": "peer", "date": "2026-11-25T19:00:00"}, "peer"),
    ],
)
def test_a_record_is_named_by_the_configuration_it_measured(rec, name):
    from benchmarks.methods import configuration

    assert configuration(rec) == name


def test_default_schedule_changes_only_the_budget(tmp_path):
    ref = harness.base_trainer_config("willags")
    cfg = harness.base_trainer_config("willags")
    apply_schedule(cfg, 5000, "default")
    assert cfg.max_num_iterations == 5000
    assert cfg.pipeline.model == ref.pipeline.model
    with pytest.raises(ValueError):
        apply_schedule(cfg, 10, "fast")


# ---------------------------------------------------------------- records, goals, markdown


def _rec(scene, method, steps, psnr, device="cpu", tag="ds2", train_s=100.0, **kw):
    r = {
        "scene": scene, "method": method, "device": device, "steps": steps, "tag": tag, "psnr": psnr,
        "ssim": 0.5, "lpips": None, "full_psnr": psnr - 0.1, "encoder_psnr": psnr - 1, "train_s": train_s,
        "s_per_step": train_s / steps, "fps": 10.0, "num_gaussians": 1234, "peak_mem_gb": 1.5, "status": "ok",
        "date": "2026-01-02T03:04:05", "command": "python benchmarks/run_benchmark.py --grid g.json",
        "machine": "2 CPU cores", "schedule": "short", "protocol_steps": 32, "image_hw": [240, 135],
        "num_train_images": 58, "num_images": 4.0,
    }  # fmt: skip
    r.update(kw)
    return r


def test_merge_replaces_same_key_and_keeps_others():
    old = [_rec("fox-wild", "willags", 300, 18.0), _rec("fox-wild", "willags", 100, 15.0),
           _rec("fox-wild", "willags", 300, 25.0, device="cuda", tag="")]  # fmt: skip
    new = [_rec("fox-wild", "willags", 300, 19.0), _rec("fox-clean", "willags", 300, 20.0)]
    merged = merge_records(old, new)
    assert len(merged) == 4
    by = {harness.record_key(r): r["psnr"] for r in merged}
    assert by[("fox-wild", "willags", "cpu", 300, "ds2")] == 19.0  # replaced
    assert by[("fox-wild", "willags", "cpu", 100, "ds2")] == 15.0  # kept
    assert by[("fox-wild", "willags", "cuda", 300, "")] == 25.0  # other device kept
    assert by[("fox-clean", "willags", "cpu", 300, "ds2")] == 20.0  # added
    # a different tag is a different record
    assert len(merge_records(merged, [_rec("fox-wild", "willags", 300, 1.0, tag="ds4")])) == 5


def test_write_outputs_merges_into_existing_file(tmp_path):
    out = tmp_path / "bench"
    harness.write_outputs([_rec("fox-wild", "willags", 300, 18.0, device="cuda", tag="")], out)
    recs = merge_records(harness.load_records(out.with_suffix(".json")), [_rec("fox-wild", "willags", 300, 17.0)])
    harness.write_outputs(recs, out)
    back = harness.load_records(out.with_suffix(".json"))
    assert sorted(r["device"] for r in back) == ["cpu", "cuda"]
    md = out.with_suffix(".md").read_text()
    assert "## cpu" in md and "## cuda" in md


def _goal(rows, start):
    (row,) = [r for r in rows if r["goal"].startswith(start)]
    return row


def test_goal_rows_missed_and_met_margins():
    recs = [
        _rec("fox-wild", "willags", 300, 20.0, train_s=200),
        _rec("fox-wild", "willags-3dgs", 300, 17.5, train_s=100),
        _rec("fox-wild", "willags-vae", 300, 18.5),
        _rec("fox-wild", "willags-lite", 100, 17.6, train_s=40),
        _rec("fox-clean", "willags", 300, 26.9),
        _rec("fox-clean", "willags-3dgs", 300, 27.2),
    ]
    rows = goal_rows(recs, "cpu")
    g1 = _goal(rows, "fox-wild: willags >= willags-3dgs (stand-in) + 4 dB")
    assert g1["status"] == "missed by 1.50 dB" and g1["met"] is False
    g2 = _goal(rows, "fox-wild: willags >= willags-vae (the VAE latent)")
    assert g2["status"] == "met (margin 1.50 dB)" and g2["met"] is True
    g4 = _goal(rows, "fox-clean")
    assert g4["status"] == "missed by 0.10 dB"  # -0.3 dB against a -0.2 dB tolerance
    g5 = _goal(rows, "fox-wild: willags-lite")
    assert g5["met"] is True and "0.40x" in g5["status"]  # 40 s vs 100 s
    assert _goal(rows, "fox-wild: mask")["status"] == "not measured"


def test_goal_rows_mask_and_stock_baseline_preferred():
    recs = [
        _rec("fox-wild", "willags", 5000, 22.0, device="cuda", tag="", mask_iou=0.5, mask_fp_rate=0.07,
             mask_recall=0.9),
        _rec("fox-wild", "splatfacto", 5000, 17.2, device="cuda", tag="", train_s=50),
        _rec("fox-wild", "willags-3dgs", 5000, 10.0, device="cuda", tag=""),
        _rec("fox-wild", "willags-lite", 5000, 17.0, device="cuda", tag="", train_s=20),
        _rec("fox-clean", "willags", 5000, 27.1, device="cuda", tag=""),
        _rec("fox-clean", "splatfacto", 5000, 27.2, device="cuda", tag=""),
    ]  # fmt: skip
    rows = goal_rows(recs, "cuda")
    g1 = _goal(rows, "fox-wild: willags >= splatfacto + 4 dB")
    assert g1["status"] == "met (margin 0.80 dB)"
    gm = _goal(rows, "fox-wild: mask")
    assert gm["status"] == "IoU missed by 0.10; FP missed by 2.0 pp" and gm["met"] is False
    assert _goal(rows, "fox-clean")["status"] == "met (margin 0.10 dB)"
    g5 = _goal(rows, "fox-wild: willags-lite")
    assert g5["met"] is False and g5["status"].startswith("missed: never reached (by 0.20 dB)")


def test_pareto_marks_dominated_points():
    recs = [
        _rec("fox-wild", "willags", 100, 15.0, train_s=50),
        _rec("fox-wild", "willags", 300, 18.0, train_s=150),
        _rec("fox-wild", "willags-3dgs", 300, 16.0, train_s=60),  # slower and worse than nothing? no: Pareto
        _rec("fox-wild", "willags-lite", 300, 14.0, train_s=70),  # dominated by willags@100
    ]
    rows = {(r["method"], r["steps"]): r["pareto"] for r in pareto_rows(recs, "cpu")}
    assert rows == {("willags", 100): True, ("willags", 300): True, ("willags-3dgs", 300): True,
                    ("willags-lite", 300): False}  # fmt: skip


def test_markdown_has_provenance_tables_goals_and_failures():
    recs = [
        _rec("default", "willags", 300, 21.0, tag=""),
        _rec(
            "fox-wild",
            "willags",
            300,
            18.0,
            mask_iou=0.4,
            mask_fp_rate=0.02,
            mask_recall=0.8,
            mask_iou_mean=0.41,
            mask_rejected=3.0,
            mask_num_images=58.0,
        ),
        _rec("fox-wild", "willags-3dgs", 300, 16.5),
        {**_rec("fox-wild", "willags-nomask", 300, 0.0), "psnr": None, "status": "failed (exit 1)"},
        # no transients in the scene: IoU undefined, the false-positive rate still shown
        _rec(
            "fox-appearance-only",
            "willags",
            300,
            17.0,
            mask_status="ok",
            mask_iou=None,
            mask_fp_rate=0.01,
            mask_rejected=0.0,
            mask_num_images=58.0,
        ),
    ]
    md = render_markdown(recs)
    assert "## cpu" in md
    assert "`python benchmarks/run_benchmark.py --grid g.json`" in md
    assert "2 CPU cores" in md and "2026-01-02" in md and "step budgets: 300" in md
    assert md.index("### default") < md.index("### fox-wild")
    assert "| willags-3dgs (stand-in) [ds2] | 300 | 16.50 |" in md
    assert "failed (exit 1)" in md
    assert "fox-wild: willags >= willags-3dgs (stand-in) + 4 dB" in md and "missed by 2.50 dB" in md
    assert "| 0.400 | 0.410 | 0.800 | 2.0% | 3/58 |" in md  # mask columns where measured
    assert "| - | - | - | 1.0% | 0/58 |" in md
    assert "### Pareto: fox-wild PSNR vs train time" in md
    assert "first train image 135x240 px" in md


# ---------------------------------------------------------------- end to end


@pytest.mark.slow
def test_tiny_grid_end_to_end(tmp_path):
    grid = {
        "device": "cpu", "steps": [5], "protocol_steps": 2, "max_test_images": 1, "mask_max_images": 2,
        "fps_views": 1, "runs": [{"scene": "default", "methods": ["willags"]}],
    }  # fmt: skip
    gpath = tmp_path / "grid.json"
    gpath.write_text(json.dumps(grid))
    out = tmp_path / "docs" / "benchmarks"
    harness.write_outputs([_rec("fox-wild", "willags", 300, 18.0, device="cuda", tag="")], out)  # a GPU record
    logs = []
    recs = harness.run_grid(gpath, out, tmp_path / "work", command="bench-test", log=logs.append)
    assert len(recs) == 1 and recs[0]["status"] == "ok", logs
    r = recs[0]
    for k in ("psnr", "ssim", "encoder_psnr", "full_psnr", "train_s", "fps", "num_gaussians", "peak_mem_gb"):
        assert isinstance(r[k], (int, float)) and np.isfinite(r[k]), k
    assert r["lpips"] is None or np.isfinite(r["lpips"])
    assert r["mask_status"] == "ok" and r["mask_num_images"] == 2  # the synthetic scene has masks_gt/
    assert r["steps"] == 5 and r["device"] == "cpu" and r["scene"] == "default" and r["command"] == "bench-test"
    back = harness.load_records(out.with_suffix(".json"))
    assert {x["device"] for x in back} == {"cpu", "cuda"}  # merged, the GPU record kept
    md = out.with_suffix(".md").read_text()
    assert "### default" in md and "bench-test" in md
    assert not (tmp_path / "work" / "default-willags-5-cpu" / "out").exists()  # checkpoints removed


def test_markdown_renders_gpu_suite_speed_records_as_their_own_table():
    speed = {
        "scene": "synthetic-box-1000000-800px",
        "method": "willags",
        "device": "NVIDIA H100",
        "steps": 0,
        "tag": "h100",
        "step_ms": 52.6,
        "step_ratio_vs_splatfacto": 3.14,
        "extra_vram_gb": 1.98,
        "host_syncs_per_step": 26.0,
        "render_fps_ratio_vs_gsplat": 0.293,
        "render_fps_ratio_vs_splatfacto": 1.09,
        "code_commit": "abc1234",
    }
    md = render_markdown([speed])
    assert "### Train step / render / memory: synthetic-box-1000000-800px" in md
    assert "| willags [h100] | 52.60 | 3.14 | +1.98 | 26 | 1.09 | 0.293 | - |" in md
    assert "commits: abc1234" in md  # the suite's records name their commit as code_commit
    assert "### Goals" not in md  # a speed-only section measures none of the accuracy goals
    assert "| PSNR |" not in md


def test_learning_rate_overrides_keep_the_schedule_ratio(tmp_path):
    from benchmarks.harness import build_config, set_lr

    cfg = build_config("willags-lowlr", 100, "cpu", None, None, "default", tmp_path)
    means = cfg.optimizers["means"]
    assert means["optimizer"].lr == 1.6e-5
    assert abs(means["scheduler"].lr_final - 1.6e-7) < 1e-12
    with pytest.raises(KeyError, match="optimizers.nope.lr"):
        set_lr(cfg, "optimizers.nope.lr", 1.0)


# ---------------------------------------------------------------- pictures, the peer, the 15000-step table


def test_render_sheets_stack_pairs_and_tint_the_transient_pixels(tmp_path):
    import torch

    gt, pred = torch.zeros(40, 30, 3), torch.ones(40, 30, 3)
    p = harness.save_right_halves(tmp_path / "r.png", [(gt, pred), (gt, pred)], [19.0, 18.0], height=20)
    im = np.asarray(Image.open(p).convert("RGB"))
    assert im.shape == (40, 30, 3)  # two columns of 15 px (30 px wide at 40 -> 20 px high), two rows
    assert im[:20].max() == 0 and im[37:].min() == 255  # GT above (black), render below (white, under the label)
    assert (im[20:37] != 255).any()  # the PSNR label is written on the render

    img = torch.full((20, 20, 3), 0.5)
    static = torch.ones(10, 10, dtype=torch.bool)
    static[:5] = False  # the upper half is transient (mask at half resolution)
    p = harness.save_masks(tmp_path / "m.png", [(img, static)], height=20)
    im = np.asarray(Image.open(p).convert("RGB")).astype(int)
    top, tinted_transient, tinted_static = im[10, 10], im[25, 10], im[35, 10]
    assert abs(top[0] - top[1]) <= 1  # the untouched image is grey
    assert tinted_transient[0] > tinted_transient[1] + 100  # transient pixels red
    assert abs(tinted_static[0] - tinted_static[1]) <= 1  # static pixels unchanged


def test_peer_adapter_fits_the_latent_through_the_peers_embedding_and_restores_it():
    import torch
    from nerfstudio.cameras.cameras import Cameras

    from benchmarks.peer import PeerForProtocol
    from willags_ns.eval.protocol import fit_latent, render_with_latent

    class FakePeer(torch.nn.Module):
        """Renders a flat image whose colour is the first 3 entries of its appearance embedding (the peer reads the
        table by cam_idx, or its mean with use_avg_appearance)."""

        def __init__(self):
            super().__init__()
            self.appearance_embeds = torch.nn.Embedding(4, 5)
            self.config = type("C", (), {"use_avg_appearance": False})()
            self.seen = []

        @property
        def device(self):
            return torch.device("cpu")

        def get_outputs(self, camera):
            md = camera.metadata or {}
            if "cam_idx" in md:
                e = self.appearance_embeds(torch.tensor(md["cam_idx"]))
            elif self.config.use_avg_appearance:
                e = self.appearance_embeds.weight.mean(0)
            else:
                e = self.appearance_embeds(torch.tensor(0))
            self.seen.append(tuple(md))
            return {"rgb": e[:3].expand(6, 8, 3)}

    peer = FakePeer()
    model = PeerForProtocol(peer)
    assert model.config.appearance == "willags" and model.appearance_nets.vae is None
    torch.testing.assert_close(model.default_latent(), peer.appearance_embeds.weight.mean(0))
    cam = Cameras(camera_to_worlds=torch.eye(4)[:3][None], fx=1.0, fy=1.0, cx=4.0, cy=3.0, width=8, height=6)
    cam.metadata = {"cam_idx": 2}
    target = torch.tensor([0.2, 0.7, 0.4]).expand(6, 8, 3)
    z, hist = fit_latent(
        lambda z: render_with_latent(model, cam, z), target, model.default_latent(), slice(0, 4), 60, 0.05
    )
    assert hist[-1] < 0.2 * hist[0]  # the fitted latent drives the peer's colours
    torch.testing.assert_close(render_with_latent(model, cam, z)[0, 0], z[:3])
    assert isinstance(peer.appearance_embeds, torch.nn.Embedding) and peer.config.use_avg_appearance is False
    assert ("cam_idx",) not in peer.seen[:-1]  # while fitting, the peer never looked its own row up
    torch.testing.assert_close(model.get_outputs(cam)["rgb"][0, 0], peer.appearance_embeds.weight[2, :3])


def test_peer_source_missing_is_a_clear_error(tmp_path, monkeypatch):
    from benchmarks import peer

    monkeypatch.setenv(peer.PEER_ENV, str(tmp_path))
    with pytest.raises(FileNotFoundError, match="KevinXu02/splatfacto-w"):
        peer.peer_source()


def test_fifteen_k_table_lists_each_run_once_next_to_its_5000_step_mean():
    base = {"status": "ok", "device": "cuda", "ssim": 0.9}
    recs = [
        {
            **base,
            "scene": "fox-wild",
            "method": "willags",
            "steps": 15000,
            "tag": "h100-15k",
            "psnr": 22.4,
            "train_psnr": 18.0,
            "num_gaussians": 100,
        },
        {**base, "scene": "fox-wild", "method": "willags", "steps": 5000, "tag": "h100-r1", "psnr": 22.0},
        {**base, "scene": "fox-wild", "method": "willags", "steps": 5000, "tag": "h100-r2", "psnr": 22.2},
        {**base, "scene": "reichstag", "method": "splatfacto", "steps": 15000, "tag": "h100-15k", "psnr": 15.1},
        {
            "scene": "reichstag",
            "method": "splatfacto",
            "kind": "long_run",
            "steps_done": 15000,
            "steps": 15000,
            "milestones": {"15000": {"psnr": 15.1, "train_psnr": 22.0, "num_gaussians": 5}},
        },
        {  # a long run as benchmarks/long_run.py records it: its train-view PSNR lives in the milestone
            **base,
            "scene": "reichstag",
            "method": "willags-auto",
            "kind": "long_run",
            "steps_done": 15000,
            "steps": 15000,
            "tag": "h100-15k",
            "psnr": 19.0,
            "milestones": {"15000": {"psnr": 19.0, "train_psnr": 28.5, "num_gaussians": 7}},
        },
    ]
    rows = [ln for ln in harness.fifteen_k_section(recs) if ln.startswith("| fox-wild") or ln.startswith("| reich")]
    assert rows == [
        "| fox-wild | willags | 22.40 | 22.10 ±0.10 (n=2) | 18.00 | 100 |",
        "| reichstag | willags-auto | 19.00 | – | 28.50 | 7 |",
        "| reichstag | splatfacto | 15.10 | – | – | – |",
    ]


def test_ablation_table_gives_each_variant_its_difference_to_the_default_mean():
    def rec(method, tag, psnr):
        return {"status": "ok", "scene": "fox-wild", "method": method, "steps": 5000, "tag": tag, "psnr": psnr}

    recs = [
        rec("willags", "h100-r1", 22.0),
        rec("willags", "h100-r1b", 22.4),
        rec("willags-nomask", "h100-r1", 20.0),
        rec("willags-nomask", "h100-r1b", 20.1),
        rec("willags-auto", "h100-r1", 22.2),
        rec("willags-field", "h100-r1", 22.1),
        rec("willags-field", "h100-r1b", 22.3),
        {**rec("willags-vae", "h200-x", 30.0)},  # not a fidelity-grid tag: left out
        {**rec("willags-noteacher", "h100-r1", 0.0), "status": "failed: timeout"},  # failed: left out
    ]
    rows = [ln for ln in harness.fidelity_section(recs) if ln.startswith("| fox-wild | 22.20")]
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    # scene, default, then harness.ABLATIONS in order
    assert dict(zip(("scene", "willags", *harness.ABLATIONS), cells, strict=True)) == {
        "scene": "fox-wild",
        "willags": "22.20 ±0.20 (n=2)",
        "willags-nomask": "**-2.15** · 20.05 ±0.05 (n=2)",
        "willags-noteacher": "–",
        "willags-field": "**+0.00** · 22.20 ±0.10 (n=2)",
        "willags-vae": "–",
        "willags-auto": "**+0.00** · 22.20 (n=1)",
        "peer": "–",
    }


def test_per_view_table_shows_which_test_view_carries_the_difference_to_the_peer():
    def rec(method, tag, views, scene="reichstag"):
        return {
            "status": "ok",
            "scene": scene,
            "method": method,
            "steps": 5000,
            "tag": tag,
            "psnr": sum(views.values()) / len(views),
            "per_image": [{"image": k, "psnr": v, "oracle_psnr": v + 1.0} for k, v in views.items()],
        }

    recs = [
        rec("willags", "h100-r1", {"a_1.jpg": 20.0, "b_2.jpg": 16.0}),
        rec("willags", "h100-r1b", {"a_1.jpg": 20.4, "b_2.jpg": 16.2}),
        rec("peer", "h100-r1", {"a_1.jpg": 20.0, "b_2.jpg": 17.5}),
        rec("willags", "h100-r1", {"c.jpg": 30.0}, scene="fox-wild"),  # not a real scene: no table
    ]
    lines = harness.fidelity_section(recs)
    start = lines.index("reichstag:")
    table = lines[start + 2 : start + 8]
    assert table == [
        "| method | n | a_1 | b_2 | mean |",
        "|---|---|---|---|---|",
        "| willags | 2 | 20.20 | 16.10 | 18.15 |",
        "| willags oracle | 2 | 21.20 | 17.10 | 19.15 |",
        "| peer | 1 | 20.00 | 17.50 | 18.75 |",
        "| peer oracle | 1 | 21.00 | 18.50 | 19.75 |",
    ]
    # no willags-nomask records: no row; then the default minus the peer, view by view
    assert lines[start + 8] == "| willags − peer | | +0.20 | -1.40 | -0.60 |"
    assert "fox-wild:" not in lines


def test_records_name_the_commit_given_by_the_gpu_command(monkeypatch):
    """On the lent GPU machine the tree's git metadata is not the source's: $WILLAGS_COMMIT names the commit."""
    from benchmarks.harness import _git_commit

    monkeypatch.delenv("WILLAGS_COMMIT", raising=False)
    here = _git_commit()
    assert here is None or len(here.split("+")[0]) >= 7
    monkeypatch.setenv("WILLAGS_COMMIT", "abc1234")
    assert _git_commit() == "abc1234"


def test_long_run_record_carries_the_seed_and_the_last_milestone(tmp_path):
    """A repeat of a long run differs from the first by its seed: the record must say which (remote/long.sh's
    LONG_SEED), and its scores are the final milestone's."""
    from benchmarks import long_run

    run = tmp_path / "fox-clean-willags-s43"
    run.mkdir()
    state = {
        "method": "willags",
        "data": "/x/fox-clean",
        "steps": 300,
        "seed": 43,
        "segments": [
            {"start_step": 0, "end_step": 149, "train_s": 2.0},
            {"start_step": 150, "end_step": 299, "train_s": 3.0},
        ],
        "scores": {"300": {"psnr": 30.5, "ssim": 0.9, "train_psnr": 33.0}, "100": {"psnr": 20.0}},
    }
    (run / long_run.STATE).write_text(json.dumps(state))
    out = tmp_path / "rec.json"
    rc = long_run.main(
        ["record", "--run-dir", str(run), "--tag", "h100-15k-s43", "--out", str(out), "--milestones", "100,300"]
    )
    assert rc == 0
    (rec,) = json.loads(out.read_text())
    assert (rec["scene"], rec["method"], rec["seed"], rec["tag"]) == ("fox-clean", "willags", 43, "h100-15k-s43")
    assert (rec["steps_done"], rec["train_s"], rec["psnr"]) == (300, 5.0, 30.5)
    assert list(rec["milestones"]) == ["100", "300"]


def test_long_run_resume_resizes_the_gaussians_in_place_so_the_optimisers_keep_them():
    import torch
    from torch import nn

    from benchmarks.long_run import _patch_resume

    class Model(nn.Module):  # the shape of splatfacto's and the peer's gauss_params
        def __init__(self, n: int):
            super().__init__()
            self.device = torch.device("cpu")
            self.gauss_params = nn.ParameterDict(
                {"means": nn.Parameter(torch.zeros(n, 3)), "opacities": nn.Parameter(torch.zeros(n, 1))}
            )
            self.embed = nn.Embedding(2, 4)

    _patch_resume(Model)
    saved = Model(7)
    with torch.no_grad():
        for p in saved.parameters():
            p.uniform_()
    model = Model(3)
    params = dict(model.gauss_params.items())
    optimiser = torch.optim.Adam(params.values())
    model.load_state_dict(saved.state_dict())
    for name, p in model.gauss_params.items():
        assert p is params[name] and torch.equal(p, saved.gauss_params[name])  # the objects the optimiser holds
    assert torch.equal(model.embed.weight, saved.embed.weight) and model.step == 30000
    assert all(p is q for p, q in zip(optimiser.param_groups[0]["params"], params.values(), strict=True))


def test_long_run_rows_list_milestones_in_step_order_and_mark_a_time_budget():
    """benchmarks.json is written with sorted keys ("10000" < "2000" as text): the rows sort milestones by step; a
    time-budget run stops at a step of its own (19, 15004), shown as it is, with its budget."""
    from benchmarks.fidelity_tables import long_run_section

    rec = {
        "kind": "long_run",
        "scene": "sacre-coeur-mini",
        "method": "willags",
        "steps": 30000,
        "steps_done": 19,
        "train_s": 253.0,
        "device": "cpu",
        "tag": "cpu-knob4-full",
        "milestones": {"10000": {"psnr": 12.0}, "19": {"psnr": 11.23}, "2000": {"psnr": 11.5}},
        "segments": [{"start_step": 0, "end_step": 18, "train_s": 253.0, "num_gaussians": 3975}],
    }
    (row,) = [ln for ln in long_run_section([rec]) if ln.startswith("| sacre")]
    assert "| 19: 11.23, 2k: 11.50, 10k: 12.00 |" in row
    (row,) = [ln for ln in long_run_section([{**rec, "time_budget_minutes": 4.0}]) if ln.startswith("| sacre")]
    assert "10k: 12.00 (time budget 4 min, cpu) |" in row
