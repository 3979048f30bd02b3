"""benchmarks/grid.py and what a grid run uses: grid parsing, scenes, the methods' configs and schedules, record
merging, docs/benchmarks.md's tables; the child's pictures and the peer's adapter; one tiny end-to-end run."""

import dataclasses
import json

import numpy as np
import pytest
from PIL import Image

from benchmarks import grid
from benchmarks.grid import parse_grid
from benchmarks.methods import apply_schedule, base_trainer_config, build_config, configuration
from benchmarks.records import load_records, merge_records, record_key
from benchmarks.tables import render_markdown, write_outputs

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
    "bad",
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
def test_parse_grid_rejects_bad_grids(bad):
    with pytest.raises(ValueError):
        parse_grid(bad)


def test_shipped_grids_parse():
    for path in sorted((grid.REPO / "configs").glob("benchmark_*.json")):
        settings, specs = parse_grid(json.loads(path.read_text()))
        assert specs and settings["description"], path.name
    _, cpu = parse_grid(json.loads((grid.REPO / "configs" / "benchmark_cpu.json").read_text()))
    assert {s.method for s in cpu} == {"willags", "willags-lite", "willags-3dgs"}


def test_resolve_scene(tmp_path):
    assert grid.resolve_scene("default") is None
    (tmp_path / "data" / "sc").mkdir(parents=True)
    assert grid.resolve_scene("sc", [str(tmp_path / "data")]) == (tmp_path / "data" / "sc").resolve()
    assert grid.resolve_scene(str(tmp_path / "data" / "sc")) == (tmp_path / "data" / "sc").resolve()
    with pytest.raises(FileNotFoundError):
        grid.resolve_scene("no-such-scene", [str(tmp_path)])


def test_downscaled_scene_mirror(tmp_path):
    src = tmp_path / "scene"
    (src / "images").mkdir(parents=True)
    (src / "transforms.json").write_text("{}")
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (7, 9, 3), dtype=np.uint8)).save(src / "images" / "a.png")
    Image.fromarray(np.full((6, 10, 3), 200, np.uint8)).save(src / "images" / "b.jpg")
    dst = grid.downscaled_scene(src, 2, cache_root=tmp_path / "cache")
    assert (dst / "transforms.json").is_symlink() and (dst / "images").is_symlink()
    assert Image.open(dst / "images_2" / "a.png").size == (4, 3)  # floor(9/2) x floor(7/2)
    small_b = np.asarray(Image.open(dst / "images_2" / "b.jpg"))
    assert small_b.shape == (3, 5, 3) and abs(int(small_b.mean()) - 200) <= 2
    mtime = (dst / "images_2" / "a.png").stat().st_mtime_ns
    assert grid.downscaled_scene(src, 2, cache_root=tmp_path / "cache") == dst
    assert (dst / "images_2" / "a.png").stat().st_mtime_ns == mtime  # reused, not rewritten
    assert not list(src.glob("images_*"))  # the source is never written
    assert grid.downscaled_scene(src, 1, cache_root=tmp_path / "cache") == src.resolve()


# ---------------------------------------------------------------- schedules


@pytest.mark.parametrize("method", ["willags", "willags-lite", "willags-3dgs", "willags-residual"])
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
    if method == "willags-residual":  # the overrides apply, and the inspector keeps the mask it forces
        assert (m.mask.enabled, m.mask.distance, m.densification) == (True, "residual", "splatfacto")
        assert "mask.enabled" in cfg.pipeline.auto_config_keep


