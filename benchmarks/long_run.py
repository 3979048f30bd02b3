"""A full-length training run (30k steps by default), trained in time-limited segments, scored at milestones.

Each `train` call resumes from the run's newest checkpoint (nerfstudio's --load-dir: parameters, optimiser and
scheduler states), trains until its time budget (--budget-s), writes a checkpoint at the last step it finished and
stops. Milestone checkpoints (--milestones) are kept with the train seconds to the end of each milestone's step;
`eval` scores each milestone under the NeRF-W protocol once. RUN_DIR/state.json holds what the run learns (train
seconds per segment and milestone, runs sharing the GPU, scores); `record` makes it a record of
benchmarks/records/benchmarks.json (benchmarks/curves.py draws PSNR vs time from its milestones).

    python -m benchmarks long-run train  --method willags --data .gpu-data/reichstag --run-dir /tmp/lr/willags --budget-s 480
    python -m benchmarks long-run eval   --run-dir /tmp/lr/willags
    python -m benchmarks long-run record --run-dir /tmp/lr/willags --tag h100-30k --out $OUT/willags-30k.json

Methods are benchmarks.methods METHODS (stock schedule: only max_num_iterations is set, as
`ns-train <method> --max-num-iterations N` does). Train seconds exclude set-up, checkpoint loading and evaluation.
"""

import argparse
import datetime as _dt
import fcntl
import gc
import json
import os
import random
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from benchmarks.child import mask_record, patch_offline, protocol_scores, sync
from benchmarks.collections import CollectionError, model_digest
from benchmarks.grid import downscaled_scene, git_commit, machine_description
from benchmarks.methods import METHODS, build_config, is_peer

STATE = "state.json"


def _state(run_dir: Path) -> dict[str, Any]:
    p = run_dir / STATE
    return json.loads(p.read_text()) if p.is_file() else {"segments": [], "scores": {}}


def _save_state(run_dir: Path, state: dict[str, Any]) -> None:
    tmp = run_dir / (STATE + f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(state, indent=1, default=str))
    tmp.replace(run_dir / STATE)


