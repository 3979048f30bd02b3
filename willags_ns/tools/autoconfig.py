"""Automatic configuration: apply `willags-inspect`'s recommendation to the model before it is built.

`ns-train willags --data DIR` (or any willags method with `--pipeline.model.auto-config True`) inspects the
scene (willags_ns/tools/inspection.py: appearance change measured on the SfM points, transients as occluded observations
that nearby views disagree with) and switches off what the evidence says the scene does not need:

- no appearance change and no transients: plain 3DGS colours (`appearance='sh'`: no latent, no mask, no teacher);
- appearance change without transients: the latent without the mask (and so without the EMA teacher and VGG);
- transients: the mask and its teacher (with the latent: the mask is part of the willags model);
- the tri-plane field stays off (measured: it did not help); the latent size follows the image count;
- the appearance-conditioned sky where a large share of the photos has no SfM points (sky or far background), off
  elsewhere: above each photo's skyline ("skyline"), or behind every pixel with the alpha penalty where the subject
  stands against the sky ("surround"; `sky.enabled`, `sky.region`, `sky.alpha_penalty`); the method's own setting
  when that was not measured (no SfM points); never with plain 3DGS (no latent to condition it on;
  `appearance='sh'` builds no sky).

Only those switches change (`overrides_from_recommendation`); every other setting is the method's own (the
resolution schedule, rasterisation mode, learning rates...). A switch the user set on the command line wins: the
trainer names those (`user_switches`: a flag for it on the command line, or a value other than the method's own
preset) in `pipeline.auto_config_keep`, and the inspector leaves them as they are (printed as kept). What was chosen, and why, is printed, written to
tensorboard (a text entry and `auto_config/*` scalars) and to `auto_config.json` beside `config.yml`; `config.yml`
is then rewritten with the resolved switches and `auto_config=False`, so `ns-render`, `ns-eval`, `ns-viewer` and
`--load-dir` rebuild exactly the trained model without inspecting again.

If the scene cannot be inspected (a layout the inspector does not read), training goes on with the method's own
configuration and a warning says why: the automatic mode never stops a run the plain method would train. config.yml
is resolved then too (`auto_config=False`, the method's own switches), so reloading it does not inspect again.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from willags_ns.splats.mcmc import cap_and_reason
from willags_ns.tools.inspection import InspectConfig, InspectError, inspect_scene, sky_settings

AUTO_CONFIG_FILE = "auto_config.json"
"""Written beside config.yml: the inspector's evidence, the recommendation and the switches applied."""


def overrides_from_recommendation(rec: dict[str, Any]) -> dict[str, Any]:
    """The model-config fields (dotted paths) a recommendation sets. Pure: the mapping is tested on its own."""
    if rec["preset"]["value"] == "willags-3dgs":
        # plain 3DGS colours: appearance='sh' also turns the latent, the mask and the teacher off in the model
        return {"appearance": "sh", "mask.enabled": False, "use_field": False}
    out = {
        "appearance": "willags",
        "mask.enabled": bool(rec["mask"]["on"]),
        "use_field": bool(rec["triplane_field"]["on"]),
        "latent.dim": int(rec["latent_dim"]["value"]),
    }
    # unmeasured (no SfM points), or a recommendation written before the sky evidence: the method's own sky stays
    if rec.get("sky", {}).get("measured"):
        out.update(sky_settings(sky_mode(rec["sky"])))
    return out


def sky_mode(sky: dict[str, Any]) -> str:
    """The sky mode of a recommendation's sky entry ("skyline" for an entry that names only on / off)."""
    return sky.get("mode") or ("skyline" if sky["on"] else "off")


AUTO_SWITCHES = (
    "appearance",
    "mask.enabled",
    "use_field",
    "latent.dim",
    "sky.enabled",
    "sky.region",
    "sky.alpha_penalty",
    "mcmc.cap_max",
)
"""Every model field the automatic configuration may set (`overrides_from_recommendation`, and MCMC's cap where
`mcmc.cap_rule` is "pixels": `capacity_override`)."""


