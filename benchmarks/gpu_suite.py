"""GPU measurement suite for willags: rasteriser parity, train-step time and profile, render FPS, peak VRAM.

One process measures all of it on one GPU:

    python -m benchmarks speed --all --n-gaussians 1000000 --size 800 --json-out $OUT/gpu_suite.json
    python -m benchmarks speed --quick --all            # CPU smoke test (< 60 s): torch backend only

Sections (each in its own try/except: a failure is recorded and the others still run; the JSON is rewritten
after every section, so a run killed at its time limit keeps what it finished; the code of each is in
``benchmarks/suite/``, this file keeps the command line, the records and the summary):

- ``--parity``: ``willags_ns.render.rasterize`` torch backend vs gsplat (both float32, CUDA) over random scenes
  and extremes; forward relative error (render, alpha) and gradient relative error per parameter (means, quats,
  scales, opacities, colors); a float64 torch reference says which side the error comes from. Without CUDA:
  torch float32 vs torch float64 only (gsplat skipped).
- ``--step``: mean train-step time (CUDA events, warm-up first) of a WillagsModel built directly (no ns-train)
  on a synthetic ~N-Gaussian scene, for splatfacto (stock nerfstudio, CUDA only), willags-3dgs (appearance="sh":
  the same code with splatfacto's colours) and willags variants; a per-component profile; host syncs per step.
- ``--memory``: peak ``torch.cuda.max_memory_allocated`` over the timed train steps per model (CUDA only).
- ``--render``: FPS of ``model.get_outputs`` with a fixed latent (eval, no grad) vs gsplat with the same
  Gaussians' colours precomputed.
- ``--components``: isolated forward+backward timings (tri-plane query, decoder MLP, hypernetwork, VGG, gsplat)
  next to their FLOP / byte floors from the measured device ceilings (METHOD.md's "two numbers").

The comparison is always at the same Gaussians (same seed points, scales from the same 3-NN distances, same
quaternions), the same camera and the same full resolution (num_downscales=0), at a step past every warm-up
(SH degree 3, mask active) with densification off (N stays fixed).
"""

import argparse
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # `python benchmarks/gpu_suite.py` from anywhere
    sys.path.insert(0, str(REPO))
os.environ.setdefault("MAX_JOBS", str(os.cpu_count() or 4))  # gsplat's JIT build

from benchmarks import _synthetic_gaussians as syn  # noqa: E402
from benchmarks.suite.components import section_components  # noqa: E402
from benchmarks.suite.models import DEFAULT_VARIANTS, QUICK_VARIANTS, VARIANTS  # noqa: E402
from benchmarks.suite.parity import section_parity  # noqa: E402
from benchmarks.suite.render import section_render  # noqa: E402
from benchmarks.suite.step import section_step  # noqa: E402
from benchmarks.suite.timing import environment, log, measure_ceilings  # noqa: E402


def build_records(res: dict, env: dict, args) -> list[dict]:
    """benchmarks/records/benchmarks.json records: {"scene", "method", "device", metric fields...}."""
    scene = f"synthetic-box-{args.n_gaussians}-{args.size}px"
    common = {"device": env["device"], "torch": env["torch"], "gsplat": env.get("gsplat"), "quick": args.quick}
    records = []
    step = res.get("step", {}).get("variants", {})
    base = res.get("step", {}).get("baseline")
    parity = res.get("parity", {})
    render = res.get("render", {})
    for v, r in step.items():
        rec = {"scene": scene, "method": v, **common, "n_gaussians": r.get("n_gaussians"), "image_size": args.size}
        for k in ("step_ms", "step_ms_wall", "peak_gb", "static_gb", "extra_vram_gb", "host_syncs_per_step"):
            if k in r:
                rec[k] = r[k]
        if "step_ratio_vs_baseline" in r:
            rec["step_ratio_vs_splatfacto"] = r["step_ratio_vs_baseline"]
            rec["step_baseline"] = base
        if "error" in r:
            rec["error"] = r["error"]
        records.append(rec)
    head = next((r for r in records if r["method"] == "willags"), None)
    if head is None:
        head = {"scene": scene, "method": "willags", **common}
        records.append(head)
    if "render_fps_ratio_vs_gsplat" in render:
        head["render_fps"] = render["willags_fps"]
        head["render_fps_ratio_vs_gsplat"] = render["render_fps_ratio_vs_gsplat"]
        head["render_baseline_backend"] = render.get("baseline_backend")
    if "render_fps_ratio_vs_splatfacto" in render:
        head["render_fps_ratio_vs_splatfacto"] = render["render_fps_ratio_vs_splatfacto"]
        head["splatfacto_render_fps"] = render["splatfacto_fps"]
    if "worst_fwd" in parity:
        head["parity_fwd_rel_err"] = parity["worst_fwd"]["value"]
        head["parity_grad_rel_err"] = parity["worst_grad"]["value"]
        head["parity_mode"] = parity["mode"]
    return records