def test_the_default_inspects_and_its_candidates_change_the_full_model(tmp_path):
    """METHODS' `willags` is the default (auto_config, the latent prior); `willags-full` is the full model without
    inspection and, as its records measured it, without the prior; the candidates the default with one change, or
    willags-noprior with one (benchmarks/methods.py base_trainer_config)."""
    methods = ("willags", "willags-full", "willags-mcmc", "willags-noprior", "willags-splitclone", "willags-prior-low")
    built = {m: build_config(m, 300, "cpu", None, None, "short", tmp_path).pipeline.model for m in methods}
    assert built["willags"].auto_config is True and built["willags-full"].auto_config is False
    assert built["willags"].latent.prior_weight == 0.002
    noprior = dataclasses.replace(built["willags"].latent, prior_weight=0.0)
    # as their records measured them: the mask from its warm-up's end whatever the renders leave (_EARLY_MASK)
    early = dataclasses.replace(built["willags"].mask, start_rule="always")
    assert built["willags"].mask.start_rule == "transients"
    assert vars(built["willags-full"]) == {
        **vars(built["willags"]),
        "auto_config": False,
        "latent": noprior,
        "mask": early,
    }
    # the default names its densification by device ("auto": MCMC on a GPU); the candidates name theirs
    assert built["willags"].densification == "auto"
    assert vars(built["willags-mcmc"]) == {**vars(built["willags"]), "densification": "mcmc"}
    assert vars(built["willags-prior-low"]) == vars(built["willags-mcmc"])  # the default's prior named
    assert vars(built["willags-noprior"]) == {**vars(built["willags-mcmc"]), "latent": noprior, "mask": early}
    assert vars(built["willags-splitclone"]) == {**vars(built["willags-noprior"]), "densification": "splatfacto"}


def test_an_optimizer_override_sets_one_groups_learning_rate_and_names_what_it_cannot(tmp_path):
    """`optimizers.<group>.lr` / `.lr_final` in a method's overrides change that group's rate and its schedule's end,
    and nothing else (the model, every other group); a bad group or field is an error that names it."""
    from benchmarks.methods import set_learning_rate

    ref = build_config("willags-earlymask", 15000, "cpu", None, None, "default", tmp_path)
    cfg = build_config("willags-prior-low-meanslr", 15000, "cpu", None, None, "default", tmp_path)
    means, ref_means = cfg.optimizers["means"], ref.optimizers["means"]
    assert (means["optimizer"].lr, means["scheduler"].lr_final) == (1.6e-5, 1.6e-7)
    assert (ref_means["optimizer"].lr, ref_means["scheduler"].lr_final) == (1.6e-4, 1.6e-6)
    assert means["scheduler"].max_steps == ref_means["scheduler"].max_steps
    assert cfg.pipeline.model == ref.pipeline.model
    assert {k: v for k, v in cfg.optimizers.items() if k != "means"} == {
        k: v for k, v in ref.optimizers.items() if k != "means"
    }
    with pytest.raises(AttributeError, match="'nope'"):
        set_learning_rate(cfg.optimizers, "optimizers.nope.lr", 1.0)
    with pytest.raises(AttributeError, match="optimizers.means.eps"):
        set_learning_rate(cfg.optimizers, "optimizers.means.eps", 1.0)


def test_the_pose_refining_candidate_changes_only_the_camera_optimiser(tmp_path):
    """`willags-prior-low-camopt` is the default with nerfstudio's camera optimiser on (SO3xR3, its optimizer group
    as splatfacto's); every other field of the model and every optimizer group as the default's."""
    ref = build_config("willags-earlymask", 15000, "cpu", None, None, "default", tmp_path)
    cfg = build_config("willags-prior-low-camopt", 15000, "cpu", None, None, "default", tmp_path)
    assert (ref.pipeline.model.camera_optimizer.mode, cfg.pipeline.model.camera_optimizer.mode) == ("off", "SO3xR3")
    cfg.pipeline.model.camera_optimizer.mode = "off"
    assert cfg.pipeline.model == ref.pipeline.model
    assert cfg.optimizers == ref.optimizers and "camera_opt" in cfg.optimizers