def capacity_override(model_config, facts: dict[str, Any]) -> tuple[int, str] | None:
    """(cap, reason) of MCMC's cap under the "pixels" rule (splats/mcmc.cap_and_reason) from the inspector's facts, or
    None where the model keeps its own cap (rule "fixed", or no megapixels measured)."""
    mcmc = getattr(model_config, "mcmc", None)
    mpx = facts.get("train_megapixels")
    if mcmc is None or mcmc.cap_rule != "pixels" or mpx is None:
        return None
    return cap_and_reason(mcmc, float(mpx))


def user_switches(model_config, preset_model_config, argv: list[str] | None = None) -> tuple[str, ...]:
    """The switches (AUTO_SWITCHES) the user chose: named as a flag in `argv` (`--pipeline.model.mask.enabled ...`), or
    differing from the method's own preset (`preset_model_config`; None: flags only). A flag that repeats the
    preset's value is only seen in argv: after parsing, it cannot be told from the default."""
    flags = {a.split("=", 1)[0] for a in (argv or []) if a.startswith("--pipeline.model.")}
    out = []
    for key in AUTO_SWITCHES:
        named = f"--pipeline.model.{key.replace('_', '-')}" in flags
        changed = preset_model_config is not None and _get(model_config, key) != _get(preset_model_config, key)
        if named or changed:
            out.append(key)
    return tuple(out)


def _get(obj, dotted: str):
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def _set(obj, dotted: str, value) -> None:
    *parents, last = dotted.split(".")
    for part in parents:
        obj = getattr(obj, part)
    setattr(obj, last, value)


def scene_dir(datamanager_config) -> Path | None:
    """The directory ns-train was pointed at (`--data`, or the dataparser's own `data`)."""
    data = datamanager_config.data if datamanager_config.data is not None else None
    if data is None:
        data = getattr(datamanager_config.dataparser, "data", None)
    return None if data is None else Path(data)


def apply_auto_config(
    model_config, data: Path | None, inspect_config: InspectConfig | None = None, keep: tuple[str, ...] = ()
) -> dict[str, Any]:
    """Inspect `data`, set the recommended switches on `model_config` (in place) and return a summary. The fields in
    `keep` (the user's own switches) are left as they are.

    The summary: {"applied": bool, "changes": {field: [before, after]}, "settings": {field: value},
    "kept": {field: the user's value where it differs from the recommendation},
    "reasons": {switch: sentence}, "switches": {component: on}, "sky": whether the model gets the sky,
    "command": equivalent ns-train line, "report": inspector report or None, "error": why nothing was applied or
    None}."""
    if data is None:
        return {
            "applied": False,
            "error": "no --data given: the embedded scene is not inspected",
            "changes": {},
            "settings": {},
            "reasons": {},
        }
    if not Path(data).exists():  # the dataparser stops on it in one line: nothing to say about the switches
        error = f"data path {data} does not exist"
        return {"applied": False, "error": error, "missing": True, "changes": {}, "settings": {}, "reasons": {}}
    icfg = inspect_config if inspect_config is not None else InspectConfig()
    icfg.data = data
    try:
        report = inspect_scene(icfg)
    except InspectError as e:
        return {"applied": False, "error": str(e), "changes": {}, "settings": {}, "reasons": {}, "report": None}
    rec = report["recommendation"]
    recommended = overrides_from_recommendation(rec)
    capacity = capacity_override(model_config, report["facts"])
    if capacity is not None:
        recommended["mcmc.cap_max"] = capacity[0]
    overrides = {k: v for k, v in recommended.items() if k not in keep}
    kept = {k: _get(model_config, k) for k, v in recommended.items() if k in keep and _get(model_config, k) != v}
    changes = {}
    for key, value in overrides.items():
        before = _get(model_config, key)
        if before != value:
            changes[key] = [before, value]
        _set(model_config, key, value)
    reasons = {
        k: rec[k]["reason"] for k in ("appearance_latent", "mask", "teacher", "triplane_field", "sky", "latent_dim")
    }
    reasons["preset"] = rec["preset"]["reason"]
    mcmc = getattr(model_config, "mcmc", None)
    if capacity is not None:
        reasons["capacity"] = capacity[1] + ("" if "mcmc.cap_max" in overrides else "; kept as you set it")
    elif mcmc is not None:  # the cap as set, and what the pixels rule would allow: the inspector says both
        reasons["capacity"] = cap_and_reason(mcmc, report["facts"].get("train_megapixels"))[1]
    switches = {k: bool(rec[k]["on"]) for k in ("appearance_latent", "mask", "teacher", "triplane_field")}
    # the user's switches stand: report the components as the model will build them
    mine = {
        "appearance": "appearance_latent",
        "mask.enabled": "mask",
        "use_field": "triplane_field",
        "sky.enabled": "sky",
    }
    for key in kept:
        if key in mine:
            reasons[mine[key]] += f"; kept as you set it: {key}={kept[key]}"
    if "appearance" in kept:
        switches["appearance_latent"] = model_config.appearance == "willags"
    if "mask.enabled" in kept:
        mask = model_config.mask
        switches["mask"] = bool(mask.enabled)
        switches["teacher"] = bool(mask.enabled and mask.teacher.enabled)
    if "use_field" in kept:
        switches["triplane_field"] = bool(model_config.use_field)
    mask = getattr(model_config, "mask", None)
    if switches["mask"] and mask is not None and mask.start_rule == "transients":  # on, but decided again later
        reasons["mask"] += (
            f"; it starts at step {mask.warmup_steps:,} only where the training photos' own renders then leave at "
            f"least {mask.start_share:.0%} of their pixels as residual blobs (mask.start_rule transients; "
            "--pipeline.model.mask.start-rule always starts it regardless)"
        )
    return {
        "applied": True,
        "error": None,
        "changes": changes,
        "settings": overrides,
        "kept": kept,
        "reasons": reasons,
        "switches": switches,
        # the sky as the model will build it (the method's own setting when not measured; appearance='sh' builds
        # none); beside "switches", whose four keys earlier auto_config.json files and their readers rely on
        "sky": model_config.appearance == "willags" and bool(model_config.sky.enabled),
        "command": rec["command"],
        "capacity_rule": None if mcmc is None else mcmc.cap_rule,
        "report": report,
    }


