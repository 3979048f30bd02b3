"""`willags-inspect --data DIR [--output FILE.json]`: analyse a scene before training and recommend a configuration.

Thin CLI over `willags_ns.tools.inspection` (the method is in its docstring; options: `willags-inspect --help`). Prints the
evidence and the recommendation; `--output` also writes them as JSON. Exit status: 0 on success, 1 when the input is
unusable (one line naming the path).
"""

import json
import sys

import tyro

from willags_ns.tools.inspection import InspectConfig, InspectError, format_report, inspect_scene


def main(cfg: InspectConfig) -> int:
    # the analysis takes seconds (docs/inspect.md), but reads up to max_images photos first: say so before it starts
    print(f"willags-inspect: analysing {cfg.data} (up to {cfg.max_images} {cfg.split} images) ...", flush=True)
    try:
        report = inspect_scene(cfg)
    except InspectError as e:
        print(f"willags-inspect: {e}", file=sys.stderr)
        return 1
    print(format_report(report))
    print(f"  analysed in {report.get('wall_s', 0):.1f} s")
    if cfg.output is not None:
        try:
            cfg.output.parent.mkdir(parents=True, exist_ok=True)
            cfg.output.write_text(json.dumps(report, indent=1))
        except OSError as e:
            print(f"willags-inspect: cannot write {cfg.output}: {e.strerror or e}", file=sys.stderr)
            return 1
        print(f"  written: {cfg.output}")
    return 0


def entrypoint() -> None:
    sys.exit(main(tyro.cli(InspectConfig)))


if __name__ == "__main__":
    entrypoint()