def _save_score(run_dir: Path, milestone: str, rec: dict[str, Any], variant: str | None = None) -> None:
    """Add one milestone's scores to the state, under a lock: `eval` runs one process per milestone at once (their
    set-up, mostly CPU, overlaps), each re-reading the state so that none overwrites another's score. A `variant`'s
    scores go to state["variants"][variant] (apart from the protocol's own, which the record is made of)."""
    with open(run_dir / (STATE + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        state = _state(run_dir)
        where = state["scores"] if variant is None else state.setdefault("variants", {}).setdefault(variant, {})
        where[milestone] = rec
        _save_state(run_dir, state)


def _ckpt_dir(run_dir: Path) -> Path:
    found = sorted(run_dir.glob("out/bench/*/run/nerfstudio_models"))  # <output_dir>/<experiment>/<method>/<ts>
    return found[0] if found else run_dir / "out" / "none"


def _ckpt_steps(run_dir: Path) -> list[int]:
    d = _ckpt_dir(run_dir)
    return sorted(int(p.stem.split("-")[1]) for p in d.glob("step-*.ckpt")) if d.is_dir() else []


def _patch_resume(model_cls) -> None:
    """Stock splatfacto's load_state_dict (and the peer's, written the same way) replaces its Parameter objects with
    new ones of the checkpoint's size, but nerfstudio's Trainer built the optimisers (and loads their state) on the
    old ones: a resumed run optimises tensors the model no longer uses and gsplat's densification indexes mismatched
    states (a device-side assert, seen here). Resize the Parameters in place instead, as WillagsModel.load_state_dict
    does."""

    def load_state_dict(self, state, **kwargs):
        self.step = 30000  # as stock: the trainer's step callback sets the real step before the next iteration
        n = state["gauss_params.means"].shape[0]
        for param in self.gauss_params.values():
            param.data = torch.zeros((n,) + param.shape[1:], device=self.device)
        torch.nn.Module.load_state_dict(self, state, **kwargs)

    model_cls.load_state_dict = load_state_dict


def _setup(
    method: str,
    data: Path,
    run_dir: Path,
    steps: int,
    seed: int,
    load_step: int | None,
    test_mode: str,
    budget_minutes: float | None = None,
    downscale: int | None = None,
):
    """A set-up nerfstudio Trainer for the run (resumed from load_step's checkpoint when given). ``budget_minutes``:
    `--pipeline.time-budget-minutes` (willags' knob: it chooses the preset and the last step, and fits the
    densification and mask schedules into it, and a plan under 2000 steps its learning rates; ``steps`` is then the
    cap, as --max-num-iterations is). ``downscale`` > 1: the photos `downscale` times smaller (the resampled mirror
    of the scene the grid's runs use)."""
    base = METHODS[method].base
    patch_offline(base)  # as the grid runs do (offline LPIPS; the peer's package on the path)
    if base == "splatfacto":
        from nerfstudio.models.splatfacto import SplatfactoModel

        _patch_resume(SplatfactoModel)
    elif is_peer(base):
        import splatfactow.splatfactow_model as pm  # type: ignore[import-not-found]

        _patch_resume(pm.SplatfactoWModel)
    if downscale is not None and downscale > 1:
        data = downscaled_scene(data, downscale)
    config = build_config(
        method, steps, "cuda" if torch.cuda.is_available() else "cpu", data, downscale, "default", run_dir / "out"
    )
    config.machine.seed = seed
    if load_step is not None:  # the model its checkpoints hold, resumed from the one of load_step
        _trained_model(config)
        config.load_dir = _ckpt_dir(run_dir)
        config.load_step = load_step
    if budget_minutes is not None:
        if not hasattr(config.pipeline, "time_budget_minutes"):
            raise SystemExit(f"long_run: {method} has no time budget (only willags' pipeline has the knob)")
        config.pipeline.time_budget_minutes = budget_minutes
    config.steps_per_save = 10**9  # checkpoints are written here: at milestones and at the end of the segment
    config.save_only_latest_checkpoint = False
    config.save_config()
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode=test_mode)
    return trainer


def _trained_model(config) -> None:
    """Resuming or scoring a willags run: the model it trained, from its own config.yml (written when it trained: the
    inspector's resolved switches, or the time budget's preset), in place of the one its method name builds today.
    Rebuilding from the name would inspect the scene again in every segment and every scoring process, and a run
    named `willags` before the default inspected (its record's configuration: willags-full) would get another model
    than its checkpoints hold. Other methods' models do not depend on the scene: left as built."""
    saved = config.get_base_dir() / "config.yml"
    if not hasattr(config.pipeline.model, "auto_config") or not saved.exists():
        return
    trained = yaml.load(saved.read_text(), Loader=yaml.Loader)
    if not hasattr(trained, "pipeline"):
        raise SystemExit(
            f"long_run: {saved} holds no run configuration (it reads as {type(trained).__name__}); the model its "
            "checkpoints hold cannot be rebuilt from it"
        )
    config.pipeline.model = trained.pipeline.model


def _milestones(spec: str, state: dict[str, Any]) -> list[int]:
    """The milestones to score: ``spec`` ("1000,2000,..."), or "all": every step whose train time the run recorded
    (its milestones, and where a time budget stopped it)."""
    if spec == "all":
        return sorted(int(k) for k in state.get("milestone_train_s", {}))
    return [int(m) for m in spec.split(",")]


def _eval_method(state: dict[str, Any]) -> str:
    """The method whose model the checkpoints hold: the preset the knob chose (it may swap willags for willags-lite
    on a CPU), else the run's."""
    chosen = ((state.get("time_budget") or {}).get("choice") or {}).get("preset")
    return chosen if chosen in METHODS else state["method"]


def milestone_spec(text: str) -> str:
    """``--milestones``: "all" or step counts separated by commas or spaces ("5000,15000", "5000 15000"), returned
    comma-separated; anything else is an argparse error naming the value."""
    if text.strip() == "all":
        return "all"
    parts = text.replace(",", " ").split()
    if not parts or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise argparse.ArgumentTypeError(f"{text!r}: expected 'all' or positive step counts such as 5000,15000")
    return ",".join(parts)


class Stop(Exception):
    """Raised by a step callback to end ``trainer.train()`` after that step."""


def train(args) -> int:
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    state = _state(run_dir)
    state.update({"method": args.method, "data": str(args.data), "steps": args.steps, "seed": args.seed})
    if args.downscale > 1:  # the photos resampled once into a mirror of the scene (benchmarks/grid.py)
        state["downscale"] = args.downscale
    done = _ckpt_steps(run_dir)
    start = done[-1] if done else None
    if start is not None and start >= args.steps - 1:
        print(f"long_run: {args.method} already at step {start}")
        return 0
    milestones = {int(m) - 1 for m in args.milestones.split(",")}  # nerfstudio counts steps from 0
    t_setup = time.perf_counter()
    if args.budget_minutes is not None and start is not None:
        raise SystemExit("long_run: a time-budget run is trained in one segment (the knob plans from its first step)")
    if args.budget_minutes is not None:
        state["time_budget_minutes"] = args.budget_minutes
    trainer = _setup(
        args.method,
        Path(args.data),
        run_dir,
        args.steps,
        args.seed,
        start,
        "val",
        args.budget_minutes,
        state.get("downscale"),
    )
    _ = trainer.pipeline.datamanager.cached_train
    setup_s = time.perf_counter() - t_setup
    device = trainer.pipeline.model.device
    seg = {
        "start_step": (start + 1) if start is not None else 0,
        "setup_s": setup_s,
        "budget_s": args.budget_s,
        "concurrent_runs": args.concurrent,
    }
    before_s = sum(s["train_s"] for s in state["segments"])  # train seconds of the earlier segments
    milestone_s = state.setdefault("milestone_train_s", {})
    t0 = [0.0]
    last = [seg["start_step"] - 1]
    budget = getattr(trainer, "time_budget", None)  # the knob's (its callback runs before this one)

    laps = seg["laps"] = []  # [steps done, train s since the segment's start, Gaussians] every --lap-every steps

    def after_step(step: int) -> None:
        last[0] = step
        if args.lap_every > 0 and (step + 1) % args.lap_every == 0:
            sync(device)  # once every lap: the clock reads the work done, not the work queued
            laps.append([step + 1, time.perf_counter() - t0[0], int(trainer.pipeline.model.num_points)])
        if args.check_finite:  # every parameter and gradient finite after every step (docs/reliability.md, row 19)
            named = trainer.pipeline.model.named_parameters()
            bad = [
                n for n, p in named if not p.isfinite().all() or (p.grad is not None and not p.grad.isfinite().all())
            ]
            if bad:
                raise RuntimeError(f"long_run: non-finite at step {step}: {bad[:20]}")
        knob_end = budget is not None and budget.stopped_after == step  # the knob ends the run after this step
        if step in milestones or step == args.steps - 1 or knob_end:
            sync(device)  # the step's work done, then the clock: the milestone's own train time
            milestone_s[str(step + 1)] = before_s + time.perf_counter() - t0[0]
            if (step == args.steps - 1 or knob_end) and hasattr(trainer, "finish_run"):
                trainer.finish_run(step)  # the run's end as ns-train ends it (Stop below skips the loop's own)
            trainer.save_checkpoint(step)
            # the state as if the segment ended here: a run killed later is scored at its milestones and resumes
            # from this checkpoint with the right train time
            done_seg = {**seg, "train_s": milestone_s[str(step + 1)] - before_s, "end_step": step}
            _save_state(run_dir, {**state, "segments": [*state["segments"], done_seg]})
        # nerfstudio's loop runs max_num_iterations steps from wherever it resumed: stop at the run's last step
        if step >= args.steps - 1 or time.perf_counter() - t0[0] > args.budget_s:
            raise Stop

    trainer.callbacks.append(
        TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], after_step, update_every_num_iters=1)
    )
    sync(device)
    t0[0] = time.perf_counter()
    stopped = False
    try:
        with torch.autograd.set_detect_anomaly(args.check_finite):  # a NaN made in a backward op raises at that op
            trainer.train()
    except Stop:
        stopped = True
    sync(device)
    seg["train_s"] = time.perf_counter() - t0[0]
    seg["end_step"] = last[0]
    if stopped and last[0] not in milestones and last[0] != args.steps - 1:
        trainer.save_checkpoint(last[0])  # where the next segment resumes
    seg["num_gaussians"] = int(trainer.pipeline.model.num_points)
    if budget is not None:
        state["time_budget"] = {**getattr(trainer, "budget_record", {}), "run": budget.summary()}
        state["end_step"] = last[0] + 1  # where the knob stopped: scored like a milestone
    if torch.cuda.is_available():
        seg["peak_mem_gb"] = torch.cuda.max_memory_allocated() / 1024**3
    # keep the milestones and the newest checkpoint only
    steps = _ckpt_steps(run_dir)
    for s in steps[:-1]:
        if s not in milestones:
            (_ckpt_dir(run_dir) / f"step-{s:09d}.ckpt").unlink()
    state["segments"].append(seg)
    _save_state(run_dir, state)
    print(
        f"long_run: {args.method} steps {seg['start_step']}..{seg['end_step']} in {seg['train_s']:.0f} s "
        f"({seg['num_gaussians']:,} Gaussians)"
    )
    return 0