def test_the_mask_candidates_change_only_the_mask_and_the_one_that_turns_it_off_pins_it(tmp_path):
    """`willags-prior-low-nomask` is the default with the mask off, kept off against the inspector;
    `willags-prior-low-maskres` the default whose mask, where the inspector turns it on, compares by the colour
    residual: the inspector still decides whether it is on. Nothing else differs."""
    ref = build_config("willags-prior-low", 15000, "cpu", None, None, "default", tmp_path)
    early = build_config("willags-earlymask", 15000, "cpu", None, None, "default", tmp_path)
    off = build_config("willags-prior-low-nomask", 15000, "cpu", None, None, "default", tmp_path)
    res = build_config("willags-prior-low-maskres", 15000, "cpu", None, None, "default", tmp_path)
    assert ref.pipeline.model.mask.enabled and not off.pipeline.model.mask.enabled
    assert "mask.enabled" in off.pipeline.auto_config_keep and "mask.enabled" not in res.pipeline.auto_config_keep
    assert (early.pipeline.model.mask.distance, res.pipeline.model.mask.distance) == ("vgg", "residual")
    off.pipeline.model.mask.enabled = True
    res.pipeline.model.mask.distance = "vgg"
    assert off.pipeline.model == ref.pipeline.model and res.pipeline.model == early.pipeline.model
    assert off.optimizers == ref.optimizers == res.optimizers


def test_the_late_mask_candidate_changes_only_when_the_inspectors_mask_starts(tmp_path):
    """`willags-prior-low-mask5k` is the default whose mask, where the inspector turns it on, starts at step 5000:
    the inspector still decides whether it is on; nothing else differs."""
    ref = build_config("willags-earlymask", 15000, "cpu", None, None, "default", tmp_path)
    cfg = build_config("willags-prior-low-mask5k", 15000, "cpu", None, None, "default", tmp_path)
    assert (ref.pipeline.model.mask.warmup_steps, cfg.pipeline.model.mask.warmup_steps) == (500, 5000)
    assert cfg.pipeline.model.mask.enabled and "mask.enabled" not in cfg.pipeline.auto_config_keep
    cfg.pipeline.model.mask.warmup_steps = 500
    assert cfg.pipeline.model == ref.pipeline.model and cfg.optimizers == ref.optimizers


def test_the_default_starts_its_mask_by_the_start_rule_and_earlymask_is_the_default_without_it(tmp_path):
    """`willags-prior-low-mask5k-gate` names the default's own mask start (step 5000, the start rule), so its runs
    are the default's; `willags-earlymask` is the default whose mask, where the inspector turns it on, starts at step
    500 whatever the renders leave (the records measured before the rule), and its folds without the mask are the
    default's runs; `willags-prior-low-mask5k` is that late mask without the rule."""
    from benchmarks.cv import BORROWS

    ref = build_config("willags-prior-low", 15000, "cpu", None, None, "default", tmp_path)
    gate = build_config("willags-prior-low-mask5k-gate", 15000, "cpu", None, None, "default", tmp_path)
    early = build_config("willags-earlymask", 15000, "cpu", None, None, "default", tmp_path)
    late = build_config("willags-prior-low-mask5k", 15000, "cpu", None, None, "default", tmp_path)
    assert gate.pipeline.model == ref.pipeline.model and gate.optimizers == ref.optimizers
    assert configuration({"method": "willags-prior-low-mask5k-gate"}) == "willags"
    mask = ref.pipeline.model.mask
    assert (mask.warmup_steps, mask.start_rule) == (5000, "transients")
    assert (early.pipeline.model.mask.warmup_steps, early.pipeline.model.mask.start_rule) == (500, "always")
    assert (late.pipeline.model.mask.warmup_steps, late.pipeline.model.mask.start_rule) == (5000, "always")
    assert early.pipeline.model.mask.enabled and "mask.enabled" not in early.pipeline.auto_config_keep
    assert BORROWS["willags-earlymask"][:2] == ("willags", ("mask_status", "mask_started"))
    early.pipeline.model.mask.warmup_steps, early.pipeline.model.mask.start_rule = 5000, "transients"
    assert early.pipeline.model == ref.pipeline.model and early.optimizers == ref.optimizers


