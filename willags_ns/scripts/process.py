"""`willags-process --images DIR --output DIR`: SfM on a folder of photos (pycolmap, CPU) -> a nerfstudio scene.

Thin CLI over `willags_ns.tools.sfm` (options: `willags-process --help`). Exit status: 0 on success, 1 when the
input or the SfM result is unusable (the message says why), 130 when interrupted (what was done is kept; the same
command resumes).
"""

import sys

import tyro

from willags_ns.tools.sfm import ProcessConfig, ProcessError, print_summary, run


def main(cfg: ProcessConfig) -> int:
    from nerfstudio.utils.rich_utils import CONSOLE

    try:
        summary = run(cfg)
    except ProcessError as e:
        CONSOLE.print(f"[bold red]willags-process: {e}")
        return 1
    except KeyboardInterrupt:
        CONSOLE.print(
            f"[bold yellow]willags-process: interrupted. Features and matches are kept in "
            f"{cfg.output / 'colmap' / 'database.db'}; run the same command again to resume."
        )
        return 130
    print_summary(summary)
    return 0


def entrypoint() -> None:
    sys.exit(main(tyro.cli(ProcessConfig)))


if __name__ == "__main__":
    entrypoint()