def read_residual(model, residual_latent: str, method: str) -> None:
    """Score a trained run with its local residual reading `residual_latent` outside training
    (modulation.residual_latent: "own" or "mean"), whatever it trained with: training does not depend on it, so one
    run scores both readouts."""
    nets = getattr(model, "appearance_nets", None)
    color_model = nets.color_model if nets is not None else None
    if color_model is None or not hasattr(color_model, "residual_latent"):
        raise SystemExit(f"long_run: --residual-latent needs a run whose colour model is the modulation ({method})")
    color_model.residual_latent = residual_latent


def evaluate(args) -> int:
    run_dir = Path(args.run_dir)
    state = _state(run_dir)
    milestones = _milestones(args.milestones, state)
    have = set(_ckpt_steps(run_dir))
    variant = args.variant or None
    done = state["scores"] if variant is None else state.get("variants", {}).get(variant, {})
    absent = [m for m in milestones if str(m) not in done and (m - 1) not in have]
    if absent:
        kept = ", ".join(str(s + 1) for s in sorted(have)) or "none"
        print(
            f"long_run: no checkpoint at step {', '.join(map(str, absent))} in {run_dir} (checkpoints kept at: {kept}); "
            "--milestones names the steps to score",
            file=sys.stderr,
        )
        if len(absent) == len(milestones):
            return 2
    for m in milestones:
        if str(m) in done or (m - 1) not in have:
            continue
        t = time.perf_counter()
        trainer = _setup(
            _eval_method(state),
            Path(state["data"]),
            run_dir,
            state["steps"],
            state["seed"],
            m - 1,
            "test",
            downscale=state.get("downscale"),
        )
        # (no budget at evaluation: the checkpoint holds the model the knob chose, its config.yml the preset)
        spec = {
            "method": state["method"],  # protocol_scores picks the peer's adapter by method
            "scene_name": Path(state["data"]).name,  # names the run's pictures and region maps
            "tag": f"s{state['seed']}-{m}" + (f"-{variant}" if variant else ""),
            # region maps ($WILLAGS_BENCH_REGIONS) of the run's last milestone, under the protocol itself
            "regions": m == state["steps"] and variant is None,
            "protocol_steps": args.protocol_steps,
            "protocol_lr": args.protocol_lr,
            "oracle": args.oracle,
            "start_candidates": args.protocol_start_candidates,
            "max_test_images": -1,
            "train_views": args.train_views,
        }
        if args.residual_latent:
            read_residual(trainer.pipeline.model, args.residual_latent, state["method"])
        rec = protocol_scores(trainer, spec)
        rec["num_gaussians"] = int(trainer.pipeline.model.num_points)
        decision = getattr(trainer.pipeline.model, "cap_decision", None)
        if decision is not None and decision.get("share") is not None:  # the "transients" cap rule's measure
            rec["cap_rule_share"] = float(decision["share"])
        started = getattr(trainer.pipeline.model, "mask_decision", None)
        if started is not None and started.get("share") is not None:  # the mask's start rule's measure and verdict
            rec["mask_start_share"] = float(started["share"])
            rec["mask_started"] = bool(started["start"])
        if m == state["steps"] and variant is None:  # the transient mask the run ended with
            rec.update(mask_record(trainer.pipeline.model, trainer.pipeline.datamanager.train_dataset))
        rec["eval_wall_s"] = time.perf_counter() - t
        if variant:
            rec["protocol"] = {
                "steps": args.protocol_steps,
                "lr": args.protocol_lr,
                "oracle": args.oracle,
                "start_candidates": args.protocol_start_candidates,
                **({"residual_latent": args.residual_latent} if args.residual_latent else {}),
            }
        _save_score(run_dir, str(m), rec, variant)
        print(
            f"long_run: {state['method']} @ {m}{' (' + variant + ')' if variant else ''}: psnr {rec.get('psnr', float('nan')):.2f} "
            f"(train views {rec.get('train_psnr', float('nan')):.2f}"
            + (
                f", {rec['train_psnr_kept']:.2f} over the {rec['train_kept_share']:.1%} of their pixels the mask keeps)"
                if "train_psnr_kept" in rec
                else ")"
            )
            + (
                f"; residual blobs in {rec['train_outlier_share']:.1%} of their pixels"
                if "train_outlier_share" in rec
                else ""
            )
        )
        del trainer
        gc.collect()
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    return 0