def test_the_million_cap_on_todays_default_changes_only_the_cap_and_takes_the_early_mask_runs_where_the_mask_is_off(
    tmp_path,
):
    """`willags-startrule-cap1m` is the default with MCMC's cap at 1M; `willags-prior-low-cap1m` the same with the
    early mask, whose runs it takes where the inspector kept the mask off (the model is the same there)."""
    from benchmarks.cv import BORROWS

    ref = build_config("willags-prior-low", 15000, "cpu", None, None, "default", tmp_path)
    cfg = build_config("willags-startrule-cap1m", 15000, "cpu", None, None, "default", tmp_path)
    early = build_config("willags-prior-low-cap1m", 15000, "cpu", None, None, "default", tmp_path)
    assert (cfg.pipeline.model.mcmc.cap_max, ref.pipeline.model.mcmc.cap_max) == (1_000_000, 300_000)
    assert BORROWS["willags-startrule-cap1m"][0] == "willags-prior-low-cap1m"
    early.pipeline.model.mask.warmup_steps, early.pipeline.model.mask.start_rule = 5000, "transients"
    assert early.pipeline.model == cfg.pipeline.model
    cfg.pipeline.model.mcmc.cap_max = 300_000
    assert cfg.pipeline.model == ref.pipeline.model and cfg.optimizers == ref.optimizers


def test_the_holdout_candidate_changes_only_the_held_out_photos(tmp_path):
    """`willags-prior-low-holdout` is the default with 8 photos' right halves held out; nothing else differs."""
    ref = build_config("willags-earlymask", 15000, "cpu", None, None, "default", tmp_path)
    cfg = build_config("willags-prior-low-holdout", 15000, "cpu", None, None, "default", tmp_path)
    assert (ref.pipeline.model.holdout.photos, cfg.pipeline.model.holdout.photos) == (0, 8)
    cfg.pipeline.model.holdout.photos = 0
    assert cfg.pipeline.model == ref.pipeline.model and cfg.optimizers == ref.optimizers


def test_the_mcmc_penalty_candidate_changes_only_the_two_penalties(tmp_path):
    """`willags-prior-low-mcmcreg` is the default with MCMC's opacity and scale penalties at a tenth; nothing else."""
    ref = build_config("willags-earlymask", 15000, "cpu", None, None, "default", tmp_path)
    cfg = build_config("willags-prior-low-mcmcreg", 15000, "cpu", None, None, "default", tmp_path)
    got, want = cfg.pipeline.model.mcmc, ref.pipeline.model.mcmc
    assert (got.opacity_reg, got.scale_reg) == (0.001, 0.001) and (want.opacity_reg, want.scale_reg) == (0.01, 0.01)
    got.opacity_reg, got.scale_reg = want.opacity_reg, want.scale_reg
    assert cfg.pipeline.model == ref.pipeline.model and cfg.optimizers == ref.optimizers


@pytest.mark.parametrize(
    "rec, name",
    [
        ({"method": "willags", "configuration": "willags-full"}, "willags-full"),  # before the default inspected
        ({"method": "willags", "configuration": "willags-splitclone"}, "willags-splitclone"),  # before MCMC
        ({"method": "willags", "date": "2026-11-28T09:00:00"}, "willags"),
        ({"method": "willags-mcmc", "date": "2026-11-27T16:00:00"}, "willags"),  # the default named in full
        ({"method": "willags", "configuration": "willags-noprior"}, "willags-noprior"),  # before the latent prior
        ({"method": "willags-prior-low", "configuration": "willags"}, "willags"),  # the default's prior named
        ({"method": "willags-prior-low"}, "willags"),
        ({"method": "willags", "configuration": "willags-earlymask"}, "willags-earlymask"),  # before the start rule
        ({"method": "willags-prior-low-mask5k-gate"}, "willags"),  # the default's mask start named
        ({"method": "willags-auto", "configuration": "willags-splitclone"}, "willags-splitclone"),
        ({"method": "willags-auto"}, "willags-auto"),  # an older full model under it
        ({"method": "peer", "date": "2026-11-25T19:00:00"}, "peer"),
    ],
)
def test_a_record_is_named_by_the_configuration_it_measured(rec, name):
    assert configuration(rec) == name