def _finite(x):
    """Strict JSON: non-finite floats become strings ("inf", "nan")."""
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def write_json(path: str | None, res: dict, env: dict, args) -> None:
    if not path:
        return
    records = _finite(build_records(res, env, args))
    res = _finite(res)
    doc = {"records": records, "environment": env, "details": res}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        json.dump(records, f, indent=1, default=str)
    with open(str(Path(path).with_suffix("")) + "_details.json", "w") as f:
        json.dump(doc, f, indent=1, default=str)


def summary(res: dict, env: dict, args, t_start: float) -> None:
    log("\n" + "=" * 100)
    log(
        f"# summary: {env['device']}, torch {env['torch']}, gsplat {env.get('gsplat')}, "
        f"N={args.n_gaussians:,}, {args.size}px, {time.perf_counter() - t_start:.0f}s total"
    )
    p = res.get("parity", {})
    s = res.get("step", {})
    r = res.get("render", {})
    v = s.get("variants", {})
    w = v.get("willags", {})
    rows = []
    if "worst_fwd" in p:
        rows.append(
            ("parity fwd rel err (worst)", f"{p['worst_fwd']['value']:.2e} [{p['worst_fwd']['case']}]", "<= 1e-4")
        )
        rows.append(
            ("parity grad rel err (worst)", f"{p['worst_grad']['value']:.2e} [{p['worst_grad']['case']}]", "<= 1e-3")
        )
        for k, x in p.get("worst_grad_per_param", {}).items():
            rows.append((f"  grad {k}", f"{x['value']:.2e} [{x['case']}]", ""))
    if "step_ratio_vs_baseline" in w:
        rows.append(
            (
                f"step ratio willags / {s.get('baseline')}",
                f"{w['step_ratio_vs_baseline']:.2f} ({w['step_ms']:.1f} ms)",
                "<= 1.5 (goal)",
            )
        )
        for name, x in v.items():
            if name != "willags" and "step_ratio_vs_baseline" in x:
                rows.append((f"  {name}", f"{x['step_ratio_vs_baseline']:.2f} ({x['step_ms']:.1f} ms)", ""))
    if "render_fps_ratio_vs_gsplat" in r:
        rows.append(
            (
                f"render FPS ratio vs {r.get('baseline_backend', 'gsplat')} (precomputed colours)",
                f"{r['render_fps_ratio_vs_gsplat']:.3f} ({r['willags_fps']:.0f} fps)",
                ">= 0.9",
            )
        )
    if "extra_vram_gb" in w:
        rows.append(("extra peak VRAM (GB)", f"{w['extra_vram_gb']:+.3f}", "<= 0.5"))
        for name, x in v.items():
            if name != "willags" and "extra_vram_gb" in x:
                rows.append((f"  {name}", f"{x['extra_vram_gb']:+.3f}", ""))
    log("| metric | value | goal |")
    log("|---|---|---|")
    for a, b, c in rows:
        log(f"| {a} | {b} | {c} |")
    for k, e in res.get("errors", {}).items():
        log(f"SECTION ERROR {k}: {e.splitlines()[-1] if e else e}")
    for k, e in res.get("skipped", {}).items():
        log(f"skipped {k}: {e}")