def per_image_scores(
    per_image: list[dict[str, Any]], keys: tuple[str, ...] = ("image", "psnr", "ssim", "lpips")
) -> list[dict[str, Any]]:
    """Each test photo's `keys` (by default its name and right-half scores), as a record keeps them: what the
    cross-validation (benchmarks/cv.py) pairs between methods photo by photo."""
    return [{k: r[k] for k in keys if k in r} for r in per_image]


VARIANT_KEYS = ("psnr", "oracle_psnr", "encoder_psnr", "left_loss_after", "fit_shift", "start_pick")
"""What a record keeps of a protocol variant's scores, over all test photos and per photo."""


def variant_scores(variants: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The scores of `eval --variant` (state.json's variants: name -> milestone -> scores) as a record keeps them:
    the protocol's settings, the means and each test photo's VARIANT_KEYS."""
    return {
        name: {
            m: {
                "protocol": v.get("protocol"),
                **{k: v[k] for k in VARIANT_KEYS if k in v},
                "per_image": per_image_scores(v.get("per_image", []), ("image", *VARIANT_KEYS)),
            }
            for m, v in sorted(by_step.items(), key=lambda kv: int(kv[0]))
        }
        for name, by_step in variants.items()
    }


def record(args) -> int:
    """The run as a record of benchmarks/records/benchmarks.json: train wall time summed over segments, PSNR at each
    milestone."""
    state = _state(Path(args.run_dir))
    segs = state["segments"]
    device = "cuda" if torch.cuda.is_available() else "cpu"
    times = state.get("milestone_train_s", {})
    shared = [s["concurrent_runs"] for s in segs if isinstance(s.get("concurrent_runs"), int)]
    rec: dict[str, Any] = {
        "scene": Path(state["data"]).name,
        "method": state["method"],
        "device": device,
        "steps": state["steps"],
        "seed": state.get("seed"),
        "tag": args.tag,
        "schedule": "default",
        "protocol_steps": args.protocol_steps,
        "kind": "long_run",
        "train_s": sum(s["train_s"] for s in segs),
        "segments": segs,
        "steps_done": (segs[-1]["end_step"] + 1) if segs else 0,
        "concurrent_runs": max([args.concurrent, *shared]),  # the most runs on the GPU in any segment
        "milestones": {
            k: {
                **{
                    kk: v[kk]
                    for kk in (
                        "psnr",
                        "ssim",
                        "lpips",
                        "train_psnr",
                        "train_psnr_kept",
                        "train_kept_share",
                        "train_outlier_share",
                        "num_gaussians",
                        "latent_spread",
                        "cap_rule_share",
                        "mask_start_share",
                        "mask_started",
                    )
                    if kk in v
                },
                **({"train_s": times[k]} if k in times else {}),
                **({"per_image": per_image_scores(v["per_image"])} if v.get("per_image") else {}),
            }
            for k, v in sorted(state["scores"].items(), key=lambda kv: int(kv[0]))
        },
        "date": _dt.datetime.now().isoformat(timespec="seconds"),
        "machine": machine_description(device),
        "commit": git_commit(),
        "status": "ok",
    }
    try:  # which SfM model the run started from: runs on two builds of one collection do not compare (cv.model_lines)
        rec["scene_model_sha256"] = model_digest(Path(state["data"]))
    except CollectionError:  # a scene without a COLMAP model here (moved, or another layout): the record says nothing
        pass
    if state.get("time_budget") is not None:
        rec["time_budget_minutes"] = state.get("time_budget_minutes")
        rec["time_budget"] = state["time_budget"]
        rec["end_step"] = state.get("end_step")
    if state.get("variants"):
        rec["protocol_variants"] = variant_scores(state["variants"])
    last = state["scores"].get(str(state.get("end_step") or state["steps"]))
    if last is not None:
        rec.update({k: last[k] for k in ("psnr", "ssim", "lpips") if k in last})
        rec.update({k: v for k, v in last.items() if k.startswith("mask_") or k == "subject_masked"})
    Path(args.out).write_text(json.dumps([rec], indent=1, default=str) + "\n")
    print(json.dumps({k: rec[k] for k in ("method", "train_s", "steps_done", "milestones")}, default=str))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("train", "eval", "record"):
        p = sub.add_parser(name)
        p.add_argument("--run-dir", required=True)
        p.add_argument(
            "--milestones",
            type=milestone_spec,
            default="7000,15000,30000",
            help="steps whose checkpoints are kept and scored (commas or spaces between them; eval: also 'all')",
        )
        p.add_argument("--protocol-steps", type=int, default=128)
    t = sub.choices["train"]
    t.add_argument("--method", required=True)
    t.add_argument("--data", required=True)
    t.add_argument("--steps", type=int, default=30000)
    t.add_argument("--seed", type=int, default=42)
    t.add_argument("--budget-s", type=float, required=True, help="stop (and checkpoint) after this many train s")
    t.add_argument("--concurrent", type=int, default=1, help="runs on the GPU during this segment, itself included")
    t.add_argument("--budget-minutes", type=float, help="willags' --pipeline.time-budget-minutes; --steps is the cap")
    t.add_argument("--check-finite", action="store_true", help="anomaly mode; stop at a non-finite parameter or grad")
    t.add_argument("--downscale", type=int, default=1, help="train and score on photos this many times smaller")
    t.add_argument(
        "--lap-every",
        type=int,
        default=500,
        help="record the train time and the Gaussians every this many steps (where a run's time goes; 0: never)",
    )
    e = sub.choices["eval"]
    e.add_argument("--train-views", type=int, default=8)
    e.add_argument("--protocol-lr", type=float, default=0.01, help="Adam learning rate of the latent fit")
    e.add_argument("--oracle", action="store_true", help="also fit the latent on the whole test image (oracle_*)")
    e.add_argument(
        "--protocol-start-candidates",
        type=int,
        default=0,
        help="training latents also tried as the fit's start (EvalProtocolConfig.start_candidates; 0: the mean alone)",
    )
    e.add_argument(
        "--variant",
        default="",
        help="score under these protocol settings apart: state.json's variants[NAME], never the record's scores "
        "(how the scores depend on the fit: more steps, another learning rate, the oracle, the start)",
    )
    e.add_argument(
        "--residual-latent",
        choices=("own", "mean"),
        help="with --variant: the latent the modulation's local residual reads outside training (its "
        "modulation.residual_latent), whatever the run trained with",
    )
    r = sub.choices["record"]
    r.add_argument("--tag", required=True)
    r.add_argument("--out", required=True)
    r.add_argument("--concurrent", type=int, default=1, help="runs sharing the GPU while this one trained")
    args = ap.parse_args(argv)
    if args.cmd == "eval" and args.residual_latent and not args.variant:
        ap.error("--residual-latent scores a protocol variant: name it with --variant")
    if args.cmd == "train" and args.milestones == "all":
        ap.error("--milestones all: train keeps checkpoints at step counts it is given (such as 5000,15000)")
    return {"train": train, "eval": evaluate, "record": record}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main())
