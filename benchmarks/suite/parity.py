"""The GPU suite's ``--parity`` section: ``willags_ns.render.rasterize``'s torch backend against gsplat
(against torch float64 without CUDA), forward and gradient relative errors over random scenes and extremes."""

import math

import torch

from benchmarks import _synthetic_gaussians as syn
from benchmarks.suite.timing import log, short_exc


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """||a - b|| / ||b|| in float64 (0 when both vanish; inf on any non-finite value)."""
    a, b = a.double(), b.double()
    if not (torch.isfinite(a).all() and torch.isfinite(b).all()):
        return math.inf
    nb = b.norm().item()
    diff = (a - b).norm().item()
    if nb < 1e-30:
        return 0.0 if diff < 1e-30 else math.inf
    return diff / nb


def _run_case(case, backend: str, device, dtype, weights):
    from willags_ns.render import rasterize

    params = {k: v.to(device=device, dtype=dtype).clone().requires_grad_(True) for k, v in case.tensors().items()}
    render, alpha, _ = rasterize(
        params["means"],
        params["quats"],
        params["scales"],
        params["opacities"],
        params["colors"],
        case.viewmats.to(device=device, dtype=dtype),
        case.Ks.to(device=device, dtype=dtype),
        case.width,
        case.height,
        sh_degree=case.sh_degree,
        render_mode=case.render_mode,
        backend=backend,
    )
    w_r, w_a = weights
    loss = (render * w_r.to(device=device, dtype=dtype)).sum() + (alpha * w_a.to(device=device, dtype=dtype)).sum()
    loss.backward()
    grads = {k: (p.grad if p.grad is not None else torch.zeros_like(p)).detach() for k, p in params.items()}
    return render.detach(), alpha.detach(), grads


def section_parity(args, cuda: bool) -> dict:
    cases = syn.parity_cases(quick=args.quick)
    dev = torch.device("cuda" if cuda else "cpu")
    rows = []
    names = ["means", "quats", "scales", "opacities", "colors"]
    mode = "torch-vs-gsplat" if cuda else "torch-fp32-vs-torch-fp64 (gsplat skipped: no CUDA)"
    for case in cases:
        g = torch.Generator().manual_seed(7)
        nch = 3 + (1 if case.render_mode == "RGB+ED" else 0)
        weights = (
            torch.rand(1, case.height, case.width, nch, generator=g),
            torch.rand(1, case.height, case.width, 1, generator=g),
        )
        row = {"case": case.name, "n": case.means.shape[0], "size": f"{case.width}x{case.height}"}
        try:
            t32 = _run_case(case, "torch", dev, torch.float32, weights)
            ref = None
            try:  # float64 reference of the same maths: a diagnostic, never a reason to lose the case
                ref = _run_case(case, "torch", dev, torch.float64, weights)
            except Exception as e:
                row["f64_error"] = short_exc(e)
            if cuda:
                gs = _run_case(case, "gsplat", dev, torch.float32, weights)
                a, b = t32, gs  # the parity metric: torch backend vs gsplat
                if ref is not None:
                    row["fwd_gsplat_vs_f64"] = max(_rel(gs[0], ref[0]), _rel(gs[1], ref[1]))
                    row["grad_gsplat_vs_f64"] = max(_rel(gs[2][k], ref[2][k]) for k in names)
            else:
                if ref is None:
                    raise RuntimeError(f"no reference: {row['f64_error']}")
                a, b = t32, ref
            row["fwd_render"] = _rel(a[0], b[0])
            row["fwd_alpha"] = _rel(a[1], b[1])
            for k in names:
                row[f"grad_{k}"] = _rel(a[2][k], b[2][k])
            row["fwd"] = max(row["fwd_render"], row["fwd_alpha"])
            row["grad"] = max(row[f"grad_{k}"] for k in names)
        except Exception as e:
            row["error"] = short_exc(e)
        rows.append(row)
    ok = [r for r in rows if "error" not in r]
    out = {"mode": mode, "cases": rows, "n_cases": len(rows), "n_errors": len(rows) - len(ok)}
    if ok:
        wf = max(ok, key=lambda r: r["fwd"])
        wg = max(ok, key=lambda r: r["grad"])
        out["worst_fwd"] = {"value": wf["fwd"], "case": wf["case"]}
        out["worst_grad"] = {"value": wg["grad"], "case": wg["case"]}
        out["worst_grad_per_param"] = {}
        for k in names:
            r = max(ok, key=lambda r: r[f"grad_{k}"])
            out["worst_grad_per_param"][k] = {"value": r[f"grad_{k}"], "case": r["case"]}
        out["pass_fwd_1e-4"] = wf["fwd"] <= 1e-4
        out["pass_grad_1e-3"] = wg["grad"] <= 1e-3
    log(f"\n## parity ({mode}); limits: forward <= 1e-4, gradients <= 1e-3")
    hdr = "| case | N | size | fwd render | fwd alpha | " + " | ".join(f"d {k}" for k in names)
    hdr += " | gsplat vs f64 fwd / grad |" if cuda else " |"
    log(hdr)
    log("|" + "---|" * (hdr.count("|") - 1))
    for r in rows:
        if "error" in r:
            log(f"| {r['case']} | {r['n']} | {r['size']} | ERROR {r['error']} |")
            continue
        cells = [f"{r['fwd_render']:.1e}", f"{r['fwd_alpha']:.1e}"] + [f"{r[f'grad_{k}']:.1e}" for k in names]
        tail = " |"
        if cuda:
            tail = (
                f" | {r['fwd_gsplat_vs_f64']:.1e} / {r['grad_gsplat_vs_f64']:.1e} |"
                if "fwd_gsplat_vs_f64" in r
                else " | - |"
            )
        log(f"| {r['case']} | {r['n']} | {r['size']} | " + " | ".join(cells) + tail)
    return out