def parse_args(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--parity", action="store_true", help="torch backend vs gsplat: forward and gradient errors")
    ap.add_argument("--step", action="store_true", help="train-step time per variant + profile + host syncs")
    ap.add_argument("--render", action="store_true", help="FPS with a fixed latent vs gsplat, precomputed colours")
    ap.add_argument("--memory", action="store_true", help="peak VRAM over one train step per variant (CUDA)")
    ap.add_argument("--components", action="store_true", help="isolated fwd+bwd timings with FLOP/byte floors")
    ap.add_argument("--all", action="store_true", help="every section")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (CPU smoke test, < 60 s)")
    ap.add_argument("--cpu", action="store_true", help="ignore CUDA even when present")
    ap.add_argument("--n-gaussians", type=int, default=None, help="Gaussians in the synthetic scene (1000000)")
    ap.add_argument("--size", type=int, default=None, help="image side in pixels (800)")
    ap.add_argument("--n-train", type=int, default=50, help="num_train_data given to the model")
    ap.add_argument("--warmup", type=int, default=None, help="warm-up train steps per variant (5)")
    ap.add_argument("--iters", type=int, default=None, help="timed train steps per variant (20)")
    ap.add_argument("--frames", type=int, default=None, help="timed render frames (100)")
    ap.add_argument("--variants", default=None, help=f"comma list from {','.join(VARIANTS)}")
    ap.add_argument("--no-profile", dest="profile", action="store_false", help="skip the per-component profile")
    ap.add_argument("--profile-variants", default="willags,willags-3dgs,splatfacto,willags-fast")
    ap.add_argument("--profile-iters", type=int, default=None)
    ap.add_argument(
        "--kernel-variants", default="", help="comma list: a torch.profiler kernel table for these (CUDA only)"
    )
    ap.add_argument(
        "--time-budget",
        type=float,
        default=480.0,
        help="seconds from start; sections (and step variants) that would start later are skipped. On a machine "
        "whose commands are killed at 600 s (the wheel install and imports run before this clock starts): <= 480",
    )
    ap.add_argument("--json-out", default=None, help="write the records (a JSON list) here, and *_details.json")
    args = ap.parse_args(argv)
    q = args.quick
    args.n_gaussians = args.n_gaussians or (3000 if q else 1_000_000)
    args.size = args.size or (64 if q else 800)
    args.warmup = args.warmup if args.warmup is not None else (1 if q else 5)
    args.iters = args.iters or (4 if q else 20)  # a multiple of 4: mask.every=4 variants average fairly
    args.frames = args.frames or (4 if q else 100)
    args.profile_iters = args.profile_iters or (4 if q else 12)
    args.variants = args.variants.split(",") if args.variants else (QUICK_VARIANTS if q else DEFAULT_VARIANTS)
    bad = [v for v in args.variants if v not in VARIANTS]
    if bad:
        ap.error(f"unknown variants {bad}; choose from {list(VARIANTS)}")
    args.profile_variants = args.profile_variants.split(",")
    args.kernel_variants = [v for v in args.kernel_variants.split(",") if v]
    if args.all or not (args.parity or args.step or args.render or args.memory or args.components):
        args.parity = args.step = args.render = args.memory = args.components = True
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    args.deadline = t_start + args.time_budget
    # the step section stops starting new variants early enough to leave the components section its minute
    args.step_deadline = args.deadline - (60.0 if args.components and not args.quick else 0.0)
    cuda = torch.cuda.is_available() and not args.cpu
    dev = torch.device("cuda" if cuda else "cpu")
    backend = "gsplat" if cuda else "torch"
    if not cuda and args.quick:
        torch.set_num_threads(1)  # a smoke test: steadier on a shared 2-core machine; its times are not measurements
    env = environment(cuda)
    log(f"# gpu_suite: {json.dumps(env)}")
    if not cuda:
        log("NOTE: no CUDA: gsplat parts are SKIPPED (parity compares torch fp32 with torch fp64; the step/render")
        log("      sections use the torch backend; stock splatfacto and VRAM numbers need CUDA).")
    res: dict = {"errors": {}, "skipped": {}}

    def run(name: str, fn) -> None:
        if time.perf_counter() - t_start > args.time_budget:
            res["skipped"][name] = f"time budget {args.time_budget:.0f}s spent"
            log(f"\n## {name}: skipped (time budget)")
            return
        t0 = time.perf_counter()
        try:
            res[name] = fn()
        except Exception:
            res["errors"][name] = traceback.format_exc()[-3000:]
            log(f"\n## {name}: FAILED\n{res['errors'][name]}")
        log(f"({name}: {time.perf_counter() - t0:.1f}s)")
        write_json(args.json_out, res, env, args)

    if cuda:
        run("ceilings", lambda: measure_ceilings(cuda))
        log(f"ceilings: {res.get('ceilings')}")

        def jit():
            from willags_ns.render import rasterize

            t0 = time.perf_counter()
            c = syn.make_parity_case("jit", 10, 32, 32, 0)
            t = {k: v.cuda() for k, v in c.tensors().items()}
            rasterize(
                t["means"],
                t["quats"],
                t["scales"],
                t["opacities"],
                t["colors"],
                c.viewmats.cuda(),
                c.Ks.cuda(),
                32,
                32,
                backend="gsplat",
            )
            torch.cuda.synchronize()
            return {"gsplat_first_call_s": time.perf_counter() - t0}

        run("gsplat_jit", jit)
        log(f"gsplat first call (JIT build or cache load): {res.get('gsplat_jit')}")
    if args.parity:
        run("parity", lambda: section_parity(args, cuda))
    if args.render:
        run("render", lambda: section_render(args, cuda, dev, backend))
    if args.memory and not args.step and not cuda:
        res["skipped"]["memory"] = "peak VRAM needs CUDA"
    elif args.step or args.memory:
        variants = [v for v in args.variants if cuda or VARIANTS[v][0] != "stock"]
        for v in args.variants:
            if v not in variants:
                res["skipped"][f"step:{v}"] = "stock splatfacto needs CUDA (hard-coded .cuda())"
        if not cuda:  # CPU bf16 autocast and inductor's C++ build are not the question here
            for v in [v for v in variants if set(VARIANTS[v][2]) & {"bf16", "compile"}]:
                variants.remove(v)
                res["skipped"][f"step:{v}"] = "bf16 / compile variants are measured on CUDA only"
        run("step", lambda: section_step(args, cuda, dev, backend, variants, memory=args.memory, timing=args.step))
        if args.memory and not cuda:
            res["skipped"]["memory"] = "peak VRAM needs CUDA"
    if args.components:
        run("components", lambda: section_components(args, cuda, dev, backend, res.get("ceilings", {})))
    summary(res, env, args, t_start)
    write_json(args.json_out, res, env, args)
    if args.json_out:
        log(f"records -> {args.json_out} (details: {str(Path(args.json_out).with_suffix(''))}_details.json)")
    return 1 if res["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