def _switches(summary: dict[str, Any]) -> dict[str, bool]:
    """The component switches of a summary, the sky included."""
    out = dict(summary.get("switches", {}))
    if summary.get("sky") is not None:
        out["sky"] = summary["sky"]
    return out


def format_summary(summary: dict[str, Any]) -> str:
    """The lines printed to the console when training starts."""
    if not summary["applied"]:
        return f"willags auto-config: not applied ({summary['error']}); training with the method's own configuration"
    lines = ["willags auto-config: " + ", ".join(f"{k}={v}" for k, v in summary["settings"].items())]
    for k, v in _switches(summary).items():
        lines.append(f"  {k}: {'ON' if v else 'off'} - {summary['reasons'][k]}")
    lines.append(f"  latent_dim: {summary['reasons']['latent_dim']}")
    if "capacity" in summary["reasons"]:
        rule = summary.get("capacity_rule") or "pixels"
        where = "where MCMC densifies: on a GPU unless --pipeline.model.densification says otherwise"
        lines.append(f"  capacity (MCMC's cap, rule {rule}; {where}): {summary['reasons']['capacity']}")
    if summary.get("kept"):
        lines.append("  kept (your flags win): " + ", ".join(f"{k}={v}" for k, v in summary["kept"].items()))
    if summary["changes"]:
        lines.append("  changed: " + ", ".join(f"{k} {a} -> {b}" for k, (a, b) in summary["changes"].items()))
    else:
        lines.append("  changed: nothing (the method's own switches are what the scene needs)")
    return "\n".join(lines)


def tensorboard_entries(summary: dict[str, Any]) -> tuple[dict[str, Any], dict[str, float]]:
    """(text dict for writer.put_config, scalars for writer.put_scalar) describing the choice."""
    text = {"auto_config": format_summary(summary)}
    scalars = {f"auto_config/{k}": float(v) for k, v in _switches(summary).items()}
    if summary["applied"]:
        scalars["auto_config/latent_dim"] = float(summary["settings"].get("latent.dim", 0))
    return text, scalars