def test_default_schedule_changes_only_the_budget(tmp_path):
    ref = base_trainer_config("willags")
    cfg = base_trainer_config("willags")
    apply_schedule(cfg, 5000, "default")
    assert cfg.max_num_iterations == 5000
    assert cfg.pipeline.model == ref.pipeline.model
    with pytest.raises(ValueError):
        apply_schedule(cfg, 10, "fast")


# ---------------------------------------------------------------- records, markdown


def _rec(scene, method, steps, psnr, device="cpu", tag="ds2", train_s=100.0, **kw):
    r = {
        "scene": scene, "method": method, "device": device, "steps": steps, "tag": tag, "psnr": psnr,
        "ssim": 0.5, "lpips": None, "full_psnr": psnr - 0.1, "encoder_psnr": psnr - 1, "train_s": train_s,
        "s_per_step": train_s / steps, "fps": 10.0, "num_gaussians": 1234, "peak_mem_gb": 1.5, "status": "ok",
        "date": "2026-01-02T03:04:05", "command": "python -m benchmarks run --grid g.json", "commit": "abc1234",
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
    by = {record_key(r): r["psnr"] for r in merged}
    assert by[("fox-wild", "willags", "cpu", 300, "ds2")] == 19.0  # replaced
    assert by[("fox-wild", "willags", "cpu", 100, "ds2")] == 15.0  # kept
    assert by[("fox-wild", "willags", "cuda", 300, "")] == 25.0  # other device kept
    assert by[("fox-clean", "willags", "cpu", 300, "ds2")] == 20.0  # added
    # a different tag is a different record
    assert len(merge_records(merged, [_rec("fox-wild", "willags", 300, 1.0, tag="ds4")])) == 5


def test_merge_names_a_record_another_commit_replaces(tmp_path, capsys):
    """The key holds no commit: a merge that replaces one commit's run by another's says so (and which tag)."""
    from benchmarks.grid import main
    from benchmarks.records import replaced_across_commits

    old = [_rec("fox-wild", "willags", 300, 18.0) | {"commit": "aaa"}, _rec("fox-clean", "willags", 300, 20.0)]
    new = [_rec("fox-wild", "willags", 300, 19.0) | {"commit": "bbb"}, _rec("fox-clean", "willags", 300, 21.0)]
    assert [(o["commit"], n["commit"]) for o, n in replaced_across_commits(old, new)] == [("aaa", "bbb")]
    assert replaced_across_commits(old, [new[0] | {"tag": "other"}]) == []
    assert replaced_across_commits(old, [new[0] | {"commit": "aaa"}]) == []

    out = tmp_path / "bench"
    write_outputs(old, out)
    (tmp_path / "new.json").write_text(json.dumps(new))
    assert main(["--merge", str(tmp_path / "new.json"), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "fox-wild willags cpu 300 ds2: the record of aaa is replaced by bbb's" in said
    assert "fox-clean" not in said.split("records ->")[0]
    assert {r["scene"]: r["psnr"] for r in load_records(out.with_suffix(".json"))} == {
        "fox-wild": 19.0,
        "fox-clean": 21.0,
    }


def test_write_outputs_merges_into_existing_file(tmp_path):
    out = tmp_path / "bench"
    write_outputs([_rec("fox-wild", "willags", 300, 18.0, device="cuda", tag="")], out)
    recs = merge_records(load_records(out.with_suffix(".json")), [_rec("fox-wild", "willags", 300, 17.0)])
    write_outputs(recs, out)
    back = load_records(out.with_suffix(".json"))
    assert sorted(r["device"] for r in back) == ["cpu", "cuda"]
    md = out.with_suffix(".md").read_text()
    assert "## Grid runs on the GPU" in md and "## Grid runs on the CPU" in md


def test_markdown_lists_every_record_in_the_table_of_its_kind():
    recs = [
        _rec("default", "willags", 300, 21.0, tag=""),
        _rec("fox-wild", "willags", 300, 18.0, mask_iou=0.4, mask_fp_rate=0.02, seed=43),
        _rec("fox-wild", "willags-3dgs", 100, 16.5),
        {**_rec("fox-wild", "willags-lite", 300, 0.0), "psnr": None, "status": "failed (exit 1)"},
        _rec("reichstag", "peer", 5000, 19.5, device="cuda", machine="NVIDIA H200 (16 CPU cores)", tag="h200-r1"),
        {  # a long run under the time budget; milestones sorted by step, not as text
            **_rec("reichstag", "willags", 30000, 19.4, device="cuda", machine="NVIDIA H100 80GB HBM3", tag="knob"),
            "kind": "long_run", "steps_done": 15004, "time_budget_minutes": 5.0,
            "milestones": {"15004": {"psnr": 19.43}, "2000": {"psnr": 18.0}, "10000": {"psnr": 19.1}},
        },
    ]  # fmt: skip
    md = render_markdown(recs)
    gpu, cpu = md.index("## Grid runs on the GPU"), md.index("## Grid runs on the CPU")
    assert gpu < md.index("### reichstag (GPU)") < cpu < md.index("### default (cpu)") < md.index("### fox-wild (cpu)")
    assert "| peer | h200-r1 | – | 5000 | 19.50 | 0.500 | – | 100 | 1,234 | H200 | abc1234 |" in md
    # the steps first, the mask columns where a run scored its mask, a failed run's status in place of its PSNR
    assert md.index("| willags-3dgs | ds2 | – | 100 |") < md.index("| willags | ds2 | 43 | 300 | 18.00 |")
    assert "| 0.400 | 2.0% | cpu | abc1234 |" in md and "| willags-lite | ds2 | – | 300 | failed (exit 1) |" in md
    assert "| reichstag | willags | knob | – | 15004 | 100 | 2k: 18.00, 10k: 19.10, 15004: 19.43 | 5 min | H100 |" in md


# ---------------------------------------------------------------- end to end


@pytest.mark.slow
def test_tiny_grid_end_to_end(tmp_path):
    spec = {
        "device": "cpu", "steps": [5], "protocol_steps": 2, "max_test_images": 1, "mask_max_images": 2,
        "fps_views": 1, "runs": [{"scene": "default", "methods": ["willags-earlymask"]}],
    }  # fmt: skip
    # willags-earlymask: the mask from its warm-up's end whatever the renders leave, so the record scores the mask
    gpath = tmp_path / "grid.json"
    gpath.write_text(json.dumps(spec))
    out = tmp_path / "docs" / "benchmarks"
    write_outputs([_rec("fox-wild", "willags", 300, 18.0, device="cuda", tag="")], out)  # a GPU record
    logs = []
    recs = grid.run_grid(gpath, out, tmp_path / "work", "bench-test", overrides={"concurrent_runs": 2}, log=logs.append)
    assert len(recs) == 1 and recs[0]["status"] == "ok", logs
    r = recs[0]
    for k in ("psnr", "ssim", "encoder_psnr", "full_psnr", "train_s", "fps", "num_gaussians", "peak_mem_gb"):
        assert isinstance(r[k], (int, float)) and np.isfinite(r[k]), k
    assert r["lpips"] is None or np.isfinite(r["lpips"])
    assert r["mask_status"] == "ok" and r["mask_num_images"] == 2  # the synthetic scene has masks_gt/
    assert r["steps"] == 5 and r["device"] == "cpu" and r["scene"] == "default" and r["command"] == "bench-test"
    assert r["concurrent_runs"] == 2  # --concurrent (benchmarks/remote/grid.sh) recorded
    back = load_records(out.with_suffix(".json"))
    assert {x["device"] for x in back} == {"cpu", "cuda"}  # merged, the GPU record kept
    assert "### default (cpu)" in out.with_suffix(".md").read_text()
    assert not (tmp_path / "work" / "default-willags-earlymask-5-cpu" / "out").exists()  # checkpoints removed


def test_markdown_renders_speed_suite_records_as_their_own_table():
    speed = {
        "scene": "synthetic-box-1000000-800px", "method": "willags", "device": "NVIDIA H100 80GB HBM3", "steps": 0,
        "tag": "h100", "step_ms": 52.6, "step_ratio_vs_splatfacto": 3.14, "extra_vram_gb": 1.98,
        "host_syncs_per_step": 26.0, "render_fps_ratio_vs_gsplat": 0.293, "render_fps_ratio_vs_splatfacto": 1.09,
        "code_commit": "abc1234",
    }  # fmt: skip
    md = render_markdown([speed])
    row = "| synthetic-box-1000000-800px | willags | h100 | H100 | 52.60 | 3.14 | +1.98 | 26 | 1.09 | 0.293 | – | abc1234 |"
    assert "## Speed suite" in md and row in md
    assert "## Grid runs" not in md and "| PSNR |" not in md


# ---------------------------------------------------------------- pictures, the peer, long runs


def test_the_render_sheet_stacks_ground_truth_over_the_render_with_its_psnr(tmp_path):
    import torch

    from benchmarks.child import save_right_halves

    gt, pred = torch.zeros(40, 30, 3), torch.ones(40, 30, 3)
    p = save_right_halves(tmp_path / "r.png", [(gt, pred), (gt, pred)], [19.0, 18.0], height=20)
    im = np.asarray(Image.open(p).convert("RGB"))
    assert im.shape == (40, 30, 3)  # two columns of 15 px (30 px wide at 40 -> 20 px high), two rows
    assert im[:20].max() == 0 and im[37:].min() == 255  # GT above (black), render below (white, under the label)
    assert (im[20:37] != 255).any()  # the PSNR label is written on the render


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
            return {"rgb": e[:3].expand(int(camera.height), int(camera.width), 3)}

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

    # the training fit the harness records after the protocol: the peer has no mask, so no kept pixels, and its
    # own row reproduces its own render
    from willags_ns.eval.protocol import train_view_scores

    own = train_view_scores(model, cam, [peer.appearance_embeds.weight[0, :3].detach().expand(6, 8, 3)])
    assert own["train_num_images"] == 1 and own["train_psnr"] > 40 and "train_psnr_kept" not in own
    from willags_ns.eval.mask_eval import mask_scores, trained_mask

    assert trained_mask(model) is None  # and so no mask scores either
    assert mask_scores(model, None, None) == {"status": "no perceptual mask in this model"}
    # and the protocol itself, as the harness scores a peer's run (its start rule and oracle included)
    from willags_ns.eval.protocol import EvalProtocolConfig, evaluate_model

    big = Cameras(camera_to_worlds=torch.eye(4)[:3][None], fx=1.0, fy=1.0, cx=16.0, cy=12.0, width=32, height=24)
    photo = torch.tensor([0.2, 0.7, 0.4]).expand(24, 32, 3)
    fitted, _ = evaluate_model(model, big, [photo], EvalProtocolConfig(steps=60, lr=0.05), ["t.jpg"])
    agg, per_image = evaluate_model(
        model, big, [photo], EvalProtocolConfig(steps=2, oracle=True, start_candidates=2), ["t.jpg"]
    )
    assert fitted["psnr"] > 20 and per_image[0]["image"] == "t.jpg" and "oracle_psnr" in agg


def test_peer_source_missing_is_a_clear_error(tmp_path, monkeypatch):
    from benchmarks import peer

    monkeypatch.setenv(peer.PEER_ENV, str(tmp_path))
    with pytest.raises(FileNotFoundError, match="KevinXu02/splatfacto-w"):
        peer.peer_source()


def test_records_name_the_commit_given_by_the_gpu_command(monkeypatch):
    """On the lent GPU machine the tree's git metadata is not the source's: $WILLAGS_COMMIT names the commit."""
    from benchmarks.grid import git_commit

    monkeypatch.delenv("WILLAGS_COMMIT", raising=False)
    here = git_commit()
    assert here is None or len(here.split("+")[0]) >= 7
    monkeypatch.setenv("WILLAGS_COMMIT", "abc1234")
    assert git_commit() == "abc1234"


def test_long_run_record_carries_the_seed_and_the_last_milestone(tmp_path):
    """A repeat of a long run differs from the first by its seed: the record must say which (remote/long.sh's
    seed), and its scores are the final milestone's."""
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
        "scores": {
            "300": {"psnr": 30.5, "ssim": 0.9, "train_psnr": 33.0, "mask_iou": 0.7, "mask_fp_rate": 0.01},
            "100": {"psnr": 20.0},
        },
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
    assert (rec["mask_iou"], rec["mask_fp_rate"]) == (0.7, 0.01)  # the transient mask the run ended with


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


def test_a_queues_archive_is_read_as_its_records_and_needs_a_file_to_keep_them(tmp_path, capsys):
    """`benchmarks merge queues.tgz --keep FILE`: every queue's rec/long-*.json (lists) in name order, the logs and
    anything else left out; without --keep it stops with one line naming the archive, and a broken archive says so."""
    import io
    import tarfile

    from benchmarks.records import queue_records

    archive = tmp_path / "queues.tgz"
    members = {
        "tmp/queues/q2/rec/long-b.json": [{"scene": "b-cv1of2", "method": "willags"}],
        "tmp/queues/q1/rec/long-a.json": [
            {"scene": "a-cv1of2", "method": "peer"},
            {"scene": "a-cv2of2", "method": "peer"},
        ],
        "tmp/queues/q1/queue.log": "not json",
        "tmp/queues/q1/rec/other.json": [{"scene": "x"}],
    }
    with tarfile.open(archive, "w:gz") as tf:
        for name, body in members.items():
            data = (body if isinstance(body, str) else json.dumps(body)).encode()
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    assert [r["scene"] for r in queue_records(archive)] == ["a-cv1of2", "a-cv2of2", "b-cv1of2"]
    with pytest.raises(SystemExit):
        grid.main(["--merge", str(archive), "--out", str(tmp_path / "out")])
    said = capsys.readouterr().err.strip().splitlines()[-1]
    assert str(archive) in said and "--keep" in said
    rec = _rec("fox-wild", "willags", 5000, 22.0, tag="q-test")
    with tarfile.open(tmp_path / "one.tgz", "w:gz") as tf:
        data = json.dumps([rec]).encode()
        info = tarfile.TarInfo("tmp/queues/q1/rec/long-fox.json")
        info.size = len(data)
        tf.addfile(info, io.BytesIO(data))
    keep, out = tmp_path / "gpu_runs" / "kept.json", tmp_path / "out"
    assert grid.main(["--merge", str(tmp_path / "one.tgz"), "--keep", str(keep), "--out", str(out)]) == 0
    assert load_records(keep) == [rec] and rec in load_records(out.with_suffix(".json"))
    (tmp_path / "broken.tgz").write_bytes(b"not a gzip")
    with pytest.raises(SystemExit, match="not a queues archive"):
        queue_records(tmp_path / "broken.tgz")
